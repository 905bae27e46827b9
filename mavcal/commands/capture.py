"""``mavcal capture --connect DEVICE``: guided live capture, then the calibration and an optional safe write.

The vehicle streams its IMU; after every new still pose the calibration is refitted and
the next pose to hold is shown in words ("nose down, rolled 45 deg left, nose towards
magnetic east") until the 95 % heading error bound reaches the target (or the capture is
aborted, stopped with Ctrl-C, or runs out of poses or time). Then the calibration summary is
printed, the outputs are written, and the parameters are written to the vehicle only after
confirmation (interactive y/N, or ``--write``/``--write --yes``) through the same safe
writer as ``calibrate --write``.

Exit codes as ``calibrate``: 0 every sensor accepted (and written when asked); 7 some sensors
accepted (only their parameters are written), some rejected; 2 usage; 3 the device does not
answer; 4 aborted (impossible field, magnetic disturbance), no sensor accepted or too little
data; 5 write failed and the vehicle was restored; 6 write failed and the restore failed; 8 the
vehicle requires MAVLink 2 signing and ``--signing-key`` is missing or wrong.
"""
from __future__ import annotations

import argparse
import sys
from typing import TextIO

from mavcal.commands.common import (
    add_link_arguments,
    check_new_backup,
    check_optional_dependencies,
    parse_location,
    signing_key,
    start_budget_s,
    write_outputs,
    write_with_report,
)
from mavcal.errors import UsageError

HELP = "guided live capture: says which pose to hold next, fits as it goes, then writes on confirmation"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_link_arguments(p)  # --connect, --baud, --timeout, --param-timeout, --retries, --dry-run, --yes
    cap = p.add_argument_group("capture")
    cap.add_argument("--target-deg", type=float, default=0.5, metavar="DEG",
                     help="stop when the 95 %% heading error bound is below this (default 0.5)")
    cap.add_argument("--max-poses", type=int, default=40, metavar="N", help="stop after N still poses (default 40)")
    cap.add_argument("--min-poses", type=int, default=8, metavar="N", help="never stop before N poses (default 8)")
    cap.add_argument("--duration", type=float, default=600.0, metavar="S",
                     help="stop after S seconds at the latest (default 600)")
    cap.add_argument("--hold", type=float, default=1.0, metavar="S",
                     help="shortest still hold that counts as a pose (default 1)")
    cap.add_argument("--rate", type=float, default=25.0, metavar="HZ", help="IMU stream rate (default 25, at least 25)")
    fit = p.add_argument_group("calibration")
    fit.add_argument("--accel", type=int, default=0, metavar="I", help="IMU instance (0-based, default 0)")
    fit.add_argument("--compass", type=int, default=0, metavar="I", help="compass instance (priority, 0-based)")
    fit.add_argument("--field-mgauss", type=float, help="Earth field magnitude to scale the compass to")
    fit.add_argument("--location", type=parse_location, metavar="LAT,LON[,ALT]",
                     help="position for the World Magnetic Model")
    out = p.add_argument_group("outputs")
    out.add_argument("--param-out", metavar="F", help="write the new parameters as a .param file")
    out.add_argument("--json", metavar="F", help="write the full JSON report ('-' for stdout)")
    out.add_argument("--report", metavar="F", help="write a self-contained HTML report (needs mavcal[plots])")
    w = p.add_argument_group("writing to the vehicle")
    w.add_argument("--write", action="store_true", help="write the parameters (asks first unless --yes)")
    w.add_argument("--force", action="store_true",
                   help="write the rejected sensors' parameters too (and values outside ArduPilot's limits)")
    w.add_argument("--backup", metavar="F", help="backup .param of the old values (default mavcal-backup-DATE.param)")


class StatusPrinter:
    """Shows capture statuses: one redrawn screen on a terminal, one line per change otherwise."""

    def __init__(self, out: TextIO, target_deg: float | None = None, tty: bool | None = None) -> None:
        self.out = out
        self.target_deg = target_deg
        self.tty = bool(out.isatty()) if tty is None else tty
        self._last = ""

    def __call__(self, st) -> None:
        from mavcal.capture import status_line, status_screen

        if self.tty:
            text = status_screen(st, self.target_deg)
            if text != self._last:
                self.out.write("\x1b[H\x1b[2J" + text + "\n")
        else:
            text = status_line(st)
            if text != self._last:
                self.out.write(text + "\n")
        self._last = text
        self.out.flush()


def _check(args: argparse.Namespace) -> None:
    if not args.target_deg > 0:
        raise UsageError("--target-deg must be > 0")
    if args.max_poses < 1 or args.min_poses < 1:
        raise UsageError("--max-poses and --min-poses must be at least 1")
    if not args.duration > 0 or not args.hold > 0 or not args.rate > 0:
        raise UsageError("--duration, --hold and --rate must be > 0")
    check_new_backup(args.backup)


def run(args: argparse.Namespace) -> int:
    from mavcal.capture import CaptureConfig
    from mavcal.capture import live as live_capture
    from mavcal.pipeline import Options
    from mavcal.segment import StillConfig

    _check(args)
    check_optional_dependencies(args)
    try:
        still = StillConfig(min_duration_s=args.hold)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    config = CaptureConfig(target_heading_deg=args.target_deg, max_intervals=args.max_poses,
                           min_intervals=min(args.min_poses, args.max_poses), still=still)
    options = Options(still=still, accel_instance=args.accel, mag_instance=args.compass,
                      field_mgauss=args.field_mgauss, location=args.location)
    printer = StatusPrinter(sys.stderr, args.target_deg)
    session = live_capture.capture_live(args.connect, config=config, options=options, on_status=printer,
                                        baud=args.baud, rate_hz=args.rate, max_duration_s=args.duration,
                                        heartbeat_timeout_s=args.timeout, budget_s=start_budget_s(args),
                                        signing_key=signing_key(args))
    st = session.status
    if st is not None and st.aborted:
        raise live_capture.CaptureAbortedError(f"capture aborted: {st.reason}")
    run = session.result()  # InsufficientDataError (exit 4) when too little was captured
    # 0 all accepted, 7 some rejected (GateError, exit 4, when none was accepted and no --force)
    offer = args.write or args.dry_run or sys.stdin.isatty()  # a write plan (with the table) follows
    code = write_outputs(run, args, f"mavcal guided capture on {args.connect}", param_table=not offer)
    # the accepted sensors' parameters only (every sensor's with --force). No log_params for the
    # device-id check: the capture recorded the very vehicle it writes to, so its compasses and
    # IMUs are the vehicle's by construction
    changes = run.params_to_write(args.force)
    if args.write or args.dry_run:
        return write_with_report(args, changes, args.backup, "calibration write") or code
    if offer:  # offer it: the diff, then y/N
        try:
            return write_with_report(replace_ns(args, yes=False), changes, args.backup, "calibration write") or code
        except UsageError as exc:
            if str(exc).startswith("cancelled"):
                print("nothing written to the vehicle")
                return code
            raise
    print("nothing written to the vehicle (use --write to write the parameters)")
    return code


def replace_ns(ns: argparse.Namespace, **kw) -> argparse.Namespace:
    """A copy of ``ns`` with some attributes changed."""
    d = dict(vars(ns))
    d.update(kw)
    return argparse.Namespace(**d)
