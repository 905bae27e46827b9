"""Read a PX4 flight log (ULog, ``.ulg``) into an :class:`~mavcal.sources.types.ImuLog` with pyulog.

What is read
------------
* ``sensor_accel`` / ``sensor_gyro`` / ``sensor_mag``: one series per topic instance (``multi_id``),
  the readings as the drivers published them, **before** PX4's calibration (offsets, scales,
  rotation): accel m/s^2, gyro rad/s, mag gauss (converted to mGauss here). Each series carries the
  sensor's device id per sample in ``extra["device_id"]`` (the key of PX4's calibration slots) and,
  for a magnetometer logged with it, ``extra["is_external"]``. Times: ``timestamp_sample`` (else
  ``timestamp``), microseconds since boot -> seconds.
* the parameters: those at the start (time of the first logged sample) and every change
  logged later, as a :class:`~mavcal.sources.types.ParamTimeline` (INT32 parameters as the
  integers pyulog decodes, never through float32).
* the position: the first 3-D GPS fix (``vehicle_gps_position`` / ``sensor_gps``), else the
  home position or the global position estimate.

PX4 logs its raw sensor topics at a low rate by default (about 1 Hz, ``SDLOG_PROFILE`` bit 2 "high
rate" or 3 "debug" raises it); a log without them (older PX4: only ``sensor_combined``, which is
calibrated and averaged) is refused with that advice. :func:`calibrated_topics` gives PX4's own
calibrated output beside them (``vehicle_acceleration``, ``vehicle_magnetometer``, the
``vehicle_imu`` velocity increments), for checking the conventions of PX4's model.

Only this module (and :mod:`mavcal.link`) imports pyulog.
"""
from __future__ import annotations

import contextlib
import io
import logging
import mmap
import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mavcal.autopilot.mavlink import MAV_AUTOPILOT_PX4
from mavcal.errors import SourceError
from mavcal.sources.types import ImuLog, ParamTimeline, SensorSeries

__all__ = ["read_ulog", "calibrated_topics", "CalibratedTopic", "MAV_AUTOPILOT_PX4", "NO_RAW_TOPICS", "load_topics",
           "start_us", "is_ulog"]

log = logging.getLogger(__name__)

#: how the refusal of a log without raw sensor topics begins
NO_RAW_TOPICS = "no raw sensor_accel/sensor_mag topics"

_RAW = (("sensor_accel", "accel", 1.0), ("sensor_gyro", "gyro", 1.0), ("sensor_mag", "mag", 1000.0))
_GPS = ("vehicle_gps_position", "sensor_gps")


#: the first bytes of every ULog (magic and version byte aside: ``ULog`` 0x01 0x12 0x35)
_MAGIC = b"ULog\x01\x12\x35"
_HEADER_BYTES = 16
#: message types of the definitions section (pyulog reads them in ``_read_file_definitions``):
#: FLAG_BITS, FORMAT, INFO, INFO_MULTIPLE, PARAMETER, PARAMETER_DEFAULT
_DEFINITION_TYPES = frozenset(b"BFIMPQ")
#: the types that end it (the data section begins): ADD_LOGGED_MSG, LOGGING, LOGGING_TAGGED
_DATA_START_TYPES = frozenset(b"ALC")
#: pyulog calls a header of an unknown type corrupt, and steps one byte, when its type is 0, its
#: size 0 or its size above this (``ULog._check_packet_corruption``)
_CORRUPT_SIZE = 10000
#: read calls pyulog may make per byte of the file, and on top (it reads a message with two calls, a
#: damaged stretch byte by byte with two calls per byte and a sync search) before its read is
#: called endless: the read of any file ends within a number of steps that grows with its size
_READS_PER_BYTE = 8
_READS_FIXED = 10_000


def _check_definitions(path: str, data) -> None:
    """Walk a ULog's header and definitions section the way pyulog 1.3 does (``ULog._read_file_header``
    and ``_read_file_definitions``), and refuse what pyulog cannot read or would read forever.

    pyulog steps one byte past a header of an unknown type that it calls corrupt (type 0, size 0 or
    above 10,000 bytes) by seeking back from where its read of the message's payload ended; when that
    payload runs past the end of the file the read is short and the seek lands *before* the header, and
    the walk repeats forever. Every message of the definitions section must end inside the file.
    """
    size = len(data)
    if size < _HEADER_BYTES or bytes(data[:7]) != _MAGIC:
        raise SourceError(f"{path}: not a ULog (its first bytes are not a ULog file header)")
    p = _HEADER_BYTES
    while p + 3 <= size:
        msg_size = data[p] | (data[p + 1] << 8)
        msg_type = data[p + 2]
        if msg_type in _DATA_START_TYPES:
            return
        if p + 3 + msg_size > size:
            raise SourceError(f"{path}: damaged ULog: the message at byte {p} of its definitions section declares "
                              f"{msg_size} bytes, past the end of the file ({size} bytes): the file is cut or corrupt "
                              "before its data")
        if msg_type in _DEFINITION_TYPES or not (msg_type == 0 or msg_size == 0 or msg_size > _CORRUPT_SIZE):
            p += 3 + msg_size
        else:  # pyulog's recovery: one byte on
            p += 1
    raise SourceError(f"{path}: damaged ULog: the file ends inside its definitions section (byte {size}): "
                      "it holds no data")


class _BoundedFile:
    """The file as pyulog sees it (``read``, ``seek``, ``tell``, ``close``), which ends a read that
    makes more read calls than :data:`_READS_PER_BYTE` per byte of the file: whatever pyulog does on
    a damaged file, the read ends, with the byte it had reached."""

    def __init__(self, path: str, size: int) -> None:
        self._fh = open(path, "rb")  # noqa: SIM115 - closed by pyulog, or by close() below
        self.path, self.size = path, size
        self.reads = 0
        self.budget = _READS_FIXED + _READS_PER_BYTE * size
        self.at = 0  # where the last read began

    def read(self, n: int = -1) -> bytes:
        self.reads += 1
        self.at = self._fh.tell()
        if self.reads > self.budget:
            raise SourceError(f"{self.path}: damaged ULog: pyulog makes no progress at byte {self.at} of {self.size} "
                              f"(more than {self.budget} reads): the file is corrupt there")
        return self._fh.read(n)

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._fh.seek(offset, whence)

    def tell(self) -> int:
        return self._fh.tell()

    def close(self) -> None:
        self._fh.close()


def _load(path: str, topics: list[str]):
    """pyulog's ``ULog`` of ``path`` (only ``topics``' data), after :func:`_check_definitions`, through a
    :class:`_BoundedFile`; pyulog's own printing goes to the debug log. Its failure is a
    :class:`SourceError` naming pyulog and the byte it had reached, never a Python exception's name."""
    try:
        from pyulog import ULog
    except ImportError:  # pragma: no cover - a core dependency
        raise SourceError("reading a PX4 .ulg log needs pyulog (pip install pyulog)") from None
    size = os.path.getsize(path)
    with open(path, "rb") as fh:
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
            _check_definitions(path, data)
    f = _BoundedFile(path, size)
    said = io.StringIO()
    try:
        with contextlib.redirect_stdout(said):
            return ULog(f, message_name_filter_list=topics, disable_str_exceptions=True)
    except SourceError:
        raise
    except MemoryError:
        raise SourceError(f"out of memory reading {path}") from None
    except Exception as exc:  # noqa: BLE001 - a third-party parser's failure on a damaged file: one line
        log.debug("pyulog failed on %s", path, exc_info=True)
        reason = str(exc) if exc.__class__.__name__.startswith("ULog") else "the file is damaged there"
        raise SourceError(f"pyulog could not parse {path} (at byte {f.at} of {size}): {reason}") from None
    finally:
        f.close()
        if said.getvalue().strip():
            log.debug("pyulog on %s: %s", path, " | ".join(said.getvalue().split("\n"))[:500])


def _start_us(ulog) -> int:
    """The log's start (its header's timestamp, microseconds): times are seconds from it, as
    a tlog's and a DataFlash log's are seconds from their start (boot), whatever clock the
    vehicle stamped with (a SITL with the wall clock stamps epoch microseconds)."""
    try:
        return max(int(getattr(ulog, "start_timestamp", 0) or 0), 0)
    except (TypeError, ValueError):
        return 0


def _times_s(d, start_us: int = 0) -> np.ndarray:
    t = np.asarray(d.data.get("timestamp_sample", d.data["timestamp"]))
    return (t.astype(np.int64) - np.int64(start_us)).astype(np.float64) / 1e6  # exact: integers first


def _vec(d, names: tuple[str, str, str]) -> np.ndarray:
    return np.stack([np.asarray(d.data[n], dtype=np.float64) for n in names], axis=1)


def _raw_series(ulog) -> list[SensorSeries]:
    out = []
    start = _start_us(ulog)
    for topic, sensor, unit in _RAW:
        for d in sorted((d for d in ulog.data_list if d.name == topic), key=lambda d: d.multi_id):
            if not {"x", "y", "z", "timestamp"} <= set(d.data):
                continue
            t = _times_s(d, start)
            order = np.argsort(t, kind="stable")
            extra = {"device_id": np.asarray(d.data.get("device_id", np.zeros(len(t))), dtype=np.float64)[order]}
            if "is_external" in d.data:
                extra["is_external"] = np.asarray(d.data["is_external"], dtype=np.float64)[order]
            vals = _vec(d, ("x", "y", "z"))[order] * unit
            out.append(SensorSeries(sensor, int(d.multi_id), topic, t[order], vals, extra=extra))
    return out


def _number(path: str, name: str, value) -> float:
    """A parameter's value as a float; pyulog hands over the raw bytes of a value whose type (``int32_t``
    / ``float``) is damaged, and such a log cannot say which calibration was in force: refused."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        return float(value)
    shown = "".join(c if c.isprintable() else "?" for c in str(name))[:40]
    raise SourceError(f"{path}: damaged ULog: parameter '{shown}' holds no number (its type is damaged), so the "
                      "parameters in force are not known")


def _params(ulog, t0: float, path: str = "") -> ParamTimeline:
    changes: dict[str, tuple[list[float], list[float]]] = {}
    for name, value in ulog.initial_parameters.items():
        changes[name] = ([t0], [_number(path, name, value)])
    start = _start_us(ulog)
    for ts, name, value in ulog.changed_parameters:
        tl, vl = changes.setdefault(name, ([], []))
        t = (int(ts) - start) / 1e6
        if tl and t < tl[-1]:
            t = tl[-1]
        tl.append(t)
        vl.append(_number(path, name, value))
    return ParamTimeline({n: (np.array(t, dtype=float), np.array(v, dtype=float)) for n, (t, v) in changes.items()})


def _first_fix(d) -> tuple[float, float, float] | None:
    data = d.data
    if "latitude_deg" in data:
        lat, lon = np.asarray(data["latitude_deg"], float), np.asarray(data["longitude_deg"], float)
        alt = np.asarray(data.get("altitude_msl_m", np.zeros(len(lat))), float)
    elif "lat" in data and np.asarray(data["lat"]).dtype.kind in "iu":  # older GPS topics: 1e-7 deg, mm
        lat, lon = np.asarray(data["lat"], float) / 1e7, np.asarray(data["lon"], float) / 1e7
        alt = np.asarray(data.get("alt", np.zeros(len(lat))), float) / 1e3
    elif "lat" in data:  # home_position, vehicle_global_position: degrees, metres
        lat, lon = np.asarray(data["lat"], float), np.asarray(data["lon"], float)
        alt = np.asarray(data.get("alt", np.zeros(len(lat))), float)
    else:
        return None
    ok = np.isfinite(lat) & np.isfinite(lon) & ((lat != 0) | (lon != 0)) & (np.abs(lat) <= 90)
    if "fix_type" in data:
        ok &= np.asarray(data["fix_type"]) >= 3
    if "valid_hpos" in data:
        ok &= np.asarray(data["valid_hpos"]) != 0
    k = np.flatnonzero(ok)
    if not len(k):
        return None
    i = int(k[0])
    return (float(lat[i]), float(lon[i]), float(alt[i]))


def _position(ulog) -> tuple[float, float, float] | None:
    by_name: dict[str, list] = {}
    for d in ulog.data_list:
        by_name.setdefault(d.name, []).append(d)
    for name in (*_GPS, "home_position", "vehicle_global_position"):
        for d in by_name.get(name, []):
            p = _first_fix(d)
            if p is not None:
                return p
    return None


def _vehicle(ulog) -> dict[str, object]:
    info = ulog.msg_info_dict
    v: dict[str, object] = {"autopilot": MAV_AUTOPILOT_PX4, "firmware": "PX4"}
    for key, name in (("ver_hw", "hardware"), ("ver_sw", "git_hash"), ("sys_name", "system")):
        if key in info:
            v[name] = str(info[key])
    return v


def read_ulog(path: str) -> ImuLog:
    """Read the raw sensor topics, the parameters and the position of a PX4 ULog.

    Raises
    ------
    SourceError
        Not a ULog or corrupt, or no raw ``sensor_accel`` topic (the one-line message says what
        the log holds and what to change on the vehicle).
    """
    topics = [t for t, _, _ in _RAW] + list(_GPS) + ["home_position", "vehicle_global_position", "sensor_combined"]
    ulog = _load(path, topics)
    series = _raw_series(ulog)
    if not any(s.sensor == "accel" and len(s) for s in series):
        held = "only the calibrated, averaged sensor_combined" if any(
            d.name == "sensor_combined" for d in ulog.data_list) else "no IMU topic"
        raise SourceError(f"{path}: {NO_RAW_TOPICS} (this PX4 log holds {held}); log them with SDLOG_PROFILE "
                          "bit 2 (high rate) or 3 (debug) set, and hold the still poses while armed or with "
                          "SDLOG_MODE logging from boot")
    t0 = min(float(s.time_s[0]) for s in series if len(s))
    warnings = []
    for s in series:
        rate = len(s) / max(float(s.time_s[-1] - s.time_s[0]), 1e-9) if len(s) > 1 else 0.0
        if rate < 5.0:
            warnings.append(f"{s.message} {s.instance} logged at {rate:.2g} Hz (PX4's default profile): too slow "
                            "for still intervals; raise SDLOG_PROFILE")
            break
    ignored = getattr(ulog, "dropouts", None)
    if ignored:
        warnings.append(f"the log has {len(ignored)} dropouts (messages lost while logging)")
    return ImuLog(source=str(path), kind="ulog", series=tuple(series), params=_params(ulog, t0, path),
                  position=_position(ulog), vehicle=_vehicle(ulog), warnings=tuple(warnings))


@dataclass(frozen=True, eq=False)
class CalibratedTopic:
    """PX4's own calibrated output (body frame): ``values`` m/s^2 or mGauss, ``time_s``,
    ``device_id`` (per sample, 0 when the topic does not carry it), ``window_s`` (per sample: the
    span the value averages, 0 when it is one filtered sample)."""

    topic: str
    instance: int
    sensor: str
    time_s: np.ndarray
    values: np.ndarray
    device_id: np.ndarray
    window_s: np.ndarray


def calibrated_topics(path: str) -> list[CalibratedTopic]:
    """``vehicle_acceleration`` (filtered accel), ``vehicle_magnetometer`` (averaged mag) and the
    ``vehicle_imu`` velocity increments as mean accelerations (Delta v / dt over ``window_s``) of a
    ULog: PX4's calibrated, rotated readings."""
    ulog = _load(path, ["vehicle_acceleration", "vehicle_magnetometer", "vehicle_imu"])
    out = []
    start = _start_us(ulog)
    for d in ulog.data_list:
        data: Mapping[str, np.ndarray] = d.data
        t = _times_s(d, start)
        n = len(t)
        if d.name == "vehicle_acceleration" and "xyz[0]" in data:
            out.append(CalibratedTopic(d.name, d.multi_id, "accel", t, _vec(d, ("xyz[0]", "xyz[1]", "xyz[2]")),
                                       np.zeros(n), np.zeros(n)))
        elif d.name == "vehicle_magnetometer" and "magnetometer_ga[0]" in data:
            dev = np.asarray(data.get("device_id", np.zeros(n)), dtype=np.float64)
            v = _vec(d, ("magnetometer_ga[0]", "magnetometer_ga[1]", "magnetometer_ga[2]")) * 1000.0
            out.append(CalibratedTopic(d.name, d.multi_id, "mag", t, v, dev, np.zeros(n)))
        elif d.name == "vehicle_imu" and "delta_velocity_dt" in data:
            dt = np.asarray(data["delta_velocity_dt"], dtype=np.float64) / 1e6
            ok = dt > 0
            dv = _vec(d, ("delta_velocity[0]", "delta_velocity[1]", "delta_velocity[2]"))
            dev = np.asarray(data["accel_device_id"], dtype=np.float64)
            out.append(CalibratedTopic(d.name, d.multi_id, "accel", t[ok], dv[ok] / dt[ok, None], dev[ok], dt[ok]))
    return out


def load_topics(path: str, topics: list[str]):
    """pyulog's ``ULog`` of ``path`` with only ``topics``' data, checked as :func:`read_ulog` does
    (:class:`SourceError` in one line when it cannot be read)."""
    return _load(path, topics)


def start_us(ulog) -> int:
    """The log's start (microseconds): the times of :func:`read_ulog` are seconds from it."""
    return _start_us(ulog)


def is_ulog(path: str) -> bool:
    """Whether the file begins with the ULog magic."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(_MAGIC)) == _MAGIC
    except OSError:
        return False
