"""Guided live capture against the loopback test vehicle, with a simulated hand that follows the advice.

The hand is a thread: it reads the latest advice (number of intervals kept, next pose), and
once the interval at the pose it holds has been counted it turns the vehicle for a moment
(``set_moving``) and holds the advised pose (yaw + the field's declination: the advice is
relative to magnetic north, the vehicle's attitude to true north).
"""
import socket
import threading
import time

import numpy as np
import pytest

from mavcal import cli, live_capture
from mavcal.ardupilot.paramfile import read_param_file
from mavcal.capture import CaptureConfig
from mavcal.link.testvehicle import CompassTruth, TestVehicle, VehicleTruth
from mavcal.segment import StillConfig

HOLD = StillConfig(min_duration_s=0.6, window_s=0.4)


def declination_deg(vehicle: TestVehicle) -> float:
    B = vehicle.truth.earth_field_ned_mgauss
    return float(np.degrees(np.arctan2(B[1], B[0])))


class AdviceHand(threading.Thread):
    """Moves ``vehicle`` to each advised pose once the pose it holds has been counted.

    ``advice()`` returns ``(n_intervals, (roll, pitch, yaw_magnetic) or None, done)``.
    """

    def __init__(self, vehicle: TestVehicle, advice, *, move_s: float = 0.3, extra_hold_s: float = 0.5):
        super().__init__(name="test-hand", daemon=True)
        self.v, self.advice = vehicle, advice
        self.decl = declination_deg(vehicle)
        self.move_s, self.extra_hold_s = move_s, extra_hold_s
        self.halt = threading.Event()
        self.poses = []

    def run(self) -> None:
        held_n = None
        while not self.halt.is_set():
            n, pose, done = self.advice()
            if done:
                return
            if pose is not None and (held_n is None or n > held_n):
                if held_n is not None and self.halt.wait(self.extra_hold_s):  # let the interval settle
                    return
                self.v.set_moving(True)
                if self.halt.wait(self.move_s):
                    return
                self.v.set_attitude(roll=pose[0], pitch=pose[1], yaw=pose[2] + self.decl)
                self.poses.append(pose)
                held_n = n
            self.halt.wait(0.05)

    def stop(self) -> None:
        self.halt.set()
        if self.is_alive():
            self.join(timeout=5)


class StatusFeed:
    """Latest CaptureStatus, as the hand's advice."""

    def __init__(self):
        self.latest = None
        self.all = []

    def __call__(self, st) -> None:
        self.latest = st
        self.all.append(st)

    def advice(self):
        st = self.latest
        if st is None:
            return 0, None, False
        a = st.next_pose
        return st.n_intervals, (None if a is None else (a.roll_deg, a.pitch_deg, a.yaw_deg)), st.done


@pytest.fixture
def vehicle():
    v = TestVehicle(truth=VehicleTruth.random(3), seed=3, heartbeat_hz=5).start()
    try:
        yield v
    finally:
        v.stop()


def test_api_capture_reaches_the_target(vehicle):
    feed = StatusFeed()
    hand = AdviceHand(vehicle, feed.advice)
    hand.start()
    try:
        sess = live_capture.capture_live(vehicle.gcs_device, config=CaptureConfig(still=HOLD), on_status=feed,
                                         rate_hz=25, max_duration_s=60)
    finally:
        hand.stop()
    st = sess.status
    assert st.done and not st.aborted, st.reason
    assert st.heading_95_deg <= 0.5 and "target" in st.reason
    assert st.n_intervals >= 8
    # the hand followed the advice: the first six poses were the six faces the session asked for
    assert len(hand.poses) >= 8
    run = sess.result()
    assert run.accepted
    c0 = vehicle.truth.compasses[0]
    new = run.mapping.new
    ofs = np.array([new["COMPASS_OFS_X"], new["COMPASS_OFS_Y"], new["COMPASS_OFS_Z"]])
    assert np.all(np.abs(ofs - np.array(c0.offsets)) < 15.0), (ofs, c0.offsets)
    # the streams went back to their default rates at the end (SET_MESSAGE_INTERVAL param2 = 0)
    resets = [c for c in vehicle.commands if c[0] == 511 and c[1][1] == 0]
    assert {int(c[1][0]) for c in resets} == {27, 116, 129}


def test_cli_capture_writes_with_write_yes(vehicle, tmp_path, monkeypatch, capsys):
    feed = StatusFeed()
    real = live_capture.capture_live

    def tee(device, *, on_status=None, **kw):  # the CLI's printer, and the hand's view of the same statuses
        def both(st):
            feed(st)
            on_status(st)
        return real(device, on_status=both, **kw)

    monkeypatch.setattr(live_capture, "capture_live", tee)
    hand = AdviceHand(vehicle, feed.advice)
    before = vehicle.params
    hand.start()
    try:
        rc = cli.main(["capture", "--connect", vehicle.gcs_device, "--hold", "0.6", "--rate", "25",
                       "--duration", "60", "--write", "--yes", "--param-out", str(tmp_path / "new.param"),
                       "--json", str(tmp_path / "run.json"), "--backup", str(tmp_path / "backup.param")])
    finally:
        hand.stop()
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert feed.latest.done and feed.latest.heading_95_deg <= 0.5
    # piped: one status line per change, with the next pose in words
    assert "next: level, nose towards magnetic north" in err
    assert "done: heading error bound" in err
    # the summary, then the safe writer's report
    assert "written and verified" in out
    new = read_param_file(tmp_path / "new.param")
    changed = [n for n, v in new.items() if not np.isclose(before[n], v, rtol=0, atol=1e-6)]
    assert changed
    for n, v in new.items():
        assert vehicle.get_param(n) == pytest.approx(float(np.float32(v)), rel=1e-6, abs=1e-6), n
    assert set(vehicle.force_saves) == {"compass", "accel"}
    backup = read_param_file(tmp_path / "backup.param")
    assert set(backup) == set(changed) and all(backup[n] == pytest.approx(before[n], abs=1e-5) for n in backup)
    assert (tmp_path / "run.json").stat().st_size > 0


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_device_that_does_not_answer_exits_3(capsys):
    t0 = time.monotonic()
    rc = cli.main(["capture", "--connect", f"udpin:127.0.0.1:{_free_udp_port()}", "--timeout", "1"])
    took = time.monotonic() - t0
    _, err = capsys.readouterr()
    assert rc == 3, err
    assert "no heartbeat" in err
    assert took < 10  # a generous bound: the heartbeat timeout is 1 s


def test_impossible_field_aborts_with_exit_4(capsys, tmp_path):
    t = VehicleTruth.random(4)
    magnet = CompassTruth(dev_id=97539, offsets=(3500.0, -400.0, 200.0), external=True)
    v = TestVehicle(truth=VehicleTruth(accels=t.accels, compasses=(magnet,) + t.compasses[1:]), seed=4,
                    heartbeat_hz=5).start()
    try:  # the vehicle sits still: the first interval already shows the field
        rc = cli.main(["capture", "--connect", v.gcs_device, "--hold", "0.6", "--duration", "30", "--write",
                       "--yes", "--backup", str(tmp_path / "b.param")])
    finally:
        v.stop()
    _, err = capsys.readouterr()
    assert rc == 4, err
    assert "capture aborted: impossible magnetic field" in err and "mGauss" in err
    assert v.param_sets == [] and v.force_saves == []  # nothing written
    assert not (tmp_path / "b.param").exists()


def test_usage_errors_exit_2(capsys):
    assert cli.main(["capture", "--connect", "udpin:127.0.0.1:1", "--target-deg", "0"]) == 2
    with pytest.raises(SystemExit) as exc:  # --connect is required (argparse exits)
        cli.main(["capture"])
    assert exc.value.code == 2
