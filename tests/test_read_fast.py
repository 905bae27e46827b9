"""The lean tlog path (integer IMU messages decoded straight into their final arrays, time base
built while reading) gives the same ImuLog as the column path, bit for bit."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from mavcal.sources import quantization as quant
from mavcal.sources import tlog_imu
from mavcal.sources.assemble import TLOG_MESSAGES, assemble_tlog
from mavcal.sources.fast_tlog import decode_tlog
from mavcal.sources.framing import GrowArray, owned_map_of
from mavcal.sources.reader import read_log

ROOT = Path(__file__).resolve().parents[1]
SITL = sorted((ROOT / "sitl_logs").glob("*.tlog"))


def _tlog(path: Path, *, n: int = 1500, reboots=(), sysids=(1,), raw_from: int = 0, raw: bool = True,
          scaled: bool = True, zero_rows=(), dup_rows=(), imu2_zero: bool = True, highres: bool = True) -> Path:
    """A tlog of RAW_IMU / SCALED_IMU / SCALED_IMU2 / HIGHRES_IMU with parameters, texts and heartbeats."""
    from pymavlink.dialects.v20 import all as mav

    rng = np.random.default_rng(7)
    links = {s: mav.MAVLink(None, srcSystem=s, srcComponent=1) for s in sysids}
    out = bytearray()

    def send(s, msg, t_us):
        out.extend(struct.pack(">Q", int(t_us)) + msg.pack(links[s]))

    def i16(x):
        return int(np.clip(x, -32768, 32767))

    boot = 5000
    for i in range(n):
        if i in reboots:
            boot = 3000 + i
        boot += 20 if i not in dup_rows else 0
        tus = 1.7e15 + i * 20000 + int(rng.integers(0, 3000))
        for s in sysids:
            acc = [i16(rng.normal(0, 30)), i16(rng.normal(0, 30)), i16(-1000 + rng.normal(0, 5))]
            gyr = [i16(rng.normal(0, 3)) for _ in range(3)]
            mg = [i16(200 + rng.normal(0, 3)), i16(-100 + rng.normal(0, 3)), i16(400 + rng.normal(0, 3))]
            if i in zero_rows:
                acc, gyr = [0, 0, 0], [0, 0, 0]
            if raw and i >= raw_from:
                send(s, mav.MAVLink_raw_imu_message(boot * 1000 + 7, *acc, *gyr, *mg, 0, 3000), tus)
            if scaled:
                send(s, mav.MAVLink_scaled_imu_message(boot, *acc, *gyr, *mg, 3000), tus + 50)
            z = [0, 0, 0] if imu2_zero else None
            mg2 = [m + 3 for m in mg]
            send(s, mav.MAVLink_scaled_imu2_message(boot, *(z or acc), *(z or gyr), *mg2, 3000), tus + 90)
            if highres and i % 3 == 0:
                send(s, mav.MAVLink_highres_imu_message(boot * 1000 + 11, *(np.array(acc) / 100.0),
                                                       *(np.array(gyr) / 1000.0), *(np.array(mg) / 1000.0),
                                                       1000.0, 0.0, 0.0, 25.0, 0x1FF, 2), tus + 120)
        if i % 97 == 0:
            send(sysids[0], mav.MAVLink_param_value_message(b"COMPASS_OFS_X", float(i % 7), 9, 500, 3), tus + 200)
        if i % 501 == 0:
            send(sysids[0], mav.MAVLink_statustext_message(6, b"ArduCopter V4.5.0 (abc)"), tus + 300)
        if i % 50 == 0:
            send(sysids[0], mav.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3), tus + 400)
    path.write_bytes(bytes(out))
    return path


def _same_log(a, b) -> None:
    def names(lg):
        return [(s.sensor, s.instance, s.message) for s in lg.series]

    assert names(a) == names(b)
    for x, y in zip(a.series, b.series):
        for f in ("time_s", "values", "log_time_s"):
            u, v = getattr(x, f), getattr(y, f)
            assert u.dtype == v.dtype and u.shape == v.shape and u.tobytes() == v.tobytes(), (x.sensor, x.instance, f)
        assert sorted(x.extra) == sorted(y.extra)
    assert sorted(a.params.changes) == sorted(b.params.changes)
    for k in a.params.changes:
        for u, v in zip(a.params.changes[k], b.params.changes[k]):
            assert u.tobytes() == v.tobytes()
    assert a.events == b.events
    assert (a.position, dict(a.vehicle), a.warnings) == (b.position, dict(b.vehicle), b.warnings)


def _from_columns(path) -> object:
    cols, stats = decode_tlog(str(path), TLOG_MESSAGES)
    return assemble_tlog(cols, str(path), stats.warnings())


CASES = {
    "reboots_zero_rows_duplicates": dict(reboots=(400, 900), zero_rows=range(100, 130), dup_rows=(300, 1200)),
    "scaled_imu_before_raw_imu": dict(raw_from=500, reboots=(800,), imu2_zero=False),
    "scaled_imu_only": dict(raw=False),
    "many_reboots": dict(n=3000, reboots=tuple(range(50, 3000, 60)), scaled=False, highres=False),
    "first_half_all_zero": dict(zero_rows=range(0, 700)),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_lean_read_equals_the_column_path(tmp_path, case):
    path = _tlog(tmp_path / f"{case}.tlog", **CASES[case])
    assert tlog_imu.decode_tlog_lean(str(path)) is not None  # the lean path is the one read_log took
    lean = read_log(path)
    _same_log(lean, _from_columns(path))
    _same_log(read_log(path, chunk_size=4099), lean)  # chunk boundaries change nothing


def test_reboots_are_found_and_shifted(tmp_path):
    path = _tlog(tmp_path / "r.tlog", reboots=(400, 900))
    lg = read_log(path)
    assert any("rebooted 2 time(s)" in w for w in lg.warnings)
    assert sum(e.kind == "reboot" for e in lg.events) == 2
    assert np.all(np.diff(lg.get("accel", 0).time_s) > 0)


def test_imu_from_two_systems_falls_back_to_columns(tmp_path):
    path = _tlog(tmp_path / "two.tlog", sysids=(1, 7), reboots=(700,))
    assert tlog_imu.decode_tlog_lean(str(path)) is None
    _same_log(read_log(path), _from_columns(path))


@pytest.mark.parametrize("path", SITL, ids=[p.name for p in SITL])
def test_bundled_logs_lean_equals_columns(path):
    _same_log(read_log(path), _from_columns(path))


def test_lean_values_live_in_owned_maps_and_untruncate_in_place(tmp_path):
    lg = read_log(_tlog(tmp_path / "a.tlog"))
    acc = lg.get("accel", 0)
    root = acc.packed.counts.base  # the int16 readings (the float values are computed from them)
    while isinstance(root.base, np.ndarray):
        root = root.base
    assert owned_map_of(root) is not None
    before = acc.values.copy()
    out, n = quant.untruncate_log(lg, in_place=True)
    assert out is lg and n > 0  # changed in its own arrays, not copied
    assert np.array_equal(acc.values, quant.untruncate(type(acc)(acc.sensor, acc.instance, acc.message,
                                                                 acc.time_s, before)).values)


def test_grow_array_keeps_unwritten_rows_zero():
    g = GrowArray(np.float64, (3,))
    g.extend(5)[:] = 1.0
    g.extend(10000)  # not written: zero
    v = g.extend(3)
    v[:] = 2.0
    del v
    a = g.array()
    assert a.shape == (10008, 3)
    assert (a[:5] == 1).all() and (a[5:10005] == 0).all() and (a[10005:] == 2).all()


@pytest.mark.parametrize("kind", ["spread", "repeats", "ulps", "empty_part"])
def test_exact_median_is_numpys_bit_for_bit(monkeypatch, kind):
    monkeypatch.setattr(tlog_imu, "_GATHER", 40)
    monkeypatch.setattr(tlog_imu, "_WINDOW", 33)
    rng = np.random.default_rng(3)
    for trial in range(60):
        parts = []
        for _ in range(int(rng.integers(1, 4))):
            n = int(rng.integers(0, 300))
            if kind == "spread":
                a, b = rng.normal(size=n) * 1e3 + 1.7e9, rng.normal(size=n)
            elif kind == "repeats":
                a, b = np.round(rng.normal(size=n), 1) + 5, np.zeros(n)
            elif kind == "ulps":
                a, b = 3.0 + (rng.random(n) < 0.5) * 4e-16, np.zeros(n)
            else:
                a, b = 1.7e9 + rng.integers(0, 10**5, n) * 1e-6, rng.integers(0, 1000, n) * 1e-3
            parts.append((a, b))
        d = np.concatenate([a - b for a, b in parts])
        if len(d) == 0:
            continue
        assert np.float64(tlog_imu.exact_median(parts)).tobytes() == np.float64(np.median(d)).tobytes(), trial
