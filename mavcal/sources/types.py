"""Data types delivered by the source layer (logs and live links).

Everything is converted once to numpy columns in SI-ish units with the unit in the name:
accelerations in m/s^2, angular rates in rad/s, magnetic field in mGauss, time in seconds.
Readings are exactly what the vehicle sent or logged: *corrected* by the calibration in
force on the vehicle. Undoing that correction is the job of :mod:`mavcal.ardupilot.recover`,
which needs the parameter timeline carried here.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

SENSORS = ("accel", "gyro", "mag")
UNITS = {"accel": "m/s^2", "gyro": "rad/s", "mag": "mGauss"}


def _ro(a) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class SensorSeries:
    """Time series of one instance of one sensor.

    Attributes
    ----------
    sensor : "accel", "gyro" or "mag"
    instance : int
        0-based instance: IMU index for accel/gyro, compass *priority* index for mag
        (RAW_IMU/SCALED_IMU -> 0, SCALED_IMU2 -> 1, SCALED_IMU3 -> 2, DataFlash I field or
        the digit of IMU2/MAG3 names minus one).
    message : str
        The message it came from ("RAW_IMU", "SCALED_IMU2", "HIGHRES_IMU", "IMU", "MAG2", ...).
    time_s : (n,) array
        Seconds. Vehicle time since boot when the message carries it, else log time.
    values : (n, 3) array
        accel in m/s^2, gyro in rad/s, mag in mGauss (see ``UNITS``).
    log_time_s : (n,) array or None
        Log/receive time (tlog timestamp, unix seconds) when different from ``time_s``.
    extra : mapping of name -> array
        Additional per-sample columns, e.g. ``"motor_ofs_mgauss"`` (n, 3) from DataFlash
        MAG.MOX/MOY/MOZ, ``"ofs_mgauss"`` (n, 3) from MAG.OfsX.., ``"health"`` (n,).
    """

    sensor: str
    instance: int
    message: str
    time_s: np.ndarray
    values: np.ndarray
    log_time_s: np.ndarray | None = None
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.sensor not in SENSORS:
            raise ValueError(f"sensor must be one of {SENSORS}, got {self.sensor!r}")
        object.__setattr__(self, "time_s", _ro(self.time_s))
        object.__setattr__(self, "values", _ro(self.values).reshape(-1, 3))
        if self.log_time_s is not None:
            object.__setattr__(self, "log_time_s", _ro(self.log_time_s))
        object.__setattr__(self, "extra", {k: _ro(v) for k, v in dict(self.extra).items()})
        if self.values.shape[0] != self.time_s.shape[0]:
            raise ValueError("time_s and values must have the same length")

    @property
    def unit(self) -> str:
        return UNITS[self.sensor]

    def __len__(self) -> int:
        return int(self.time_s.shape[0])


@dataclass(frozen=True, eq=False)
class ParamTimeline:
    """Values of parameters over time, as logged (PARM) or received (PARAM_VALUE).

    ``changes[name]`` is a pair of arrays ``(time_s, value)`` sorted by time. The first
    entry is the value at log start (or at the time it was first seen). ``value_at`` gives
    the value in force at given times: a change counts from its own time on; before the
    first record the first value is used.
    """

    changes: Mapping[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def __contains__(self, name: str) -> bool:
        return name in self.changes

    def names(self) -> list[str]:
        return sorted(self.changes)

    def initial(self, name: str, default: float | None = None) -> float | None:
        if name not in self.changes:
            return default
        return float(self.changes[name][1][0])

    def final(self, name: str, default: float | None = None) -> float | None:
        if name not in self.changes:
            return default
        return float(self.changes[name][1][-1])

    def value_at(self, name: str, time_s, default: float | None = None) -> np.ndarray:
        """Value in force at each of ``time_s`` (array). NaN where unknown and no default."""
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        if name not in self.changes:
            return np.full(t.shape, np.nan if default is None else float(default))
        ts, vs = self.changes[name]
        idx = np.searchsorted(ts, t, side="right") - 1
        return np.asarray(vs)[np.clip(idx, 0, len(vs) - 1)]

    def values_at(self, names: Iterable[str], time_s) -> dict[str, np.ndarray]:
        """Values of each of ``names`` the timeline has, in force at each of ``time_s``
        (one vectorised lookup per name; names it lacks are left out)."""
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        return {n: self.value_at(n, t) for n in names if n in self.changes}

    def first_seen(self, name: str) -> float | None:
        """Time of the first record of ``name`` (None if it never appears)."""
        if name not in self.changes:
            return None
        return float(self.changes[name][0][0])

    def change_times(self, names: Iterable[str]) -> np.ndarray:
        """Sorted times (after the first record) at which any of ``names`` changed value."""
        out: list[float] = []
        for n in names:
            if n in self.changes:
                ts, vs = self.changes[n]
                for k in range(1, len(vs)):
                    if vs[k] != vs[k - 1]:
                        out.append(float(ts[k]))
        return np.array(sorted(set(out)))

    def snapshot(self, time_s: float | None = None) -> dict[str, float]:
        """All parameters as a dict: the values in force at ``time_s`` (default: the last)."""
        if time_s is None:
            return {n: float(v[-1]) for n, (t, v) in self.changes.items()}
        return {n: float(self.value_at(n, time_s)[0]) for n in self.changes}


@dataclass(frozen=True)
class LogEvent:
    """Something that happened, for raw recovery and reports.

    kind: "statustext" (STATUSTEXT / DataFlash MSG; ``text``), "command" (COMMAND_LONG/INT
    sent to the vehicle; ``code`` = command id, ``params`` = its params), "command_ack"
    (``code`` = command, ``result`` in ``params[0]``), "accelcal_pos" (MAV_CMD_ACCELCAL_VEHICLE_POS),
    "reboot" (the vehicle restarted: ``time_s`` just after the last sample of the old boot),
    "param_set" (PARAM_SET sent to the vehicle: ``text`` = parameter name, ``params`` = (value,)).
    Raw recovery treats reboots, calibration reports and PARAM_SETs as events that may
    change parameters (:mod:`mavcal.ardupilot.param_history`).
    """

    time_s: float
    kind: str
    text: str = ""
    code: int = 0
    params: tuple[float, ...] = ()


@dataclass(frozen=True, eq=False)
class ImuLog:
    """Everything mavcal reads from one source.

    Attributes
    ----------
    source : str  path or device string
    kind : "tlog", "dataflash", "csv" or "live"
    series : tuple of SensorSeries, every sensor instance present
    params : ParamTimeline, on the same time base as the series' ``time_s``
    events : tuple of LogEvent
    position : (lat_deg, lon_deg, alt_m) or None, vehicle/home position if known
    vehicle : mapping with what is known of the vehicle (``"sysid"``, ``"autopilot"``,
        ``"vehicle_type"``, ``"firmware"`` ...)
    warnings : tuple of str, what was skipped and how many (bad CRC, unknown messages...)
    """

    source: str
    kind: str
    series: tuple[SensorSeries, ...]
    params: ParamTimeline = field(default_factory=ParamTimeline)
    events: tuple[LogEvent, ...] = ()
    position: tuple[float, float, float] | None = None
    vehicle: Mapping[str, object] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    def get(self, sensor: str, instance: int = 0) -> SensorSeries | None:
        for s in self.series:
            if s.sensor == sensor and s.instance == instance:
                return s
        return None

    def instances(self, sensor: str) -> list[int]:
        return sorted({s.instance for s in self.series if s.sensor == sensor})
