"""Guided capture: pose words, advice, stop and abort rules (offline, with the test vehicle's sensor model)."""
import sys
from pathlib import Path

import numpy as np
import pytest

from mavcal.capture import CaptureConfig, CaptureSession, candidate_poses, coverage_map, describe_pose, euler_matrix
from mavcal.testing.capture_truth import heading_error_vs_truth
from mavcal.testing.vehicle import CompassTruth, TestVehicle, VehicleTruth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from capture_guidance import Hand  # noqa: E402  (the simulated hand of the benchmark)

pytestmark = pytest.mark.cpu_sensitive  # .ci/avx2 runs these as an AVX2-only CPU would (issue 30)


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
    st = hand.follow(sess, 20)
    assert st.done and not st.aborted, st.reason
    assert st.heading_95_deg <= 0.5 and st.n_intervals >= 8
    assert "target" in st.reason
    run = sess.result()
    assert run.accepted
    # the vehicle's truth: the written calibration's heading error, level, within the target
    assert heading_error_vs_truth(v, run.params_to_write()) <= 0.5  # seen 0.21 (the bound said 0.38)
    assert heading_error_vs_truth(v, {}) > 10  # the check sees a calibration that is wrong (seen 52)
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


def _rotated(seed=3, orient=6):
    """Random sensor errors and an external compass mounted rotated (COMPASS_ORIENT ``orient``)."""
    import dataclasses

    t = VehicleTruth.random(seed)
    comp = dataclasses.replace(t.compasses[0], orientation=orient)
    v = TestVehicle(truth=dataclasses.replace(t, compasses=(comp,) + t.compasses[1:]), seed=seed,
                    params={"COMPASS_ORIENT": orient})
    B = np.array(v.truth.earth_field_ned_mgauss)
    return v, Hand(v), float(np.degrees(np.arctan2(B[1], B[0])))


def _go(hand, decl, pose):
    return hand.go(euler_matrix(pose[0], pose[1], pose[2] + decl))


def test_advice_never_repeats_a_recorded_pose_and_a_quick_return_is_reported_and_refitted():
    """Rotated compass: after the plan and a fit, every advice is a pose not yet recorded; a
    return to the last pose within 3 s merges into its interval (count unchanged) and is said."""
    v, hand, decl = _rotated()
    sess = CaptureSession(v.params, CaptureConfig(target_heading_deg=0.01, min_intervals=8))
    st = sess.update()
    held = []
    for _ in range(9):
        a = st.next_pose
        pose = (a.roll_deg, a.pitch_deg, a.yaw_deg)
        assert pose not in held  # never a recorded pose
        sess.add(_go(hand, decl, pose))
        held.append(pose)
        st = sess.update()
    assert st.n_intervals == 9 and sess.run is not None
    fits = sess.run
    # back to the last pose within 3 s (a short turn away and back): merged, said, refitted
    away = (held[-1][0] + 30.0, held[-1][1], held[-1][2])
    hand.hold_s = 0.2
    sess.add(_go(hand, decl, away))
    hand.hold_s = 2.0
    sess.add(_go(hand, decl, held[-1]))
    st = sess.update()
    assert st.n_intervals == 9
    assert any("merged into that interval" in m for m in st.messages), st.messages
    assert sess.run is not fits  # the merged interval changed: a new fit
    assert len(sess.run.segmentation.intervals[-1].pieces_s) == 2
    a = st.next_pose
    assert (a.roll_deg, a.pitch_deg, a.yaw_deg) not in held


def test_a_stall_changes_the_advice_and_says_why():
    v, hand, decl = _rotated(seed=4)
    sess = CaptureSession(v.params, CaptureConfig(stall_advices=3))
    st = sess.update()
    for _ in range(2):
        sess.add(_go(hand, decl, (st.next_pose.roll_deg, st.next_pose.pitch_deg, st.next_pose.yaw_deg)))
        st = sess.update()
    stuck = st.next_pose
    # the hand never gets there: no new interval, advice after advice
    seen = []
    for _ in range(3):
        st = sess.update()
        seen.append(st)
    assert sess.stalls == 1
    assert any("no new still interval for 3 advices" in m for m in seen[-1].messages)
    assert (st.next_pose.roll_deg, st.next_pose.pitch_deg, st.next_pose.yaw_deg) != \
        (stuck.roll_deg, stuck.pitch_deg, stuck.yaw_deg)


class _FakeStdin:
    def __init__(self, text: str, tty: bool = True):
        self.text, self.tty = text, tty

    def isatty(self) -> bool:
        return self.tty

    def readline(self) -> str:
        return self.text


def test_the_confirmation_prompt_is_on_the_terminal_not_stderr(monkeypatch, capsys):
    from mavcal.commands import common
    from mavcal.errors import UsageError

    monkeypatch.delenv("CI", raising=False)
    # a controlling terminal: prompt and answer go through it (seen even with `> f 2> g`)
    import io

    class Tty(io.StringIO):
        def close(self) -> None:
            self.shown = self.getvalue()
            super().close()

    tty = Tty()
    monkeypatch.setattr(common, "_open_tty", lambda: tty)
    monkeypatch.setattr(Tty, "readline", lambda self, *a: "y\n")
    monkeypatch.setattr("sys.stdin", _FakeStdin("n\n"))
    common.confirm("write 3 parameter(s)?", False)
    assert tty.shown == "write 3 parameter(s)? [y/N] "
    out, err = capsys.readouterr()
    assert err == "" and out == ""

    # no /dev/tty: the prompt goes to stdout, the answer comes from stdin
    def no_tty():
        raise OSError("no tty")

    monkeypatch.setattr(common, "_open_tty", no_tty)
    with pytest.raises(UsageError, match="cancelled"):
        common.confirm("write 3 parameter(s)?", False)
    out, err = capsys.readouterr()
    assert out == "write 3 parameter(s)? [y/N] " and err == ""
    # nobody to answer: refused without asking
    monkeypatch.setattr("sys.stdin", _FakeStdin("y\n", tty=False))
    with pytest.raises(UsageError, match="stdin is not a terminal"):
        common.confirm("write?", False)
    monkeypatch.setattr("sys.stdin", _FakeStdin("y\n"))
    monkeypatch.setenv("CI", "true")
    with pytest.raises(UsageError, match="CI is set"):
        common.confirm("write?", False)
    common.confirm("write?", True)  # --yes
    assert capsys.readouterr() == ("", "")


def test_the_summary_says_why_the_held_out_error_was_not_run():
    """8 intervals, each pose once: no held-out error, and the summary says why instead of nan."""
    from mavcal.report.text import summary_text

    v, hand, decl = _rotated(seed=5, orient=0)
    sess = CaptureSession(v.params, CaptureConfig(target_heading_deg=0.01, max_intervals=8))
    st = sess.update()
    while not st.done:
        sess.add(_go(hand, decl, (st.next_pose.roll_deg, st.next_pose.pitch_deg, st.next_pose.yaw_deg)))
        st = sess.update()
    run = sess.result()
    assert np.isnan(run.quality.holdout_accel_mps2)
    text = summary_text(run)
    assert "nan" not in text
    assert "held-out error: not run (" in text and ("held twice" in text or "leaving one of" in text)


def test_the_status_screen_shows_the_calibrated_field_and_the_raw_one_as_raw():
    from mavcal.capture import status_screen

    v, hand, decl = _rotated(seed=3, orient=0)
    sess = CaptureSession(v.params, CaptureConfig(target_heading_deg=0.01))
    st = sess.update()
    sess.add(_go(hand, decl, (0, 0, 0)))
    st = sess.update()
    assert st.field_calibrated_mgauss is None and "mGauss raw (not calibrated yet)" in status_screen(st)
    for _ in range(8):
        sess.add(_go(hand, decl, (st.next_pose.roll_deg, st.next_pose.pitch_deg, st.next_pose.yaw_deg)))
        st = sess.update()
    mapped = sess.run.mapping.compass[0].field_mgauss  # the magnitude the written calibration gives
    assert abs(st.field_calibrated_mgauss - mapped) < 0.01 * mapped
    assert abs(st.field_mgauss - mapped) > 0.05 * mapped  # the raw reading is off (offsets, soft iron)
    screen = status_screen(st)
    assert f"field: {st.field_calibrated_mgauss:.0f} mGauss calibrated (raw reading {st.field_mgauss:.0f}" in screen
