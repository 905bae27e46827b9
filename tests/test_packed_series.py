"""Packed tlog readings: int16 telemetry stored, float64 values computed on access, bit for bit.

A tlog's IMU readings are int16 integers times a unit (``mavcal.sources.quantization.TRUNCATED_UNITS``);
the reader keeps the integers (:class:`~mavcal.sources.types.PackedValues`, a quarter of the
float64 memory) and every access computes the values the float path gave. Untruncating only
sets the half step.
"""
from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest

from mavcal.pipeline import prepare
from mavcal.sources.assemble import MG_TO_MS2, TLOG_MESSAGES
from mavcal.sources.fast_tlog import decode_tlog
from mavcal.sources.quantization import TRUNCATED_UNITS, untruncate, untruncate_log
from mavcal.sources.reader import read_log
from mavcal.sources.types import ImuLog, PackedValues, SensorSeries

SITL = Path(__file__).resolve().parents[1] / "sitl_logs"
#: the reader's arithmetic per sensor (value = count * mul / div) and the float path it replaces
UNITS = {"accel": (MG_TO_MS2, 1.0), "gyro": (1.0, 1000.0), "mag": (1.0, 1.0)}


def _float_path(sensor: str, counts: np.ndarray) -> np.ndarray:
    """What the reader computed before: the integers cast to float64, then ``*= MG_TO_MS2`` (accel)
    or ``/= 1000.0`` (gyro)."""
    v = counts.astype(np.float64)
    if sensor == "accel":
        v *= MG_TO_MS2
    elif sensor == "gyro":
        v /= 1000.0
    return v


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _counts(n: int = 5000) -> np.ndarray:
    rng = np.random.default_rng(11)
    c = rng.integers(-32768, 32768, size=(n, 3)).astype(np.int16)
    c[:8] = [[0, 0, 0], [1, -1, 0], [-32768, 32767, 0], [999, -999, 1000], [-1000, 1, -1],
             [9807, -9806, 9806], [32767, 32767, 32767], [-32768, -32768, -32768]]
    return c


def _series(sensor: str, values) -> SensorSeries:
    n = len(values)
    return SensorSeries(sensor, 0, "RAW_IMU", np.arange(n) * 0.01, values, np.arange(n) * 0.01 + 1e9)


@pytest.mark.parametrize("sensor", ["accel", "gyro", "mag"])
def test_packed_values_are_the_float_path_bit_for_bit(sensor, monkeypatch):
    c = _counts()
    ref = _series(sensor, _float_path(sensor, c))
    p = _series(sensor, PackedValues(c, *UNITS[sensor]))
    assert _same(p.values, ref.values) and p.values.dtype == np.float64
    assert not p.values.flags.writeable
    q = TRUNCATED_UNITS["RAW_IMU"][sensor]
    u, ref_u = untruncate(p), untruncate(ref)
    assert u.packed is not None and u.packed.counts is p.packed.counts  # only the half step set
    assert u.packed.half_step == 0.5 * q and p.packed.half_step == 0.0  # the original is left alone
    assert _same(u.values, ref_u.values)
    assert _same(u.values, ref.values + 0.5 * q * np.sign(ref.values))
    assert _same(untruncate(u).values, untruncate(ref_u).values)  # a second untruncation as on floats
    import mavcal.sources.types as types_mod

    monkeypatch.setattr(types_mod, "_DECODE_ROWS", 7)  # block boundaries change nothing
    assert _same(u.values, ref_u.values) and _same(p.values, ref.values)


@pytest.mark.parametrize("rows", [slice(None), slice(10, 300), slice(None, None, 7), slice(4990, 6000),
                                  np.array([3, 1, 4, 1, 5, 4999])])
def test_values_at_computes_the_rows_of_values(rows):
    c = _counts()
    for s in (untruncate(_series("accel", PackedValues(c, MG_TO_MS2))), _series("gyro", _float_path("gyro", c))):
        assert _same(np.ascontiguousarray(s.values_at(rows)), s.values[rows])


def test_values_are_computed_on_access_not_kept():
    s = _series("accel", PackedValues(_counts(), MG_TO_MS2))
    a, b = s.values, s.values
    assert a is not b and _same(a, b)
    assert not any(isinstance(v, np.ndarray) and v.dtype == np.float64 and v.shape == a.shape
                   for v in vars(s).values())  # nothing float64 of the values' size is held
    f = _series("accel", np.ones((10, 3)))
    assert f.values is f.values and f.packed is None  # float values are the stored array


def test_replace_keeps_working_and_the_series_stays_frozen():
    c = _counts(100)
    s = _series("gyro", PackedValues(c, 1.0, 1000.0))
    moved = dataclasses.replace(s, time_s=s.time_s + 5.0)  # other fields: the integers are kept
    assert moved.packed is not None and moved.packed.counts is s.packed.counts
    assert _same(moved.values, s.values) and _same(moved.time_s, s.time_s + 5.0)
    floats = dataclasses.replace(s, values=s.values * 2.0)
    assert floats.packed is None and _same(floats.values, s.values * 2.0)
    repacked = dataclasses.replace(floats, values=PackedValues(c, 1.0, 1000.0))
    assert repacked.packed is not None and _same(repacked.values, s.values)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.values = np.zeros((100, 3))  # type: ignore[misc]
    with pytest.raises(ValueError):
        dataclasses.replace(s, values=np.zeros((99, 3)))  # wrong length
    with pytest.raises(ValueError):
        PackedValues(np.zeros((3, 3)))  # floats are not integer readings
    back = pickle.loads(pickle.dumps(s))
    assert back.packed is not None and _same(back.values, s.values)


def test_any_nonzero_reads_the_integers():
    z = np.zeros((500, 3), dtype=np.int16)
    assert not _series("mag", PackedValues(z)).any_nonzero()
    z[499, 1] = -1
    assert _series("mag", PackedValues(z)).any_nonzero()
    assert untruncate(_series("mag", PackedValues(z))).any_nonzero()


def test_in_place_untruncation_sets_the_half_step_of_the_series_itself():
    c = _counts(200)
    log = ImuLog("x", "tlog", (_series("accel", PackedValues(c, MG_TO_MS2)), _series("mag", PackedValues(c))))
    kept = [s.values for s in log.series]
    out, n = untruncate_log(log, in_place=False)  # a copy: the log handed in is left as read
    assert n == 2 and out is not log and all(s.packed.half_step == 0.0 for s in log.series)
    assert all(_same(s.values, k) for s, k in zip(log.series, kept))
    done, n = untruncate_log(log, in_place=True)
    assert n == 2 and done is log
    for s, u, k in zip(log.series, out.series, kept):
        assert s.packed.counts is u.packed.counts and _same(s.values, u.values) and not _same(s.values, k)
    with pytest.raises(ValueError):
        log.series[0].mark_untruncated(0.5)  # once only


@pytest.mark.parametrize("name", ["sitl01.tlog", "sitl02.tlog"])
def test_a_read_tlog_stores_int16_and_computes_the_former_floats(name):
    """The tlog series hold int16 (6 bytes a row instead of 24) and give the values the float
    reader gave (RAW_IMU from the message columns with the former arithmetic)."""
    path = SITL / name
    log = read_log(path)
    for s in log.series:
        assert s.packed is not None and s.packed.counts.dtype == np.int16
        assert s.packed.nbytes == 6 * len(s) and s.values.nbytes == 24 * len(s)
    cols, _ = decode_tlog(str(path), TLOG_MESSAGES)
    raw = cols["RAW_IMU"]
    for sensor, names in (("accel", ("xacc", "yacc", "zacc")), ("gyro", ("xgyro", "ygyro", "zgyro")),
                          ("mag", ("xmag", "ymag", "zmag"))):
        s = log.get(sensor, 0)
        c = np.stack([np.asarray(raw[k]) for k in names], axis=1)
        c = c[(c != 0).any(axis=1)] if sensor == "mag" else c
        assert len(c) == len(s)  # (no dropped or repeated row in these logs)
        assert _same(s.values, _float_path(sensor, c))


def test_prepare_keeps_the_logged_series_packed():
    prep = prepare(SITL / "sitl02.tlog")
    assert all(s.packed is not None and s.packed.untruncated for s in prep.log.series)
    assert all(g.packed is not None for g in prep.raw.gyro)  # the logged gyro itself
    assert all(s.packed is None for s in prep.raw.accel + prep.raw.mag)  # recovered: new floats
