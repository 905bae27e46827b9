"""``mavcal segments SOURCE``: the still intervals of a recording and whether they suffice.

Reads the source, undoes the calibration the vehicle applied (the raw readings), finds
the intervals in which the vehicle was held still and prints them with the coverage
diagnosis: text for people, ``--json`` for scripts.

Exit codes: 0 when at least one still interval was found (the diagnosis says when the data
are insufficient for a full calibration), 3 for an unreadable source, 4 when no still
interval was found at all (nothing a calibration could use), 2 for bad options.
"""
from __future__ import annotations

import argparse
import json
import math
from typing import Any, Dict

import numpy as np

from mavcal.errors import SegmentationError, UsageError

HELP = "find the still intervals of a log and diagnose whether they can calibrate"


def _cfg_defaults():
    from mavcal.segment import StillConfig

    return StillConfig()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = _cfg_defaults()
    parser.add_argument("source", metavar="SOURCE", help="log file (.tlog, .bin, .csv) or MAVLink device")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.add_argument("--no-recover", action="store_true",
                        help="segment the readings as logged (skip undoing the vehicle's calibration)")
    parser.add_argument("--samples", action="store_true", help="with --json: include every interval's samples")
    g = parser.add_argument_group("thresholds")
    g.add_argument("--window", type=float, default=d.window_s, metavar="S",
                   help=f"sliding window in seconds (default {d.window_s}; at least "
                        f"{d.min_window_samples} samples)")
    g.add_argument("--gyro", type=float, default=d.gyro_rad_s, metavar="RAD_S",
                   help=f"RMS gyro rate of a still window, rad/s (default {d.gyro_rad_s})")
    g.add_argument("--accel-std", type=float, default=d.accel_std_mps2, metavar="MPS2",
                   help=f"per-axis accel std of a still window, m/s^2 (default {d.accel_std_mps2})")
    g.add_argument("--mag-std", type=float, default=d.mag_std_mgauss, metavar="MGAUSS",
                   help=f"per-axis mag std of a still window without gyro, mGauss (default {d.mag_std_mgauss})")
    g.add_argument("--min-duration", type=float, default=d.min_duration_s, metavar="S",
                   help=f"shortest interval, seconds (default {d.min_duration_s})")
    g.add_argument("--min-samples", type=int, default=d.min_samples, metavar="N",
                   help=f"fewest samples per interval (default {d.min_samples})")
    g.add_argument("--trim", type=float, default=d.trim_s, metavar="S",
                   help=f"time cut from each interval edge, seconds (default {d.trim_s})")
    g.add_argument("--merge-deg", type=float, default=d.merge_deg, metavar="DEG",
                   help=f"merge neighbouring intervals closer than this (default {d.merge_deg})")
    g.add_argument("--cluster-deg", type=float, default=d.cluster_deg, metavar="DEG",
                   help=f"gravity directions closer than this are one orientation (default {d.cluster_deg})")
    g.add_argument("--no-gyro", action="store_true", help="decide stillness without the gyro")


def _config(args):
    from mavcal.segment import StillConfig

    try:
        return StillConfig(window_s=args.window, gyro_rad_s=args.gyro, accel_std_mps2=args.accel_std,
                           mag_std_mgauss=args.mag_std, min_duration_s=args.min_duration,
                           min_samples=args.min_samples, trim_s=args.trim, merge_deg=args.merge_deg,
                           cluster_deg=args.cluster_deg, use_gyro=not args.no_gyro)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _num(x: float) -> Any:
    return None if x is None or not math.isfinite(x) else float(x)


def _report(src: str, raw, seg, samples: bool) -> Dict[str, Any]:
    from mavcal.segment import axis_label

    cov = seg.coverage
    out: Dict[str, Any] = {
        "source": src,
        "sample_rate_hz": _num(seg.sample_rate_hz),
        "window_samples": seg.window_samples,
        "used_gyro": seg.used_gyro,
        "used_mag": seg.used_mag,
        "config": {k: getattr(seg.config, k) for k in seg.config.__dataclass_fields__},
        "intervals": [],
        "coverage": {
            "status": cov.status,
            "n_intervals": cov.n_intervals,
            "n_orientations": cov.n_orientations,
            "scatter_eigenvalues": [float(v) for v in cov.scatter_eigenvalues],
            "largest_empty_cap_deg": _num(cov.largest_empty_cap_deg),
            "messages": list(cov.messages),
        },
        "warnings": list(seg.warnings),
    }
    if raw is not None:
        out["recovery"] = {
            "frames": dict(raw.frames),
            "warnings": list(raw.warnings),
            "accel_cal_periods": [list(p) for p in raw.accel_cal_periods],
            "params_used": {k: [list(p) for p in v] for k, v in raw.params_used.items()},
        }
    for iv in seg.intervals:
        d = {
            "start_s": iv.start_s,
            "end_s": iv.end_s,
            "duration_s": iv.duration_s,
            "n_accel": {str(k): v for k, v in iv.n_accel.items()},
            "n_mag": {str(k): v for k, v in iv.n_mag.items()},
            "gravity_dir": [float(v) for v in iv.gravity_dir],
            "label": axis_label(iv.gravity_dir),
        }
        if samples:
            d["accel_mps2"] = {str(k): np.asarray(v).tolist() for k, v in iv.accel_mps2.items()}
            d["mag_mgauss"] = {str(k): np.asarray(v).tolist() for k, v in iv.mag_mgauss.items()}
        out["intervals"].append(d)
    return out


def _print_text(rep: Dict[str, Any]) -> None:
    print(f"{rep['source']}: accel 0 at {rep['sample_rate_hz'] or 0:.1f} Hz, window {rep['window_samples']} "
          f"samples, stillness from accel{' + gyro' if rep['used_gyro'] else ''}"
          f"{' + mag' if rep['used_mag'] else ''}")
    rec = rep.get("recovery")
    if rec:
        print(f"raw readings: accel in {rec['frames']['accel']}, mag in {rec['frames']['mag']}")
        for a, b in rec["accel_cal_periods"]:
            print(f"  onboard accel calibration ran {a:.1f}..{b:.1f} s (readings there already uncorrected)")
        for w in rec["warnings"]:
            print(f"  note: {w}")
    ivs = rep["intervals"]
    print(f"{len(ivs)} still interval{'s' if len(ivs) != 1 else ''}")
    if ivs:
        print(f"{'#':>3} {'start_s':>9} {'end_s':>9} {'dur_s':>6} {'n_acc':>6} {'n_mag':>6}  gravity (body)")
        for i, d in enumerate(ivs):
            g = d["gravity_dir"]
            print(f"{i:>3} {d['start_s']:>9.2f} {d['end_s']:>9.2f} {d['duration_s']:>6.1f} "
                  f"{d['n_accel'].get('0', 0):>6} {d['n_mag'].get('0', 0):>6}  "
                  f"({g[0]:+.2f} {g[1]:+.2f} {g[2]:+.2f}) {d['label']}")
    c = rep["coverage"]
    ev = c["scatter_eigenvalues"]
    print(f"coverage: {c['status']}: {c['n_orientations']} distinct orientation"
          f"{'s' if c['n_orientations'] != 1 else ''}, smallest scatter eigenvalue {ev[0]:.3f} "
          f"(ideal 0.333), largest empty cap {c['largest_empty_cap_deg']:.0f} deg")
    for w in rep["warnings"]:
        print(f"  - {w}")


def run(args) -> int:
    from mavcal.ardupilot.recover import recover_raw
    from mavcal.segment import find_still_intervals
    from mavcal.sources import open_source

    cfg = _config(args)
    log_ = open_source(args.source)
    raw = None if args.no_recover else recover_raw(log_)
    seg = find_still_intervals(log_ if raw is None else raw, cfg)
    rep = _report(str(args.source), raw, seg, bool(args.samples))
    if args.json:
        print(json.dumps(rep, indent=1))
    else:
        _print_text(rep)
    if not seg.intervals:
        why = [w for w in seg.warnings if not w.startswith("no still intervals")]
        raise SegmentationError(f"no still intervals in {args.source}"
                                + (f": {'; '.join(why)}" if why else " (the vehicle never stayed still "
                                   "long enough, or the thresholds are too strict)"))
    return 0
