"""A lossy UDP relay on loopback: drops and duplicates datagrams each way, seeded.

It sits between a vehicle that sends to a UDP port (ArduPilot SITL's ``--serialN
udpclient:127.0.0.1:PORT``, :class:`mavcal.testing.vehicle.TestVehicle` with ``"udpout"``)
and a ground station that listens (``udpin:127.0.0.1:TOOL_PORT``)::

    vehicle --> 127.0.0.1:vehicle_port [relay] --> 127.0.0.1:tool_port  (the tool's udpin)
    vehicle <-- (learned address)      [relay] <-- the tool's replies

The vehicle side learns the vehicle's address from its first datagram; the tool side sends
from its own socket, so the tool answers the relay. Each datagram is dropped with probability
``loss`` and sent twice with probability ``dup`` (per direction), decided by a
``random.Random(seed)``; :attr:`LossRelay.stats` counts them. A blackout drops everything
both ways for a while: now (:meth:`LossRelay.blackout`) or scripted to start when the tool
sends its n-th message of a MAVLink id (:meth:`LossRelay.blackout_at`: "in the middle of a
write", the n-th PARAM_SET; that datagram itself is not blacked out). One thread, loopback only, stopped by
:meth:`LossRelay.stop` (or the context manager).
"""
from __future__ import annotations

import math
import random
import select
import socket
import threading
import time
from typing import Any

__all__ = ["LossRelay"]

_HOST = "127.0.0.1"


class LossRelay:
    """A UDP relay that drops ``loss`` and duplicates ``dup`` of the datagrams each way.

    Parameters
    ----------
    tool_port : int
        Where the tool listens (its ``udpin:127.0.0.1:tool_port``).
    loss, dup : float
        Probabilities per datagram, each direction (``loss_in``/``loss_out`` override per
        direction: ``in`` = tool to vehicle, ``out`` = vehicle to tool).
    seed : int
        Seeds the drop/duplicate decisions.
    vehicle_port : int
        The port the vehicle sends to; 0 picks a free one (read :attr:`vehicle_port`).
    """

    def __init__(self, tool_port: int, *, loss: float = 0.3, dup: float = 0.05, seed: int = 0,
                 vehicle_port: int = 0, loss_in: float | None = None, loss_out: float | None = None) -> None:
        for p in (loss, dup, loss_in, loss_out):
            if p is not None and not 0.0 <= p <= 1.0:
                raise ValueError("probabilities must be within [0, 1]")
        self.tool_addr = (_HOST, int(tool_port))
        self.loss_in = loss if loss_in is None else loss_in
        self.loss_out = loss if loss_out is None else loss_out
        self.dup = dup
        self._rng = random.Random(seed)
        self._vehicle_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._vehicle_sock.bind((_HOST, vehicle_port))
        self._tool_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._tool_sock.bind((_HOST, 0))
        for s in (self._vehicle_sock, self._tool_sock):
            s.setblocking(False)
        self.vehicle_port: int = self._vehicle_sock.getsockname()[1]
        self._vehicle_addr: Any = None
        self.stats = {"out": 0, "in": 0, "dropped_out": 0, "dropped_in": 0, "dup_out": 0, "dup_in": 0,
                      "blacked_out": 0}
        self._blackout_until = float("-inf")
        self._script: tuple[int, int, float] | None = None  # (msgid, datagrams still to pass, seconds)
        #: time.monotonic() at which each blackout started
        self.blackouts: list[float] = []
        self._running = False
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ lifetime
    def start(self) -> LossRelay:
        """Start relaying (idempotent). Returns self."""
        if not self._running:
            self._running = True
            self._thread = threading.Thread(target=self._run, name=f"LossRelay:{self.vehicle_port}", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close both sockets (idempotent)."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for s in (self._vehicle_sock, self._tool_sock):
            try:
                s.close()
            except OSError:
                pass

    def __enter__(self) -> LossRelay:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def tool_device(self) -> str:
        """The device string the tool opens: ``udpin:127.0.0.1:TOOL_PORT``."""
        return f"udpin:{self.tool_addr[0]}:{self.tool_addr[1]}"

    @property
    def tool_side_addr(self) -> tuple[str, int]:
        """The relay's own address on the tool side: where the tool's replies go."""
        return (_HOST, int(self._tool_sock.getsockname()[1]))

    def set_loss(self, loss: float | None = None, dup: float | None = None) -> None:
        """Change the loss (both ways) and/or duplication at run time."""
        with self._lock:
            if loss is not None:
                self.loss_in = self.loss_out = float(loss)
            if dup is not None:
                self.dup = float(dup)

    def blackout(self, seconds: float) -> None:
        """Drop every datagram both ways for ``seconds`` from now (``math.inf``: for good)."""
        with self._lock:
            self._start_blackout(seconds)

    def blackout_at(self, msgid: int, nth: int, seconds: float) -> None:
        """Black out for ``seconds`` once the tool has sent its ``nth`` message of MAVLink id
        ``msgid`` from now on (that datagram itself is not blacked out)."""
        with self._lock:
            self._script = (int(msgid), max(1, int(nth)), float(seconds))

    def _start_blackout(self, seconds: float) -> None:
        now = time.monotonic()
        self._blackout_until = math.inf if math.isinf(seconds) else now + float(seconds)
        self.blackouts.append(now)

    def _scripted(self, data: bytes) -> None:
        """Count ``data`` (from the tool) against the blackout script; start it at the n-th."""
        if self._script is None or _msgid(data) != self._script[0]:
            return
        msgid, left, seconds = self._script
        if left > 1:
            self._script = (msgid, left - 1, seconds)
        else:
            self._script = None
            self._start_blackout(seconds)

    # ------------------------------------------------------------------ the loop
    def _copies(self, direction: str, data: bytes = b"") -> int:
        with self._lock:
            loss = self.loss_out if direction == "out" else self.loss_in
            self.stats[direction] += 1
            if time.monotonic() < self._blackout_until:
                self.stats["blacked_out"] += 1
                return 0
            if direction == "in":
                self._scripted(data)
            if loss and self._rng.random() < loss:
                self.stats["dropped_" + direction] += 1
                return 0
            if self.dup and self._rng.random() < self.dup:
                self.stats["dup_" + direction] += 1
                return 2
            return 1

    def _forward(self, src: socket.socket) -> None:
        for _ in range(256):
            try:
                data, addr = src.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable from a peer not listening (yet)
                return
            if src is self._vehicle_sock:
                self._vehicle_addr = addr
                dest, out, direction = self.tool_addr, self._tool_sock, "out"
            else:
                if self._vehicle_addr is None:
                    continue  # the vehicle has not spoken yet: nowhere to send
                dest, out, direction = self._vehicle_addr, self._vehicle_sock, "in"
            for _ in range(self._copies(direction, data)):
                try:
                    out.sendto(data, dest)
                except OSError:  # a full buffer or nobody listening: lost, like a radio
                    pass

    def _run(self) -> None:
        socks = [self._vehicle_sock, self._tool_sock]
        while self._running:
            try:
                readable, _, _ = select.select(socks, [], [], 0.05)
            except (OSError, ValueError):
                return
            for s in readable:
                self._forward(s)


def _msgid(data: bytes) -> int | None:
    """The MAVLink message id of the first frame of a datagram (None: not MAVLink)."""
    if len(data) >= 10 and data[0] == 0xFD:
        return data[7] | data[8] << 8 | data[9] << 16
    if len(data) >= 6 and data[0] == 0xFE:
        return data[5]
    return None
