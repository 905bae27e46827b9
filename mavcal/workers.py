"""Jobs in forked worker processes: :class:`ForkPool` (one recording's fits, a fleet's logs).

One recording's accelerometer/compass pairs (and then its accelerometers) are fitted
independently of each other, each from the same prepared readings; a fleet's logs are
calibrated independently of each other. With ``workers > 1`` :class:`ForkPool` runs such
jobs in worker processes **forked** from this one, so a worker inherits the readings
(hundreds of MB on a long log) without copying or pickling them: only each job's arguments
(options, a few small arrays) go to the worker and only its result (parameters, gates,
numbers: never the readings) comes back. The fits are seeded and run the same code on the
same BLAS, so the results are those of ``workers = 1``, where the jobs run in this process
one after the other.

Resources follow the work, not a number typed: a worker is forked only when a job waits and
no worker is free, so there are never more workers than jobs at once, and never more than
:func:`worker_limit` (the CPUs this process may use, at most :data:`MAX_WORKERS`: the
process tree stays within 16 processes on any machine). Each worker holds one job's working
memory at a time (a fleet worker one log; it is replaced after ``max_tasks`` jobs, so its
allocator's fragmentation does not grow).

Workers die with their parent: on Linux the kernel kills a worker when the thread that
forked it ends (``prctl(PR_SET_PDEATHSIG, SIGKILL)``, set by the worker at its start; a
parent that died before that is caught by its pid), elsewhere a thread in the worker checks
the parent's pid twice a second; an idle worker also ends when its pipe to the parent
closes. Ctrl-C goes to the parent only (workers ignore SIGINT), which stops the workers as
it leaves. A worker that dies (the kernel's out-of-memory killer, a signal) fails the job
it was running with :class:`WorkerDiedError` (one line, exit code 70 when it reaches the
CLI); the other jobs go on.

Forking needs an operating system that forks (Linux, macOS); elsewhere, and for a single
job, the jobs run in this process. Fork only from a program that owns its process: the
CLI does (``mavcal calibrate --jobs``), a host application with its own threads (MAVProxy)
keeps ``workers = 1``. Each worker is one more process with its own BLAS: set
``OPENBLAS_NUM_THREADS=1`` (the CLI does), or the BLAS threads of the workers compete for
the cores the workers use.

Memory: a forked worker shares the parent's pages until either writes them; what it adds
is its own job's working arrays (tens of MB for a fit). ``ru_maxrss`` of the process tree,
which counts the shared pages in each process, is the parent's peak plus about that.
"""
from __future__ import annotations

import ctypes
import itertools
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection, wait
from typing import Any, Generic, TypeVar

from mavcal.errors import MavcalError

__all__ = ["ForkPool", "can_fork", "default_workers", "worker_limit", "MAX_WORKERS", "Outcome", "WorkerDiedError"]

S = TypeVar("S")
log = logging.getLogger(__name__)

#: (ok, value): the job's result, or the MavcalError it raised (any other exception propagates)
Outcome = tuple[bool, Any]

#: Most worker processes, whatever the CPUs: a recording has a few sensor pairs to fit, and a
#: fleet worker holds a whole log; with the parent the process tree stays within 16.
MAX_WORKERS = 15

_SHARED: Any = None  # what the forked workers inherit (set before the first fork)
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


class WorkerDiedError(MavcalError):
    """A worker process died while it ran a job (killed by a signal, e.g. by the kernel when
    the machine ran out of memory): the job has no result. Exit code 70 (EX_SOFTWARE)."""

    exit_code = 70


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_workers(most: int = 4) -> int:
    """The CPUs this process may run on, at most ``most`` (a recording has a few pairs to fit)."""
    return max(1, min(_cpus(), most))


def worker_limit() -> int:
    """Most worker processes worth starting here: the CPUs this process may use (the jobs are
    CPU-bound: more processes only compete for them), at most :data:`MAX_WORKERS`."""
    return max(1, min(_cpus(), MAX_WORKERS))


def can_fork() -> bool:
    """Whether worker processes can be forked here."""
    return "fork" in multiprocessing.get_all_start_methods()


def _run(fn: Callable[[Any, Any], Any], shared: Any, item: Any) -> Outcome:
    try:
        return True, fn(shared, item)
    except MavcalError as exc:
        return False, exc


# --------------------------------------------------------------------------- in the worker

def _die_with_parent(parent: int) -> None:
    """Make this worker end when its parent does (module docstring)."""
    armed = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)
    if not armed:
        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(0.5)
            os._exit(1)

        threading.Thread(target=watch, name="mavcal-parent-watch", daemon=True).start()


def _worker_main(conn: Connection, inherited: list[Connection], parent: int, max_tasks: int | None) -> None:
    global _SHARED
    shared, _SHARED = _SHARED, None  # the jobs' own; a job may start a pool of its own
    for c in inherited:  # this process's copies of the parent's ends: the pipes close when the parent dies
        c.close()
    _die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    for _ in itertools.count() if max_tasks is None else range(max_tasks):
        try:
            msg = conn.recv()
        except (EOFError, OSError):  # the parent closed the pool or died
            break
        if msg is None:
            break
        fn, item = msg
        try:
            reply: tuple = ("done", _run(fn, shared, item))
        except BaseException as exc:  # a bug: raised again in the parent
            reply = ("raise", exc, traceback.format_exc())
        try:
            conn.send(reply)
        except Exception as exc:  # an exception that does not pickle, say
            conn.send(("raise", RuntimeError(f"{type(exc).__name__}: {exc}"), traceback.format_exc()))
    conn.close()


# --------------------------------------------------------------------------- in the parent

class _Worker:
    """One forked worker: its process id, the parent's end of its pipe, the job it runs.

    Forked with :func:`os.fork` rather than :class:`multiprocessing.Process`, whose exit
    handler joins every child it started: a parent interrupted between forking a worker and
    recording it would wait there for ever. Here nothing waits for a worker at exit; an
    unrecorded one reads EOF (or gets its death signal) when the parent goes."""

    def __init__(self, inherited: list[Connection], max_tasks: int | None) -> None:
        self.job: tuple[int, Any] | None = None  # (order, item) while busy
        self.left = max_tasks  # jobs it takes before it ends (None: no limit)
        self.status: int | None = None  # exit code once reaped (-N: killed by signal N)
        self.conn, child = multiprocessing.Pipe(duplex=True)
        parent = os.getpid()
        for f in (sys.stdout, sys.stderr):  # nothing buffered here is written twice
            try:
                f.flush()
            except (AttributeError, ValueError, OSError):
                pass
        pid = os.fork()
        if pid == 0:  # the worker: it never returns from here
            code = 1
            try:
                _worker_main(child, inherited + [self.conn], parent, max_tasks)
                code = 0
            finally:
                os._exit(code)
        self.pid = pid
        child.close()

    def send(self, fn: Callable, order: int, item: Any) -> None:
        self.conn.send((fn, item))
        self.job = (order, item)
        if self.left is not None:
            self.left -= 1

    def _reap(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the process to end; True once it has (and is reaped)."""
        end = time.monotonic() + timeout_s
        while self.status is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped elsewhere
                self.status = 0
                break
            if pid:
                self.status = os.waitstatus_to_exitcode(status)
                break
            if time.monotonic() >= end:
                return False
            time.sleep(0.005)
        return True

    def _kill(self) -> None:
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def died(self) -> WorkerDiedError:
        self._reap(5.0)
        code = self.status
        if code is not None and code < 0:
            try:
                how = f"was killed by signal {-code} ({signal.Signals(-code).name})"
            except ValueError:
                how = f"was killed by signal {-code}"
        else:
            how = f"ended with status {code}"
        hint = " (out of memory?)" if code == -signal.SIGKILL else ""
        return WorkerDiedError(f"a worker process {how}{hint} during its job; run with --jobs 1 to run it here")

    def stop(self, now: bool) -> None:
        if now:
            self._kill()
        self.conn.close()  # an idle worker reads EOF and ends
        if not self._reap(10.0):
            self._kill()
            self._reap(60.0)


class ForkPool(Generic[S]):
    """Run ``fn(shared, item)`` jobs in up to ``workers`` forked processes (or here).

    Use as a context manager; :meth:`run` may be called several times (a worker is forked
    when a job waits for one, and kept until the pool closes or it has run ``max_tasks``
    jobs). ``shared`` is handed to every job: inherited by the workers, never pickled; ``fn``
    and the items must pickle (module-level functions, dataclasses, arrays). ``workers`` is
    capped at :func:`worker_limit`.
    """

    def __init__(self, shared: S, workers: int, *, max_tasks: int | None = None) -> None:
        self.shared = shared
        self.workers = max(1, min(int(workers), worker_limit())) if can_fork() else 1
        self.max_tasks = max_tasks
        self._procs: list[_Worker] = []
        self._forking = False

    def __enter__(self) -> ForkPool[S]:
        return self

    def __exit__(self, *exc: object) -> None:
        self._close()

    @property
    def pids(self) -> list[int]:
        """The worker processes alive now."""
        return [w.pid for w in self._procs]

    def _close(self) -> None:
        global _SHARED
        while self._procs:
            w = self._procs.pop()
            w.stop(now=w.job is not None)
        if self._forking:
            self._forking = False
            _SHARED = None

    def run(self, fn: Callable[[S, Any], Any], items: Sequence[Any],
            then: Callable[[Any, Outcome], Sequence[Any]], done: Callable[[int], None] | None = None) -> None:
        """Run ``fn(shared, item)`` for every item and for every item ``then`` asks for.

        As each job finishes, ``then(item, outcome)`` is called in this process and the items
        it returns are run too, as soon as a worker is free: a job that needs another one's
        result starts when that one is done, not when a whole round is. ``done(k)`` is called
        as the k-th job finishes. With one worker the jobs run here, first in, first out.
        An exception raised by ``then`` (or by a job, other than a MavcalError) stops the run:
        the jobs not yet started are dropped, the running ones killed. A job whose worker
        died has the outcome ``(False, WorkerDiedError)``.
        """
        if self.workers == 1:
            self._run_here(fn, deque(items), then, done, 0)
            return
        if len(items) == 1 and not self._procs:  # one job: here, without forking for it
            outcome = _run(fn, self.shared, items[0])
            if done is not None:
                done(1)
            follow = then(items[0], outcome)
            if follow:
                self.run(fn, follow, then, None if done is None else lambda k: done(k + 1))
            return
        order = itertools.count()
        queue = deque((next(order), item) for item in items)
        finished = 0
        try:
            while queue or any(w.job is not None for w in self._procs):
                self._dispatch(fn, queue)
                for item, outcome in self._collect():
                    finished += 1
                    if done is not None:
                        done(finished)
                    queue.extend((next(order), it) for it in then(item, outcome))
        except BaseException:
            for w in [w for w in self._procs if w.job is not None]:  # their results would go to the next run
                self._procs.remove(w)
                w.stop(now=True)
            raise

    def _dispatch(self, fn: Callable, queue: deque) -> None:
        """Hand the waiting jobs to free workers, forking one where none is free."""
        while queue:
            w = next((w for w in self._procs if w.job is None), None)
            if w is None:
                if len(self._procs) >= self.workers:
                    return
                w = self._fork()
            order, item = queue.popleft()
            try:
                w.send(fn, order, item)
            except OSError:  # it died while idle: the job goes to another one
                queue.appendleft((order, item))
                self._procs.remove(w)
                w.stop(now=True)

    def _fork(self) -> _Worker:
        global _SHARED
        if not self._forking:
            if _SHARED is not None:
                raise RuntimeError("one ForkPool with workers at a time")
            _SHARED = self.shared
            self._forking = True
        w = _Worker([p.conn for p in self._procs], self.max_tasks)
        self._procs.append(w)
        return w

    def _collect(self) -> list[tuple[Any, Outcome]]:
        """Wait for at least one busy worker to finish or die; the finished jobs' (item,
        outcome) in the order they were started (follow-ups then queue in a fixed order)."""
        busy = {w.conn: w for w in self._procs if w.job is not None}
        ready = wait(list(busy))  # an answer, or EOF: the worker's end closed as it died
        out: list[tuple[int, Any, Outcome]] = []
        for w in (busy[r] for r in ready):
            assert w.job is not None
            order, item = w.job
            try:
                reply = w.conn.recv()
            except (EOFError, OSError):  # its end of the pipe closed with no answer
                reply = None
            if reply is None:  # the process died during its job
                out.append((order, item, (False, w.died())))
                self._procs.remove(w)
                w.stop(now=True)
                continue
            w.job = None
            if reply[0] == "raise":
                log.debug("in the worker:\n%s", reply[2])
                raise reply[1]
            out.append((order, item, reply[1]))
            if w.left is not None and w.left <= 0:  # it ends now; another is forked if jobs wait
                self._procs.remove(w)
                w.stop(now=False)
        return [(item, outcome) for _, item, outcome in sorted(out, key=lambda t: t[0])]

    def _run_here(self, fn: Callable[[S, Any], Any], queue: deque, then: Callable[[Any, Outcome], Sequence[Any]],
                  done: Callable[[int], None] | None, finished: int) -> None:
        while queue:
            item = queue.popleft()
            outcome = _run(fn, self.shared, item)
            finished += 1
            if done is not None:
                done(finished)
            queue.extend(then(item, outcome))
