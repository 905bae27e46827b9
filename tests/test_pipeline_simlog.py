"""End to end on simulated ArduPilot logs with a known truth: .bin and .tlog, with a wrong
calibration in force on the simulated autopilot, hand tremor and motion between poses."""
import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.evaluate import attitude_errors
from mavcal.errors import UsageError
from mavcal.pipeline import Options, calibrate_source
from mavcal.testing.simlog import AccelErrorTruth, MagTruth, SimConfig, simulate_session

SOFT = ((1.04, 0.02, -0.01), (0.02, 0.97, 0.015), (-0.01, 0.015, 1.01))  # symmetric: ArduPilot can hold it
HARD = (120.0, -80.0, 45.0)
BIAS = (0.15, -0.1, 0.25)
GAIN = (1.02, 0.98, 1.01)
FIELD = (200.0, 15.0, 450.0)
POSES = [(0, 0, 0), (90, 0, 30), (-90, 0, 200), (0, 90, 120), (0, -90, 300), (180, 0, 60),
         (45, 45, 10), (-45, 30, 250), (135, -30, 150), (-135, -45, 80), (30, -20, 330), (60, 60, 100)]


@pytest.fixture(scope="module", params=["bin", "tlog"])
def run(request, tmp_path_factory):
    kind = request.param
    cfg = SimConfig(accels=(AccelErrorTruth(bias_mps2=BIAS, gain=GAIN, noise_mps2=0.03),),
                    mags=(MagTruth(hard_iron_mgauss=HARD, soft_iron=SOFT, noise_mgauss=1.5),),
                    compass_cals=(fw.CompassCal(ofs_mgauss=(10.0, 0.0, -5.0), external=True),),
                    earth_field_ned_mgauss=FIELD, poses_deg=tuple(POSES), hold_s=3.0, move_s=1.5, seed=7)
    path = tmp_path_factory.mktemp("sim") / f"s.{kind}"
    simulate_session(cfg, **{kind: path})
    return kind, calibrate_source(str(path), Options(uncertainty_draws=60))


def test_recovers_the_truth_from_simulated_logs(run):
    kind, r = run
    am, cm = r.mapping.accel[0], r.mapping.compass[0]
    assert len(r.intervals_used) >= len(POSES) - 1
    np.testing.assert_allclose(am.new.ofs_mps2, BIAS, atol=0.01)
    np.testing.assert_allclose(am.new.scale, 1 / np.array(GAIN), atol=0.002)
    np.testing.assert_allclose(cm.new.ofs_mgauss, -np.array(HARD), atol=1.5)
    K = np.array(SOFT)

    def raw_accel(f):  # u = K (f / g) ... the simulator's accelerometer: gain * f + bias (board frame)
        return f * np.array(GAIN) + BIAS

    def raw_mag(B):
        return B @ K.T + HARD

    e = attitude_errors(raw_accel, raw_mag, am.new, cm.new, FIELD)
    assert e.max_heading_deg < 0.3 and e.max_tilt_deg < 0.1, e
    assert e.max_heading_deg <= r.quality.heading_95_deg * 1.5 + 0.05


def test_quality_stage_reproduces_the_run_quality(run):
    """The pipeline only chains: quality_of on the run's own calibration and mapping gives its Quality."""
    from mavcal.judging.quality import quality_of

    _, r = run
    am, cm = r.mapping.accel[0], r.mapping.compass[0]
    q = r.quality
    again = quality_of(r.calibration, am, cm, am.old.board_matrix, 60, 0,
                       (q.holdout_accel_mps2, q.holdout_mag_mgauss))
    assert again == q


def test_truth_functions_are_the_reading_model():
    """raw = K R g + b (paper Eq. sensor_reading_model) with the body frame = engine frame."""
    from mavcal.judging.quality import truth_functions

    K_a = fw.GRAVITY_MSS * np.diag([1.0, 1.02, 0.98])
    b_a = np.array([0.1, -0.2, 0.3])
    h = np.array([1.0, 0.0, 1.5])
    K_m = np.diag([500.0, 480.0, 510.0]) / np.linalg.norm(h)
    b_m = np.array([40.0, 0.0, -20.0])
    ra, rm = truth_functions(K_a, b_a, K_m, b_m, h, np.eye(3), np.eye(3), 500.0)
    f = np.array([[0.0, 0.0, -fw.GRAVITY_MSS], [fw.GRAVITY_MSS, 0.0, 0.0]])
    np.testing.assert_allclose(ra(f), f / fw.GRAVITY_MSS @ K_a.T + b_a)
    B = np.array([[200.0, 0.0, 300.0]])
    np.testing.assert_allclose(rm(B), B * np.linalg.norm(h) / 500.0 @ K_m.T + b_m)


def test_open_source_sends_devices_to_link_live(monkeypatch):
    """A device string goes to mavcal.link.live.record_device (imported lazily), a path to read_log."""
    import sys
    import types

    from mavcal.pipeline import open_source

    calls = []
    fake = types.ModuleType("mavcal.link.live")
    fake.record_device = lambda device, **kw: calls.append((device, kw)) or "log"
    monkeypatch.setitem(sys.modules, "mavcal.link.live", fake)
    assert open_source("udpin:127.0.0.1:14550", baud=57600, duration_s=3.0) == "log"
    assert calls == [("udpin:127.0.0.1:14550", {"baud": 57600, "duration_s": 3.0, "heartbeat_timeout_s": 5.0,
                                                "param_timeout_s": 30.0, "rate_hz": 50.0, "progress": None,
                                                "tlog": None})]
    open_source("udpin:127.0.0.1:14550", tlog="s.tlog")  # the recording kept, for a device only
    assert calls[-1][1]["tlog"] == "s.tlog"
    with pytest.raises(UsageError, match="log file already"):
        open_source("x.tlog", tlog="s.tlog")
