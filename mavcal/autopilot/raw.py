"""The raw readings any autopilot's recovery gives the fit (:class:`RawImu`): the vocabulary of
"recover raw", whatever firmware undid its own correction (ArduPilot's model,
PX4's: ``recover_raw``)."""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from mavcal.sources.types import SensorSeries

__all__ = ["RawImu", "log_warnings_once", "ACCEL_FRAME", "MAG_FRAME"]

#: the recovery's warnings already logged at WARNING by this process (a live capture recovers the
#: readings at every update: the same warning again and again would flood the console)
_LOGGED: set[str] = set()


def log_warnings_once(logger: logging.Logger, warnings) -> None:
    """Log each warning at WARNING the first time this process meets it, at DEBUG after that (every
    warning is also in :attr:`RawImu.warnings`, which the reports show)."""
    for w in warnings:
        logger.log(logging.DEBUG if w in _LOGGED else logging.WARNING, "%s", w)
        if len(_LOGGED) < 10000:
            _LOGGED.add(w)


ACCEL_FRAME = "board frame (before AHRS_ORIENTATION)"
MAG_FRAME = "body frame after COMPASS_ORIENT/AHRS_ORIENTATION"


@dataclass(frozen=True, eq=False)
class RawImu:
    """Raw (uncorrected) IMU readings recovered from a log.

    Attributes
    ----------
    source : str
    accel : tuple of SensorSeries
        One per accelerometer instance; ``values`` in m/s^2, **board frame**. ``extra``
        holds ``"calibrating"`` (n,) 1.0 where the sample was taken while an accel
        calibration ran (the firmware had suspended offsets/scale).
    mag : tuple of SensorSeries
        One per compass (priority index); ``values`` in mGauss, **body frame after
        orientation**.
    gyro : tuple of SensorSeries
        As logged (corrected, body frame, rad/s); used to detect stillness.
    params_used : mapping name -> tuple of (time_s, value)
        Every calibration parameter the inversion used, with the values in force over the
        span of the data (first entry: value at the start).
    frames : mapping sensor -> frame description
    warnings : tuple of str
    accel_cal_periods : tuple of (start_s, end_s)
        Periods during which ArduPilot's accelerometer calibration ran (samples there
        were not inverse-corrected for offsets/scale).
    board_rotation : (3, 3) array or None
        R_A of AHRS_ORIENTATION (at the end of the data): board frame -> body frame.
    accel_cal_without_imu : tuple of (start_s, end_s)
        Accelerometer calibrations whose prompts the log holds but during which it has
        (almost) no IMU readings (:func:`accel_cal_without_imu`): the poses held then are lost.
    cal_origin : mapping sensor -> str
        Per sensor (``"accel0"``, ``"compass1"``, as the gates name them) where the calibration
        in force that was undone came from: ``"the recording's parameters"``, ``"the vehicle"``,
        ``"--params FILE"`` (:mod:`mavcal.in_force`), or ``"raw readings"`` (a CSV).
    cal_missing : mapping sensor -> tuple of str
        The sensors whose calibration in force is **not known** (the recording lacks some or all
        of its parameters), each with the names missing. Their readings were recovered with the
        firmware's defaults to be judged, but their new values are never written
        (:func:`mavcal.in_force.in_force_gates`).
    """

    source: str
    accel: tuple[SensorSeries, ...]
    mag: tuple[SensorSeries, ...]
    gyro: tuple[SensorSeries, ...] = ()
    params_used: Mapping[str, tuple[tuple[float, float], ...]] = field(default_factory=dict)
    frames: Mapping[str, str] = field(default_factory=lambda: {"accel": ACCEL_FRAME, "mag": MAG_FRAME})
    warnings: tuple[str, ...] = ()
    accel_cal_periods: tuple[tuple[float, float], ...] = ()
    board_rotation: np.ndarray | None = None
    accel_cal_without_imu: tuple[tuple[float, float], ...] = ()
    cal_origin: Mapping[str, str] = field(default_factory=dict)
    cal_missing: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def accel_instances(self) -> list[int]:
        return [s.instance for s in self.accel]

    def mag_instances(self) -> list[int]:
        return [s.instance for s in self.mag]

    def get(self, sensor: str, instance: int = 0) -> SensorSeries | None:
        for s in {"accel": self.accel, "mag": self.mag, "gyro": self.gyro}[sensor]:
            if s.instance == instance:
                return s
        return None

    @property
    def time_span_s(self) -> tuple[float, float]:
        ts = [s.time_s for s in self.accel + self.mag if len(s)]
        if not ts:
            return (0.0, 0.0)
        return (float(min(t[0] for t in ts)), float(max(t[-1] for t in ts)))
