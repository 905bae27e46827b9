"""How a calibration is judged as attitude: the attitude grid and the tilt/heading errors it leaves.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.evaluate`, which holds its ArduPilot implementation."""
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
