"""The limits a calibration is checked against before it is written (``apply``/``restore``/the writer).

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.limits`, which holds its ArduPilot implementation."""
from __future__ import annotations

from mavcal.ardupilot.limits import (
    ACCEL_OFFSET_MAX_MPS2,
    ACCEL_SCALE_RANGE,
    AHRS_TRIM_MAX_RAD,
    COMPASS_OFFSET_MAX_DEFAULT_MGAUSS,
    CUSTOM_ANGLE_MAX_DEG,
    DIA_RANGE,
    FIELD_RANGE_MGAUSS,
    ODI_MAX,
    LimitViolation,
    check_limits,
    compass_offset_max,
    failing_kinds,
    related_names,
    sensor_of,
)

__all__ = ["ACCEL_OFFSET_MAX_MPS2", "ACCEL_SCALE_RANGE", "AHRS_TRIM_MAX_RAD",
           "COMPASS_OFFSET_MAX_DEFAULT_MGAUSS",
           "CUSTOM_ANGLE_MAX_DEG", "DIA_RANGE", "FIELD_RANGE_MGAUSS",
           "LimitViolation", "ODI_MAX", "check_limits", "compass_offset_max", "failing_kinds",
           "related_names", "sensor_of"]
