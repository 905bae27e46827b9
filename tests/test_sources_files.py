"""File readers: real logs (fast decoder == pymavlink), units, time base, edge cases, fuzz."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mav2

from mavcal.errors import MavcalError, SourceError
from mavcal.sources import read_log
from mavcal.sources.assemble import REBOOT_BACKSTEP_S, TLOG_MESSAGES, _next_reboot
from mavcal.sources.fast_tlog import crc_x25, decode_tlog
from mavcal.sources.framing import mark_path as _mark_path
from mavcal.sources.framing import path_from as _path_from
from mavcal.sources.progress import ProgressPrinter, auto_progress
from mavcal.sources.wmm import field_at, field_ned
from mavcal.testing.damaged import python_exception_named

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "data" / "real"
SITL = REPO / "sitl_logs"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="real logs not available")

REAL_LOGS = ["2023-05-17 12-18-48.tlog", "2024-04-05 09-19-03.tlog", "2024-04-05 09-36-27.tlog", "flight.tlog",
             "00000124.BIN", "log171.bin", "00000-2021-12-02_13-34-15.bin", "test.BIN"]


def assert_same(a, b):
    def key(log_):
        return [(s.sensor, s.instance, s.message) for s in log_.series]

    assert key(a) == key(b)
    for x, y in zip(a.series, b.series):
        np.testing.assert_array_equal(x.time_s, y.time_s)
        np.testing.assert_array_equal(x.values, y.values)
        if x.log_time_s is None:
            assert y.log_time_s is None
        else:
            np.testing.assert_array_equal(x.log_time_s, y.log_time_s)
        assert set(x.extra) == set(y.extra)
        for k in x.extra:
            np.testing.assert_array_equal(x.extra[k], y.extra[k])
    assert a.params.names() == b.params.names()
    for n in a.params.names():
        np.testing.assert_array_equal(a.params.changes[n][0], b.params.changes[n][0])
        np.testing.assert_array_equal(a.params.changes[n][1], b.params.changes[n][1])
    assert a.events == b.events
    assert a.position == b.position


@needs_real
@pytest.mark.parametrize("name", REAL_LOGS)
def test_fast_decoder_identical_to_pymavlink(name):
    path = REAL / name
    assert_same(read_log(path), read_log(path, fast=False))


def test_fast_decoder_identical_to_pymavlink_sitl():
    assert_same(read_log(SITL / "sitl02.tlog"), read_log(SITL / "sitl02.tlog", fast=False))


def test_small_chunks_give_the_same_result():
    a = read_log(SITL / "sitl02.tlog")
    b = read_log(SITL / "sitl02.tlog", chunk_size=4096 + 17)
    assert_same(a, b)


@needs_real
def test_small_chunks_dataflash():
    assert_same(read_log(REAL / "log171.bin"), read_log(REAL / "log171.bin", chunk_size=5000))


@needs_real
def test_bad_crc_records_counted():
    path = REAL / "2023-05-17 12-18-48.tlog"
    lg = read_log(path)
    # the 991 bad frames are DISTANCE_SENSOR/CAMERA_*: types read_log does not decode, so by
    # default their CRC is not checked (a debug note, not a user warning)
    assert not any("bad CRC" in w for w in lg.warnings)
    _, stats0 = decode_tlog(str(path), TLOG_MESSAGES)
    assert stats0.crc_unchecked > 0 and any("CRC checked only" in n for n in stats0.notes())
    _, stats = decode_tlog(str(path), TLOG_MESSAGES, check_all_crc=True)
    assert stats.bad_crc == 991 and stats.crc_unchecked == 0
    assert any("991 MAVLink frames with a bad CRC" in w for w in stats.warnings())
    assert len(lg.get("accel", 0)) == 781
    assert lg.instances("accel") == [0]  # SCALED_IMU2 accel is all zero: no IMU 2
    assert lg.instances("mag") == [0, 1]


@needs_real
def test_units_and_reference_values_tlog():
    lg = read_log(REAL / "2024-04-05 09-19-03.tlog")
    acc = lg.get("accel", 0)
    assert acc.message == "RAW_IMU" and acc.unit == "m/s^2"
    # level, corrected: |a| about 999 mG
    assert np.median(np.linalg.norm(acc.values[:20], axis=1)) == pytest.approx(0.999 * 9.80665, rel=0.01)
    # parameters on the series time base: the accel cal result arrives ~135 s after the first RAW_IMU
    ts, vs = lg.params.changes["INS_ACCSCAL_Y"]
    assert vs[-1] == pytest.approx(0.9420, abs=1e-3)
    assert 125 < ts[-1] - acc.time_s[0] < 145
    assert lg.vehicle["firmware"].startswith("ArduSub V4.5.0")


@needs_real
def test_reboot_keeps_time_monotonic():
    lg = read_log(REAL / "2024-04-05 09-36-27.tlog")
    assert any("rebooted 1 time" in w for w in lg.warnings)
    for s in lg.series:
        assert np.all(np.diff(s.time_s) > 0)
        # time_s advances like the log time across the reboot
        span_t = s.time_s[-1] - s.time_s[0]
        span_l = s.log_time_s[-1] - s.log_time_s[0]
        assert span_t == pytest.approx(span_l, abs=3.0)


@needs_real
def test_dataflash_instances_and_extras():
    lg = read_log(REAL / "00000124.BIN")
    mag = lg.get("mag", 1)
    assert mag.message == "MAG" and set(mag.extra) == {"ofs_mgauss", "motor_ofs_mgauss", "health"}
    # COMPASS_OFS2 ~ (23.2, 223.7, -423.7), MAG.Ofs is its int16 truncation
    np.testing.assert_allclose(mag.extra["ofs_mgauss"][0], [23, 223, -423], atol=1.01)
    assert lg.params.final("INS_ACCSCAL_Y") == pytest.approx(0.9420, abs=1e-4)
    assert lg.params.initial("INS_ACCSCAL_Y") == pytest.approx(0.9428, abs=1e-4)
    assert any(e.kind == "statustext" and "Calibration successful" in e.text for e in lg.events)
    old = read_log(REAL / "log171.bin")  # IMU2/IMU3/MAG2/MAG3 names, no I, PARM without TimeUS
    assert old.instances("accel") == [0, 1, 2] and old.instances("mag") == [0, 1, 2]
    assert old.get("accel", 2).message == "IMU3"
    assert old.position is not None and old.position[0] == pytest.approx(-35.36, abs=0.01)


def test_sitl_time_base_matches_truth():
    truth = json.loads((SITL / "sitl01.truth.json").read_text())
    lg = read_log(SITL / "sitl01.tlog")
    acc = lg.get("accel", 0)
    assert lg.instances("accel") == [0, 1] and lg.instances("mag") == [0, 1, 2]
    for w in truth["dance"]["windows"]:
        # the still window in vehicle boot time and in tlog time must be the same samples
        i = np.searchsorted(acc.time_s, w["still_start_boot_ms"] * 1e-3)
        assert acc.log_time_s[i] == pytest.approx(w["still_start_unix_usec"] * 1e-6, abs=0.1)
    # position (home) and the WMM field there agree with the SITL reference
    dec, inc, f = field_at(*lg.position)
    ref = truth["reference"]
    assert dec == pytest.approx(ref["declination_deg"], abs=1.0)
    assert f == pytest.approx(ref["earth_field_norm_mgauss"], rel=0.03)
    np.testing.assert_allclose(field_ned(*lg.position), ref["earth_field_ned_mgauss"], atol=15)


@needs_real
def test_csv_reader():
    lg = read_log(REAL / "acc_log.csv")
    acc = lg.get("accel")
    assert lg.kind == "csv" and len(acc) == 16000
    assert acc.time_s[1] - acc.time_s[0] == pytest.approx(0.01)
    assert any("100 Hz" in w for w in lg.warnings)
    assert 0.95 * 9.80665 < np.median(np.linalg.norm(acc.values, axis=1)) < 1.04 * 9.80665
    lg2 = read_log(REAL / "acc_log.csv", csv_rate_hz=50)
    assert lg2.get("accel").time_s[1] == pytest.approx(0.02)


# --------------------------------------------------------------------------- synthetic tlogs
class _Buf:
    def __init__(self):
        self.data = bytearray()

    def write(self, b):
        self.data += b


def make_mav(v1=False, signed=False):
    m = mav2.MAVLink(_Buf(), srcSystem=1, srcComponent=1)
    if signed:
        m.signing.secret_key = b"k" * 32
        m.signing.sign_outgoing = True
        m.signing.link_id = 1
        m.signing.timestamp = 1
    return m


def tlog_bytes(msgs, t0_us=1_700_000_000_000_000, v1_every=0, signed=False):
    out = bytearray()
    m2 = make_mav(signed=signed)
    m1 = make_mav()
    for k, msg in enumerate(msgs):
        use_v1 = v1_every and k % v1_every == 0
        buf = msg.pack(m1 if use_v1 else m2, force_mavlink1=bool(use_v1))
        out += struct.pack(">Q", t0_us + k * 20_000) + buf
    return bytes(out)


def imu_msgs(n, boot0_ms=1000, mag_scale=1):
    msgs = []
    for k in range(n):
        tb = boot0_ms + 20 * k
        msgs.append(mav2.MAVLink_raw_imu_message(tb * 1000, 10, -20, -1000 + k % 3, 1, 2, 3, 200, -50, 400))
        msgs.append(mav2.MAVLink_scaled_imu2_message(tb, 0, 0, 0, 0, 0, 0, 0, 0, 0))
        if k % 10 == 0:
            msgs.append(mav2.MAVLink_param_value_message(b"COMPASS_OFS_X", float(k), 9, 10, 0))
            msgs.append(mav2.MAVLink_highres_imu_message(tb * 1000, 0.1, 0.2, -9.8, 0, 0, 0,
                                                         0.2 * mag_scale, -0.05 * mag_scale, 0.4 * mag_scale,
                                                         0, 0, 0, 0, 0, 0))
    return msgs


def write(tmp_path, name, data):
    p = tmp_path / name
    p.write_bytes(data)
    return p


def test_synthetic_tlog_units_and_zero_truncation(tmp_path):
    p = write(tmp_path, "a.tlog", tlog_bytes(imu_msgs(50)))
    lg = read_log(p)
    acc = lg.get("accel", 0)
    np.testing.assert_allclose(acc.values[0], np.array([10, -20, -1000]) * 9.80665 / 1000)
    np.testing.assert_allclose(lg.get("gyro", 0).values[0], [0.001, 0.002, 0.003])
    np.testing.assert_allclose(acc.time_s[:2], [1.0, 1.02])
    assert lg.get("mag", 1) is None and lg.get("accel", 1) is None  # all-zero SCALED_IMU2
    assert lg.params.final("COMPASS_OFS_X") == 40.0 and len(lg.params.changes["COMPASS_OFS_X"][0]) == 5
    assert_same(lg, read_log(p, fast=False))
    # HIGHRES_IMU in gauss (fixed firmware) -> mGauss; instance 0 mag comes from RAW_IMU
    assert any("in gauss" in w for w in lg.warnings)


def test_highres_mag_unit_bug_detected(tmp_path):
    msgs = [m for m in imu_msgs(30, mag_scale=1e6) if m.get_type() == "HIGHRES_IMU"]
    lg = read_log(write(tmp_path, "h.tlog", tlog_bytes(msgs)))
    mag = lg.get("mag", 0)
    assert mag.message == "HIGHRES_IMU"
    np.testing.assert_allclose(mag.values[0], [200, -50, 400], rtol=1e-5)
    assert any("mGauss*1000" in w for w in lg.warnings)
    lg2 = read_log(write(tmp_path, "h2.tlog", tlog_bytes([m for m in imu_msgs(30) if m.get_type() == "HIGHRES_IMU"])))
    np.testing.assert_allclose(lg2.get("mag", 0).values[0], [200, -50, 400], rtol=1e-5)


def test_mixed_v1_v2_and_signed(tmp_path):
    base = read_log(write(tmp_path, "b.tlog", tlog_bytes(imu_msgs(40))))
    mixed = read_log(write(tmp_path, "m.tlog", tlog_bytes(imu_msgs(40), v1_every=3)))
    signed = tlog_bytes(imu_msgs(40), signed=True)
    assert signed.count(b"\xfd") > 0
    sg = read_log(write(tmp_path, "s.tlog", signed))
    for lg in (mixed, sg):
        np.testing.assert_array_equal(lg.get("accel", 0).values, base.get("accel", 0).values)
        np.testing.assert_array_equal(lg.get("accel", 0).time_s, base.get("accel", 0).time_s)
    cols, stats = decode_tlog(str(tmp_path / "s.tlog"), ["RAW_IMU"])
    assert stats.signed == stats.frames > 0
    assert_same(sg, read_log(tmp_path / "s.tlog", fast=False))


def test_bad_crc_and_garbage_are_skipped_and_counted(tmp_path):
    data = bytearray(tlog_bytes(imu_msgs(60)))
    good = read_log(write(tmp_path, "g.tlog", bytes(data)))
    n = len(good.get("accel", 0))
    # corrupt one payload byte of a RAW_IMU frame (CRC now wrong) and insert garbage elsewhere
    i = data.index(bytes([0xFD, 26]), 2000)  # RAW_IMU v2 frame (len 26 after zero truncation or 29)
    data[i + 12] ^= 0xFF
    j = len(data) // 2
    data[j:j] = b"\x00garbage\xfe\x11" * 3
    lg = read_log(write(tmp_path, "c.tlog", bytes(data)))
    assert n - 3 <= len(lg.get("accel", 0)) < n
    assert any("bad CRC" in w for w in lg.warnings)
    assert any("unparseable bytes" in w for w in lg.warnings)


def test_crc_checked_only_for_decoded_types_unless_asked(tmp_path):
    msgs = imu_msgs(40)
    data = bytearray(tlog_bytes(msgs))
    # corrupt one payload byte of a PARAM_VALUE frame (id 22) and of a RAW_IMU frame (id 27)
    i = data.index(b"COMPASS_OFS_X", 500)
    data[i + 3] ^= 0x55
    j = data.index(bytes([0xFD, 26]), 2000)
    data[j + 12] ^= 0xFF
    p = write(tmp_path, "c.tlog", bytes(data))
    cols, stats = decode_tlog(str(p), ["RAW_IMU", "SCALED_IMU2"])
    assert stats.bad_crc == 1 and stats.bad_crc_by_id == {27: 1}
    n_other = sum(m.get_type() not in ("RAW_IMU", "SCALED_IMU2") for m in msgs)
    assert stats.crc_unchecked == n_other
    assert any(f"{n_other} MAVLink frames of other types were not checked" in w for w in stats.notes())
    assert len(cols["RAW_IMU"]["xacc"]) == 39 and len(cols["SCALED_IMU2"]["xacc"]) == 40
    _, all_stats = decode_tlog(str(p), ["RAW_IMU", "SCALED_IMU2"], check_all_crc=True)
    assert all_stats.bad_crc == 2 and all_stats.bad_crc_by_id == {22: 1, 27: 1} and all_stats.crc_unchecked == 0
    # read_log decodes PARAM_VALUE: its bad frame is dropped like pymavlink drops it
    lg = read_log(p)
    assert any("2 MAVLink frames with a bad CRC" in w for w in lg.warnings)
    assert_same(lg, read_log(p, fast=False))


def test_path_contraction_matches_pointer_doubling():
    rng = np.random.default_rng(3)
    for _ in range(2000):
        n = int(rng.integers(1, 80))
        step = np.where(rng.random(n) < 0.7, 1, rng.integers(1, 6, n))
        succ = np.minimum(np.arange(n) + step, n)
        succ[rng.random(n) < 0.05] = n
        start = int(rng.integers(0, n + 1))
        np.testing.assert_array_equal(_path_from(succ, start), _mark_path(succ, start))


def test_reboot_search_matches_running_max_definition():
    rng = np.random.default_rng(4)
    for n in (1, 2, 50, 4096, 4097, 30_000):
        boot = np.cumsum(rng.random(n) * 0.02)
        for i in rng.integers(1, max(n, 2), 6):
            if i < n:
                boot[i:] -= rng.choice([0.5, 1.99, 2.5, 100.0])
        i0, got, want = 0, [], []
        while (i0 := _next_reboot(boot, i0)) is not None:
            got.append(i0)
        i0 = 0
        while True:
            runmax = np.maximum.accumulate(boot[i0:])
            drop = np.flatnonzero(boot[i0 + 1:] < runmax[:-1] - REBOOT_BACKSTEP_S)
            if len(drop) == 0:
                break
            i0 = i0 + 1 + int(drop[0])
            want.append(i0)
        assert got == want


def test_crc_matches_pymavlink():
    from pymavlink.mavutil import x25crc

    rng = np.random.default_rng(1)
    data = rng.integers(0, 256, 500, dtype=np.uint8)
    starts = np.array([0, 10, 100, 3])
    lens = np.array([5, 40, 0, 200])
    extra = np.array([7, 200, 0, 255], dtype=np.uint8)
    got = crc_x25(data, starts, lens, extra)
    for k in range(4):
        buf = bytearray(data[starts[k]:starts[k] + lens[k]].tobytes()) + bytes([extra[k]])
        assert got[k] == x25crc(buf).crc
    # many frames, odd and even lengths (the two-byte table path), repeated lengths
    starts = rng.integers(0, 190, 400)
    lens = rng.integers(0, 300, 400) % (500 - starts)
    extra = rng.integers(0, 256, 400).astype(np.uint8)
    got = crc_x25(data, starts, lens, extra)
    for k in range(400):
        buf = bytearray(data[starts[k]:starts[k] + lens[k]].tobytes()) + bytes([extra[k]])
        assert got[k] == x25crc(buf).crc


def test_reboot_in_synthetic_tlog(tmp_path):
    msgs = imu_msgs(30, boot0_ms=50_000) + imu_msgs(30, boot0_ms=500)  # second boot starts near 0
    lg = read_log(write(tmp_path, "r.tlog", tlog_bytes(msgs)))
    acc = lg.get("accel", 0)
    assert np.all(np.diff(acc.time_s) > 0)
    assert any("rebooted 1 time" in w for w in lg.warnings)
    assert acc.time_s[0] == pytest.approx(50.0)
    # params on the same time base: last change within the series time span
    ts = lg.params.changes["COMPASS_OFS_X"][0]
    assert acc.time_s[0] - 1 < ts[-1] < acc.time_s[-1] + 1


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("name,data,match", [
    ("empty.tlog", b"", "empty"),
    ("empty.bin", b"", "empty"),
    ("random.tlog", bytes(np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8)), "no MAVLink|no IMU"),
    ("random.bin", bytes(np.random.default_rng(1).integers(0, 256, 20000, dtype=np.uint8)), "no DataFlash|no IMU"),
    ("x.xyz", b"abc", "unknown log type"),
    ("noheader.csv", b"1,2,3\n4,5,6\n", "ax,ay,az"),
    ("empty2.csv", b"\n", "ax,ay,az|empty|no numeric"),
    ("text.log", b"hello world\nno FMT here\n", "no IMU"),
])
def test_bad_files_give_one_line_source_errors(tmp_path, name, data, match):
    p = write(tmp_path, name, data)
    with pytest.raises(SourceError, match=match) as ei:
        read_log(p)
    assert "\n" not in str(ei.value)


def test_missing_file_and_no_imu(tmp_path):
    with pytest.raises(SourceError, match="no such file"):
        read_log(str(tmp_path / "nope.tlog"))
    hb = [mav2.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3)] * 5
    with pytest.raises(SourceError, match="no IMU messages"):
        read_log(write(tmp_path, "hb.tlog", tlog_bytes(hb)))


@needs_real
def test_truncated_and_corrupt_fmt_dataflash(tmp_path):
    data = (REAL / "test.BIN").read_bytes()
    lg = read_log(write(tmp_path, "t.bin", data[:30000]))
    assert len(lg.get("accel", 0)) < 45
    bad = bytearray(data)
    # corrupt the FMT record of IMU (its Format string): IMU records are then unknown
    k = bad.index(b"IMU\x00", 0)
    bad[k + 4:k + 8] = b"\xff\xff\xff\xff"
    lg2 = read_log(write(tmp_path, "f.bin", bytes(bad)))
    assert any("corrupt FMT" in w for w in lg2.warnings)
    assert lg2.get("accel", 0) is None or len(lg2.get("accel", 0)) <= 45


def _mutations(data: bytes, seed: int, n: int):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        b = bytearray(data)
        kind = rng.integers(0, 3)
        if kind == 0:  # flip bytes
            for i in rng.integers(0, len(b), 20):
                b[i] ^= int(rng.integers(1, 256))
        elif kind == 1:  # truncate
            b = b[: int(rng.integers(1, len(b)))]
        else:  # splice a random block
            i = int(rng.integers(0, len(b)))
            b[i:i] = bytes(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8))
        yield bytes(b)


def _read_ok_or_mavcal_error(path):
    """Read a damaged file: its ImuLog, or a MavcalError of one line naming no Python exception. Any other
    exception (a reader's bug, e.g. an IndexError) escapes and fails the test (issue 35)."""
    try:
        lg = read_log(path)
    except MavcalError as exc:
        assert "\n" not in str(exc)
        assert python_exception_named(str(exc)) is None, str(exc)
        return None
    for s in lg.series:
        assert len(s.time_s) == len(s.values)
    return lg


def test_fuzz_mutated_sitl_tlog(tmp_path):
    data = (SITL / "sitl02.tlog").read_bytes()[:200_000]
    for k, mut in enumerate(_mutations(data, 7, 25)):
        _read_ok_or_mavcal_error(write(tmp_path, f"f{k}.tlog", mut))


@needs_real
def test_fuzz_mutated_dataflash(tmp_path):
    data = (REAL / "test.BIN").read_bytes()
    for k, mut in enumerate(_mutations(data, 11, 25)):
        _read_ok_or_mavcal_error(write(tmp_path, f"f{k}.bin", mut))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(min_size=0, max_size=3000), ext=st.sampled_from([".tlog", ".bin", ".log", ".csv"]))
def test_fuzz_random_bytes(tmp_path, data, ext):
    # random bytes with some MAVLink/DataFlash start markers sprinkled in
    p = tmp_path / f"h{ext}"
    p.write_bytes(data.replace(b"\x01", b"\xfd").replace(b"\x02", b"\xa3\x95"))
    _read_ok_or_mavcal_error(p)


# --------------------------------------------------------------------------- progress, wmm
def test_progress_printer_and_silence_when_piped():
    import io

    s = io.StringIO()
    pr = ProgressPrinter("x.tlog", s, min_interval_s=0)
    pr(50, 100)
    pr(100, 100)
    out = s.getvalue()
    assert "50%" in out and "100%" in out and out.endswith("\n")
    assert auto_progress("x", io.StringIO()) is None  # not a TTY: silent


def test_progress_callback_called(tmp_path):
    calls = []
    read_log(SITL / "sitl02.tlog", progress=lambda d, t: calls.append((d, t)), chunk_size=100_000)
    assert len(calls) >= 5 and calls[-1][0] == calls[-1][1]


def test_wmm_field():
    dec, inc, f = field_at(47.4, 8.5)  # Zurich
    assert 1 < dec < 6 and 60 < inc < 66 and 460 < f < 500
    ned = field_ned(47.4, 8.5)
    assert np.linalg.norm(ned) == pytest.approx(f)
    assert ned[2] > 0  # northern hemisphere: field points down
    with pytest.raises(MavcalError):
        field_at(95, 0)


def test_a_concatenated_log_says_its_reboots_in_one_short_line(tmp_path, sitl_dir):
    """Issue 14: plain copies of one tlog (each a new boot) gave a 1,000-character warning."""
    data = (sitl_dir / "sitl01.tlog").read_bytes()
    p = tmp_path / "copies.tlog"
    p.write_bytes(data * 6)
    lg = read_log(p)
    (w,) = [w for w in lg.warnings if "rebooted" in w]
    assert "rebooted 5 time(s)" in w and "(2 more)" in w and len(w) < 200
