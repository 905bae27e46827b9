"""Vectorised ArduPilot DataFlash (.bin) decoder.

A DataFlash log is a sequence of records ``[0xA3 0x95 type][body]`` whose length comes from
the FMT record (type 128) that defines ``type``. This module

1. finds and validates every FMT record (first pass, chunked),
2. finds the record starts with numpy, following pymavlink ``DFReader_binary``'s rule: a
   record of known type at ``p`` is followed by the first ``A3 95 <known type>`` at or after
   ``p + length`` (the bytes in between are skipped and counted), and
3. decodes the records of the requested message names into numpy columns through
   structured dtypes built from their FMT format string, applying the same multipliers as
   DFReader (``c/C/e/E`` / 100, ``L`` / 1e7) so values are identical to DFReader's.

Like DFReader, all FMT records of the file define the known types (DFReader indexes the
whole file before reading it). Memory is bounded by a few chunks plus the decoded columns (grown in place,
never held twice).
"""
from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from mavcal.sources.framing import ColumnBuffer, mark_path
from mavcal.sources.progress import ProgressFn

log = logging.getLogger(__name__)

HEAD1, HEAD2 = 0xA3, 0x95
FMT_TYPE = 0x80
FMT_LEN = 89
DEFAULT_CHUNK = 2 * 1024 * 1024  # working memory: a few times this (32 MiB made it ~110 MB; 2 MiB is faster than 4)

# DataFlash format character -> (numpy dtype, multiplier)  (pymavlink DFReader.FORMAT_TO_STRUCT)
FORMAT_TO_DTYPE = {
    "a": ("<i2", None, 32), "b": ("i1", None, 1), "B": ("u1", None, 1), "g": ("<f2", None, 1),
    "h": ("<i2", None, 1), "H": ("<u2", None, 1), "i": ("<i4", None, 1), "I": ("<u4", None, 1),
    "f": ("<f4", None, 1), "n": ("S4", None, 1), "N": ("S16", None, 1), "Z": ("S64", None, 1),
    "c": ("<i2", 0.01, 1), "C": ("<u2", 0.01, 1), "e": ("<i4", 0.01, 1), "E": ("<u4", 0.01, 1),
    "L": ("<i4", 1.0e-7, 1), "d": ("<f8", None, 1), "M": ("i1", None, 1), "q": ("<i8", None, 1),
    "Q": ("<u8", None, 1),
}


@dataclass(frozen=True)
class DFFormat:
    """One FMT record: message type number, name, record length, format and column names."""

    type: int
    name: str
    length: int
    format: str
    columns: tuple[str, ...]

    def dtype(self) -> np.dtype:
        fields = []
        seen = set()
        for col, ch in zip(self.columns, self.format):
            dt, _, n = FORMAT_TO_DTYPE[ch]
            name = col
            while name in seen:  # duplicate column names (seen in broken logs)
                name += "_"
            seen.add(name)
            fields.append((name, dt, (n,)) if n > 1 else (name, dt))
        return np.dtype(fields)

    def multipliers(self) -> dict[str, float]:
        out = {}
        for c, ch in zip(self.columns, self.format):
            m = FORMAT_TO_DTYPE[ch][1]
            if m is not None:
                out[c] = float(m)
        return out


def _format_size(fmt: str) -> int | None:
    size = 0
    for ch in fmt:
        if ch not in FORMAT_TO_DTYPE:
            return None
        dt, _, n = FORMAT_TO_DTYPE[ch]
        size += np.dtype(dt).itemsize * n
    return size


_FMT_DTYPE = np.dtype([("Type", "u1"), ("Length", "u1"), ("Name", "S4"), ("Format", "S16"), ("Columns", "S64")])


@dataclass
class DFStats:
    """Counts of what the decoder saw and skipped (for ``ImuLog.warnings``)."""

    records: int = 0
    skipped_bytes: int = 0
    resyncs: int = 0
    truncated: int = 0
    bad_fmt: int = 0
    conflicting_fmt: int = 0

    def warnings(self) -> list[str]:
        w = []
        if self.skipped_bytes:
            w.append(f"skipped {self.skipped_bytes} unparseable bytes in {self.resyncs} place(s)")
        if self.truncated:
            w.append("the last record is truncated (log cut off)")
        if self.bad_fmt:
            w.append(f"ignored {self.bad_fmt} corrupt FMT record(s)")
        if self.conflicting_fmt:
            w.append(f"ignored {self.conflicting_fmt} FMT record(s) redefining a type differently")
        return w


Wanted = dict[int, tuple[DFFormat, np.dtype, dict[str, float]]]
_FMT_FORMAT = DFFormat(FMT_TYPE, "FMT", FMT_LEN, "BBnNZ", ("Type", "Length", "Name", "Format", "Columns"))
_FMT_BODY = FMT_LEN - 3
_PARSED_LIMIT = 4096  # distinct FMT bodies remembered (a real log has a few hundred)


def _parse_fmt(r) -> DFFormat | None:
    try:
        name = r["Name"].split(b"\0", 1)[0].decode("ascii")
        fmt = r["Format"].split(b"\0", 1)[0].decode("ascii")
        cols = r["Columns"].split(b"\0", 1)[0].decode("ascii")
    except UnicodeDecodeError:
        return None
    length = int(r["Length"])
    if not name or not name.isprintable() or not cols.isprintable():
        return None
    if int(r["Type"]) == FMT_TYPE:
        return DFFormat(FMT_TYPE, "FMT", FMT_LEN, "BBnNZ", ("Type", "Length", "Name", "Format", "Columns"))
    size = _format_size(fmt)
    columns = tuple(cols.split(",")) if cols else ()
    if size is None or size + 3 != length or len(columns) != len(fmt):
        return None
    return DFFormat(int(r["Type"]), name, length, fmt, columns)


class _FormatTable:
    """The FMT records read so far: formats by type (the first definition wins), record lengths by
    type, and the decoders of the wanted message names.

    Every distinct FMT body is parsed once: each restart of the logger, and each copy of a log,
    repeats the same FMT records byte for byte.
    """

    def __init__(self, names: Iterable[str], stats: DFStats) -> None:
        self.formats: dict[int, DFFormat] = {}
        self.lengths = np.zeros(256, dtype=np.int64)
        self.lengths[FMT_TYPE] = FMT_LEN  # FMT records are known before any FMT-of-FMT
        self.names = set(names)
        self.stats = stats
        self.wanted: Wanted = {}
        self.is_wanted = np.zeros(256, dtype=bool)
        self._parsed: dict[bytes, DFFormat | None] = {}
        if _FMT_FORMAT.name in self.names:  # decoded from the start, like every other FMT-defined type
            self._want(_FMT_FORMAT)

    def _want(self, f: DFFormat) -> None:
        self.wanted[f.type] = (f, f.dtype(), f.multipliers())
        self.is_wanted[f.type] = True

    def add_bodies(self, raw: bytes) -> list[int]:
        """Apply FMT record bodies (``raw``: 86 bytes each, in file order); the types they newly define."""
        new = []
        formats, parsed = self.formats, self._parsed
        for i in range(0, len(raw), _FMT_BODY):
            key = raw[i:i + _FMT_BODY]
            if key in parsed:
                f = parsed[key]
            else:
                f = _parse_fmt(np.frombuffer(key, dtype=_FMT_DTYPE)[0])
                if len(parsed) < _PARSED_LIMIT:
                    parsed[key] = f
            if f is None:
                self.stats.bad_fmt += 1
                continue
            old = formats.get(f.type)
            if old is None:
                formats[f.type] = f
                self.lengths[f.type] = f.length
                new.append(f.type)
                if f.name in self.names:
                    self._want(f)
            elif old is not f and old != f:
                self.stats.conflicting_fmt += 1
        return new

    def scan(self, b: np.ndarray, p: np.ndarray, ty: np.ndarray) -> list[int]:
        """Apply the whole FMT records among the candidates ``p`` (types ``ty``) of chunk ``b``."""
        fc = p[(ty == FMT_TYPE) & (p + FMT_LEN <= len(b))]
        if len(fc) == 0:
            return []
        return self.add_bodies(np.lib.stride_tricks.sliding_window_view(b, _FMT_BODY)[fc + 3].tobytes())

    def finish(self) -> Wanted:
        """The wanted decoders in the order of the formats (FMT itself last unless its own FMT record came)."""
        self.formats.setdefault(FMT_TYPE, _FMT_FORMAT)
        return {t: self.wanted[t] for t in self.formats if t in self.wanted}


def read_formats(path: str, *, chunk_size: int = DEFAULT_CHUNK, stats: DFStats | None = None) -> dict[int, DFFormat]:
    """All valid FMT records of a DataFlash file, by type number (first definition wins)."""
    table = _FormatTable((), stats if stats is not None else DFStats())
    _scan_formats(path, table, chunk_size)
    return table.formats


def _scan_formats(path: str, table: _FormatTable, chunk_size: int) -> None:
    with open(path, "rb", buffering=0) as fh:
        chunks = _Chunks(fh, os.path.getsize(path), chunk_size, FMT_LEN)
        for start, end, b in chunks:
            table.scan(b, *chunks.candidates(b, end - start))


_SEARCH_BLOCK = 256 * 1024  # bytes searched for A3 at a time


class _Chunks:
    """A file in chunks ``[start, end)`` with ``after`` bytes more, each read into the same buffer
    (no allocation, and no fresh pages, per chunk): a chunk's array is valid until the next is read."""

    def __init__(self, fh, size: int, chunk: int, after: int) -> None:
        self.fh, self.size, self.chunk, self.after = fh, size, chunk, after
        self._buf = bytearray(min(chunk + after, size))
        self._arr = np.frombuffer(self._buf, dtype=np.uint8)
        self._eq = np.empty(max(min(chunk, size, _SEARCH_BLOCK), 1), dtype=bool)

    def __iter__(self) -> Iterator[tuple[int, int, np.ndarray]]:
        view = memoryview(self._buf)
        start = 0
        while start < self.size:
            end = min(start + self.chunk, self.size)
            want = min(end + self.after, self.size) - start
            self.fh.seek(start)
            got = 0
            while got < want:
                k = self.fh.readinto(view[got:want])
                if not k:
                    break
                got += k
            yield start, end, self._arr[:got]
            start = end

    def candidates(self, b: np.ndarray, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``p < hi`` of every ``A3 95`` of chunk ``b`` that has a type byte, and those type bytes."""
        lim = max(min(hi, len(b) - 2), 0)
        found = [np.zeros(0, dtype=np.intp)]
        for a in range(0, lim, len(self._eq)):  # the mask of a block at a time: a small scratch
            eq = self._eq[:min(lim - a, len(self._eq))]
            np.equal(b[a:a + len(eq)], HEAD1, out=eq)
            found.append(np.flatnonzero(eq) + a)
        p = np.concatenate(found)
        p = p[b[p + 1] == HEAD2]
        return p, b[p + 2]


def decode_dataflash(path: str, msg_names: Iterable[str], *, chunk_size: int = DEFAULT_CHUNK,
                     progress: ProgressFn | None = None, one_pass: bool = True
                     ) -> tuple[dict[str, dict[str, np.ndarray]], dict[int, DFFormat], DFStats]:
    """Decode the records of the given message names of a DataFlash .bin file.

    Parameters
    ----------
    path : str
    msg_names : iterable of str, e.g. ``["IMU", "MAG", "PARM"]``
    chunk_size : int
        Bytes per read.
    progress : callable(done_bytes, total_bytes), optional
        Called during the record pass.
    one_pass : bool
        False: read the FMT records of the whole file before the records (the two-pass
        reference order; the result is the same, see Notes).

    Returns
    -------
    columns : dict name -> dict column -> (n,) array
        Columns under their FMT names with DFReader's multipliers applied (float64 then);
        strings as ``bytes`` arrays; plus ``_index`` (record number in the file). Only the
        names present in the log appear.
    formats : dict type -> DFFormat
    stats : DFStats

    Notes
    -----
    One pass reads the FMT records as they come and frames each chunk with the types defined
    so far. That equals framing with the FMT records of the whole file (DFReader's rule)
    unless a type first defined in a later chunk had a candidate record start in an earlier
    one: then the file is read again, its FMT records first (two passes, the same result).
    """
    names = list(msg_names)
    progress = _monotonic(progress)  # a second pass reports only past what the first one did
    table = _FormatTable(names, DFStats())
    columns = _record_pass(path, table, chunk_size, progress, growing=True) if one_pass else None
    if columns is None:
        table = _FormatTable(names, DFStats())
        _scan_formats(path, table, chunk_size)
        columns = _record_pass(path, table, chunk_size, progress, growing=False)
        assert columns is not None
    return columns, table.formats, table.stats


def _monotonic(progress: ProgressFn | None) -> ProgressFn | None:
    """``progress`` called only when the done count passes its highest so far (a second pass)."""
    if progress is None:
        return None
    high = [0]

    def report(done: int, total: int) -> None:
        if done > high[0]:
            high[0] = done
            progress(done, total)
    return report


def _record_pass(path: str, table: _FormatTable, chunk_size: int, progress: ProgressFn | None,
                 growing: bool) -> dict[str, dict[str, np.ndarray]] | None:
    """Frame and decode every chunk; ``growing``: apply each chunk's FMT records first (None when a
    type defined late had a candidate record start in an earlier chunk: see :func:`decode_dataflash`)."""
    size = os.path.getsize(path)
    stats = table.stats
    parts: dict[int, ColumnBuffer] = {}
    seen = np.zeros(256, dtype=bool)  # types of the candidate starts framed so far
    expected = 0
    with open(path, "rb", buffering=0) as fh:
        chunks = _Chunks(fh, size, chunk_size, 256)
        for start, end, b in chunks:
            p, ty = chunks.candidates(b, end - start)
            if growing:
                new = table.scan(b, p, ty)
                if new and bool(seen[new].any()):
                    return None
            if expected < end:
                loc = expected - start
                if growing:
                    seen[ty[np.searchsorted(p, loc):]] = True
                recs = _frame(p, ty, end - start, table.lengths, loc, stats)
                if recs is not None and recs.count == 0:
                    expected = end
                elif recs is not None:
                    # trailing garbage after the last record is ignored, as DFReader does
                    expected = start + _decode_records(b, recs, table, parts)
            del b, p, ty
            if progress:
                progress(end, size)
    return _join(table.finish(), parts)


@dataclass(frozen=True)
class _Path:
    """The records of one chunk, as runs of candidates (see :func:`_frame`).

    ``p``, ``ty``, ``nxt``: the candidates of a known type (positions, types, record ends);
    ``ends``: the last candidate of each run; ``entry``: per run, the first candidate of it on
    the path (a huge number for runs off the path: the path covers ``entry[r] .. ends[r]``);
    ``before``: per run, the records of the path before it; ``count`` records, the last one
    the candidate ``last``.
    """

    p: np.ndarray
    ty: np.ndarray
    nxt: np.ndarray
    ends: np.ndarray
    entry: np.ndarray
    before: np.ndarray
    count: int
    last: int


_OFF_PATH = np.iinfo(np.int64).max


def _frame(p: np.ndarray, ty: np.ndarray, hi: int, lengths: np.ndarray, loc_exp: int, stats: DFStats
           ) -> _Path | None:
    """The records of one chunk (no record: ``count`` 0); None if no candidate has a known type.

    As DFReader: a record at ``p`` is followed by the first ``A3 95 <known type>`` at or after
    ``p + length``; the path starts at the first candidate at or after ``loc_exp``. Gaps are
    counted in ``stats`` (at the very start a log may begin with garbage: counted the same).

    The candidates fall into runs where each record ends at or before the next candidate (whose
    successor is therefore the next candidate); the path enters a run, follows it to its end
    and jumps to the first candidate at or after that end: only the runs are followed by pointer
    doubling, and the successor search is made for run ends only.
    """
    ln = lengths[ty]
    known = ln > 0
    if not known.all():
        p, ty, ln = p[known], ty[known], ln[known]
    n = len(p)
    if n == 0:
        return None
    first = int(np.searchsorted(p, loc_exp))
    if first >= n:
        empty = np.zeros(0, dtype=np.int64)
        return _Path(p, ty, p, empty, empty, empty, 0, -1)
    nxt = p + ln
    d = p[1:] - nxt[:-1]  # bytes from a record's end to the next candidate (< 0: that one starts inside it)
    brk = np.empty(n, dtype=bool)
    np.less(d, 0, out=brk[:-1])
    brk[-1] = True
    ends = np.flatnonzero(brk)  # run r: the candidates ends[r - 1] + 1 .. ends[r]
    ne = nxt[ends]
    s = np.searchsorted(p, ne)  # successor of each run end (n: none in this chunk)
    s[ne >= hi] = n
    on = np.flatnonzero(mark_path(np.searchsorted(ends, s), int(np.searchsorted(ends, first))))
    entries = np.empty(len(on), dtype=np.int64)
    entries[0] = first
    entries[1:] = s[on[:-1]]
    last = ends[on]
    cnt = last - entries + 1
    entry = np.full(len(ends), _OFF_PATH, dtype=np.int64)
    entry[on] = entries
    before = np.zeros(len(ends), dtype=np.int64)
    before[on] = np.cumsum(cnt) - cnt
    _count_gaps(p, d, nxt, ends, entry, entries, last, loc_exp, stats)
    return _Path(p, ty, nxt, ends, entry, before, int(cnt.sum()), int(last[-1]))


def _count_gaps(p: np.ndarray, d: np.ndarray, nxt: np.ndarray, ends: np.ndarray, entry: np.ndarray,
                entries: np.ndarray, last: np.ndarray, loc_exp: int, stats: DFStats) -> None:
    """Skipped bytes between the records of the path (and before its first): at its start, where it
    jumps from run to run, and inside runs (a record ending before the next candidate)."""
    gaps = [np.array([p[entries[0]] - loc_exp]), p[entries[1:]] - nxt[last[:-1]]]
    soft = np.flatnonzero(d > 0)  # never a run end: d >= 0 there
    if len(soft):
        soft = soft[soft >= entry[np.searchsorted(ends, soft)]]  # on the path
        gaps.append(d[soft])
    g = np.concatenate(gaps)
    stats.skipped_bytes += int(g[g > 0].sum())
    stats.resyncs += int((g > 0).sum())


def _decode_records(b: np.ndarray, fr: _Path, table: _FormatTable, parts: dict[int, ColumnBuffer]) -> int:
    """Append the columns of the wanted records of one chunk to ``parts`` (one buffer per type);
    the end of its last record (in the chunk)."""
    stats = table.stats
    end = int(fr.nxt[fr.last])
    # only the last record can be cut off: every other one ends at or before the next start
    cut = end > len(b)
    stats.truncated += int(cut)
    first_recno = stats.records
    stats.records += fr.count
    wc = np.flatnonzero(table.is_wanted[fr.ty])  # the wanted candidates, then those on the path
    run = np.searchsorted(fr.ends, wc)
    entry = fr.entry[run]
    on = wc >= entry
    if cut:
        on &= wc != fr.last
    if not on.all():
        wc, run, entry = wc[on], run[on], entry[on]
    if len(wc) == 0:
        return end
    rank = fr.before[run] + (wc - entry)  # record number in the chunk
    wt = fr.ty[wc]
    for t, (f, dt, mults) in table.wanted.items():
        m = wt == t
        if not m.any():
            continue
        # gather only the record bodies (a window view indexes bytes, not an index per byte)
        rec = np.lib.stride_tricks.sliding_window_view(b, f.length - 3)[fr.p[wc[m]] + 3].view(dt).ravel()
        part = {}
        for name in dt.names or ():
            col = rec[name]  # a field view: copied once, into the column buffer
            mult = mults.get(name)
            if mult is not None:
                # as DFReader: dividing by 1e2/1e7 is more accurate than multiplying
                col = col.astype(np.float64) / (1 / mult)
            part[name] = col
        part["_index"] = rank[m] + first_recno
        buf = parts.get(t)
        if buf is None:
            buf = parts[t] = ColumnBuffer()
        buf.append(part)
    return end


def _join(wanted: Wanted, parts: dict[int, ColumnBuffer]) -> dict[str, dict[str, np.ndarray]]:
    """One column dict per message name (a name defined under two type numbers is merged by record order)."""
    columns: dict[str, dict[str, np.ndarray]] = {}
    for t, (f, _, _) in wanted.items():
        if t not in parts or not parts[t].n:
            continue
        cols = parts[t].columns()
        if f.name in columns:  # same name defined under two type numbers
            prev = columns[f.name]
            if set(prev) != set(cols):
                continue
            cols = {k: np.concatenate([prev[k], cols[k]]) for k in cols}
            order = np.argsort(cols["_index"], kind="stable")
            cols = {k: v[order] for k, v in cols.items()}
        columns[f.name] = cols
    return columns
