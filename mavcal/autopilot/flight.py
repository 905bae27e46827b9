"""The compass's in-flight compensation in force (motor interference model) of a recording.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.flight`, which holds its ArduPilot implementation."""
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
