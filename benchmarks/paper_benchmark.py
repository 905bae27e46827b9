"""Reproduce the paper's simulated experiments and compare with the exact ML optimum.

For each of R Monte Carlo runs (default 100) the sensors are drawn as in the paper's
Table I; a training set of 50 intervals and a test set of 50 intervals are drawn, and
runs with N intervals use the first N (the paper's "merged" sets).

Sections:
1. delta vs gamma (N = 15), all four variants, training and test: the paper's algorithm
   alone (``refine=False``), stopped at each gamma in 1e-6 .. 10 (one run, snapshotted at
   the first iteration where J_{k-1} - J_k < gamma: the same algorithm stopping at different
   times, as in the paper); and mavcal's default (the same block steps, then the joint
   refinement) from each of those snapshots.
2. delta vs N (8 .. 50, gamma = 1e-4), all four variants, both paths, training and test.
3. The exact ML optimum of J' by a generic solver: scipy ``least_squares`` (finite-
   difference Jacobian) started at the ground truth in the paper's gauge; per run
   delta/delta_opt, J/J_opt, time/time_generic (N = 15, NCAR).
4. Speed: median ``mavcal.calibrate`` time vs N (8 .. 200), single process.

Writes paper.md, paper.json and PNG plots (about 10 min on one free core) into
benchmarks/out/, or into the tracked benchmarks/results/ with ``--save`` (benchmarks/README.md);
``--quick`` (5 runs, N in 8/15/30, about 1 min) writes paper_quick.md/json instead and no plots.
Usage:

    python benchmarks/paper_benchmark.py [--runs 100] [--quick] [--save | --out DIR]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from lsq_truth import G, least_squares_from_truth, unpack  # benchmarks/lsq_truth.py

import mavcal
from mavcal.core import calibrate as C
from mavcal.core import steps
from mavcal.core.models import MODELS
from mavcal.core.types import Calibration, SensorModel
from mavcal.sim.paper import SimData, Truth, draw_intervals, draw_sensors

OUT = Path(__file__).resolve().parent / "out"  # --save: benchmarks/results/ (benchmarks/README.md)
GAMMAS = [1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0]
NS = [8, 10, 12, 15, 20, 25, 30, 40, 50]
METHODS = ["ncar", "ncdr", "fcar", "dcar"]


def subset(d: SimData, n: int) -> SimData:
    t = d.truth
    return SimData(d.accel_sets[:n], d.mag_sets[:n],
                   Truth(t.sensors, t.orientations[:n], t.n_accel[:n], t.n_mag[:n]))


def cal_from_state(st, a, m, method) -> Calibration:
    return Calibration(accel=SensorModel(st.K_a, st.b_a, st.Sigma_a), mag=SensorModel(st.K_m, st.b_m, st.Sigma_m, "mag"),
                       gravity=np.array([0, 0, -1.0]), field=np.array([1, 0, st.h_z]), orientations=st.R,
                       cost=steps.partial_cost(st, a, m), iterations=0, converged=True, message="", method=method)


def deltas(cal, train: SimData, test: SimData):
    da, dm = mavcal.reconstruction_error(cal, train.truth)
    R = mavcal.estimate_orientations(cal, test.accel_sets, test.mag_sets)
    ta, tm = mavcal.reconstruction_error(cal, test.truth, orientations=R)
    return [da, dm, ta, tm]


def gamma_sweep(train: SimData, test: SimData, method: str, seed: int):
    """One block-steps run to gamma = 1e-6, snapshotted at every gamma; + LM from each snapshot."""
    a, m = C._stats(train.accel_sets, train.mag_sets, None)
    t0 = time.perf_counter()
    st0 = C.initial_state(a, m, np.random.default_rng(seed))
    t_init = time.perf_counter() - t0
    snaps = {}
    times = {}
    pending = sorted(GAMMAS, reverse=True)
    tstart = time.perf_counter()

    def cb(k, st, J, dJ, checked):
        while pending and checked and dJ < pending[0]:
            g = pending.pop(0)
            snaps[g] = (st, k)
            times[g] = t_init + time.perf_counter() - tstart

    st, k, how = C.run_block_steps(st0, a, m, method, min(GAMMAS), 5000, on_iteration=cb)
    for g in pending:  # never reached (iteration limit): last state
        snaps[g] = (st, k)
        times[g] = t_init + time.perf_counter() - tstart
    out = {}
    for g in GAMMAS:
        stg, kg = snaps[g]
        plain = cal_from_state(stg, a, m, method)
        t1 = time.perf_counter()
        res, Sa, Sm = C._refine(MODELS["full"], stg, a, m, method, g)
        t_ref = time.perf_counter() - t1
        p = res.params
        refined = Calibration(accel=SensorModel(p.gains[0], p.biases[0], Sa), mag=SensorModel(p.gains[1], p.biases[1], Sm, "mag"),
                              gravity=np.array([0, 0, -1.0]), field=np.array([1, 0, p.h_z]), orientations=p.R,
                              cost=res.cost, iterations=0, converged=True, message="", method=method)
        out[g] = {"plain": deltas(plain, train, test) + [times[g], kg, plain.cost],
                  "refined": deltas(refined, train, test) + [times[g] + t_ref, kg, refined.cost]}
    return out


def generic_optimum(train: SimData):
    """Exact optimum of J' by scipy least_squares from the truth (paper gauge, Sigma_hat)."""
    a, m = C._stats(train.accel_sets, train.mag_sets, None)
    t0 = time.perf_counter()
    sol, R0 = least_squares_from_truth(train.accel_sets, train.mag_sets, train.truth, a.sigma_hat, m.sigma_hat)
    dt = time.perf_counter() - t0
    Ka, ba, Km, bm, hz, R = unpack(sol.x, R0)
    cal = Calibration(accel=SensorModel(Ka, ba, a.sigma_hat), mag=SensorModel(Km, bm, m.sigma_hat, "mag"),
                      gravity=G, field=np.array([1, 0, hz]), orientations=R, cost=float(2 * sol.cost),
                      iterations=int(sol.nfev), converged=bool(sol.success), message=sol.message)
    return cal, dt


def q(x, p):
    return float(np.percentile(x, p))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--quick", action="store_true", help="fewer runs and grid points (smoke test)")
    args = ap.parse_args(argv)
    runs = 5 if args.quick else args.runs
    ns = [8, 15, 30] if args.quick else NS
    OUT.mkdir(parents=True, exist_ok=True)
    res = {"runs": runs, "gammas": GAMMAS, "ns": ns, "gamma": {}, "n": {}, "optimum": [], "speed": {}}
    t_all = time.perf_counter()
    datasets = []
    for r in range(runs):
        rng = np.random.default_rng(1000 + r)
        s = draw_sensors(rng)
        datasets.append((draw_intervals(s, 50, rng), draw_intervals(s, 50, rng)))

    # 1. delta vs gamma
    for meth in METHODS:
        res["gamma"][meth] = [gamma_sweep(subset(tr, 15), subset(te, 15), meth, r)
                              for r, (tr, te) in enumerate(datasets)]
        print(f"gamma sweep {meth} done ({time.perf_counter() - t_all:.0f} s)", file=sys.stderr)

    # 2. delta vs N (gamma = 1e-4)
    for meth in METHODS:
        res["n"][meth] = {}
        for n in ns:
            rows = []
            for r, (tr, te) in enumerate(datasets):
                trn, ten = subset(tr, n), subset(te, n)
                t0 = time.perf_counter()
                plain = mavcal.calibrate(trn.accel_sets, trn.mag_sets, method=meth, seed=r, model="full", refine=False)
                t1 = time.perf_counter()
                full = mavcal.calibrate(trn.accel_sets, trn.mag_sets, method=meth, seed=r, model="full")
                t2 = time.perf_counter()
                rows.append({"plain": deltas(plain, trn, ten) + [t1 - t0], "refined": deltas(full, trn, ten) + [t2 - t1]})
            res["n"][meth][n] = rows
        print(f"N sweep {meth} done ({time.perf_counter() - t_all:.0f} s)", file=sys.stderr)

    # 3. exact optimum (N = 15, NCAR, default calibrate) vs generic solver from the truth
    for r, (tr, te) in enumerate(datasets):
        trn, ten = subset(tr, 15), subset(te, 15)
        t0 = time.perf_counter()
        cal = mavcal.calibrate(trn.accel_sets, trn.mag_sets, method="ncar", seed=r)
        t_cal = time.perf_counter() - t0
        opt, t_gen = generic_optimum(trn)
        d_cal, d_opt = deltas(cal, trn, ten), deltas(opt, trn, ten)
        res["optimum"].append({"delta": d_cal, "delta_opt": d_opt, "J": cal.cost, "J_opt": opt.cost,
                               "time": t_cal, "time_generic": t_gen, "model": cal.model})
    print(f"optimum comparison done ({time.perf_counter() - t_all:.0f} s)", file=sys.stderr)

    # 4. speed vs N (single process, median of repeated calls)
    for n in [8, 15, 25, 50, 100, 200]:
        ts = []
        for r in range(min(runs, 30)):
            rng = np.random.default_rng(5000 + r)
            d = draw_intervals(draw_sensors(rng), n, rng)
            t0 = time.perf_counter()
            mavcal.calibrate(d.accel_sets, d.mag_sets, seed=r)
            ts.append(time.perf_counter() - t0)
        res["speed"][n] = {"median_ms": 1e3 * float(np.median(ts)), "p90_ms": 1e3 * q(ts, 90)}
    res["total_s"] = time.perf_counter() - t_all
    stem = "paper_quick" if args.quick else "paper"
    (OUT / f"{stem}.json").write_text(json.dumps(res, default=float))
    report(res, stem, " --quick" if args.quick else "")
    if not args.quick:
        plots(res)
    return 0


def report(res, stem: str = "paper", flags: str = "") -> None:
    L = []
    runs = res["runs"]
    opt = res["optimum"]
    d = np.array([o["delta"] for o in opt])
    do = np.array([o["delta_opt"] for o in opt])
    J = np.array([o["J"] for o in opt])
    Jo = np.array([o["J_opt"] for o in opt])
    t = np.array([o["time"] for o in opt])
    tg = np.array([o["time_generic"] for o in opt])
    ok_train = int(np.sum((d[:, 0] < 0.1) & (d[:, 1] < 0.1)))
    ok_test = int(np.sum((d[:, 2] < 0.1) & (d[:, 3] < 0.1)))
    ok_test_opt = int(np.sum((do[:, 2] < 0.1) & (do[:, 3] < 0.1)))
    ratio = d / do
    L.append(f"# mavcal vs the paper's experiments ({runs} Monte Carlo runs)\n")
    L.append(f"Produced by `python benchmarks/paper_benchmark.py{flags}`"
             + (f" --runs {runs}" if runs != 100 and not flags else "") + f"; {res.get('total_s', 0):.0f} s.\n")
    L.append("## Targets (NCAR, N = 15, default `mavcal.calibrate`)\n")
    L.append("| quantity | value | target |")
    L.append("|---|---|---|")
    L.append(f"| runs with delta_a and delta_m < 0.1 (training) | {ok_train}/{runs} | >= 99/100 |")
    L.append(f"| runs with delta_a and delta_m < 0.1 (test) | {ok_test}/{runs} (exact optimum: {ok_test_opt}/{runs}) | optimum's own |")
    L.append(f"| median J/J_opt | {np.median(J / Jo):.6f} | <= 1.001 |")
    L.append(f"| max J/J_opt | {np.max(J / Jo):.6f} | |")
    L.append(f"| worst delta/delta_opt, training (accel, mag) | {ratio[:, 0].max():.4f}, {ratio[:, 1].max():.4f} | <= 1.05 |")
    L.append(f"| worst delta/delta_opt, test (accel, mag) | {ratio[:, 2].max():.4f}, {ratio[:, 3].max():.4f} | <= 1.05 |")
    L.append(f"| median calibrate time | {1e3 * np.median(t):.2f} ms | <= 10 ms |")
    L.append(f"| median time / time_generic (per run) | {np.median(t / tg):.4f} | <= 0.5 |")
    L.append(f"| median generic least_squares time from the truth | {1e3 * np.median(tg):.1f} ms | |")
    sp = res["speed"]
    L.append(f"| median calibrate time, N = 100 | {sp[100]['median_ms'] if 100 in sp else sp['100']['median_ms']:.2f} ms | <= 50 ms |")
    L.append("")
    L.append("## Speed vs N (median of up to 30 runs, one process)\n")
    L.append("| N | median ms | p90 ms |")
    L.append("|---|---|---|")
    for n, v in sp.items():
        L.append(f"| {n} | {v['median_ms']:.2f} | {v['p90_ms']:.2f} |")
    ns_ = np.array([float(k) for k in sp])
    ms_ = np.array([v["median_ms"] for v in sp.values()])
    slope = np.polyfit(np.log(ns_), np.log(ms_), 1)[0]
    L.append(f"\nlog-log slope of time vs N: {slope:.2f} (1 = linear)\n")
    L.append("## delta vs gamma (N = 15): median [90th percentile] over runs\n")
    for path in ("plain", "refined"):
        L.append(f"### {'paper algorithm alone (refine=False)' if path == 'plain' else 'mavcal default (block steps + joint refinement)'}\n")
        L.append("| method | gamma | delta_a train | delta_m train | delta_a test | delta_m test | time ms | block iterations |")
        L.append("|---|---|---|---|---|---|---|---|")
        for meth, runs_ in res["gamma"].items():
            for g in res["gammas"]:
                arr = np.array([r_[g][path] if g in r_ else r_[str(g)][path] for r_ in runs_])
                cells = [f"{np.median(arr[:, k]):.4f} [{q(arr[:, k], 90):.4f}]" for k in range(4)]
                L.append(f"| {meth} | {g:g} | " + " | ".join(cells) + f" | {1e3 * np.median(arr[:, 4]):.1f} | {np.median(arr[:, 5]):.0f} |")
        L.append("")
    L.append("## delta vs N (gamma = 1e-4): median [90th percentile], fraction of runs with both deltas < 0.1\n")
    for path in ("plain", "refined"):
        L.append(f"### {'paper algorithm alone' if path == 'plain' else 'mavcal default'}\n")
        L.append("| method | N | delta_a train | delta_m train | delta_a test | delta_m test | train < 0.1 | test < 0.1 | time ms |")
        L.append("|---|---|---|---|---|---|---|---|---|")
        for meth, byn in res["n"].items():
            for n, rows in byn.items():
                arr = np.array([r_[path] for r_ in rows])
                cells = [f"{np.median(arr[:, k]):.4f} [{q(arr[:, k], 90):.4f}]" for k in range(4)]
                fr = np.mean((arr[:, 0] < 0.1) & (arr[:, 1] < 0.1))
                ft = np.mean((arr[:, 2] < 0.1) & (arr[:, 3] < 0.1))
                L.append(f"| {meth} | {n} | " + " | ".join(cells) + f" | {fr:.2f} | {ft:.2f} | {1e3 * np.median(arr[:, 4]):.1f} |")
        L.append("")
    (OUT / f"{stem}.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


def plots(res) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plots (pip install -e .[plots])", file=sys.stderr)
        return
    labels = ["accel train", "mag train", "accel test", "mag test"]
    for path in ("plain", "refined"):
        fig, axs = plt.subplots(2, 3, figsize=(15, 8))
        for k in range(4):
            ax = axs.flat[k]
            for meth, runs_ in res["gamma"].items():
                arr = np.array([[r_[g][path][k] for g in res["gammas"]] for r_ in runs_])
                ax.plot(np.log10(res["gammas"]), np.log10(np.median(arr, 0)), "o-", label=meth.upper())
                ax.fill_between(np.log10(res["gammas"]), np.log10(np.percentile(arr, 10, 0)),
                                np.log10(np.percentile(arr, 90, 0)), alpha=0.15)
            ax.set_title(f"delta, {labels[k]}")
            ax.set_xlabel("log10 gamma")
            ax.set_ylabel("log10 delta")
            ax.legend()
        ax = axs.flat[4]
        for meth, runs_ in res["gamma"].items():
            arr = np.array([[r_[g][path][4] for g in res["gammas"]] for r_ in runs_])
            ax.plot(np.log10(res["gammas"]), np.log10(np.median(arr, 0)), "o-", label=meth.upper())
        ax.set_title("calibration time")
        ax.set_xlabel("log10 gamma")
        ax.set_ylabel("log10 time [s]")
        ax.legend()
        axs.flat[5].axis("off")
        fig.suptitle(f"delta and time vs gamma, N = 15 ({'paper algorithm alone' if path == 'plain' else 'mavcal default'})")
        fig.tight_layout()
        fig.savefig(OUT / f"gamma_{path}.png", dpi=80)
        plt.close(fig)
        fig, axs = plt.subplots(2, 3, figsize=(15, 8))
        for k in range(4):
            ax = axs.flat[k]
            for meth, byn in res["n"].items():
                ns = list(byn)
                arr = np.array([[r_[path][k] for r_ in byn[n]] for n in ns]).T
                ax.plot([float(n) for n in ns], np.log10(np.median(arr, 0)), "o-", label=meth.upper())
                ax.fill_between([float(n) for n in ns], np.log10(np.percentile(arr, 10, 0)),
                                np.log10(np.percentile(arr, 90, 0)), alpha=0.15)
            ax.axhline(-1, color="k", lw=0.5)
            ax.set_title(f"delta, {labels[k]}")
            ax.set_xlabel("N")
            ax.set_ylabel("log10 delta")
            ax.legend()
        ax = axs.flat[4]
        for meth, byn in res["n"].items():
            ns = list(byn)
            ax.plot([float(n) for n in ns], np.log10([np.median([r_[path][4] for r_ in byn[n]]) for n in ns]), "o-",
                    label=meth.upper())
        ax.set_title("calibration time")
        ax.set_xlabel("N")
        ax.set_ylabel("log10 time [s]")
        ax.legend()
        axs.flat[5].axis("off")
        fig.suptitle(f"delta and time vs N, gamma = 1e-4 ({'paper algorithm alone' if path == 'plain' else 'mavcal default'})")
        fig.tight_layout()
        fig.savefig(OUT / f"n_{path}.png", dpi=80)
        plt.close(fig)


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
