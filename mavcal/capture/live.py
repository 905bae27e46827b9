"""Guided capture on a live vehicle: connect, stream, fit as the poses come, say the next pose.

:func:`capture_live` drives a :class:`mavcal.capture.CaptureSession` from a MAVLink device
(:class:`mavcal.link.live.LiveRecorder`): it fetches the vehicle's parameters (the
calibration in force on the readings), asks for the IMU streams, feeds every received batch
to the session and calls :meth:`~mavcal.capture.CaptureSession.update` about twice a second,
handing each :class:`~mavcal.capture.CaptureStatus` to a callback, until the session is done
(target reached, aborted, maximum poses), the caller asks to stop, or a time limit. At the
end the IMU messages get their default rates back.

It only captures: the caller gets the session back and decides what to do with
``session.result()`` (the ``capture`` command prints it, writes files and, when confirmed,
writes the parameters through the safe writer).

The library logs and never prints.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Callable

from mavcal.capture.session import CaptureConfig, CaptureSession, CaptureStatus
from mavcal.errors import InsufficientDataError
from mavcal.link.live import open_recorder
from mavcal.link.position import VehiclePosition
from mavcal.link.signing import SigningKey
from mavcal.link.streams import STREAM_MESSAGE_IDS, needed_stream_ids, reset_streams
from mavcal.pipeline import Options
from mavcal.sources.types import SensorSeries

__all__ = ["capture_live", "CaptureAbortedError", "LiveCaptureInfo"]

log = logging.getLogger(__name__)


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
    warnings: tuple[str, ...] = ()


class _CaptureLoop:
    """Feeds batches to a session and updates it every ``update_every_s`` until it is done."""

    def __init__(self, on_status: Callable[[CaptureStatus], None] | None, should_stop: Callable[[], bool] | None,
                 max_duration_s: float, update_every_s: float) -> None:
        self.on_status = on_status
        self.should_stop = should_stop
        self.max_duration_s = max_duration_s
        self.update_every_s = update_every_s
        self.t_start = time.monotonic()
        self.updates = 0

    def _update(self, session: CaptureSession) -> CaptureStatus:
        st = session.update()
        self.updates += 1
        if self.on_status is not None:
            self.on_status(st)
        return st

    def _stop_requested(self, session: CaptureSession, now: float) -> bool:
        """Stop the session when the caller asks or the time is up; True if it was stopped."""
        if self.should_stop is not None and self.should_stop():
            session.stop("stopped by the user")
            return True
        if now - self.t_start >= self.max_duration_s:
            session.stop(f"time limit of {self.max_duration_s:g} s reached")
            return True
        return False

    def run(self, session: CaptureSession, batches: Iterable[Sequence[SensorSeries]],
            position: Callable[[], VehiclePosition | None] = lambda: None) -> None:
        """Until the session is done; a KeyboardInterrupt stops it as the user would."""
        self.t_start = time.monotonic()
        last_update = float("-inf")
        stopping = False
        try:
            for batch in batches:
                session.add(batch)
                if session.position is None and (pos := position()) is not None:  # a GPS fix came later
                    session.position, session.position_source = pos.location, pos.source
                now = time.monotonic()
                if not stopping:
                    stopping = self._stop_requested(session, now)
                if stopping or now - last_update >= self.update_every_s:
                    last_update = now
                    if self._update(session).done:
                        break
        except KeyboardInterrupt:
            log.info("capture interrupted by the user")
            session.stop("stopped by the user")
            self._update(session)


class _WatchedLoop(_CaptureLoop):
    """As :class:`_CaptureLoop`, with every batch handed to ``on_batch`` as it arrives, also while
    the session updates (a refit takes up to seconds): the update runs on a helper thread, the
    batches received meanwhile are added when it is over, and ``on_status`` is called from the
    capture's thread."""

    def __init__(self, on_batch: Callable[[CaptureSession, Sequence[SensorSeries]], None], *args: Any) -> None:
        super().__init__(*args)
        self.on_batch = on_batch

    def run(self, session: CaptureSession, batches: Iterable[Sequence[SensorSeries]],
            position: Callable[[], Any] | None = None) -> None:
        """Until the session is done; a KeyboardInterrupt stops it as the user would.
        ``position``: a vehicle position that may come after the start (``.location``,
        ``.source``), given to the session when it has none."""
        self.t_start = time.monotonic()
        last_update = float("-inf")
        stopping = False
        pending: list[Sequence[SensorSeries]] = []
        updater = _Updater(session)
        try:
            for batch in batches:
                self.on_batch(session, batch)
                pending.append(batch)
                if updater.busy():
                    continue
                st = updater.take()  # the finished update's status (its exception raised here)
                if st is not None and self._report(st).done:
                    return
                for b in pending:
                    session.add(b)
                pending.clear()
                if position is not None and session.position is None and (pos := position()) is not None:
                    session.position, session.position_source = pos.location, pos.source  # a GPS fix came later
                now = time.monotonic()
                if not stopping:
                    stopping = self._stop_requested(session, now)
                if stopping or now - last_update >= self.update_every_s:
                    last_update = now
                    updater.start()
        except KeyboardInterrupt:
            log.info("capture interrupted by the user")
            updater.join()
            session.stop("stopped by the user")
            self._update(session)
        finally:
            updater.join()

    def _report(self, st: CaptureStatus) -> CaptureStatus:
        self.updates += 1
        if self.on_status is not None:
            self.on_status(st)
        return st


class _Updater:
    """One ``session.update()`` at a time on a helper thread (named ``mavcal-capture-update``)."""

    def __init__(self, session: CaptureSession) -> None:
        self.session = session
        self._thread: threading.Thread | None = None
        self._result: CaptureStatus | None = None
        self._error: BaseException | None = None

    def _work(self) -> None:
        try:
            self._result = self.session.update()
        except BaseException as exc:  # handed to the capture's thread by take()
            self._error = exc

    def start(self) -> None:
        self._result, self._error = None, None
        self._thread = threading.Thread(target=self._work, name="mavcal-capture-update", daemon=True)
        self._thread.start()

    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def take(self) -> CaptureStatus | None:
        """The status of the update that finished since the last take (None if none)."""
        if self._thread is None:
            return None
        self._thread.join()
        self._thread = None
        if self._error is not None:
            raise self._error
        return self._result

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()


def capture_live(device: str, *, config: CaptureConfig | None = None, options: Options | None = None,
                 on_status: Callable[[CaptureStatus], None] | None = None,
                 on_batch: Callable[[CaptureSession, Sequence[SensorSeries]], None] | None = None, baud: int = 115200,
                 rate_hz: float = 25.0, should_stop: Callable[[], bool] | None = None,
                 max_duration_s: float = 600.0, update_every_s: float = 0.5, batch_s: float = 0.1,
                 heartbeat_timeout_s: float = 5.0, param_timeout_s: float = 30.0,
                 on_info: Callable[[LiveCaptureInfo], None] | None = None, budget_s: float = 15.0,
                 signing_key: SigningKey | None = None, tlog: str | os.PathLike[str] | None = None) -> CaptureSession:
    """Run a guided capture on a live vehicle and return the session.

    Parameters
    ----------
    device : str
        pymavlink device string (``udpin:HOST:PORT``, ``tcp:HOST:PORT``, a serial port...).
    config : CaptureConfig, optional
        Target, interval limits, still-interval thresholds (default ``CaptureConfig()``).
    options : pipeline.Options, optional
        Instances, field magnitude, location... (the session replaces ``still``).
    on_status : callable, optional
        Called with every :class:`CaptureStatus` (about every ``update_every_s``), from the
        calling thread. Exceptions propagate.
    on_batch : callable, optional
        ``on_batch(session, batch)`` with every received batch as it arrives (about every
        ``batch_s``), from the calling thread, also while the session refits (the updates then
        run on a helper thread; ``on_status`` is still called from the calling thread): e.g.
        the live page's attitude. Exceptions propagate.
    baud, rate_hz, batch_s : int, float, float
        Serial baud rate; IMU stream rate to ask for (at least 25 Hz); receive batch length.
    should_stop : callable, optional
        Polled after every batch; True stops the capture ("stopped by the user").
    max_duration_s, update_every_s : float
        The capture stops after this long ("time limit ... reached"); seconds between
        ``session.update()`` calls (not on every batch: a fit costs up to a few hundred ms).
    heartbeat_timeout_s, param_timeout_s, budget_s : float
        Bounds on waiting for the vehicle's heartbeat and for its parameter table; how long
        the start (heartbeat once the device is heard, stream requests) retries on a lossy link.
    signing_key, tlog : SigningKey, path, optional
        Sign the link (:mod:`mavcal.link.signing`); save all it receives in this telemetry log.
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
    SigningError
        The vehicle requires MAVLink 2 signing and ``signing_key`` is missing or wrong (exit 8).
    LinkError
        The device cannot be opened, sends no heartbeat, no parameters or no IMU data
        (exit code 3).
    """
    rec = open_recorder(device, baud=baud, heartbeat_timeout_s=heartbeat_timeout_s, budget_s=budget_s,
                        signing_key=signing_key, tlog=tlog)
    loop = _CaptureLoop(on_status, should_stop, max_duration_s, update_every_s)
    if on_batch is not None:  # the live page: batches handed over as they come, refits on a helper thread
        loop = _WatchedLoop(on_batch, on_status, should_stop, max_duration_s, update_every_s)
    method = "?"
    streams = STREAM_MESSAGE_IDS
    try:
        params = rec.fetch_params(timeout_s=param_timeout_s)
        position = rec.read_position()  # the World Magnetic Model's field strength, unless --location/--field-mgauss
        session = CaptureSession(params, config or CaptureConfig(), options, source=device,
                                 position=position.location if position is not None else None)
        session.position_source = position.source if position is not None else ""
        streams = needed_stream_ids(params)  # only the IMU messages this vehicle has
        method = rec.start_streams(rate_hz, message_ids=streams)
        log.info("capturing from %s (%s streams at %g Hz)", device, method, rate_hz)
        loop.run(session, rec.iter_batches(None, batch_s), position=rec.current_position)
        return session
    finally:
        reset_streams(rec.link, streams)
        if on_info is not None:
            on_info(LiveCaptureInfo(device, method, time.monotonic() - loop.t_start, loop.updates,
                                    tuple(rec.warnings)))
        rec.close()
