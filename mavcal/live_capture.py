"""Guided capture on a live vehicle: connect, stream, fit as the poses come, say the next pose.

:func:`capture_live` drives a :class:`mavcal.capture.CaptureSession` from a MAVLink device
(:class:`mavcal.sources.live.LiveSource`): it fetches the vehicle's parameters (the
calibration in force on the readings), asks for the IMU streams, feeds every received batch
to the session and calls :meth:`~mavcal.capture.CaptureSession.update` about twice a second,
handing each :class:`~mavcal.capture.CaptureStatus` to a callback, until the session is done
(target reached, aborted, maximum poses), the caller asks to stop, or a time limit.

It only captures: the caller gets the session back and decides what to do with
``session.result()`` (the ``capture`` command prints it, writes files and, when confirmed,
writes the parameters through the safe writer).

Also here, for the MAVProxy module (where MAVProxy owns the read loop):

* :class:`FedConnection`, a stand-in for a pymavlink connection that is *fed* received
  messages by their owner and queues what is sent for the owner's thread, so a
  :class:`mavcal.link.connection.Link` - and with it the safe parameter writer - runs on a
  link it does not read itself;
* :func:`status_line` and :func:`status_screen`, the text of a status (one line / one
  terminal screen), shared by the command and the module.

The library logs and never prints.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional, Tuple

from mavcal.capture import CaptureConfig, CaptureSession, CaptureStatus, coverage_map
from mavcal.errors import InsufficientDataError
from mavcal.pipeline import Options

__all__ = ["capture_live", "CaptureAbortedError", "FedConnection", "QueuedSender", "flush_outbox", "status_line",
           "status_screen", "STREAM_MESSAGE_IDS", "LiveCaptureInfo", "stream_interval_commands"]

log = logging.getLogger(__name__)

#: the IMU messages a capture streams: RAW_IMU, SCALED_IMU2, SCALED_IMU3
STREAM_MESSAGE_IDS: Tuple[int, ...] = (27, 116, 129)
_MAV_CMD_SET_MESSAGE_INTERVAL = 511


class CaptureAbortedError(InsufficientDataError):
    """The capture gave up on the data (impossible field, magnetic disturbance); exit code 4."""


@dataclass(frozen=True)
class LiveCaptureInfo:
    """How a live capture went (handed to ``capture_live``'s ``on_info`` callback).

    Attributes
    ----------
    device : str
    stream_method : str
        ``"interval"`` (SET_MESSAGE_INTERVAL) or ``"data_stream"`` (REQUEST_DATA_STREAM).
    elapsed_s : float
        Wall time from the first batch to the end.
    updates : int
        ``session.update()`` calls.
    warnings : tuple of str
        From the source (e.g. an incomplete parameter download).
    """

    device: str
    stream_method: str
    elapsed_s: float
    updates: int
    warnings: Tuple[str, ...] = ()


def capture_live(device: str, *, config: CaptureConfig = CaptureConfig(), options: Optional[Options] = None,
                 on_status: Optional[Callable[[CaptureStatus], None]] = None, baud: int = 115200,
                 rate_hz: float = 25.0, should_stop: Optional[Callable[[], bool]] = None,
                 max_duration_s: float = 600.0, update_every_s: float = 0.5, batch_s: float = 0.1,
                 heartbeat_timeout_s: float = 5.0, param_timeout_s: float = 30.0,
                 on_info: Optional[Callable[[LiveCaptureInfo], None]] = None) -> CaptureSession:
    """Run a guided capture on a live vehicle and return the session.

    Parameters
    ----------
    device : str
        pymavlink device string (``udpin:HOST:PORT``, ``tcp:HOST:PORT``, a serial port...).
    config : CaptureConfig
        Target, interval limits, still-interval thresholds.
    options : pipeline.Options, optional
        Instances, field magnitude, location... (the session replaces ``still``).
    on_status : callable, optional
        Called with every :class:`CaptureStatus` (about every ``update_every_s``), from the
        calling thread. Exceptions propagate.
    baud : int
        Serial baud rate.
    rate_hz : float
        IMU stream rate to ask for (at least 25 Hz).
    should_stop : callable, optional
        Polled after every batch; True stops the capture ("stopped by the user").
    max_duration_s : float
        The capture stops after this long ("time limit ... reached").
    update_every_s : float
        Seconds between ``session.update()`` calls (not on every batch: a fit costs up to a
        few hundred ms).
    batch_s : float
        Receive batch length.
    heartbeat_timeout_s, param_timeout_s : float
        Bounds on waiting for the vehicle's heartbeat and for its parameter table.
    on_info : callable, optional
        Called once at the end with a :class:`LiveCaptureInfo`.

    Returns
    -------
    CaptureSession
        Done (``session.status.done``): target reached, aborted, stopped or out of time.
        A KeyboardInterrupt during the capture stops it the same way ("stopped by the user")
        and the session is returned, so what was captured can still be used.

    Raises
    ------
    LinkError
        The device cannot be opened, sends no heartbeat, no parameters or no IMU data
        (exit code 3).
    """
    from mavcal.sources.live import LiveSource

    src = LiveSource(device, baud=baud, heartbeat_timeout_s=heartbeat_timeout_s)
    t_start = time.monotonic()
    updates = 0
    method = "?"
    try:
        params = src.fetch_params(timeout_s=param_timeout_s)
        session = CaptureSession(params, config, options, source=device)
        method = src.start_streams(rate_hz)
        log.info("capturing from %s (%s streams at %g Hz)", device, method, rate_hz)
        t_start = time.monotonic()
        last_update = float("-inf")
        stopping = False
        try:
            for batch in src.iter_batches(None, batch_s):
                session.add(batch)
                now = time.monotonic()
                if not stopping:
                    if should_stop is not None and should_stop():
                        session.stop("stopped by the user")
                        stopping = True
                    elif now - t_start >= max_duration_s:
                        session.stop(f"time limit of {max_duration_s:g} s reached")
                        stopping = True
                if stopping or now - last_update >= update_every_s:
                    last_update = now
                    st = session.update()
                    updates += 1
                    if on_status is not None:
                        on_status(st)
                    if st.done:
                        break
        except KeyboardInterrupt:
            log.info("capture interrupted by the user")
            session.stop("stopped by the user")
            st = session.update()
            updates += 1
            if on_status is not None:
                on_status(st)
        return session
    finally:
        _default_rates(src.connection, src.target_system, src.target_component)
        if on_info is not None:
            on_info(LiveCaptureInfo(device, method, time.monotonic() - t_start, updates, tuple(src.warnings)))
        src.close()


def stream_interval_commands(mav: Any, target_system: int, target_component: int,
                             rate_hz: Optional[float]) -> None:
    """Ask for the capture's IMU messages at ``rate_hz`` (SET_MESSAGE_INTERVAL), or None: default rates."""
    interval_us = 0 if rate_hz is None else int(round(1e6 / max(float(rate_hz), 1.0)))
    for mid in STREAM_MESSAGE_IDS:
        mav.command_long_send(target_system, target_component, _MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                              mid, interval_us, 0, 0, 0, 0, 0)


def _default_rates(conn: Any, target_system: Optional[int], target_component: Optional[int]) -> None:
    """Give the IMU messages back their default rates (best effort; the link may be dead)."""
    if target_system is None:
        return
    try:
        stream_interval_commands(conn.mav, target_system, target_component or 0, None)
    except Exception as exc:  # a dead socket: nothing to restore
        log.debug("could not reset the stream rates: %s", exc)


# ----------------------------------------------------------------------------------------------
# status text
# ----------------------------------------------------------------------------------------------
def _fmt(x: Optional[float], nd: int = 2) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def status_line(st: CaptureStatus) -> str:
    """One line for a log or a piped terminal: intervals, bound, and the next pose in words.

    The next pose also comes as angles, ``(roll R pitch P yaw Y deg magnetic)``, so a
    program can follow it.
    """
    head = f"{st.n_intervals} intervals, {'still' if st.still_now else 'moving'}, heading {_fmt(st.heading_95_deg)} deg"
    if st.done:
        return f"{head}: {'ABORTED: ' if st.aborted else 'done: '}{st.reason}"
    if st.next_pose is None:
        return f"{head}: {st.reason}"
    a = st.next_pose
    return (f"{head}; next: {a.words} (roll {a.roll_deg:.0f} pitch {a.pitch_deg:.0f} yaw {a.yaw_deg:.0f} "
            f"deg magnetic)")


def status_screen(st: CaptureStatus, target_deg: Optional[float] = None) -> str:
    """A terminal screen of the capture state: still now?, intervals, coverage, bound, next pose."""
    lines = ["mavcal guided capture (Ctrl-C stops and keeps what was captured)", ""]
    lines.append(f"still now: {'yes' if st.still_now else 'no'}        intervals kept: {st.n_intervals}")
    tgt = f" (target {target_deg:g})" if target_deg is not None else ""
    lines.append(f"heading error bound 95 %: {_fmt(st.heading_95_deg)} deg{tgt}    tilt: {_fmt(st.tilt_95_deg, 3)} deg"
                 f"    model: {st.model or '-'}")
    if st.field_mgauss is not None:
        lines.append(f"field: {st.field_mgauss:.0f} mGauss")
    lines += ["", "gravity directions covered (body frame; columns: azimuth, rows: elevation):",
              coverage_map(st.gravity_dirs), ""]
    if st.done:
        lines.append(("ABORTED: " if st.aborted else "DONE: ") + st.reason)
    elif st.next_pose is not None:
        a = st.next_pose
        lines.append(f"NEXT POSE: {a.words}")
        lines.append(f"           (roll {a.roll_deg:.0f}, pitch {a.pitch_deg:.0f}, yaw {a.yaw_deg:.0f} deg "
                     f"from magnetic north)")
        lines.append(st.reason)
    lines += [f"note: {m}" for m in st.messages]
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# a connection fed by someone else's read loop
# ----------------------------------------------------------------------------------------------
class QueuedSender:
    """Stands in for a pymavlink ``MAVLink`` encoder: every ``*_send`` call goes to an outbox.

    The outbox's owner sends them with :func:`flush_outbox` on its own thread.
    """

    def __init__(self, outbox: "queue.Queue[Tuple[str, tuple, dict]]") -> None:
        self._outbox = outbox

    def __getattr__(self, name: str) -> Callable[..., None]:
        if not name.endswith("_send"):
            raise AttributeError(name)

        def send(*args: Any, **kwargs: Any) -> None:
            self._outbox.put((name, args, kwargs))

        return send


def flush_outbox(outbox: "queue.Queue[Tuple[str, tuple, dict]]", mav: Any, max_messages: int = 200) -> int:
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
    """

    def __init__(self, target_system: int, target_component: int, *, address: str = "fed",
                 max_queued: int = 20000, outbox: "Optional[queue.Queue[Tuple[str, tuple, dict]]]" = None) -> None:
        self.target_system = int(target_system)
        self.target_component = int(target_component)
        self.address = address
        self._in: "queue.Queue[Any]" = queue.Queue(maxsize=max_queued)
        self._outbox: "queue.Queue[Tuple[str, tuple, dict]]" = outbox if outbox is not None else queue.Queue()
        self.mav = QueuedSender(self._outbox)
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

    def recv_match(self, blocking: bool = False, timeout: Optional[float] = None, **_: Any) -> Any:
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
