"""Run a fleet's logs: in the fork pool here, or on a Dask cluster; rows to the table as they come.

:func:`run_fleet` hands each log to a worker (:func:`calibrate_entry`), which reads the log
itself (a local path or a URL, :func:`mavcal.fleet.inputs.fetch`), hashes its content, skips it
when the table already has its key (content hash + mavcal version), else calibrates it exactly
as ``mavcal calibrate LOG`` of it alone (:func:`mavcal.batch.calibrate_one`). Each result comes
back to this process, which appends its row to the table at once and reports progress.

On one machine the workers are :class:`mavcal.workers.ForkPool`'s (``jobs``); with
``scheduler_address`` (``tcp://HOST:8786``, or ``DASK_SCHEDULER_ADDRESS`` in the environment)
the jobs run on that Dask cluster's workers (``dask.distributed``; each worker must have mavcal
installed and reach the logs), with Dask's retries for a worker that dies mid-job.
"""
from __future__ import annotations

import functools
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

from mavcal.batch import BatchRow, calibrate_one, fleet_exit_code
from mavcal.errors import MavcalError, UsageError
from mavcal.fleet.drift import DriftLog
from mavcal.fleet.inputs import fetch
from mavcal.fleet.table import CALIBRATE, ResultsTable, flat_row, row_key, unread_key
from mavcal.workers import ForkPool, Outcome, WorkerDiedError

log = logging.getLogger(__name__)

__all__ = ["FleetJob", "FleetResult", "FleetRun", "calibrate_entry", "run_fleet", "DASK_RETRIES"]

#: How many times Dask runs a log's job again after its worker died.
DASK_RETRIES = 2
#: Fewest jobs handed to a Dask cluster at once (else four per worker): more wait here, not on the scheduler.
MIN_WINDOW = 64
WINDOW_PER_WORKER = 4
#: Seconds to wait for the Dask scheduler to answer.
CONNECT_TIMEOUT_S = 20.0
#: Logs a fork-pool worker handles before it is replaced (as :func:`mavcal.batch.calibrate_many`).
MAX_TASKS_PER_CHILD = 8


@dataclass(frozen=True)
class FleetJob:
    """What every log of a fleet run is calibrated with (sent to, or inherited by, the workers)."""

    options: object  # mavcal.pipeline.Options (calibrate), mavcal.fleet.flight.FlightOptions (flight)
    csv_rate_hz: float | None = None
    version: str = ""
    done: frozenset[str] = frozenset()  # keys of the rows the table has already
    kind: str = "calibrate"  # or "flight": what is done with each log


@dataclass(frozen=True)
class FleetResult:
    """One log's outcome: its row (None when skipped: the table has it), content hash, size."""

    source: str
    sha256: str | None
    size_bytes: int | None
    row: Any  # BatchRow (calibrate), mavcal.fleet.flight.FlightRow (flight); None when skipped


@dataclass
class FleetRun:
    """What :func:`run_fleet` returns. The parent holds no row beyond what it needs: counts, the
    worst exit code, and :class:`mavcal.fleet.drift.DriftLog` (every row of the table, earlier
    runs' too, reduced to the accepted logs' offsets). With ``keep_rows`` also this run's rows
    (input order) and the names of the logs skipped (their rows are in the table already) and
    of those not calibrated because the table had their content under another name (their row
    is that one's, under their name)."""

    rows: list[BatchRow] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    copied: list[str] = field(default_factory=list)
    drift: Any = field(default_factory=DriftLog)  # DriftLog; mavcal.fleet.flight.InterferenceLog for flights
    n_calibrated: int = 0
    n_skipped: int = 0
    n_copied: int = 0
    n_failed: int = 0
    exit_code: int = 0  # the worst of this run's rows and of the skipped and copied logs' rows in the table


def _failed(source: str, exc: MavcalError, options) -> BatchRow:
    return BatchRow(source=source, ok=False, error=str(exc), exit_code=int(exc.exit_code),
                    accel_instance=options.accel_instance, compass_instance=options.mag_instance)


def calibrate_entry(job: FleetJob, source: str) -> FleetResult:
    """Read, hash and (unless the table has it) calibrate one log, or with ``job.kind ==
    "flight"`` analyse its flight: a worker's job."""
    try:
        with fetch(source) as (path, sha, size):
            if row_key(sha, job.version) in job.done:
                return FleetResult(source, sha, size, None)
            if job.kind == "flight":
                from mavcal.fleet.flight import analyse_one

                return FleetResult(source, sha, size, analyse_one(path, source, job.options))  # type: ignore[arg-type]
            row = calibrate_one(path, job.options, job.csv_rate_hz)
    except MavcalError as exc:  # unreadable (exit 3), or a URL without the fleet extra: keyed by its name
        if row_key(unread_key(source), job.version) in job.done:
            return FleetResult(source, None, None, None)
        return FleetResult(source, None, None, _kind(job.kind)[2](source, exc, job.options))
    return FleetResult(source, sha, size, _renamed(row, path, source) if path != source else row)


def _kind(kind: str) -> tuple:
    """(the table's layout, its flat row, a failed log's row, the drift-over-time log) of a kind of job."""
    if kind == "flight":
        from mavcal.fleet.flight import FLIGHT, InterferenceLog, failed_row, flat_flight_row

        return FLIGHT, flat_flight_row, failed_row, InterferenceLog
    if kind != "calibrate":
        raise ValueError(f"kind must be 'calibrate' or 'flight', got {kind!r}")
    return CALIBRATE, flat_row, _failed, DriftLog


def _copy_row(row: dict, source: str) -> dict:
    """A table row of a log with the content of ``row``'s log: the same, under its own name."""
    import time as _time

    from mavcal.fleet.table import utc

    old = row["source"]
    out = {k: (v.replace(old, source) if isinstance(v, str) else v) for k, v in row.items()}
    out["finished_utc"] = utc(_time.time())
    return out


def _renamed(row: BatchRow, path: str, source: str) -> BatchRow:
    """The row of a URL's local copy ``path`` naming the URL, in its messages too."""
    def r(s: str) -> str:
        return s.replace(path, source)

    return replace(row, source=source, error=None if row.error is None else r(row.error),
                   failed_gates=tuple(map(r, row.failed_gates)), warnings=tuple(map(r, row.warnings)),
                   not_determined_why=r(row.not_determined_why),
                   sensors=tuple(replace(v, reasons=tuple(map(r, v.reasons))) for v in row.sensors))


def _indexed(job: FleetJob, item: tuple[int, str]) -> FleetResult:
    return calibrate_entry(job, item[1])


#: glibc's mallopt parameters, and the largest mmap threshold it takes on a 64-bit machine
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 << 20
_GLIBC_MMAP_THRESHOLD = 128 << 10


@functools.lru_cache(maxsize=1)
def _libc():
    """glibc, found once per worker process (``find_library`` runs ``ldconfig``), or None."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018  (glibc's own: mallopt means what is said below)
        return libc
    except (OSError, AttributeError):
        return None


@contextmanager
def roomy_heap() -> Iterator[bool]:
    """The C heap as a forked worker has it, for one log in a Dask worker; yields whether it changed.

    Dask's nanny starts each worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (its
    ``distributed.nanny.pre-spawn-environ``). glibc then keeps its mmap threshold fixed at
    128 KiB (a threshold set by the environment turns the dynamic one off), so every numpy
    array above 128 KiB is a fresh ``mmap``, page-faulted in and ``munmap``-ed when freed:
    measured, 30,000 page faults and 0.05 s more CPU per log (+20 %; the same in a plain
    process started with that variable). Here, while the log is calibrated, such arrays come
    from the heap again (mmap threshold 32 MiB, trim threshold 64 MiB, as glibc's dynamic
    thresholds would reach); after it the worker's settings are put back and the heap trimmed
    (``malloc_trim``), so the worker returns the memory as Dask wants. Only when the variable
    is set (and ``MALLOC_MMAP_THRESHOLD_`` is not), on glibc; elsewhere nothing changes."""
    trim = os.environ.get("MALLOC_TRIM_THRESHOLD_")
    libc = _libc() if trim and "MALLOC_MMAP_THRESHOLD_" not in os.environ else None
    try:
        was_trim = int(trim) if trim else 0
    except ValueError:
        libc = None
    if libc is None:
        yield False
        return
    libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)
    libc.mallopt(_M_TRIM_THRESHOLD, 2 * _MMAP_THRESHOLD_MAX)
    try:
        yield True
    finally:
        libc.mallopt(_M_MMAP_THRESHOLD, _GLIBC_MMAP_THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, was_trim)
        libc.malloc_trim(0)


def _dask_entry(source: str, job: FleetJob) -> FleetResult:
    with roomy_heap():
        return calibrate_entry(job, source)


def scheduler_from_env(given: str | None) -> str | None:
    """The Dask scheduler to use: ``given``, else ``DASK_SCHEDULER_ADDRESS``, else None (here)."""
    return given or os.environ.get("DASK_SCHEDULER_ADDRESS") or None


def _on_dask(address: str, job: FleetJob, sources: Sequence[str], take: Callable[[int, FleetResult], None]) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise UsageError("--scheduler-address needs the fleet extra (dask[distributed]), which is not installed: "
                         "pip install 'mavcal[fleet]'") from None
    try:
        client = Client(address, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise UsageError(f"--scheduler-address {address}: cannot reach the Dask scheduler ({exc})") from None
    try:
        with client.as_current():
            shared = client.scatter(job, broadcast=True)
            # a window of jobs at a time (not a million futures at once): the scheduler holds a few per worker
            window = max(MIN_WINDOW, WINDOW_PER_WORKER * len(client.scheduler_info().get("workers", {})))
            todo = iter(enumerate(sources))
            index: dict = {}
            running = as_completed(with_results=True, raise_errors=False)

            def submit_next() -> None:
                for i, source in todo:
                    fut = client.submit(_dask_entry, source, job=shared, retries=DASK_RETRIES, pure=False)
                    index[fut.key] = i
                    running.add(fut)
                    return

            for _ in range(window):
                submit_next()
            for fut, res in running:
                i = index.pop(fut.key)
                if isinstance(res, BaseException):  # its workers died DASK_RETRIES + 1 times (KilledWorker), a bug
                    exc = WorkerDiedError(f"the Dask job failed: {type(res).__name__}: {res}")
                    res = FleetResult(sources[i], None, None, _kind(job.kind)[2](sources[i], exc, job.options))
                take(i, res)
                fut.release()
                submit_next()
    finally:
        client.close()


def run_fleet(sources: Sequence[str], options, *, jobs: int = 1, table: str | None = None,
              scheduler_address: str | None = None, csv_rate_hz: float | None = None,
              progress: Callable[[FleetResult], None] | None = None, keep_rows: bool = True,
              kind: str = "calibrate") -> FleetRun:
    """Calibrate every log of ``sources`` (expanded already: :func:`mavcal.fleet.inputs.expand_sources`).

    Parameters
    ----------
    sources : sequence of str
        Local paths and URLs, one per log.
    options : mavcal.pipeline.Options
    jobs : int
        Fork-pool workers on this machine (ignored with a scheduler).
    table : str, optional
        The results table (``.csv`` or ``.parquet``): rows appended as the logs finish; the
        logs it already has (same content, same mavcal version) are skipped.
    scheduler_address : str, optional
        A Dask scheduler (``tcp://HOST:PORT``) to run the jobs on.
    progress : callable, optional
        Called in this process with each log's :class:`FleetResult` as it finishes.
    kind : str
        ``"calibrate"`` (``options``: mavcal.pipeline.Options) or ``"flight"``, the in-flight
        compass check of each log (``options``: :class:`mavcal.fleet.flight.FlightOptions`).
    keep_rows : bool
        Keep this run's rows (:attr:`FleetRun.rows`: for a table printed at the end, ``--json``);
        without, the memory of this process does not grow with the rows (module docstring).
    """
    from mavcal import __version__

    if int(jobs) < 1:
        raise UsageError(f"jobs must be at least 1, got {jobs}")
    sources = [str(s) for s in sources]
    layout, flat_of, _, drift_log = _kind(kind)
    writer = ResultsTable(table, layout=layout) if table else None
    got = _Collector(FleetRun(drift=drift_log()), writer, flat_of, str(__version__), keep_rows, progress)
    if writer is not None:
        writer.open(each=got.known)
    got.job = job = FleetJob(options, csv_rate_hz, got.version, frozenset(got.done), kind)
    finished = False
    try:
        if scheduler_address:
            _on_dask(scheduler_address, job, sources, got.take)
        else:
            _on_fork_pool(job, int(jobs), sources, got.take)
        finished = True
    finally:
        if writer is not None:
            writer.close(finished=finished)
    got.out.rows = [got.kept[i] for i in sorted(got.kept)]
    got.out.exit_code = fleet_exit_code(got.worst)
    return got.out


class _Collector:
    """This process's side of a fleet run: each log's result to the table as it comes, reduced to
    counts, the worst exit code and the drift log (the rows themselves kept only with ``keep_rows``)."""

    def __init__(self, out: FleetRun, writer: ResultsTable | None, flat_of, version: str, keep_rows: bool,
                 progress: Callable[[FleetResult], None] | None) -> None:
        self.out, self.writer, self.flat_of, self.version = out, writer, flat_of, version
        self.keep_rows, self.progress = keep_rows, progress
        self.done: set[str] = set()
        self.had: dict[str, tuple[tuple[str, ...], bool, int]] = {}  # key -> the table's logs of it, ok, exit code
        self.kept: dict[int, Any] = {}
        self.worst: list[BatchRow] = []
        self.job: FleetJob | None = None

    def known(self, r: dict) -> None:
        """A row the table had when the run started."""
        self.out.drift.add(r)
        if r.get("content_sha256"):
            key = row_key(r["content_sha256"], r["mavcal_version"])
            self.done.add(key)
            names = self.had[key][0] if key in self.had else ()
            self.had[key] = ((*names, str(r["source"])), bool(r["ok"]), int(r["exit_code"] or 0))

    def worse(self, source: str, ok: bool, exit_code: int) -> None:
        r = BatchRow(source=source, ok=ok, exit_code=exit_code)
        if not self.worst or fleet_exit_code([self.worst[0], r]) == r.exit_code != self.worst[0].exit_code:
            self.worst[:] = [r]

    def take(self, i: int, res: FleetResult) -> None:
        out, writer, had = self.out, self.writer, self.had
        key = row_key(res.sha256 or unread_key(res.source), self.version)
        original = _table_row(writer, key) if (writer is not None and res.row is None and key in had
                                                and res.source not in had[key][0]) else None
        if original is not None and writer is not None:  # the content, under another name: its row, renamed
            flat = _copy_row(original, res.source)
            writer.append(flat)
            out.drift.add(flat)
            had[key] = ((*had[key][0], res.source), had[key][1], had[key][2])
            out.n_copied += 1
            if self.keep_rows:
                out.copied.append(res.source)
            self.worse(res.source, had[key][1], had[key][2])
        elif res.row is None:
            out.n_skipped += 1
            if self.keep_rows:
                out.skipped.append(res.source)
            if key in had:
                self.worse(res.source, had[key][1], had[key][2])
        else:
            log.info("%s: %s", res.source, "ok" if res.row.ok else res.row.error)
            flat = self.flat_of(res.row, res.sha256 or unread_key(res.source), res.size_bytes or 0, self.version)
            if writer is not None:
                writer.append(flat)
            out.drift.add(flat)
            out.n_calibrated += 1
            out.n_failed += 0 if res.row.ok else 1
            self.worse(res.source, res.row.ok, res.row.exit_code)
            if self.keep_rows:
                self.kept[i] = res.row
        if self.progress is not None:
            self.progress(res)


def _on_fork_pool(job: FleetJob, jobs: int, sources: Sequence[str], take: Callable[[int, FleetResult], None]) -> None:
    def then(item: tuple[int, str], outcome: Outcome) -> list:
        i, source = item
        ok, res = outcome
        if not ok:  # its worker process died (out of memory?): this log alone fails
            res = FleetResult(source, None, None, _kind(job.kind)[2](source, res, job.options))
        take(i, res)
        return []

    with ForkPool(job, min(jobs, max(1, len(sources))), max_tasks=MAX_TASKS_PER_CHILD) as pool:
        pool.run(_indexed, list(enumerate(sources)), then)


def _table_row(writer: ResultsTable, key: str) -> dict | None:
    """The table's row of ``key`` (read again from the table: a copy is rare, the rows are not kept)."""
    found = None

    def look(r: dict) -> None:
        nonlocal found
        if found is None and r.get("content_sha256") and row_key(r["content_sha256"], r["mavcal_version"]) == key:
            found = r

    writer.each_row(look)
    return found
