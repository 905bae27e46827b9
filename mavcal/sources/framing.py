"""Numpy helpers shared by the vectorised log decoders (:mod:`.fast_tlog`, :mod:`.fast_dataflash`).

Both decoders find record starts the same way: every candidate start byte of a chunk points
to its successor (the candidate right after its record, or a resynchronisation point), and
the records are the nodes on the path from the expected position. :func:`path_from` marks
that path without a Python loop per record. :class:`ColumnBuffer` grows the decoded columns
in place chunk by chunk, so the decoders hold the columns once (no join at the end).

This module knows nothing of MAVLink or DataFlash (and imports no pymavlink dialect, so a
DataFlash read does not pay for loading one).
"""
from __future__ import annotations

import mmap
from collections.abc import Iterator, Mapping

import numpy as np

__all__ = ["mark_path", "first_at_or_after", "path_from", "ColumnBuffer", "GrowArray", "OwnedMap", "owned_map_of",
           "file_chunks"]


def mark_path(succ: np.ndarray, start: int) -> np.ndarray:
    """Boolean mask of the nodes reached from ``start`` following ``succ`` (pointer doubling).

    ``succ`` maps node -> next node (strictly increasing), ``len(succ)`` is the end sentinel.
    """
    n = len(succ)
    on = np.zeros(n + 1, dtype=bool)
    if start >= n:
        return on[:n]
    jump = np.append(succ, n).astype(np.int64)
    on[start] = True
    reached = np.array([start], dtype=np.int64)
    # after step k, `reached` holds the first 2**k nodes of the path
    while True:
        nxt = jump[reached]
        new = nxt[~on[nxt]]
        if len(new) == 0:
            break
        on[new] = True
        reached = np.concatenate([reached, new])
        jump = jump[jump]
    return on[:n]


def first_at_or_after(flags: np.ndarray) -> np.ndarray:
    """``out[i]`` = smallest ``k >= i`` with ``flags[k]``, else ``len(flags)``; ``out`` has one extra entry."""
    n = len(flags)
    e = np.where(flags, np.arange(n, dtype=np.int64), n)
    out = np.empty(n + 1, dtype=np.int64)
    out[n] = n
    out[:n] = np.minimum.accumulate(e[::-1])[::-1]
    return out


def path_from(succ: np.ndarray, start: int) -> np.ndarray:
    """Same as :func:`mark_path` (nodes reached from ``start``), linear-time on long chains.

    Runs of nodes whose successor is the next node are contracted first: the path enters a
    run somewhere and follows it to its end, so only the entry points (``start`` and the
    successors of run ends) need pointer doubling; the marked runs are then filled in.
    """
    n = len(succ)
    if start >= n:
        return np.zeros(n, dtype=bool)
    idx = np.arange(n, dtype=np.int64)
    brk = succ != idx + 1
    brk[-1] = True
    run_end = first_at_or_after(brk)[:n]
    is_entry = np.zeros(n + 1, dtype=bool)
    is_entry[succ[brk]] = True
    is_entry[start] = True
    entries = np.flatnonzero(is_entry[:n])
    nxt = succ[run_end[entries]]  # next entry after following the run (or n)
    k = np.searchsorted(entries, nxt)
    k[nxt >= n] = len(entries)
    on_e = mark_path(k, int(np.searchsorted(entries, start)))
    first = entries[on_e]
    last = run_end[first]
    cover = np.zeros(n + 1, dtype=np.int64)
    cover[first] += 1
    cover[last + 1] -= 1
    return np.cumsum(cover[:n]) > 0


class OwnedMap(mmap.mmap):
    """An anonymous private memory map made by this package for decoded columns.

    Arrays over such a map are this process's own memory (no file behind them), as safe to
    change in place as a heap array: :func:`owned_map_of` tells them from views of foreign
    memory (e.g. a ``numpy.memmap`` of a file)."""


def _new_map(nbytes: int) -> OwnedMap:
    return OwnedMap(-1, max(nbytes, 1), flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)


def owned_map_of(a: np.ndarray) -> OwnedMap | None:
    """The :class:`OwnedMap` whose memory the base array ``a`` is, else None."""
    buf = a.base
    if isinstance(buf, memoryview):
        buf = buf.obj
    return buf if isinstance(buf, OwnedMap) else None


class GrowArray:
    """One column of fixed dtype and row shape, grown in place in an :class:`OwnedMap`.

    :meth:`extend` adds rows and returns a writable view of them to fill: the values are
    decoded straight into the final array (no piece per chunk, no join). Rows that are not
    written stay zero without ever becoming resident (fresh anonymous pages), so an all-zero
    column costs no memory. :meth:`array` trims the map to the rows and returns the column.
    """

    def __init__(self, dtype, shape: tuple[int, ...] = ()) -> None:
        self.dtype = np.dtype(dtype)
        self.shape = tuple(shape)
        self._row = self.dtype.itemsize * int(np.prod(self.shape, dtype=np.int64))
        self._map: OwnedMap | None = _new_map(4096 * self._row)
        self._cap = 4096
        self._full: np.ndarray | None = None  # a view of the whole capacity, kept until the map grows
        self.n = 0

    def _view(self, rows: int) -> np.ndarray:
        assert self._map is not None
        return np.frombuffer(self._map, dtype=self.dtype,
                             count=rows * (self._row // self.dtype.itemsize)).reshape((rows,) + self.shape)

    def extend(self, m: int) -> np.ndarray:
        """Add ``m`` rows (zero) and return a view of them; drop the view before the next call."""
        need = self.n + m
        if need > self._cap:
            self._cap = max(need, 2 * self._cap)
            assert self._map is not None
            self._full = None  # a map with a view of it cannot be resized
            self._resize(self._cap * self._row)
        if self._full is None:
            self._full = self._view(self._cap)
        out = self._full[self.n:need]
        self.n = need
        return out

    def _resize(self, nbytes: int) -> None:
        """The map grown or trimmed to ``nbytes`` in place (``mremap``); when a view of it is still
        referenced elsewhere (a sampling profiler's frame, e.g. a Dask worker's, keeps a finished
        call's locals a moment), the kernel may not move it: then a new map with the rows copied."""
        assert self._map is not None
        try:
            self._map.resize(nbytes)
        except BufferError:
            new = _new_map(nbytes)
            keep = min(nbytes, self.n * self._row)
            with memoryview(new) as dst, memoryview(self._map) as src:
                dst[:keep] = src[:keep]
            self._map = new

    def rows(self) -> np.ndarray:
        """The rows so far (a view: drop it before the next :meth:`extend`)."""
        return self._view(self.n)

    def array(self) -> np.ndarray:
        """The column (its map trimmed to the rows); the buffer is empty afterwards."""
        assert self._map is not None
        self._full = None
        self._resize(max(self.n, 1) * self._row)
        out = self._view(self.n)
        self._map, self._cap, self.n = None, 0, 0
        return out


class ColumnBuffer:
    """Columns that grow in place as per-chunk pieces are appended (no join at the end).

    Each column lives in its own anonymous memory map, grown geometrically with ``mremap``
    (:meth:`mmap.mmap.resize`): growing never copies, the unused capacity is never touched
    (so it is not resident) and the map is trimmed to the final length at the end. The
    returned columns are numpy arrays over those maps (freed with them). Collecting the
    pieces and concatenating them instead holds the columns twice, and growing heap arrays
    leaves the old buffers resident in the process heap: both made the peak about twice the
    columns.
    """

    def __init__(self) -> None:
        self._cols: dict[str, GrowArray] = {}
        self.n = 0

    def append(self, part: Mapping[str, np.ndarray]) -> None:
        """Append one piece: a dict column -> array, all of the same length and the same keys each time."""
        m = len(next(iter(part.values())))
        for key, v in part.items():
            col = self._cols.get(key)
            if col is None:
                col = self._cols[key] = GrowArray(v.dtype, v.shape[1:])
            col.extend(m)[:] = v
        self.n += m

    def columns(self) -> dict[str, np.ndarray]:
        """The columns, trimmed to the appended length; the buffer is empty afterwards."""
        out = {key: col.array() for key, col in self._cols.items()}
        self._cols, self.n = {}, 0
        return out


def file_chunks(fh, size: int, chunk: int, before: int, after: int) -> Iterator[tuple[int, int, int, np.ndarray]]:
    """Read a file in chunks ``[start, end)`` with ``before`` bytes of context before and ``after`` after.

    Yields ``(base, start, end, b)`` where ``b`` holds the file bytes ``[base, min(end + after, size))``
    and ``base = max(start - before, 0)``. Only one chunk is in memory at a time.
    """
    start = 0
    while start < size:
        base = max(start - before, 0)
        end = min(start + chunk, size)
        fh.seek(base)
        yield base, start, end, np.frombuffer(fh.read(min(end + after, size) - base), dtype=np.uint8)
        start = end
