"""A serial cable for the tests: a pseudo-terminal the tool opens, relayed to a vehicle, pullable.

The tool opens :attr:`SerialCable.path` (a symlink to the slave side of a pty, as udev's
``/dev/serial/by-id/...`` names are symlinks to ``/dev/ttyACM0``) as it would a flight
controller's USB port. The relay copies bytes between the pty's master and the vehicle, which
is either

* a TCP server (:class:`mavcal.testing.vehicle.TestVehicle` with ``"tcp"``): ``SerialCable(tcp_port=...)``;
* another pty whose slave the vehicle opens itself (ArduPilot SITL's ``--serialN
  uart:/dev/pts/K:BAUD``): ``SerialCable()``, then :attr:`vehicle_tty`.

Like a telemetry radio, the relay carries at most ``baud / 10`` bytes per second each way
(``baud=None``: as fast as the pty goes) and buffers at most :data:`BUFFER_BYTES` per direction:
it reads from a side only while its buffer has room, so a sender that outruns the rate sees a
full port (ArduPilot then sends fewer messages, as it does on a radio).

:meth:`SerialCable.pull` is a pulled cable: the tool's pty is closed (its reader gets "device
reports readiness to read but returned no data") and its path removed; :meth:`SerialCable.plug`
(or ``pull(seconds)``, scripted) makes a new pty and points the same path at it.
:meth:`SerialCable.pull_at` pulls when the tool has sent its n-th message of a MAVLink id ("right
after the 4th PARAM_SET"). ``speaks_at``: the vehicle's bytes reach the tool intact only while the
tool's end is set to that baud rate (read from the pty's termios), scrambled otherwise, as a
radio at another rate would look. One thread; stopped by :meth:`stop` (or the context manager).
"""
from __future__ import annotations

import contextlib
import os
import select
import socket
import tempfile
import termios
import threading
import time
import tty
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["SerialCable", "BUFFER_BYTES", "baud_of"]

#: bytes buffered per direction (a SiK radio's buffer is of this order)
BUFFER_BYTES = 2048

_SPEEDS = {getattr(termios, f"B{b}"): b for b in (1200, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
           if hasattr(termios, f"B{b}")}


def baud_of(fd: int) -> int | None:
    """The baud rate a pty's termios (read on either side) is set to, or None."""
    try:
        return _SPEEDS.get(termios.tcgetattr(fd)[5])
    except (termios.error, OSError):
        return None


def mavlink_ids() -> Any:
    """A function of a chunk of a byte stream -> the MAVLink ids of the whole frames it completes."""
    mav = mavlink2.MAVLink(None)
    mav.robust_parsing = True

    def ids(data: bytes) -> list[int]:
        try:
            msgs = mav.parse_buffer(data) or []
        except mavlink2.MAVError:
            return []
        return [m.get_msgId() for m in msgs if m.get_type() != "BAD_DATA"]

    return ids


def _new_pty() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)  # no echo, no line editing before the tool configures the port
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


class _Bucket:
    """At most ``rate`` bytes per second (None: no limit), with a burst of 1/20 s."""

    def __init__(self, rate: float | None) -> None:
        self.rate = rate
        self.tokens = 0.0
        self.t = time.monotonic()

    def allow(self, want: int) -> int:
        if self.rate is None:
            return want
        now = time.monotonic()
        self.tokens = min(self.tokens + (now - self.t) * self.rate, max(self.rate / 20.0, 64.0))
        self.t = now
        n = min(want, int(self.tokens))
        self.tokens -= n
        return n


class SerialCable:
    """A pty the tool opens at :attr:`path`, relayed to a vehicle at ``baud / 10`` bytes per second.

    Parameters
    ----------
    tcp_port : int, optional
        The vehicle is a TCP server on 127.0.0.1 at this port; default: a pty (:attr:`vehicle_tty`).
    baud : int, optional
        The radio's rate (bytes per second = baud / 10); None: no limit.
    speaks_at : int, optional
        The vehicle's bytes reach the tool intact only while its end is set to this baud rate.
    directory : path, optional
        Where the :attr:`path` symlink lives (default: a new temporary directory).
    """

    def __init__(self, *, tcp_port: int | None = None, baud: int | None = None, speaks_at: int | None = None,
                 directory: str | os.PathLike[str] | None = None) -> None:
        self.baud = baud
        self.speaks_at = speaks_at
        self._own_dir = directory is None
        self.directory = Path(tempfile.mkdtemp(prefix="mavcal-cable-") if directory is None else directory)
        self.path = str(self.directory / "usb-ArduPilot_fmuv3-if00")
        self._sock: socket.socket | None = None
        self._veh_master: int | None = None
        self._veh_slave: int | None = None
        self.vehicle_tty: str | None = None
        if tcp_port is not None:
            self._sock = socket.create_connection(("127.0.0.1", int(tcp_port)), timeout=5.0)
            self._sock.setblocking(False)
        else:
            self._veh_master, self._veh_slave, self.vehicle_tty = _new_pty()
        self._tool_master: int | None = None
        self._tool_idle_until = 0.0
        self.tool_tty: str | None = None
        self._lock = threading.RLock()
        self._to_tool = bytearray()
        self._to_vehicle = bytearray()
        self._in_bucket = _Bucket(None if baud is None else baud / 10.0)
        self._out_bucket = _Bucket(None if baud is None else baud / 10.0)
        self._parser = mavlink_ids()
        self._pull_at: tuple[int, int, float] | None = None
        self._counts: dict[int, int] = {}
        self._plug_due: float | None = None
        #: (monotonic s pulled, monotonic s plugged back or None)
        self.pulls: list[list[float | None]] = []
        self.stats = {"to_tool": 0, "to_vehicle": 0, "dropped": 0, "scrambled": 0}
        self._running = False
        self._thread: threading.Thread | None = None
        self.plug()

    # ---------------------------------------------------------------- the tool's end
    @property
    def plugged(self) -> bool:
        return self._tool_master is not None

    def plug(self) -> None:
        """A new pty for the tool, at :attr:`path` (idempotent while plugged)."""
        with self._lock:
            if self._tool_master is not None:
                return
            self._tool_master, slave, self.tool_tty = _new_pty()
            os.close(slave)  # nobody but the tool has its end open (mavcal names other holders as busy)
            tmp = self.path + ".new"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self.tool_tty, tmp)
            os.replace(tmp, self.path)
            self._plug_due = None
            if self.pulls and self.pulls[-1][1] is None:
                self.pulls[-1][1] = time.monotonic()

    def pull(self, for_s: float | None = None) -> None:
        """Pull the cable: the tool's pty is closed and :attr:`path` removed; plugged back (a new
        pty at the same path) after ``for_s`` seconds, or by :meth:`plug`."""
        with self._lock:
            if self._tool_master is None:
                return
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
            with contextlib.suppress(OSError):
                os.close(self._tool_master)
            self._tool_master = None
            self._to_tool.clear()
            self._to_vehicle.clear()
            self.pulls.append([time.monotonic(), None])
            self._plug_due = None if for_s is None else time.monotonic() + for_s

    def pull_at(self, msg_id: int, n: int, for_s: float) -> None:
        """Pull the cable for ``for_s`` seconds right after the tool sent its ``n``-th message ``msg_id``
        (that message itself reaches the vehicle)."""
        with self._lock:
            self._pull_at = (int(msg_id), int(n), float(for_s))

    def sent(self, msg_id: int) -> int:
        """How many messages ``msg_id`` the tool has sent through the cable."""
        with self._lock:
            return self._counts.get(int(msg_id), 0)

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> SerialCable:
        if not self._running:
            self._running = True
            self._thread = threading.Thread(target=self._run, name="SerialCable", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.pull()
        for fd in (self._veh_master, self._veh_slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._veh_master = self._veh_slave = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._own_dir:
            with contextlib.suppress(OSError):
                for p in self.directory.iterdir():
                    p.unlink()
                self.directory.rmdir()

    def __enter__(self) -> SerialCable:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---------------------------------------------------------------- the relay
    def _vehicle_read(self, n: int) -> bytes:
        try:
            if self._sock is not None:
                return self._sock.recv(n)
            assert self._veh_master is not None
            return os.read(self._veh_master, n)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:  # EIO: the vehicle has not opened its end yet
            return b""

    def _vehicle_write(self, data: bytes) -> int:
        try:
            if self._sock is not None:
                return self._sock.send(data)
            assert self._veh_master is not None
            return os.write(self._veh_master, data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError:
            return 0

    def _scramble(self, data: bytes) -> bytes:
        if self.speaks_at is None or self._tool_master is None or baud_of(self._tool_master) == self.speaks_at:
            return data
        self.stats["scrambled"] += len(data)
        return bytes((b * 7 + 0x35) & 0xFF for b in data)  # what a UART at the wrong rate makes of them

    def _count(self, data: bytes) -> float | None:
        """Count the tool's messages; the pull's length when this chunk holds the scripted n-th one."""
        for mid in self._parser(data):
            self._counts[mid] = self._counts.get(mid, 0) + 1
            if self._pull_at is not None and mid == self._pull_at[0] and self._counts[mid] == self._pull_at[1]:
                for_s = self._pull_at[2]
                self._pull_at = None
                return for_s
        return None

    def _step(self) -> None:
        with self._lock:
            if self._plug_due is not None and time.monotonic() >= self._plug_due:
                self.plug()
            rlist: list[Any] = []
            if (len(self._to_vehicle) < BUFFER_BYTES and self._tool_master is not None
                    and time.monotonic() >= self._tool_idle_until):
                rlist.append(self._tool_master)
            if len(self._to_tool) < BUFFER_BYTES:
                rlist.append(self._sock if self._sock is not None else self._veh_master)
        try:
            readable, _, _ = select.select(rlist, [], [], 0.005)
        except (OSError, ValueError):
            readable = []
        with self._lock:
            pull_for: float | None = None
            for r in readable:
                if r is self._tool_master and self._tool_master is not None:
                    try:
                        data = os.read(self._tool_master, BUFFER_BYTES - len(self._to_vehicle))
                    except (BlockingIOError, InterruptedError):
                        data = b""
                    except OSError:  # EIO: the tool has not opened its end (or closed it): look again soon
                        data = b""
                        self._tool_idle_until = time.monotonic() + 0.02
                    if data:
                        self._to_vehicle += data
                        pull_for = self._count(data) if pull_for is None else pull_for
                elif r is not self._tool_master:
                    data = self._vehicle_read(BUFFER_BYTES - len(self._to_tool))
                    if data and self._tool_master is None:
                        self.stats["dropped"] += len(data)  # the cable is out: nobody hears it
                    elif data:
                        self._to_tool += self._scramble(data)
            n = self._out_bucket.allow(len(self._to_vehicle))
            if n:
                sent = self._vehicle_write(bytes(self._to_vehicle[:n]))
                del self._to_vehicle[:sent]
                self.stats["to_vehicle"] += sent
            n = self._in_bucket.allow(len(self._to_tool))
            if n and self._tool_master is not None:
                try:
                    sent = os.write(self._tool_master, bytes(self._to_tool[:n]))
                except (BlockingIOError, InterruptedError):
                    sent = 0
                except OSError:
                    sent = n  # nobody on the tool's end: lost
                    self.stats["dropped"] += n
                del self._to_tool[:sent]
                self.stats["to_tool"] += sent
            if pull_for is not None:
                # the triggering message reaches the vehicle first
                while self._to_vehicle:
                    sent = self._vehicle_write(bytes(self._to_vehicle))
                    del self._to_vehicle[:sent]
                    if not sent:
                        break
                self.pull(pull_for)

    def _run(self) -> None:
        while self._running:
            self._step()
