"""The guided capture stops only when every sensor that will be written meets its target
(issue 22): every compass's heading bound and every accelerometer's own tilt bound; the advice
goes to the sensor furthest from its target; a sensor that cannot get there is named with the
reason and the capture can finish without it. Offline, with the benchmark's simulated hand
holding the test vehicle's 3 IMUs and 3 compasses."""
import queue
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mavcal.capture import CaptureConfig, CaptureSession, status_line, status_screen
from mavcal.capture.progress import SensorProgress, stop_reason
from mavcal.capture.worker import CaptureWorker
from mavcal.sources.types import SensorSeries
from mavcal.testing.capture_truth import heading_error_vs_truth
from mavcal.testing.vehicle import TestVehicle, VehicleTruth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from capture_guidance import Hand  # noqa: E402  (the simulated hand of the benchmark)

pytestmark = pytest.mark.cpu_sensitive  # .ci/avx2 runs these as an AVX2-only CPU would (issue 30)

ALL = ("accel0", "accel1", "accel2", "compass0", "compass1", "compass2")


class DisturbedHand(Hand):
    """Compass 1 sits next to something that bends the field differently in every pose."""

    def __init__(self, *a, disturb_mgauss: float = 200.0, **kw):
        super().__init__(*a, **kw)
        self.rng = np.random.default_rng(99)
        self.disturb = disturb_mgauss

    def go(self, C):
        out = super().go(C)
        d = self.rng.normal(0.0, self.disturb, 3)
        return [replace(s, values=np.trunc(s.values + d)) if s.sensor == "mag" and s.instance == 1 else s
                for s in out]


def _capture(hand, sess, poses=30, on_status=None):
    return hand.follow(sess, poses, on_status)


def test_every_sensor_reaches_its_target_and_is_accepted_with_the_default_settings():
    v = TestVehicle(truth=VehicleTruth.random(6), seed=6)
    sess = CaptureSession(v.params)  # the product's defaults
    advised_for = []

    def check(st):
        if st.advice_for is not None and st.sensors:
            todo = [p for p in st.sensors if not p.met and not p.blocked]
            if todo:  # the advice goes to the sensor furthest from its target
                assert st.advice_for == max(todo, key=lambda p: p.distance).sensor
            advised_for.append(st.advice_for)
        return False

    st = _capture(Hand(v, instances=(0, 1, 2)), sess, on_status=check)
    assert st.done and not st.aborted, st.reason
    assert tuple(p.sensor for p in st.sensors) == ALL
    assert all(p.met for p in st.sensors), st.sensors
    assert "on every compass" in st.reason and "on every accelerometer" in st.reason
    assert st.heading_95_deg <= 0.5
    # the advice was checked (it went to the sensor furthest from its target); this vehicle meets
    # every target at its first fit since a chance chi2/dof no longer widens the extra compasses'
    # bounds, so advice to other sensors is checked in the accelerometer test below
    assert advised_for
    run = sess.result()
    assert {x.sensor: x.accepted for x in run.gates.verdicts()} == dict.fromkeys(ALL, True)
    assert "every sensor's bound/target (deg): accel0 tilt" in status_screen(st)
    written = run.params_to_write()
    for k in range(len(v.truth.compasses)):  # the vehicle's truth: every compass within the target, level
        assert heading_error_vs_truth(v, written, instance=k) <= 0.5, k


def test_a_disturbed_compass_is_named_with_the_reason_and_the_capture_can_finish_without_it():
    v = TestVehicle(truth=VehicleTruth.random(7), seed=7)
    sess = CaptureSession(v.params, CaptureConfig(max_intervals=25))
    offered = []

    def until_offered(st):
        if st.offer_finish_without:
            offered.append(st)
            return True
        return False

    st = _capture(DisturbedHand(v, instances=(0, 1, 2)), sess, on_status=until_offered)
    assert offered, [p for p in st.sensors]
    st = offered[-1]
    assert st.offer_finish_without == ("compass1",) and not st.done
    c1 = next(p for p in st.sensors if p.sensor == "compass1")
    assert "disturbance" in c1.blocked or "not improved" in c1.blocked, c1
    assert any(m.startswith("compass1 cannot reach its target") for m in st.messages)
    assert "compass1 cannot reach the target: stop to finish without" in status_line(st)
    # 'mavcal finish' in MAVProxy: the worker's finish job drops it from the stop rule
    w = CaptureWorker(lambda: None)
    try:
        w.session, w.status, w.capturing = sess, st, True
        before = st
        w.submit("finish")
        said = _said(w, "going on without")
        assert said.startswith("mavcal: going on without compass1: the capture ends when the other sensors")
        deadline = time.monotonic() + 60
        while sess.status is before and time.monotonic() < deadline:  # the update that follows
            time.sleep(0.05)
        st = sess.status
        others = [p for p in st.sensors if p.sensor != "compass1"]
        # which branch this takes depends on the simulated hand's data, which move with the CPU's
        # floating-point paths (issue 30): both are the product's rule, checked for consistency here
        # and each on its own, whatever the digits, in test_finish_ends_the_capture_when_the_others_are_met
        if all(p.met for p in others):  # the others were there already: done at once, without compass1
            assert st.done and "finished without compass1" in st.reason, st.reason
            _said(w, "capture finished")
        else:  # else the capture goes on for them, and says what each still needs
            assert not st.done and st.advice_for != "compass1"
            for p in others:
                if not p.met and p.bound_deg is not None and p.bound_deg <= p.target_deg:
                    assert p.needs and any(m.startswith(f"{p.sensor}'s bound is at its target") for m in st.messages)
        assert next(p for p in st.sensors if p.sensor == "compass1").dropped
    finally:
        assert w.shutdown(timeout_s=60)


def _progress(sensor, bound, target=0.5, **kw):
    return SensorProgress(sensor, "tilt" if sensor.startswith("accel") else "heading", bound, target, **kw)


def test_finish_ends_the_capture_when_the_others_are_met():
    """The stop rule on given progress, no fit: a finish asked for while every other sensor meets
    its target ends the capture at once, whatever its last digits; a sensor whose bound is under
    its target while calibrate's coverage rule still fails it has not met it, and the capture goes on."""
    from types import SimpleNamespace

    from mavcal.autopilot.gates import GateReport

    v = TestVehicle(truth=VehicleTruth.random(7), seed=7)
    sess = CaptureSession(v.params)
    run = SimpleNamespace(gates=GateReport(()))
    blocked = "its calibrated field magnitude differs by 85 % between poses"
    sess._progress = (_progress("accel0", 0.06, 0.3), _progress("compass0", 0.49999),
                      _progress("compass1", 42.0, blocked=blocked))
    done, reason, offer = sess._stop_rule(run, 9, False, "")
    assert not done and offer == ("compass1",) and "compass1 cannot" in reason
    assert sess.finish_without() == ("compass1",)
    sess._progress = tuple(replace(p, dropped=True) if p.sensor == "compass1" else p for p in sess._progress)
    done, reason, offer = sess._stop_rule(run, 9, False, "")
    assert done and "finished without compass1" in reason and blocked in reason, reason
    # a bound at its target whose poses do not identify the sensor yet: not met, the capture goes on
    needs = "field directions: only 7 distinct field directions (value 7, limit >= 8 distinct)"
    sess._progress = (_progress("accel0", 0.06, 0.3), _progress("compass0", 0.39, needs=needs),
                      _progress("compass1", 42.0, blocked=blocked, dropped=True))
    assert not sess._progress[1].met
    done, reason, offer = sess._stop_rule(run, 9, False, "")
    assert not done and offer == ()


def _said(w, text, timeout=60.0):
    deadline = time.monotonic() + timeout
    seen = []
    while time.monotonic() < deadline:
        try:
            seen.append(w.out.get(timeout=0.1))
        except queue.Empty:
            continue
        if text in seen[-1]:
            return seen[-1]
    raise AssertionError(f"the worker did not say {text!r}: {seen}")


def test_finish_outside_a_capture_and_with_nothing_to_drop():
    w = CaptureWorker(lambda: None)
    try:
        w.submit("finish")
        assert _said(w, "not capturing") == "mavcal: not capturing"
    finally:
        assert w.shutdown()


def test_the_advice_goes_to_an_accelerometer_when_it_is_the_furthest_from_its_target():
    v = TestVehicle(truth=VehicleTruth.random(8), seed=8)
    # a tilt target no 8-pose capture meets, a heading target every one does: the accelerometers lead
    sess = CaptureSession(v.params, CaptureConfig(target_tilt_deg=0.02, target_heading_deg=5.0, max_intervals=10))
    seen = []
    st = _capture(Hand(v, instances=(0, 1, 2)), sess, poses=10, on_status=lambda s: seen.append(s) and False)
    assert all(s.advice_for is None for s in seen if s.n_intervals < 6)  # the fixed plan before a fit
    after_fit = [s for s in seen if s.sensors and s.sensors[0].bound_deg is not None and not s.done]
    to_accel = [s for s in after_fit if s.advice_for.startswith("accel")]
    assert len(to_accel) >= len(after_fit) - 1  # (a compass's fit can glitch for one pose at 9 intervals)
    # each accelerometer's tilt bound falls as the poses advised for them come in
    tilt = [max(p.bound_deg for p in s.sensors if p.kind == "tilt") for s in after_fit]
    assert tilt[-1] < 0.9 * tilt[0]
    assert st.done and "maximum" in st.reason


def test_the_stop_reason_names_the_worst_sensor_of_each_kind_and_those_left_out():
    ps = (SensorProgress("accel0", "tilt", 0.05, 0.3), SensorProgress("accel1", "tilt", 0.12, 0.3),
          SensorProgress("compass0", "heading", 0.41, 0.5),
          SensorProgress("compass1", "heading", 3.2, 0.5, blocked="disturbed", dropped=True))
    r = stop_reason(ps)
    assert r.startswith("heading error bound 0.41 deg <= target 0.5 deg on every compass (worst: compass0)")
    assert "tilt error bound 0.12 deg <= target 0.3 deg on every accelerometer (worst: accel1)" in r
    assert r.endswith("finished without compass1 (disturbed)")
    assert ps[1].met and not ps[3].met and ps[3].distance == 3.2 / 0.5
    assert SensorProgress("accel2", "tilt", None, 0.3).distance == float("inf")


def test_no_imu_data_yet_has_no_sensors_and_the_plan():
    sess = CaptureSession({})
    st = sess.update()
    assert st.sensors == () and st.next_pose is not None and not st.done
    sess.add([SensorSeries("gyro", 0, "RAW_IMU", np.arange(3.0), np.zeros((3, 3)))])
    assert sess.update().sensors == ()
