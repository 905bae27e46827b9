"""What poses within reach tell of an accelerometer's scales (issue 37): the X/Y ones, not the Z one.

A level-calibrated accelerometer (offsets set, scales at 1) keeps its factory scale errors, up to
+-5 %. At a steep field they limit the heading at a tilt (the tilt error times tan of the dip). This
benchmark asks whether the poses of a ``--max-tilt 15`` capture could identify them instead: on the
simulated captures of ``large_vehicle.py``'s honesty check (level-calibrated, CMAC, -66 deg dip), the
compass fit of the capture's end (:func:`mavcal.core.held.calibrate_held`, its inputs taken as mavcal
passed them) is repeated with the X/Y scales free:

* ``X/Y held``: every scale held at 1, its prior 3 % carried (mavcal's fit before issue 37);
* ``X/Y free (mavcal)``: K_a[11], K_a[22] free, K_a[33] held with its 3 % prior carried (what the
  poses give of the X/Y-to-Z ratios when the Z scale is not known: a level calibration never knows
  it; the fit mavcal makes and writes);
* ``X/Y free, Z known``: the same with K_a[33] held at its truth, no prior (the poses' own power).

Per capture: the ratios K_a[11]/K_a[33] and K_a[22]/K_a[33] against their truth, their 1-sigma, and
the heading error at 30 deg of tilt the worse ratio's error alone would leave at this dip
(tan(dip) x the tilt error, |d ratio| sin 30 cos 30).

    python benchmarks/reach_scales.py [--seeds 1000 ...] [--save]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import large_vehicle as lv  # noqa: E402  (the honesty check's simulated captures)

import mavcal.fits  # noqa: E402
from mavcal.core.held import calibrate_held  # noqa: E402
from mavcal.coverage import held_priors  # noqa: E402
from mavcal.sources.wmm import field_at  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"
G0 = 9.80665


def _capture_inputs(seed: int) -> tuple[dict, dict]:
    """The last held fit's inputs of the seed's level-calibrated capture, and the capture's outcome."""
    seen: dict = {}
    real = mavcal.fits.calibrate_held

    def spy(sa, sm, K_a, b_a, **kw):
        seen.update(sa=sa, sm=sm, K_a=K_a, b_a=b_a, kw=kw)
        return real(sa, sm, K_a, b_a, **kw)

    mavcal.fits.calibrate_held = spy
    try:
        outcome = lv.honesty_capture(seed, "level")
    finally:
        mavcal.fits.calibrate_held = real
    return seen, outcome


def _ratios(cal) -> tuple[np.ndarray, np.ndarray]:
    """K_a[jj] / K_a[33] for j = 1, 2 and their 1-sigma (the covariance's, linearised)."""
    names, C, K = cal.param_names, cal.param_cov, np.diag(cal.accel.gain)
    i3 = names.index("K_a[33]")
    r, sd = np.empty(2), np.empty(2)
    for j in range(2):
        i = names.index(f"K_a[{j + 1}{j + 1}]")
        g = np.zeros(len(names))
        g[i], g[i3] = 1.0 / K[2], -K[j] / K[2] ** 2
        r[j], sd[j] = K[j] / K[2], float(np.sqrt(max(g @ C @ g, 0.0)))
    return r, sd


def run(seed: int, dip_deg: float) -> dict:
    seen, outcome = _capture_inputs(seed)
    sa, sm, K_a, b_a, kw = seen["sa"], seen["sm"], seen["K_a"], seen["b_a"], seen["kw"]
    rng = np.random.default_rng(50_000 + seed)  # honesty_capture's draw of the truth, in its order
    rng.uniform(-0.5, 0.5, 3)
    k = rng.uniform(0.95, 1.05, 3)
    truth = k[2] / k[:2]  # K_a = g / scale: K_a[jj] / K_a[33] = scale[3] / scale[j]
    free = [h for h in kw["held"] if h not in ("K_a[11]", "K_a[22]")]
    held = free + ["K_a[11]", "K_a[22]"]
    h_z = kw.get("h_z")
    incl = float(np.degrees(np.arctan(h_z))) if h_z is not None else None
    rows = {}
    K_true = K_a.copy()
    K_true[2, 2] = G0 / k[2]
    for name, hold, K, prior in (("X/Y held (3 % prior)", held, K_a, held_priors(K_a, "level", incl)),
                                 ("X/Y free (mavcal)", free, K_a, held_priors(K_a, "level", incl)),
                                 ("X/Y free, Z known", free, K_true, {})):
        cal = calibrate_held(sa, sm, K, b_a, held=hold, prior_sd=prior, h_z=h_z)
        r, sd = _ratios(cal)
        err = np.abs(r - truth)
        rows[name] = dict(ratios=r.tolist(), sd=sd.tolist(), error=err.tolist(),
                          heading30_deg=float(np.degrees(np.tan(np.radians(abs(dip_deg))) * err.max()
                                                         * np.sin(np.radians(30)) * np.cos(np.radians(30)))))
    return dict(seed=seed, truth=truth.tolist(), outcome=outcome["outcome"], bound_deg=outcome.get("bound_deg"),
                fits=rows)


def table(rows: list[dict]) -> str:
    head = ("| seed | truth K11/K33, K22/K33 | fit | ratios | 1 sigma | error | heading at 30 deg from the ratio "
            "error alone (deg) |\n|" + "---|" * 7)
    out = [head]
    for r in rows:
        for name, f in r["fits"].items():
            out.append(f"| {r['seed']} | {r['truth'][0]:.4f}, {r['truth'][1]:.4f} | {name} "
                       f"| {f['ratios'][0]:.4f}, {f['ratios'][1]:.4f} | {f['sd'][0]:.4f}, {f['sd'][1]:.4f} "
                       f"| {f['error'][0]:.4f}, {f['error'][1]:.4f} | {f['heading30_deg']:.2f} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", nargs="+", type=int, default=list(range(1000, 1006)))
    args = ap.parse_args(argv)
    t0 = time.time()
    dip = field_at(*lv.SITES["CMAC"][:3])[1]
    rows = [run(s, dip) for s in args.seeds]
    sd_free = [max(r["fits"]["X/Y free (mavcal)"]["sd"]) for r in rows]
    sd_known = [max(r["fits"]["X/Y free, Z known"]["sd"]) for r in rows]
    md = (f"# What poses within reach tell of an accelerometer's scales (issue 37)\n\nProduced by "
          f"`python benchmarks/reach_scales.py {' '.join(sys.argv[1:])}`".rstrip() +
          f" ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {time.time() - t0:.0f} s). Level-calibrated "
          f"accelerometers (scales 0.95-1.05 left at 1), `--max-tilt 15` captures at CMAC (dip {dip:.1f} deg).\n\n"
          f"With the Z scale unknown (as a level calibration leaves it), the poses give the X/Y-to-Z scale ratios "
          f"to {min(sd_free):.3f}-{max(sd_free):.3f} (1 sigma); with it known, to "
          f"{min(sd_known):.4f}-{max(sd_known):.4f}. ±15 deg tilts tell an X scale from the Z scale only through "
          "gravity's curvature along Z (1 - cos 15 deg = 3.4 %) or the compass's view of the tilt, which rests on "
          "the field's dip (the World Magnetic Model's to 0.5 deg): the Z scale is what they cannot give, and a "
          "ratio error of the size above is still 0.8-1 deg of heading at 30 deg of tilt at this dip (the compass, "
          "fitted with it, keeps the heading within the bound over the tilts the poses cover).\n\n"
          + table(rows) + "\n")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "reach_scales.md").write_text(md)
    (OUT / "reach_scales.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
