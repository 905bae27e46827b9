"""``mavcal apply FILE --connect DEVICE``: write a .param file to the vehicle, safely.

Every value about to change is saved to a backup .param file first; each write is
confirmed by the vehicle's echo; on any failure everything written is restored from the
backup (exit 5), or the parameters in doubt are listed (exit 6).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Iterable, Optional, TextIO

from mavcal.ardupilot.paramfile import format_param_value, read_param_file
from mavcal.ardupilot.protocol import force_save_kinds
from mavcal.errors import ParamWriteError, RestoreFailedError, UsageError

HELP = "write a .param file to the vehicle (backup first, verify every value, undo on failure)"


def add_link_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by apply and restore."""
    parser.add_argument("--connect", required=True, metavar="DEVICE",
                        help="MAVLink device: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a serial port")
    parser.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    parser.add_argument("--timeout", type=float, default=5.0, metavar="S",
                        help="seconds to wait for the vehicle's heartbeat (default 5)")
    parser.add_argument("--param-timeout", type=float, default=1.0, metavar="S",
                        help="seconds to wait for each parameter echo (default 1)")
    parser.add_argument("--retries", type=int, default=3, help="PARAM_SET attempts per parameter (default 3)")
    parser.add_argument("--dry-run", action="store_true", help="show what would change; write nothing")
    parser.add_argument("--yes", "-y", action="store_true", help="do not ask for confirmation")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help=".param file (NAME VALUE or NAME,VALUE lines)")
    add_link_arguments(parser)
    parser.add_argument("--backup", metavar="F", default=None,
                        help="where to save the current values first (default mavcal-backup-DATE-TIME.param)")


def print_table(results: Iterable, out: TextIO, *, show_status: bool = True) -> None:
    """Print an old -> new table of :class:`~mavcal.link.writer.ParamResult`."""
    rows = []
    for r in results:
        if not r.changed:
            status = "unchanged"
        elif r.restored is True:
            status = "restored"
        elif r.restored is False:
            status = "IN DOUBT"
        elif r.ok:
            status = "ok" if r.attempts else "to write"
        else:
            status = "FAILED" if r.attempts else "not written"
        rows.append((r.name, format_param_value(r.old), format_param_value(r.expected), status))
    if not rows:
        return
    w = max(16, max(len(x[0]) for x in rows))
    wo = max(10, max(len(x[1]) for x in rows))
    wn = max(10, max(len(x[2]) for x in rows))
    out.write(f"{'PARAMETER':<{w}}  {'OLD':>{wo}}     {'NEW':<{wn}}" + ("  STATUS\n" if show_status else "\n"))
    for name, old, new, status in rows:
        out.write(f"{name:<{w}}  {old:>{wo}}  -> {new:<{wn}}" + (f"  {status}\n" if show_status else "\n"))


def confirm(prompt: str, assume_yes: bool) -> None:
    """Ask on the terminal; refuse (UsageError) without a terminal unless ``assume_yes``."""
    if assume_yes:
        return
    if not sys.stdin.isatty():
        raise UsageError("not writing without confirmation: stdin is not a terminal (use --yes)")
    answer = input(f"{prompt} [y/N] ").strip().lower()
    if answer not in ("y", "yes"):
        raise UsageError("cancelled; nothing was written")


def write_with_report(args: argparse.Namespace, changes: dict, backup: Optional[str], what: str) -> int:
    """Connect, show the diff, confirm, write with the safe writer, print the outcome."""
    from mavcal.link.connection import open_link
    from mavcal.link.params import fetch_all_params
    from mavcal.link.writer import default_backup_path, write_params

    out = sys.stdout
    link = open_link(args.connect, baud=args.baud, timeout_s=args.timeout)
    try:
        table = fetch_all_params(link, timeout_s=max(30.0, 10 * args.param_timeout),
                                 retry_s=max(0.2, args.param_timeout / 2))
        plan = write_params(link, changes, backup_path=None, params=table, dry_run=True,
                            retries=args.retries, timeout_s=args.param_timeout)
        n_changed = len(plan.changed)
        print_table(plan.results, out)
        if n_changed == 0:
            out.write("nothing to change: the vehicle already holds every value\n")
            return 0
        if args.dry_run:
            out.write(f"dry run: {n_changed} of {len(plan.results)} parameters would change; nothing written\n")
            return 0
        confirm(f"write {n_changed} parameter(s) to system {link.target_system}?", args.yes)
        bpath = backup or str(default_backup_path())
        kinds = force_save_kinds(r.name for r in plan.changed)
        try:
            report = write_params(link, changes, backup_path=bpath, params=table, force_save=kinds,
                                  retries=args.retries, timeout_s=args.param_timeout,
                                  link_timeout_s=max(3.0, 3 * args.param_timeout))
        except RestoreFailedError as exc:
            if exc.report is not None:
                print_table(exc.report.results, out)
            out.write("parameters in doubt (value on the vehicle unknown):\n")
            for name in exc.in_doubt:
                out.write(f"  {name}\n")
            out.write(f"restore them when the vehicle answers again: mavcal restore {bpath} --connect {args.connect}\n")
            raise
        except ParamWriteError as exc:
            if exc.report is not None:
                print_table(exc.report.results, out)
            out.write(f"{what} failed; every value written was restored (backup kept in {bpath})\n")
            raise
        print_table(report.changed, out)
        out.write(f"{report.message}; backup of the old values in {report.backup_path}\n")
        if report.force_saved:
            out.write(f"calibration marked saved ({', '.join(report.force_saved)}), device ids stored\n")
        if report.force_save_failed:
            out.write(f"warning: the vehicle did not acknowledge the force-save of {', '.join(report.force_save_failed)}\n")
        if report.reboot_required:
            out.write(f"reboot the vehicle for {', '.join(report.reboot_required)} to take effect\n")
        return 0
    finally:
        link.close()


def run(args: argparse.Namespace) -> int:
    changes = read_param_file(args.file)
    if not changes:
        raise UsageError(f"{args.file}: no parameters in the file")
    if args.backup is not None and Path(args.backup).exists():
        raise UsageError(f"backup file {args.backup!r} already exists; not overwriting it")
    return write_with_report(args, changes, args.backup, "write")
