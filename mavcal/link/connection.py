"""Open a MAVLink link to a vehicle and run the one receive loop on it.

pymavlink's ``recv_match(type=...)`` throws away every message it skips, so a program that
calls it from several places loses messages (a PARAM_VALUE eaten while waiting for a
COMMAND_ACK). :class:`Link` owns the only read loop on its connection: callers register
handlers and then *pump* the loop (:meth:`Link.pump`, :meth:`Link.wait`) until their condition
holds. Every message received goes to every handler registered for its type.

A :class:`Link` is not thread-safe: one thread owns it and pumps it.

Starting a session under loss: :func:`open_link` waits ``timeout_s`` for the vehicle's
HEARTBEAT, and as long as ``budget_s`` when the device is heard (any MAVLink from it) but no
heartbeat got through yet, so a lossy link gets the same retry budget as the writes while a
dead device still fails after ``timeout_s``.

Signing (:mod:`mavcal.link.signing`): with ``signing_key`` every message is signed and only
validly signed ones are accepted; without one, a vehicle whose heartbeat is signed is asked
once (with retries) for a parameter, and when it never answers our unsigned requests the
error says the vehicle requires signing (:class:`~mavcal.errors.SigningError`, exit 8), not
that the link is lossy.

Device strings are pymavlink's: ``udpin:HOST:PORT`` (listen), ``udpout:HOST:PORT`` (send
first), ``udp:HOST:PORT`` (= udpin), ``tcp:HOST:PORT`` (client), ``tcpin:HOST:PORT``, or a
serial device (``/dev/ttyACM0``, ``COM3``, any path to a character device) with ``baud``, opened by
:mod:`mavcal.link.serial_port` (exclusively; one-line reasons; a pulled cable waited out as a
silence); ``auto``: the serial port found by :mod:`mavcal.link.autodetect`.
"""
from __future__ import annotations

import itertools
import logging
import os
import struct
import time
from collections import deque
from typing import Any, BinaryIO, Callable

from pymavlink import mavutil

from mavcal.autopilot.mavlink import MAV_AUTOPILOT_PX4  # a PX4, whose integer parameters travel bytewise
from mavcal.errors import LinkError, SigningError, SourceError
from mavcal.link.autodetect import AUTO, find_port
from mavcal.link.serial_port import (
    GARBAGE_BYTES,
    SerialConnection,
    is_serial_device,
    no_mavlink_reason,
    open_serial,
    probe_bauds,
)
from mavcal.link.signing import NEEDS_KEY, SigningKey, is_signed, setup_signing, signing_problem

__all__ = ["Link", "open_link", "as_link", "GCS_SYSTEM_ID", "GCS_COMPONENT_ID", "MAV_AUTOPILOT_PX4",
           "param_from_wire", "param_to_wire"]

log = logging.getLogger(__name__)

#: our own ids: never a ground station's (255 / MAV_COMP_ID_MISSIONPLANNER 190, which Mission Planner
#: and QGroundControl use, MAVProxy 255/0), so that mavcal beside one of them on the same vehicle (a
#: forwarded link, docs/live-link.md) is a separate peer to the vehicle and to the router, and its
#: heartbeats never count as the pilot's ground station (ArduPilot's SYSID_MYGCS, the GCS failsafe).
#: 245 is a system id no vehicle or ground station takes by default; 25 is MAV_COMP_ID_USER1.
GCS_SYSTEM_ID = 245
GCS_COMPONENT_ID = 25

Handler = Callable[[Any], None]

#: MAV_PARAM_TYPE of the integer types -> (struct format, bytes)
_INT_TYPES = {1: ("<B", 1), 2: ("<b", 1), 3: ("<H", 2), 4: ("<h", 2), 5: ("<I", 4), 6: ("<i", 4)}


def param_from_wire(value: float, param_type: int, bytewise: bool) -> float:
    """A PARAM_VALUE's value: on a bytewise vehicle (PX4) an integer type's value is the integer in
    the low bytes of the float field (reinterpreted, never cast); else the float as sent."""
    fmt = _INT_TYPES.get(int(param_type)) if bytewise else None
    if fmt is None:
        return float(value)
    raw = struct.pack("<f", value)
    return float(struct.unpack(fmt[0], raw[:fmt[1]])[0])


def param_to_wire(value: float, param_type: int, bytewise: bool) -> float:
    """The float field a PARAM_SET of ``value`` carries: on a bytewise vehicle an integer type's bytes
    (reinterpreted as a float32), else the value itself (float32)."""
    fmt = _INT_TYPES.get(int(param_type)) if bytewise else None
    if fmt is None:
        return float(struct.unpack("<f", struct.pack("<f", value))[0])
    raw = struct.pack(fmt[0], int(round(value))).ljust(4, b"\0")
    return float(struct.unpack("<f", raw)[0])


#: the vehicle's messages sent at a steady rate whatever is asked (HEARTBEAT), or while a write
#: asks for them (ATTITUDE, :mod:`mavcal.link.silence`); their arrivals measure the rate
PERIODIC_TYPES = frozenset(("HEARTBEAT", "ATTITUDE"))
_PERIODIC_WINDOW = 16

_NETWORK_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:")


class Link:
    """One pymavlink connection with a single dispatching receive loop.

    Parameters
    ----------
    conn : pymavlink.mavutil.mavfile
        An open connection. If ``target_system`` is not given, the connection must already
        have seen the vehicle's HEARTBEAT (``conn.target_system`` set by ``wait_heartbeat``).
    target_system, target_component : int, optional
        The vehicle's ids; default to the connection's.
    device : str, optional
        Device string, for messages only.
    """

    def __init__(self, conn: Any, *, target_system: int | None = None,
                 target_component: int | None = None, device: str | None = None) -> None:
        self.conn = conn
        self.target_system = int(target_system if target_system is not None else conn.target_system)
        self.target_component = int(target_component if target_component is not None
                                    else (conn.target_component or 1))
        self.device = device or getattr(conn, "address", "") or "?"
        self._handlers: dict[str, dict[int, Handler]] = {}
        self._ids = itertools.count(1)
        self.last_heartbeat_s: float | None = None
        #: time.monotonic() of the last message from the vehicle (starts "now")
        self.last_rx_s: float = time.monotonic()
        self.messages_received = 0
        #: the vehicle's messages received and lost, from the gaps in their sequence numbers (a
        #: duplicate or a late message is neither): the link's loss (:mod:`mavcal.link.silence`)
        self.vehicle_received = 0
        self.vehicle_lost = 0
        self._last_seq: int | None = None
        #: time.monotonic() of the vehicle's last few periodic messages, by type (their rates)
        self.periodic_rx_s: dict[str, deque[float]] = {t: deque(maxlen=_PERIODIC_WINDOW) for t in PERIODIC_TYPES}
        #: send a GCS HEARTBEAT this often while pumping (None: never; :func:`open_link` sends
        #: them while it waits for the vehicle either way)
        self.heartbeat_period_s: float | None = None
        self._last_hb_sent = float("-inf")
        #: the signing key set on the connection (None: unsigned)
        self.signing_key: SigningKey | None = None
        #: messages from the vehicle that arrived signed
        self.signed_received = 0
        self._tlog: BinaryIO | None = None
        #: HEARTBEAT.autopilot of the vehicle (None: not known); PX4 sends integers bytewise
        self.autopilot: int | None = None

    @property
    def bytewise_params(self) -> bool:
        """Whether integer parameters travel bytewise in the float field (PX4)."""
        return self.autopilot == MAV_AUTOPILOT_PX4

    def param_value(self, m: Any) -> float:
        """The value of a PARAM_VALUE from this vehicle (:func:`param_from_wire`)."""
        return param_from_wire(m.param_value, m.param_type, self.bytewise_params)

    # -- ids ---------------------------------------------------------------------------------
    @property
    def mav(self) -> Any:
        """The pymavlink ``MAVLink`` encoder (``conn.mav``) used to send messages."""
        return self.conn.mav

    def silent_for(self) -> float:
        """Seconds since the vehicle last sent anything (heartbeats included)."""
        return time.monotonic() - self.last_rx_s

    def is_from_vehicle(self, m: Any) -> bool:
        """True if ``m`` was sent by the target system/component."""
        return m.get_srcSystem() == self.target_system and m.get_srcComponent() == self.target_component

    # -- handlers ----------------------------------------------------------------------------
    def add_handler(self, msg_type: str, fn: Handler) -> tuple[str, int]:
        """Call ``fn(msg)`` for every received message of ``msg_type`` (``"*"`` = all).

        Returns a token for :meth:`remove_handler`.
        """
        key = next(self._ids)
        self._handlers.setdefault(msg_type, {})[key] = fn
        return (msg_type, key)

    def remove_handler(self, token: tuple[str, int]) -> None:
        """Unregister a handler added with :meth:`add_handler` (unknown tokens are ignored)."""
        self._handlers.get(token[0], {}).pop(token[1], None)

    def save_tlog(self, path: str | os.PathLike[str]) -> None:
        """Save every message received from now on in ``path``, as a telemetry log: each message's
        bytes as received (signature included) after its receive time, an 8-byte big-endian count of
        microseconds since 1970: the format MAVProxy and Mission Planner write, which
        :func:`mavcal.sources.read_log` reads back (pymavlink's own ``setup_logfile`` is skipped by
        its UDP connections). Closed with the link; ``SourceError`` when the file cannot be created."""
        try:
            self._tlog = open(path, "wb")  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise SourceError(f"cannot save the telemetry log {os.fspath(path)!r}: {exc.strerror or exc}") from None

    def _dispatch(self, m: Any) -> None:
        mtype = m.get_type()
        if mtype == "BAD_DATA":
            return
        if self._tlog is not None:
            self._write_tlog(m)
        self.messages_received += 1
        if self.is_from_vehicle(m):
            self.last_rx_s = time.monotonic()
            if self._count_seq(m) and mtype in PERIODIC_TYPES:
                self.periodic_rx_s[mtype].append(self.last_rx_s)
            if is_signed(m):
                self.signed_received += 1
            if mtype == "HEARTBEAT":
                self.last_heartbeat_s = self.last_rx_s
        for table in (self._handlers.get(mtype), self._handlers.get("*")):
            if table:
                for fn in list(table.values()):
                    fn(m)

    def _count_seq(self, m: Any) -> bool:
        """Count a message from the vehicle by its sequence number; False for a duplicate."""
        seq = int(m.get_seq())
        if self._last_seq is not None:
            gap = (seq - self._last_seq - 1) % 256
            if gap >= 128:  # a duplicate (gap 255) or a late message: not a new one
                return False
            self.vehicle_lost += gap
        self._last_seq = seq
        self.vehicle_received += 1
        return True

    def _write_tlog(self, m: Any) -> None:
        try:
            assert self._tlog is not None
            self._tlog.write(struct.pack(">Q", int(time.time() * 1e6)) + bytes(m.get_msgbuf()))
        except OSError as exc:  # a full disk: the session goes on, the file stops here
            log.warning("the telemetry log %s stops here: %s", self._tlog.name if self._tlog else "?", exc)
            self._close_tlog()

    def _close_tlog(self) -> None:
        f, self._tlog = self._tlog, None
        if f is not None:
            try:
                f.close()
            except OSError as exc:  # a full disk shows at the last flush
                log.warning("the telemetry log %s may be incomplete: %s", f.name, exc)

    # -- the receive loop --------------------------------------------------------------------
    def _keepalive(self) -> None:
        """A GCS HEARTBEAT when ``heartbeat_period_s`` has passed (best effort: a failed send is logged)."""
        if self.heartbeat_period_s is None:
            return
        now = time.monotonic()
        if now - self._last_hb_sent >= self.heartbeat_period_s:
            self._last_hb_sent = now
            try:
                self.send_gcs_heartbeat()
            except LinkError as exc:  # udpout to an unreachable host, a closed tcp peer...
                log.debug("heartbeat not sent: %s", exc)

    def _recv(self, timeout_s: float) -> Any:
        self._keepalive()
        try:
            if timeout_s <= 0:
                return self.conn.recv_match(blocking=False)
            return self.conn.recv_match(blocking=True, timeout=timeout_s)
        except (OSError, ValueError) as exc:  # socket closed / reset, serial unplugged
            raise LinkError(f"{self.device}: connection lost: {exc}") from None

    def pump(self, timeout_s: float) -> int:
        """Receive and dispatch messages for ``timeout_s`` seconds; return how many arrived."""
        deadline = time.monotonic() + max(timeout_s, 0.0)
        n = 0
        while True:
            remaining = deadline - time.monotonic()
            m = self._recv(remaining if remaining > 0 else 0.0)
            if m is not None:
                self._dispatch(m)
                n += 1
                continue
            if remaining <= 0:
                return n

    def wait(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Pump the loop until ``predicate()`` is true or ``timeout_s`` passes.

        Returns
        -------
        bool
            The final value of ``predicate()``.
        """
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while not predicate():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return predicate()
            m = self._recv(min(remaining, 0.05))
            if m is not None:
                self._dispatch(m)
        return True

    # -- sending -----------------------------------------------------------------------------
    def send_gcs_heartbeat(self) -> None:
        """Send one GCS HEARTBEAT (lets a ``udpout`` peer learn our address)."""
        try:
            self.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        except OSError as exc:
            raise LinkError(f"{self.device}: cannot send: {exc}") from None

    def close(self) -> None:
        """Close the underlying connection (and the telemetry log it saves, if any)."""
        try:
            self.conn.close()
        except Exception:  # pragma: no cover - closing a broken socket
            pass
        self._close_tlog()

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_vehicle_heartbeat(m: Any) -> bool:
    return (m.get_type() == "HEARTBEAT"
            and m.type != mavutil.mavlink.MAV_TYPE_GCS
            and m.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID)


def _connect(device: str, baud: int, source_system: int, source_component: int,
             signing_key: SigningKey | None) -> Any:
    if signing_key is not None:
        # signing is MAVLink 2 only; pymavlink would otherwise start in MAVLink 1 and replace its
        # encoder (and the signing state with it) on the first MAVLink 2 frame. pymavlink sets
        # this variable itself at that switch.
        os.environ["MAVLINK20"] = "1"
    if is_serial_device(device):  # exclusive, one-line reasons, a pulled cable waited for
        conn = open_serial(device, baud, source_system=source_system, source_component=source_component)
        if signing_key is not None:
            setup_signing(conn, signing_key)
        return conn
    kwargs: dict[str, Any] = dict(source_system=source_system, source_component=source_component,
                                  dialect="ardupilotmega", autoreconnect=False)
    if device.startswith("tcp:"):
        kwargs["retries"] = 0  # one connect attempt: pymavlink would otherwise sleep and print
    elif not device.startswith(_NETWORK_PREFIXES):
        kwargs["baud"] = baud
    try:
        conn = mavutil.mavlink_connection(device, **kwargs)
    except Exception as exc:  # socket / serial errors of many kinds
        raise LinkError(f"cannot open {device}: {exc}") from None
    if signing_key is not None:
        setup_signing(conn, signing_key)
    return conn


#: a serial port that sent only bytes that never parse is judged (the wrong baud rate) after this long
_GARBAGE_AFTER_S = 2.0


def _garbage_only(link: Link) -> bool:
    """A serial port that sent :data:`GARBAGE_BYTES` and not one MAVLink message: the wrong baud rate."""
    conn = link.conn
    return (isinstance(conn, SerialConnection) and link.messages_received == 0
            and conn.bytes_received >= GARBAGE_BYTES)


def _wait_heartbeat(link: Link, target_system: int | None, timeout_s: float, budget_s: float) -> Any:
    """The first vehicle HEARTBEAT: wait ``timeout_s``, or ``budget_s`` once the device is heard; a
    serial port that sends only garbage is given up after :data:`_GARBAGE_AFTER_S`."""
    found: list[Any] = []

    def on_heartbeat(m: Any) -> None:
        if not found and _is_vehicle_heartbeat(m) and (target_system is None or m.get_srcSystem() == target_system):
            found.append(m)

    def heard() -> bool:  # a lossy link: messages from the device, not frames refused for their signature
        return link.messages_received > 0

    token = link.add_handler("HEARTBEAT", on_heartbeat)
    start = time.monotonic()
    try:
        while not found:
            limit = start + (max(timeout_s, budget_s) if heard() else timeout_s)
            remaining = limit - time.monotonic()
            if remaining <= 0:
                break
            if time.monotonic() - start >= min(_GARBAGE_AFTER_S, timeout_s) and _garbage_only(link):
                break
            link.send_gcs_heartbeat()
            link.wait(lambda: bool(found), min(0.5, remaining))
    finally:
        link.remove_handler(token)
    return found[0] if found else None


def _answers_unsigned(link: Link, budget_s: float, retry_s: float = 0.5) -> bool:
    """True once the vehicle answers an unsigned request (PARAM_REQUEST_READ of index 0),
    asked every ``retry_s`` for at most ``budget_s``."""
    answered: list[bool] = []

    def on_value(m: Any) -> None:  # the answer to our request: index 0 (a broadcast of a changed
        if link.is_from_vehicle(m) and int(m.param_index) == 0:  # parameter has index 65535)
            answered.append(True)

    token = link.add_handler("PARAM_VALUE", on_value)
    deadline = time.monotonic() + budget_s
    try:
        while not answered and time.monotonic() < deadline:
            link.mav.param_request_read_send(link.target_system, link.target_component, b"", 0)
            link.wait(lambda: bool(answered), min(retry_s, max(deadline - time.monotonic(), 0.0)))
    finally:
        link.remove_handler(token)
    return bool(answered)


def open_link(device: str, *, baud: int = 115200, timeout_s: float = 5.0,
              source_system: int = GCS_SYSTEM_ID, source_component: int = GCS_COMPONENT_ID,
              target_system: int | None = None, budget_s: float = 15.0,
              signing_key: SigningKey | None = None, tlog: str | os.PathLike[str] | None = None) -> Link:
    """Open ``device`` and wait for a vehicle HEARTBEAT.

    Parameters
    ----------
    device : str
        pymavlink device string (see the module docstring); ``"auto"``: the one serial port that looks
        like a flight controller (:func:`mavcal.link.autodetect.find_port`).
    baud : int
        Serial baud rate (ignored for network links).
    timeout_s : float
        How long to wait for the vehicle's HEARTBEAT when nothing at all is heard.
    source_system, source_component : int
        Our own MAVLink ids.
    target_system : int, optional
        Only accept a vehicle with this system id (default: the first vehicle heard).
    budget_s : float
        How long to keep waiting for a HEARTBEAT once the device is heard (a lossy link), and
        for an answer to an unsigned request when the vehicle signs and no key was given.
    signing_key : SigningKey, optional
        Sign every message and accept only validly signed ones (:mod:`mavcal.link.signing`).
    tlog : path, optional
        Save every message received from now on in this file (:meth:`Link.save_tlog`).

    Returns
    -------
    Link
        With ``target_system``/``target_component`` taken from the HEARTBEAT.

    Raises
    ------
    SigningError
        The vehicle requires signing and no key was given, or its signatures do not match
        ``signing_key``, or it does not sign although a key was given (exit code 8).
    LinkError
        The device cannot be opened or no vehicle HEARTBEAT arrives in time.
    """
    if not device:
        raise LinkError("no device given")
    if device == AUTO:
        device = find_port().device
    conn = _connect(device, baud, source_system, source_component, signing_key)
    link = Link(conn, target_system=target_system or 0, target_component=0, device=device)
    if tlog is not None:
        try:
            link.save_tlog(tlog)
        except SourceError:
            link.close()
            raise
    link.signing_key = signing_key
    try:
        hb = _wait_heartbeat(link, target_system, timeout_s, budget_s)
        if hb is None:
            problem = signing_problem(conn, signing_key)
            if problem is not None:
                raise SigningError(f"{device}: {problem}")
            waited = max(timeout_s, budget_s) if link.messages_received else timeout_s
            if isinstance(conn, SerialConnection) and not link.messages_received:
                garbage = conn.bytes_received > 0  # bytes, never a frame: the wrong rate (few bytes: a slow talker)
                answered = probe_bauds(conn) if garbage else None
                raise LinkError(no_mavlink_reason(conn.device, conn.baud, garbage=garbage, waited_s=waited,
                                                  answered_at=answered))
            raise LinkError(f"no heartbeat from a vehicle on {device} within {waited:g} s")
        link.target_system = hb.get_srcSystem()
        link.target_component = hb.get_srcComponent()
        link.autopilot = int(hb.autopilot)
        conn.target_system = link.target_system
        conn.target_component = link.target_component
        if signing_key is None and is_signed(hb) and not _answers_unsigned(link, max(timeout_s, budget_s)):
            raise SigningError(f"{device}: {NEEDS_KEY}")
    except LinkError:
        link.close()
        raise
    log.info("connected to system %d component %d on %s%s", link.target_system, link.target_component, device,
             " (signed)" if signing_key is not None else "")
    return link


def as_link(conn_or_link: Any) -> Link:
    """Return ``conn_or_link`` if it is a :class:`Link`, else wrap a pymavlink connection."""
    if isinstance(conn_or_link, Link):
        return conn_or_link
    if getattr(conn_or_link, "target_system", 0) in (0, None):
        raise LinkError("the connection has not seen a vehicle heartbeat yet (call wait_heartbeat first)")
    return Link(conn_or_link)
