"""What the subcommands share: arguments (link, still-interval thresholds, ``--location``),
output writing, and the one flow that writes parameters to a vehicle.

The texts come from :mod:`mavcal.report.text` (the MAVProxy module uses the same words).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any, TextIO

from mavcal.errors import GateError, SourceError, UsageError

__all__ = ["add_json_argument", "json_output", "BACKUP_HELP",
           "parse_location", "add_link_arguments", "add_still_arguments", "still_config", "write_text_output",
           "write_outputs", "confirm", "write_with_report", "resolve_device", "resolve_connect",
           "check_new_backup", "add_device_map_arguments", "slot_maps",
           "add_write_budget_argument", "add_signing_arguments", "signing_key", "start_budget_s",
           "add_save_tlog_argument", "check_save_tlog", "say_tlog_saved"]


# --------------------------------------------------------------------------- arguments

#: how every command that writes parameters names its default backup file
#: (:func:`mavcal.link.backup.default_backup_path`)
BACKUP_HELP = ("backup .param of the old values, never overwritten (default mavcal-backup-YYYYmmdd-HHMMSS.param "
               "in the current directory)")


def add_json_argument(parser: Any, what: str = "the JSON report") -> None:
    """``--json [F]``, the same in every subcommand: write ``what`` to the file F, or to stdout
    with ``-`` or with no F (the people's text then goes to stderr)."""
    parser.add_argument("--json", nargs="?", const="-", default=None, metavar="F",
                        help=f"write {what} to F ('-' or no F: stdout, the text then goes to stderr)")


#: what a log file's name ends with (:func:`mavcal.sources.reader.read_log`'s types)
LOG_SUFFIXES = (".tlog", ".bin", ".log", ".ulg", ".csv")


def is_log_file(path: str | None) -> bool:
    """``path`` is an existing file named as a log (an input, never an output to write over)."""
    return path not in (None, "-") and Path(str(path)).suffix.lower() in LOG_SUFFIXES and Path(str(path)).is_file()


def json_source_switch(args, sources: list[str]) -> list[str]:
    """``--json LOG`` with no SOURCE after it (argparse gave the log to ``--json``): LOG is the
    source and the JSON goes to stdout, in every subcommand; ``--json LOG`` beside a SOURCE is
    refused (LOG would be written over). Returns the sources."""
    if not sources and is_log_file(args.json):
        sources, args.json = [args.json], "-"
    if is_log_file(args.json):
        raise UsageError(f"--json {args.json}: that is a log (an input), not the JSON file to write: give the JSON "
                         "file's name (--json report.json) or --json - for stdout; nothing was done")
    return sources


def json_output(dest: str, doc: Any, say: TextIO | None = None) -> None:
    """Write ``doc`` as JSON to ``dest`` (``-``: stdout); a file is named on ``say`` (stdout by default)
    as the .param and the HTML report are."""
    write_text_output(dest, json.dumps(doc, indent=1, default=str))
    if dest != "-":
        print(f"JSON report written to {dest}", file=say or sys.stdout)

def parse_location(text: str) -> tuple:
    """argparse type of ``--location``: ``LAT,LON[,ALT]`` in degrees (and metres) -> (lat, lon, alt)."""
    try:
        parts = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError("expected LAT,LON[,ALT] in degrees (and metres)") from None
    if len(parts) not in (2, 3) or not (-90 <= parts[0] <= 90 and -180 <= parts[1] <= 180):
        raise argparse.ArgumentTypeError("expected LAT,LON[,ALT] with -90 <= LAT <= 90, -180 <= LON <= 180")
    return tuple(parts + [0.0] * (3 - len(parts)))


def add_link_arguments(parser: argparse.ArgumentParser) -> None:
    """The vehicle link and write options (apply, restore, capture)."""
    parser.add_argument("--connect", default="auto", metavar="DEVICE",
                        help="MAVLink device: a serial port (/dev/ttyACM0, COM3), udpin:HOST:PORT, udpout:HOST:PORT, "
                             "tcp:HOST:PORT, or auto (the default: the one serial port that looks like a flight "
                             "controller)")
    parser.add_argument("--baud", type=int, default=115200,
                        help="serial baud rate (default 115200; telemetry radios usually run at 57600)")
    parser.add_argument("--timeout", type=float, default=5.0, metavar="S",
                        help="seconds to wait for the vehicle's heartbeat (default 5)")
    parser.add_argument("--param-timeout", type=float, default=1.0, metavar="S",
                        help="seconds to wait for each parameter echo (default 1)")
    parser.add_argument("--retries", type=int, default=3,
                        help="PARAM_SET attempts per parameter at least (default 3; see --write-budget)")
    add_write_budget_argument(parser)
    add_signing_arguments(parser)
    parser.add_argument("--dry-run", action="store_true", help="show what would change; write nothing")
    parser.add_argument("--yes", "-y", action="store_true", help="do not ask for confirmation")


def resolve_device(device: str, say: TextIO | None = None) -> str:
    """``auto``: the serial port that looks like a flight controller (:mod:`mavcal.link.autodetect`),
    said on ``say`` (stderr); any other device as given."""
    if device != "auto":
        return device
    from mavcal.link.autodetect import find_port

    port = find_port()
    print(f"mavcal: --connect auto: {port.label()}", file=say or sys.stderr)
    return port.device


def resolve_connect(args: argparse.Namespace) -> None:
    """``args.connect`` resolved (:func:`resolve_device`) before the command opens it."""
    if getattr(args, "connect", None) == "auto":
        args.connect = resolve_device(args.connect)


def add_write_budget_argument(parser: Any) -> None:
    """``--write-budget S``: how long each PARAM_SET / force-save / read keeps being retried."""
    parser.add_argument("--write-budget", type=float, default=None, metavar="S",
                        help="seconds to keep retrying each PARAM_SET, force-save and read on a lossy link "
                             "(default 15 x --param-timeout)")


def add_signing_arguments(parser: Any) -> None:
    """``--signing-key PASSPHRASE`` / ``--signing-key-file F``: MAVLink 2 signing, MAVProxy's key derivation."""
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--signing-key", metavar="PASSPHRASE", default=None,
                   help="sign the link with MAVLink 2 signing; the key is SHA-256 of PASSPHRASE, as MAVProxy's "
                        "'signing setup PASSPHRASE' (visible in the process list: prefer --signing-key-file)")
    g.add_argument("--signing-key-file", metavar="F", default=None,
                   help="as --signing-key, with the passphrase on the first line of the file F")


def signing_key(args: argparse.Namespace):
    """The :class:`mavcal.link.signing.SigningKey` of ``--signing-key``/``--signing-key-file``, or None."""
    from mavcal.link.signing import key_from_file, key_from_passphrase

    if getattr(args, "signing_key_file", None):
        return key_from_file(args.signing_key_file)
    if getattr(args, "signing_key", None) is not None:
        return key_from_passphrase(args.signing_key)
    return None


def start_budget_s(args: argparse.Namespace) -> float:
    """How long the start of a session (heartbeat, parameter reads, stream requests) keeps
    retrying on a lossy link: the write budget (``--write-budget``, default 15 x --param-timeout)."""
    from mavcal.link.writer import DEFAULT_BUDGET_FACTOR

    budget = getattr(args, "write_budget", None)
    return float(budget) if budget is not None else DEFAULT_BUDGET_FACTOR * float(args.param_timeout)


def add_device_map_arguments(parser: Any) -> None:
    """``--map-compass`` / ``--map-imu LOGSLOT:VEHICLESLOT``: write a log's sensor to another vehicle slot."""
    parser.add_argument("--map-compass", action="append", default=[], metavar="LOG:VEHICLE",
                        help="write the log's compass LOG to the vehicle's compass VEHICLE, even if their device "
                             "ids differ (repeatable); named as the verdicts name them, 0-based like --compass: "
                             "compass0:compass1 (plain numbers are the 1-based priority slots: 1:2 is the same)")
    parser.add_argument("--map-imu", action="append", default=[], metavar="LOG:VEHICLE",
                        help="write the log's accelerometer LOG to the vehicle's VEHICLE, even if their INS_ACC*_ID "
                             "differ (repeatable); accel0:accel1 (0-based like --accel), or 1-based numbers 1:2")


class _DeprecatedAlias(argparse.Action):
    """Stores into the new option's destination and says once that the spelling is old."""

    def __init__(self, option_strings, dest, new: str = "", **kw) -> None:
        self.new = new
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(f"mavcal: warning: {option_string} is deprecated, use {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_still_arguments(parser: Any) -> None:
    """The still-interval thresholds (``calibrate`` and ``segments`` alike), defaults from
    :class:`mavcal.segment.StillConfig`. ``--gyro`` is a hidden, deprecated alias of
    ``--gyro-threshold``."""
    from mavcal.segment import StillConfig

    d = StillConfig()
    g = parser.add_argument_group("still intervals")
    g.add_argument("--window", type=float, default=d.window_s, metavar="S",
                   help=f"sliding window in seconds (default {d.window_s}; at least {d.min_window_samples} samples)")
    g.add_argument("--gyro-threshold", type=float, default=d.gyro_rad_s, metavar="RAD_S",
                   help=f"RMS gyro rate of a still window, rad/s (default {d.gyro_rad_s})")
    g.add_argument("--gyro", dest="gyro_threshold", type=float, action=_DeprecatedAlias, new="--gyro-threshold",
                   help=argparse.SUPPRESS)
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


def still_config(args: argparse.Namespace):
    """The :class:`mavcal.segment.StillConfig` of :func:`add_still_arguments`' options (UsageError if invalid)."""
    from mavcal.segment import StillConfig

    try:
        return StillConfig(window_s=args.window, gyro_rad_s=args.gyro_threshold, accel_std_mps2=args.accel_std,
                           mag_std_mgauss=args.mag_std, min_duration_s=args.min_duration,
                           min_samples=args.min_samples, trim_s=args.trim, merge_deg=args.merge_deg,
                           cluster_deg=args.cluster_deg, use_gyro=not args.no_gyro)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


# --------------------------------------------------------------------------- outputs

def write_text_output(dest: str, text: str) -> None:
    """Print ``text`` for ``dest == '-'``, else write it to the file ``dest`` (UsageError if it cannot)."""
    if dest == "-":
        print(text)
        return
    from mavcal.outputs import write_atomic

    try:
        write_atomic(dest, text)  # an interrupted run leaves the old file whole
    except SourceError as exc:
        raise UsageError(str(exc)) from None


#: the options that name a file a command writes, and those that name a file it reads
OUTPUT_OPTIONS = ("param_out", "json", "report", "backup", "save_tlog")
INPUT_OPTIONS = ("sources", "source", "file", "backup_file", "params", "signing_key_file")


def check_output_paths(args: argparse.Namespace) -> None:
    """Before any work: refuse an output that is an input or another output
    (:func:`mavcal.outputs.check_outputs`, exit code 9)."""
    from mavcal.outputs import check_outputs

    outs = [(f"--{o.replace('_', '-')}", getattr(args, o, None)) for o in OUTPUT_OPTIONS]
    ins: list = []
    for o in INPUT_OPTIONS:
        v = getattr(args, o, None)
        ins += list(v) if isinstance(v, (list, tuple)) else [v]
    check_outputs([(o, p) for o, p in outs if isinstance(p, str)], [p for p in ins if isinstance(p, str)])


def check_optional_dependencies(args: argparse.Namespace) -> None:
    """Before any work: refuse (exit 2, nothing done) an output whose optional dependency is
    missing, rather than fail after the whole calibration with half the outputs written."""
    if getattr(args, "report", None):
        from mavcal.report.html import missing_dependencies

        missing = missing_dependencies()
        if missing:
            raise UsageError(f"--report needs {', '.join(missing)}, which is not installed: "
                             "pip install 'mavcal[plots]' (or leave out --report); nothing was done")


def write_outputs(run, args: argparse.Namespace, title: str, *, param_table: bool = True) -> int:
    """Print the summary, write --json/--report, apply the per-sensor verdicts, then write
    --param-out with the accepted sensors' parameters (every sensor's with ``--force``, the
    rejected ones' lines marked with the failed gate).

    Shared by ``calibrate`` and ``capture``. Returns the run's exit code (0 all accepted,
    7 some rejected); raises GateError (exit 4) when no sensor was accepted and ``--force``
    was not given; the JSON and HTML reports are written first, so the reasons are on disk
    either way. With ``--json -`` the JSON alone goes to stdout (the summary to stderr).
    ``param_table`` False leaves the parameter table out of the summary (a write follows, whose
    plan shows the parameters against the vehicle's values).
    """
    from mavcal.report.json import to_json
    from mavcal.report.text import gate_refusal_text, rejection_notes, summary_text

    say = sys.stderr if args.json == "-" else sys.stdout
    print(summary_text(run, param_table=param_table, force=bool(args.force)), file=say)
    if args.json:
        json_output(args.json, to_json(run), say)
    if args.report:
        from mavcal.report import write_html
        write_html(run, args.report, force=bool(args.force))
        print(f"report written to {args.report}", file=say)
    code = run.exit_code
    forceable = bool(run.params_to_write(True))  # False: only sensors whose calibration in force is not known
    if code == 4 and not (args.force and forceable):
        if args.param_out or getattr(args, "write", False):
            hint = ("use --force" if forceable else "connect again (the parameters must download)"
                    if run.log.kind == "live" else "give the parameters in force with --params FILE")
            print(gate_refusal_text(run, hint), file=sys.stderr, end="")
        raise GateError("calibration rejected: " + "; ".join(f"{s} {why}" for s, why in rejection_notes(run).items()))
    if args.param_out:
        values = run.write_param_file(args.param_out, force=bool(args.force), title=title)
        left = sorted(set(run.mapping.new) - set(values))
        print(f"parameters written to {args.param_out}"
              + (f" ({len(left)} of rejected sensors left out: they keep their current values)" if left else ""),
              file=say)
    return 0 if args.force else code


# --------------------------------------------------------------------------- the write flow

def add_save_tlog_argument(parser: Any) -> None:
    """``--save-tlog F``: keep what a live session received, as a telemetry log."""
    parser.add_argument("--save-tlog", metavar="F", default=None,
                        help="live source: also save everything the vehicle sends (parameters, position, IMU "
                             "streams) as the telemetry log F, to keep, share, or calibrate again with "
                             "'mavcal calibrate F'")


def say_tlog_saved(args: argparse.Namespace) -> None:
    """One line on stderr once ``--save-tlog``'s recording is complete (whatever the fit then says)."""
    path = getattr(args, "save_tlog", None)
    if path and Path(path).exists() and not getattr(args, "quiet", False):
        print(f"recording saved to {path} (calibrate it again: mavcal calibrate {path})", file=sys.stderr)


def check_save_tlog(path: str | None) -> None:
    """UsageError unless ``--save-tlog``'s file can be created: a new name in a folder that exists
    (a recording is never overwritten, as a backup)."""
    if path is None:
        return
    p = Path(path)
    _refuse_existing(path, "--save-tlog:")
    if not p.parent.is_dir():
        raise UsageError(f"--save-tlog: the folder of {path!r} does not exist")
    if not os.access(p.parent, os.W_OK):
        raise UsageError(f"--save-tlog: cannot create files in the folder of {path!r}")


def check_new_backup(path: str | None) -> None:
    """UsageError when a backup file was named and already exists (never overwrite one)."""
    if path is not None:
        _refuse_existing(path, "backup file")


def _refuse_existing(path: str, what: str) -> None:
    """UsageError when ``path`` exists: a file mavcal keeps for the user is never overwritten."""
    if Path(path).exists():
        raise UsageError(f"{what} {path!r} already exists; not overwriting it")


def _open_tty() -> TextIO:
    """The controlling terminal, read and write (OSError without one)."""
    return open("/dev/tty", "r+", encoding="utf-8")  # noqa: SIM115 (closed by the caller)


def confirm(prompt: str, assume_yes: bool) -> None:
    """Ask y/N on the terminal the user sees; refuse (UsageError) when nobody can answer.

    The prompt goes to the controlling terminal (``/dev/tty``), else to stdout, never to
    stderr (with ``2> file`` it would be invisible, as ``input()`` does on a console). No
    terminal on stdin, or ``CI`` set (CI runners may give a pseudo-terminal nobody reads):
    refused unless ``assume_yes`` (``--yes``).
    """
    if assume_yes:
        return
    if os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no"):
        raise UsageError("not writing without confirmation: CI is set, nobody can answer (use --yes)")
    if not sys.stdin.isatty():
        raise UsageError("not writing without confirmation: stdin is not a terminal (use --yes)")
    try:
        tty = _open_tty()
    except OSError:
        sys.stdout.write(f"{prompt} [y/N] ")
        sys.stdout.flush()
        answer = sys.stdin.readline()
    else:
        with tty:
            tty.write(f"{prompt} [y/N] ")
            tty.flush()
            answer = tty.readline()
    if answer.strip().lower() not in ("y", "yes"):
        raise UsageError("cancelled; nothing was written")


def slot_maps(args: argparse.Namespace) -> tuple[dict[int, int], dict[int, int]]:
    from mavcal.autopilot.protocol import parse_slot_map

    maps: tuple[dict[int, int], dict[int, int]] = ({}, {})
    for m, kind, texts in ((maps[0], "compass", getattr(args, "map_compass", None) or []),
                           (maps[1], "imu", getattr(args, "map_imu", None) or [])):
        for t in texts:
            try:
                a, b = parse_slot_map(_one_based(t, kind), kind)
            except ValueError as exc:
                raise UsageError(f"--map-{kind}: {exc}") from None
            m[a] = b
    return maps


def _one_based(text: str, kind: str) -> str:
    """``compass0:compass1`` / ``accel0:accel1`` (the sensor names the verdicts print, 0-based)
    -> the 1-based ``1:2`` of :func:`mavcal.autopilot.protocol.parse_slot_map`; plain numbers pass."""
    prefixes = ("compass",) if kind == "compass" else ("accel", "imu")
    parts = text.split(":")
    if len(parts) != 2 or not any(p.startswith(prefixes) for p in parts):
        return text
    out = []
    for p in parts:
        name = next((x for x in prefixes if p.startswith(x)), None)
        if name is None or not p[len(name):].isdigit():
            raise ValueError(f"expected {prefixes[0]}N:{prefixes[0]}M (0-based, as the verdicts name them), "
                             f"got {text!r}")
        out.append(str(int(p[len(name):]) + 1))
    return ":".join(out)


def _matched_changes(args: argparse.Namespace, changes: dict, log_params: dict | None, table: dict) -> dict:
    """The log's calibration checked against the vehicle's device ids (UsageError on a
    mismatch) and moved to the vehicle slots the user mapped."""
    from mavcal.autopilot.protocol import device_id_problems, remap_changes

    if log_params is None:
        return changes
    cmap, imap = slot_maps(args)
    values = {n: v for n, (v, _) in table.items()}
    problems = device_id_problems(changes, log_params, values, compass_map=cmap, imu_map=imap)
    if problems:
        raise UsageError("; ".join(problems))
    try:
        return remap_changes(changes, compass_map=cmap, imu_map=imap)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _vehicle_values(link, args: argparse.Namespace, names: list) -> dict:
    """The part of the vehicle's table the write needs (:func:`mavcal.link.writer.fetch_for_write`)."""
    from mavcal.autopilot.protocol import id_names, related_names
    from mavcal.link.writer import fetch_for_write

    context = related_names(names) + id_names()
    return fetch_for_write(link, names, context=context, timeout_s=args.param_timeout,
                           fetch_timeout_s=max(30.0, 10 * args.param_timeout), budget_s=start_budget_s(args))


def write_with_report(args: argparse.Namespace, changes: dict, backup: str | None, what: str,
                      out: TextIO | None = None, log_params: dict | None = None, vehicle_check=None) -> int:
    """Connect to ``args.connect``, show the diff, confirm, write with the safe writer
    (:func:`mavcal.link.writer.write_params`) and print the outcome (:mod:`mavcal.report.text`).

    ``log_params``: the parameters of the log the calibration comes from; its compasses and
    IMUs must be the vehicle's by device id (``--map-compass`` / ``--map-imu`` to override).
    Values outside ArduPilot's limits are refused before any write unless ``args.force``.
    ``vehicle_check(link, table)``: called once the vehicle's values are read, before anything is
    shown or written; it raises to refuse the vehicle.
    """
    from mavcal.autopilot.protocol import force_save_kinds
    from mavcal.errors import ParamWriteError
    from mavcal.link.backup import default_backup_path
    from mavcal.link.connection import open_link
    from mavcal.link.writer import write_params
    from mavcal.report.text import plan_text, write_done_text, write_failed_text

    out = out or sys.stdout
    resolve_connect(args)
    force = bool(getattr(args, "force", False))
    opts = dict(retries=args.retries, timeout_s=args.param_timeout, budget_s=getattr(args, "write_budget", None),
                allow_out_of_range=force)
    link = open_link(args.connect, baud=args.baud, timeout_s=args.timeout, budget_s=start_budget_s(args),
                     signing_key=signing_key(args))
    try:
        table = _vehicle_values(link, args, list(changes))
        if vehicle_check is not None:
            vehicle_check(link, table)
        changes = _matched_changes(args, changes, log_params, table)
        if set(changes) - set(table):
            table.update(_vehicle_values(link, args, list(changes)))
        plan = write_params(link, changes, backup_path=None, params=table, dry_run=True, **opts)
        out.write(plan_text(plan, dry_run=args.dry_run))
        _warn_out_of_range(changes, table, force)
        if not plan.changed or args.dry_run:
            return 0
        confirm(f"write {len(plan.changed)} parameter(s) to system {link.target_system}?", args.yes)
        bpath = backup or str(default_backup_path())
        try:
            report = write_params(link, changes, backup_path=bpath, params=table,
                                  force_save=force_save_kinds(r.name for r in plan.changed),
                                  **opts)
        except ParamWriteError as exc:
            out.write(write_failed_text(exc, what, bpath, args.connect))
            raise
        out.write(write_done_text(report))
        return 0
    finally:
        link.close()


def _warn_out_of_range(changes: dict, table: dict, force: bool) -> None:
    """With --force, say loudly (stderr) which values break ArduPilot's limits and what is not
    marked calibrated."""
    from mavcal.autopilot.protocol import check_limits, failing_kinds

    values = {n: v for n, (v, _) in table.items()}
    bad = check_limits(changes, values)
    if not (force and bad):
        return
    from mavcal.report.text import forced_limits_text

    sys.stderr.write(forced_limits_text([v.message for v in bad], sorted(failing_kinds(changes, values))))
