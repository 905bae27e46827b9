"""Serial ports: recognised, opened exclusively, their failures said in one line, a pulled cable waited for.

A flight controller on a USB cable (``/dev/ttyACM0``, ``/dev/cu.usbmodem*``, ``COM3``), a
telemetry radio (``/dev/ttyUSB0``, usually 57600 baud) or any path to a character device, also
through a symlink (udev's ``/dev/serial/by-id/...`` names) is a serial device
(:func:`is_serial_device`). :func:`open_serial` opens it with pyserial:

* **exclusively**: pyserial's ``exclusive=True`` (an advisory ``flock``) and ``TIOCEXCL``, so a
  ground station that opens the port after mavcal is refused, and a port another program
  already holds that way is reported busy rather than shared (two programs reading one serial
  port each get half the bytes);
* **its failures in one line** each (:func:`open_error`): no such port (the ports seen are
  listed), busy (locked, or on Linux open in another process, named: :func:`port_holders`,
  since MAVProxy and pymavlink scripts open ports without a lock), permission denied (the
  ``dialout`` group on Linux), not a serial port;
* **a pulled cable is waited for**: when the port fails under a read or a write (the USB
  device went away: "device reports readiness to read but returned no data"), the connection
  closes it, drops what is sent meanwhile (as a radio loses frames) and tries to open the same
  path again every :data:`REOPEN_PERIOD_S`. To the caller the vehicle is only silent for a
  while, which the writer already waits out (:mod:`mavcal.link.silence`): the write resumes
  when the vehicle is back, or is undone when it stays away past the write's budget.

A port that exists but speaks no MAVLink at the baud rate given answers with bytes that never
parse; :func:`probe_bauds` then listens at the common rates (:data:`COMMON_BAUDS`, as MAVProxy
and QGroundControl try them) and :func:`no_mavlink_reason` says which one answered.
"""
from __future__ import annotations

import errno
import logging
import os
import re
import stat
import sys
import time
from collections.abc import Sequence
from typing import Any

from pymavlink import mavutil

from mavcal.errors import LinkError

__all__ = ["is_serial_device", "split_baud", "open_serial", "open_error", "SerialConnection", "probe_bauds",
           "no_mavlink_reason", "port_holders", "COMMON_BAUDS", "RADIO_BAUD", "REOPEN_PERIOD_S", "GARBAGE_BYTES",
           "ports_seen"]

log = logging.getLogger(__name__)

#: the rates :func:`probe_bauds` tries: SiK radios, USB/most UARTs, fast companion links
COMMON_BAUDS = (57600, 115200, 921600)
#: what telemetry radios (SiK, RFD900) run at by default
RADIO_BAUD = 57600
#: a pulled port is tried again this often
REOPEN_PERIOD_S = 0.25
#: bytes that arrive without one MAVLink frame among them: the wrong baud rate, not silence
GARBAGE_BYTES = 64
#: a write blocked this long loses its bytes (a stuck port), as a radio would
_WRITE_TIMEOUT_S = 1.0

_NETWORK_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:", "mcast:", "ws:", "wss:",
                     "wsserver:", "uds:", "unix:")
_WINDOWS_PORT = re.compile(r"^(\\\\\.\\)?COM\d+$", re.I)


def split_baud(device: str) -> tuple[str, int | None]:
    """MAVProxy's ``DEVICE,BAUD`` form (``/dev/ttyUSB0,57600``) -> (device, baud); else (device, None)."""
    head, sep, tail = device.rpartition(",")
    if sep and tail.isdigit() and not os.path.exists(device):
        return head, int(tail)
    return device, None


def is_serial_device(device: str) -> bool:
    """True for a serial port: ``/dev/...``, ``COMn``, or any path to a character device (through
    symlinks too); False for a network device string or a file."""
    s, _ = split_baud(str(device))
    if not s or s.lower().startswith(_NETWORK_PREFIXES):
        return False
    if s.startswith("/dev/") or _WINDOWS_PORT.match(s):
        return True
    try:
        if os.path.islink(s) and not os.path.exists(s):  # a udev-style name whose device is gone
            return os.path.realpath(s).startswith("/dev/")
        return stat.S_ISCHR(os.stat(s).st_mode)
    except PermissionError:  # a path we may not look at: opening it says why
        return True
    except (OSError, ValueError):
        return False


def ports_seen() -> list[str]:
    """The serial ports pyserial lists on this machine (device names)."""
    try:
        from serial.tools import list_ports

        return sorted(p.device for p in list_ports.comports())
    except Exception:  # pragma: no cover - a platform pyserial cannot list
        return []


def _seen_text() -> str:
    seen = ports_seen()
    return f" (serial ports here: {', '.join(seen)})" if seen else " (no serial port found on this machine)"


def open_error(device: str, exc: BaseException) -> LinkError:
    """One line saying why ``device`` could not be opened (pyserial's exception ``exc``)."""
    code = getattr(exc, "errno", None)
    text = str(exc)
    if code in (errno.EACCES, errno.EPERM) and not (os.name == "nt"):
        hint = ("add yourself to the dialout group (sudo usermod -aG dialout $USER; uucp on Arch), then log in again"
                if sys.platform.startswith("linux") else "check who may open it")
        return LinkError(f"permission denied opening {device}: {hint}")
    if (code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK) or "exclusively lock" in text
            or (os.name == "nt" and ("Access is denied" in text or code == errno.EACCES))):
        return _busy(device, port_holders(device))
    if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO) or "FileNotFoundError" in text:
        return LinkError(f"no serial port {device}: is the cable plugged in and the board powered?{_seen_text()}")
    if code == errno.EIO:
        return LinkError(f"{device} does not answer (input/output error): unplug it and plug it back")
    reason = getattr(exc, "strerror", None) or text
    return LinkError(f"cannot open {device}: {reason}")


def _check_path(device: str, quiet: bool = False) -> None:
    """The one-line reasons a path gives before any open: missing (a broken symlink too), not a port
    (``quiet``: without listing the ports seen, as the reopening of a pulled port tries again and again)."""
    if _WINDOWS_PORT.match(device) or os.name == "nt":
        return
    try:
        mode = os.stat(device).st_mode
    except PermissionError as exc:
        raise open_error(device, exc) from None
    except (FileNotFoundError, NotADirectoryError):
        broken = f" (a link to {os.readlink(device)}, which is gone)" if os.path.islink(device) else ""
        raise LinkError(f"no serial port {device}{broken}: is the cable plugged in and the board powered?"
                        f"{'' if quiet else _seen_text()}") from None
    if not stat.S_ISCHR(mode):
        raise LinkError(f"{device} is not a serial port (not a character device)")


def port_holders(device: str) -> list[str]:
    """Other processes that have ``device`` open, as ``name (pid N)`` (Linux: their /proc/PID/fd;
    processes of other users are not visible to a normal user). Empty elsewhere."""
    if not sys.platform.startswith("linux"):
        return []
    try:
        rdev = os.stat(device).st_rdev
    except OSError:
        return []
    me = os.getpid()
    out = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or int(pid) == me:
            continue
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                st = os.stat(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if stat.S_ISCHR(st.st_mode) and st.st_rdev == rdev:
                try:
                    with open(f"/proc/{pid}/comm") as f:
                        name = f.read().strip()
                except OSError:
                    name = "?"
                out.append(f"{name} (pid {pid})")
                break
    return out


def _busy(device: str, who: Sequence[str] = ()) -> LinkError:
    held = f"{', '.join(who)} has it open" if who else "another program holds it"
    return LinkError(f"{device} is busy: {held} (Mission Planner, QGroundControl, MAVProxy?): close it there, or "
                     "have it forward MAVLink to mavcal over UDP (docs/live-link.md)")


def _open_port(device: str, baud: int, reopen: bool = False) -> Any:
    """A pyserial port on ``device``, exclusive (flock and TIOCEXCL), non-blocking reads; LinkError else.
    ``reopen``: a pulled port tried again (every REOPEN_PERIOD_S): no port list, no search for holders."""
    import serial

    _check_path(device, quiet=reopen)
    try:
        port = serial.Serial(device, baud, timeout=0, write_timeout=_WRITE_TIMEOUT_S, dsrdtr=False, rtscts=False,
                             xonxoff=False, exclusive=True)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise open_error(device, exc) from None
    who = [] if reopen else port_holders(device)  # one that opened it without a lock (MAVProxy) reads it too
    if who:
        port.close()
        raise _busy(device, who)
    try:  # others opening it now get EBUSY, as QGroundControl's own ports do
        import fcntl
        import termios

        fcntl.ioctl(port.fileno(), termios.TIOCEXCL)
    except (ImportError, AttributeError, OSError, ValueError):
        pass
    return port


class SerialConnection(mavutil.mavserial):
    """pymavlink's serial connection, opened exclusively, that waits out a pulled cable.

    When the port fails under a read or a write it is closed; reads return nothing and writes are
    dropped until the same path opens again (tried every :data:`REOPEN_PERIOD_S`). ``pulls``
    counts the times the port went away, ``bytes_received`` the bytes read."""

    def __init__(self, device: str, baud: int, *, source_system: int, source_component: int) -> None:
        self.bytes_received = 0
        self.pulls = 0
        self._down_since: float | None = None
        self._next_try = 0.0
        self._closed = False
        self.baud = baud
        self.device = device
        self.autoreconnect = False
        self.force_connected = False
        self.rtscts = False
        self.port = _open_port(device, baud)
        fd = self.port.fileno()
        mavutil.set_close_on_exec(fd)
        mavutil.mavfile.__init__(self, fd, device, source_system=source_system, source_component=source_component)

    @property
    def is_down(self) -> bool:
        """True while the port is gone (pulled) and not opened again yet."""
        return self._down_since is not None

    def _lost(self, exc: BaseException) -> None:
        self.pulls += 1
        log.warning("%s went away (%s): waiting for it to come back", self.device, exc)
        try:
            self.port.close()
        except Exception:  # pragma: no cover - closing a dead port
            pass
        self.fd = None
        self._down_since = time.monotonic()
        self._next_try = self._down_since + REOPEN_PERIOD_S

    def _reopen(self) -> bool:
        now = time.monotonic()
        if self._closed or now < self._next_try:
            return False
        self._next_try = now + REOPEN_PERIOD_S
        try:
            port = _open_port(self.device, self.baud, reopen=True)
        except LinkError as exc:
            log.debug("%s: not back yet: %s", self.device, exc)
            return False
        self.port = port
        self.fd = port.fileno()
        mavutil.set_close_on_exec(self.fd)
        log.warning("%s is back after %.1f s", self.device, now - (self._down_since or now))
        self._down_since = None
        return True

    def recv(self, n: int | None = None) -> bytes:
        import serial

        if self._closed or (self._down_since is not None and not self._reopen()):
            if not self._closed:
                time.sleep(0.01)  # pymavlink's select() sleeps only while fd is None; keep a busy loop cool
            return b""
        try:
            data = super().recv(n)
        except (serial.SerialException, OSError) as exc:
            self._lost(exc)
            return b""
        self.bytes_received += len(data)
        return data

    def write(self, buf: Any) -> int:
        import serial

        if self._closed or (self._down_since is not None and not self._reopen()):
            return -1  # lost, as a radio loses a frame; the caller's retries cover it
        try:
            return int(self.port.write(bytes(buf)) or 0)
        except serial.SerialTimeoutException:
            log.debug("%s: a write timed out (%d bytes lost)", self.device, len(buf))
            return -1
        except (serial.SerialException, OSError) as exc:
            self._lost(exc)
            return -1

    def set_baudrate(self, baudrate: int) -> None:
        self.baud = baudrate
        if not self.is_down:
            self.port.baudrate = baudrate

    def close(self) -> None:
        self._closed = True
        try:
            self.port.close()
        except Exception:  # pragma: no cover - closing a dead port
            pass


def open_serial(device: str, baud: int, *, source_system: int, source_component: int) -> SerialConnection:
    """Open the serial port ``device`` (``DEVICE,BAUD`` overrides ``baud``); LinkError with a one-line
    reason when it cannot be opened."""
    dev, given = split_baud(device)
    mavutil.set_dialect("ardupilotmega")
    return SerialConnection(dev, given or baud, source_system=source_system, source_component=source_component)


def _speaks_mavlink(conn: SerialConnection, listen_s: float) -> bool:
    """True when a valid MAVLink frame arrives within ``listen_s`` at the port's current rate."""
    try:
        conn.port.reset_input_buffer()
    except Exception:  # pragma: no cover - a port gone meanwhile
        return False
    conn.mav.buf = bytearray()
    conn.mav.buf_index = 0
    deadline = time.monotonic() + listen_s
    while time.monotonic() < deadline:
        m = conn.recv_match(blocking=True, timeout=min(0.1, max(deadline - time.monotonic(), 0.0)))
        if m is not None and m.get_type() != "BAD_DATA":
            return True
    return False


def probe_bauds(conn: SerialConnection, bauds: Sequence[int] = COMMON_BAUDS, listen_s: float = 1.2) -> int | None:
    """The first of ``bauds`` (other than the port's own) at which MAVLink arrives, or None. The
    port is left at its own rate."""
    own = conn.baud
    try:
        for b in bauds:
            if b == own:
                continue
            conn.set_baudrate(b)
            if _speaks_mavlink(conn, listen_s):
                return b
        return None
    finally:
        if not conn.is_down:
            conn.set_baudrate(own)


def no_mavlink_reason(device: str, baud: int, *, garbage: bool, waited_s: float, answered_at: int | None) -> str:
    """The one line of a serial port without a vehicle heartbeat at ``baud``."""
    if answered_at is not None:
        return f"no MAVLink on {device} at {baud} baud, but it answered at {answered_at}: --baud {answered_at}"
    fix = (f"telemetry radios usually run at {RADIO_BAUD}: --baud {RADIO_BAUD}" if baud != RADIO_BAUD
           else "a USB cable runs at any rate, a radio at the rate it was set to (SERIALn_BAUD): --baud 115200?")
    if garbage:
        tried = ", ".join(str(b) for b in COMMON_BAUDS if b != baud)
        return (f"{device} sends bytes but no MAVLink at {baud} baud (nor at {tried}): the wrong baud rate, "
                f"or not a flight controller; {fix}")
    return (f"no heartbeat from a vehicle on {device} at {baud} baud within {waited_s:g} s (nothing received): "
            f"is the vehicle powered, and is this its port? {fix}")
