"""The vectorised log decoders: chunk invariance, memory that does not grow with the file,
the shared framing helpers, and the benchmark log builders (time-shifted copies)."""
from __future__ import annotations

import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from mavcal.sources import read_log
from mavcal.sources.fast_dataflash import decode_dataflash
from mavcal.sources.fast_tlog import crc_x25, decode_tlog
from mavcal.sources.framing import ColumnBuffer, file_chunks, mark_path, path_from
from mavcal.sources.reader import DATAFLASH_MESSAGES, TLOG_MESSAGES

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import biglogs  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SITL02 = REPO / "sitl_logs" / "sitl02.tlog"
REAL = REPO.parent / "shared" / "data" / "real"
needs_real = pytest.mark.skipif(not (REAL / "00000124.BIN").is_file(), reason="real logs not available")


def assert_same_columns(a, b):
    assert list(a) == list(b)
    for name in a:
        assert list(a[name]) == list(b[name]), name
        for k in a[name]:
            x, y = a[name][k], b[name][k]
            assert x.dtype == y.dtype and x.shape == y.shape, (name, k)
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), (name, k)


def test_column_buffer_equals_concatenation():
    rng = np.random.default_rng(0)
    buf = ColumnBuffer()
    pieces = []
    for m in (1, 3000, 0, 5000, 17, 9000):  # several growths of the maps
        p = {"t": rng.random(m), "i": rng.integers(0, 99, m).astype(np.int16),
             "v": rng.integers(-5, 5, (m, 3)).astype(np.int8), "s": rng.choice([b"a", b"bc", b""], m).astype("S2")}
        pieces.append(p)
        buf.append(p)
    assert buf.n == sum(len(p["t"]) for p in pieces)
    cols = buf.columns()
    assert buf.n == 0
    for k in pieces[0]:
        want = np.concatenate([p[k] for p in pieces])
        assert cols[k].dtype == want.dtype and cols[k].shape == want.shape
        np.testing.assert_array_equal(cols[k], want)
    cols["t"][0] = -1.0  # writable, independent arrays
    assert cols["t"][0] == -1.0


def test_path_contraction_matches_pointer_doubling_on_long_chains():
    rng = np.random.default_rng(5)
    for n in (1, 2, 1000, 50_000):
        step = np.where(rng.random(n) < 0.95, 1, rng.integers(1, 40, n))
        succ = np.minimum(np.arange(n) + step, n)
        for start in (0, n // 3, n - 1, n):
            np.testing.assert_array_equal(path_from(succ, start), mark_path(succ, start))


def test_file_chunks_cover_the_file_with_context(tmp_path):
    data = np.arange(1000, dtype=np.uint32).astype(np.uint8).tobytes()
    p = tmp_path / "x.bin"
    p.write_bytes(data)
    ends = []
    with open(p, "rb") as fh:
        for base, start, end, b in file_chunks(fh, len(data), 300, 8, 20):
            assert base == max(start - 8, 0)
            assert b.tobytes() == data[base:min(end + 20, len(data))]
            ends.append((start, end))
    assert ends == [(0, 300), (300, 600), (600, 900), (900, 1000)]


@pytest.mark.parametrize("chunk", [4096, 65_536, 1 << 20])
def test_tlog_decode_does_not_depend_on_chunks(chunk):
    ref, ref_stats = decode_tlog(str(SITL02), TLOG_MESSAGES)
    got, stats = decode_tlog(str(SITL02), TLOG_MESSAGES, chunk_size=chunk)
    assert_same_columns(ref, got)
    assert vars(stats) == vars(ref_stats)
    assert stats.frames > 20_000 and len(got["RAW_IMU"]["_index"]) == 5665


def test_corrupt_tlog_decode_does_not_depend_on_chunks(tmp_path):
    d = bytearray(SITL02.read_bytes())
    rng = np.random.default_rng(7)
    for i in sorted(rng.integers(0, len(d) - 400, 60).tolist(), reverse=True):
        if i % 2:
            d[i] ^= 0x5A
        else:
            del d[i:i + int(rng.integers(1, 300))]
    p = tmp_path / "bad.tlog"
    p.write_bytes(bytes(d))
    ref, ref_stats = decode_tlog(str(p), TLOG_MESSAGES)
    got, stats = decode_tlog(str(p), TLOG_MESSAGES, chunk_size=5000)
    assert_same_columns(ref, got)
    assert vars(stats) == vars(ref_stats)
    assert ref_stats.skipped_bytes > 0 and ref_stats.bad_crc > 0


@needs_real
@pytest.mark.parametrize("name", ["00000124.BIN", "log171.bin"])
def test_dataflash_decode_does_not_depend_on_chunks(name):
    ref, ref_fmt, ref_stats = decode_dataflash(str(REAL / name), DATAFLASH_MESSAGES)
    got, fmt, stats = decode_dataflash(str(REAL / name), DATAFLASH_MESSAGES, chunk_size=7000)
    assert_same_columns(ref, got)
    assert fmt == ref_fmt and vars(stats) == vars(ref_stats)
    assert len(got["IMU"]["_index"]) > 1000


def _traced_peak(fn):
    tracemalloc.start()
    try:
        out = fn()
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_tlog_working_memory_does_not_grow_with_the_file(tmp_path):
    small, big = tmp_path / "s.tlog", tmp_path / "b.tlog"
    biglogs.build_tlog(small, 2e6)
    biglogs.build_tlog(big, 12e6)
    chunk = 1 << 20
    (cs, _), peak_s = _traced_peak(lambda: decode_tlog(str(small), TLOG_MESSAGES, chunk_size=chunk))
    (cb, _), peak_b = _traced_peak(lambda: decode_tlog(str(big), TLOG_MESSAGES, chunk_size=chunk))
    col_bytes = sum(a.nbytes for c in cb.values() for a in c.values())
    assert len(cb["RAW_IMU"]["_index"]) == 6 * len(cs["RAW_IMU"]["_index"])
    # the columns live in memory maps; the heap holds only a chunk's work, whatever the file size
    assert col_bytes > 9e6
    assert peak_b < 1.3 * peak_s + 1e6
    assert peak_b < 16 * chunk


@needs_real
def test_dataflash_working_memory_does_not_grow_with_the_file(tmp_path):
    small, big = tmp_path / "s.bin", tmp_path / "b.bin"
    biglogs.build_bin(small, 4e6)
    biglogs.build_bin(big, 16e6)
    chunk = 1 << 20
    (cs, _, _), peak_s = _traced_peak(lambda: decode_dataflash(str(small), DATAFLASH_MESSAGES, chunk_size=chunk))
    (cb, _, _), peak_b = _traced_peak(lambda: decode_dataflash(str(big), DATAFLASH_MESSAGES, chunk_size=chunk))
    assert len(cb["IMU"]["TimeUS"]) == 4 * len(cs["IMU"]["TimeUS"])
    assert peak_b < 1.3 * peak_s + 1e6
    assert peak_b < 16 * chunk


def test_tlog_copies_follow_each_other_and_keep_every_sample(tmp_path):
    p = tmp_path / "three.tlog"
    assert biglogs.build_tlog(p, 3 * SITL02.stat().st_size) == 3
    cols, stats = decode_tlog(str(p), ["RAW_IMU", "SCALED_IMU2", "ATTITUDE"], check_all_crc=True)
    assert stats.bad_crc == 0 and stats.skipped_bytes == 0
    one, _ = decode_tlog(str(SITL02), ["RAW_IMU", "SCALED_IMU2", "ATTITUDE"])
    for name, field in (("RAW_IMU", "time_usec"), ("SCALED_IMU2", "time_boot_ms"), ("ATTITUDE", "time_boot_ms")):
        n = len(one[name][field])
        assert len(cols[name][field]) == 3 * n
        t = cols[name][field].astype(np.int64)
        assert t[n] > t[n - 1] and t[2 * n] > t[2 * n - 1]
        assert np.all(np.diff(cols[name]["_log_time_s"]) >= 0)
        np.testing.assert_array_equal(cols[name]["xacc" if "IMU" in name else "roll"][n:2 * n],
                                      one[name]["xacc" if "IMU" in name else "roll"])
    lg1, lg3 = read_log(SITL02), read_log(p)
    acc1 = [len(s) for s in lg1.series if s.sensor == "accel"]
    assert [len(s) for s in lg3.series if s.sensor == "accel"] == [3 * k for k in acc1]


@needs_real
def test_bin_copies_follow_each_other_and_keep_every_sample(tmp_path):
    src = REAL / "00000124.BIN"
    p = tmp_path / "two.bin"
    assert biglogs.build_bin(p, 1.5 * src.stat().st_size) == 2
    cols, _, stats = decode_dataflash(str(p), ["IMU", "MAG", "BARO"])
    one, _, _ = decode_dataflash(str(src), ["IMU", "MAG", "BARO"])
    assert stats.skipped_bytes == 0 and stats.truncated == 0  # whole records only
    for name in ("IMU", "MAG", "BARO"):
        n = len(one[name]["TimeUS"])
        t = cols[name]["TimeUS"]
        assert len(t) == 2 * n and t[n] > t[:n].max()
        np.testing.assert_array_equal(t[n:] - t[:n], np.full(n, t[n] - t[0]))
    np.testing.assert_array_equal(cols["BARO"]["SMS"][n:] - cols["BARO"]["SMS"][:n],
                                  np.full(n, (cols["BARO"]["TimeUS"][n] - cols["BARO"]["TimeUS"][0]) // 1000))
    lg1, lg2 = read_log(src), read_log(p)
    assert [len(s) for s in lg2.series] == [2 * len(s) for s in lg1.series]


def test_crc_x25_equals_pymavlink_for_every_length_and_offset():
    """Word-at-a-time CRC gathered straight from the bytes: every length parity (0 included),
    unaligned starts, frames ending at the last byte."""
    from pymavlink.mavutil import x25crc

    rng = np.random.default_rng(0)
    data = rng.integers(0, 256, 3000).astype(np.uint8)
    lengths = np.r_[np.arange(0, 300), rng.integers(0, 300, 700), [5, 6]]
    starts = np.r_[rng.integers(0, 2700, 1000), [len(data) - 5, len(data) - 6]]
    extra = rng.integers(0, 256, len(starts)).astype(np.uint8)
    got = crc_x25(data, starts, lengths, extra)
    for s, n, e, c in zip(starts.tolist(), lengths.tolist(), extra.tolist(), got.tolist()):
        ref = x25crc(bytes(data[s:s + n]))
        ref.accumulate(bytes([e]))
        assert c == ref.crc, (s, n)
