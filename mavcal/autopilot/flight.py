"""The compass's in-flight compensation in force (motor interference model) of a recording.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.flight`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
from __future__ import annotations

from mavcal.ardupilot.flight import (
    COMPENSATION_CURRENT,
    COMPENSATION_OFF,
    COMPENSATION_THROTTLE,
    MOTCT,
    InForce,
    compass_in_use,
    in_force,
    motor_param_values,
    motor_type,
    motor_type_value,
    offset_names,
    raw_field,
)

__all__ = ["COMPENSATION_CURRENT", "COMPENSATION_OFF", "COMPENSATION_THROTTLE",
           "InForce", "MOTCT", "compass_in_use", "in_force", "motor_param_values", "motor_type",
           "motor_type_value", "offset_names", "raw_field"]
