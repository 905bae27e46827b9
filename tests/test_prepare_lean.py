"""Issue 11: reading and preparing a long log without extra copies, the same results (issue 23:
the readings as stored and untruncated bit for bit, IEEE arithmetic on stored integers that no
CPU rounds differently; what recovery and segmentation compute within 1e-9 relative).

The untruncation works in place on a log ``prepare`` read itself; raw recovery and the
still-window statistics work a chunk of rows at a time. None of that may change a value:
these tests compare against the copying path and against one chunk covering everything.
"""
from __future__ import annotations

import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import mavcal.ardupilot.recover as recover_mod
import mavcal.sources.quantization as quant_mod
import mavcal.window_stats as stats_mod
from mavcal.ardupilot.recover import recover_raw
from mavcal.pipeline import Options, prepare
from mavcal.segment import StillConfig, find_still_intervals
from mavcal.sources.quantization import untruncate_log
from mavcal.sources.reader import read_log
from mavcal.sources.types import ImuLog, SensorSeries
from mavcal.testing.numbers import array_differences

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import biglogs  # noqa: E402

SITL = Path(__file__).resolve().parents[1] / "sitl_logs"


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit for bit: for readings as stored (decoded integers, the half step added)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    """Computed values (raw recovery, interval directions): within 1e-9 at each row's scale."""
    return a.dtype == b.dtype and array_differences(a, b, axis=-1) is None


def _assert_same_prepared(p, q) -> None:
    for a, b in zip(p.log.series, q.log.series):
        assert _same(a.values, b.values) and _same(a.time_s, b.time_s)
    for sensor in ("accel", "mag", "gyro"):
        for a, b in zip(getattr(p.raw, sensor), getattr(q.raw, sensor)):
            assert _close(a.values, b.values)
            assert a.extra.keys() == b.extra.keys()
            assert all(_close(a.extra[k], b.extra[k]) for k in a.extra)
    assert len(p.segmentation) == len(q.segmentation) > 0
    for u, v in zip(p.segmentation.intervals, q.segmentation.intervals):
        assert (u.start_s, u.end_s, u.pieces_s) == (v.start_s, v.end_s, v.pieces_s)
        assert _close(u.accel_dir, v.accel_dir)
        for k in u.accel_mps2:
            assert _close(u.accel_mps2[k], v.accel_mps2[k])
        for k in u.mag_mgauss:
            assert _close(u.mag_mgauss[k], v.mag_mgauss[k])
    assert p.warnings == q.warnings


def test_in_place_untruncation_equals_the_copy():
    path = SITL / "sitl02.tlog"
    copied, n_copied = untruncate_log(read_log(path))
    mine = read_log(path)
    before = [s.packed.counts for s in mine.series]  # a tlog's readings are stored packed
    done, n_done = untruncate_log(mine, in_place=True)
    assert done is mine and n_done == n_copied == len(mine.series)
    for a, b, arr in zip(copied.series, done.series, before):
        assert _same(a.values, b.values)
        assert b.packed.counts is arr  # the same integers, no second copy (only the half step set)
        assert not b.values.flags.writeable and not b.packed.counts.flags.writeable


def test_in_place_untruncation_copies_shared_or_foreign_values():
    v = np.array([[1.0, -2.0, 0.0], [3.0, 0.0, -1.0]])
    t = np.array([0.0, 0.1])
    shared = ImuLog("x", "tlog", (SensorSeries("accel", 0, "RAW_IMU", t, v), SensorSeries("mag", 0, "RAW_IMU", t, v)))
    out, n = untruncate_log(shared, in_place=True)
    assert n == 2 and out is not shared
    assert np.array_equal(shared.series[0].values, v)  # the shared array is left alone
    assert np.array_equal(out.series[1].values, v + 0.5 * np.sign(v))
    big = np.array([[1.0, -2.0, 0.0], [3.0, 0.0, -1.0], [5.0, 5.0, 5.0]])
    part = ImuLog("x", "tlog", (SensorSeries("mag", 0, "RAW_IMU", t, big[:2]),))  # a slice of a larger array
    out, n = untruncate_log(part, in_place=True)
    assert n == 1 and np.array_equal(big[:2], v) and np.array_equal(out.series[0].values, v + 0.5 * np.sign(v))


def test_prepare_of_a_path_equals_prepare_of_its_log_and_leaves_a_given_log_alone():
    path = SITL / "sitl02.tlog"
    given = read_log(path)
    kept = [np.array(s.values) for s in given.series]
    _assert_same_prepared(prepare(path), prepare(given))
    for s, k in zip(given.series, kept):
        assert _same(s.values, k)


def test_prepare_of_an_owned_log_untruncates_in_its_own_arrays_with_the_same_result():
    """``owned=True`` (what ``mavcal calibrate`` and ``segments`` pass): no copy of the series'
    readings, the receive times dropped, and every value equals the copying path's."""
    path = SITL / "sitl02.tlog"
    handed = read_log(path)
    arrays = [s.packed.counts for s in handed.series]  # a tlog's readings are stored packed
    times = [s.time_s for s in handed.series]
    assert all(s.log_time_s is not None for s in handed.series)
    mine = prepare(handed, owned=True)
    assert [(s.sensor, s.instance) for s in mine.log.series] == [(s.sensor, s.instance) for s in handed.series]
    assert all(s.packed.counts is a for s, a in zip(mine.log.series, arrays))
    assert all(s.time_s is t for s, t in zip(mine.log.series, times))
    raw = mine.raw.accel + mine.raw.mag + mine.raw.gyro
    assert all(s.log_time_s is None for s in mine.log.series + raw)
    assert all(s.log_time_s is not None for s in prepare(read_log(path)).log.series)  # kept when not owned
    as_read = read_log(path)
    assert any(not _same(s.values, r.values) for s, r in zip(mine.log.series, as_read.series))  # changed in place
    _assert_same_prepared(mine, prepare(as_read))


@pytest.mark.parametrize("window_s", [0.5, 2.0])
def test_chunked_statistics_are_the_same(monkeypatch, window_s):
    """Tiny chunks (and windows longer than a chunk) give exactly what one chunk gives."""
    path = SITL / "sitl02.tlog"
    opts = Options(still=StillConfig(window_s=window_s, min_duration_s=max(1.5, window_s)))
    monkeypatch.setattr(stats_mod, "CHUNK", 10**9)
    monkeypatch.setattr(recover_mod, "_CHUNK_ROWS", 10**9)
    monkeypatch.setattr(quant_mod, "_CHUNK_ROWS", 10**9)
    whole = prepare(path, opts)
    monkeypatch.setattr(stats_mod, "CHUNK", 37)
    monkeypatch.setattr(recover_mod, "_CHUNK_ROWS", 53)
    monkeypatch.setattr(quant_mod, "_CHUNK_ROWS", 11)
    assert whole.segmentation.window_samples > 37 or window_s < 1  # windows longer than a chunk too
    _assert_same_prepared(whole, prepare(path, opts))


@pytest.mark.parametrize("w", [3, 50, 200])
def test_chunked_window_deviation_is_the_full_length_formula(monkeypatch, w):
    """The sliding standard deviation, a chunk at a time, equals the full-length expression (within 1e-9)."""
    x = np.random.default_rng(3).normal(9.0, 0.3, size=(1000, 3))
    c1 = np.vstack([np.zeros((1, 3)), np.cumsum(x, axis=0)])  # the former full-length computation
    c2 = np.vstack([np.zeros((1, 3)), np.cumsum(x * x, axis=0)])
    m = (c1[w:] - c1[:-w]) / w
    ref = np.sqrt(np.maximum((c2[w:] - c2[:-w]) / w - m * m, 0.0)).max(axis=1)
    sd_max = stats_mod.rolling_sd_max
    for chunk in (64, 101, 10**6):
        monkeypatch.setattr(stats_mod, "CHUNK", chunk)
        assert _close(sd_max(x, w), ref)


def _prepare_stage_memory(path):
    """Traced heap peaks (bytes) of the untruncation, the raw recovery beyond its result and
    the segmentation, and the accel-0 sample count."""
    log = read_log(path)
    tracemalloc.start()
    try:
        log, _ = untruncate_log(log, in_place=True)
        _, untruncate_peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        raw = recover_raw(log)
        after, peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        find_still_intervals(raw)
        _, seg_peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return untruncate_peak, peak - after, seg_peak - after, len(raw.accel[0])


def test_prepare_working_memory_is_bounded_by_chunks(tmp_path, monkeypatch):
    """Beyond their results, the untruncation and the raw recovery hold a chunk's work and the
    segmentation a few bytes per sample (the full-length version: hundreds)."""
    for mod, name in ((stats_mod, "CHUNK"), (recover_mod, "_CHUNK_ROWS"), (quant_mod, "_CHUNK_ROWS")):
        monkeypatch.setattr(mod, name, 4096)
    small, big = tmp_path / "s.tlog", tmp_path / "b.tlog"
    biglogs.build_tlog(small, 2e6)
    biglogs.build_tlog(big, 12e6)
    u_s, r_s, s_s, n_s = _prepare_stage_memory(small)
    u_b, r_b, s_b, n_b = _prepare_stage_memory(big)
    assert n_b > 5 * n_s
    assert max(u_s, u_b) < 4096 * 3 * 8 * 2  # one chunk of one series
    assert max(r_s, r_b) < 1 << 20  # a few chunks of temporaries, whatever the length
    assert (s_b - s_s) / (n_b - n_s) < 32  # bytes per accel-0 sample (the accel samples alone: 24)
