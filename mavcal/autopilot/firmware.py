"""ArduPilot's calibration form (AccelCal, CompassCal: offsets, scale, soft iron, orientation) and how it
corrects a reading; the common form the pipeline judges every autopilot's calibration in (PX4's
:mod:`mavcal.px4.firmware` converts to it with ``ardupilot_form``).

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.firmware`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
from __future__ import annotations

from mavcal.ardupilot.firmware import (
    COMPASS_MAX_SCALE,
    COMPASS_MIN_SCALE,
    GRAVITY_MSS,
    MAX_COMPASSES,
    MAX_IMUS,
    AccelCal,
    AccelNames,
    BoardNames,
    CompassCal,
    CompassNames,
    GyroNames,
    Names3,
    accel_cal_from_params,
    accel_param_names,
    accel_param_values,
    apply_accel,
    apply_compass,
    board_param_names,
    compass_cal_from_params,
    compass_param_names,
    compass_param_values,
    custom_rotation_angles,
    effective_scale,
    gyro_param_names,
    param_value_plausible,
    soft_iron_matrix,
    undo_accel,
    undo_compass,
)

__all__ = ["AccelCal", "AccelNames", "BoardNames", "COMPASS_MAX_SCALE", "COMPASS_MIN_SCALE", "CompassCal",
           "CompassNames", "GRAVITY_MSS", "GyroNames", "MAX_COMPASSES", "MAX_IMUS", "Names3",
           "accel_cal_from_params", "accel_param_names", "accel_param_values", "apply_accel",
           "apply_compass", "board_param_names", "compass_cal_from_params", "compass_param_names",
           "compass_param_values", "custom_rotation_angles", "effective_scale", "gyro_param_names",
           "param_value_plausible", "soft_iron_matrix", "undo_accel", "undo_compass"]
