"""PX4's ``Rotation`` enum (``src/lib/conversion/rotation.h``) as matrices.

PX4 builds each rotation as ``Dcmf(Eulerf(roll, pitch, yaw))`` from the degrees of its
``rot_lookup`` table (``rotation.cpp``, ``get_rot_matrix``): ``Rz(yaw) Ry(pitch) Rx(roll)``, the
convention of :func:`mavcal.autopilot.rotations.euler_to_matrix`. PX4's values are not
ArduPilot's beyond 37 (38 is (90, 68, 293) in whole degrees; 39.. differ), hence this table.
Every sensor rotation is preceded by the level adjustment ``SENS_BOARD_{X,Y,Z}_OFF``
(``Dcmf(GetSensorLevelAdjustment()) * get_rot_matrix(rotation)`` in the sensor_calibration
classes): :func:`sensor_rotation`.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mavcal.autopilot.rotations import euler_to_matrix, matrix_to_euler, rotation_angle_deg

__all__ = ["ROT_LOOKUP_DEG", "WRITABLE_MAX", "rotation_matrix", "sensor_rotation", "nearest_rotation",
           "euler_deg", "rotation_angle_deg"]

#: enum -> (roll, pitch, yaw) degrees, PX4's rot_lookup
ROT_LOOKUP_DEG: dict[int, tuple[int, int, int]] = dict(enumerate([
    (0, 0, 0), (0, 0, 45), (0, 0, 90), (0, 0, 135), (0, 0, 180), (0, 0, 225), (0, 0, 270), (0, 0, 315),
    (180, 0, 0), (180, 0, 45), (180, 0, 90), (180, 0, 135), (0, 180, 0), (180, 0, 225), (180, 0, 270),
    (180, 0, 315), (90, 0, 0), (90, 0, 45), (90, 0, 90), (90, 0, 135), (270, 0, 0), (270, 0, 45), (270, 0, 90),
    (270, 0, 135), (0, 90, 0), (0, 270, 0), (0, 180, 90), (0, 180, 270), (90, 90, 0), (180, 90, 0), (270, 90, 0),
    (90, 180, 0), (270, 180, 0), (90, 270, 0), (180, 270, 0), (270, 270, 0), (90, 180, 90), (90, 0, 270),
    (90, 68, 293), (0, 315, 0), (90, 315, 0), (270, 0, 180), (270, 0, 270), (0, 90, 180), (0, 9, 180),
    (0, 45, 0), (270, 0, 225), (270, 0, 315),
]))
#: the largest value the rotation parameters accept in this PX4 (parameter metadata: max 40)
WRITABLE_MAX = 40


def rotation_matrix(value: int, custom_deg: Sequence[float] | None = None) -> np.ndarray:
    """Matrix of PX4 rotation ``value`` (100: the custom Euler angles ``custom_deg``)."""
    v = int(value)
    if v == 100:
        if custom_deg is None:
            raise ValueError("PX4 rotation 100 (custom Euler angles) needs its roll, pitch and yaw")
        return euler_to_matrix(*np.radians(np.asarray(custom_deg, dtype=float)))
    if v not in ROT_LOOKUP_DEG:
        raise ValueError(f"unknown PX4 rotation {value!r} (valid: 0..{max(ROT_LOOKUP_DEG)}, 100)")
    return euler_to_matrix(*np.radians(ROT_LOOKUP_DEG[v]))


def sensor_rotation(value: int, level_deg: Sequence[float], custom_deg: Sequence[float] | None = None) -> np.ndarray:
    """``L @ R(value)``: the rotation PX4 applies to a sensor, after the level adjustment
    ``L`` = Euler(``SENS_BOARD_{X,Y,Z}_OFF``)."""
    return euler_to_matrix(*np.radians(np.asarray(level_deg, dtype=float))) @ rotation_matrix(value, custom_deg)


def nearest_rotation(R: np.ndarray, level_deg: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple[int, float]:
    """The writable rotation (0..40) whose ``L @ R(value)`` is closest to ``R``: (value, degrees apart)."""
    L = euler_to_matrix(*np.radians(np.asarray(level_deg, dtype=float)))
    best, err = 0, np.inf
    for v in range(WRITABLE_MAX + 1):
        e = rotation_angle_deg(L @ rotation_matrix(v), R)
        if e < err - 1e-9:
            best, err = v, e
    return best, float(err)


def euler_deg(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) degrees of ``R`` in the same convention."""
    r, p, y = matrix_to_euler(R)
    return float(np.degrees(r)), float(np.degrees(p)), float(np.degrees(y))
