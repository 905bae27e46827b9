"""``mavcal apply FILE --connect DEVICE``: write a .param file to the vehicle, safely.

Values outside the autopilot's limits (:func:`mavcal.autopilot.protocol.check_limits`) are refused before any
write unless ``--force``. Every value about to change is saved to a backup .param file first; each write is
confirmed by the vehicle's echo; on any failure everything written is restored from the
backup (exit 5), or the parameters in doubt are listed (exit 6).
"""
from __future__ import annotations

import argparse

from mavcal.autopilot.paramfile import read_param_file
from mavcal.commands.common import BACKUP_HELP, add_link_arguments, check_new_backup, write_with_report
from mavcal.errors import UsageError

HELP = "write a .param file to the vehicle (backup first, verify every value, undo on failure)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help=".param file (NAME VALUE or NAME,VALUE lines)")
    add_link_arguments(parser)
    parser.add_argument("--backup", metavar="F", default=None,
                        help=BACKUP_HELP)
    parser.add_argument("--force", action="store_true",
                        help="write values outside ArduPilot's limits anyway (loudly; those sensors are not "
                             "marked calibrated)")


def run(args: argparse.Namespace) -> int:
    changes = read_param_file(args.file)
    if not changes:
        raise UsageError(f"{args.file}: no parameters in the file")
    check_new_backup(args.backup)
    return write_with_report(args, changes, args.backup, "write")
