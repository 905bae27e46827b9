"""The mapping of a joint fit onto an autopilot's parameters: its result types and shared steps.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.mapping`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
from __future__ import annotations

from mavcal.ardupilot.mapping import (
    G0,
    NO_FIELD_SOURCE,
    AccelMapping,
    CompassMapping,
    ParamMapping,
    accel_frame,
    combine,
    field_correction,
    field_magnitude,
    map_accel,
    map_calibration,
    map_compass,
    merge_mappings,
    old_values,
)

__all__ = ["AccelMapping", "CompassMapping", "G0", "NO_FIELD_SOURCE", "ParamMapping",
           "accel_frame", "combine", "field_correction", "field_magnitude", "map_accel", "map_calibration",
           "map_compass", "merge_mappings", "old_values"]
