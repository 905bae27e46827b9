"""End to end on simulated ArduPilot logs with a known truth: .bin and .tlog, with a wrong
calibration in force on the simulated autopilot, hand tremor and motion between poses."""
import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.evaluate import attitude_errors
from mavcal.pipeline import Options, calibrate_source
from mavcal.testing.simlog import AccelErrorTruth as AccelTruth
from mavcal.testing.simlog import MagTruth, SimConfig, simulate_session

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
    cfg = SimConfig(accels=(AccelTruth(bias_mps2=BIAS, gain=GAIN, noise_mps2=0.03),),
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
