"""Guided capture: pose words, advice, stop and abort rules (offline, with the test vehicle's sensor model)."""
import sys
from pathlib import Path

import numpy as np
import pytest

from mavcal.capture import CaptureConfig, CaptureSession, candidate_poses, coverage_map, describe_pose, euler_matrix
from mavcal.testing.vehicle import CompassTruth, TestVehicle, VehicleTruth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from capture_guidance import Hand  # noqa: E402  (the simulated hand of the benchmark)


@pytest.mark.parametrize("pose, words", [
    ((0, 0, 0), "level, nose towards magnetic north"),
    ((0, -90, 90), "nose down"),
    ((0, 90, 0), "nose up"),
    ((-90, 0, 90), "on its left side"),
    ((90, 0, 0), "on its right side"),
    ((180, 0, 0), "upside down"),
    ((-45, -45, 0), "rolled 45 deg left"),
])
def test_pose_words(pose, words):
    assert words in describe_pose(*pose)


def test_candidates_are_distinct_rotations():
    mats = np.array([euler_matrix(*p) for p in candidate_poses()])
    assert len(mats) > 100
    np.testing.assert_allclose(mats @ np.swapaxes(mats, 1, 2), np.broadcast_to(np.eye(3), mats.shape), atol=1e-12)


def _session(truth, target=0.5):
    v = TestVehicle(truth=truth, seed=3)
    return v, Hand(v), CaptureSession(v.params, CaptureConfig(target_heading_deg=target))


def test_following_the_advice_reaches_the_target():
    v, hand, sess = _session(VehicleTruth.random(3))
    st = sess.update()
    assert st.next_pose is not None and st.n_intervals == 0
    B = np.array(v.truth.earth_field_ned_mgauss)
    decl = np.degrees(np.arctan2(B[1], B[0]))
    for _ in range(20):
        a = st.next_pose
        sess.add(hand.go(euler_matrix(a.roll_deg, a.pitch_deg, a.yaw_deg + decl)))
        st = sess.update()
        if st.done:
            break
    assert st.done and not st.aborted, st.reason
    assert st.heading_95_deg <= 0.5 and st.n_intervals >= 8
    assert "target" in st.reason
    run = sess.result()
    assert run.accepted
    # the first advised poses are the six faces, distinct gravity directions
    g = np.array([p.gravity_body for p in sess.poses_advised[:6]])
    assert np.all((g @ g.T - np.eye(6)) < 0.75)  # no two within ~40 deg of each other
    assert "#" in coverage_map(st.gravity_dirs)


def test_magnet_next_to_the_compass_aborts_with_the_reason():
    t = VehicleTruth.random(4)
    bad = CompassTruth(dev_id=97539, offsets=(3500.0, -400.0, 200.0), external=True)
    truth = VehicleTruth(accels=t.accels, compasses=(bad,) + t.compasses[1:])
    v, hand, sess = _session(truth)
    st = sess.update()
    for pose in [(0, 0, 0), (-90, 0, 90)]:
        sess.add(hand.go(euler_matrix(*pose)))
        st = sess.update()
        if st.done:
            break
    assert st.aborted and st.done
    assert "magnet" in st.reason and "mGauss" in st.reason


def test_user_stop():
    v, hand, sess = _session(VehicleTruth.random(5))
    sess.add(hand.go(euler_matrix(0, 0, 0)))
    sess.stop("stopped by the user")
    st = sess.update()
    assert st.done and st.reason == "stopped by the user" and not st.aborted


def test_the_package_re_exports_the_session_the_screen_and_the_live_loop():
    import mavcal.capture as cap
    from mavcal.capture import live, screen, session

    assert cap.CaptureSession is session.CaptureSession and cap.status_line is screen.status_line
    assert cap.capture_live is live.capture_live and issubclass(cap.CaptureAbortedError, Exception)
    with pytest.raises(AttributeError):
        cap.no_such_name  # noqa: B018
