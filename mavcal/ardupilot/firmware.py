"""How ArduPilot applies its sensor calibration, forward and inverse (pure numpy).

Compass (``AP_Compass_Backend::rotate_field`` then ``correct_field``), per sample::

    b         = R_mount @ s                      # body frame after orientation
    corrected = M @ (k * (b + OFS)) + motor_ofs

``R_mount`` is ``COMPASS_ORIENTn`` for an external compass and ``AHRS_ORIENTATION`` for an
internal one; ``k = COMPASS_SCALEn`` only when it lies in [1/1.5, 1.5], else 1; ``M`` is the
symmetric DIA/ODI matrix, skipped entirely (ODI included) when DIA is all zero;
``motor_ofs`` is the motor compensation the firmware added (logged as MAG.MOX/MOY/MOZ).
The inverse gives the body-frame field after orientation::

    b = (1/k) * M^-1 @ (corrected - motor_ofs) - OFS

Accelerometer (``AP_InertialSensor_Backend::_rotate_and_correct_accel``), per sample::

    body = R_A @ (S * (u - OFS))        # u: board-frame raw, S = INS_ACCSCAL, R_A = AHRS_ORIENTATION
    u    = (R_A.T @ body) / S + OFS

While an accelerometer calibration runs the firmware skips the offsets and scale but still
applies ``R_A`` (``calibrating=True`` below).

Only :mod:`mavcal.ardupilot` knows parameter names; the ``*_param_names`` functions are
the single place that spells them.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import TypedDict

import numpy as np

from mavcal.autopilot.calform import (  # noqa: F401  (re-exported: the form is the neutral layer's)
    COMPASS_MAX_SCALE,
    COMPASS_MIN_SCALE,
    AccelCal,
    CompassCal,
    apply_accel,
    apply_compass,
    effective_scale,
    soft_iron_matrix,
    undo_accel,
    undo_compass,
)
from mavcal.autopilot.rotations import CUSTOM_1, CUSTOM_2, is_valid_rotation
from mavcal.core.constants import GRAVITY_MPS2

__all__ = [
    "GRAVITY_MSS",
    "COMPASS_MIN_SCALE",
    "COMPASS_MAX_SCALE",
    "MAX_COMPASSES",
    "MAX_IMUS",
    "param_value_plausible",
    "compass_param_names",
    "accel_param_names",
    "gyro_param_names",
    "board_param_names",
    "CompassCal",
    "AccelCal",
    "soft_iron_matrix",
    "effective_scale",
    "apply_compass",
    "undo_compass",
    "apply_accel",
    "undo_accel",
    "compass_cal_from_params",
    "accel_cal_from_params",
    "custom_rotation_angles",
    "compass_param_values",
    "accel_param_values",
]

GRAVITY_MSS = GRAVITY_MPS2  # ArduPilot's name for the one constant
MAX_COMPASSES = 3
MAX_IMUS = 5
_XYZ = ("X", "Y", "Z")


# --------------------------------------------------------------------------- names

Names3 = tuple[str, str, str]


class CompassNames(TypedDict):
    """The parameter names of one compass slot (see :func:`compass_param_names`)."""

    ofs: Names3
    dia: Names3
    odi: Names3
    mot: Names3
    scale: str
    orient: str
    external: str
    dev_id: str
    prio_id: str
    use: str


class AccelNames(TypedDict):
    """The parameter names of one accelerometer (see :func:`accel_param_names`)."""

    ofs: Names3
    scale: Names3
    id: str


class GyroNames(TypedDict):
    """The parameter names of one gyroscope (see :func:`gyro_param_names`)."""

    ofs: Names3
    id: str


class BoardNames(TypedDict):
    """Vehicle-wide names (see :func:`board_param_names`)."""

    orientation: str
    custom1: Names3
    custom2: Names3
    trim: Names3
    motct: str


def _xyz(prefix: str) -> Names3:
    return (f"{prefix}_X", f"{prefix}_Y", f"{prefix}_Z")


def compass_param_names(instance: int) -> CompassNames:
    """Parameter names of compass ``instance`` (0-based priority/state slot).

    Returns
    -------
    dict with keys ``ofs``, ``dia``, ``odi``, ``mot`` (tuples of 3 names, X/Y/Z),
    ``scale``, ``orient``, ``external``, ``dev_id``, ``prio_id``, ``use`` (single names).

    Examples
    --------
    >>> compass_param_names(1)["ofs"]
    ('COMPASS_OFS2_X', 'COMPASS_OFS2_Y', 'COMPASS_OFS2_Z')
    """
    k = int(instance)
    if not 0 <= k < MAX_COMPASSES:
        raise ValueError(f"compass instance must be 0..{MAX_COMPASSES - 1}, got {instance}")
    s = "" if k == 0 else str(k + 1)
    return {
        "ofs": _xyz(f"COMPASS_OFS{s}"),
        "dia": _xyz(f"COMPASS_DIA{s}"),
        "odi": _xyz(f"COMPASS_ODI{s}"),
        "mot": _xyz(f"COMPASS_MOT{s}"),
        "scale": f"COMPASS_SCALE{s}",
        "orient": f"COMPASS_ORIENT{s}",
        "external": "COMPASS_EXTERNAL" if k == 0 else f"COMPASS_EXTERN{k + 1}",
        "dev_id": f"COMPASS_DEV_ID{s}",
        "prio_id": f"COMPASS_PRIO{k + 1}_ID",
        "use": f"COMPASS_USE{s}",
    }


def accel_param_names(instance: int) -> AccelNames:
    """Parameter names of accelerometer ``instance`` (0-based IMU index).

    Returns
    -------
    dict with keys ``ofs``, ``scale`` (tuples of 3 names) and ``id``.

    Examples
    --------
    >>> accel_param_names(0)["ofs"][0], accel_param_names(2)["scale"][1], accel_param_names(3)["ofs"][2]
    ('INS_ACCOFFS_X', 'INS_ACC3SCAL_Y', 'INS4_ACCOFFS_Z')
    """
    i = int(instance)
    if not 0 <= i < MAX_IMUS:
        raise ValueError(f"accel instance must be 0..{MAX_IMUS - 1}, got {instance}")
    if i == 0:
        ofs, scal, ident = "INS_ACCOFFS", "INS_ACCSCAL", "INS_ACC_ID"
    elif i < 3:
        ofs, scal, ident = f"INS_ACC{i + 1}OFFS", f"INS_ACC{i + 1}SCAL", f"INS_ACC{i + 1}_ID"
    else:
        ofs, scal, ident = f"INS{i + 1}_ACCOFFS", f"INS{i + 1}_ACCSCAL", f"INS{i + 1}_ACC_ID"
    return {
        "ofs": _xyz(ofs),
        "scale": _xyz(scal),
        "id": ident,
    }


def gyro_param_names(instance: int) -> GyroNames:
    """Parameter names of gyroscope ``instance`` (0-based IMU index), as
    :func:`accel_param_names` for the accelerometer of the same IMU.

    Returns
    -------
    dict with keys ``ofs`` (tuple of 3 names, X/Y/Z) and ``id``.

    Examples
    --------
    >>> gyro_param_names(0)["ofs"][0], gyro_param_names(1)["id"], gyro_param_names(3)["ofs"][2]
    ('INS_GYROFFS_X', 'INS_GYR2_ID', 'INS4_GYROFFS_Z')
    """
    i = int(instance)
    if not 0 <= i < MAX_IMUS:
        raise ValueError(f"gyro instance must be 0..{MAX_IMUS - 1}, got {instance}")
    if i == 0:
        ofs, ident = "INS_GYROFFS", "INS_GYR_ID"
    elif i < 3:
        ofs, ident = f"INS_GYR{i + 1}OFFS", f"INS_GYR{i + 1}_ID"
    else:
        ofs, ident = f"INS{i + 1}_GYROFFS", f"INS{i + 1}_GYR_ID"
    return {"ofs": _xyz(ofs), "id": ident}


def board_param_names() -> BoardNames:
    """Vehicle-wide names: ``orientation`` (AHRS_ORIENTATION), ``custom1``/``custom2``
    (CUST_ROTn_ROLL/PIT/YAW), ``trim`` (AHRS_TRIM_X/Y/Z), ``motct`` (COMPASS_MOTCT)."""
    return {
        "orientation": "AHRS_ORIENTATION",
        "custom1": ("CUST_ROT1_ROLL", "CUST_ROT1_PITCH", "CUST_ROT1_YAW"),
        "custom2": ("CUST_ROT2_ROLL", "CUST_ROT2_PITCH", "CUST_ROT2_YAW"),
        "trim": ("AHRS_TRIM_X", "AHRS_TRIM_Y", "AHRS_TRIM_Z"),
        "motct": "COMPASS_MOTCT",
    }


def _orientation_names() -> frozenset[str]:
    return frozenset([board_param_names()["orientation"]]
                     + [compass_param_names(k)["orient"] for k in range(MAX_COMPASSES)])


_ORIENTATION_NAMES = _orientation_names()


def param_value_plausible(name: str, value: float) -> bool:
    """False for a value no ArduPilot firmware can hold (a damaged log record): not a finite
    number, or a rotation parameter (AHRS_ORIENTATION, COMPASS_ORIENTn) that is not one of
    the rotations mavcal can apply (0..43, 101, 102).

    Examples
    --------
    >>> param_value_plausible("AHRS_ORIENTATION", 109), param_value_plausible("AHRS_ORIENTATION", 2)
    (False, True)
    """
    v = float(value)
    if not np.isfinite(v):
        return False
    if name in _ORIENTATION_NAMES:
        return v == round(v) and abs(v) < 1e6 and is_valid_rotation(int(v))
    return True


# --------------------------------------------------------------------------- from params

def custom_rotation_angles(params: Mapping[str, float], orient: int) -> tuple[float, float, float] | None:
    """CUST_ROTn_ROLL/PIT/YAW (degrees) for ``orient`` 101/102, None otherwise or if missing."""
    o = int(round(float(orient)))
    if o not in (CUSTOM_1, CUSTOM_2):
        return None
    names = board_param_names()["custom1" if o == CUSTOM_1 else "custom2"]
    if not all(n in params for n in names):
        return None
    return tuple(float(params[n]) for n in names)  # type: ignore[return-value]


def _get3(params: Mapping[str, float], names, default) -> tuple[tuple[float, float, float], list[str]]:
    out, missing = [], []
    for n, d in zip(names, default):
        if n in params and params[n] is not None and np.isfinite(params[n]):
            out.append(float(params[n]))
        else:
            out.append(float(d))
            missing.append(n)
    return (out[0], out[1], out[2]), missing


def compass_cal_from_params(params: Mapping[str, float], instance: int,
                            missing: list[str] | None = None) -> CompassCal:
    """Build the :class:`CompassCal` of compass ``instance`` from a name -> value mapping.

    Missing parameters take the firmware defaults (OFS 0, DIA 1, ODI 0, SCALE 1, ORIENT 0,
    AHRS_ORIENTATION 0); their names are appended to ``missing`` if a list is given. The
    mounting rotation is COMPASS_ORIENTn for an external compass (COMPASS_EXTERNn != 0) and
    AHRS_ORIENTATION for an internal one; when COMPASS_EXTERNn is missing the compass is
    taken as external if COMPASS_ORIENTn != 0, else internal.
    """
    names = compass_param_names(instance)
    miss: list[str] = []
    ofs, m = _get3(params, names["ofs"], (0.0, 0.0, 0.0))
    miss += m
    dia, m = _get3(params, names["dia"], (1.0, 1.0, 1.0))
    miss += m
    odi, m = _get3(params, names["odi"], (0.0, 0.0, 0.0))
    miss += m
    mot, _ = _get3(params, names["mot"], (0.0, 0.0, 0.0))
    scale = params.get(names["scale"])
    if scale is None:
        miss.append(names["scale"])
        scale = 1.0
    ext_v = params.get(names["external"])
    orient_v = params.get(names["orient"])
    board = params.get(board_param_names()["orientation"])
    if ext_v is None:
        external = None
        is_ext = orient_v is not None and int(round(orient_v)) != 0
    else:
        external = bool(int(round(ext_v)) != 0)
        is_ext = external
    if is_ext:
        orient = int(round(orient_v)) if orient_v is not None else 0
    else:
        orient = int(round(board)) if board is not None else 0
    if missing is not None:
        missing.extend(miss)
    return CompassCal(ofs_mgauss=ofs, dia=dia, odi=odi, scale=float(scale), orient=orient,
                      external=external, custom_deg=custom_rotation_angles(params, orient), mot=mot)


def accel_cal_from_params(params: Mapping[str, float], instance: int,
                          missing: list[str] | None = None) -> AccelCal:
    """Build the :class:`AccelCal` of IMU ``instance`` from a name -> value mapping.

    Missing parameters take the defaults (OFFS 0, SCAL 1, AHRS_ORIENTATION 0) and are
    appended to ``missing`` if given.
    """
    names = accel_param_names(instance)
    miss: list[str] = []
    ofs, m = _get3(params, names["ofs"], (0.0, 0.0, 0.0))
    miss += m
    scale, m = _get3(params, names["scale"], (1.0, 1.0, 1.0))
    miss += m
    bn = board_param_names()["orientation"]
    board = params.get(bn)
    if board is None:
        miss.append(bn)
        board = 0
    if missing is not None:
        missing.extend(miss)
    return AccelCal(ofs_mps2=ofs, scale=scale, board_orient=int(round(board)),
                    custom_deg=custom_rotation_angles(params, int(round(board))))


def compass_param_values(cal: CompassCal, instance: int) -> dict[str, float]:
    """Inverse of :func:`compass_cal_from_params` for the calibration values (OFS, DIA, ODI,
    SCALE): name -> value. ORIENT/EXTERNAL are not included (they are configuration)."""
    names = compass_param_names(instance)
    out: dict[str, float] = {}
    for keys, vals in ((names["ofs"], cal.ofs_mgauss), (names["dia"], cal.dia), (names["odi"], cal.odi)):
        for n, v in zip(keys, vals):
            out[n] = float(v)
    out[names["scale"]] = float(cal.scale)
    return out


def accel_param_values(cal: AccelCal, instance: int) -> dict[str, float]:
    """name -> value of INS_ACCnOFFS/SCAL for ``cal``."""
    names = accel_param_names(instance)
    out: dict[str, float] = {}
    for keys, vals in ((names["ofs"], cal.ofs_mps2), (names["scale"], cal.scale)):
        for n, v in zip(keys, vals):
            out[n] = float(v)
    return out
