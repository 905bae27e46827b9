"""A ground-station probe of a vehicle's MAVLink protocol, for tests that compare vehicles.

:class:`MavProbe` opens a device (the loopback :class:`~mavcal.testing.vehicle.TestVehicle`'s
``gcs_device``, or a :class:`~mavcal.testing.sitl.SitlVehicle`'s ``tool_device`` from inside
its namespace) as GCS 255/190, sends single protocol messages and returns what came back as
plain :class:`Received` records (type, dict of fields, time), so a test can state the same
observable outcome for both vehicles without importing pymavlink itself.

Everything is synchronous: :meth:`MavProbe.collect` reads for a while (or until a predicate
holds) and keeps what arrived; each request method clears nothing and returns only the
messages that arrived after it was sent.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["MavProbe", "Received", "const"]

GCS_SYSTEM, GCS_COMPONENT = 255, 190


def const(name: str) -> int:
    """A MAVLink enum value or message id by name, e.g. ``const("MAV_CMD_REQUEST_MESSAGE")``,
    ``const("MAVLINK_MSG_ID_RAW_IMU")``."""
    return int(getattr(mavlink2, name))


@dataclass(frozen=True)
class Received:
    """One message from the vehicle: its type, its fields and when it arrived (monotonic s)."""

    type: str
    fields: dict[str, Any] = field(hash=False)
    time_s: float = 0.0
    src: tuple[int, int] = (0, 0)

    def __getitem__(self, key: str) -> Any:
        return self.fields[key]


class MavProbe:
    """A GCS on ``device`` (pymavlink device string) talking to one vehicle."""

    def __init__(self, device: str, *, heartbeat_timeout_s: float = 30.0) -> None:
        self._conn = mavutil.mavlink_connection(device, source_system=GCS_SYSTEM, source_component=GCS_COMPONENT,
                                                dialect="ardupilotmega")
        # a vehicle that listens (udpin, tcp) learns of this GCS from its first message
        self._conn.mav.heartbeat_send(const("MAV_TYPE_GCS"), const("MAV_AUTOPILOT_INVALID"), 0, 0, 0)
        hb = self._conn.wait_heartbeat(timeout=heartbeat_timeout_s)
        if hb is None:
            self._conn.close()
            raise TimeoutError(f"no heartbeat on {device} within {heartbeat_timeout_s:g} s")
        self.target = (hb.get_srcSystem(), hb.get_srcComponent())
        # ArduPilot sends its broadcasts (echoes of a set, STATUSTEXT) only on channels that
        # have heard from a GCS: now that the address is known (udpin), be heard
        self._conn.mav.heartbeat_send(const("MAV_TYPE_GCS"), const("MAV_AUTOPILOT_INVALID"), 0, 0, 0)
        self.first_heartbeat = _record(hb)

    def close(self) -> None:
        self._conn.close()

    # ---------------------------------------------------------------- receiving
    def collect(self, seconds: float, types: Iterable[str] | None = None,
                until: Callable[[list[Received]], bool] | None = None) -> list[Received]:
        """The messages (of ``types``) from the vehicle for ``seconds``, or until ``until(got)``."""
        keep = None if types is None else set(types)
        got: list[Received] = []
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return got
            m = self._conn.recv_match(blocking=True, timeout=min(left, 0.05))
            if m is None or m.get_type() == "BAD_DATA" or (m.get_srcSystem(), m.get_srcComponent()) != self.target:
                continue
            if keep is None or m.get_type() in keep:
                got.append(_record(m))
                if until is not None and until(got):
                    return got

    def drain(self) -> None:
        """Forget whatever is waiting in the socket."""
        self.collect(0.2)

    # ---------------------------------------------------------------- sending
    def param_request_read(self, name: str = "", index: int = -1) -> None:
        self._conn.mav.param_request_read_send(*self.target, name.encode(), index)

    def param_request_list(self) -> None:
        self._conn.mav.param_request_list_send(*self.target)

    def param_set(self, name: str, value: float, param_type: str = "MAV_PARAM_TYPE_REAL32") -> None:
        self._conn.mav.param_set_send(*self.target, name.encode(), float(value), const(param_type))

    def command_long(self, command: str | int, *params: float) -> None:
        cmd = const(command) if isinstance(command, str) else int(command)
        p = (list(params) + [0.0] * 7)[:7]
        self._conn.mav.command_long_send(*self.target, cmd, 0, *p)

    def request_data_stream(self, stream: str, rate_hz: int, start: bool) -> None:
        self._conn.mav.request_data_stream_send(*self.target, const(stream), rate_hz, 1 if start else 0)

    # ---------------------------------------------------------------- request and answer
    def read_param(self, name: str, timeout_s: float = 3.0) -> Received | None:
        """PARAM_REQUEST_READ by name (retried once a second); the answer, or None."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.param_request_read(name)
            got = self.collect(min(1.0, deadline - time.monotonic()), {"PARAM_VALUE"},
                               until=lambda g: any(r["param_id"] == name for r in g))
            for r in got:
                if r["param_id"] == name:
                    return r
        return None

    def set_and_wait(self, name: str, value: float, timeout_s: float = 3.0,
                     types: Iterable[str] = ("PARAM_VALUE", "STATUSTEXT", "PARAM_ERROR")) -> list[Received]:
        """One PARAM_SET, and what arrives until its echo (plus 0.3 s), or for ``timeout_s``."""
        self.param_set(name, value)
        got = self.collect(timeout_s, types, until=lambda g: any(
            r.type == "PARAM_VALUE" and r["param_id"] == name for r in g))
        return got + self.collect(0.3, types)

    def command_and_wait(self, command: str | int, *params: float, timeout_s: float = 3.0,
                         types: Iterable[str] = ("COMMAND_ACK",)) -> list[Received]:
        """One COMMAND_LONG, and what arrives (of ``types``, COMMAND_ACK always) until its ACK
        plus 0.5 s."""
        cmd = const(command) if isinstance(command, str) else int(command)
        want = set(types) | {"COMMAND_ACK"}
        self.command_long(cmd, *params)
        got = self.collect(timeout_s, want, until=lambda g: any(
            r.type == "COMMAND_ACK" and r["command"] == cmd for r in g))
        return got + self.collect(0.5, want)


def _record(m: Any) -> Received:
    d = m.to_dict()
    d.pop("mavpackettype", None)
    return Received(m.get_type(), d, time.monotonic(), (m.get_srcSystem(), m.get_srcComponent()))
