"""The vehicle's position, read live, for the World Magnetic Model.

ArduPilot's own compass calibration scales the compass to the field strength the World
Magnetic Model gives at the vehicle's position; a live mavcal command does the same. The
position comes from the messages a log's reader uses too (:mod:`mavcal.sources.assemble`):

* ``GPS_RAW_INT`` with a 3D fix or better: "vehicle GPS";
* ``GLOBAL_POSITION_INT`` (the EKF's estimate; 0, 0 until it has an origin):
  "vehicle position estimate";
* ``HOME_POSITION``: "vehicle home".

:func:`read_position` asks for each with ``MAV_CMD_REQUEST_MESSAGE`` (one answer each, no
stream rate is changed), again every ``retry_s`` on a lossy link, and returns the first valid
one (GPS preferred when several arrived together), or None when every message answered
without a position (no GPS fix, no home) or the time is up. :class:`PositionWatch` also takes
messages fed from someone else's read loop (the MAVProxy module).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

from pymavlink import mavutil

from mavcal.link.connection import Link

__all__ = ["VehiclePosition", "position_from_message", "PositionWatch", "request_position", "read_position",
           "POSITION_MESSAGES"]

_A = mavutil.mavlink

#: message -> the words naming it as a position's source; in order of preference
POSITION_MESSAGES: dict[str, str] = {"GPS_RAW_INT": "vehicle GPS",
                                     "GLOBAL_POSITION_INT": "vehicle position estimate",
                                     "HOME_POSITION": "vehicle home"}
_IDS = {"GPS_RAW_INT": _A.MAVLINK_MSG_ID_GPS_RAW_INT, "GLOBAL_POSITION_INT": _A.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        "HOME_POSITION": _A.MAVLINK_MSG_ID_HOME_POSITION}
_GPS_FIX_3D = 3


@dataclass(frozen=True)
class VehiclePosition:
    """A position the vehicle reported: degrees, metres (MSL), and where it came from."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    source: str

    @property
    def location(self) -> tuple[float, float, float]:
        """``(lat_deg, lon_deg, alt_m)``, as ``--location`` and :attr:`ImuLog.position`."""
        return (self.lat_deg, self.lon_deg, self.alt_m)

    def describe(self) -> str:
        """``"vehicle GPS -35.3633, 149.1652"``."""
        return f"{self.source} {self.lat_deg:.4f}, {self.lon_deg:.4f}"


def position_from_message(m: Any) -> VehiclePosition | None:
    """The position in ``m`` (GPS_RAW_INT with a 3D fix, GLOBAL_POSITION_INT, HOME_POSITION), else None."""
    mtype = m.get_type()
    if mtype == "GPS_RAW_INT":
        if int(m.fix_type) < _GPS_FIX_3D:
            return None
        lat, lon, alt = m.lat, m.lon, m.alt
    elif mtype == "GLOBAL_POSITION_INT":
        lat, lon, alt = m.lat, m.lon, m.alt
    elif mtype == "HOME_POSITION":
        lat, lon, alt = m.latitude, m.longitude, m.altitude
    else:
        return None
    if lat == 0 and lon == 0:  # no fix / no origin yet
        return None
    lat_deg, lon_deg = float(lat) * 1e-7, float(lon) * 1e-7
    if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0):
        return None
    return VehiclePosition(lat_deg, lon_deg, float(alt) * 1e-3, POSITION_MESSAGES[mtype])


class PositionWatch:
    """Remembers the latest valid position per message from the vehicle ``(sysid, compid)``,
    and which messages answered at all (with or without a position)."""

    def __init__(self, vehicle: tuple[int, int] | None = None) -> None:
        self.vehicle = vehicle
        self.latest: dict[str, VehiclePosition] = {}
        self.answered: set[str] = set()

    def feed(self, m: Any) -> None:
        """Look at one received message (any type; other types are ignored)."""
        mtype = m.get_type()
        if mtype not in POSITION_MESSAGES:
            return
        if self.vehicle is not None and (m.get_srcSystem(), m.get_srcComponent()) != self.vehicle:
            return
        self.answered.add(mtype)
        pos = position_from_message(m)
        if pos is not None:
            self.latest[mtype] = pos

    def best(self) -> VehiclePosition | None:
        """The GPS position if known, else the position estimate, else home; None if none."""
        return next((self.latest[k] for k in POSITION_MESSAGES if k in self.latest), None)


def request_position(mav: Any, target_system: int, target_component: int,
                     messages: tuple[str, ...] = tuple(POSITION_MESSAGES)) -> None:
    """One MAV_CMD_REQUEST_MESSAGE per position message (``mav``: an encoder or a QueuedSender)."""
    for name in messages:
        mav.command_long_send(target_system, target_component, _A.MAV_CMD_REQUEST_MESSAGE, 0,
                              _IDS[name], 0, 0, 0, 0, 0, 0)


def read_position(link: Link, *, timeout_s: float = 3.0, retry_s: float = 0.5) -> VehiclePosition | None:
    """Ask the vehicle where it is (see the module docstring); None when it does not know.

    Requests are repeated every ``retry_s`` for the messages that have not answered, until a
    valid position arrives, every message answered without one (no GPS fix, no EKF origin, no
    home) or was refused (a COMMAND_ACK other than accepted for each request of a round: the
    vehicle cannot send it), or ``timeout_s`` passes.
    """
    watch = PositionWatch((link.target_system, link.target_component))
    refusals = [0]

    def on_ack(m: Any) -> None:
        if (link.is_from_vehicle(m) and m.command == _A.MAV_CMD_REQUEST_MESSAGE
                and m.result not in (_A.MAV_RESULT_ACCEPTED, _A.MAV_RESULT_IN_PROGRESS)):
            refusals[0] += 1

    tokens = [link.add_handler(k, watch.feed) for k in POSITION_MESSAGES]
    tokens.append(link.add_handler("COMMAND_ACK", on_ack))
    deadline = time.monotonic() + timeout_s
    try:
        while watch.best() is None:
            pending = tuple(k for k in POSITION_MESSAGES if k not in watch.answered)
            remaining = deadline - time.monotonic()
            if not pending or remaining <= 0:
                break
            refusals[0] = 0
            request_position(link.mav, link.target_system, link.target_component, pending)
            done = _found_or_refused(watch, refusals, len(pending))
            link.wait(done, min(retry_s, remaining))
            if watch.best() is None and refusals[0] >= len(pending):
                break  # the vehicle cannot send any of them
    finally:
        for t in tokens:
            link.remove_handler(t)
    return watch.best()


def _found_or_refused(watch: PositionWatch, refusals: list[int], n: int) -> Callable[[], bool]:
    return lambda: watch.best() is not None or refusals[0] >= n
