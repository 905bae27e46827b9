"""Record IMU data from a live vehicle over a :class:`~mavcal.link.connection.Link` into an ImuLog.

Built on the link's one receive loop (:class:`~mavcal.link.connection.Link`), the one
parameter download (:func:`mavcal.link.params.download_params`), the one stream request
(:func:`mavcal.link.streams.start_streams`) and the assembly shared with the log files
(:func:`mavcal.sources.assemble.assemble_tlog`). Typical use::

    with open_recorder("udpin:0.0.0.0:14550") as rec:     # LinkError if no heartbeat
        params = rec.fetch_params()                        # dict name -> value
        rec.read_position()                                # GPS/home for the WMM, or None
        rec.start_streams(rate_hz=50)                      # SET_MESSAGE_INTERVAL or fallback
        for batch in rec.iter_batches(duration_s=30):      # tuples of SensorSeries
            ...
        imu_log = rec.snapshot()                           # everything so far as an ImuLog

or, in one call, :func:`record_device`.

Time: ``time_s`` of the batches is the vehicle boot time of each message; ``snapshot()``
uses the same time base rules as tlogs (see :mod:`mavcal.sources.assemble`), with the host
receive time (unix s) as ``log_time_s``.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from mavcal.errors import LinkError
from mavcal.link.connection import Link, open_link
from mavcal.link.params import download_params
from mavcal.link.position import POSITION_MESSAGES, PositionWatch, VehiclePosition, read_position, request_position
from mavcal.link.signing import SigningKey
from mavcal.link.streams import STREAM_MESSAGE_IDS, needed_stream_ids, send_message_intervals, start_streams
from mavcal.sources.assemble import IMU_MESSAGES, SCALED_INSTANCE, TLOG_MESSAGES, assemble_tlog, imu_series
from mavcal.sources.types import ImuLog, SensorSeries

__all__ = ["LiveRecorder", "open_recorder", "record_device", "imu_batch_from_messages", "RecordingProgress",
           "PROGRESS_PERIOD_S"]

log = logging.getLogger(__name__)

#: the order of a batch's series: instance 0 from RAW_IMU (SCALED_IMU last: the same data)
#: REQUEST_DATA_STREAM's stream of the IMU messages (the fallback of :func:`start_streams`)
_RAW_SENSORS = 1  # MAV_DATA_STREAM_RAW_SENSORS
_BATCH_ORDER = ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "SCALED_IMU")
#: a GCS HEARTBEAT this often while recording, as a ground station does
GCS_HEARTBEAT_PERIOD_S = 1.0

#: how often a recording reports its progress
PROGRESS_PERIOD_S = 0.5
#: while the vehicle's position is unknown (no GPS fix yet at boot), ask for it this often
POSITION_ASK_PERIOD_S = 5.0
#: no IMU sample for this long while the vehicle is heard: the streams are asked for again (a vehicle
#: that a replugged USB cable rebooted has forgotten them)
STREAM_REASK_S = 3.0
#: the first accelerometer's rate received over the first :data:`RATE_CHECK_S` of streaming below
#: this fraction of the rate asked: the link is too slow for it (a warning; the capture goes on)
SLOW_LINK_FRACTION = 0.7
RATE_CHECK_S = 5.0

Batch = tuple[SensorSeries, ...]


@dataclass(frozen=True)
class RecordingProgress:
    """How far a recording is (handed to ``on_progress`` of :func:`record_device`)."""

    elapsed_s: float
    duration_s: float
    samples: int  # accelerometer samples received so far (every IMU instance)

    @property
    def remaining_s(self) -> float:
        return max(0.0, self.duration_s - self.elapsed_s)

    @property
    def done(self) -> bool:
        return self.elapsed_s >= self.duration_s


class LiveRecorder:
    """Keeps every message of interest a :class:`Link` receives, as rows, while registered on it.

    Parameters
    ----------
    link : Link
        An open link to the vehicle (its target ids known, e.g. from :func:`open_link`). The
        recorder registers a handler on it and sends a GCS heartbeat every second while the
        link is pumped.
    owns_link : bool
        Close the link with the recorder.
    """

    def __init__(self, link: Link, *, owns_link: bool = False) -> None:
        self.link = link
        self.device = link.device
        self.owns_link = owns_link
        self.warnings: list[str] = []
        self.params: dict[str, float] = {}
        #: the vehicle's position (:meth:`read_position`), for the World Magnetic Model
        self.position: VehiclePosition | None = None
        #: seconds each start-up request (stream rates) keeps being retried on a lossy link
        self.budget_s = 0.0
        self._rows: dict[str, list[tuple]] = {n: [] for n in TLOG_MESSAGES}
        self._fields: dict[str, Sequence[str]] = {}
        self._batch_mark: dict[str, int] = {n: 0 for n in IMU_MESSAGES}
        self._index = 0
        self._token = link.add_handler("*", self._record)
        self._positions = PositionWatch((link.target_system, link.target_component))
        self._position_tokens = [link.add_handler(k, self._positions.feed) for k in POSITION_MESSAGES]
        self._position_asked: float | None = None  # None: not asked for (read_position not called)
        #: the streams asked for (:meth:`start_streams`): (rate, message ids, method), and their watch
        self._streams: tuple[float, tuple[int, ...], str] | None = None
        self._streams_t0 = self._last_imu = self._last_ask = 0.0
        self._imu_samples = 0
        self._rate_checked = False
        #: the first accelerometer's rate received over the first RATE_CHECK_S of streaming (Hz)
        self.imu_rate_hz: float | None = None
        link.heartbeat_period_s = GCS_HEARTBEAT_PERIOD_S

    @property
    def target_system(self) -> int:
        return self.link.target_system

    @property
    def target_component(self) -> int:
        return self.link.target_component

    def _record(self, m: Any) -> None:
        self._index += 1
        typ = m.get_type()
        if typ in self._rows:
            if typ not in self._fields:
                self._fields[typ] = m.get_fieldnames()
            self._rows[typ].append((self._index, time.time(), m.get_srcSystem(), m.get_srcComponent(),
                                    tuple(getattr(m, f) for f in self._fields[typ])))

    def pump(self, timeout_s: float = 0.05) -> int:
        """Receive (and record) for ``timeout_s``; returns how many messages arrived."""
        return self.link.pump(timeout_s)

    # ------------------------------------------------------------------ parameters, streams
    def fetch_params(self, timeout_s: float = 30.0, retry_s: float = 0.5) -> dict[str, float]:
        """Fetch all parameters (:func:`~mavcal.link.params.download_params`); dict name -> value.

        Incomplete after ``timeout_s``: a warning (in :attr:`warnings` and the snapshot);
        nothing at all: :class:`LinkError`.
        """
        dl = download_params(self.link, timeout_s, retry_s=retry_s)
        if not dl.table:
            raise LinkError(f"no parameters received from {self.device} within {timeout_s:g} s")
        if not dl.complete:
            w = f"only {len(dl.table)} of {dl.count} parameters received within {timeout_s:g} s"
            log.warning(w)
            self.warnings.append(w)
        self.params = {name: value for name, (value, _) in dl.table.items()}
        return dict(self.params)

    def start_streams(self, rate_hz: float = 50.0, ack_timeout_s: float = 1.0, data_timeout_s: float = 2.0,
                      message_ids: Sequence[int] = STREAM_MESSAGE_IDS) -> str:
        """:func:`mavcal.link.streams.start_streams` on this link (retried for :attr:`budget_s`):
        ``"interval"`` or ``"data_stream"``. From then on :meth:`iter_batches` watches the streams:
        asked for again when they stop while the vehicle is heard, and a warning when the link
        carries less than :data:`SLOW_LINK_FRACTION` of the rate asked."""
        method = start_streams(self.link, rate_hz, ack_timeout_s=ack_timeout_s, data_timeout_s=data_timeout_s,
                               message_ids=message_ids, budget_s=self.budget_s)
        self._streams = (max(float(rate_hz), 1.0), tuple(message_ids), method)
        self._streams_t0 = self._last_imu = self._last_ask = time.monotonic()
        self._imu_samples, self._rate_checked = 0, False
        return method

    def _watch_streams(self, batch: Batch) -> None:
        """Ask again for streams that stopped while the vehicle is heard; say once when the link is too slow."""
        if self._streams is None:
            return
        rate_hz, ids, method = self._streams
        now = time.monotonic()
        n = sum(len(s.time_s) for s in batch if s.sensor == "accel" and s.instance == 0)
        if n:
            if not self._rate_checked and now - self._last_imu > 1.0:  # after a silence: measure from here
                self._streams_t0, self._imu_samples = now, 0
            self._last_imu = now
            if now - self._streams_t0 < RATE_CHECK_S:
                self._imu_samples += n
        elif (now - self._last_imu >= STREAM_REASK_S and now - self._last_ask >= STREAM_REASK_S
              and self.link.silent_for() < GCS_HEARTBEAT_PERIOD_S * 1.5):
            self._last_ask = now
            log.warning("no IMU data from %s for %.0f s while it is heard: asking for the streams again",
                        self.device, now - self._last_imu)
            try:
                if method == "interval":
                    send_message_intervals(self.link.mav, self.target_system, self.target_component, rate_hz, ids)
                else:
                    self.link.mav.request_data_stream_send(self.target_system, self.target_component,
                                                           _RAW_SENSORS, int(round(rate_hz)), 1)
            except OSError as exc:  # a dead socket: the silence goes on, the capture says so
                log.debug("stream request not sent: %s", exc)
        if not self._rate_checked and now - self._streams_t0 >= RATE_CHECK_S and now - self._last_imu < 1.0:
            self._rate_checked = True
            self.imu_rate_hz = self._imu_samples / (now - self._streams_t0)
            if self.imu_rate_hz < SLOW_LINK_FRACTION * rate_hz:
                w = (f"the link carries the IMU at {self.imu_rate_hz:.0f} Hz of the {rate_hz:g} Hz asked: too slow "
                     f"for the streams (a 57600-baud radio carries about 5.7 kB/s); the capture goes on, slower")
                log.warning(w)
                self.warnings.append(w)

    def read_position(self, timeout_s: float = 3.0) -> VehiclePosition | None:
        """Ask the vehicle where it is (:func:`mavcal.link.position.read_position`); kept in
        :attr:`position` and given to the snapshot (None: the vehicle does not know)."""
        self.position = read_position(self.link, timeout_s=timeout_s) or self._positions.best()
        if self.position is not None:
            log.info("vehicle position for the World Magnetic Model: %s", self.position.describe())
        self._position_asked = time.monotonic()
        return self.position

    def current_position(self) -> VehiclePosition | None:
        """:attr:`position`, or the first the vehicle reported since (a GPS fix that came
        later); while none is known it is asked for every :data:`POSITION_ASK_PERIOD_S` as
        the recording runs (once :meth:`read_position` was called)."""
        if self.position is None:
            self.position = self._positions.best()
            now = time.monotonic()
            if (self.position is None and self._position_asked is not None
                    and now - self._position_asked >= POSITION_ASK_PERIOD_S):
                self._position_asked = now
                request_position(self.link.mav, self.link.target_system, self.link.target_component)
            elif self.position is not None:
                log.info("vehicle position for the World Magnetic Model: %s", self.position.describe())
        return self.position

    # ------------------------------------------------------------------ samples
    def _new_batch(self) -> Batch:
        out: list[SensorSeries] = []
        for name in _BATCH_ORDER:
            rows = self._rows[name]
            a, b = self._batch_mark[name], len(rows)
            self._batch_mark[name] = b
            rows = [r for r in rows[a:b] if r[2] == self.target_system]
            if rows:
                out.extend(imu_series(name, self._fields[name], [r[4] for r in rows], [r[1] for r in rows]))
        return tuple(out)

    def iter_batches(self, duration_s: float | None = None, batch_s: float = 0.2) -> Iterator[Batch]:
        """Yield the new IMU samples every ``batch_s`` (tuples of SensorSeries, may be empty).

        Runs for ``duration_s`` (forever if None; stop by breaking out of the loop).
        """
        end = None if duration_s is None else time.monotonic() + duration_s
        while end is None or time.monotonic() < end:
            left = batch_s if end is None else min(batch_s, end - time.monotonic())
            self.pump(max(left, 0.0))
            self.current_position()
            batch = self._new_batch()
            self._watch_streams(batch)
            yield batch

    def capture(self, duration_s: float, callback: Callable[[Batch], None] | None = None,
                batch_s: float = 0.2, on_progress: Callable[[RecordingProgress], None] | None = None) -> None:
        """Receive for ``duration_s``, passing each batch to ``callback`` if given, and a
        :class:`RecordingProgress` to ``on_progress`` every :data:`PROGRESS_PERIOD_S` and once at the end."""
        start = time.monotonic()
        last, samples = -PROGRESS_PERIOD_S, 0
        for batch in self.iter_batches(duration_s, batch_s):
            samples += sum(len(s.time_s) for s in batch if s.sensor == "accel")
            if callback is not None:
                callback(batch)
            elapsed = time.monotonic() - start
            if on_progress is not None and elapsed - last >= PROGRESS_PERIOD_S:
                last = elapsed
                on_progress(RecordingProgress(min(elapsed, duration_s), duration_s, samples))
        if on_progress is not None:
            on_progress(RecordingProgress(duration_s, duration_s, samples))

    def snapshot(self) -> ImuLog:
        """Everything received so far as an :class:`ImuLog` of kind ``"live"``."""
        cols = {}
        for name, rows in self._rows.items():
            if not rows:
                continue
            c = {k: np.array([r[4][i] for r in rows]) for i, k in enumerate(self._fields[name])}
            c["_index"] = np.array([r[0] for r in rows], dtype=np.int64)
            c["_log_time_s"] = np.array([r[1] for r in rows], dtype=float)
            c["_sysid"] = np.array([r[2] for r in rows])
            c["_compid"] = np.array([r[3] for r in rows])
            cols[name] = c
        imu_log = assemble_tlog(cols, self.device, self.warnings)
        self.current_position()
        if self.position is not None:
            return dataclasses.replace(imu_log, kind="live", position=self.position.location,
                                       position_source=self.position.source)
        return dataclasses.replace(imu_log, kind="live")

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Stop recording (and close the link if the recorder owns it)."""
        for token in [self._token, *self._position_tokens]:
            self.link.remove_handler(token)
        self.link.heartbeat_period_s = None
        if self.owns_link:
            self.link.close()

    def __enter__(self) -> LiveRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_recorder(device: str, *, baud: int = 115200, heartbeat_timeout_s: float = 5.0, budget_s: float = 15.0,
                  signing_key: SigningKey | None = None, tlog: str | os.PathLike[str] | None = None) -> LiveRecorder:
    """Open ``device`` (:func:`~mavcal.link.connection.open_link`) and record from it.

    ``budget_s``: how long the start (heartbeat once the device is heard, stream requests)
    keeps retrying on a lossy link; ``signing_key``: sign the link (:mod:`mavcal.link.signing`);
    ``tlog``: save everything received in this telemetry log (:func:`~mavcal.link.connection.open_link`).

    Raises
    ------
    SigningError
        The vehicle requires signing and the key is missing or wrong (exit 8).
    LinkError
        The device cannot be opened or no vehicle heartbeat arrives within ``heartbeat_timeout_s``.
    """
    rec = LiveRecorder(open_link(device, baud=baud, timeout_s=heartbeat_timeout_s, budget_s=budget_s,
                                 signing_key=signing_key, tlog=tlog), owns_link=True)
    rec.budget_s = budget_s
    return rec


def record_device(device: str, *, baud: int = 115200, duration_s: float = 10.0, heartbeat_timeout_s: float = 5.0,
                  param_timeout_s: float = 30.0, rate_hz: float = 50.0,
                  progress: Callable[[int, int], None] | None = None,
                  on_progress: Callable[[RecordingProgress], None] | None = None, budget_s: float = 15.0,
                  signing_key: SigningKey | None = None, tlog: str | os.PathLike[str] | None = None) -> ImuLog:
    """Record ``duration_s`` seconds of IMU data from a live vehicle as an ImuLog of kind ``"live"``.

    Connect (``LinkError`` when no heartbeat within ``heartbeat_timeout_s``; ``SigningError``
    when the vehicle requires signing and ``signing_key`` is missing or wrong), fetch all
    parameters (bounded by ``param_timeout_s``; an incomplete table is a warning of the log),
    ask where the vehicle is (its GPS / position estimate / home, for the World Magnetic Model:
    the log's ``position`` and ``position_source``), stream the IMU messages the vehicle has
    (:func:`mavcal.link.streams.needed_stream_ids`) at ``rate_hz`` and record. ``budget_s``
    bounds the retries of the start on a lossy link. ``tlog``: save everything received
    (parameters, position, IMU streams) in this telemetry log, which ``mavcal calibrate``
    reads back to the same calibration.

    Parameters
    ----------
    device : str
        pymavlink device string (``udp:HOST:PORT``, ``udpin:``, ``udpout:``, ``tcp:HOST:PORT``,
        a serial port with ``baud``).
    progress : callable, optional
        ``progress(elapsed_ms, duration_ms)`` every :data:`PROGRESS_PERIOD_S` of the recording
        and once at its end: the ``(done, total)`` shape of :func:`mavcal.sources.read_log`'s
        byte count, so any ``(done, total)`` bar shows how far the recording is.
    on_progress : callable, optional
        The same moments with a :class:`RecordingProgress` (elapsed and remaining seconds,
        samples so far), e.g. for a status line.
    """
    def report(p: RecordingProgress) -> None:
        if progress is not None:
            progress(int(round(p.elapsed_s * 1000)), int(round(p.duration_s * 1000)))
        if on_progress is not None:
            on_progress(p)

    with open_recorder(device, baud=baud, heartbeat_timeout_s=heartbeat_timeout_s, budget_s=budget_s,
                       signing_key=signing_key, tlog=tlog) as rec:
        params = rec.fetch_params(timeout_s=param_timeout_s)
        rec.read_position()
        rec.start_streams(rate_hz=rate_hz, message_ids=needed_stream_ids(params))
        rec.capture(duration_s, on_progress=report if (progress or on_progress) else None)
        return rec.snapshot()


def imu_batch_from_messages(messages: Sequence[Any], target_system: int | None = None) -> Batch:
    """Convert received pymavlink IMU messages into a batch of :class:`SensorSeries`.

    The same conversion as :meth:`LiveRecorder.iter_batches`, for code that receives the
    messages itself (e.g. the MAVProxy module, where MAVProxy owns the read loop).

    Parameters
    ----------
    messages : sequence of pymavlink messages
        In receive order; types other than RAW_IMU, SCALED_IMU, SCALED_IMU2 and SCALED_IMU3
        are ignored.
    target_system : int, optional
        Keep only messages from this system id.

    Returns
    -------
    tuple of SensorSeries
        accel/gyro/mag per instance (RAW_IMU and SCALED_IMU: 0, SCALED_IMU2: 1,
        SCALED_IMU3: 2); host receive time (``m._timestamp``, else now) as ``log_time_s``.
    """
    groups: dict[str, list[Any]] = {}
    for m in messages:
        name = m.get_type()
        if name not in SCALED_INSTANCE:
            continue
        if target_system is not None and m.get_srcSystem() != target_system:
            continue
        groups.setdefault(name, []).append(m)
    out: list[SensorSeries] = []
    now = time.time()
    for name in _BATCH_ORDER:
        msgs = groups.get(name)
        if not msgs:
            continue
        fields = msgs[0].get_fieldnames()
        values = [tuple(getattr(m, k) for k in fields) for m in msgs]
        times = [float(getattr(m, "_timestamp", None) or now) for m in msgs]
        out.extend(imu_series(name, fields, values, times))
    return tuple(out)
