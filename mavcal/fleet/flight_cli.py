"""``mavcal flight`` over many logs: its many-log options and run (:mod:`mavcal.fleet.flight`).

The command's hook: LOG takes several (``nargs="+"``), :func:`add_fleet_arguments` adds the
options, and ``run`` calls :func:`run_many` when :func:`is_many` (else the single log as before).
"""
from __future__ import annotations

__all__ = ["add_fleet_arguments", "is_many", "run_many"]


def add_fleet_arguments(parser) -> None:
    """The many-log options of ``mavcal flight`` (its LOG argument then takes several: ``nargs="+"``)."""
    g = parser.add_argument_group("many logs (docs/fleet.md)")
    g.add_argument("--table", metavar="F", help="results table, one row per log written as it finishes (.csv, or "
                   ".parquet with mavcal[fleet]); run again with the same table, the logs it has are skipped")
    g.add_argument("--scheduler-address", metavar="tcp://HOST:PORT",
                   help="run the per-log jobs on this Dask scheduler (default: DASK_SCHEDULER_ADDRESS, else the "
                        "--jobs processes here); needs mavcal[fleet]")
    g.add_argument("--jobs", type=int, default=None, metavar="N", help="logs analysed at once here (processes)")
    g.add_argument("--drift-html", metavar="F", help="write a self-contained HTML page of each vehicle's compass "
                   "interference over its flights, a plot per vehicle whose interference grew")


def is_many(args) -> bool:
    """Whether ``mavcal flight`` was given a fleet: several logs, a directory, glob, @LIST or URL,
    or one of the many-log options."""
    import os

    from mavcal.fleet.inputs import is_url

    logs = list(args.log) if isinstance(args.log, (list, tuple)) else [args.log]
    fleety = any(s.startswith("@") or is_url(s) or os.path.isdir(s) or (any(c in s for c in "*?[")
                                                                       and not os.path.exists(s)) for s in logs)
    opts = any(getattr(args, o, None) for o in ("table", "scheduler_address", "drift_html", "jobs"))
    return len(logs) > 1 or fleety or opts


def run_many(args) -> int:
    """``mavcal flight SOURCE... [--table F] [--scheduler-address A] [--jobs N] [--drift-html F] [--json F]``:
    every log's in-flight check, a table of them, interference over time; the worst log's exit code."""
    import sys
    from dataclasses import asdict

    from mavcal.errors import UsageError
    from mavcal.fleet.flight import (  # here, not at the top: `mavcal --help` builds this command's parser
        PRINTED_MAX,
        FlightOptions,
        format_flight_table,
        interference_html,
        interference_text,
    )
    from mavcal.fleet.inputs import expand_sources
    from mavcal.fleet.progress import progress_line
    from mavcal.fleet.run import run_fleet, scheduler_from_env
    from mavcal.outputs import check_outputs, write_atomic
    from mavcal.workers import worker_limit

    for opt in ("param_out", "write", "dry_run", "html"):
        if getattr(args, opt, None):
            raise UsageError(f"--{opt.replace('_', '-')} is about one vehicle's flight: give a single LOG, without "
                             "--table, --scheduler-address, --jobs or --drift-html")
    logs = list(args.log) if isinstance(args.log, (list, tuple)) else [args.log]
    table = getattr(args, "table", None)
    if table and not str(table).lower().endswith((".csv", ".parquet")):
        raise UsageError(f"--table {table}: give a .csv or a .parquet file")
    sched = scheduler_from_env(getattr(args, "scheduler_address", None))
    if sched and not sched.startswith(("tcp://", "tls://", "inproc://", "ws")):
        raise UsageError(f"--scheduler-address {sched}: give tcp://HOST:PORT")
    jobs = getattr(args, "jobs", None) or 1
    if jobs < 1:
        raise UsageError("--jobs must be at least 1")
    jobs = min(jobs, worker_limit())
    sources = expand_sources(logs)
    if table:  # the table (and a Parquet table's journal) is no log of the fleet, even under its directory
        import os

        mine = {os.path.abspath(t) for t in (table, f"{table}.journal.csv")}
        sources = [s for s in sources if os.path.abspath(s) not in mine]
    json_dest = getattr(args, "json", None)
    html = getattr(args, "drift_html", None)
    check_outputs([("--table", table), ("--json", json_dest), ("--drift-html", html)], sources)
    quiet = bool(getattr(args, "quiet", False))
    keep = bool(json_dest) or not table or len(sources) <= PRINTED_MAX
    shown = progress_line(sys.stderr, len(sources), quiet=quiet)
    try:
        done = run_fleet(sources, FlightOptions(getattr(args, "yaw", "ekf"), getattr(args, "driver", "auto")),
                         jobs=jobs, table=table, scheduler_address=sched, progress=shown, keep_rows=keep,
                         kind="flight")
    finally:
        if shown is not None:
            shown.close()
    out = sys.stderr if json_dest == "-" else sys.stdout
    if keep:
        print(format_flight_table(done.rows) if done.rows else "no log analysed in this run", file=out)
    else:
        print(f"{done.n_calibrated} logs analysed in this run ({done.n_failed} failed): their rows are in {table} "
              f"(the table is printed here for up to {PRINTED_MAX} logs)", file=out)
    if done.n_skipped:
        print(f"{done.n_skipped} log(s) already in {table} (same content, same mavcal version): skipped, their rows "
              "are there", file=out)
    if done.n_copied:
        print(f"{done.n_copied} log(s) with the content of a log already in {table} under another name: not analysed "
              "again, its row written under their name", file=out)
    text = interference_text(done.drift)
    if text:
        print(text, file=out)
    if html:
        write_atomic(html, interference_html(done.drift))
        print(f"interference over time written to {html}", file=out)
    if json_dest:
        from mavcal.commands.common import json_output

        json_output(json_dest, [{**asdict(r), "cells": dict(r.cells)} for r in done.rows])
    print(f"exit code {done.exit_code} (the worst log's)", file=out)
    return done.exit_code
