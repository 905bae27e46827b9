"""How a calibration is judged as attitude: the attitude grid and the tilt/heading errors it leaves.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.evaluate`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
from __future__ import annotations

from mavcal.ardupilot.evaluate import (
    G0,
    AttitudeErrors,
    GridErrors,
    attitude_errors,
    attitude_grid,
    body_vectors,
    heading_errors_deg,
    max_errors_deg,
)

__all__ = ["AttitudeErrors", "G0", "GridErrors", "attitude_errors", "attitude_grid", "body_vectors",
           "heading_errors_deg", "max_errors_deg"]
