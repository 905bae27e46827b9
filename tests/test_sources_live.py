"""Live recording (mavcal.link.live) against a small loopback MAVLink peer started and stopped by each test."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
from pymavlink import mavutil

from mavcal.errors import LinkError, MavcalError, SourceError
from mavcal.link.live import imu_batch_from_messages, open_recorder, record_device
from mavcal.link.params import fetch_all_params
from mavcal.link.streams import send_message_intervals
from mavcal.sources import read_log

PARAMS = {f"COMPASS_OFS_{a}": v for a, v in zip("XYZ", (12.5, -40.0, 101.25))}
PARAMS.update({f"INS_ACCOFFS_{a}": v for a, v in zip("XYZ", (0.01, -0.02, 0.3))})
PARAMS.update({"AHRS_ORIENTATION": 0.0, "COMPASS_DEV_ID": 97539.0})


def free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class FakeVehicle(threading.Thread):
    """A tiny ArduPilot-like peer: heartbeat, parameters, RAW_IMU/SCALED_IMU2 streams.

    ``ack_interval``: answer SET_MESSAGE_INTERVAL (else only REQUEST_DATA_STREAM works).
    ``drop_index``: a parameter index left out of the PARAM_REQUEST_LIST answer (must be
    fetched with PARAM_REQUEST_READ). ``lost_index``: an index never sent at all.
    """

    def __init__(self, device: str, ack_interval: bool = True, drop_index: int = 2,
                 lost_index: int | None = None) -> None:
        super().__init__(daemon=True)
        self.conn = mavutil.mavlink_connection(device, source_system=1, source_component=1)
        self.ack_interval = ack_interval
        self.drop_index = drop_index
        self.lost_index = lost_index
        self.gcs_heartbeats = 0
        self.intervals = []  # (message id, interval us) of every SET_MESSAGE_INTERVAL
        self.names = sorted(PARAMS)
        self.stop_evt = threading.Event()
        self.rate_hz = 0.0
        self.read_requests = []
        self.boot = time.monotonic()

    def send_param(self, i: int) -> None:
        if i == self.lost_index:
            return
        n = self.names[i]
        self.conn.mav.param_value_send(n.encode(), PARAMS[n], 9, len(self.names), i)

    def run(self) -> None:
        last_hb = 0.0
        last_imu = 0.0
        end = time.monotonic() + 20.0  # bounded whatever happens
        while not self.stop_evt.is_set() and time.monotonic() < end:
            now = time.monotonic()
            if now - last_hb > 0.1:
                self.conn.mav.heartbeat_send(2, 3, 0, 0, 0)  # QUADROTOR, ARDUPILOTMEGA
                last_hb = now
            if self.rate_hz and now - last_imu >= 1.0 / self.rate_hz:
                last_imu = now
                tb = int((now - self.boot) * 1000)
                self.conn.mav.raw_imu_send(tb * 1000, 10, -20, -1000, 1, 2, 3, 200, -50, 400)
                self.conn.mav.scaled_imu2_send(tb, 0, 0, 0, 0, 0, 0, 210, -60, 410)
            m = self.conn.recv_msg()
            if m is None:
                time.sleep(0.001)
                continue
            t = m.get_type()
            if t == "PARAM_REQUEST_LIST":
                for i in range(len(self.names)):
                    if i != self.drop_index:
                        self.send_param(i)
            elif t == "PARAM_REQUEST_READ":
                self.read_requests.append(m.param_index)
                if 0 <= m.param_index < len(self.names):
                    self.send_param(m.param_index)
            elif t == "HEARTBEAT" and m.type == mavutil.mavlink.MAV_TYPE_GCS:
                self.gcs_heartbeats += 1
            elif t == "COMMAND_LONG" and m.command == mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                self.intervals.append((int(m.param1), int(m.param2)))
                if self.ack_interval and m.param2 > 0:
                    self.conn.mav.command_ack_send(511, 0)
                    self.rate_hz = max(self.rate_hz, 1e6 / m.param2)
            elif t == "REQUEST_DATA_STREAM":
                self.rate_hz = float(m.req_message_rate)

    def stop(self) -> None:
        self.stop_evt.set()
        self.join(timeout=5)
        self.conn.close()


@pytest.fixture
def vehicle_factory():
    started = []

    def make(device, **kw):
        v = FakeVehicle(device, **kw)
        v.start()
        started.append(v)
        return v

    yield make
    for v in started:
        v.stop()


@pytest.mark.timeout(30)
def test_live_udpin_params_streams_and_snapshot(vehicle_factory):
    port = free_port()
    veh = vehicle_factory(f"udpout:127.0.0.1:{port}")
    with open_recorder(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=5) as src:
        assert src.target_system == 1 and src.target_component == 1
        params = src.fetch_params(timeout_s=10, retry_s=0.3)
        assert params == pytest.approx(PARAMS)
        assert 2 in veh.read_requests  # the dropped index was re-requested
        assert src.start_streams(rate_hz=50) == "interval"
        batches = list(src.iter_batches(duration_s=0.6, batch_s=0.1))
        got = [s for b in batches for s in b if s.sensor == "accel"]
        assert got and all(s.instance == 0 for s in got)
        np.testing.assert_allclose(got[0].values[0], np.array([10, -20, -1000]) * 9.80665e-3)
        snap = src.snapshot()
    assert snap.kind == "live"
    acc = snap.get("accel", 0)
    assert len(acc) >= 15  # ~50 Hz for > 0.6 s
    assert np.all(np.diff(acc.time_s) > 0)
    assert snap.get("accel", 1) is None  # SCALED_IMU2 has zero accel: no IMU 2
    np.testing.assert_allclose(snap.get("mag", 1).values[0], [210, -60, 410])
    assert snap.params.final("COMPASS_OFS_Z") == pytest.approx(101.25)
    assert snap.vehicle["sysid"] == 1


@pytest.mark.timeout(30)
def test_live_fallback_to_request_data_stream(vehicle_factory):
    port = free_port()
    veh = vehicle_factory(f"udpout:127.0.0.1:{port}", ack_interval=False)
    with open_recorder(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=5) as src:
        assert src.start_streams(rate_hz=25, ack_timeout_s=0.3) == "data_stream"
        assert veh.rate_hz == 25
        src.capture(0.3)
        assert len(src.snapshot().get("accel", 0)) >= 3


@pytest.mark.timeout(30)
def test_live_udpout_side(vehicle_factory):
    port = free_port()
    vehicle_factory(f"udpin:127.0.0.1:{port}")
    # we talk first (heartbeat), the peer answers to our address
    with open_recorder(f"udpout:127.0.0.1:{port}", heartbeat_timeout_s=5) as src:
        assert src.target_system == 1
        assert src.link.conn is not None  # usable by a later parameter writer


@pytest.mark.timeout(20)
def test_silent_device_raises_link_error_quickly():
    port = free_port()
    t0 = time.monotonic()
    with pytest.raises(LinkError, match="no heartbeat"):
        open_recorder(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=0.5)
    assert time.monotonic() - t0 < 5


@pytest.mark.timeout(20)
def test_unreachable_devices_are_link_errors():
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()  # nothing listens there
    with pytest.raises(LinkError):
        record_device(f"tcp:127.0.0.1:{port}", heartbeat_timeout_s=0.5)
    with pytest.raises(MavcalError):
        record_device("/dev/does-not-exist-mavcal", heartbeat_timeout_s=0.5)


@pytest.mark.timeout(30)
def test_record_device_connects_fetches_streams_and_records(vehicle_factory):
    port = free_port()
    veh = vehicle_factory(f"udpout:127.0.0.1:{port}")
    log_ = record_device(f"udpin:127.0.0.1:{port}", duration_s=1.2, rate_hz=50, param_timeout_s=10)
    assert log_.kind == "live" and log_.source == f"udpin:127.0.0.1:{port}"
    assert len(log_.get("accel", 0)) >= 30  # ~50 Hz for 1.2 s
    assert log_.params.final("COMPASS_DEV_ID") == 97539.0
    assert not any("parameters received" in w for w in log_.warnings)  # the table was complete
    # SET_MESSAGE_INTERVAL for RAW_IMU, SCALED_IMU2, SCALED_IMU3 at 50 Hz, and a GCS heartbeat every second
    assert sorted(veh.intervals) == [(27, 20000), (116, 20000), (129, 20000)]
    assert veh.gcs_heartbeats >= 2


@pytest.mark.timeout(30)
def test_incomplete_parameter_table_is_a_warning_of_the_recording(vehicle_factory):
    port = free_port()
    vehicle_factory(f"udpout:127.0.0.1:{port}", lost_index=3)
    with open_recorder(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=5) as rec:
        params = rec.fetch_params(timeout_s=1.0, retry_s=0.2)
        assert len(params) == len(PARAMS) - 1
        with pytest.raises(LinkError, match="incomplete"):  # the strict download says so
            fetch_all_params(rec.link, 0.5, retry_s=0.2)
        rec.start_streams(rate_hz=25)
        rec.capture(0.3)
        log_ = rec.snapshot()
    assert f"only {len(PARAMS) - 1} of {len(PARAMS)} parameters received within 1 s" in log_.warnings


def test_file_reader_refuses_a_device():
    with pytest.raises(SourceError, match="record_device"):
        read_log("udpin:127.0.0.1:14550")


class _Encoder:
    def __init__(self):
        self.sent = []

    def command_long_send(self, *args):
        self.sent.append(args)


def test_message_intervals_and_their_reset():
    mav = _Encoder()
    send_message_intervals(mav, 1, 1, 50.0)
    send_message_intervals(mav, 1, 1, None)
    cmd = mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert [(a[2], a[4], a[5]) for a in mav.sent] == [(cmd, 27, 20000), (cmd, 116, 20000), (cmd, 129, 20000),
                                                      (cmd, 27, 0), (cmd, 116, 0), (cmd, 129, 0)]


def test_imu_batch_from_messages_converts_units_and_instances():
    A = mavutil.mavlink
    raw = A.MAVLink_raw_imu_message(2_000_000, 10, -20, -1000, 1, 2, 3, 200, -50, 400)
    imu2 = A.MAVLink_scaled_imu2_message(2000, 0, 0, 0, 0, 0, 0, 210, -60, 410)
    hb = A.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3)
    batch = imu_batch_from_messages([hb, imu2, raw])
    got = {(s.sensor, s.instance, s.message): s for s in batch}
    assert set(got) == {("accel", 0, "RAW_IMU"), ("gyro", 0, "RAW_IMU"), ("mag", 0, "RAW_IMU"),
                        ("mag", 1, "SCALED_IMU2")}  # no accel/gyro for the all-zero SCALED_IMU2
    np.testing.assert_allclose(got["accel", 0, "RAW_IMU"].values[0], np.array([10, -20, -1000]) * 9.80665e-3)
    np.testing.assert_allclose(got["gyro", 0, "RAW_IMU"].values[0], [0.001, 0.002, 0.003])
    assert got["mag", 1, "SCALED_IMU2"].time_s[0] == pytest.approx(2.0)
    assert imu_batch_from_messages([raw], target_system=1) == ()  # built here: source system 0


def test_sources_knows_nothing_of_devices():
    import ast
    from pathlib import Path

    import mavcal.sources

    for path in Path(mavcal.sources.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                assert not (node.module or "").startswith("mavcal.link"), path.name
    assert not hasattr(mavcal.sources, "LiveSource")
