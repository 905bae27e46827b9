"""``mavcal calibrate SOURCE...``: read -> raw recovery -> intervals -> calibration ->
ArduPilot parameters -> quality gates -> .param / JSON / HTML outputs -> optional safe write.

Exit codes: 0 success; 2 usage; 3 unreadable source or no IMU data; 4 calibration rejected
by the gates or too little data; 5 write failed and the vehicle was restored; 6 write
failed and the restore failed (the parameters in doubt are listed).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mavcal.errors import GateError, UsageError

HELP = "calibrate from a log or a live link, check quality, write .param/JSON/HTML, optionally write the vehicle"


def _location(text: str):
    try:
        parts = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError("expected LAT,LON[,ALT] in degrees (and metres)") from None
    if len(parts) not in (2, 3) or not (-90 <= parts[0] <= 90 and -180 <= parts[1] <= 180):
        raise argparse.ArgumentTypeError("expected LAT,LON[,ALT] with -90 <= LAT <= 90, -180 <= LON <= 180")
    return tuple(parts + [0.0] * (3 - len(parts)))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sources", nargs="+", metavar="SOURCE",
                   help="log file(s) (.tlog, .bin, .log, .csv) or one MAVLink device (udpin:..., tcp:..., /dev/ttyACM0)")
    out = p.add_argument_group("outputs")
    out.add_argument("--param-out", metavar="F", help="write the new parameters as a .param file (MAVProxy/Mission Planner)")
    out.add_argument("--json", metavar="F", help="write the full JSON report ('-' for stdout)")
    out.add_argument("--report", metavar="F", help="write a self-contained HTML report (needs mavcal[plots])")
    out.add_argument("--jobs", type=int, default=1, metavar="N", help="with several logs: parallel processes")
    fit = p.add_argument_group("calibration")
    fit.add_argument("--method", default="ncar", choices=["ncar", "ncdr", "fcar", "dcar"], help="paper variant")
    fit.add_argument("--model", default="auto", choices=["auto", "full", "diag-accel", "ardupilot", "offsets-scales"])
    fit.add_argument("--accel", type=int, default=0, metavar="I",
                     help="primary IMU instance (0-based, default 0): its board frame and quality numbers")
    fit.add_argument("--compass", type=int, default=0, metavar="I", help="primary compass instance (priority, 0-based)")
    fit.add_argument("--primary-only", action="store_true",
                     help="calibrate only the primary IMU and compass (default: every instance with data)")
    fit.add_argument("--field-mgauss", type=float, help="Earth field magnitude to scale the compass to")
    fit.add_argument("--location", type=_location, metavar="LAT,LON[,ALT]", help="position for the World Magnetic Model")
    fit.add_argument("--orient-tol", type=float, default=1.0, metavar="DEG",
                     help="snap the compass rotation to a standard COMPASS_ORIENT within this angle (default 1)")
    fit.add_argument("--no-custom-rotation", action="store_true", help="never use CUST_ROT (101/102) orientations")
    fit.add_argument("--force-external", action="store_true",
                     help="internal compass: write COMPASS_EXTERN=2 so its misalignment goes into COMPASS_ORIENT")
    fit.add_argument("--duration", type=float, default=60.0, metavar="S", help="live source: seconds to record")
    seg = p.add_argument_group("still intervals")
    seg.add_argument("--gyro-threshold", type=float, metavar="RAD_S", help="RMS rate below which it is still")
    seg.add_argument("--accel-std", type=float, metavar="MPS2", help="largest accel std in a still window")
    seg.add_argument("--min-duration", type=float, metavar="S", help="shortest still interval")
    w = p.add_argument_group("writing to the vehicle")
    w.add_argument("--write", action="store_true", help="write the parameters to the vehicle (safe writer)")
    w.add_argument("--connect", metavar="DEVICE", help="vehicle to write to (default: SOURCE when it is a device)")
    w.add_argument("--force", action="store_true", help="write even if a quality gate failed")
    w.add_argument("--dry-run", action="store_true", help="show the parameter diff; write nothing")
    w.add_argument("--backup", metavar="F", help="backup .param of the old values (default mavcal-backup-DATE.param)")
    w.add_argument("--baud", type=int, default=115200)
    w.add_argument("--timeout", type=float, default=5.0, metavar="S", help="heartbeat timeout")
    w.add_argument("--param-timeout", type=float, default=1.0, metavar="S", help="wait for each parameter echo")
    w.add_argument("--retries", type=int, default=3)
    w.add_argument("--yes", "-y", action="store_true", help="do not ask for confirmation before writing")


def _options(args):
    from dataclasses import replace

    from mavcal.pipeline import Options
    from mavcal.segment import StillConfig

    still = StillConfig()
    kw = {}
    if args.gyro_threshold is not None:
        kw["gyro_rad_s"] = args.gyro_threshold
    if args.accel_std is not None:
        kw["accel_std_mps2"] = args.accel_std
    if args.min_duration is not None:
        kw["min_duration_s"] = args.min_duration
    try:
        still = replace(still, **kw)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return Options(still=still, method=args.method, model=args.model, accel_instance=args.accel,
                   mag_instance=args.compass, all_instances=not args.primary_only, field_mgauss=args.field_mgauss, location=args.location,
                   orient_tol_deg=args.orient_tol, allow_custom=not args.no_custom_rotation,
                   force_external=args.force_external)


def summary(run) -> str:
    """Short human summary (the report module's text; kept here for the commands that print it)."""
    from mavcal.report import summary_text

    return summary_text(run)


def write_outputs(run, args, title: str) -> None:
    """Print the summary, write --json/--report, apply the gates, then write --param-out.

    Shared by ``calibrate`` and ``capture``. Raises GateError (exit 4) when a quality gate
    failed and ``--force`` was not given; the JSON and HTML reports are written first, so
    the reasons are on disk either way.
    """
    from mavcal.ardupilot.paramfile import write_param_file
    from mavcal.pipeline import run_to_json

    print(summary(run))
    if args.json:
        text = json.dumps(run_to_json(run), indent=1)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).write_text(text)
    if args.report:
        from mavcal.report import write_html
        write_html(run, args.report)
        print(f"report written to {args.report}")
    if not run.accepted and not args.force:
        if args.param_out or getattr(args, "write", False):
            print("nothing written: the calibration failed a quality gate (use --force to override)", file=sys.stderr)
        raise GateError("calibration rejected: " + "; ".join(f"{g.sensor} {g.name}" for g in run.gates.failures()))
    if args.param_out:
        write_param_file(args.param_out, run.mapping.new, header=[title, f"model {run.calibration.model}"])
        print(f"parameters written to {args.param_out}")


def _single(args, source: str) -> int:
    from mavcal.link.live import record_device
    from mavcal.pipeline import calibrate_source
    from mavcal.sources import is_device
    from mavcal.sources.progress import auto_progress

    opts = _options(args)
    device = is_device(source)
    if device:
        log_ = record_device(source, baud=args.baud, duration_s=args.duration, progress=auto_progress("recording"))
        run = calibrate_source(log_, opts)
    else:
        run = calibrate_source(source, opts, progress=auto_progress(f"reading {Path(source).name}"))
    write_outputs(run, args, f"mavcal calibration of {run.source}")
    if args.write or args.dry_run:
        target = args.connect or (source if device else None)
        if target is None:
            raise UsageError("--write needs --connect DEVICE when SOURCE is a log")
        from mavcal.commands.apply import write_with_report

        args.connect = target
        if args.backup is not None and Path(args.backup).exists():
            raise UsageError(f"backup file {args.backup!r} already exists; not overwriting it")
        return write_with_report(args, dict(run.mapping.new), args.backup, "calibration write")
    return 0


def run(args) -> int:
    if args.jobs < 1:
        raise UsageError("--jobs must be at least 1")
    if len(args.sources) == 1:
        return _single(args, args.sources[0])
    if args.write or args.dry_run or args.param_out or args.report:
        raise UsageError("--write, --dry-run, --param-out and --report take a single SOURCE")
    from mavcal.batch import calibrate_many, format_fleet_table

    rows = calibrate_many(list(args.sources), _options(args), jobs=args.jobs)
    print(format_fleet_table(rows))
    if args.json:
        from dataclasses import asdict
        text = json.dumps([asdict(r) for r in rows], indent=1, default=str)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).write_text(text)
    return max((r.exit_code for r in rows), default=0)
