"""Raw recovery on real and SITL logs: the accel-cal jump, the SITL model equations,
missing parameters."""
import json
from pathlib import Path

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.recover import ACCEL_FRAME, MAG_FRAME, recover_raw
from mavcal.autopilot.rotations import rotation_matrix
from mavcal.sources import read_log
from mavcal.sources.types import ImuLog, LogEvent, ParamTimeline, SensorSeries

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REAL = SHARED / "data" / "real"
SITL = SHARED / "sitl_logs"


def _need(p: Path) -> Path:
    if not p.exists():
        pytest.skip(f"{p} not available")
    return p


def test_missing_parameters_are_reported_and_readings_kept():
    t = np.arange(10) * 0.1
    acc = SensorSeries("accel", 0, "IMU", t, np.tile([0.1, 0.2, -9.8], (10, 1)))
    mag = SensorSeries("mag", 0, "MAG", t, np.tile([100.0, 0.0, 300.0], (10, 1)))
    raw = recover_raw(ImuLog("x", "dataflash", (acc, mag)))
    np.testing.assert_array_equal(raw.get("accel", 0).values, acc.values)
    np.testing.assert_array_equal(raw.get("mag", 0).values, mag.values)
    assert any("treated as raw" in w and "accel 0" in w for w in raw.warnings)
    assert any("treated as raw" in w and "mag 0" in w for w in raw.warnings)
    assert raw.frames == {"accel": ACCEL_FRAME, "mag": MAG_FRAME}
    # a CSV never carries parameters: the same readings, and no warning about it (issue 24)
    raw = recover_raw(ImuLog("x", "csv", (acc, mag)))
    np.testing.assert_array_equal(raw.get("accel", 0).values, acc.values)
    assert not any("treated as raw" in w for w in raw.warnings)


def test_parameter_change_counts_from_its_time():
    t = np.arange(10) * 1.0
    mag = SensorSeries("mag", 0, "MAG", t, np.tile([100.0, 0.0, 300.0], (10, 1)))
    params = ParamTimeline({"COMPASS_OFS_X": (np.array([0.0, 5.0]), np.array([10.0, 30.0])),
                            "COMPASS_SCALE": (np.array([0.0]), np.array([2.0]))})  # out of range: ignored
    raw = recover_raw(ImuLog("x", "tlog", (mag,), params))
    x = raw.get("mag", 0).values[:, 0]
    np.testing.assert_allclose(x, np.where(t < 5, 90.0, 70.0))
    assert raw.params_used["COMPASS_OFS_X"] == ((0.0, 10.0), (5.0, 30.0))


def test_accel_cal_period_from_events_is_not_corrected():
    t = np.arange(100) * 0.5
    cal = fw.AccelCal((0.05, -0.02, 0.2), (0.998, 0.942, 0.997), 16)
    u = np.tile([0.05, -9.80665 / 0.942 - 0.02 + 0.3, 0.2], (100, 1))  # board Y down, raw |a| ~ 10.1
    in_cal = (t >= 20) & (t < 35)
    logged = np.where(in_cal[:, None], fw.apply_accel(cal, u, calibrating=True), fw.apply_accel(cal, u))
    names = fw.accel_param_names(0)
    params = {n: (np.array([0.0]), np.array([v])) for n, v in fw.accel_param_values(cal, 0).items()}
    params["AHRS_ORIENTATION"] = (np.array([0.0]), np.array([16.0]))
    events = (LogEvent(18.0, "command", code=241, params=(0, 0, 0, 0, 1, 0, 0)),
              LogEvent(19.9, "statustext", text="Place vehicle level and press any key."),
              LogEvent(35.1, "statustext", text="Calibration successful"))
    log_ = ImuLog("x", "tlog", (SensorSeries("accel", 0, "RAW_IMU", t, logged),), ParamTimeline(params), events)
    raw = recover_raw(log_)
    assert raw.accel_cal_periods == ((20.0, 35.0),)
    np.testing.assert_allclose(raw.get("accel", 0).values, u, atol=1e-9)
    np.testing.assert_array_equal(raw.get("accel", 0).extra["calibrating"], in_cal.astype(float))
    assert names["scale"][1] in raw.params_used


@pytest.mark.parametrize("name", ["00000124.BIN", "2024-04-05 09-19-03.tlog", "2023-05-17 12-18-48.tlog"])
def test_real_six_pose_logs_jump_is_removed(name):
    log_ = read_log(_need(REAL / name))
    raw = recover_raw(log_)
    assert len(raw.accel_cal_periods) == 1
    a0, b0 = raw.accel_cal_periods[0]
    logged, rec = log_.get("accel", 0), raw.get("accel", 0)
    t = logged.time_s
    before = (t > a0 - 8) & (t < a0 - 1)
    during = (t >= a0) & (t < a0 + 7)
    n_log = np.linalg.norm(logged.values, axis=1)
    n_raw = np.linalg.norm(rec.values, axis=1)
    # the vehicle is level and still around the start: logged |a| jumps 9.81 -> 10.42 ...
    assert np.median(n_log[before]) == pytest.approx(9.81, abs=0.03)
    assert np.median(n_log[during]) == pytest.approx(10.42, abs=0.03)
    # ... the recovered raw |a| does not
    assert abs(np.median(n_raw[before]) - np.median(n_raw[during])) < 0.02
    # the calibration's new parameters count from its end: still continuous there
    after = (t > b0) & (t < b0 + 1.2)
    last = (t < b0) & (t > b0 - 1.2)
    if after.sum() and last.sum():
        assert abs(np.median(n_raw[after]) - np.median(n_raw[last])) < 0.1
    assert "INS_ACCSCAL_Y" in raw.params_used and len(raw.params_used["INS_ACCSCAL_Y"]) == 2


@pytest.mark.parametrize("name", ["sitl01", "sitl02"])
def test_sitl_raw_matches_truth_model(name):
    truth = json.loads(_need(SITL / f"{name}.truth.json").read_text())
    raw = recover_raw(read_log(_need(SITL / f"{name}.tlog")))
    S = truth["injected_sim_params"]
    Msim = fw.soft_iron_matrix([S[f"SIM_MAG1_DIA_{a}"] for a in "XYZ"], [S[f"SIM_MAG1_ODI_{a}"] for a in "XYZ"])
    ofs = np.array([S[f"SIM_MAG1_OFS_{a}"] for a in "XYZ"])
    Rs = rotation_matrix(int(S.get("SIM_MAG1_ORIENT", 0)))
    Rc = rotation_matrix(int(truth["vehicle_cal_params_in_force"].get("COMPASS_ORIENT", 0)))
    bias = np.array([S[f"SIM_ACC1_BIAS_{a}"] for a in "XYZ"])
    scal = np.array([S[f"SIM_ACC1_SCAL_{a}"] for a in "XYZ"])
    a, m = raw.get("accel", 0), raw.get("mag", 0)
    unix = a.time_s[0] > 1e9
    for w in truth["dance"]["windows"]:
        t0, t1 = ((w["still_start_unix_usec"] / 1e6, w["still_end_unix_usec"] / 1e6) if unix
                  else (w["still_start_boot_ms"] / 1e3, w["still_end_boot_ms"] / 1e3))
        sa = (a.time_s >= t0) & (a.time_s <= t1)
        sm = (m.time_s >= t0) & (m.time_s <= t1)
        assert sa.sum() > 100 and sm.sum() > 100
        B = np.array(w["true_mag_body_mgauss"])
        f = np.array(w["true_specific_force_body_mss"])
        exp_m = Rc @ (S.get("SIM_MAG1_SCALING", 1.0) * Rs.T @ (np.linalg.solve(Msim, B) - ofs))
        np.testing.assert_allclose(m.values[sm].mean(axis=0), exp_m, atol=1.5)   # 1 mGauss truncation
        np.testing.assert_allclose(a.values[sa].mean(axis=0), f / scal + bias, atol=0.012)  # 1 mG


def test_many_parameter_changes_match_a_per_sample_lookup():
    """Piecewise application (one lookup per parameter per span) equals undoing each sample
    with the values in force at its own time."""
    rng = np.random.default_rng(4)
    t = np.arange(2000) * 0.1
    logged = rng.normal(0, 300, (2000, 3))
    ct = np.sort(rng.uniform(0, 200, 150))
    params = ParamTimeline({"COMPASS_OFS_X": (np.r_[0.0, ct], rng.normal(0, 50, 151)),
                            "COMPASS_DIA_Y": (np.array([0.0, 77.7]), np.array([1.0, 1.1])),
                            "COMPASS_SCALE": (np.array([0.0]), np.array([1.0]))})
    raw = recover_raw(ImuLog("x", "dataflash", (SensorSeries("mag", 0, "MAG", t, logged),), params))
    expect = np.array([fw.undo_compass(fw.compass_cal_from_params(params.snapshot(float(tt)), 0), v[None])[0]
                       for tt, v in zip(t, logged)])
    np.testing.assert_allclose(raw.get("mag", 0).values, expect, rtol=1e-12, atol=1e-9)  # float rounding


def _calibrating_mask(t, periods):
    m = np.zeros(len(t), bool)
    for a, b in periods:
        m |= (t >= a) & (t < b)
    return m


@pytest.mark.parametrize("shuffled", [False, True])
def test_many_accel_calibrations_each_mark_their_own_samples(shuffled):
    """Hundreds of calibration windows (a day's log): each window's samples are found by a
    sorted search (by a mask when the times are not sorted), with the same result."""
    rng = np.random.default_rng(7)
    t = np.arange(40000) * 0.02
    acc = np.tile([0.0, 0.0, -9.80665], (len(t), 1)) + rng.normal(0, 0.01, (len(t), 3))
    starts = np.arange(10.0, 790.0, 4.0)
    events = [e for s in starts for e in (LogEvent(float(s), "statustext", "Place vehicle level and press any key"),
                                          LogEvent(float(s) + 2.0, "statustext", "Calibration successful"))]
    order = rng.permutation(len(t)) if shuffled else np.arange(len(t))
    log_ = ImuLog("x", "tlog", (SensorSeries("accel", 0, "RAW_IMU", t[order], acc[order]),), events=tuple(events))
    raw = recover_raw(log_)
    assert len(raw.accel_cal_periods) == len(starts)
    assert shuffled or not raw.accel_cal_without_imu  # (unsorted times have no meaningful sample period)
    got = raw.get("accel", 0)
    np.testing.assert_array_equal(got.extra["calibrating"] == 1.0, _calibrating_mask(got.time_s, raw.accel_cal_periods))
