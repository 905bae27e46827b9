"""ArduPilot's ``Rotation`` enum as rotation matrices.

Convention (AP_Math ``Vector3::rotate`` / ``Matrix3::from_euler``): "rotate v by rotation r"
means ``v' = R(r) @ v`` with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (3-2-1 Euler, roll
applied to the vector first). ``rotate_inverse`` applies ``R.T``. Example: ``YAW_90`` maps
(x, y, z) to (-y, x, z).

The angles of every enum value come from ArduPilot's ``AP_Math/tests/test_rotations.cpp``
(each value is tested there to equal ``from_euler(roll, pitch, yaw)``); 38 is the Solo leg
compass rotation (90, 68.8, 293.3). 101/102 are the custom rotations ``CUST_ROT1_*`` /
``CUST_ROT2_*`` (degrees, same Euler convention), which the caller must supply.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = [
    "ROTATIONS",
    "ROTATION_NAMES",
    "AUTO_ROTATION_SKIP",
    "CUSTOM_1",
    "CUSTOM_2",
    "euler_to_matrix",
    "matrix_to_euler",
    "rotation_matrix",
    "nearest_rotation",
    "is_valid_rotation",
]

CUSTOM_OLD = 100
CUSTOM_1 = 101
CUSTOM_2 = 102

# value -> (name, roll_deg, pitch_deg, yaw_deg)
_TABLE: dict[int, tuple[str, float, float, float]] = {
    0: ("NONE", 0, 0, 0),
    1: ("YAW_45", 0, 0, 45),
    2: ("YAW_90", 0, 0, 90),
    3: ("YAW_135", 0, 0, 135),
    4: ("YAW_180", 0, 0, 180),
    5: ("YAW_225", 0, 0, 225),
    6: ("YAW_270", 0, 0, 270),
    7: ("YAW_315", 0, 0, 315),
    8: ("ROLL_180", 180, 0, 0),
    9: ("ROLL_180_YAW_45", 180, 0, 45),
    10: ("ROLL_180_YAW_90", 180, 0, 90),
    11: ("ROLL_180_YAW_135", 180, 0, 135),
    12: ("PITCH_180", 0, 180, 0),
    13: ("ROLL_180_YAW_225", 180, 0, 225),
    14: ("ROLL_180_YAW_270", 180, 0, 270),
    15: ("ROLL_180_YAW_315", 180, 0, 315),
    16: ("ROLL_90", 90, 0, 0),
    17: ("ROLL_90_YAW_45", 90, 0, 45),
    18: ("ROLL_90_YAW_90", 90, 0, 90),
    19: ("ROLL_90_YAW_135", 90, 0, 135),
    20: ("ROLL_270", 270, 0, 0),
    21: ("ROLL_270_YAW_45", 270, 0, 45),
    22: ("ROLL_270_YAW_90", 270, 0, 90),
    23: ("ROLL_270_YAW_135", 270, 0, 135),
    24: ("PITCH_90", 0, 90, 0),
    25: ("PITCH_270", 0, 270, 0),
    26: ("PITCH_180_YAW_90", 0, 180, 90),
    27: ("PITCH_180_YAW_270", 0, 180, 270),
    28: ("ROLL_90_PITCH_90", 90, 90, 0),
    29: ("ROLL_180_PITCH_90", 180, 90, 0),
    30: ("ROLL_270_PITCH_90", 270, 90, 0),
    31: ("ROLL_90_PITCH_180", 90, 180, 0),
    32: ("ROLL_270_PITCH_180", 270, 180, 0),
    33: ("ROLL_90_PITCH_270", 90, 270, 0),
    34: ("ROLL_180_PITCH_270", 180, 270, 0),
    35: ("ROLL_270_PITCH_270", 270, 270, 0),
    36: ("ROLL_90_PITCH_180_YAW_90", 90, 180, 90),
    37: ("ROLL_90_YAW_270", 90, 0, 270),
    38: ("ROLL_90_PITCH_68_YAW_293", 90, 68.8, 293.3),
    39: ("PITCH_315", 0, 315, 0),
    40: ("ROLL_90_PITCH_315", 90, 315, 0),
    41: ("PITCH_7", 0, 7, 0),
    42: ("ROLL_45", 45, 0, 0),
    43: ("ROLL_315", 315, 0, 0),
}

#: Values ArduPilot's compass auto-rotation never proposes: 26/27 duplicate 14/10, 38 is the
#: Solo leg compass, 41 is "too close to NONE" (``CompassCalibrator::calculate_orientation``).
AUTO_ROTATION_SKIP = frozenset({26, 27, 38, 41})

ROTATION_NAMES: dict[int, str] = {k: v[0] for k, v in _TABLE.items()}
ROTATION_NAMES[CUSTOM_OLD] = "CUSTOM_OLD"
ROTATION_NAMES[CUSTOM_1] = "CUSTOM_1"
ROTATION_NAMES[CUSTOM_2] = "CUSTOM_2"

#: Euler angles (roll, pitch, yaw) in degrees of every standard value 0..43.
ROTATIONS: dict[int, tuple[float, float, float]] = {k: (float(v[1]), float(v[2]), float(v[3]))
                                                    for k, v in _TABLE.items()}


def euler_to_matrix(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """ArduPilot ``Matrix3::from_euler``: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Parameters
    ----------
    roll_rad, pitch_rad, yaw_rad : float or array
        Angles in radians; arrays (broadcast together) give one matrix per element.

    Returns
    -------
    (3, 3) array, or (..., 3, 3) for array angles
        Rotation matrix; ``R @ v`` rotates a body vector to the reference frame.
    """
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    rows = ((cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy),
            (cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy),
            (-sp, sr * cp, cr * cp))
    return np.stack([np.stack(np.broadcast_arrays(*row), axis=-1) for row in rows], axis=-2).astype(float)


def matrix_to_euler(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`euler_to_matrix` (ArduPilot ``Matrix3::to_euler``), radians.

    Pitch is in [-pi/2, pi/2]; roll and yaw in (-pi, pi].
    """
    R = np.asarray(R, dtype=float)
    pitch = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return float(roll), float(pitch), float(yaw)


def _clean(R: np.ndarray) -> np.ndarray:
    # exact zeros and ones for right-angle rotations (sin(pi) = 1.2e-16)
    R = np.where(np.abs(R) < 1e-12, 0.0, R)
    R = np.where(np.abs(np.abs(R) - 1.0) < 1e-12, np.sign(R), R)
    return R


_MATRICES: dict[int, np.ndarray] = {}
for _k, (_r, _p, _y) in ROTATIONS.items():
    _m = _clean(euler_to_matrix(*np.radians([_r, _p, _y])))
    _m.setflags(write=False)
    _MATRICES[_k] = _m


def is_valid_rotation(value: int) -> bool:
    """True for 0..43, 101 and 102 (values a parameter may hold and mavcal can apply)."""
    return int(value) in _MATRICES or int(value) in (CUSTOM_1, CUSTOM_2)


def rotation_matrix(value: int, custom: Sequence[float] | None = None) -> np.ndarray:
    """Matrix of ArduPilot rotation ``value``.

    Parameters
    ----------
    value : int
        Rotation enum 0..43, or 101/102 (custom).
    custom : (roll_deg, pitch_deg, yaw_deg), optional
        The ``CUST_ROTn_ROLL/PIT/YAW`` angles; required for 101/102.

    Returns
    -------
    (3, 3) read-only array ``R`` with ``rotated = R @ v``.

    Raises
    ------
    ValueError
        Unknown value, 100 (deprecated, converted at boot by the firmware), or a custom
        rotation without angles.
    """
    v = int(round(float(value)))
    if v in _MATRICES:
        return _MATRICES[v]
    if v in (CUSTOM_1, CUSTOM_2):
        if custom is None:
            raise ValueError(f"rotation {v} (custom) needs the CUST_ROT{v - 100}_ROLL/PIT/YAW angles")
        m = euler_to_matrix(*np.radians(np.asarray(custom, dtype=float)))
        m.setflags(write=False)
        return m
    if v == CUSTOM_OLD:
        raise ValueError("rotation 100 (CUSTOM_OLD) is converted to 101/102 by the firmware at boot; "
                         "give the converted value")
    raise ValueError(f"unknown ArduPilot rotation {value!r} (valid: 0..43, 101, 102)")


def rotation_angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    """Angle in degrees of the rotation ``A @ B.T`` (how far apart two rotations are)."""
    c = (np.trace(np.asarray(A) @ np.asarray(B).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def nearest_rotation(R: np.ndarray, include_skipped: bool = False) -> tuple[int, float]:
    """Standard rotation closest to matrix ``R``.

    Parameters
    ----------
    R : (3, 3) array
        A rotation (need not be exactly orthonormal).
    include_skipped : bool
        By default the values ArduPilot's auto-rotation skips (26, 27, 38, 41, see
        :data:`AUTO_ROTATION_SKIP`) are not candidates, so a duplicate matrix resolves to
        the canonical 10/14 and near-identity matrices to NONE rather than PITCH_7.

    Returns
    -------
    (value, angle_error_deg)
    """
    R = np.asarray(R, dtype=float)
    best, best_ang = 0, np.inf
    for k, m in _MATRICES.items():
        if not include_skipped and k in AUTO_ROTATION_SKIP:
            continue
        a = rotation_angle_deg(R, m)
        if a < best_ang - 1e-9:
            best, best_ang = k, a
    return best, float(best_ang)
