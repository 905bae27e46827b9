"""The fits of one recording in several processes: :class:`ForkPool`.

One recording's accelerometer/compass pairs (and then its accelerometers) are fitted
independently of each other, each from the same prepared readings. With ``workers > 1``
:class:`ForkPool` runs them in worker processes **forked** from this one, so a worker
inherits the readings (hundreds of MB on a long log) without copying or pickling them:
only each job's arguments (options, a few small arrays) go to the worker and only its
result (parameters, gates, numbers: never the readings) comes back. The fits are seeded
and deterministic, so the results are the same, to the bit, as with ``workers = 1``,
where the jobs run in this process one after the other.

Forking needs an operating system that forks (Linux, macOS); elsewhere, and for a single
job, the jobs run in this process. Fork only from a program that owns its process: the
CLI does (``mavcal calibrate --jobs``), a host application with its own threads (MAVProxy)
keeps ``workers = 1``. Each worker is one more process with its own BLAS: set
``OPENBLAS_NUM_THREADS=1`` (the CLI does), or the BLAS threads of the workers compete for
the cores the workers use.

Memory: a forked worker shares the parent's pages until either writes them; what it adds
is its own fit's working arrays (tens of MB). ``ru_maxrss`` of the process tree, which
counts the shared pages in each process, is the parent's peak plus about that.
"""
from __future__ import annotations

import gc
import itertools
import logging
import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Generic, TypeVar

from mavcal.errors import MavcalError
from mavcal.memory import return_large_blocks

__all__ = ["ForkPool", "can_fork", "default_workers", "Outcome"]

S = TypeVar("S")
log = logging.getLogger(__name__)

#: (ok, value): the job's result, or the MavcalError it raised (any other exception propagates)
Outcome = tuple[bool, Any]

_SHARED: Any = None  # what the forked workers inherit (set before the first fork)


def default_workers(most: int = 4) -> int:
    """The CPUs this process may run on, at most ``most`` (a recording has a few pairs to fit)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(n, most))


def can_fork() -> bool:
    """Whether worker processes can be forked here."""
    return "fork" in multiprocessing.get_all_start_methods()


def _run(fn: Callable[[Any, Any], Any], shared: Any, item: Any) -> Outcome:
    try:
        return True, fn(shared, item)
    except MavcalError as exc:
        return False, exc


def _in_worker(fn: Callable[[Any, Any], Any], item: Any) -> Outcome:
    return _run(fn, _SHARED, item)


def _worker_start() -> None:
    """A fit worker's large arrays are given back when freed, not kept by its allocator: its
    own memory is what its fit needs, not its high-water mark (see :mod:`mavcal.memory`)."""
    return_large_blocks()


class ForkPool(Generic[S]):
    """Run ``fn(shared, item)`` jobs in ``workers`` forked processes (or here).

    Use as a context manager; :meth:`run` may be called several times (the workers are
    forked once, at the first job that goes to them). ``shared`` is handed to every job:
    inherited by the workers, never pickled; ``fn`` and the items must pickle (module-level
    functions, dataclasses, arrays).
    """

    def __init__(self, shared: S, workers: int) -> None:
        self.shared = shared
        self.workers = max(1, int(workers)) if can_fork() else 1
        self._pool: ProcessPoolExecutor | None = None

    def __enter__(self) -> ForkPool[S]:
        return self

    def __exit__(self, *exc: object) -> None:
        self._close()

    def _close(self) -> None:
        global _SHARED
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
            _SHARED = None
            gc.unfreeze()

    def run(self, fn: Callable[[S, Any], Any], items: Sequence[Any],
            then: Callable[[Any, Outcome], Sequence[Any]], done: Callable[[int], None] | None = None) -> None:
        """Run ``fn(shared, item)`` for every item and for every item ``then`` asks for.

        As each job finishes, ``then(item, outcome)`` is called in this process and the items
        it returns are run too, as soon as a worker is free: a job that needs another one's
        result starts when that one is done, not when a whole round is. ``done(k)`` is called
        as the k-th job finishes. With one worker the jobs run here, first in, first out.
        An exception raised by ``then`` stops the run (the jobs not yet started are dropped).
        """
        if self.workers == 1:
            self._run_here(fn, deque(items), then, done, 0)
            return
        if len(items) == 1 and self._pool is None:  # one job: here, without forking for it
            outcome = _run(fn, self.shared, items[0])
            if done is not None:
                done(1)
            follow = then(items[0], outcome)
            if follow:
                self.run(fn, follow, then, None if done is None else lambda k: done(k + 1))
            return
        pool = self._executor()
        order = itertools.count()
        running: dict[Future, tuple[int, Any]] = {}

        def submit(batch: Sequence[Any]) -> None:
            for item in batch:
                running[pool.submit(_in_worker, fn, item)] = (next(order), item)

        submit(items)
        finished = 0
        try:
            while running:
                ready, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in sorted(ready, key=lambda f: running[f][0]):  # as submitted: follow-ups in a fixed order
                    outcome = f.result()
                    _, item = running.pop(f)
                    finished += 1
                    if done is not None:
                        done(finished)
                    submit(then(item, outcome))
        except BrokenProcessPool:  # a worker was killed (out of memory?): nothing is lost but time
            log.warning("a fit worker process died (out of memory?); the fits run in this process instead")
            left = deque(item for _, item in sorted(running.values(), key=lambda v: v[0]))
            self._close()
            self.workers = 1
            self._run_here(fn, left, then, done, finished)

    def _run_here(self, fn: Callable[[S, Any], Any], queue: deque, then: Callable[[Any, Outcome], Sequence[Any]],
                  done: Callable[[int], None] | None, finished: int) -> None:
        while queue:
            item = queue.popleft()
            outcome = _run(fn, self.shared, item)
            finished += 1
            if done is not None:
                done(finished)
            queue.extend(then(item, outcome))

    def _executor(self) -> ProcessPoolExecutor:
        global _SHARED
        if self._pool is None:
            if _SHARED is not None:
                raise RuntimeError("one ForkPool with workers at a time")
            _SHARED = self.shared
            gc.freeze()  # the objects so far stay out of the workers' collections: their pages are not copied
            self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("fork"),
                                             initializer=_worker_start)
        return self._pool
