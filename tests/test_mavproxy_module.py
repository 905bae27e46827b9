"""The mavcal MAVProxy module in a real MAVProxy process, talking to the loopback test vehicle.

MAVProxy is driven through its stdin (as a person types), its output is read line by line;
the simulated hand (tests/test_live_capture.py) follows the advice the module prints. The
process is killed in a finally; every wait is bounded.
"""
import importlib.util
import os
import re
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from test_live_capture import AdviceHand

from mavcal.autopilot.paramfile import read_param_file
from mavcal.testing.vehicle import VehicleTruth

pytestmark = pytest.mark.skipif(importlib.util.find_spec("MAVProxy") is None,
                                reason="MAVProxy is not installed (pip install mavcal[test])")

_ADVICE = re.compile(r"mavcal: (\d+) intervals, \w+, heading (?:\S+ deg|not determined)"
                     r"(?:; next: .*\(roll (\S+) pitch (\S+) yaw (\S+) deg magnetic\)|: (done|ABORTED))")


class MAVProxy:
    """A MAVProxy process: send lines to its stdin, wait for patterns in its output."""

    def __init__(self, master: str, cwd, out: str | None = None):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.started = time.monotonic()  # MAVProxy asks for its stream rates every 15 s from about now
        self.p = subprocess.Popen([sys.executable, "-m", "MAVProxy.mavproxy", "--master", master, "--no-state",
                                   "--default-modules=link,param", *(["--out", out] if out else [])],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, cwd=str(cwd), env=env)
        self.lines = []
        self.cond = threading.Condition()
        self.reader = threading.Thread(target=self._read, name="mavproxy-reader", daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            with self.cond:
                self.lines.append(line.rstrip("\n"))
                self.cond.notify_all()
        with self.cond:
            self.cond.notify_all()

    def send(self, text: str) -> int:
        """Type one command; returns the output position before it (for expect(after=...))."""
        with self.cond:
            mark = len(self.lines)
        self.p.stdin.write(text + "\n")
        self.p.stdin.flush()
        return mark

    def expect(self, pattern: str, timeout: float = 15.0, after: int = 0):
        """The first match of ``pattern`` in the output after line ``after`` (fails after ``timeout``)."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        i = after
        with self.cond:
            while True:
                while i < len(self.lines):
                    m = rx.search(self.lines[i])
                    if m:
                        return m, i + 1
                    i += 1
                left = deadline - time.monotonic()
                if left <= 0 or (self.p.poll() is not None and not self.reader.is_alive()):
                    tail = "\n".join(self.lines[-40:])
                    pytest.fail(f"no {pattern!r} in MAVProxy's output within {timeout} s; last lines:\n{tail}")
                self.cond.wait(min(left, 0.2))

    def advice(self):
        """The module's latest status line as the hand's advice."""
        with self.cond:
            for line in reversed(self.lines):
                m = _ADVICE.search(line)
                if m:
                    n = int(m.group(1))
                    if m.group(5):
                        return n, None, True
                    return n, tuple(float(m.group(k)) for k in (2, 3, 4)), False
        return 0, None, False

    def close(self) -> None:
        try:
            if self.p.poll() is None:
                self.p.stdin.close()  # EOF: MAVProxy unloads its modules and exits
                self.p.wait(timeout=10)
        except (subprocess.TimeoutExpired, OSError):
            pass
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait(timeout=5)
            self.reader.join(timeout=5)


class RawImuClock(threading.Thread):
    """Receive times of the RAW_IMU messages MAVProxy forwards to its ``--out`` (what the vehicle streams)."""

    def __init__(self):
        super().__init__(name="test-raw-imu", daemon=True)
        from pymavlink import mavutil

        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        self.port = s.getsockname()[1]
        s.close()
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}")
        self.times = []
        self.halt = threading.Event()

    def run(self) -> None:
        while not self.halt.is_set():
            m = self.conn.recv_match(type="RAW_IMU", blocking=True, timeout=0.1)
            if m is not None:
                self.times.append(time.monotonic())

    def rates(self, t0: float, t1: float, window_s: float = 1.0):
        """RAW_IMU per second in 1 s windows sliding by 0.25 s over [t0, t1]."""
        t = np.array(self.times)
        starts = np.arange(t0, t1 - window_s, 0.25)
        return [int(((t >= a) & (t < a + window_s)).sum()) / window_s for a in starts]

    def stop(self) -> None:
        self.halt.set()
        self.join(timeout=5)
        self.conn.close()


def _changed_rows(lines, start):
    """(name, new value) of the writer's table rows marked ok after output line ``start``."""
    rows = {}
    for line in lines[start:]:
        m = re.search(r"(\w+)\s+\S+\s+->\s+(\S+)\s+ok$", line)
        if m:
            rows[m.group(1)] = float(m.group(2))
    return rows


def test_mavproxy_module_capture_fit_write_restore_unload(tmp_path, start_vehicle):
    v = start_vehicle(truth=VehicleTruth.random(3), seed=3, heartbeat_hz=2)
    before = v.params
    clock = RawImuClock()
    clock.start()
    mp = MAVProxy(v.gcs_device, tmp_path, out=f"udp:127.0.0.1:{clock.port}")
    hand = AdviceHand(v, mp.advice)
    try:
        mp.expect(r"Detected vehicle 1:1", timeout=20)
        loaded = mp.send("module load mavcal.mavproxy_mavcal")
        _, at = mp.expect(r"Loaded module mavcal\.mavproxy_mavcal", after=loaded)
        _, at = mp.expect(r"mavcal threads: mavcal-worker$", after=mp.send("mavcal threads"))
        mp.send("mavcal set hold_s 0.6")
        # the product's defaults (no min_poses): the capture stops when every sensor meets its target
        mp.send(f"mavcal set backup_dir {tmp_path / 'backups'}")
        _, at = mp.expect(r"mavcal: capture started", after=mp.send("mavcal start"))
        t_started = time.monotonic()
        mp.expect(r"next: level, nose towards magnetic north", after=at)
        hand.start()
        _, at2 = mp.expect(r"NEXT POSE: ", after=mp.send("mavcal status"))
        mp.expect(r"mavcal next pose: .* intervals kept", after=mp.send("mavcal next"))
        m, at = mp.expect(r"capture (finished|aborted)", timeout=180, after=at)
        t_finished = time.monotonic()
        assert m.group(1) == "finished", "\n".join(mp.lines[-30:])
        done, _ = mp.expect(r"mavcal: (\d+) intervals, .*: done: heading error bound (\S+) deg", after=at - 2)
        assert int(done.group(1)) >= 8 and float(done.group(2)) <= 0.5
        mp.expect(r"mavcal: fit done", after=at)  # fitted on its own at the end
        # the fit ends with the per-sensor verdicts and the module's next step
        for sensor in ("accel0", "accel1", "accel2", "compass0", "compass1", "compass2"):  # every one
            mp.expect(rf"^{sensor}: accepted$", after=at)
        mp.expect(r"next: write the parameters \('mavcal write'\), then reboot the vehicle", after=at)
        hand.stop()
        mark = mp.send("mavcal fit")
        mp.expect(r"mavcal: fitting 100%", after=mark)  # the console shows the fit's progress
        mp.expect(r"heading", after=mark)
        _, at = mp.expect(r"mavcal: fit done", after=mark)
        # write: first the diff and the question, nothing written
        mark = mp.send("mavcal write")
        mp.expect(r"type 'mavcal write yes' to write them", after=mark)
        assert v.param_sets == []
        mark = mp.send("mavcal write yes")
        _, at = mp.expect(r"mavcal: \d+ parameters written and verified; backup of the old values in (\S+)",
                          timeout=30, after=mark)
        mp.expect(r"calibration marked saved \(compass, accel\)", after=mark)
        rows = _changed_rows(mp.lines, mark)
        assert rows and all(v.get_param(n) == pytest.approx(x, rel=1e-5, abs=1e-5) for n, x in rows.items())
        assert set(v.force_saves) == {"compass", "accel"}
        ofs = np.array([v.get_param(f"COMPASS_OFS_{a}") for a in "XYZ"])
        assert np.all(np.abs(ofs - np.array(v.truth.compasses[0].offsets)) < 15.0)
        backups = sorted((tmp_path / "backups").glob("mavcal-backup-*.param"))
        assert len(backups) == 1 and set(read_param_file(backups[0])) == set(rows)
        # restore through the same writer puts the old values back
        mark = mp.send(f"mavcal restore {backups[0]} yes")
        mp.expect(r"mavcal: \d+ parameters written and verified", timeout=30, after=mark)
        assert all(v.get_param(n) == pytest.approx(before[n], abs=1e-5) for n in rows)
        # unload: the worker stops, no mavcal thread is left in the MAVProxy process
        mark = mp.send("module unload mavcal")
        mp.expect(r"mavcal: unloaded; worker stopped; mavcal threads left: none", after=mark)
        mp.expect(r"Unloaded module mavcal", after=mark)
        mp.expect(r"Unknown command 'mavcal", after=mp.send("mavcal threads"))
        _check_stream_rates(v, mp, clock, t_started, t_finished)
    finally:
        hand.stop()
        mp.close()
        clock.stop()
        v.stop()


def _check_stream_rates(v, mp, clock, t_started, t_finished):
    """Issue 13 item 5: one SET_MESSAGE_INTERVAL per IMU message the vehicle has (3 here), at the
    asked rate, and no reset of our own; MAVProxy's REQUEST_DATA_STREAM (every 15 s) is paused
    during the capture, so the IMU rate stays at ours; MAVProxy's own rate is back after the
    capture (MAVProxy re-requested it: no reset of ours was needed).

    What the vehicle received is checked, not only the rate seen: on a loaded machine a starved
    MAVProxy forwards fewer messages for a second (6 Hz was seen), and a slow acknowledgement
    makes the start repeat a request (link: a request is sent until its own ack arrives), which
    says nothing about the pause or the resets."""
    intervals = [p for cmd, p in v.commands if cmd == 511]  # MAV_CMD_SET_MESSAGE_INTERVAL
    assert {int(p[0]) for p in intervals} == {27, 116, 129}, intervals  # RAW_IMU, SCALED_IMU2, SCALED_IMU3
    assert all(p[1] == pytest.approx(40000) for p in intervals), intervals  # 25 Hz, never a reset (-1/0)
    during_requests = [r for r in v.stream_requests if t_started + 1.0 < r[0] < t_finished - 0.5]
    assert during_requests == [], during_requests  # MAVProxy's periodic request paused
    during = clock.rates(t_started + 1.5, t_finished)
    assert during and np.median(during) >= 12, during  # asked 25 Hz; MAVProxy's 4 Hz would show as <= 5
    # MAVProxy asks for its stream rates every 15 s: the capture spanned such a moment
    assert t_finished - mp.started > 15.5, "the capture ended before MAVProxy's first periodic stream request"
    after = clock.rates(t_finished + 1.5, t_finished + 3.5)
    assert after and max(after) <= 6, after
