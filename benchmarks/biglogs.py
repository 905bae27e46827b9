"""Deterministic big logs for benchmarks: N time-shifted copies of a real log.

Plain concatenation of a log repeats its timestamps, so a reader that sorts/deduplicates
by time keeps one copy and the benchmark measures nothing. These builders shift every time
field of copy ``k`` by ``k * span`` (``span`` = the widest range of any time field + 1 s) so the
copies follow each other and every sample of every copy is kept.

* :func:`build_bin`: copies of a DataFlash log (default ``00000124.BIN``). Only whole records
  are copied (a source cut off mid-record would otherwise leave garbage between copies,
  which DataFlash readers report as "bad header"). Shifted: the boot-time fields
  ``TimeUS``, ``SampleUS``, ``RTimeUS``, ``US`` (µs, uint64) and ``TimeMS``, ``SMS``,
  ``CTimeMS``, ``LastMeasMS`` (ms, uint32) of every record type that has them. GPS-week
  times (GMS/GWk) are not boot times and are left alone.
* :func:`build_tlog`: copies of a tlog (default ``sitl_logs/sitl02.tlog``). Shifted: the
  8-byte big-endian receive timestamp of every frame and each message's ``time_usec``
  (µs) and ``time_boot_ms`` (ms); the CRC of every patched frame is recomputed (with the
  message's CRC_EXTRA), so pymavlink reads the result without a single bad CRC.

Both write the file in whole copies until it reaches ``size_bytes`` (at least one copy) and
return the number of copies. Same inputs -> byte-identical output.

* :func:`build_intervals_tlog`: a simulated hand-held session (:mod:`mavcal.testing.simlog`)
  with ``n`` random poses held 2 s each, 0.8 s of motion between, 25 Hz: a log of about ``n``
  still intervals, for the cost against the interval count at a small size per interval.

    python benchmarks/biglogs.py tlog /tmp/big.tlog 100e6
    python benchmarks/biglogs.py intervals /tmp/n2000.tlog 2000
"""
from __future__ import annotations

import re
import struct
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from pymavlink.dialects.v20 import all as dialect  # noqa: E402

from mavcal.sources.fast_tlog import crc_x25  # noqa: E402

DEFAULT_BIN = REPO.parent / "shared" / "data" / "real" / "00000124.BIN"
DEFAULT_TLOG = REPO / "sitl_logs" / "sitl02.tlog"

#: DataFlash boot-time fields: name -> (format char, microseconds per unit)
DF_TIME_FIELDS = {"TimeUS": ("Q", 1), "SampleUS": ("Q", 1), "RTimeUS": ("Q", 1), "US": ("Q", 1),
                  "TimeMS": ("I", 1000), "SMS": ("I", 1000), "CTimeMS": ("I", 1000), "LastMeasMS": ("I", 1000)}
#: MAVLink message time fields: name -> microseconds per unit
TLOG_TIME_FIELDS = {"time_usec": 1, "time_boot_ms": 1000}
_DF_SIZES = {"a": 64, "b": 1, "B": 1, "g": 2, "h": 2, "H": 2, "i": 4, "I": 4, "f": 4, "n": 4, "N": 16, "Z": 64,
             "c": 2, "C": 2, "e": 4, "E": 4, "L": 4, "d": 8, "M": 1, "q": 8, "Q": 8}
_GAP_US = 1_000_000

# a time site: byte offsets of one field in the file, its width/endianness and its unit
Site = tuple[np.ndarray, str, int]


def _shift_sites(buf: np.ndarray, sites: list[Site], shift_us: int) -> None:
    """Add ``shift_us`` (converted to each site's unit) to every time field of ``buf`` in place."""
    for offsets, dtype, unit_us in sites:
        width = np.dtype(dtype).itemsize
        idx = offsets[:, None] + np.arange(width)
        vals = np.ascontiguousarray(buf[idx]).view(dtype).ravel()
        vals = vals + np.array(shift_us // unit_us, dtype=vals.dtype)
        buf[idx] = vals.astype(dtype).view(np.uint8).reshape(-1, width)


def _span_us(data: np.ndarray, sites: list[Site]) -> int:
    """Shift between copies: more than the range of every time field (each site is one field)."""
    rng = 0
    for offsets, dtype, unit_us in sites:
        if len(offsets):
            v = np.ascontiguousarray(data[offsets[:, None] + np.arange(np.dtype(dtype).itemsize)]).view(dtype)
            rng = max(rng, (int(v.max()) - int(v.min())) * unit_us)
    return rng + _GAP_US


def _write_copies(dst: Path, data: np.ndarray, sites: list[Site], span_us: int, size_bytes: float,
                  fix=None) -> int:
    copies = max(1, int(-(-size_bytes // len(data))))
    span_us = -(-span_us // 1000) * 1000  # whole milliseconds: ms fields shift exactly as µs fields
    with open(dst, "wb") as fh:
        for k in range(copies):
            buf = data.copy()
            if k:
                _shift_sites(buf, sites, k * span_us)
                if fix is not None:
                    fix(buf)
            fh.write(buf.tobytes())
    return copies


# --------------------------------------------------------------------------- DataFlash

def _df_records(data: bytes) -> tuple[list[tuple[int, int]], dict[int, tuple[str, str, list[str]]], int]:
    """Walk a clean DataFlash log: (pos, type) of each whole record, the formats, and the end."""
    fmt_cols = ["Type", "Length", "Name", "Format", "Columns"]
    formats: dict[int, tuple[str, str, list[str]]] = {0x80: ("FMT", "BBnNZ", fmt_cols)}
    lengths = {0x80: 89}
    recs = []
    p = 0
    n = len(data)
    while p + 3 <= n:
        if data[p] != 0xA3 or data[p + 1] != 0x95 or data[p + 2] not in lengths:
            raise ValueError(f"DataFlash source is not clean at byte {p}")
        t = data[p + 2]
        if p + lengths[t] > n:
            break  # truncated last record: not copied
        if t == 0x80:
            typ, ln = data[p + 3], data[p + 4]
            name, fmt, cols = (data[p + a:p + b].split(b"\0", 1)[0].decode() for a, b in ((5, 9), (9, 25), (25, 89)))
            formats[typ] = (name, fmt, cols.split(","))
            lengths[typ] = ln
        recs.append((p, t))
        p += lengths[t]
    return recs, formats, p


def _df_sites(recs, formats) -> list[Site]:
    by_key: dict[tuple[int, int, str, int], list[int]] = {}
    field_offsets: dict[int, list[tuple[int, str, int]]] = {}
    for t, (_, fmt, cols) in formats.items():
        offs, o = [], 3
        for ch, col in zip(fmt, cols):
            if col in DF_TIME_FIELDS and DF_TIME_FIELDS[col][0] == ch:
                offs.append((o, "<u8" if ch == "Q" else "<u4", DF_TIME_FIELDS[col][1]))
            o += _DF_SIZES[ch]
        field_offsets[t] = offs
    for p, t in recs:
        for o, dt, unit in field_offsets.get(t, ()):
            by_key.setdefault((t, o, dt, unit), []).append(p + o)
    return [(np.array(v, dtype=np.int64), dt, unit) for (_, _, dt, unit), v in sorted(by_key.items())]


def build_bin(dst: Path, size_bytes: float, src: Path = DEFAULT_BIN) -> int:
    """Write ``ceil(size_bytes / source)`` time-shifted copies of the DataFlash log ``src`` to ``dst``."""
    raw = Path(src).read_bytes()
    recs, formats, end = _df_records(raw)
    data = np.frombuffer(raw[:end], dtype=np.uint8)
    sites = _df_sites(recs, formats)
    return _write_copies(Path(dst), data, sites, _span_us(data, sites), size_bytes)


# --------------------------------------------------------------------------- tlog

def _tlog_frames(data: bytes):
    """Walk a clean tlog: (record pos, frame pos, msgid, header length, payload length, frame length)."""
    out = []
    p = 0
    while p + 8 + 3 <= len(data):
        f = p + 8
        stx, plen = data[f], data[f + 1]
        if stx == 0xFD:
            hlen, sig = 10, 13 if data[f + 2] & 1 else 0
            msgid = data[f + 7] | data[f + 8] << 8 | data[f + 9] << 16
        elif stx == 0xFE:
            hlen, sig, msgid = 6, 0, data[f + 5]
        else:
            raise ValueError(f"tlog source is not clean at byte {p}")
        flen = hlen + plen + 2 + sig
        if f + flen > len(data):
            break
        out.append((p, f, msgid, hlen, plen, flen))
        p = f + flen
    return out, p


def _field_offsets(msgid: int) -> list[tuple[int, str, int]]:
    cls = dialect.mavlink_map.get(msgid)
    if cls is None:
        return []
    fmt = cls.unpacker.format
    fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
    out, o = [], 0
    for name, code in zip(cls.ordered_fieldnames, _struct_codes(fmt[1:])):
        width = struct.calcsize("<" + code)
        if name in TLOG_TIME_FIELDS and code in ("Q", "I"):
            out.append((o, "<u8" if code == "Q" else "<u4", TLOG_TIME_FIELDS[name]))
        o += width
    return out


def _struct_codes(fmt: str) -> list[str]:
    return [c + t for c, t in re.findall(r"(\d*)([a-zA-Z?])", fmt)]


def build_tlog(dst: Path, size_bytes: float, src: Path = DEFAULT_TLOG) -> int:
    """Write ``ceil(size_bytes / source)`` time-shifted copies of the tlog ``src`` to ``dst``."""
    raw = Path(src).read_bytes()
    frames, end = _tlog_frames(raw)
    data = np.frombuffer(raw[:end], dtype=np.uint8)
    by_key: dict[tuple[int, int, str, int], list[int]] = {(-1, 0, ">u8", 1): [r[0] for r in frames]}
    patched = []
    offsets_of: dict[int, list[tuple[int, str, int]]] = {}
    for _rec, f, msgid, hlen, plen, _flen in frames:
        if msgid not in offsets_of:
            offsets_of[msgid] = _field_offsets(msgid)
        hit = False
        for o, dt, unit in offsets_of[msgid]:
            if o + np.dtype(dt).itemsize <= plen:  # a v2 payload may be truncated of trailing zeros
                by_key.setdefault((msgid, o, dt, unit), []).append(f + hlen + o)
                hit = True
        if hit:
            patched.append((f, hlen, plen, dialect.mavlink_map[msgid].crc_extra))
    sites = [(np.array(v, dtype=np.int64), dt, unit) for (_, _, dt, unit), v in sorted(by_key.items())]
    pf = np.array(patched, dtype=np.int64).reshape(-1, 4)
    starts, lengths, extra = pf[:, 0] + 1, pf[:, 1] - 1 + pf[:, 2], pf[:, 3].astype(np.uint16)
    crc_at = pf[:, 0] + pf[:, 1] + pf[:, 2]
    span = _span_us(data, sites)

    def fix(buf: np.ndarray) -> None:
        crc = crc_x25(buf, starts, lengths, extra)
        buf[crc_at] = (crc & 0xFF).astype(np.uint8)
        buf[crc_at + 1] = (crc >> 8).astype(np.uint8)

    return _write_copies(Path(dst), data, sites, span, size_bytes, fix)


def build_intervals_tlog(dst: Path, n_intervals: int, seed: int = 0) -> int:
    """Write a simulated session of ``n_intervals`` random poses (each held 2 s) to ``dst``;
    returns ``n_intervals``. Deterministic for a given seed."""
    from mavcal.testing.simlog import SimConfig, simulate_session

    rng = np.random.default_rng(seed)
    n = int(n_intervals)
    poses = tuple(zip(rng.uniform(-180, 180, n).tolist(), rng.uniform(-80, 80, n).tolist(),
                      rng.uniform(-180, 180, n).tolist()))
    simulate_session(SimConfig(poses_deg=poses, hold_s=2.0, move_s=0.8, rate_hz=25.0, seed=seed + 1), tlog=dst)
    return n


def main(argv=None) -> int:
    kind, dst, size = (argv or sys.argv[1:])[:3]
    if kind == "intervals":
        build_intervals_tlog(Path(dst), int(float(size)))
        print(f"{dst}: {int(float(size))} poses, {Path(dst).stat().st_size / 1e6:.1f} MB")
        return 0
    n = (build_tlog if kind == "tlog" else build_bin)(Path(dst), float(size))
    print(f"{dst}: {n} copies, {Path(dst).stat().st_size / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
