"""``mavcal restore BACKUP --connect DEVICE``: put back the values saved by ``mavcal apply``.

It uses the same safe writer and the same limits as ``apply`` (``--force`` to override):
the vehicle's current values are saved to a new backup first
(so a restore can itself be undone), every value is confirmed by echo and read back.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from mavcal.autopilot.paramfile import read_param_file
from mavcal.commands.common import add_link_arguments, check_new_backup, write_with_report
from mavcal.errors import UsageError

HELP = "restore parameters from a backup written by 'mavcal apply' (same safe writer)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("backup_file", metavar="BACKUP", help="backup .param file to restore")
    add_link_arguments(parser)
    parser.add_argument("--backup", metavar="F", default=None,
                        help="backup .param of the values before the restore, never overwritten (default "
                             "BACKUP-before-restore-YYYYmmdd-HHMMSS.param beside BACKUP)")
    parser.add_argument("--force", action="store_true",
                        help="restore values outside ArduPilot's limits anyway (loudly; those sensors are not "
                             "marked calibrated)")


def run(args: argparse.Namespace) -> int:
    changes = read_param_file(args.backup_file)
    if not changes:
        raise UsageError(f"{args.backup_file}: no parameters in the backup")
    if args.backup is not None:
        check_new_backup(args.backup)
        backup = args.backup
    else:
        src = Path(args.backup_file)
        stem = f"{src.stem}-before-restore-{time.strftime('%Y%m%d-%H%M%S')}"
        p = src.with_name(stem + ".param")
        n = 1
        while p.exists():
            p = src.with_name(f"{stem}-{n}.param")
            n += 1
        backup = str(p)
    return write_with_report(args, changes, backup, "restore")
