"""A vehicle on a serial port: a pty (:class:`mavcal.testing.serial_cable.SerialCable`) relayed to the
loopback test vehicle, opened by path as a USB port is, through a udev-like symlink.

The sessions: a write through the symlinked port at radio speed; a cable pulled for 3 s right
after the 4th PARAM_SET of a 15-parameter write and plugged back at the same path (the write
resumes: exit 0, every value held); the one-line reasons, each within 5 s: no such port, busy
(held exclusively by another program), permission denied (the dialout group), no MAVLink at the
baud rate given (the rate that answered is named), nothing received; a second writer (a ground
station beside mavcal) changing a parameter during the write is caught by the read-back.
"""
from __future__ import annotations

import errno
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import serial
from pymavlink import mavutil

from mavcal.errors import LinkError
from mavcal.link.connection import GCS_COMPONENT_ID, GCS_SYSTEM_ID, open_link
from mavcal.link.serial_port import is_serial_device, open_error
from mavcal.sources.reader import is_device
from mavcal.testing.serial_cable import SerialCable
from mavcal.testing.vehicle import TestVehicle, VehicleTruth

PARAM_SET_ID = mavutil.mavlink.MAVLINK_MSG_ID_PARAM_SET
NAMES = tuple(f"COMPASS_OFS{s}_{a}" for s in ("", "2", "3") for a in "XYZ") + tuple(
    f"INS_ACC{s}OFFS_{a}" for s in ("", "2") for a in "XYZ")
ENV = dict(os.environ, CI="", MAVCAL_TEST="1")


def _f32(x: float) -> float:
    return float(np.float32(x))


def _mavcal(*argv: str, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mavcal", *argv], capture_output=True, text=True, timeout=timeout,
                          env=ENV, **kw)


@pytest.fixture()
def cabled():
    """A test vehicle (2 Hz heartbeat) behind a cable at 57600 baud."""
    vehicle = TestVehicle("tcp", heartbeat_hz=2.0).start()
    cable = SerialCable(tcp_port=vehicle.port, baud=57600).start()
    try:
        yield vehicle, cable
    finally:
        cable.stop()
        vehicle.stop()


def test_a_symlinked_pty_is_a_serial_device(cabled):
    _, cable = cabled
    assert os.path.islink(cable.path) and not cable.path.startswith("/dev/")
    assert is_serial_device(cable.path) and is_device(cable.path)
    for name in ("/dev/ttyACM0", "/dev/ttyUSB0", "/dev/cu.usbmodem14201", "COM3", "/dev/ttyUSB0,57600"):
        assert is_serial_device(name) and is_device(name), name
    for name in ("udpin:127.0.0.1:14550", "tcp:127.0.0.1:5760", __file__):
        assert not is_serial_device(name), name


def test_apply_writes_over_the_symlinked_port_at_radio_speed(cabled, tmp_path):
    vehicle, cable = cabled
    values = {n: 3.0 + k for k, n in enumerate(NAMES[:3])}
    pfile = tmp_path / "cal.param"
    pfile.write_text("".join(f"{n} {v}\n" for n, v in values.items()))
    proc = _mavcal("apply", str(pfile), "--connect", cable.path, "--baud", "57600", "--yes",
                   "--backup", str(tmp_path / "b.param"))
    assert proc.returncode == 0, proc.stderr
    assert "written and verified" in proc.stdout
    assert {n: vehicle.get_param(n) for n in values} == {n: _f32(v) for n, v in values.items()}


def test_segments_records_from_a_symlinked_port(cabled):
    vehicle, cable = cabled
    vehicle.set_moving(False)
    proc = _mavcal("segments", cable.path, "--baud", "57600", "--duration", "2")
    assert "not a file" not in proc.stderr
    assert proc.returncode in (0, 4), proc.stderr  # recorded (2 s may hold too little to segment)
    assert "Traceback" not in proc.stderr


def test_a_cable_pulled_mid_write_for_3_s_resumes_the_write(cabled, tmp_path):
    vehicle, cable = cabled
    values = {n: (20.0 + k if n.startswith("COMPASS") else 0.1 * k) for k, n in enumerate(NAMES)}
    pfile = tmp_path / "cal.param"
    pfile.write_text("".join(f"{n} {v}\n" for n, v in values.items()))
    before = vehicle.params
    cable.pull_at(PARAM_SET_ID, 4, 3.0)
    proc = _mavcal("apply", str(pfile), "--connect", cable.path, "--baud", "57600", "--yes",
                   "--backup", str(tmp_path / "b.param"), timeout=240)
    after = vehicle.params
    assert len(cable.pulls) == 1 and cable.pulls[0][1] is not None, f"{cable.pulls}\n{proc.stdout}\n{proc.stderr}"
    assert cable.pulls[0][1] - cable.pulls[0][0] == pytest.approx(3.0, abs=0.2)
    assert proc.returncode == 0, f"rc {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    assert after == dict(before, **{n: _f32(v) for n, v in values.items()})
    assert "went away" in proc.stderr and "is back" in proc.stderr


# ------------------------------------------------------------------ one-line reasons, each within 5 s
def _fails_within(device: str, baud: int = 115200, limit_s: float = 5.0) -> str:
    t0 = time.monotonic()
    with pytest.raises(LinkError) as exc:
        open_link(device, baud=baud, timeout_s=5.0)
    took = time.monotonic() - t0
    text = str(exc.value)
    assert took < limit_s, f"{took:.1f} s: {text}"
    assert "\n" not in text
    return text


def _one_line_exit_3(device: str, *extra: str) -> str:
    proc = _mavcal("capture", "--connect", device, *extra, timeout=60)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 3, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("mavcal: error: "), proc.stderr
    return lines[0]


def test_a_missing_port_says_so(tmp_path):
    text = _fails_within("/dev/ttyACM97")
    assert "no serial port /dev/ttyACM97" in text and "plugged in" in text, text
    assert "no serial port /dev/ttyACM97" in _one_line_exit_3("/dev/ttyACM97")
    os.symlink("/dev/pts/999999", tmp_path / "by-id")  # a udev name whose device is gone
    assert "which is gone" in _fails_within(str(tmp_path / "by-id"))


def test_a_port_held_by_another_program_is_busy(cabled):
    _, cable = cabled
    holder = serial.Serial(cable.path, 57600, exclusive=True)  # as a ground station holds it
    try:
        text = _fails_within(cable.path)
        assert "is busy" in text and "another program" in text
        assert "is busy" in _one_line_exit_3(cable.path)
    finally:
        holder.close()
    # and mavcal holds it the same way: a ground station opening it after mavcal is refused
    link = open_link(cable.path, baud=57600)
    try:
        with pytest.raises(serial.SerialException):
            serial.Serial(cable.path, 57600, exclusive=True)
    finally:
        link.close()


def test_tiocexcl_busy_and_permission_errors_read_as_one_line():
    """The errno a port held with TIOCEXCL gives a non-root opener (EBUSY), and EACCES (the dialout group)."""
    busy = open_error("/dev/ttyACM0", serial.SerialException(errno.EBUSY, "could not open port: Device busy"))
    assert "/dev/ttyACM0 is busy" in str(busy)
    denied = open_error("/dev/ttyACM0", serial.SerialException(errno.EACCES, "could not open port: denied"))
    assert "permission denied opening /dev/ttyACM0" in str(denied)
    if sys.platform.startswith("linux"):
        assert "dialout" in str(denied)


_AS_NOBODY = """
import os, sys, time
from pymavlink import mavutil
import fcntl, termios, serial, serial.tools.list_ports
from mavcal.errors import LinkError
from mavcal.link.connection import open_link
mavutil.set_dialect("ardupilotmega")
if os.geteuid() == 0:  # root opens anything: drop to nobody, everything imported already
    os.setgroups([]); os.setgid(65534); os.setuid(65534)
t0 = time.monotonic()
try:
    open_link(sys.argv[1], baud=57600, timeout_s=5.0)
except LinkError as exc:
    print(f"{time.monotonic() - t0:.2f} {exc}")
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the dialout group is Linux's")
def test_a_port_without_permission_names_the_dialout_group(cabled, tmp_path):
    _, cable = cabled
    os.chmod(cable.tool_tty, 0o600 if os.geteuid() == 0 else 0)  # as /dev/ttyACM0 is root:dialout 660
    proc = subprocess.run([sys.executable, "-c", _AS_NOBODY, cable.path], capture_output=True, text=True,
                          timeout=60, env=ENV, cwd="/")
    took, _, text = proc.stdout.strip().partition(" ")
    assert proc.returncode == 0 and text, proc.stderr
    assert float(took) < 5.0
    assert "\n" not in text and "permission denied" in text and "dialout" in text, text


def test_the_wrong_baud_rate_names_the_one_that_answers():
    vehicle = TestVehicle("tcp", heartbeat_hz=2.0).start()
    cable = SerialCable(tcp_port=vehicle.port, baud=57600, speaks_at=57600).start()
    try:
        text = _fails_within(cable.path, baud=115200)
        assert "no MAVLink" in text and "at 115200 baud" in text and "answered at 57600: --baud 57600" in text, text
        assert cable.stats["scrambled"] > 0
        link = open_link(cable.path, baud=57600)  # the rate it named works
        link.close()
    finally:
        cable.stop()
        vehicle.stop()


def test_a_port_that_sends_nothing_names_the_radio_rate():
    with SerialCable(tcp_port=None) as cable:  # a pty whose other end nobody opened
        text = _fails_within(cable.path, limit_s=7.0)
    assert "nothing received" in text and "--baud 57600" in text, text


def test_our_ids_are_not_a_ground_stations():
    assert (GCS_SYSTEM_ID, GCS_COMPONENT_ID) != (255, 190)
    assert GCS_SYSTEM_ID != 255 and GCS_COMPONENT_ID != 190


def test_a_second_writer_during_the_write_is_caught_by_the_read_back(cabled, tmp_path):
    """A ground station beside mavcal sets COMPASS_OFS_X to its own value while mavcal's write is on
    (right after mavcal's PARAM_SET of COMPASS_OFS_Y): never reported as written."""
    vehicle, cable = cabled
    pfile = tmp_path / "cal.param"
    pfile.write_text("COMPASS_OFS_X 20\nCOMPASS_OFS_Y 21\nCOMPASS_OFS_Z 22\n")
    before = vehicle.params

    def meddle() -> None:
        deadline = time.monotonic() + 60
        while not any(s[0] == "COMPASS_OFS_Y" for s in vehicle.param_sets) and time.monotonic() < deadline:
            time.sleep(0.001)
        vehicle.set_param_local("COMPASS_OFS_X", 99.0, announce=True)  # as another GCS's write, echoed

    threading.Thread(target=meddle, daemon=True).start()
    proc = _mavcal("apply", str(pfile), "--connect", cable.path, "--baud", "57600", "--yes",
                   "--backup", str(tmp_path / "b.param"))
    assert proc.returncode == 5, f"rc {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "written and verified" not in proc.stdout
    assert "read-back does not confirm COMPASS_OFS_X (got 99.0, expected 20.0)" in proc.stderr
    assert {n: vehicle.get_param(n) for n in ("COMPASS_OFS_Y", "COMPASS_OFS_Z")} == {
        n: before[n] for n in ("COMPASS_OFS_Y", "COMPASS_OFS_Z")}


def test_a_capture_keeps_its_poses_over_a_pulled_cable_and_goes_on_after_a_reboot(caplog):
    """A cable pulled for 3 s mid-capture while the board reboots (USB power: it forgets the streams
    it was asked for): the intervals held so far are kept, the streams are asked for again once the
    vehicle is heard, and the capture counts new poses after it."""
    from mavcal.capture import CaptureConfig
    from mavcal.capture import live as live_capture
    from mavcal.segment import StillConfig

    vehicle = TestVehicle("tcp", truth=VehicleTruth.random(3), seed=3, heartbeat_hz=5.0).start()
    cable = SerialCable(tcp_port=vehicle.port, baud=115200).start()
    poses = [(0, 0, 0), (0, 90, 0), (90, 0, 0), (180, 0, 0), (0, -90, 0), (-90, 0, 0), (0, 45, 90), (45, 0, 200)]
    vehicle.run_pose_script(poses, hold_s=1.6, move_s=0.4)
    seen: list = []
    at_pull: list[int] = []

    def on_status(st) -> None:
        seen.append(st.n_intervals)
        if st.n_intervals >= 2 and not at_pull:
            at_pull.append(st.n_intervals)
            cable.pull(3.0)
            other = mavutil.mavlink_connection(f"tcp:127.0.0.1:{vehicle.port}", source_system=200)
            other.mav.command_long_send(vehicle.sysid, vehicle.compid,
                                        mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 1, 0, 0, 0, 0, 0, 0)
            time.sleep(0.2)
            other.close()

    caplog.set_level("WARNING")
    try:
        sess = live_capture.capture_live(cable.path, config=CaptureConfig(still=StillConfig(min_duration_s=0.6,
                                                                                             window_s=0.4)),
                                         on_status=on_status, max_duration_s=40,
                                         should_stop=lambda: bool(at_pull) and seen[-1] >= at_pull[0] + 2)
    finally:
        cable.stop()
        vehicle.stop()
    assert at_pull and vehicle.reboots == 1 and cable.pulls[0][1] is not None  # (pulls[1]: the cable's stop)
    assert sess.status.n_intervals >= at_pull[0] + 2, (at_pull, seen[-5:])  # counted after the pull
    assert "asking for the streams again" in caplog.text
    assert "too slow" not in caplog.text  # a silence is not a slow link


@pytest.mark.parametrize("baud, slow", [(9600, True), (115200, False)])
def test_a_link_too_slow_for_the_streams_asked_is_said(baud, slow):
    """At 9600 baud (960 bytes/s) the IMU messages asked at 25 Hz cannot all pass: one warning with the
    rate received; at 115200 they do, and nothing is said."""
    from mavcal.link.live import RATE_CHECK_S, open_recorder

    vehicle = TestVehicle("tcp", heartbeat_hz=2.0).start()
    cable = SerialCable(tcp_port=vehicle.port, baud=baud).start()
    try:
        rec = open_recorder(cable.path, baud=baud)
        try:
            rec.start_streams(25.0)
            for _ in rec.iter_batches(RATE_CHECK_S + 1.5):
                pass
        finally:
            rec.close()
    finally:
        cable.stop()
        vehicle.stop()
    assert rec.imu_rate_hz is not None
    said = [w for w in rec.warnings if "too slow" in w]
    if slow:
        assert rec.imu_rate_hz < 17.5 and len(said) == 1, (rec.imu_rate_hz, rec.warnings)
        assert f"{rec.imu_rate_hz:.0f} Hz of the 25 Hz asked" in said[0]
    else:
        assert rec.imu_rate_hz > 22.0 and not said, (rec.imu_rate_hz, rec.warnings)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="other processes' open files: Linux's /proc")
def test_a_port_another_program_opened_without_a_lock_is_busy_and_named(cabled):
    """MAVProxy and pymavlink scripts open a port without any lock; two readers would each get half of
    the bytes, so such a holder is found in /proc and named."""
    _, cable = cabled
    holder = subprocess.Popen([sys.executable, "-c", "import os, sys, time; fd = os.open(sys.argv[1], os.O_RDWR | "
                               "os.O_NOCTTY); print('open', flush=True); time.sleep(60)", cable.path],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        text = _fails_within(cable.path)
        assert "is busy" in text and f"(pid {holder.pid}) has it open" in text, text
    finally:
        holder.kill()
        holder.wait()
    open_link(cable.path, baud=57600).close()  # once it is gone, the port opens
