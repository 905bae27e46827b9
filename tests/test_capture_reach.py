"""The guided capture of a vehicle that cannot be turned over (``--max-tilt``, issue 27): only
poses within the tilt limit are advised, "can't do this one" gets another pose, the capture
stops when the compass's bound reaches what such poses can give (or its target), and the result
writes the compass and the accelerometer's offsets (issue 37; its scales kept), right to within
0.5 deg of heading at level."""
import sys
from pathlib import Path

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.evaluate import attitude_errors, attitude_grid
from mavcal.capture import CaptureConfig, CaptureSession, candidate_poses, euler_matrix
from mavcal.capture.session import reach_plan
from mavcal.testing.vehicle import TestVehicle, VehicleTruth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from capture_guidance import Hand  # noqa: E402  (the simulated hand of the benchmark)


def _tilt_deg(pose) -> float:
    C = euler_matrix(*pose)
    return float(np.degrees(np.arccos(np.clip(C[2, 2], -1.0, 1.0))))


@pytest.mark.parametrize("max_tilt", [5.0, 15.0])
def test_candidates_and_plan_stay_within_the_tilt_limit(max_tilt):
    poses = candidate_poses(max_tilt) + reach_plan(max_tilt)
    assert max(_tilt_deg(q) for q in poses) <= max_tilt + 0.1
    assert {q[2] for q in candidate_poses(max_tilt)} == {float(y) for y in range(0, 360, 45)}  # any heading


def _vehicle(seed: int) -> TestVehicle:
    """A vehicle whose accelerometer was calibrated before (0.02 m/s^2 off its truth): the
    calibration poses within reach keep."""
    truth = VehicleTruth.random(seed)
    v = TestVehicle(truth=truth, seed=seed)
    a = truth.accels[0]
    for name, value in fw.accel_param_values(fw.AccelCal(ofs_mps2=tuple(np.array(a.offsets) + 0.02),
                                                         scale=a.scale), 0).items():
        v.set_param_local(name, value)
    return v


def test_capture_within_reach_follows_skips_and_writes_the_compass_and_the_accel_offsets():
    v = _vehicle(3)
    hand = Hand(v)
    sess = CaptureSession(v.params, CaptureConfig(max_tilt_deg=15.0, max_intervals=30))
    B = np.array(v.truth.earth_field_ned_mgauss)
    decl = np.degrees(np.arctan2(B[1], B[0]))
    st = sess.update()
    skipped = None
    for k in range(30):
        a = st.next_pose
        if k == 3:  # "can't do this one": another pose, and the one skipped is never advised again
            skipped = (a.roll_deg, a.pitch_deg, a.yaw_deg)
            a = sess.skip_pose()
            assert (a.roll_deg, a.pitch_deg, a.yaw_deg) != skipped and sess.status.next_pose == a
        sess.add(hand.go(euler_matrix(a.roll_deg, a.pitch_deg, a.yaw_deg + decl)))
        st = sess.update()
        if st.done:
            break
    assert st.done and not st.aborted, st.reason
    assert "the bound has reached its floor" in st.reason or "<= target 0.5 deg" in st.reason, st.reason
    advised = [(p.roll_deg, p.pitch_deg, p.yaw_deg) for p in sess.poses_advised]
    assert max(_tilt_deg(q) for q in advised) <= 15.1
    assert skipped not in advised[advised.index(skipped) + 1:]
    assert [p.sensor for p in st.sensors] == ["compass0"]  # the stop rule is the compass's
    run = sess.result()
    assert run.accepted and [v_.sensor for v_ in run.verdicts] == ["accel0", "compass0"]
    write = run.params_to_write()
    # the accelerometer's offsets fitted (in force 0.02 m/s^2 off: closer now), its scales kept as they were
    at = v.truth.accels[0]
    ofs = np.array([write[n] for n in fw.accel_param_names(0)["ofs"]])
    assert np.abs(ofs - np.array(at.offsets)).max() < 0.02, ofs
    old_scale = fw.accel_cal_from_params(v.params, 0).scale
    assert fw.accel_cal_from_params({**v.params, **write}, 0).scale == pytest.approx(old_scale, rel=1e-6)
    ct, at = v.truth.compasses[0], v.truth.accels[0]
    M = fw.soft_iron_matrix(ct.dia, ct.odi)
    written = fw.compass_cal_from_params({**v.params, **write}, 0)
    accel_now = fw.accel_cal_from_params({**v.params, **write}, 0)
    for max_tilt, bound in ((0.0, 0.5), (15.0, run.quality.heading_95_deg)):
        e = attitude_errors(lambda f: f / np.array(at.scale) + np.array(at.offsets),
                            lambda b: b @ np.linalg.inv(M).T / ct.scale - np.array(ct.offsets),
                            accel_now, written, B, attitude_grid(max_tilt_deg=max_tilt))
        assert e.max_heading_deg <= bound, (max_tilt, e)


@pytest.mark.parametrize("deg", ["60", "0.5", "-5"])
def test_max_tilt_outside_what_counts_as_within_reach_is_a_usage_error(deg, capsys):
    from mavcal import cli

    assert cli.main(["capture", "--connect", "udpin:127.0.0.1:1", "--max-tilt", deg]) == 2
    assert "--max-tilt must be 3-40 deg" in capsys.readouterr().err
