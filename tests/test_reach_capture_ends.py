"""A capture within reach always ends, and its advice never loops (issue 37), on the offline
simulated vehicle with the issue's errors: SIM_MAG1_OFS (-134, 117.1, -198.7), DIA (1.038, 1.0616,
0.9742), ODI (0.0135, 0.0012, 0.0085), the accelerometer's SIM_ACC1 errors, the wrong calibration
in force of the SITL fixture, at CMAC (a -66 deg dip), --max-tilt 15."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from mavcal.capture import CaptureConfig, CaptureSession, euler_matrix
from mavcal.errors import EstimationError
from mavcal.sources.wmm import field_at
from mavcal.testing.sitl import DEFAULT_HOME, WRONG_CALIBRATION
from mavcal.testing.vehicle import TestVehicle
from mavcal.testing.vehicle_sensors import AccelCalTruth, VehicleTruth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from capture_guidance import Hand  # noqa: E402  (the simulated hand of the benchmark)

CMAC = DEFAULT_HOME[:3]


def _vehicle(orientation: int = 0, configured: int = 0) -> TestVehicle:
    d, i, F = (np.radians(field_at(*CMAC)[0]), np.radians(field_at(*CMAC)[1]), field_at(*CMAC)[2])
    base = VehicleTruth.random(0)
    c0 = dataclasses.replace(base.compasses[0], offsets=(-134.0, 117.1, -198.7), dia=(1.038, 1.0616, 0.9742),
                             odi=(0.0135, 0.0012, 0.0085), orientation=orientation, noise_mgauss=1.7)
    truth = dataclasses.replace(base, accels=(AccelCalTruth((-0.021, 0.005, -0.431), (0.9716, 0.9736, 1.0294)),)
                                + base.accels[1:], compasses=(c0,) + base.compasses[1:],
                                earth_field_ned_mgauss=(F * np.cos(i) * np.cos(d), F * np.cos(i) * np.sin(d),
                                                        F * np.sin(i)))
    v = TestVehicle(truth=truth, seed=0)
    for name, value in {**WRONG_CALIBRATION, "COMPASS_ORIENT": float(configured)}.items():
        v.set_param_local(name, value)
    return v


def _capture(v: TestVehicle, max_poses: int = 40):
    sess = CaptureSession(v.params, CaptureConfig(max_tilt_deg=15.0, max_intervals=40), position=CMAC)
    shown: list[tuple[int, tuple[str, ...]]] = []
    st = Hand(v).follow(sess, max_poses, lambda s: shown.append((s.n_intervals, s.messages)))
    return sess, st, shown


def test_the_issue_vehicle_ends_within_25_poses_and_never_repeats_a_pose_without_saying_why():
    """The issue's accelerometer in force looks calibrated but its X/Y scales are 2-4 % off its truth: the
    poses say so, the bound carries it, and the capture ends with a verdict naming the accelerometer."""
    sess, st, shown = _capture(_vehicle())
    advised = [(p.roll_deg, p.pitch_deg, p.yaw_deg) for p in sess.poses_advised]
    assert st.done and not st.aborted and st.n_intervals <= 25, st.reason
    for k in range(1, len(advised)):  # a pose advised again only with the status saying why, when it is advised
        if advised[k] in advised[:k]:
            assert any("advised again" in m for m in shown[k - 1][1]), (k, advised[k], shown[k - 1])
    run = sess.result()
    (v,) = [v for v in run.verdicts if v.sensor == "compass0"]
    assert v.accepted or "the limit is the accelerometer, calibrated, but its X/Y scales" in " ".join(v.reasons)


def test_with_no_fit_ever_the_plan_never_cycles_and_the_cap_ends_with_what_was_measured(monkeypatch):
    """The SITL report of issue 37: no fit ever came ("heading -" throughout) and the advice
    cycled the plan's eight poses until 40 intervals."""
    import mavcal.capture.session as session

    def no_fit(*a, **k):
        raise EstimationError("no fit in this test")

    monkeypatch.setattr(session, "calibrate_prepared", no_fit)
    sess, st, shown = _capture(_vehicle())
    advised = [(p.roll_deg, p.pitch_deg, p.yaw_deg) for p in sess.poses_advised]
    assert st.done and st.n_intervals == 25, (st.n_intervals, st.reason)
    assert len(set(advised)) == len(advised), advised  # never a pose asked for before
    assert "25 poses" in st.reason and "distinct heading(s)" in st.reason and "deg from the first pose" in st.reason
    yaws = {q[2] for q in advised}
    assert len(yaws) >= 12, yaws  # new headings between those held, not the same six again


def test_headings_short_after_the_plan_are_said_with_those_seen_and_those_to_add():
    """Only two headings held (the person turns the vehicle end for end): once the plan's count of
    poses is held, the status lists the headings seen and the headings to add."""
    v = _vehicle()
    hand = Hand(v)
    sess = CaptureSession(v.params, CaptureConfig(max_tilt_deg=15.0), position=CMAC)
    B = np.array(v.truth.earth_field_ned_mgauss)
    decl = np.degrees(np.arctan2(B[1], B[0]))
    poses = [(0, 0, 0), (0, 15, 0), (15, 0, 0), (0, 0, 180), (0, -15, 180), (-15, 0, 180), (10.6, 10.6, 0),
             (-10.6, -10.6, 180)]
    for q in poses:
        sess.add(hand.go(euler_matrix(q[0], q[1], q[2] + decl)))
    st = sess.update()
    said = [m for m in st.messages if m.startswith("poses within reach")]
    assert said and "only 2 distinct heading(s)" in said[0] and "headings seen" in said[0], st.messages
    assert "0, 180 deg" in said[0] and "deg from the first pose's heading" in said[0], said


def test_a_compass_mounted_rotated_is_found_fitted_and_written_never_a_disturbance():
    """Issue 37: SIM_MAG1_ORIENT 6 with COMPASS_ORIENT 0 was blamed on a magnetic disturbance after
    32 poses; the tilts of the plan tell the turn, the fit takes it and COMPASS_ORIENT 6 is written."""
    sess, st, _ = _capture(_vehicle(orientation=6))
    assert st.done and not st.aborted and st.n_intervals <= 25, st.reason
    assert "disturbance" not in st.reason, st.reason
    run = sess.result()
    assert run.params_to_write(force=True).get("COMPASS_ORIENT") == 6.0
    said = "\n".join(run.reach.lines()) if getattr(run, "reach", None) is not None else ""
    kept = " ".join(k.text() for k in run.kept)
    assert "compass0 orientation kept" not in kept, kept
    assert not said or "turned 270 deg" in said, said


def test_a_compass_mounted_rotated_and_configured_so_is_calibrated():
    sess, st, _ = _capture(_vehicle(orientation=6, configured=6))
    assert st.done and not st.aborted and st.n_intervals <= 25, st.reason
    assert "mounted rotated" not in st.reason


def test_a_heading_bound_above_its_gate_names_the_kept_accelerometer():
    """Issue 37, item 4: the accelerometer in force 0.5 m/s^2 off (SITL's reproduction): a compass
    rejected for its heading bound (a gate of 0.2 deg here: its bound is about 0.5) is told that the
    bound counts the kept accelerometer's calibration and what to do, not "more poses at different
    headings, or steel and magnets"."""
    from dataclasses import replace

    from mavcal.autopilot.gates import GateConfig

    sess, st, _ = _capture(_vehicle())
    assert st.done and not st.aborted, st.reason
    opts = replace(sess.options, holdout=True, gates=GateConfig(heading_95_max_deg=0.2))
    run = sess.result(opts)
    verdict = {v.sensor: v for v in run.verdicts}["compass0"]
    assert not verdict.accepted
    said = " ".join(verdict.reasons)
    assert "the limit is the accelerometer" in said and "calibrate the accelerometer" in said, said
    assert "steel and magnets" not in said, said
