"""Where a benchmark writes its results: the convention every script in benchmarks/ follows.

By default a run writes into ``benchmarks/out/`` (untracked: the directory carries its own
``.gitignore``), so running a benchmark never rewrites the tracked numbers the documentation quotes.
``--save`` writes into ``benchmarks/results/`` (tracked; commit the change on purpose);
``--out DIR`` writes anywhere else. See benchmarks/README.md.

A script applies it in its ``__main__`` block, before calling ``main``; ``main`` and the rest of
the script keep writing into the module-level ``OUT``::

    if __name__ == "__main__":
        from bench_output import output_dir

        OUT, _argv = output_dir(sys.argv[1:])
        sys.exit(main(_argv))
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"  # tracked: written only with --save
SCRATCH = HERE / "out"  # untracked default

__all__ = ["RESULTS", "SCRATCH", "output_dir", "add_output_arguments"]


def add_output_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--save`` and ``--out DIR`` to a benchmark's own parser."""
    g = parser.add_argument_group("where the results go (benchmarks/README.md)")
    g.add_argument("--save", action="store_true",
                   help=f"write into {RESULTS.relative_to(HERE.parent)}/ (tracked; default: "
                        f"{SCRATCH.relative_to(HERE.parent)}/, untracked)")
    g.add_argument("--out", type=Path, metavar="DIR", help="write into DIR instead")


def resolve(save: bool, out: Path | None) -> Path:
    """The directory chosen by ``--save`` / ``--out``, created (the scratch one with its .gitignore)."""
    if save and out is not None:
        raise SystemExit("--save and --out exclude each other")
    target = out if out is not None else (RESULTS if save else SCRATCH)
    target.mkdir(parents=True, exist_ok=True)
    if target.resolve() == SCRATCH:
        ignore = target / ".gitignore"
        if not ignore.exists():
            ignore.write_text("# benchmark results of unsaved runs (benchmarks/README.md)\n*\n")
    return target


def output_dir(argv: Sequence[str] | None = None, *, strict: bool = False) -> tuple[Path, list[str]]:
    """Take ``--save`` / ``--out DIR`` out of ``argv``; returns (directory, the other arguments).

    With ``strict`` the other arguments are refused (for a script whose ``main`` takes none)
    and ``--help`` is answered here; otherwise ``--help`` is left to the script's own parser.
    """
    parser = argparse.ArgumentParser(add_help=strict, description="Benchmark output options.")
    add_output_arguments(parser)
    args_in = list(sys.argv[1:] if argv is None else argv)
    if strict:
        args, rest = parser.parse_args(args_in), []
    else:
        args, rest = parser.parse_known_args(args_in)
    if {"-h", "--help"} & set(rest):  # the script's parser answers and exits; create nothing
        return (RESULTS if args.save else args.out or SCRATCH), rest
    target = resolve(args.save, args.out)
    print(f"results go to {target}", file=sys.stderr)
    return target, rest
