"""What the writer needs to know about ArduPilot parameter *names*.

The safe writer in :mod:`mavcal.link.writer` is name-agnostic; the few name rules it needs
live here, next to the rest of the ArduPilot knowledge:

* :func:`vector_group`: ArduPilot stores ``*_X/_Y/_Z`` calibration values as one
  ``AP_Vector3f``; a PARAM_SET of its X element makes the vehicle echo all three
  (``AP_Param::send_parameter``; Y or Z echo only themselves), so the writer must expect
  sibling echoes.
* :func:`needs_reboot`: parameters whose new value is only read at boot
  (``@RebootRequired`` and code reading, research note section 8).
* :func:`force_save_kinds`: which ``MAV_CMD_PREFLIGHT_CALIBRATION`` force-saves a set of
  changes calls for, so the device ids are stored with the new calibration (section 1.4).
"""
from __future__ import annotations

import re
from collections.abc import Iterable

from mavcal.autopilot.mavlink import (  # noqa: F401  (re-exported)
    MAV_CMD,
    MAV_CMD_ACCELCAL_VEHICLE_POS,
    MAV_CMD_PREFLIGHT_CALIBRATION,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    valid_param_name,
)

__all__ = ["vector_group", "needs_reboot", "force_save_kinds", "valid_param_name", "CUSTOM_ROTATIONS", "MAV_CMD",
           "MAV_CMD_PREFLIGHT_CALIBRATION", "MAV_CMD_SET_MESSAGE_INTERVAL", "MAV_CMD_ACCELCAL_VEHICLE_POS"]

# Vector3f parameters (prefix before _X/_Y/_Z) that hold calibration or geometry values.
_VECTOR_PREFIX_RE = re.compile(
    r"^(?:"
    r"COMPASS_(?:OFS|DIA|ODI|MOT)[23]?"          # compass offsets, soft iron, motor comp
    r"|INS_(?:ACC|GYR)[23]?OFFS"                  # accel / gyro offsets, IMU 1..3
    r"|INS_ACC[23]?SCAL"                          # accel scale, IMU 1..3
    r"|INS[45]_(?:ACC|GYR)OFFS|INS[45]_ACCSCAL"   # IMU 4/5
    r"|INS_POS[1-3]|INS[45]_POS"                  # IMU positions
    r"|AHRS_TRIM"
    r"|COMPASS_PMOT[1-4]"
    r")$"
)

#: Rotation enum values that refer to CUST_ROTn_* (AP_CustomRotations)
CUSTOM_ROTATIONS = (101, 102)

_REBOOT_RE = re.compile(
    r"^(?:COMPASS_PRIO[1-3]_ID|COMPASS_ENABLE|COMPASS_DISBLMSK|CUST_ROT_ENABLE|CUST_ROT[12]_(?:ROLL|PITCH|YAW))$"
)
_ORIENT_RE = re.compile(r"^(?:COMPASS_ORIENT[23]?|AHRS_ORIENTATION)$")


def vector_group(name: str) -> tuple[str, str, str] | None:
    """The three element names of the Vector3 parameter ``name`` belongs to, or None.

    Parameters
    ----------
    name : str
        A parameter name such as ``"COMPASS_OFS2_Y"``.

    Returns
    -------
    tuple of str or None
        ``("COMPASS_OFS2_X", "COMPASS_OFS2_Y", "COMPASS_OFS2_Z")`` for a vector element,
        None for a scalar parameter.
    """
    if len(name) < 3 or name[-2:] not in ("_X", "_Y", "_Z"):
        return None
    prefix = name[:-2]
    if not _VECTOR_PREFIX_RE.match(prefix):
        return None
    return (prefix + "_X", prefix + "_Y", prefix + "_Z")


def needs_reboot(name: str, value: float | None = None) -> bool:
    """True if a new value of ``name`` only takes effect after a reboot.

    Parameters
    ----------
    name : str
        Parameter name.
    value : float, optional
        The new value. An orientation parameter (``COMPASS_ORIENTn``, ``AHRS_ORIENTATION``)
        needs a reboot only when set to a custom rotation (101/102), because the custom
        rotation matrix is built once at boot (``AP_CustomRotations``).
    """
    if _REBOOT_RE.match(name):
        return True
    if value is not None and _ORIENT_RE.match(name):
        return int(round(value)) in CUSTOM_ROTATIONS
    return False


def force_save_kinds(names: Iterable[str]) -> tuple[str, ...]:
    """Which force-saves (``"compass"``, ``"accel"``) a set of changed parameters calls for.

    Writing ``COMPASS_*`` calibration values by PARAM_SET does not store ``COMPASS_DEV_ID``;
    ``MAV_CMD_PREFLIGHT_CALIBRATION`` param2=76 does (param5=76 for ``INS_ACC*_ID``).
    """
    kinds = []
    names = list(names)
    if any(re.match(r"^COMPASS_(?:OFS|DIA|ODI|SCALE|MOT|ORIENT|EXTERN)", n) for n in names):
        kinds.append("compass")
    if any(re.match(r"^INS[0-9]?_ACC[0-9]?(?:OFFS|SCAL)", n) for n in names):
        kinds.append("accel")
    return tuple(kinds)
