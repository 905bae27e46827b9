"""Vectorised MAVLink telemetry-log (.tlog) decoder.

A tlog is a sequence of ``[8-byte big-endian unix time in µs][MAVLink v1 or v2 frame]``.
This module finds the frames with numpy over the file bytes, verifies the CRC-16/MCRF4XX
(with the per-message CRC_EXTRA of pymavlink's ``all`` dialect, as mavutil uses) of the frames
of the requested message ids and decodes their payloads into numpy columns through structured
dtypes. Frames of other types are not CRC-checked by default (a CRC never changes the framing;
``check_all_crc=True`` checks them too), and the warnings say how many were not. It never
creates a Python object per message, and it reads the file in chunks, so memory stays bounded
by the chunk size plus the decoded columns.

Framing rule (same as pymavlink's stream parser on a well-formed tlog): after a frame at
offset ``p`` of total length ``L`` the next frame starts at ``p + L + 8``. A frame with a
bad CRC is consumed whole (pymavlink returns ``BAD_DATA`` for it and goes on after it). When
the byte there is not a MAVLink start byte (corruption), the decoder re-synchronises on the
next start byte after ``p`` whose preceding 8 bytes are a plausible timestamp (years
2000-2100) and counts the skipped bytes. Signed v2 frames (13-byte signature) are
accepted (the signature is not checked, as pymavlink does without a key), and v2 payloads
truncated of trailing zeros are zero-padded to the full message length.

The reference is pymavlink: ``tests/test_sources_files.py`` checks that the values decoded
here are identical to a ``recv_match`` loop on the real logs.
"""
from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from mavcal.sources.framing import ColumnBuffer, file_chunks, first_at_or_after, path_from
from mavcal.sources.progress import ProgressFn

try:  # the dialect mavutil uses by default (superset of ardupilotmega)
    from pymavlink.dialects.v20 import all as _dialect
except ImportError:  # pragma: no cover
    from pymavlink.dialects.v20 import ardupilotmega as _dialect


log = logging.getLogger(__name__)

STX_V1 = 0xFE
STX_V2 = 0xFD
_TS_MIN_US = 946684800 * 10**6  # 2000-01-01
_TS_MAX_US = 4102444800 * 10**6  # 2100-01-01
_MAX_FRAME = 10 + 255 + 2 + 13
DEFAULT_CHUNK = 2 * 1024 * 1024  # small enough for the temporaries to stay cached/reused (faster than 4 or 32 MiB)



def _make_crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint16)
    for b in range(256):
        # x25 accumulate of byte b into crc 0 gives the table entry for index b
        tmp = b & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        table[b] = ((tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return table


_CRC_TABLE = _make_crc_table()


def _make_crc_table16(t8: np.ndarray) -> np.ndarray:
    """Table advancing the CRC by two bytes at once: ``crc' = T16[crc ^ (b0 | b1 << 8)]``.

    Both bytes of the 16-bit register are shifted out by two byte steps, so the new CRC is a
    function of ``crc ^ word`` alone.
    """
    x = np.arange(65536, dtype=np.uint32)
    t = t8.astype(np.uint32)
    a = t[x & 0xFF]
    return ((a >> 8) ^ t[(x >> 8) ^ (a & 0xFF)]).astype(np.uint16)


_CRC_TABLE16 = _make_crc_table16(_CRC_TABLE)

# msgid -> message class, crc_extra arrays for vectorised lookup
_MAP = _dialect.mavlink_map
_IDS = np.array(sorted(_MAP), dtype=np.int64)
_EXTRA = np.array([_MAP[i].crc_extra for i in _IDS], dtype=np.uint16)


def _struct_dtype(cls) -> tuple[np.dtype, list[str]]:
    """numpy structured dtype of a pymavlink message class's wire payload (packed, LE)."""
    fmt = cls.unpacker.format
    if isinstance(fmt, bytes):
        fmt = fmt.decode()
    assert fmt[0] == "<"
    codes = {"b": "i1", "B": "u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "q": "<i8",
             "Q": "<u8", "f": "<f4", "d": "<f8", "c": "S1"}
    parts = re.findall(r"(\d*)([a-zA-Z?])", fmt[1:])
    names = list(cls.ordered_fieldnames)
    if len(parts) != len(names):
        raise RuntimeError(f"cannot map {cls.msgname} format {fmt}")
    fields: list[tuple] = []
    for name, (count, code) in zip(names, parts):
        n = int(count) if count else 1
        if code == "s":
            fields.append((name, f"S{n}"))
        elif n > 1:
            fields.append((name, codes[code], (n,)))
        else:
            fields.append((name, codes[code]))
    dt = np.dtype(fields)
    if dt.itemsize != cls.unpacker.size:
        raise RuntimeError(f"dtype size mismatch for {cls.msgname}")
    return dt, names


def msgid_of(name: str) -> int:
    """MAVLink message id of a message name of the ardupilotmega dialect."""
    for i, cls in _MAP.items():
        if cls.msgname == name:
            return int(i)
    raise KeyError(name)


def crc_x25(data: np.ndarray, starts: np.ndarray, lengths: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """CRC-16/MCRF4XX of ``data[starts[k] : starts[k] + lengths[k]]`` followed by ``extra[k]``.

    Vectorised over frames: frames are grouped by length, each group's bytes (plus the extra
    byte) are copied into one block and the CRC advances two bytes (one column of the
    transposed block) at a time with a 65536-entry table.

    Parameters
    ----------
    data : (N,) uint8 array
    starts, lengths : (m,) int arrays
    extra : (m,) uint8/uint16 array, the CRC_EXTRA byte appended to each frame

    Returns
    -------
    (m,) uint16 array
    """
    out = np.empty(len(starts), dtype=np.uint16)
    if len(starts) == 0:
        return out
    data = np.asarray(data, dtype=np.uint8)
    starts = np.asarray(starts, dtype=np.int64)
    lengths = np.asarray(lengths, dtype=np.int64)
    extra = np.asarray(extra)
    # lengths of MAVLink frames are < 300: a 16-bit key sorts by radix
    key = lengths.astype(np.uint16) if int(lengths.max()) < 65536 else lengths
    order = np.argsort(key, kind="stable")
    bounds = np.flatnonzero(np.diff(key[order])) + 1
    for grp in np.split(order, bounds):
        n = int(lengths[grp[0]])
        g = len(grp)
        total = n + 1  # bytes through the CRC, extra included
        odd = total & 1
        # row layout: [pad if odd][data bytes][extra]; pairs after the pad are (b0,b1), (b2,b3)...
        buf = np.empty((g, total + odd), dtype=np.uint8)
        if n > 0:
            buf[:, odd:odd + n] = np.lib.stride_tricks.sliding_window_view(data, n)[starts[grp]]
        buf[:, -1] = extra[grp]
        crc = np.full(g, 0xFFFF, dtype=np.uint16)
        words = np.ascontiguousarray(buf.view("<u2").T)
        if odd:  # the first byte alone, then whole words
            crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ buf[:, 1]) & 0xFF]
            words = words[1:]
        x = np.empty_like(crc)
        for w in words:  # crc = T16[crc ^ w], without a temporary per step
            np.bitwise_xor(crc, w, out=x)
            np.take(_CRC_TABLE16, x, out=crc)
        out[grp] = crc
    return out


@dataclass
class TlogStats:
    """Counts of what the decoder saw and skipped (for ``ImuLog.warnings``)."""

    frames: int = 0
    bad_crc: int = 0
    bad_crc_by_id: dict[int, int] = field(default_factory=dict)
    unknown_id: int = 0
    bad_header: int = 0
    truncated: int = 0
    skipped_bytes: int = 0
    resyncs: int = 0
    signed: int = 0
    v1: int = 0
    v2: int = 0
    #: frames of known message types whose CRC was not checked (types not decoded)
    crc_unchecked: int = 0

    def notes(self) -> list[str]:
        """Informational lines (logged at debug level, not shown as warnings)."""
        if self.crc_unchecked:
            return [f"CRC checked only for the decoded message types: {self.crc_unchecked} MAVLink frames "
                    "of other types were not checked"]
        return []

    def warnings(self) -> list[str]:
        """What was skipped, for the user."""
        w = []
        if self.bad_crc:
            top = ", ".join(f"id {k}: {v}" for k, v in sorted(self.bad_crc_by_id.items(), key=lambda kv: -kv[1])[:5])
            w.append(f"skipped {self.bad_crc} MAVLink frames with a bad CRC ({top})")
        if self.unknown_id:
            w.append(f"skipped {self.unknown_id} MAVLink frames with an unknown message id")
        if self.bad_header:
            w.append(f"skipped {self.bad_header} MAVLink v2 frames with invalid incompat flags")
        if self.truncated:
            w.append(f"skipped {self.truncated} truncated MAVLink frame(s) at the end of the file")
        if self.skipped_bytes:
            w.append(f"skipped {self.skipped_bytes} unparseable bytes in {self.resyncs} place(s)")
        return w


def _candidates(b: np.ndarray, lo: int, hi: int, expected: int):
    """Candidate frame starts of a chunk that some path can reach, or None.

    Returns (cand, direct, strong): local positions of 0xFD/0xFE bytes in ``[lo, hi)``, the
    position right after each one's frame and the next timestamp (a direct hit), and whether
    the 8 bytes before it are a plausible timestamp. Only candidates hit directly by some
    candidate, those with a plausible timestamp and the expected one are kept, which drops
    most 0xFD/0xFE bytes inside payloads before the graph is built.
    """
    nb = len(b)
    cand = np.flatnonzero((b[lo:hi] - np.uint8(STX_V2)) <= 1) + lo  # 0xFD or 0xFE
    cand = cand[cand >= 8]
    if len(cand):
        cand = cand[cand + np.where(b[cand] == STX_V2, 10, 6) <= nb]  # need the header inside b
    if len(cand) == 0:
        return None
    isv2 = b[cand] == STX_V2
    signed = isv2 & ((b[np.minimum(cand + 2, nb - 1)] & 1) != 0)
    direct = cand + b[cand + 1] + np.where(isv2, 20, 16) + np.where(signed, 13, 0)  # + hlen + 2 + sig + 8
    # timestamp plausibility (for resynchronisation only): the top 16 bits of a unix time in
    # microseconds between 2000 and 2100 are 0x0003..0x000E
    hi16 = b[cand - 7]
    strong = (b[cand - 8] == 0) & (hi16 >= (_TS_MIN_US >> 48)) & (hi16 <= (_TS_MAX_US >> 48))
    target = np.zeros(hi + 1, dtype=bool)
    target[direct[direct < hi]] = True
    keep = target[cand] | strong | (cand == expected)
    if not keep.any():
        return None
    return cand[keep], direct[keep], strong[keep]


def _direct_successors(cand: np.ndarray, direct: np.ndarray, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """(hit, j): whether each candidate's direct successor is a candidate, and its index (else n)."""
    n = len(cand)
    is_cand = np.zeros(hi + 1, dtype=bool)
    is_cand[cand] = True
    hit = (direct < hi) & is_cand[np.minimum(direct, hi)]
    # index of the direct successor: a few candidates ahead (usually the next one)
    j = np.full(n, n, dtype=np.int64)
    pend = np.flatnonzero(hit)
    d = 1
    while len(pend):
        if d > 8:
            j[pend] = np.searchsorted(cand, direct[pend])
            break
        jj = np.minimum(pend + d, n - 1)
        found = cand[jj] == direct[pend]
        j[pend[found]] = jj[found]
        pend = pend[~found]
        d += 1
    return hit, j


def _skipped(pos: np.ndarray, ends: np.ndarray, first_gap: int) -> tuple[int, int]:
    """(skipped bytes, resyncs): the gap before the first frame plus those between path frames."""
    skipped = resyncs = 0
    if first_gap > 0:
        skipped, resyncs = first_gap, 1
    if len(pos) > 1:
        gaps = pos[1:] - ends[:-1]
        nz = gaps != 0
        skipped += int(np.abs(gaps[nz]).sum())
        resyncs += int(nz.sum())
    return skipped, resyncs


def _frame_arrays(b: np.ndarray, pos: np.ndarray) -> dict[str, np.ndarray]:
    isv2 = b[pos] == STX_V2
    hlen = np.where(isv2, 10, 6)
    plen = b[pos + 1].astype(np.int64)
    incompat = np.where(isv2, b[pos + 2], 0).astype(np.int64)
    signed = isv2 & ((incompat & 1) != 0)
    flen = hlen + plen + 2 + np.where(signed, 13, 0)
    return dict(pos=pos, isv2=isv2, hlen=hlen, plen=plen, flen=flen, incompat=incompat, signed=signed)


def _frames_in(b: np.ndarray, lo: int, hi: int, expected: int):
    """Find the frames of one chunk.

    ``b`` holds file bytes from some base; candidate start bytes are at local positions
    ``lo <= p < hi``; ``expected`` is the local position where the next frame should start.
    Returns (frame arrays or None, next expected local position, skipped bytes, resyncs).

    Candidates form a graph: each goes to the candidate right after its frame and timestamp
    (a direct hit), else to the next candidate with a plausible timestamp (resync); the
    frames are the path from the expected position (see :func:`_candidates`).
    """
    found = _candidates(b, lo, hi, expected)
    if found is None:
        return None, hi, 0, 0
    cand, direct, strong = found
    n = len(cand)
    hit, j = _direct_successors(cand, direct, hi)
    first_strong = first_at_or_after(strong)  # first strong candidate at or after each one
    resync = first_strong[1:]
    succ = np.where(hit, j, np.where(direct >= hi, n, resync))
    s0 = int(np.searchsorted(cand, expected))
    if not (s0 < n and cand[s0] == expected):
        s0 = int(first_strong[s0]) if s0 <= n else n
    idx = np.flatnonzero(path_from(succ, s0))
    if len(idx) == 0:
        return None, hi, 0, 0
    first_gap = int(cand[s0] - expected) if s0 < n and cand[s0] != expected and expected < hi else 0
    skipped, resyncs = _skipped(cand[idx], direct[idx], first_gap)
    last = idx[-1]
    nxt = int(direct[last]) if hit[last] or direct[last] >= hi else int(cand[resync[last]]) if resync[last] < n else hi
    return _frame_arrays(b, cand[idx]), nxt, skipped, resyncs


def wanted_messages(msg_names: Iterable[str]) -> dict[int, tuple[str, np.dtype, list[str]]]:
    """Message id -> (name, structured payload dtype, field names) of the given message names."""
    wanted = {}
    for name in msg_names:
        mid = msgid_of(name)
        wanted[mid] = (name,) + _struct_dtype(_MAP[mid])
    return wanted


def decode_tlog(path: str, msg_names: Iterable[str], *, chunk_size: int = DEFAULT_CHUNK,
                progress: ProgressFn | None = None, check_all_crc: bool = False
                ) -> tuple[dict[str, dict[str, np.ndarray]], TlogStats]:
    """Decode the given message types of a tlog into numpy columns.

    Parameters
    ----------
    path : str
        The .tlog file.
    msg_names : iterable of str
        MAVLink message names (ardupilotmega dialect) to decode, e.g. ``["RAW_IMU"]``.
    chunk_size : int
        Bytes per read; the decoder's working memory is a few times this, plus the decoded
        columns (grown in place, never held twice).
    progress : callable(done_bytes, total_bytes), optional
    check_all_crc : bool
        Also verify the CRC of frames of the types that are not decoded (to count them in
        ``stats.bad_crc``). By default only the decoded types are checked (a frame's CRC
        does not change the framing); the others are counted in ``stats.crc_unchecked``.

    Returns
    -------
    columns : dict name -> dict column -> (n,) array
        Every payload field under its pymavlink name (strings as ``bytes`` arrays with trailing
        NULs stripped by numpy, arrays as (n, k)), plus ``_log_time_s`` (tlog timestamp, s),
        ``_index`` (frame number in the file), ``_sysid``, ``_compid``.
    stats : TlogStats
    """
    wanted = wanted_messages(msg_names)
    sink = ColumnSink(wanted)
    stats = scan_tlog(path, wanted, sink, chunk_size=chunk_size, progress=progress, check_all_crc=check_all_crc)
    return sink.columns(), stats


class ColumnSink:
    """Receives the decoded records of :func:`scan_tlog` as the columns :func:`decode_tlog` returns."""

    def __init__(self, wanted: dict[int, tuple[str, np.dtype, list[str]]]) -> None:
        self.wanted = wanted
        self.parts: dict[int, ColumnBuffer] = {mid: ColumnBuffer() for mid in wanted}

    def take(self, mid: int, rec: np.ndarray, ts_us: np.ndarray, frame_no: np.ndarray, sysid: np.ndarray,
             compid: np.ndarray) -> None:
        """Records ``rec`` (structured) of message ``mid`` with their tlog time (µs), frame numbers and ids."""
        part = {n: rec[n] for n in self.wanted[mid][2]}  # field views: copied once, into the column buffer
        part["_log_time_s"] = ts_us.astype(np.float64) * 1.0e-6
        part["_index"] = frame_no
        part["_sysid"] = sysid
        part["_compid"] = compid
        self.parts[mid].append(part)

    def chunk_done(self) -> None:
        """Every record of one chunk has been taken (in message-id order)."""

    def columns(self) -> dict[str, dict[str, np.ndarray]]:
        return _join(self.wanted, self.parts)


def scan_tlog(path: str, wanted: dict[int, tuple[str, np.dtype, list[str]]], sink, *,
              chunk_size: int = DEFAULT_CHUNK, progress: ProgressFn | None = None,
              check_all_crc: bool = False) -> TlogStats:
    """Frame a tlog chunk by chunk and hand the good records of the ``wanted`` ids (see
    :func:`wanted_messages`) to ``sink.take`` (then ``sink.chunk_done()`` per chunk), in file
    order. :func:`decode_tlog` is this with a :class:`ColumnSink`."""
    size = os.path.getsize(path)
    stats = TlogStats()
    expected = 8  # first STX after the first timestamp
    # two stages: the framing of a chunk needs where the previous chunk's last frame ends, the
    # decoding of its frames does not; a worker thread decodes chunk k (numpy releases the
    # GIL in its loops) while this thread frames chunk k + 1. One chunk in flight: the
    # columns grow in file order and every count is the same as in one thread.
    with open(path, "rb") as fh, ThreadPoolExecutor(max_workers=1) as pool:
        pending: Future | None = None
        for base, start, end, b in file_chunks(fh, size, chunk_size, 8, _MAX_FRAME + 8):
            if expected < end:
                frames, nxt, skipped, resyncs = _frames_in(b, start - base, end - base, expected - base)
                stats.skipped_bytes += skipped
                stats.resyncs += resyncs
                if frames is not None:
                    expected = base + nxt
                    if pending is not None:
                        pending.result()
                    pending = pool.submit(_decode_frames, b, frames, wanted, sink, stats,
                                          base + len(b) == size, check_all_crc, stats.frames)
                    stats.frames += len(frames["pos"])
                else:
                    expected = max(expected, end)
            del b
            if progress:
                progress(end, size)
        if pending is not None:
            pending.result()
    return stats


def _join(wanted, out_parts) -> dict[str, dict[str, np.ndarray]]:
    columns: dict[str, dict[str, np.ndarray]] = {}
    for mid, (name, dt, names) in wanted.items():
        if out_parts[mid].n:
            columns[name] = out_parts[mid].columns()
        else:
            columns[name] = {k: np.zeros((0,) + dt[k].shape, dtype=dt[k].base) for k in names}
            columns[name].update(_log_time_s=np.zeros(0), _index=np.zeros(0, np.int64),
                                 _sysid=np.zeros(0, np.uint8), _compid=np.zeros(0, np.uint8))
    return columns


def _decode_frames(b, fr, wanted, sink, stats, at_eof, check_all_crc=False, first_frame=0):
    """Check and decode the frames ``fr`` of chunk ``b`` (``first_frame``: the file's frame
    number of the first one) into ``sink``, counting in ``stats`` what is skipped."""
    nb = len(b)
    pos, isv2, hlen, plen, flen = fr["pos"], fr["isv2"], fr["hlen"], fr["plen"], fr["flen"]
    inside = pos + flen <= nb
    ntrunc = int((~inside).sum())
    frame_no = np.arange(len(pos), dtype=np.int64) + first_frame
    incompat, signed = fr["incompat"], fr["signed"]
    if ntrunc:
        if at_eof:
            stats.truncated += ntrunc
        pos, isv2, hlen, plen, flen = pos[inside], isv2[inside], hlen[inside], plen[inside], flen[inside]
        incompat, signed, frame_no = incompat[inside], signed[inside], frame_no[inside]
    stats.v2 += int(isv2.sum())
    stats.v1 += len(isv2) - int(isv2.sum())
    stats.signed += int(signed.sum())
    badhdr = isv2 & ((incompat & 0xFE) != 0)
    stats.bad_header += int(badhdr.sum())
    msgid = np.where(isv2, b[pos + 7].astype(np.int64) | (b[pos + 8].astype(np.int64) << 8)
                     | (b[pos + 9].astype(np.int64) << 16), b[np.minimum(pos + 5, nb - 1)].astype(np.int64))
    k = np.searchsorted(_IDS, msgid)
    kc = np.minimum(k, len(_IDS) - 1)
    known = (_IDS[kc] == msgid) & ~badhdr
    nknown = int(known.sum())
    stats.unknown_id += len(known) - nknown - int(badhdr.sum())
    # the CRC is checked for the frames that are decoded (or all known frames on request)
    check = known if check_all_crc else known & np.isin(msgid, list(wanted))
    kk = np.flatnonzero(check)
    stats.crc_unchecked += nknown - len(kk)
    crc_calc = crc_x25(b, pos[kk] + 1, hlen[kk] - 1 + plen[kk], _EXTRA[kc[kk]])
    cpos = pos[kk] + hlen[kk] + plen[kk]
    crc_got = b[cpos].astype(np.uint16) | (b[cpos + 1].astype(np.uint16) << 8)
    ok_k = crc_calc == crc_got
    bad = kk[~ok_k]
    stats.bad_crc += len(bad)
    if len(bad):
        ids, cnt = np.unique(msgid[bad], return_counts=True)
        for i, c in zip(ids.tolist(), cnt.tolist()):
            stats.bad_crc_by_id[i] = stats.bad_crc_by_id.get(i, 0) + c
    good = kk[ok_k]
    # the good frames grouped by message id, each group in frame order (a stable radix sort:
    # the decoded ids are < 65536)
    gid = msgid[good]
    small = len(gid) == 0 or int(gid.max()) < 65536
    by_id = np.argsort(gid.astype(np.uint16) if small else gid, kind="stable")
    gid_sorted = gid[by_id]
    windows = {}
    for mid, (_name, dt, _names) in wanted.items():
        g0, g1 = np.searchsorted(gid_sorted, [mid, mid + 1])
        if g1 == g0:
            continue
        sel = good[by_id[g0:g1]]
        full = dt.itemsize
        p0 = pos[sel] + hlen[sel]
        pl = plen[sel]
        fits = p0 + full <= nb
        if full not in windows:
            windows[full] = np.lib.stride_tricks.sliding_window_view(b, full)
        if fits.all():
            raw = windows[full][p0]
        else:  # payloads near the end of the buffer (v2 truncated): gather byte by byte
            raw = np.empty((len(sel), full), dtype=np.uint8)
            raw[fits] = windows[full][p0[fits]]
            raw[~fits] = b[np.minimum(p0[~fits, None] + np.arange(full), nb - 1)]
        short = np.flatnonzero(pl < full)
        if len(short):  # v2 payloads truncated of trailing zeros: zero-pad (per truncated length)
            ls = pl[short]
            for n_kept in np.unique(ls).tolist():
                raw[short[ls == n_kept], n_kept:] = 0
        rec = raw.view(dt).ravel()
        if "ts" not in windows:  # big-endian u8 at every byte offset (unaligned view, no copy)
            windows["ts"] = np.ndarray((nb - 7,), dtype=">u8", buffer=b, strides=(1,))
        ps = pos[sel]
        v2 = isv2[sel]
        sink.take(mid, rec, windows["ts"][ps - 8], frame_no[sel], b[ps + np.where(v2, 5, 3)],
                  b[ps + np.where(v2, 6, 4)])
    sink.chunk_done()
