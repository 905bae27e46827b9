"""Live source against a small loopback MAVLink peer started and stopped by each test."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
from pymavlink import mavutil

from mavcal.errors import LinkError, MavcalError
from mavcal.sources import open_source
from mavcal.sources.live import LiveSource

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
    fetched with PARAM_REQUEST_READ).
    """

    def __init__(self, device: str, ack_interval: bool = True, drop_index: int = 2) -> None:
        super().__init__(daemon=True)
        self.conn = mavutil.mavlink_connection(device, source_system=1, source_component=1)
        self.ack_interval = ack_interval
        self.drop_index = drop_index
        self.names = sorted(PARAMS)
        self.stop_evt = threading.Event()
        self.rate_hz = 0.0
        self.read_requests = []
        self.boot = time.monotonic()

    def send_param(self, i: int) -> None:
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
            elif t == "COMMAND_LONG" and m.command == 511:
                if self.ack_interval:
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
    with LiveSource(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=5) as src:
        assert src.target_system == 1 and src.target_component == 1
        params = src.fetch_params(timeout_s=10, idle_s=0.3)
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
    with LiveSource(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=5) as src:
        assert src.start_streams(rate_hz=25, ack_timeout_s=0.3) == "data_stream"
        assert veh.rate_hz == 25
        src.capture(0.3)
        assert len(src.snapshot().get("accel", 0)) >= 3


@pytest.mark.timeout(30)
def test_live_udpout_side(vehicle_factory):
    port = free_port()
    vehicle_factory(f"udpin:127.0.0.1:{port}")
    # we talk first (heartbeat), the peer answers to our address
    with LiveSource(f"udpout:127.0.0.1:{port}", heartbeat_timeout_s=5) as src:
        assert src.target_system == 1
        assert src.connection is not None  # usable by a later parameter writer


@pytest.mark.timeout(20)
def test_silent_device_raises_link_error_quickly():
    port = free_port()
    t0 = time.monotonic()
    with pytest.raises(LinkError, match="no heartbeat"):
        LiveSource(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=0.5)
    assert time.monotonic() - t0 < 5


@pytest.mark.timeout(20)
def test_unreachable_devices_are_link_errors():
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()  # nothing listens there
    with pytest.raises(LinkError):
        open_source(f"tcp:127.0.0.1:{port}", heartbeat_timeout_s=0.5)
    with pytest.raises(MavcalError):
        open_source("/dev/does-not-exist-mavcal", heartbeat_timeout_s=0.5)
