"""The limits a calibration is checked against before it is written (``apply``/``restore``/the writer).

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.limits`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
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
