"""What the writer needs to know about a parameter name: vector groups, reboot, force-saves.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.protocol`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
from __future__ import annotations

from mavcal.ardupilot.protocol import (
    CUSTOM_ROTATIONS,
    MAV_CMD,
    MAV_CMD_ACCELCAL_VEHICLE_POS,
    MAV_CMD_PREFLIGHT_CALIBRATION,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    force_save_kinds,
    needs_reboot,
    valid_param_name,
    vector_group,
)

__all__ = ["CUSTOM_ROTATIONS", "MAV_CMD", "MAV_CMD_ACCELCAL_VEHICLE_POS", "MAV_CMD_PREFLIGHT_CALIBRATION",
           "MAV_CMD_SET_MESSAGE_INTERVAL", "force_save_kinds", "needs_reboot", "valid_param_name",
           "vector_group"]
