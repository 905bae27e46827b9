"""Live MAVLink source: connect, fetch parameters, stream IMU data.

One :class:`LiveSource` owns one pymavlink connection and is the only code that reads
from it: every received message goes through :meth:`LiveSource.pump`, which files it
(parameters, IMU samples, acks, status texts). Other code (e.g. a parameter writer) can
use :attr:`LiveSource.connection` to *send*, and :meth:`pump` / :meth:`wait_for` to read.

Typical use::

    with LiveSource("udpin:0.0.0.0:14550") as src:        # LinkError if no heartbeat
        params = src.fetch_params()                        # dict name -> value
        src.start_streams(rate_hz=50)                      # SET_MESSAGE_INTERVAL or fallback
        for batch in src.iter_batches(duration_s=30):      # tuples of SensorSeries
            ...
        imu_log = src.snapshot()                           # everything so far as an ImuLog

Time: ``time_s`` of the batches is the vehicle boot time of each message; ``snapshot()``
uses the same time base rules as tlogs (see :mod:`mavcal.sources.reader`), with the host
receive time (unix s) as ``log_time_s``.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from pymavlink import mavutil

from mavcal.errors import LinkError, MavcalError
from mavcal.sources.reader import (
    IMU_MESSAGES, MG_TO_MS2, TLOG_MESSAGES, _SCALED_INSTANCE, assemble_tlog)
from mavcal.sources.types import ImuLog, SensorSeries

log = logging.getLogger(__name__)

MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_DATA_STREAM_RAW_SENSORS = 1
MAV_RESULT_ACCEPTED = 0
STREAM_MESSAGES = {"RAW_IMU": 27, "SCALED_IMU2": 116, "SCALED_IMU3": 129}
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6


class LiveSource:
    """A live MAVLink vehicle.

    Parameters
    ----------
    device : str
        pymavlink device string: ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``udp:``,
        ``tcp:HOST:PORT`` or a serial port.
    baud : int
        Serial baud rate.
    heartbeat_timeout_s : float
        Time to wait for the vehicle's heartbeat before raising :class:`LinkError`.
    source_system, source_component : int
        Our MAVLink ids (a ground station: 255 / 190).
    """

    def __init__(self, device: str, *, baud: int = 115200, heartbeat_timeout_s: float = 5.0,
                 source_system: int = 255, source_component: int = 190) -> None:
        self.device = str(device)
        self.warnings: List[str] = []
        self._rows: Dict[str, List[tuple]] = {n: [] for n in TLOG_MESSAGES}
        self._fields: Dict[str, Sequence[str]] = {}
        self._batch_mark: Dict[str, int] = {n: 0 for n in IMU_MESSAGES}
        self._index = 0
        self.params: Dict[str, float] = {}
        self._param_index: Dict[int, str] = {}
        self.param_count: Optional[int] = None
        self._acks: List[Tuple[int, int, float]] = []
        self.target_system: Optional[int] = None
        self.target_component: Optional[int] = None
        self._last_hb_sent = 0.0
        try:
            self.connection = mavutil.mavlink_connection(
                self.device, baud=baud, source_system=source_system, source_component=source_component,
                autoreconnect=False, retries=1, reconnect_delay=0.2)
        except MavcalError:
            raise
        except Exception as exc:  # socket / serial errors
            raise LinkError(f"cannot open {self.device}: {exc}") from None
        try:
            self._wait_heartbeat(heartbeat_timeout_s)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ reading
    def _send_heartbeat(self) -> None:
        now = time.monotonic()
        if now - self._last_hb_sent >= 1.0:
            self._last_hb_sent = now
            try:
                self.connection.mav.heartbeat_send(MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, 0)
            except Exception as exc:  # udpout to an unreachable host, closed tcp...
                log.debug("heartbeat send failed: %s", exc)

    def pump(self, timeout_s: float = 0.05) -> int:
        """Read and file every message available within ``timeout_s``; returns how many."""
        deadline = time.monotonic() + timeout_s
        n = 0
        while True:
            self._send_heartbeat()
            try:
                m = self.connection.recv_msg()
            except MavcalError:
                raise
            except Exception as exc:
                raise LinkError(f"link {self.device} failed: {exc}") from None
            if m is None:
                if time.monotonic() >= deadline:
                    return n
                time.sleep(0.002)
                continue
            n += 1
            self._file(m)

    def _file(self, m) -> None:
        typ = m.get_type()
        if typ == "BAD_DATA":
            return
        self._index += 1
        now = time.time()
        sysid = m.get_srcSystem()
        if typ == "HEARTBEAT" and self.target_system is None:
            if m.autopilot != MAV_AUTOPILOT_INVALID and m.type != MAV_TYPE_GCS:
                self.target_system = sysid
                self.target_component = m.get_srcComponent()
        if typ in self._rows:
            if typ not in self._fields:
                self._fields[typ] = m.get_fieldnames()
            self._rows[typ].append((self._index, now, sysid, m.get_srcComponent(),
                                    tuple(getattr(m, f) for f in self._fields[typ])))
        if self.target_system is not None and sysid != self.target_system:
            return
        if typ == "PARAM_VALUE" and m.get_srcComponent() in (1, 190, self.target_component):
            self.params[m.param_id] = float(m.param_value)
            if m.param_index != 65535:
                self._param_index[int(m.param_index)] = m.param_id
                self.param_count = int(m.param_count)
        elif typ == "COMMAND_ACK":
            self._acks.append((int(m.command), int(m.result), time.monotonic()))

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Pump messages until ``predicate()`` is true or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        while True:
            if predicate():
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return predicate()
            self.pump(min(0.05, left))

    def _wait_heartbeat(self, timeout_s: float) -> None:
        if not self.wait_for(lambda: self.target_system is not None, timeout_s):
            raise LinkError(f"no heartbeat from {self.device} within {timeout_s:g} s")
        self.connection.target_system = self.target_system
        self.connection.target_component = self.target_component
        log.info("vehicle sysid %s compid %s on %s", self.target_system, self.target_component, self.device)

    # ------------------------------------------------------------------ parameters
    def fetch_params(self, timeout_s: float = 30.0, idle_s: float = 1.0) -> Dict[str, float]:
        """Fetch all parameters (PARAM_REQUEST_LIST, then PARAM_REQUEST_READ of missing indices).

        Returns the dict of values received. Incomplete after ``timeout_s``: a warning (in
        :attr:`warnings` and the snapshot); nothing at all: :class:`LinkError`.
        """
        mav = self.connection.mav
        mav.param_request_list_send(self.target_system, self.target_component)
        deadline = time.monotonic() + timeout_s
        last_count = -1
        last_change = time.monotonic()
        while time.monotonic() < deadline:
            self.pump(0.05)
            got = len(self._param_index)
            if got != last_count:
                last_count, last_change = got, time.monotonic()
            if self.param_count is not None and got >= self.param_count:
                break
            if time.monotonic() - last_change >= idle_s:
                if self.param_count is None:
                    mav.param_request_list_send(self.target_system, self.target_component)
                else:
                    missing = [i for i in range(self.param_count) if i not in self._param_index]
                    for i in missing[:20]:
                        mav.param_request_read_send(self.target_system, self.target_component, b"", i)
                last_change = time.monotonic()
        if not self.params:
            raise LinkError(f"no parameters received from {self.device} within {timeout_s:g} s")
        if self.param_count is not None and len(self._param_index) < self.param_count:
            w = f"only {len(self._param_index)} of {self.param_count} parameters received within {timeout_s:g} s"
            log.warning(w)
            self.warnings.append(w)
        return dict(self.params)

    # ------------------------------------------------------------------ streams
    def start_streams(self, rate_hz: float = 50.0, ack_timeout_s: float = 1.0, data_timeout_s: float = 2.0) -> str:
        """Ask for RAW_IMU, SCALED_IMU2 and SCALED_IMU3 at ``rate_hz`` (at least 25 Hz).

        Uses MAV_CMD_SET_MESSAGE_INTERVAL; falls back to REQUEST_DATA_STREAM
        (MAV_DATA_STREAM_RAW_SENSORS) when it is not acknowledged or no RAW_IMU arrives.
        Returns ``"interval"`` or ``"data_stream"``.
        """
        rate_hz = max(float(rate_hz), 25.0)
        mav = self.connection.mav
        interval_us = int(round(1e6 / rate_hz))
        t0 = time.monotonic()
        accepted = False
        for name, mid in STREAM_MESSAGES.items():
            mav.command_long_send(self.target_system, self.target_component, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                  mid, interval_us, 0, 0, 0, 0, 0)
        ok = self.wait_for(lambda: any(a[0] == MAV_CMD_SET_MESSAGE_INTERVAL and a[2] >= t0 for a in self._acks),
                           ack_timeout_s)
        if ok:
            accepted = any(a[0] == MAV_CMD_SET_MESSAGE_INTERVAL and a[1] == MAV_RESULT_ACCEPTED and a[2] >= t0
                           for a in self._acks)
        n0 = len(self._rows["RAW_IMU"])
        if accepted and self._wait_rate(n0, rate_hz, data_timeout_s):
            return "interval"
        log.info("SET_MESSAGE_INTERVAL %s; falling back to REQUEST_DATA_STREAM",
                 "not accepted" if not accepted else "gave no data")
        mav.request_data_stream_send(self.target_system, self.target_component, MAV_DATA_STREAM_RAW_SENSORS,
                                     int(round(rate_hz)), 1)
        n0 = len(self._rows["RAW_IMU"])
        if not self._wait_rate(n0, 1.0, data_timeout_s):
            raise LinkError(f"no RAW_IMU data from {self.device} after requesting it")
        return "data_stream"

    def _wait_rate(self, n0: int, rate_hz: float, timeout_s: float) -> bool:
        need = max(2, int(rate_hz * 0.2))
        return self.wait_for(lambda: len(self._rows["RAW_IMU"]) - n0 >= need, timeout_s)

    # ------------------------------------------------------------------ samples
    def _new_batch(self) -> Tuple[SensorSeries, ...]:
        out: List[SensorSeries] = []
        for name in ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "SCALED_IMU"):
            rows = self._rows[name]
            a, b = self._batch_mark[name], len(rows)
            self._batch_mark[name] = b
            rows = [r for r in rows[a:b] if self.target_system is None or r[2] == self.target_system]
            if rows:
                out.extend(_imu_series(name, self._fields[name], [r[4] for r in rows], [r[1] for r in rows]))
        return tuple(out)

    def iter_batches(self, duration_s: Optional[float] = None, batch_s: float = 0.2) -> Iterator[Tuple[SensorSeries, ...]]:
        """Yield the new IMU samples every ``batch_s`` (tuples of SensorSeries, may be empty).

        Runs for ``duration_s`` (forever if None; stop by breaking out of the loop).
        """
        end = None if duration_s is None else time.monotonic() + duration_s
        while end is None or time.monotonic() < end:
            left = batch_s if end is None else min(batch_s, end - time.monotonic())
            self.pump(max(left, 0.0))
            yield self._new_batch()

    def capture(self, duration_s: float, callback: Optional[Callable[[Tuple[SensorSeries, ...]], None]] = None,
                batch_s: float = 0.2) -> None:
        """Receive for ``duration_s``, passing each batch to ``callback`` if given."""
        for batch in self.iter_batches(duration_s, batch_s):
            if callback is not None:
                callback(batch)

    def snapshot(self) -> ImuLog:
        """Everything received so far as an :class:`ImuLog` of kind ``"live"``."""
        cols = {}
        for name, rows in self._rows.items():
            if not rows:
                continue
            f = list(self._fields[name])
            c = {k: np.array([r[4][i] for r in rows]) for i, k in enumerate(f)}
            c["_index"] = np.array([r[0] for r in rows], dtype=np.int64)
            c["_log_time_s"] = np.array([r[1] for r in rows], dtype=float)
            c["_sysid"] = np.array([r[2] for r in rows])
            c["_compid"] = np.array([r[3] for r in rows])
            cols[name] = c
        imu_log = assemble_tlog(cols, self.device, self.warnings)
        return dataclasses.replace(imu_log, kind="live")

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        try:
            self.connection.close()
        except Exception:  # pragma: no cover - closing a dead socket
            pass

    def __enter__(self) -> "LiveSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_BATCH_ORDER = ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "SCALED_IMU")


def _imu_series(name: str, fields: Sequence[str], values: Sequence[tuple],
                log_times: Sequence[float]) -> List[SensorSeries]:
    """accel/gyro/mag :class:`SensorSeries` of rows of one IMU message type (SI units, mGauss).

    The one unit conversion of live IMU messages: milli-g -> m/s^2, mrad/s -> rad/s, mGauss
    as sent; rows whose accel and gyro are all zero (no IMU) or whose mag is all zero (no
    compass) are left out of that sensor's series.
    """
    f = list(fields)
    v = np.array(values, dtype=float)
    t = v[:, f.index("time_boot_ms")] * 1e-3 if "time_boot_ms" in f else v[:, f.index("time_usec")] * 1e-6
    lt = np.asarray(log_times, dtype=float)
    acc = v[:, [f.index("xacc"), f.index("yacc"), f.index("zacc")]]
    gyr = v[:, [f.index("xgyro"), f.index("ygyro"), f.index("zgyro")]]
    mag = v[:, [f.index("xmag"), f.index("ymag"), f.index("zmag")]]
    inst = _SCALED_INSTANCE[name]
    imu = ~((acc == 0).all(axis=1) & (gyr == 0).all(axis=1))
    hm = ~(mag == 0).all(axis=1)
    out: List[SensorSeries] = []
    if imu.any():
        out.append(SensorSeries("accel", inst, name, t[imu], acc[imu] * MG_TO_MS2, lt[imu]))
        out.append(SensorSeries("gyro", inst, name, t[imu], gyr[imu] / 1000.0, lt[imu]))
    if hm.any():
        out.append(SensorSeries("mag", inst, name, t[hm], mag[hm], lt[hm]))
    return out


def imu_batch_from_messages(messages: Sequence[object],
                            target_system: Optional[int] = None) -> Tuple[SensorSeries, ...]:
    """Convert received pymavlink IMU messages into a batch of :class:`SensorSeries`.

    The same conversion as :meth:`LiveSource.iter_batches`, for code that receives the
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
    groups: Dict[str, List[object]] = {}
    for m in messages:
        name = m.get_type()  # type: ignore[attr-defined]
        if name not in _SCALED_INSTANCE:
            continue
        if target_system is not None and m.get_srcSystem() != target_system:  # type: ignore[attr-defined]
            continue
        groups.setdefault(name, []).append(m)
    out: List[SensorSeries] = []
    now = time.time()
    for name in _BATCH_ORDER:
        msgs = groups.get(name)
        if not msgs:
            continue
        fields = msgs[0].get_fieldnames()  # type: ignore[attr-defined]
        values = [tuple(getattr(m, k) for k in fields) for m in msgs]
        times = [float(getattr(m, "_timestamp", None) or now) for m in msgs]
        out.extend(_imu_series(name, fields, values, times))
    return tuple(out)
