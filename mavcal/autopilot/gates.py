"""The gates a calibration passes before it is written, their thresholds (:class:`GateConfig`) and verdicts.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.gates`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
from __future__ import annotations

from mavcal.ardupilot.gates import (
    CAUSE_IN_FORCE,
    EARTH_FIELD_MGAUSS,
    FIT_ADVICE,
    HEADING_ADVICE,
    YES_NO_GATES,
    Gate,
    GateConfig,
    GateReport,
    SensorVerdict,
    accel_gates,
    compass_gates,
    reason_text,
)

__all__ = ["CAUSE_IN_FORCE", "EARTH_FIELD_MGAUSS", "FIT_ADVICE", "Gate", "GateConfig", "GateReport",
           "HEADING_ADVICE", "SensorVerdict", "YES_NO_GATES", "accel_gates", "compass_gates", "reason_text"]
