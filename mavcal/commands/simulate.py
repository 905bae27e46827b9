"""``mavcal simulate``: calibrate a data set simulated as in the paper's Table I and compare with the truth."""
from __future__ import annotations

import json
import time

import numpy as np

HELP = "calibrate a simulated data set (the paper's Monte Carlo set-up) and compare with the truth"


def add_arguments(p) -> None:
    p.add_argument("--seed", type=int, default=1, help="random seed of the simulation (default 1)")
    p.add_argument("--intervals", type=int, default=15, help="number of still intervals N (default 15)")
    p.add_argument("--method", default="ncar", choices=["ncar", "ncdr", "fcar", "dcar"], help="paper variant")
    p.add_argument("--tol", type=float, default=1e-4, help="stop condition gamma (default 1e-4)")
    p.add_argument("--json", action="store_true", help="machine-readable output")


def run(args) -> int:
    import mavcal
    from mavcal import sim

    if args.intervals < 1:
        from mavcal.errors import UsageError
        raise UsageError("--intervals must be a positive number")
    data = sim.simulate(args.intervals, seed=args.seed)
    t0 = time.perf_counter()
    cal = mavcal.calibrate(data.accel_sets, data.mag_sets, method=args.method, tol=args.tol, seed=args.seed)
    dt = time.perf_counter() - t0
    delta_a, delta_m = mavcal.reconstruction_error(cal, data.truth)
    K_a, b_a, K_m, b_m, h_z, _ = data.truth.in_paper_gauge()
    out = {
        "intervals": args.intervals, "method": args.method, "model": cal.model, "model_reason": cal.model_reason,
        "time_ms": dt * 1e3, "cost": cal.cost, "dof": cal.dof, "converged": cal.converged,
        "delta_accel": delta_a, "delta_mag": delta_m,
        "max_gain_error": {"accel": float(np.abs(cal.accel.gain - K_a).max()),
                           "mag": float(np.abs(cal.mag.gain - K_m).max())},
        "max_bias_error": {"accel": float(np.abs(cal.accel.bias - b_a).max()),
                           "mag": float(np.abs(cal.mag.bias - b_m).max())},
        "h_z": {"estimate": cal.h_z, "truth": h_z},
    }
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    np.set_printoptions(precision=5, suppress=True)
    print(f"simulated {args.intervals} still intervals (seed {args.seed}), the paper's Table I set-up")
    print(f"calibrated with {args.method.upper()} in {dt * 1e3:.1f} ms: {cal.message}")
    print(f"model: {cal.model_reason}")
    print(f"reconstruction error delta (noise std units): accel {delta_a:.4f}, mag {delta_m:.4f}")
    print(f"max |gain error|: accel {out['max_gain_error']['accel']:.2e}, mag {out['max_gain_error']['mag']:.2e}")
    print(f"max |bias error|: accel {out['max_bias_error']['accel']:.2e}, mag {out['max_bias_error']['mag']:.2e}")
    print(f"h_z: {cal.h_z:.6f} (truth {h_z:.6f})")
    print("K_a =\n" + str(cal.accel.gain))
    print("K_m =\n" + str(cal.mag.gain))
    return 0
