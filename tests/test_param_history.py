"""Honest parameter history: a logged value counts only back to the last event that could
have changed it (a tlog whose PARAM_VALUE stream starts after an onboard compass calibration)."""
from pathlib import Path

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.param_history import change_events, known_values
from mavcal.ardupilot.protocol import MAV_CMD
from mavcal.ardupilot.recover import recover_raw
from mavcal.segment import find_still_intervals
from mavcal.sources import read_log
from mavcal.sources.types import LogEvent, ParamTimeline
from mavcal.testing.logwriters import TlogWriter
from mavcal.testing.simlog import G, MagTruth, SimConfig, simulate_session

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"

BOOT_S = 30.0           # vehicle boot time at the start of the simulated session
START_CAL_S = 20.0      # MAV_CMD_DO_START_MAG_CAL for compass 2
REPORT_S = 40.0         # "Mag(1) good orientation": the new COMPASS_OFS2 is in force
PARAMS_FROM_S = 45.0    # the PARAM_VALUE stream starts here (after the calibration)

OLD = (fw.CompassCal(), fw.CompassCal(ofs_mgauss=(-40.0, 25.0, 10.0)))
NEW = (fw.CompassCal(), fw.CompassCal(ofs_mgauss=(400.0, -150.0, 90.0)))


def _write_late_params_tlog(path: Path):
    """10 Hz RAW_IMU + SCALED_IMU2; compass 2's offsets change at REPORT_S by an onboard
    calibration; the parameters are only sent from PARAMS_FROM_S on."""
    cfg = SimConfig(mags=(MagTruth((30.0, -10.0, 20.0)), MagTruth((-35.0, 20.0, 15.0))),
                    compass_cals=OLD, compass_cals_after=NEW, change_at_s=REPORT_S, rate_hz=10.0, seed=5)
    sim = simulate_session(cfg)
    t = sim.accel_time_s[0]
    with TlogWriter(path) as w:
        w.command_long(1.7e9 + START_CAL_S, MAV_CMD["MAV_CMD_DO_START_MAG_CAL"], (2, 0, 1, 0, 0))
        w.statustext(1.7e9 + REPORT_S, "Mag(1) good orientation: 0 5.0")
        for j, name in enumerate(sorted(sim.params_after)):
            w.param_value(1.7e9 + PARAMS_FROM_S + 0.002 * j, name, sim.params_after[name], j, len(sim.params_after))
        for j, tt in enumerate(t):
            a = sim.accel_logged_mps2[0][j] * 1000.0 / G
            g = sim.gyro_rad_s[0][j] * 1000.0
            boot_us = int(round((BOOT_S + tt) * 1e6))
            w.raw_imu(1.7e9 + tt, boot_us, a, g, sim.mag_logged_mgauss[0][j])
            w.scaled_imu(2, 1.7e9 + tt, boot_us // 1000, np.zeros(3), np.zeros(3), sim.mag_logged_mgauss[1][j])
    return sim


@pytest.fixture(scope="module")
def late(tmp_path_factory):
    path = tmp_path_factory.mktemp("late") / "late_params.tlog"
    sim = _write_late_params_tlog(path)
    log_ = read_log(str(path))
    return sim, log_, recover_raw(log_)


def test_values_before_the_calibration_report_are_left_out(late):
    sim, log_, raw = late
    m1 = raw.get("mag", 1)
    t_sim = m1.time_s - BOOT_S
    before = t_sim < REPORT_S - 0.05
    after = t_sim >= REPORT_S + 0.05
    assert np.all(np.isnan(m1.values[before])) and np.all(m1.extra["params_known"][before] == 0)
    assert np.all(np.isfinite(m1.values[after])) and np.all(m1.extra["params_known"][after] == 1)
    # after the report the recovered field is the true raw field (1 mGauss truncation)
    truth = np.interp(t_sim[after], sim.mag_time_s[1], np.arange(len(sim.mag_time_s[1]))).round().astype(int)
    np.testing.assert_allclose(m1.values[after], sim.mag_raw_mgauss[1][truth], atol=1.01)
    # applying the late value to the whole log (the old behaviour) would be 440 mGauss off
    assert np.linalg.norm(np.subtract(NEW[1].ofs_mgauss, OLD[1].ofs_mgauss)) > 400


def test_the_warning_says_which_sensor_how_long_and_why(late):
    _, _, raw = late
    msg = [w for w in raw.warnings if w.startswith("mag 1:") and "left out" in w]
    assert len(msg) == 1
    assert f"{BOOT_S:.1f}" in msg[0] and f"{BOOT_S + REPORT_S - 0.1:.1f}" in msg[0]
    assert "COMPASS_OFS2_X/Y/Z, COMPASS_DIA2_X/Y/Z" in msg[0] and "first seen at 75.0 s" in msg[0]
    assert "compass calibration report" in msg[0]
    assert not any(w.startswith(("mag 0:", "accel 0:")) and "left out" in w for w in raw.warnings)


def test_sensors_the_event_does_not_concern_keep_every_reading(late):
    sim, _, raw = late
    m0, a0 = raw.get("mag", 0), raw.get("accel", 0)
    assert "params_known" not in m0.extra and "params_known" not in a0.extra
    assert np.all(np.isfinite(m0.values)) and np.all(np.isfinite(a0.values))
    np.testing.assert_allclose(m0.values, sim.mag_raw_mgauss[0], atol=1.01)


def test_still_intervals_exclude_the_unknown_readings(late):
    _, _, raw = late
    seg = find_still_intervals(raw)
    early = [iv for iv in seg.intervals if iv.end_s < BOOT_S + REPORT_S]
    late_ivs = [iv for iv in seg.intervals if iv.start_s > BOOT_S + REPORT_S]
    assert early and late_ivs
    assert all(iv.n_mag[1] == 0 and iv.n_mag[0] > 0 for iv in early)
    assert all(iv.n_mag[1] > 0 for iv in late_ivs)
    assert all(np.all(np.isfinite(v)) for iv in seg.intervals for v in iv.mag_mgauss.values())


def test_without_an_event_the_first_value_counts_from_the_start():
    params = ParamTimeline({"COMPASS_OFS2_X": (np.array([50.0]), np.array([7.0]))})
    kv = known_values(params, "COMPASS_OFS2_X", change_events(()))
    assert kv is not None
    np.testing.assert_array_equal(kv.at(np.array([0.0, 49.0, 60.0])), [7.0, 7.0, 7.0])
    # an event that concerns another compass does not matter either
    other = change_events((LogEvent(20.0, "statustext", "Mag(0) good orientation: 0 5.0"),))
    kv = known_values(params, "COMPASS_OFS2_X", other)
    assert kv is not None and np.all(kv.known(np.array([0.0, 30.0])))


def test_a_reboot_between_two_values_leaves_the_gap_unknown():
    params = ParamTimeline({"COMPASS_DIA_X": (np.array([10.0, 300.0]), np.array([1.0, 1.05]))})
    events = change_events((LogEvent(100.0, "command", code=MAV_CMD["MAV_CMD_DO_START_MAG_CAL"], params=(0,)),
                            LogEvent(200.0, "statustext", "Mag(0) good orientation: 0 9.0"),
                            LogEvent(290.0, "reboot", "vehicle reboot")))
    kv = known_values(params, "COMPASS_DIA_X", events)
    assert kv is not None
    # the old value holds until the calibration report (a started calibration changes nothing
    # yet), the new one from the reboot; in between it is not known
    np.testing.assert_array_equal(kv.known(np.array([5.0, 150.0, 199.0, 200.0, 289.0, 290.0, 400.0])),
                                  [True, True, True, False, False, True, True])
    np.testing.assert_array_equal(kv.at(np.array([150.0, 295.0])), [1.0, 1.05])
    assert "vehicle reboot" in kv.explain(250.0, params) and "calibration report" in kv.explain(250.0, params)


def test_real_log_reboot_after_compass_calibration():
    path = REAL / "2024-04-05 09-36-27.tlog"
    if not path.exists():
        pytest.skip(f"{path} not available")
    log_ = read_log(str(path))
    reboots = [e.time_s for e in log_.events if e.kind == "reboot"]
    assert [round(t, 1) for t in reboots] == [289.2]
    raw = recover_raw(log_)
    msg = [w for w in raw.warnings if "left out" in w]
    assert len(msg) == 1 and msg[0].startswith("mag 0:") and "COMPASS_DIA_X" in msg[0]
    m0 = raw.get("mag", 0)
    gap = (m0.time_s > 220.5) & (m0.time_s < reboots[0])
    assert np.all(np.isnan(m0.values[gap])) and np.all(np.isfinite(m0.values[~gap]))
    np.testing.assert_array_equal(m0.extra["params_known"], (~gap).astype(float))
