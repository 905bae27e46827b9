"""``mavcal segments SOURCE``: the still intervals of a recording and whether they suffice.

Reads the source and prepares it exactly as ``mavcal calibrate`` does
(:func:`mavcal.pipeline.prepare`: integer truncation undone, the calibration the vehicle
applied undone), finds the intervals in which the vehicle was held still with the same
thresholds and options as ``calibrate`` and prints them with the coverage diagnosis: text
for people, ``--json`` for scripts.

Per sensor it says whether the coverage can identify it (gravity directions for an
accelerometer, field directions, i.e. poses at different headings, for a compass) and which
poses to add: the rule of :mod:`mavcal.coverage`, the same function whose verdict
``calibrate``'s data gates apply.

Exit codes (one rule: 4 whenever ``calibrate`` could not use the intervals):
0 the coverage is "ok" or "reduced" and at least one sensor can be identified (a
calibration can run, with a reduced model when "reduced"); 4 the coverage is
"insufficient" (no still interval at all, or too few / too few orientations for any model)
or it identifies no sensor; 3 unreadable source; 2 bad options. The report (text or
``--json``) is printed first either way.
"""
from __future__ import annotations

import argparse
import builtins
import math
import sys
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from mavcal.commands.common import add_json_argument, add_still_arguments, json_output, still_config
from mavcal.errors import SegmentationError, UsageError

HELP = "find the still intervals of a log and diagnose whether they can calibrate"
EPILOG = """\
exit codes:
  0  coverage ok or reduced and at least one sensor identifiable: a calibration can run
  4  coverage insufficient (no still interval, or too few intervals/orientations for any
     model) or no sensor identifiable
  3  unreadable source      2  bad options      70  internal error (a bug: report it with -vv)
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG  # exit codes in --help
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("source", metavar="SOURCE", nargs="?",
                        help="log file (.tlog, .bin, .log, .ulg, .csv) or MAVLink device")
    add_json_argument(parser, "the intervals and coverage as JSON")
    parser.add_argument("--no-recover", action="store_true",
                        help="segment the readings as logged (skip undoing the vehicle's calibration)")
    parser.add_argument("--samples", action="store_true", help="with --json: include every interval's samples")
    parser.add_argument("--duration", type=float, default=10.0, metavar="S",
                        help="live source: seconds to record (default 10)")
    parser.add_argument("--baud", type=int, default=115200, help="live source: serial baud rate (default 115200)")
    add_still_arguments(parser)
    add_csv_rate_argument(parser)


def add_csv_rate_argument(parser: argparse.ArgumentParser) -> None:
    """``--csv-rate HZ`` (segments and calibrate): the sample rate of a CSV without a time column."""
    parser.add_argument("--csv-rate", type=float, default=None, metavar="HZ",
                        help="sample rate of a CSV log without a time column (default: 100 Hz assumed); the "
                             "still-interval durations are measured with it")


def csv_rate(args) -> float:
    """``--csv-rate`` (UsageError unless a positive number), or the reader's assumption."""
    from mavcal.sources.reader import DEFAULT_CSV_RATE_HZ

    rate = getattr(args, "csv_rate", None)
    if rate is None:
        return DEFAULT_CSV_RATE_HZ
    if not (math.isfinite(rate) and rate > 0):
        raise UsageError(f"--csv-rate must be a positive number of Hz, got {rate}")
    return float(rate)


def csv_rate_hint(log_) -> str:
    """What to do when too few still intervals were found in a CSV without a time column."""
    from mavcal.sources.reader import csv_rate_was_assumed

    if log_ is None or not csv_rate_was_assumed(log_):
        return ""
    return ("; the CSV has no time column, so its sample rate was assumed: if its still holds are shorter than "
            "the detector's --window/--min-duration at that rate, give the real rate with --csv-rate HZ (a lower "
            "rate lengthens them) or shorten --window and --min-duration")


def _num(x: float) -> Any:
    return None if x is None or not math.isfinite(x) else float(x)


def _report(src: str, raw, seg, samples: bool, sensors, reach=None) -> dict[str, Any]:
    from mavcal.gravity_spread import axis_label

    cov = seg.coverage
    out: dict[str, Any] = {
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
        "sensors": [{"sensor": c.sensor, "identifiable": c.identifiable, "n_intervals": c.n_intervals,
                     "n_orientations": c.n_orientations, "n_field_directions": c.n_field_directions,
                     "missing": list(c.missing), "add": c.add, "text": c.text()} for c in sensors],
        "warnings": list(seg.warnings),
        "reach": None if reach is None else {
            "max_tilt_deg": _num(reach.max_tilt_deg), "n_field_directions": reach.n_field_directions,
            "compass_identified": reach.compass_identified, "missing": list(reach.missing), "add": reach.add,
            "kept": [{"sensor": k.sensor, "parameter": k.what, "why": k.why, "pose": k.pose} for k in reach.kept],
            "text": reach.lines()},
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


def _print_text(rep: dict[str, Any], out: TextIO) -> None:
    def print(*a) -> None:  # noqa: A001 (every line of the text goes to ``out``)
        builtins.print(*a, file=out)

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
    print(f"gravity coverage: {c['status']}: {c['n_orientations']} distinct orientation"
          f"{'s' if c['n_orientations'] != 1 else ''}, smallest scatter eigenvalue {ev[0]:.3f} "
          f"(ideal 0.333), largest empty cap {c['largest_empty_cap_deg']:.0f} deg")
    for w in rep["warnings"]:
        print(f"  - {w}")
    if rep["sensors"]:
        print("per sensor (the data gates of calibrate apply the same rule):")
        for d in rep["sensors"]:
            print(f"  {d['text']}")
    if rep["reach"]:
        print("what the poses identify (a vehicle turned on the ground and tilted a little; calibrate fits this):")
        for line in rep["reach"]["text"]:
            print(f"  {line}")


def _segment(args, cfg):
    """(log, raw or None, segmentation): the recording as ``calibrate`` prepares it
    (:func:`mavcal.pipeline.prepare`), or, with ``--no-recover``, the readings as logged."""
    from mavcal.pipeline import Options, open_source, prepare
    from mavcal.sources.progress import auto_progress
    from mavcal.sources.reader import is_device, read_log

    src = str(args.source)
    if src == "auto":
        from mavcal.commands.common import resolve_device

        src = resolve_device(src)
    progress = auto_progress("recording" if is_device(src) else f"reading {Path(src).name}")
    log_ = (open_source(src, baud=args.baud, duration_s=args.duration, progress=progress) if is_device(src)
            else read_log(src, progress=progress, csv_rate_hz=csv_rate(args)))
    if args.no_recover:
        from mavcal.segment import find_still_intervals

        return log_, None, find_still_intervals(log_, cfg)
    prep = prepare(log_, Options(still=cfg), owned=True)
    return prep.log, prep.raw, prep.segmentation


def sensor_coverages(seg):
    """Every sensor's coverage by :mod:`mavcal.coverage`'s rule with ``calibrate``'s default gates
    (compasses paired with accelerometer 0, as ``calibrate`` pairs them by default)."""
    from mavcal.coverage import sensor_coverages as coverages
    from mavcal.pipeline import Options, coverage_rule

    return coverages(seg, 0, coverage_rule(Options(), seg))


def reach(seg):
    """What poses within reach identify (:func:`mavcal.coverage.segmentation_reach`), with
    ``calibrate``'s default gates and pairing; None when the rule does not apply."""
    from mavcal.coverage import segmentation_reach
    from mavcal.pipeline import Options, coverage_rule

    return segmentation_reach(seg, 0, None, coverage_rule(Options(), seg))


def _source(args) -> str:
    """SOURCE; ``segments --json LOG`` (the old switch before the log) still reads LOG."""
    from mavcal.commands.common import json_source_switch

    if args.source is None and args.json not in (None, "-"):
        args.source, args.json = args.json, "-"
    if args.source is None:
        raise UsageError("segments needs a SOURCE (a log file or a MAVLink device)")
    json_source_switch(args, [args.source])  # never a log as the JSON file
    return str(args.source)


def run(args) -> int:
    _source(args)
    cfg = still_config(args)
    csv_rate(args)
    log_, raw, seg = _segment(args, cfg)
    within = reach(seg) if seg.intervals else None
    sensors = sensor_coverages(seg) if seg.intervals else []
    if within is not None:
        from mavcal.coverage import within_reach

        sensors = [within_reach(c, within) for c in sensors]
    rep = _report(str(args.source), raw, seg, bool(args.samples), sensors, within)
    _print_text(rep, sys.stderr if args.json == "-" else sys.stdout)
    if args.json:
        json_output(args.json, rep)
    if not seg.intervals:
        why = [w for w in seg.warnings if not w.startswith("no still intervals")]
        raise SegmentationError(f"no still intervals in {args.source}"
                                + (f": {'; '.join(why)}" if why else " (the vehicle never stayed still "
                                   "long enough, or the thresholds are too strict)") + csv_rate_hint(log_))
    if within is not None and within.compass_identified:
        return 0  # calibrate fits the compass with the accelerometer's Z scale held
    if seg.coverage.status == "insufficient":
        raise SegmentationError(f"{args.source}: the still intervals cannot calibrate: "
                                + "; ".join(seg.coverage.messages) + csv_rate_hint(log_))
    if sensors and not any(c.identifiable for c in sensors):
        raise SegmentationError(f"{args.source}: the still intervals identify no sensor: "
                                + "; ".join(f"{c.sensor}: {c.missing[0]}" for c in sensors) + csv_rate_hint(log_))
    return 0
