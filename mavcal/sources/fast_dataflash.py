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
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mavcal.sources.framing import ColumnBuffer, file_chunks, path_from
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


def read_formats(path: str, *, chunk_size: int = DEFAULT_CHUNK, stats: DFStats | None = None) -> dict[int, DFFormat]:
    """All valid FMT records of a DataFlash file, by type number (first definition wins)."""
    size = os.path.getsize(path)
    formats: dict[int, DFFormat] = {}
    stats = stats if stats is not None else DFStats()
    with open(path, "rb") as fh:
        for _, start, end, b in file_chunks(fh, size, chunk_size, 0, FMT_LEN):
            n = end - start
            p = np.flatnonzero(b[: n] == HEAD1)
            p = p[p + FMT_LEN <= len(b)]
            p = p[(b[p + 1] == HEAD2) & (b[p + 2] == FMT_TYPE)]
            if len(p) == 0:
                continue
            recs = np.lib.stride_tricks.sliding_window_view(b, FMT_LEN - 3)[p + 3].view(_FMT_DTYPE).ravel()
            for r in recs:
                f = _parse_fmt(r)
                if f is None:
                    stats.bad_fmt += 1
                    continue
                old = formats.get(f.type)
                if old is None:
                    formats[f.type] = f
                elif old != f:
                    stats.conflicting_fmt += 1
    return formats


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


_FMT_FORMAT = DFFormat(FMT_TYPE, "FMT", FMT_LEN, "BBnNZ", ("Type", "Length", "Name", "Format", "Columns"))
Wanted = dict[int, tuple[DFFormat, np.dtype, dict[str, float]]]


def decode_dataflash(path: str, msg_names: Iterable[str], *, chunk_size: int = DEFAULT_CHUNK,
                     progress: ProgressFn | None = None
                     ) -> tuple[dict[str, dict[str, np.ndarray]], dict[int, DFFormat], DFStats]:
    """Decode the records of the given message names of a DataFlash .bin file.

    Parameters
    ----------
    path : str
    msg_names : iterable of str, e.g. ``["IMU", "MAG", "PARM"]``
    chunk_size : int
        Bytes per read.
    progress : callable(done_bytes, total_bytes), optional
        Called during the record pass (the FMT pass is a plain byte search).

    Returns
    -------
    columns : dict name -> dict column -> (n,) array
        Columns under their FMT names with DFReader's multipliers applied (float64 then);
        strings as ``bytes`` arrays; plus ``_index`` (record number in the file). Only the
        names present in the log appear.
    formats : dict type -> DFFormat
    stats : DFStats
    """
    size = os.path.getsize(path)
    stats = DFStats()
    formats = read_formats(path, chunk_size=chunk_size, stats=stats)
    formats.setdefault(FMT_TYPE, _FMT_FORMAT)
    lengths = np.zeros(256, dtype=np.int64)
    for t, f in formats.items():
        lengths[t] = f.length
    names = set(msg_names)
    wanted: Wanted = {t: (f, f.dtype(), f.multipliers()) for t, f in formats.items() if f.name in names}
    parts: dict[int, ColumnBuffer] = {t: ColumnBuffer() for t in wanted}
    expected = 0
    with open(path, "rb") as fh:
        for _, start, end, b in file_chunks(fh, size, chunk_size, 0, 256):
            if expected < end:
                recs = _records_in(b, end - start, lengths, expected - start, stats)
                if recs is not None and len(recs[0]) == 0:
                    expected = end
                elif recs is not None:
                    pos, typ, ln = recs
                    # trailing garbage after the last record is ignored, as DFReader does
                    expected = start + int(pos[-1] + ln[-1])
                    _decode_records(b, recs, wanted, parts, stats)
            del b
            if progress:
                progress(end, size)
    return _join(wanted, parts), formats, stats


def _records_in(b: np.ndarray, hi: int, lengths: np.ndarray, loc_exp: int, stats: DFStats):
    """Records of one chunk starting in ``[0, hi)``: (pos, type, length) arrays, or None if no candidate.

    As DFReader: a record at ``p`` is followed by the first ``A3 95 <known type>`` at or after
    ``p + length``; the path starts at the first candidate at or after ``loc_exp``. Gaps are
    counted in ``stats`` (at the very start a log may begin with garbage: counted the same).
    """
    nb = len(b)
    p = np.flatnonzero(b[: min(hi, nb - 2)] == HEAD1)
    p = p[(b[p + 1] == HEAD2) & (lengths[b[p + 2]] > 0)]
    if len(p) == 0:
        return None
    ln = lengths[b[p + 2]]
    nxt = p + ln
    succ = np.where(nxt >= hi, len(p), np.searchsorted(p, nxt))  # first candidate at or after p + length
    idx = np.flatnonzero(path_from(succ, int(np.searchsorted(p, loc_exp))))
    pos, ln = p[idx], ln[idx]
    if len(pos):
        gaps = np.empty(len(pos), dtype=np.int64)
        gaps[0] = pos[0] - loc_exp
        gaps[1:] = pos[1:] - (pos[:-1] + ln[:-1])
        stats.skipped_bytes += int(gaps[gaps > 0].sum())
        stats.resyncs += int((gaps > 0).sum())
    return pos, b[pos + 2], ln


def _decode_records(b: np.ndarray, recs, wanted: Wanted, parts: dict[int, ColumnBuffer],
                    stats: DFStats) -> None:
    """Append the columns of the wanted records of one chunk to ``parts`` (one dict per type)."""
    pos, typ, ln = recs
    inside = pos + ln <= len(b)
    stats.truncated += int((~inside).sum())
    recno = np.arange(len(pos), dtype=np.int64) + stats.records
    stats.records += len(pos)
    for t, (f, dt, mults) in wanted.items():
        sel = np.flatnonzero((typ == t) & inside)
        if len(sel) == 0:
            continue
        # gather only the record bodies (a window view indexes bytes, not an index per byte)
        rec = np.lib.stride_tricks.sliding_window_view(b, f.length - 3)[pos[sel] + 3].view(dt).ravel()
        part = {}
        for name in dt.names or ():
            col = rec[name]  # a field view: copied once, into the column buffer
            m = mults.get(name)
            if m is not None:
                # as DFReader: dividing by 1e2/1e7 is more accurate than multiplying
                col = col.astype(np.float64) / (1 / m)
            part[name] = col
        part["_index"] = recno[sel]
        parts[t].append(part)


def _join(wanted: Wanted, parts: dict[int, ColumnBuffer]) -> dict[str, dict[str, np.ndarray]]:
    """One column dict per message name (a name defined under two type numbers is merged by record order)."""
    columns: dict[str, dict[str, np.ndarray]] = {}
    for t, (f, _, _) in wanted.items():
        if not parts[t].n:
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
