"""Open a MAVLink link to a vehicle and run the one receive loop on it.

pymavlink's ``recv_match(type=...)`` throws away every message it skips, so a program that
calls it from several places loses messages (a PARAM_VALUE eaten while waiting for a
COMMAND_ACK). :class:`Link` owns the only read loop on its connection: callers register
handlers and then *pump* the loop (:meth:`Link.pump`, :meth:`Link.wait`) until their condition
holds. Every message received goes to every handler registered for its type.

A :class:`Link` is not thread-safe: one thread owns it and pumps it.

Device strings are pymavlink's: ``udpin:HOST:PORT`` (listen), ``udpout:HOST:PORT`` (send
first), ``udp:HOST:PORT`` (= udpin), ``tcp:HOST:PORT`` (client), ``tcpin:HOST:PORT``, or a
serial device (``/dev/ttyACM0``, ``COM3``) with ``baud``.
"""
from __future__ import annotations

import itertools
import logging
import time
from typing import Any, Callable

from pymavlink import mavutil

from mavcal.errors import LinkError

__all__ = ["Link", "open_link", "as_link", "GCS_SYSTEM_ID", "GCS_COMPONENT_ID"]

log = logging.getLogger(__name__)

#: our own ids: a ground station (255) and MAV_COMP_ID_MISSIONPLANNER (190), as MAVProxy uses
GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = 190

Handler = Callable[[Any], None]

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
        #: send a GCS HEARTBEAT this often while pumping (None: never; :func:`open_link` sends
        #: them while it waits for the vehicle either way)
        self.heartbeat_period_s: float | None = None
        self._last_hb_sent = float("-inf")

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

    def _dispatch(self, m: Any) -> None:
        mtype = m.get_type()
        if mtype == "BAD_DATA":
            return
        self.messages_received += 1
        if self.is_from_vehicle(m):
            self.last_rx_s = time.monotonic()
            if mtype == "HEARTBEAT":
                self.last_heartbeat_s = self.last_rx_s
        for table in (self._handlers.get(mtype), self._handlers.get("*")):
            if table:
                for fn in list(table.values()):
                    fn(m)

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
        """Close the underlying connection."""
        try:
            self.conn.close()
        except Exception:  # pragma: no cover - closing a broken socket
            pass

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_vehicle_heartbeat(m: Any) -> bool:
    return (m.get_type() == "HEARTBEAT"
            and m.type != mavutil.mavlink.MAV_TYPE_GCS
            and m.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID)


def open_link(device: str, *, baud: int = 115200, timeout_s: float = 5.0,
              source_system: int = GCS_SYSTEM_ID, source_component: int = GCS_COMPONENT_ID,
              target_system: int | None = None) -> Link:
    """Open ``device`` and wait for a vehicle HEARTBEAT.

    Parameters
    ----------
    device : str
        pymavlink device string (see the module docstring).
    baud : int
        Serial baud rate (ignored for network links).
    timeout_s : float
        How long to wait for the vehicle's HEARTBEAT.
    source_system, source_component : int
        Our own MAVLink ids.
    target_system : int, optional
        Only accept a vehicle with this system id (default: the first vehicle heard).

    Returns
    -------
    Link
        With ``target_system``/``target_component`` taken from the HEARTBEAT.

    Raises
    ------
    LinkError
        The device cannot be opened or no vehicle HEARTBEAT arrives within ``timeout_s``.
    """
    if not device:
        raise LinkError("no device given")
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
    link = Link(conn, target_system=target_system or 0, target_component=0, device=device)
    found: list[Any] = []

    def on_heartbeat(m: Any) -> None:
        if not found and _is_vehicle_heartbeat(m) and (target_system is None or m.get_srcSystem() == target_system):
            found.append(m)

    token = link.add_handler("HEARTBEAT", on_heartbeat)
    deadline = time.monotonic() + timeout_s
    try:
        while not found:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            link.send_gcs_heartbeat()
            link.wait(lambda: bool(found), min(0.5, remaining))
    except LinkError:
        link.close()
        raise
    finally:
        link.remove_handler(token)
    if not found:
        link.close()
        raise LinkError(f"no heartbeat from a vehicle on {device} within {timeout_s:g} s")
    hb = found[0]
    link.target_system = hb.get_srcSystem()
    link.target_component = hb.get_srcComponent()
    conn.target_system = link.target_system
    conn.target_component = link.target_component
    log.info("connected to system %d component %d on %s", link.target_system, link.target_component, device)
    return link


def as_link(conn_or_link: Any) -> Link:
    """Return ``conn_or_link`` if it is a :class:`Link`, else wrap a pymavlink connection."""
    if isinstance(conn_or_link, Link):
        return conn_or_link
    if getattr(conn_or_link, "target_system", 0) in (0, None):
        raise LinkError("the connection has not seen a vehicle heartbeat yet (call wait_heartbeat first)")
    return Link(conn_or_link)
