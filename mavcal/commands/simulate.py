"""``mavcal simulate``: calibrate a data set simulated as in the paper's Table I and compare with the truth."""
from __future__ import annotations

import builtins
import sys
import time

import numpy as np

from mavcal.commands.common import add_json_argument, json_output

HELP = "calibrate a simulated data set (the paper's Monte Carlo set-up) and compare with the truth"


def add_arguments(p) -> None:
    p.add_argument("--seed", type=int, default=1, help="random seed of the simulation (default 1)")
    p.add_argument("--intervals", type=int, default=15, help="number of still intervals N (default 15)")
    p.add_argument("--method", default="ncar", choices=["ncar", "ncdr", "fcar", "dcar"], help="paper variant")
    p.add_argument("--tol", type=float, default=1e-4, help="stop condition gamma (default 1e-4)")
    add_json_argument(p, "the result as JSON")


def run(args) -> int:
    import mavcal
    from mavcal import sim
    from mavcal.core.models import MODEL_CHAIN, MODELS
    from mavcal.errors import UsageError

    least = MODELS[MODEL_CHAIN[-1]].min_intervals
    if args.intervals < least:  # said in the simulation's terms (no vehicle to hold still here)
        raise UsageError(f"--intervals {args.intervals}: a simulated data set needs at least {least} still intervals "
                         f"for the simplest model ({MODELS['full'].min_intervals} for the full joint model)")
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
    say = sys.stderr if args.json == "-" else sys.stdout
    np.set_printoptions(precision=5, suppress=True)
    _print_text(args, cal, out, dt, h_z, say)
    if args.json:
        json_output(args.json, out)
    return 0


def _print_text(args, cal, out: dict, dt: float, h_z: float, say) -> None:
    def print(*a) -> None:  # noqa: A001 (every line goes to ``say``)
        builtins.print(*a, file=say)

    delta_a, delta_m = out["delta_accel"], out["delta_mag"]
    print(f"simulated {args.intervals} still intervals (seed {args.seed}), the paper's Table I set-up")
    print(f"calibrated with {args.method.upper()} in {dt * 1e3:.1f} ms: {cal.message}")
    print(f"model: {cal.model_reason}")
    print(f"reconstruction error delta (noise std units): accel {delta_a:.4f}, mag {delta_m:.4f}")
    print(f"max |gain error|: accel {out['max_gain_error']['accel']:.2e}, mag {out['max_gain_error']['mag']:.2e}")
    print(f"max |bias error|: accel {out['max_bias_error']['accel']:.2e}, mag {out['max_bias_error']['mag']:.2e}")
    print(f"h_z: {cal.h_z:.6f} (truth {h_z:.6f})")
    print("K_a =\n" + str(cal.accel.gain))
    print("K_m =\n" + str(cal.mag.gain))
