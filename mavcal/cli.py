"""The ``mavcal`` command line.

Each subcommand lives in its own module under :mod:`mavcal.commands` and exposes
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``. This module only
dispatches, configures logging and maps :class:`mavcal.errors.MavcalError` to one-line
messages and exit codes; it never shows a traceback for bad input.

Any other exception escaping a subcommand is a bug in mavcal (bad input must raise a
:class:`MavcalError` where it is found): it is reported as one line, ``mavcal: internal
error: ...``, with exit code :data:`EXIT_INTERNAL` (70, EX_SOFTWARE of sysexits.h); ``-vv``
logs its traceback.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

import mavcal
from mavcal.errors import MavcalError

log = logging.getLogger("mavcal.cli")

#: exit code of an unexpected exception (a bug: please report it with the ``-vv`` output)
EXIT_INTERNAL = 70

# subcommand name -> module under mavcal.commands
COMMANDS = {
    "simulate": "simulate",
    "segments": "segments",
    "calibrate": "calibrate",
    "apply": "apply",
    "restore": "restore",
    "capture": "capture",
    "flight": "flight",
}


class _Parser(argparse.ArgumentParser):
    """argparse that exits with code 2 and a one-line message on usage errors."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(2, f"mavcal: error: {message}\n")


def _load(name: str):
    try:
        return importlib.import_module(f"mavcal.commands.{COMMANDS[name]}")
    except ModuleNotFoundError as exc:  # a subcommand not built yet
        if exc.name and exc.name.startswith("mavcal.commands"):
            return None
        raise


def _global_options(parser: argparse.ArgumentParser, default) -> None:
    """``-v`` / ``-q``: on the top-level parser (``default`` 0 / False) and again on every
    subcommand (``default`` SUPPRESS, so that ``mavcal -q calibrate LOG`` and ``mavcal
    calibrate LOG -q`` mean the same and a subcommand without them keeps the top level's)."""
    parser.add_argument("-v", "--verbose", action="count", default=0 if default is None else default,
                        help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", default=False if default is None else default,
                        help="only errors on stderr: no warnings, notes or progress (the results still print)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mavcal", description="Joint accelerometer + compass calibration for ArduPilot and PX4.")
    parser.add_argument("--version", action=_Version, help="show mavcal's version and exit")
    _global_options(parser, None)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        mod = _load(name)
        if mod is None:
            continue
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        _global_options(p, argparse.SUPPRESS)
        p.set_defaults(_run=mod.run, _parser=p)
    return parser


class _Version(argparse.Action):
    """``--version``: argparse's, with the version read (from the package's metadata) only when
    asked for, not by every command's start."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"mavcal {mavcal.__version__}")
        parser.exit()


def main(argv: list[str] | None = None) -> int:
    # every matrix here is small (3N x P at most): BLAS threads only spin up, and with the fit
    # worker processes (calibrate --jobs) they would compete for the same cores; one each,
    # unless the user chose otherwise (read when numpy is first imported, i.e. after this)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # a wrong option of a subcommand: its usage, not the top level's
        getattr(args, "_parser", parser).error(f"unrecognized arguments: {' '.join(extra)}")
    if not getattr(args, "_run", None):
        parser.print_help(sys.stderr)
        return 2
    level = logging.ERROR if args.quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="mavcal: %(levelname)s: %(message)s")
    logging.captureWarnings(True)  # numpy/scipy RuntimeWarnings go through logging (-q hides them)
    try:
        from mavcal.commands.common import check_output_paths

        check_output_paths(args)  # an output that is an input: refused before any work
        return int(args._run(args) or 0)
    except MavcalError as exc:
        print(f"mavcal: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("mavcal: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as exc:  # a bug, not bad input: one line, the traceback only with -vv
        log.debug("internal error", exc_info=True)
        print(f"mavcal: internal error: {type(exc).__name__}: {exc} (a bug in mavcal; -vv shows where)",
              file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
