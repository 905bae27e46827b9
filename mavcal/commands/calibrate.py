"""``mavcal calibrate SOURCE...``: read -> raw recovery -> intervals -> calibration ->
ArduPilot parameters -> quality gates -> .param / JSON / HTML outputs -> optional safe write.

Exit codes (see :data:`EPILOG`): 0 every sensor with data accepted; 7 some accepted (those
written / in the .param), some rejected; 4 none accepted, or too little data; 2 usage;
3 unreadable source or no IMU data; 5 write failed and the vehicle was restored; 6 write
failed and the restore failed (the parameters in doubt are listed).
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import TextIO

from mavcal.commands.common import (
    BACKUP_HELP,
    add_device_map_arguments,
    add_json_argument,
    add_save_tlog_argument,
    add_signing_arguments,
    add_still_arguments,
    add_write_budget_argument,
    check_new_backup,
    check_optional_dependencies,
    check_save_tlog,
    json_output,
    parse_location,
    resolve_device,
    say_tlog_saved,
    signing_key,
    slot_maps,
    start_budget_s,
    still_config,
    write_outputs,
    write_with_report,
)
from mavcal.commands.segments import add_csv_rate_argument, csv_rate, csv_rate_hint
from mavcal.errors import InsufficientDataError, MavcalError, UsageError

EPILOG = """\
every accelerometer and compass with data gets its own verdict: accepted, or rejected with
the reasons (gate, value, limit, what to do). Only the accepted sensors' parameters go into
--param-out and --write; a rejected sensor keeps its current values (--force includes it,
its lines marked with the failed gate in the .param file). A sensor whose calibration in
force is not in the log (recorded without its parameters) is never written, not even with
--force: give them with --params FILE, or record with them.

exit codes:
  0  every sensor with data accepted (all written)
  7  some sensors accepted (written / in the .param), some rejected
  4  no sensor accepted, or too little data to calibrate
  2  usage error      3  unreadable source or no IMU data
  5  write failed, vehicle restored      6  write failed and restore failed
  8  the vehicle requires MAVLink 2 signing: no or wrong --signing-key (nothing written)
  9  an output file is an input (the log, --params; also through a link) or another output
     (refused before any work)
  70 internal error (a bug in mavcal: please report it with the -vv output)
several logs: the worst log's code, worst first: an error, too little data (4), every
sensor rejected (4), some accepted (7), all accepted (0)
with --json, a log that was read but could not be calibrated still gets its report: every
sensor with data rejected with the reason, "exit_code" and "error".
"""

HELP = "calibrate from a log or a live link, check quality, write .param/JSON/HTML, optionally write the vehicle"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.epilog = EPILOG  # exit codes in --help
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("sources", nargs="*", metavar="SOURCE",
                   help="log file(s) (.tlog, .bin, .log, .ulg, .csv) or one MAVLink device "
                        "(udpin:..., tcp:..., /dev/ttyACM0); for a fleet also a directory (every log under it), "
                        "a glob, @LIST (a file with one path/URL per line) and URLs (s3://bucket/prefix/, "
                        "https://..., needs mavcal[fleet])")
    out = p.add_argument_group("outputs")
    out.add_argument("--param-out", metavar="F",
                     help="write the new parameters as a .param file (MAVProxy/Mission Planner)")
    add_json_argument(out, "the full JSON report")
    out.add_argument("--report", metavar="F", help="write a self-contained HTML report (needs mavcal[plots])")
    out.add_argument("--jobs", type=int, default=None, metavar="N",
                     help="parallel processes: with several logs, logs at once (default 1); with one log, its "
                          "sensor fits at once (default: the CPUs, at most 4); more than the CPUs (or than 15) "
                          "is capped, with a note")
    fleet = p.add_argument_group("many logs (docs/fleet.md)")
    fleet.add_argument("--table", metavar="F",
                       help="results table, one row per log written as it finishes (.csv, or .parquet with "
                            "mavcal[fleet]); run again with the same table, the logs it has are skipped")
    fleet.add_argument("--scheduler-address", metavar="tcp://HOST:PORT",
                       help="run the logs on this Dask cluster (default: $DASK_SCHEDULER_ADDRESS, else the "
                            "--jobs processes here); needs mavcal[fleet]")
    fleet.add_argument("--drift-html", metavar="F",
                       help="write a self-contained HTML page of drift over time per vehicle (the table's rows "
                            "with --table, else this run's), a plot per vehicle that moved")
    fit = p.add_argument_group("calibration")
    fit.add_argument("--method", default="ncar", choices=["ncar", "ncdr", "fcar", "dcar"], help="paper variant")
    fit.add_argument("--model", default="auto", choices=["auto", "full", "diag-accel", "ardupilot", "offsets-scales"])
    fit.add_argument("--accel", type=int, default=0, metavar="I",
                     help="primary IMU instance (0-based, default 0): its board frame and quality numbers")
    fit.add_argument("--compass", type=int, default=0, metavar="I", help="primary compass instance (priority, 0-based)")
    fit.add_argument("--primary-only", action="store_true",
                     help="calibrate only the primary IMU and compass (default: every instance with data)")
    only = fit.add_mutually_exclusive_group()
    only.add_argument("--accel-only", nargs="*", type=int, metavar="I",
                      help="calibrate and write only accelerometers (all, or the instances I...), each from its "
                           "own still poses; no compass needed")
    only.add_argument("--compass-only", nargs="*", type=int, metavar="I",
                      help="calibrate and write only compasses (all, or the instances I...); the accelerometer "
                           "--accel is used as the reference and not written")
    fit.add_argument("--field-mgauss", type=float,
                     help="Earth field magnitude to scale the compass to (default: the World Magnetic Model at the "
                          "logged position or --location; without either the compass keeps its own scale and the "
                          "field strength is not checked)")
    fit.add_argument("--location", type=parse_location, metavar="LAT,LON[,ALT]",
                     help="position for the World Magnetic Model")
    fit.add_argument("--orient-tol", type=float, default=1.0, metavar="DEG",
                     help="snap the compass rotation to a standard COMPASS_ORIENT within this angle (default 1)")
    fit.add_argument("--no-custom-rotation", action="store_true", help="never use CUST_ROT (101/102) orientations")
    fit.add_argument("--force-external", action="store_true",
                     help="internal compass: write COMPASS_EXTERNAL (COMPASS_EXTERNn for compass n) = 2 so its "
                          "misalignment goes into COMPASS_ORIENT")
    fit.add_argument("--params", metavar="FILE",
                     help="the vehicle's parameters when the log was recorded (a .param file saved by Mission "
                          "Planner, QGroundControl or MAVProxy): the calibration in force of the sensors whose "
                          "parameters the log lacks (without it such a sensor is judged but never written)")
    fit.add_argument("--duration", type=float, default=60.0, metavar="S", help="live source: seconds to record")
    add_save_tlog_argument(fit)
    add_still_arguments(p)
    add_csv_rate_argument(p)
    w = p.add_argument_group("writing to the vehicle")
    w.add_argument("--write", action="store_true", help="write the parameters to the vehicle (safe writer)")
    w.add_argument("--connect", metavar="DEVICE", help="vehicle to write to (default: SOURCE when it is a device)")
    w.add_argument("--force", action="store_true", help="write even if a quality gate failed")
    w.add_argument("--dry-run", action="store_true", help="show the parameter diff; write nothing")
    w.add_argument("--backup", metavar="F", help=BACKUP_HELP)
    w.add_argument("--baud", type=int, default=115200,
                   help="serial baud rate of a live SOURCE or --connect device (default 115200)")
    w.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for the vehicle's heartbeat (live SOURCE and --write; default 5)")
    w.add_argument("--param-timeout", type=float, default=1.0, metavar="S",
                   help="seconds to wait for each parameter echo (default 1)")
    w.add_argument("--retries", type=int, default=3,
                   help="PARAM_SET attempts per parameter at least (default 3; see --write-budget)")
    w.add_argument("--yes", "-y", action="store_true", help="do not ask for confirmation before writing")
    add_write_budget_argument(w)
    add_signing_arguments(w)
    add_device_map_arguments(w)


class RecordingPrinter:
    """Shows a live recording's progress on one redrawn terminal line: elapsed and remaining
    seconds and the samples so far (a :class:`mavcal.link.live.RecordingProgress` per call)."""

    def __init__(self, out: TextIO) -> None:
        self.out = out

    def __call__(self, p) -> None:
        line = (f"recording: {p.elapsed_s:4.0f} of {p.duration_s:.0f} s, {p.remaining_s:.0f} s left, "
                f"{p.samples} samples")
        self.out.write(f"\r{line}\x1b[K" + ("\n" if p.done else ""))
        self.out.flush()


def recording_printer(out: TextIO, *, quiet: bool = False) -> RecordingPrinter | None:
    """A :class:`RecordingPrinter` on ``out`` when it is a terminal and not ``quiet``; else None (silent)."""
    try:
        tty = out.isatty()
    except (AttributeError, ValueError):
        tty = False
    return RecordingPrinter(out) if tty and not quiet else None


def _options(args):
    from mavcal.pipeline import Options

    sensors, only = "both", None
    for kind, given in (("accel", getattr(args, "accel_only", None)), ("compass", getattr(args, "compass_only", None))):
        if given is not None:
            sensors, only = kind, (tuple(given) or None)
    return Options(still=still_config(args), method=args.method, model=args.model, accel_instance=args.accel,
                   mag_instance=args.compass, all_instances=not args.primary_only, field_mgauss=args.field_mgauss,
                   location=args.location, orient_tol_deg=args.orient_tol, allow_custom=not args.no_custom_rotation,
                   force_external=args.force_external, sensors=sensors, only_instances=only)


def _refused(args, source: str, exc: MavcalError, prep, opts) -> None:
    """--json of a recording that could not be calibrated: every sensor with data rejected with
    the reason, the exit code and the refusal (then the error goes on to the CLI)."""
    if not args.json:
        return
    from mavcal.pipeline import refusal_verdicts
    from mavcal.report.json import refusal_json

    verdicts = refusal_verdicts(prep, exc, opts) if prep is not None else ()
    json_output(args.json, refusal_json(source, exc, verdicts, prep))


def _single(args, source: str) -> int:
    from mavcal.pipeline import calibrate_prepared, prepare
    from mavcal.sources.progress import auto_progress
    from mavcal.sources.reader import is_device, read_log
    from mavcal.workers import default_workers

    opts = replace(_options(args), workers=args.jobs or default_workers())
    device = is_device(source)
    prep = None
    progress = None if device else auto_progress(f"reading {Path(source).name}")
    try:
        if device:
            from mavcal.link.live import record_device

            source = resolve_device(source)
            log_ = record_device(source, baud=args.baud, duration_s=args.duration, heartbeat_timeout_s=args.timeout,
                                 budget_s=start_budget_s(args), signing_key=signing_key(args), tlog=args.save_tlog,
                                 on_progress=recording_printer(sys.stderr, quiet=getattr(args, "quiet", False)))
            say_tlog_saved(args)
        else:
            log_ = read_log(source, progress=progress, csv_rate_hz=csv_rate(args))
        prep = prepare(log_, opts, progress=progress, owned=True, params=args.params)
        del log_  # handed over: what prepare dropped from it is freed now, not after the fits
        run = calibrate_prepared(prep, opts, progress=progress)
    except MavcalError as exc:  # no fit at all: the JSON still says why, per sensor
        if isinstance(exc, UsageError):
            raise
        hint = csv_rate_hint(prep.log if prep is not None else None)
        if hint and isinstance(exc, InsufficientDataError):
            exc = type(exc)(f"{exc}{hint}")
        _refused(args, source, exc, prep, opts)
        raise exc from None
    finally:
        if progress is not None:
            progress.close()  # an error message then starts on a line of its own
    code = write_outputs(run, args, f"mavcal calibration of {run.source}")
    if args.write or args.dry_run:
        args.connect = args.connect or source  # checked before any work (check_flags)
        return write_with_report(args, run.params_to_write(args.force), args.backup, "calibration write",
                                 log_params=dict(run.params_before)) or code
    return code


def _cap_jobs(args) -> None:
    """``--jobs`` at most :func:`mavcal.workers.worker_limit` (the CPUs, at most 15), with one
    line on stderr when it was more: processes beyond the CPUs only compete for them, and
    each holds memory (a process per number typed once forked 5,738 and ran out of memory)."""
    if args.jobs is None:
        return
    if args.jobs < 1:
        raise UsageError("--jobs must be at least 1")
    from mavcal.workers import worker_limit

    limit = worker_limit()
    if args.jobs > limit:
        if not getattr(args, "quiet", False):
            print(f"mavcal: --jobs {args.jobs} is more than the {limit} processes worth running here "
                  f"(the CPUs this process may use, at most 15): using {limit}", file=sys.stderr)
        args.jobs = limit


def _check_numbers(args) -> None:
    """Numbers no run could use (a zero field strength, a negative timeout, sensor -1): refused."""
    import math

    def positive(v) -> bool:
        return v is not None and math.isfinite(v) and v > 0

    bad = [f"--{n.replace('_', '-')} must be a positive number (got {v})"
           for n, v in (("field_mgauss", args.field_mgauss), ("timeout", args.timeout),
                        ("param_timeout", args.param_timeout), ("write_budget", args.write_budget),
                        ("duration", args.duration), ("baud", args.baud))
           if v is not None and not positive(v)]
    if not (math.isfinite(args.orient_tol) and args.orient_tol >= 0):
        bad.append(f"--orient-tol must be 0 or more degrees (got {args.orient_tol})")
    if args.retries < 1:
        bad.append(f"--retries must be at least 1 (got {args.retries})")
    insts = [args.accel, args.compass] + list(args.accel_only or []) + list(args.compass_only or [])
    if any(i < 0 for i in insts):
        bad.append("sensor instances count from 0 (accel0, compass1 as the verdicts name them)")
    if bad:
        raise UsageError("; ".join(bad))


def _expand_fleet(args) -> None:
    """The fleet's SOURCEs expanded (directories, globs, @LIST, URLs: one entry per log) and
    ``args.fleet``: whether this is a many-log run (several logs, a fleet SOURCE, --table or a
    scheduler)."""
    import os

    from mavcal.fleet.inputs import expand_sources, is_url
    from mavcal.fleet.run import scheduler_from_env

    given = list(args.sources)
    fleety = [s for s in given if s.startswith("@") or is_url(s) or os.path.isdir(s)
              or (any(c in s for c in "*?[") and not os.path.exists(s))]
    table, sched = getattr(args, "table", None), getattr(args, "scheduler_address", None)
    args.sources = expand_sources(given) if fleety else given
    args.fleet = len(args.sources) > 1 or bool(fleety or table or sched or getattr(args, "drift_html", None))
    if args.fleet:
        args.scheduler_address = scheduler_from_env(sched)
        if args.scheduler_address and not args.scheduler_address.startswith(("tcp://", "tls://", "inproc://", "ws")):
            raise UsageError(f"--scheduler-address {args.scheduler_address}: give tcp://HOST:PORT")
        if table and not str(table).lower().endswith((".csv", ".parquet")):
            raise UsageError(f"--table {table}: give a .csv or a .parquet file")


def check_flags(args) -> None:
    """Refuse (UsageError, exit 2) every combination of options that cannot work, before the
    source is read: nothing is done and the message names the options the user gave."""
    from mavcal.commands.common import json_source_switch
    from mavcal.sources.reader import is_device

    args.sources = json_source_switch(args, list(args.sources))  # `calibrate --json LOG`: LOG, JSON on stdout
    if not args.sources:
        raise UsageError("calibrate needs a SOURCE: a log file, several, or a MAVLink device")
    _expand_fleet(args)
    several = args.fleet
    if several and (args.write or args.dry_run or args.param_out or args.report):
        raise UsageError("--write, --dry-run, --param-out and --report take a single SOURCE (a log file or a device), "
                         "without --table, --scheduler-address or --drift-html")
    writes = args.write or args.dry_run
    if several and any(is_device(s) for s in args.sources):
        raise UsageError("a live device is calibrated alone: give it as the only SOURCE")
    if writes and not (args.connect or is_device(args.sources[0])):
        given = "--write" if args.write else "--dry-run"
        raise UsageError(f"{given} needs --connect DEVICE when SOURCE is a log (the vehicle to write to); "
                         "nothing was done")
    if args.write and args.dry_run:
        raise UsageError("--dry-run shows what --write would change without writing: give one of them")
    unused = [o for o, v in (("--connect", args.connect), ("--backup", args.backup),
                             ("--map-compass", args.map_compass), ("--map-imu", args.map_imu),
                             ("--write-budget", args.write_budget)) if v]
    if unused and not writes:
        raise UsageError(f"{', '.join(unused)} only appl{'ies' if len(unused) == 1 else 'y'} with --write or "
                         "--dry-run; nothing was done")
    if args.params and (several or is_device(args.sources[0])):
        raise UsageError("--params gives the parameters of one recorded log: a single log SOURCE (a live vehicle "
                         "sends its own); nothing was done")
    if args.save_tlog and not is_device(args.sources[0]):
        raise UsageError("--save-tlog keeps a live recording: SOURCE is a log file already; nothing was done")
    _check_numbers(args)
    if args.params:  # read before any work: a bad file is refused at once (exit 3)
        from mavcal.autopilot.paramfile import read_param_file

        read_param_file(args.params)
    check_save_tlog(args.save_tlog)
    if args.write:
        check_new_backup(args.backup)
    slot_maps(args)  # --map-compass / --map-imu spelled right
    still_config(args)  # the thresholds (UsageError when invalid)
    csv_rate(args)


def run(args) -> int:
    check_flags(args)
    _cap_jobs(args)
    check_optional_dependencies(args)
    if not args.fleet:
        return _single(args, args.sources[0])
    return _fleet(args)


#: A fleet run with --table prints its table at the end up to this many logs (and keeps their rows for it)
PRINTED_MAX = 1000


def _fleet(args) -> int:
    from dataclasses import asdict

    from mavcal.batch import format_fleet_table
    from mavcal.fleet.drift import drift_text
    from mavcal.fleet.progress import progress_line
    from mavcal.fleet.run import run_fleet

    if args.table:  # the table (and a Parquet table's journal) is no log of the fleet, even under its directory
        import os

        from mavcal.outputs import same_file

        mine = [args.table, f"{args.table}.journal.csv"]
        args.sources = [s for s in args.sources if not any(
            same_file(s, t) or os.path.abspath(s) == os.path.abspath(t) for t in mine)]
    from mavcal.outputs import check_outputs

    check_outputs([("--table", args.table), ("--json", args.json), ("--drift-html", args.drift_html)], args.sources)
    shown = progress_line(sys.stderr, len(args.sources), quiet=getattr(args, "quiet", False))
    # the rows stay in this process only for what needs them all: --json, a run without a table
    # (the table printed at the end is its only output), or a fleet small enough to print
    keep = bool(args.json) or not args.table or len(args.sources) <= PRINTED_MAX
    try:
        done = run_fleet(list(args.sources), _options(args), jobs=args.jobs or 1, table=args.table,
                         scheduler_address=args.scheduler_address, csv_rate_hz=csv_rate(args), progress=shown,
                         keep_rows=keep)
    finally:
        if shown is not None:
            shown.close()
    out = sys.stderr if args.json == "-" else sys.stdout  # --json -: the JSON alone on stdout
    if keep:
        print(format_fleet_table(done.rows) if done.rows else "no log calibrated in this run", file=out)
    else:
        print(f"{done.n_calibrated} logs calibrated in this run ({done.n_failed} failed): their rows are in "
              f"{args.table} (the table is printed here for up to {PRINTED_MAX} logs); exit code {done.exit_code} "
              "(the worst log's)", file=out)
    if done.n_skipped:
        print(f"{done.n_skipped} log(s) already in {args.table} (same content, same mavcal version): "
              "skipped, their rows are there", file=out)
    if done.n_copied:
        print(f"{done.n_copied} log(s) with the content of a log already in {args.table} under another name: "
              "not calibrated again, its row written under their name", file=out)
    if args.table or args.drift_html:
        text = drift_text(done.drift)
        if text:
            print(text, file=out)
    if args.drift_html:
        from mavcal.fleet.drift import drift_html
        from mavcal.outputs import write_atomic

        write_atomic(args.drift_html, drift_html(done.drift))
        print(f"drift over time written to {args.drift_html}", file=out)
    if args.json:
        json_output(args.json, [asdict(r) for r in done.rows])
    return done.exit_code
