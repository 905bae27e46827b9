"""Data types delivered by the source layer (logs and live links).

Everything is converted once to numpy columns in SI-ish units with the unit in the name:
accelerations in m/s^2, angular rates in rad/s, magnetic field in mGauss, time in seconds.
Readings are exactly what the vehicle sent or logged: *corrected* by the calibration in
force on the vehicle. Undoing that correction is the job of the autopilot's model (``recover_raw``),
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


#: rows decoded per step of :meth:`PackedValues.decode` (the temporaries stay small and cached)
_DECODE_ROWS = 1 << 15


@dataclass(frozen=True, eq=False)
class PackedValues:
    """Integer telemetry readings standing for the float64 values of a series, computed on access.

    A tlog's IMU readings are int16 telemetry (milli-g, mrad/s, mGauss): storing the integers
    takes a quarter of the memory of the float64 values. :meth:`decode` gives the values with
    the arithmetic of the reader, bit for bit: ``counts`` cast to float64, times ``mul``
    (when not 1), divided by ``div`` (when not 1), then ``half_step * sign`` added when the
    truncation was undone (``v + (0.5 * q) * sign(v)``, :mod:`mavcal.sources.quantization`;
    the sign of the value is the sign of the integer).

    Attributes
    ----------
    counts : (n, 3) int16 array, read-only
    mul, div : float
        The unit: value = count * mul / div (accel ``GRAVITY_MPS2 / 1000`` and 1, gyro 1 and
        1000, mag 1 and 1).
    half_step : float
        Half the telemetry unit when the truncation has been undone, else 0.
    """

    counts: np.ndarray
    mul: float = 1.0
    div: float = 1.0
    half_step: float = 0.0

    def __post_init__(self) -> None:
        c = np.asarray(self.counts)
        if c.dtype.kind not in "iu":
            raise ValueError(f"packed counts must be integers, got {c.dtype}")
        if c.ndim != 2 or c.shape[1:] != (3,):
            c = c.reshape(-1, 3)
        if c.flags.writeable:
            c = c.view()
            c.setflags(write=False)
        object.__setattr__(self, "counts", c)

    def __len__(self) -> int:
        return int(self.counts.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.counts.nbytes)

    @property
    def untruncated(self) -> bool:
        return self.half_step != 0.0

    def decode(self, rows: slice | np.ndarray | None = None) -> np.ndarray:
        """The float64 values (n, 3) of ``rows`` (all by default; a slice or an index array),
        a new read-only array, computed a block of rows at a time."""
        c = self.counts if rows is None else self.counts[rows]
        out = np.empty(c.shape, dtype=np.float64)
        step = _DECODE_ROWS
        sign = np.empty((min(len(c), step), 3), dtype=np.float64) if self.half_step != 0.0 else None
        for i in range(0, len(c), step):
            ci, o = c[i:i + step], out[i:i + step]
            o[...] = ci
            if self.mul != 1.0:
                o *= self.mul
            if self.div != 1.0:
                o /= self.div
            if sign is not None:
                s = sign[:len(ci)]
                np.sign(ci, out=s)  # -1, 0 or 1: the sign of the value
                s *= self.half_step
                o += s
        out.setflags(write=False)
        return out

    def take(self, rows: slice | np.ndarray) -> PackedValues:
        """The rows ``rows`` (their integers; the same arithmetic)."""
        return PackedValues(self.counts[rows], self.mul, self.div, self.half_step)

    def with_half_step(self, half_step: float) -> PackedValues:
        """The same integers with the truncation undone by ``half_step`` (no copy of them)."""
        return PackedValues(self.counts, self.mul, self.div, half_step)


@dataclass(frozen=True, eq=False, init=False)
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
    values : (n, 3) float64 array
        accel in m/s^2, gyro in rad/s, mag in mGauss (see ``UNITS``). Given as an array or
        as :class:`PackedValues` (integer telemetry, what the tlog reader gives): then it is
        computed on every access (not kept: take it once and keep the array while needed;
        :meth:`values_at` computes some rows only, :attr:`packed` gives the integers).
    log_time_s : (n,) array or None
        Log/receive time (tlog timestamp, unix seconds) when different from ``time_s``.
    extra : mapping of name -> array
        Additional per-sample columns, e.g. ``"motor_ofs_mgauss"`` (n, 3) from DataFlash
        MAG.MOX/MOY/MOZ, ``"ofs_mgauss"`` (n, 3) from MAG.OfsX.., ``"health"`` (n,).

    ``dataclasses.replace`` works as for any dataclass (``replace(s, values=...)`` with an
    array or :class:`PackedValues`; a replace of other fields keeps the values as stored).
    """

    sensor: str
    instance: int
    message: str
    time_s: np.ndarray
    log_time_s: np.ndarray | None
    extra: Mapping[str, np.ndarray]
    # the values as given: a read-only float array or PackedValues (``values`` is what to read)
    _stored: np.ndarray | PackedValues = field(repr=False)

    def __init__(self, sensor: str, instance: int, message: str, time_s: np.ndarray,
                 values: np.ndarray | PackedValues | None = None, log_time_s: np.ndarray | None = None,
                 extra: Mapping[str, np.ndarray] | None = None,
                 _stored: np.ndarray | PackedValues | None = None) -> None:
        if sensor not in SENSORS:
            raise ValueError(f"sensor must be one of {SENSORS}, got {sensor!r}")
        if values is None:  # dataclasses.replace of other fields hands the stored values back
            if _stored is None:
                raise TypeError("SensorSeries needs values")
            values = _stored
        stored = values if isinstance(values, PackedValues) else _ro(values).reshape(-1, 3)
        setattr_ = object.__setattr__
        setattr_(self, "sensor", sensor)
        setattr_(self, "instance", instance)
        setattr_(self, "message", message)
        setattr_(self, "time_s", _ro(time_s))
        setattr_(self, "log_time_s", None if log_time_s is None else _ro(log_time_s))
        setattr_(self, "extra", {k: _ro(v) for k, v in dict(extra or {}).items()})
        setattr_(self, "_stored", stored)
        if len(stored) != self.time_s.shape[0]:
            raise ValueError("time_s and values must have the same length")

    @property
    def values(self) -> np.ndarray:
        """(n, 3) float64, read-only (computed on each access when packed)."""
        st = self._stored
        return st.decode() if isinstance(st, PackedValues) else st

    @property
    def packed(self) -> PackedValues | None:
        """The integer readings the values are computed from, or None (float values)."""
        st = self._stored
        return st if isinstance(st, PackedValues) else None

    def values_at(self, rows: slice | np.ndarray) -> np.ndarray:
        """``values[rows]``, computing only those rows when packed (a slice or an index array)."""
        st = self._stored
        return st.decode(rows) if isinstance(st, PackedValues) else st[rows]

    def any_nonzero(self) -> bool:
        """Whether some value is not 0.0 (NaN counts as non-zero), looking at the first rows first:
        a real series shows a non-zero value at once, only an all-zero one is read to its end."""
        st = self._stored
        x = st.counts if isinstance(st, PackedValues) else st  # a value is 0.0 exactly when its integer is 0
        return bool(np.count_nonzero(x[:64])) or bool(np.count_nonzero(x))

    def mark_untruncated(self, half_step: float) -> None:
        """Set the half step of a packed series *in place* (the truncation undone, no value
        rewritten). Only for a series nobody else reads as read:
        :func:`mavcal.sources.quantization.untruncate_log` with ``in_place=True``."""
        p = self.packed
        if p is None or p.untruncated:
            raise ValueError("only a packed series not yet untruncated can be marked untruncated")
        object.__setattr__(self, "_stored", p.with_half_step(half_step))

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
    change parameters (ArduPilot's parameter history).
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
    position_source : str, where a live position came from (``"vehicle GPS"``...); "" for a log's
    vehicle : mapping with what is known of the vehicle (``"sysid"``, ``"autopilot"``,
        ``"vehicle_type"``, ``"firmware"`` ...)
    warnings : tuple of str, what was skipped and how many (bad CRC, unknown messages...)
    param_origins : mapping of parameter name to where its value came from, for the names that did
        not come from the source itself (``"--params vehicle.param"``: a parameter file given with
        the recording, :func:`mavcal.in_force.with_param_file`); every other name came from the
        recording (a log) or the vehicle (a live link)
    """

    source: str
    kind: str
    series: tuple[SensorSeries, ...]
    params: ParamTimeline = field(default_factory=ParamTimeline)
    events: tuple[LogEvent, ...] = ()
    position: tuple[float, float, float] | None = None
    vehicle: Mapping[str, object] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    position_source: str = ""
    param_origins: Mapping[str, str] = field(default_factory=dict)

    def get(self, sensor: str, instance: int = 0) -> SensorSeries | None:
        for s in self.series:
            if s.sensor == sensor and s.instance == instance:
                return s
        return None

    def instances(self, sensor: str) -> list[int]:
        return sorted({s.instance for s in self.series if s.sensor == sensor})

    def origin_of(self, names: Iterable[str]) -> str:
        """Where the values of ``names`` (those the timeline has) came from, in words: the
        recording's parameters, the vehicle (a live link) or a parameter file given with it
        (``param_origins``); several joined by " and "."""
        own = "the vehicle" if self.kind == "live" else "the recording's parameters"
        found = {self.param_origins.get(n, own) for n in names if n in self.params}
        return " and ".join(sorted(found)) if found else ""
