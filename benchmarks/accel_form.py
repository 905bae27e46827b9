"""The accelerometer's own fit on short captures: which false-alarm rate for its form test.

`mavcal.core.accel_fit.fit_accel` keeps the diagonal gain unless a likelihood-ratio test
rejects it for the upper-triangular one at ``FORM_ALPHA``. With 10-11 intervals the upper form
has 1-2 spare equations: once chosen, its tilt bound is about 2 deg and the tilt gate (0.5 deg)
rejects the accelerometer. This script measures, for several alphas, on simulated captures of
the SITL tests' poses (``SPREAD_POSES``; 82 samples a pose, 0.02 m/s^2 noise, RAW_IMU's 1 mg
truncation undone as mavcal undoes it) with a symmetric cross-axis term of a given size:

* how often the upper form is chosen, and how often the tilt gate then rejects the sensor;
* how often the written values' true tilt error (ArduPilot holds a diagonal gain only) exceeds
  the reported 95 % bound, and the worst true tilt error.

    python benchmarks/accel_form.py [--runs 200] [--save]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.mapping import map_accel
from mavcal.core.accel_fit import FORM_ALPHA, fit_accel
from mavcal.core.constants import GRAVITY_MPS2 as G
from mavcal.core.stats import chi2_sf, interval_stats
from mavcal.judging.quality import accel_tilt_bounds
from mavcal.testing.sitl_hand import SPREAD_POSES
from mavcal.testing.vehicle import euler_to_matrix

OUT = Path(__file__).resolve().parent / "out"
STEP = G / 1000.0  # RAW_IMU's 1 mg
ALPHAS = (1e-2, 1e-4, 1e-6)
TILT_GATE_DEG = 0.5


def _capture(rng: np.random.Generator, poses, delta: float):
    """One simulated capture: truth (K, b) and the interval statistics mavcal would form."""
    K = np.diag(rng.uniform(0.97, 1.03, 3))
    off = rng.normal(size=3)
    off = delta * off / np.linalg.norm(off)
    K[0, 1] = K[1, 0] = off[0]
    K[0, 2] = K[2, 0] = off[1]
    K[1, 2] = K[2, 1] = off[2]
    b = rng.uniform(-0.3, 0.3, 3)
    sets = []
    for p in poses:
        d = euler_to_matrix(*np.radians(p)).T @ np.array([0.0, 0.0, -1.0])
        x = np.trunc((G * (K @ d) + b + rng.normal(0, 0.02, (82, 3))) / STEP)  # int16 mg, truncated
        sets.append((x + 0.5 * np.sign(x)) * STEP)  # mavcal's untruncation
    return K, b, interval_stats(sets, "accel_sets", noise_floor=STEP / np.sqrt(12))


def run_case(n_poses: int, delta: float, runs: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    res = {a: {"upper": 0, "rejected": 0, "beyond_bound": 0, "worst_tilt_deg": 0.0} for a in ALPHAS}
    for _ in range(runs):
        K, b, st = _capture(rng, SPREAD_POSES[:n_poses], delta)
        diag, upper = fit_accel(st, form="diag"), fit_accel(st, form="upper")
        p = chi2_sf(max(diag.cost - upper.cost, 0.0), 3)
        for a, r in res.items():
            fit = upper if p <= a else diag
            am = map_accel(fit.gain, fit.bias, fw.AccelCal(), 0)
            bound, _ = accel_tilt_bounds(fit, am, 200, 0)
            truth = dataclasses.replace(fit, gain=G * K, bias=b)
            true_tilt, _ = accel_tilt_bounds(truth, am, 0, 0)  # no draws: the truth's own tilt error
            r["upper"] += fit.form == "upper"
            r["rejected"] += bound > TILT_GATE_DEG
            r["beyond_bound"] += true_tilt > bound
            r["worst_tilt_deg"] = max(r["worst_tilt_deg"], true_tilt)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--poses", type=int, nargs="+", default=[10, 14])
    ap.add_argument("--deltas", type=float, nargs="+", default=[0.0, 0.001, 0.002, 0.004],
                    help="cross-axis terms (fraction of 1 g; 0.001 = 0.057 deg)")
    args = ap.parse_args(argv)
    L = ["# The accelerometer's form test: false alarms and honesty by alpha\n",
         f"Produced by `python benchmarks/accel_form.py --runs {args.runs}`. Simulated captures of the first N of "
         "the SITL tests' poses, a symmetric cross-axis term of the size given; per alpha: upper form chosen, "
         f"sensor rejected by the tilt gate ({TILT_GATE_DEG} deg), true tilt error of the written (diagonal) values "
         f"beyond the reported 95 % bound, worst true tilt error. mavcal uses alpha = {FORM_ALPHA:g}.\n",
         "| poses | cross-axis (deg) | alpha | upper chosen | rejected | true tilt > 95 % bound | worst true tilt (deg) |",
         "|---|---|---|---|---|---|---|"]
    for n in args.poses:
        for delta in args.deltas:
            res = run_case(n, delta, args.runs)
            for a, r in res.items():
                L.append(f"| {n} | {np.degrees(delta):.3f} | {a:g} | {r['upper']}/{args.runs} | "
                         f"{r['rejected']}/{args.runs} | {r['beyond_bound']}/{args.runs} | {r['worst_tilt_deg']:.3f} |")
            print("\n".join(L[-len(res):]), flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "accel_form.md").write_text("\n".join(L) + "\n")
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
