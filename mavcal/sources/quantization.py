"""Undo the bias of integer telemetry truncated toward zero.

ArduPilot casts RAW_IMU / SCALED_IMU{,2,3} readings to int16 (milli-g, mrad/s, mGauss) and
DataFlash MAG fields to int16 mGauss by truncation toward zero: every reading is biased
by up to one unit toward zero, about half a unit on average when the noise spans a unit or
more. Adding half a unit away from zero to every non-zero reading removes that bias (the
remaining error is a zero-mean quantisation error of +-0.5 unit). A tool that wants to beat
the onboard calibration (which works on float samples) must do this: at 1 mGauss the bias is
a 0.5 mGauss offset error on every axis.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from mavcal.core.constants import GRAVITY_MPS2
from mavcal.sources.types import ImuLog, SensorSeries

# message -> sensor -> telemetry unit in the series' units
TRUNCATED_UNITS: dict[str, dict[str, float]] = {
    **{m: {"accel": GRAVITY_MPS2 / 1000.0, "gyro": 1e-3, "mag": 1.0}
       for m in ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")},
    **{m: {"mag": 1.0} for m in ("MAG", "MAG2", "MAG3")},
}


def quantization_step(series: SensorSeries) -> float:
    """The integer step of the series' readings (0 for float data)."""
    return TRUNCATED_UNITS.get(series.message, {}).get(series.sensor, 0.0)


def untruncate(series: SensorSeries) -> SensorSeries:
    """The series with half a unit added away from zero to every non-zero integer reading."""
    q = quantization_step(series)
    if q == 0.0:
        return series
    v = np.asarray(series.values)
    return replace(series, values=v + 0.5 * q * np.sign(v))


def untruncate_log(log: ImuLog) -> tuple[ImuLog, int]:
    """Apply :func:`untruncate` to every series of ``log``; returns (log, series changed)."""
    out, n = [], 0
    for s in log.series:
        t = untruncate(s)
        n += t is not s
        out.append(t)
    return replace(log, series=tuple(out)), n
