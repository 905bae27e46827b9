"""Simulated logs: writers produce what pymavlink and mavcal's readers read, the truth is
consistent with ArduPilot's forward model, and sim -> log -> reader -> raw recovery returns
the simulated raw readings to int16 truncation."""
from dataclasses import replace

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.recover import recover_raw
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.sources import read_log
from mavcal.testing.logwriters import DataFlashWriter, TlogWriter, int16_trunc
from mavcal.testing.simlog import AccelErrorTruth, MagTruth, SimConfig, simulate_session

G = GRAVITY_MPS2

CFG = SimConfig(
    accels=(AccelErrorTruth((0.3, -0.2, 0.15), (1.02, 0.97, 1.01), (0.004, -0.003, 0.002)),
            AccelErrorTruth((-0.1, 0.05, 0.2), (0.99, 1.01, 1.0))),
    mags=(MagTruth((120.0, -60.0, 210.0), ((1.05, 0.02, 0.0), (0.02, 0.96, 0.01), (0.0, 0.01, 1.0))),
          MagTruth((15.0, 25.0, -35.0))),
    accel_cals=(fw.AccelCal((0.1, -0.05, 0.2), (1.0, 0.95, 1.02), 16), fw.AccelCal((0.02, 0, 0), (1, 1, 1), 16)),
    compass_cals=(fw.CompassCal((-80, 40, -100), (1.02, 0.98, 1.0), (0.01, -0.02, 0.005), 1.1, 0, True),
                  fw.CompassCal((5, -5, 5), orient=16, external=False)),
    change_at_s=30.0,
    compass_cals_after=(fw.CompassCal((-95, 45, -110), (1.0, 1.0, 1.0), (0, 0, 0), 0.0, 0, True),
                        fw.CompassCal((7, -3, 2), (0, 0, 0), (0.3, 0.3, 0.3), 1.0, 16, False)),
    accel_cal_period_s=(37.5, 58.0),  # starts and ends while held still, as onboard
    accel_cals_after=(fw.AccelCal((0.3, -0.2, 0.15), (0.98, 1.03, 0.99), 16),
                      fw.AccelCal((0.02, 0, 0), (1, 1, 1), 16)),
    seed=7,
)


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    tl = simulate_session(CFG, tlog=d / "s.tlog")
    cfg_bin = replace(CFG, motor_ofs_mgauss=((3.0, -2.0, 5.0), (0.0, 0.0, 0.0)))
    bn = simulate_session(cfg_bin, bin=d / "s.bin")
    return {"tlog": tl, "bin": bn}


def test_int16_truncation_toward_zero():
    np.testing.assert_array_equal(int16_trunc([1.9, -1.9, -0.5, 40000.0, -40000.0]), [1, -1, 0, 32767, -32768])


def test_writers_are_read_by_pymavlink(tmp_path):
    from pymavlink import mavutil

    with TlogWriter(tmp_path / "x.tlog") as w:
        w.heartbeat(1.7e9)
        w.param_value(1.7e9 + 0.1, "COMPASS_OFS_X", 12.5)
        w.raw_imu(1.7e9 + 0.2, 200_000, (1.9, -2.7, -1000.4), (0, 0, 0), (100.9, -50.2, 300))
        w.scaled_imu(3, 1.7e9 + 0.3, 300, (0, 0, 0), (0, 0, 0), (-7.9, 0, 1))
    m = mavutil.mavlink_connection(str(tmp_path / "x.tlog"))
    msgs = []
    while (x := m.recv_match()) is not None:
        msgs.append(x)
    assert [x.get_type() for x in msgs] == ["HEARTBEAT", "PARAM_VALUE", "RAW_IMU", "SCALED_IMU3"]
    assert msgs[1].param_id == "COMPASS_OFS_X" and msgs[1].param_value == 12.5
    assert (msgs[2].xacc, msgs[2].yacc, msgs[2].zacc, msgs[2].xmag) == (1, -2, -1000, 100)
    assert msgs[2]._timestamp == pytest.approx(1.7e9 + 0.2, abs=1e-6)
    assert msgs[3].xmag == -7

    with DataFlashWriter(tmp_path / "x.bin") as d:
        d.parm(1000, "INS_ACCSCAL_Y", 0.942)
        d.imu(2000, 1, (0.01, 0, 0), (0.1, 0.2, -9.8))
        d.mag(3000, 2, (100.7, -200.9, 300), (12.5, -3.9, 0), (1, 2, 3))
        d.msg(4000, "Calibration successful")
    m = mavutil.mavlink_connection(str(tmp_path / "x.bin"))
    got = {}
    while (x := m.recv_match()) is not None:
        got.setdefault(x.get_type(), []).append(x)
    assert got["IMU"][0].I == 1 and got["IMU"][0].AccZ == pytest.approx(-9.8, abs=1e-6)
    mg = got["MAG"][0]
    assert (mg.I, mg.MagX, mg.MagY, mg.OfsX, mg.OfsY, mg.MOZ) == (2, 100, -200, 12, -3, 3)
    assert got["MSG"][0].Message == "Calibration successful"
    assert m.params["INS_ACCSCAL_Y"] == pytest.approx(0.942, abs=1e-6)


def test_truth_matches_the_firmware_forward_model(sims):
    s = sims["tlog"]
    t = s.accel_time_s[0]
    before = t < CFG.change_at_s
    calib = s.calibrating[0]
    assert calib.any() and not calib[before].all()
    exp = fw.apply_accel(replace(CFG.accel_cals[0]), s.accel_raw_mps2[0][before & ~calib])
    np.testing.assert_allclose(s.accel_logged_mps2[0][before & ~calib], exp, atol=1e-5)
    # raw accel magnitude: gravity through the raw errors, not the corrected 9.81
    assert np.median(np.linalg.norm(s.accel_raw_mps2[0], axis=1)) == pytest.approx(G, rel=0.05)
    assert len(s.still_windows_s) == len(CFG.poses_deg)


@pytest.mark.parametrize("kind", ["tlog", "bin"])
def test_round_trip_recovers_simulated_raw(sims, kind):
    s = sims[kind]
    log_ = read_log(s.paths[kind])
    raw = recover_raw(log_)
    assert raw.warnings == ()
    for i in range(2):
        a = raw.get("accel", i)
        assert len(a) == len(s.accel_raw_mps2[i])
        err = np.abs(a.values - s.accel_raw_mps2[i]).max()
        # tlog: 1 mG truncation / scale 0.95; bin: float32
        assert err < (0.0105 if kind == "tlog" else 1e-5), err
        m = raw.get("mag", i)
        assert len(m) == len(s.mag_raw_mgauss[i])
        errm = np.abs(m.values - s.mag_raw_mgauss[i]).max()
        assert errm < 1.05, errm  # 1 mGauss truncation (of the field, and of MAG.MO*)
    # the parameter change and the onboard accel calibration were honoured
    assert len(raw.params_used["COMPASS_OFS_X"]) == 2
    assert len(raw.accel_cal_periods) == 1
    a0, b0 = raw.accel_cal_periods[0]
    t = raw.get("accel", 0).time_s
    # edges land on the sample where the suspended correction starts/ends
    dt = np.median(np.diff(t))
    assert abs((a0 - t[0]) - 37.5) <= dt + 1e-6 and abs((b0 - t[0]) - 58.0) <= dt + 1e-6


def test_mavlink2_tlog(tmp_path):
    cfg = replace(CFG, poses_deg=CFG.poses_deg[:3], change_at_s=None, accel_cal_period_s=None,
                  compass_cals_after=None, accel_cals_after=None)
    s = simulate_session(cfg, tlog=tmp_path / "v2.tlog", mavlink2=True)
    raw = recover_raw(read_log(tmp_path / "v2.tlog"))
    np.testing.assert_allclose(raw.get("mag", 0).values, s.mag_raw_mgauss[0], atol=1.05)
