"""What the writer needs to know about a parameter name: vector groups, reboot, force-saves.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.protocol`, which holds its ArduPilot implementation."""
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
