"""PX4's calibration parameter names, slots and types (the single place that spells them).

Read in PX4's ``src/lib/sensor_calibration/Utilities.cpp`` (``CAL_%s%u_ID`` slots searched
for the sensor's device id, ``CAL_%s%u_%c%s`` for the X/Y/Z vectors) and the parameter
metadata of the PX4 build in ``../shared/px4`` (``etc/extras/parameters.json.xz``):

* accelerometer slot n (0..3): ``CAL_ACCn_ID`` (device id, INT32), ``_PRIO``, ``_ROT`` (INT32),
  ``_{X,Y,Z}OFF`` (m/s^2), ``_{X,Y,Z}SCALE`` (0.1..3.0);
* magnetometer slot n: ``CAL_MAGn_ID``, ``_PRIO``, ``_ROT`` (-1 internal, 0..40, 100 custom
  Euler angles ``_ROLL``/``_PITCH``/``_YAW`` in degrees), ``_{X,Y,Z}OFF`` (gauss),
  ``_{X,Y,Z}SCALE`` (0.1..3.0), ``_{X,Y,Z}ODIAG``, ``_{X,Y,Z}COMP`` (power compensation);
* the board: ``SENS_BOARD_ROT`` (INT32) and ``SENS_BOARD_{X,Y,Z}_OFF`` (degrees);
  thermal compensation ``TC_A_ENABLE`` / ``TC_M_ENABLE``; ``CAL_MAG_COMP_TYP``.

A slot applies to the sensor whose device id is in its ``_ID``, whatever the topic instance.
"""
from __future__ import annotations

import re
from collections.abc import Container, Mapping
from typing import TypedDict

__all__ = ["DETOUR_STEP", "DETOUR_DWELL_S", "calibration_vector", "detoured_order", "MAX_SLOTS", "SCALE_RANGE",
           "ROT_INTERNAL", "ROT_CUSTOM", "AccelNames", "MagNames", "accel_names",
           "mag_names", "board_names", "is_int32", "find_slot", "free_slot", "device_ids", "is_px4_params",
           "is_calibration",
           "THERMAL_ACCEL", "THERMAL_MAG", "MAG_COMP_TYPE", "MAG_AUTOCAL"]

MAX_SLOTS = 4
SCALE_RANGE = (0.1, 3.0)
ROT_INTERNAL = -1
ROT_CUSTOM = 100
THERMAL_ACCEL = "TC_A_ENABLE"
THERMAL_MAG = "TC_M_ENABLE"
MAG_COMP_TYPE = "CAL_MAG_COMP_TYP"
MAG_AUTOCAL = "SENS_MAG_AUTOCAL"
_XYZ = ("X", "Y", "Z")
#: how far the detour of a changed CAL_* vector's pivot lies from its target (see detoured_order). PX4's
#: calibration library (src/lib/sensor_calibration: ``set_offset``, ``set_scale``, ``set_offdiagonal``)
#: takes a changed vector (OFF, SCALE, ODIAG) into use only when it differs from the one in use by more
#: than a threshold (Euclidean norm): seen on the PX4 SITL (main, August 2026) 0.005 gauss for
#: magnetometer offsets and 0.01 for scales and off-diagonals (0.01 for all in older sources), each
#: vector on its own, the values reading back new either way. The step exceeds twice any of them.
DETOUR_STEP = 0.1
#: seconds PX4 gets to see the detours (a parameter update: it looks at its sensors' rate) before the rest
DETOUR_DWELL_S = 0.3
_VECTOR = re.compile(r"^(CAL_(?:ACC|MAG)[0-9]_)([XYZ])(OFF|SCALE|ODIAG)$")

Names3 = tuple[str, str, str]


class AccelNames(TypedDict):
    id: str
    prio: str
    rot: str
    ofs: Names3
    scale: Names3


class MagNames(TypedDict):
    id: str
    prio: str
    rot: str
    ofs: Names3
    scale: Names3
    odiag: Names3
    comp: Names3
    custom: Names3


def _vec(prefix: str, suffix: str) -> Names3:
    return (f"{prefix}{_XYZ[0]}{suffix}", f"{prefix}{_XYZ[1]}{suffix}", f"{prefix}{_XYZ[2]}{suffix}")


def _check(slot: int) -> None:
    if not 0 <= int(slot) < MAX_SLOTS:
        raise ValueError(f"PX4 calibration slot {slot} out of range 0..{MAX_SLOTS - 1}")


def accel_names(slot: int) -> AccelNames:
    """``CAL_ACC<slot>_*``."""
    _check(slot)
    p = f"CAL_ACC{int(slot)}_"
    return AccelNames(id=p + "ID", prio=p + "PRIO", rot=p + "ROT", ofs=_vec(p, "OFF"), scale=_vec(p, "SCALE"))


def mag_names(slot: int) -> MagNames:
    """``CAL_MAG<slot>_*``."""
    _check(slot)
    p = f"CAL_MAG{int(slot)}_"
    return MagNames(id=p + "ID", prio=p + "PRIO", rot=p + "ROT", ofs=_vec(p, "OFF"), scale=_vec(p, "SCALE"),
                    odiag=_vec(p, "ODIAG"), comp=_vec(p, "COMP"), custom=(p + "ROLL", p + "PITCH", p + "YAW"))


def board_names() -> tuple[str, Names3]:
    """(``SENS_BOARD_ROT``, ``SENS_BOARD_{X,Y,Z}_OFF``)."""
    return "SENS_BOARD_ROT", ("SENS_BOARD_X_OFF", "SENS_BOARD_Y_OFF", "SENS_BOARD_Z_OFF")


def is_int32(name: str) -> bool:
    """Whether PX4 keeps ``name`` as an INT32 (sent bytewise in PARAM_VALUE / PARAM_SET)."""
    return name.endswith(("_ID", "_ROT", "_PRIO")) or name in (board_names()[0], THERMAL_ACCEL, THERMAL_MAG,
                                                               MAG_COMP_TYPE, MAG_AUTOCAL)


def _names(kind: str, slot: int):
    return accel_names(slot) if kind == "accel" else mag_names(slot)


def find_slot(params: Mapping[str, float], kind: str, device_id: int) -> int | None:
    """The slot whose ``_ID`` is ``device_id`` (PX4's ``FindCurrentCalibrationIndex``), or None."""
    if not device_id:
        return None
    for k in range(MAX_SLOTS):
        v = params.get(_names(kind, k)["id"])
        if v is not None and int(v) & 0xFFFFFFFF == int(device_id) & 0xFFFFFFFF:
            return k
    return None


def free_slot(params: Mapping[str, float], kind: str) -> int | None:
    """The first slot whose ``_ID`` is 0 (where PX4's own calibration would store a new device)."""
    for k in range(MAX_SLOTS):
        n = _names(kind, k)["id"]
        if n in params and int(params[n]) == 0:
            return k
    return None


def device_ids(params: Mapping[str, float], kind: str) -> dict[int, int]:
    """slot -> device id of every non-empty slot."""
    out = {}
    for k in range(MAX_SLOTS):
        v = params.get(_names(kind, k)["id"])
        if v:
            out[k] = int(v) & 0xFFFFFFFF
    return out


def is_calibration(name: str) -> bool:
    """Whether ``name`` is a calibration or board-mounting parameter (``CAL_*``, ``SENS_BOARD_*``)."""
    return name.startswith(("CAL_", "SENS_BOARD_"))


def is_px4_params(names: Container[str]) -> bool:
    """Whether a set of parameter names is PX4's (it holds a calibration slot id or the board rotation)."""
    return board_names()[0] in names or accel_names(0)["id"] in names or mag_names(0)["id"] in names


def calibration_vector(name: str) -> Names3 | None:
    """The three names of the CAL_* vector ``name`` belongs to (``CAL_MAG0_YODIAG`` -> X/Y/Z ODIAG), or None."""
    m = _VECTOR.match(name)
    return _vec(m.group(1), m.group(3)) if m else None


def detoured_order(changes: Mapping[str, float]) -> tuple[dict[str, float], dict[str, float]]:
    """The order in which to send ``changes`` to PX4 so that each changed CAL_* vector is taken into use
    whole, and the detours to send before them.

    PX4 compares each vector with the one in use at every parameter change and ignores a difference
    up to a threshold (see :data:`DETOUR_STEP`): written one component at a time, a vector's last small
    change is left out of use although it reads back new (seen on the PX4 SITL: a 0.004 change of
    ``CAL_MAG0_ZODIAG`` alone, 2 mGauss; in a calibration's write, 0.3 deg of heading). So one component
    of each vector (its pivot: the first one changed) is first sent :data:`DETOUR_STEP` away from its
    target (towards the default, 0 or 1), and its target last, after the vector's other components:
    whatever PX4 held before, the pivot in use is then within a threshold of the detour, so the last
    change exceeds the threshold and PX4 takes the whole vector as written. The caller lets PX4 see the
    detours (a parameter update) before the rest follows.

    Returns
    -------
    (dict, dict)
        ``changes`` reordered (each pivot right after the last other component of its vector) and
        ``{pivot name: detour value}``. Names that are not CAL_* vectors keep their place.
    """
    groups: dict[Names3, list[str]] = {}
    for n in changes:
        g = calibration_vector(n)
        if g is not None:
            groups.setdefault(g, []).append(n)
    out: dict[str, float] = {}
    for n, v in changes.items():
        g = calibration_vector(n)
        members = groups[g] if g is not None else [n]
        if len(members) > 1 and n == members[0]:
            continue  # the pivot goes last
        out[n] = float(v)
        if len(members) > 1 and n == members[-1]:
            out[members[0]] = float(changes[members[0]])
    detours = {}
    for g, members in groups.items():
        t, default = float(changes[members[0]]), 1.0 if g[0].endswith("SCALE") else 0.0
        detours[members[0]] = t - DETOUR_STEP if t > default else t + DETOUR_STEP
    return out, detours
