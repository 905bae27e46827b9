"""A :class:`~mavcal.link.connection.Link` fed by someone else's read loop (MAVProxy).

For a program that does not own the read loop of its link: the owner hands every received
message of interest to :meth:`FedConnection.feed` (any thread) and sends what was queued with
:func:`flush_outbox` on its own thread; wrapped in a :class:`~mavcal.link.connection.Link`, a
:class:`FedConnection` runs the parameter protocol and the safe writer unchanged in another
thread (``Link`` reads with :meth:`FedConnection.recv_match`).
"""
from __future__ import annotations

import queue
import threading
from typing import Any, Callable

__all__ = ["FedConnection", "QueuedSender", "flush_outbox"]


class QueuedSender:
    """Stands in for a pymavlink ``MAVLink`` encoder: every ``*_send`` call goes to an outbox.

    The outbox's owner sends them with :func:`flush_outbox` on its own thread.
    """

    def __init__(self, outbox: queue.Queue[tuple[str, tuple, dict]], src_system: int | None = None) -> None:
        self._outbox = outbox
        #: the system id the owner's encoder sends as (MAVProxy's ``source_system``); None: not known
        self.srcSystem = src_system

    def __getattr__(self, name: str) -> Callable[..., None]:
        if not name.endswith("_send"):
            raise AttributeError(name)

        def send(*args: Any, **kwargs: Any) -> None:
            self._outbox.put((name, args, kwargs))

        return send


def flush_outbox(outbox: queue.Queue[tuple[str, tuple, dict]], mav: Any, max_messages: int = 200) -> int:
    """Send up to ``max_messages`` queued ``(method, args, kwargs)`` calls with the encoder ``mav``."""
    n = 0
    while n < max_messages:
        try:
            name, args, kwargs = outbox.get_nowait()
        except queue.Empty:
            break
        getattr(mav, name)(*args, **kwargs)
        n += 1
    return n


class FedConnection:
    """A pymavlink connection stand-in whose messages are fed in and whose sends are queued.

    For a program that does not own the read loop of its link (MAVProxy): the owner calls
    :meth:`feed` with every received message of interest (any thread) and
    :meth:`flush_outbox` with the real encoder on its own thread; wrapped in a
    :class:`mavcal.link.connection.Link`, this runs the parameter protocol and the safe
    writer unchanged in another thread (``Link`` reads with :meth:`recv_match`).

    Parameters
    ----------
    target_system, target_component : int
        The vehicle's ids.
    address : str
        Shown in messages.
    max_queued : int
        Received messages kept while nobody reads; the oldest are dropped beyond this.
    outbox : queue.Queue, optional
        Where sends are queued (several connections may share the owner's one outbox);
        default a new queue.
    source_system : int, optional
        The system id the owner sends as (replies addressed to another system are not ours);
        None: not known, every reply is taken as ours.
    """

    def __init__(self, target_system: int, target_component: int, *, address: str = "fed",
                 max_queued: int = 20000, outbox: queue.Queue[tuple[str, tuple, dict]] | None = None,
                 source_system: int | None = None) -> None:
        self.target_system = int(target_system)
        self.target_component = int(target_component)
        self.address = address
        self._in: queue.Queue[Any] = queue.Queue(maxsize=max_queued)
        self._outbox: queue.Queue[tuple[str, tuple, dict]] = outbox if outbox is not None else queue.Queue()
        self.mav = QueuedSender(self._outbox, source_system)
        self._closed = threading.Event()
        self.dropped = 0

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def feed(self, m: Any) -> None:
        """Hand over one received message (thread-safe, never blocks)."""
        if self._closed.is_set():
            return
        while True:
            try:
                self._in.put_nowait(m)
                return
            except queue.Full:
                try:
                    self._in.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def recv_match(self, blocking: bool = False, timeout: float | None = None, **_: Any) -> Any:
        """The next fed message, or None (pymavlink's signature; no ``type`` filtering).

        Raises OSError once closed (a :class:`Link` turns it into a LinkError).
        """
        if self._closed.is_set():
            raise OSError("connection closed")
        try:
            if not blocking:
                return self._in.get_nowait()
            return self._in.get(timeout=max(timeout or 0.0, 0.0) if timeout is not None else None)
        except queue.Empty:
            return None

    def flush_outbox(self, mav: Any, max_messages: int = 200) -> int:
        """Send the queued messages with the real encoder ``mav``; returns how many went."""
        return flush_outbox(self._outbox, mav, max_messages)

    def close(self) -> None:
        """Stop accepting messages; a reader waiting in :meth:`recv_match` gets OSError next."""
        self._closed.set()
