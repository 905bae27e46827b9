"""Heading and tilt errors of a calibration (in the common form) over a grid of attitudes.

Given a *truth* (functions giving the raw accelerometer and compass readings for the true
specific force and field in the body frame) and the parameters written to the vehicle,
run the readings through the calibration form's correction (:mod:`mavcal.autopilot.calform`) and
compare with the truth at every attitude of a grid:

* tilt error: angle between the corrected and the true specific force;
* heading error: the heading of the corrected field, levelled with the attitude that
  the corrected accelerometer gives (what the autopilot sees when still), minus the true
  heading; ``heading_compass_only`` levels with the true attitude instead (the compass's
  own share).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from mavcal.autopilot import calform as fw
from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.core.constants import GRAVITY_MPS2

G0 = GRAVITY_MPS2


def attitude_grid(step_deg: float = 15.0, max_tilt_deg: float = 45.0) -> np.ndarray:
    """Body-to-NED rotations C = Rz(yaw) Ry(pitch) Rx(roll) on a regular grid, (M, 3, 3).

    Default: the flight envelope, roll and pitch in [-45, 45] deg and every yaw, in 15 deg
    steps (near +-90 deg pitch the heading is ill-defined and any compass error is
    amplified by 1/cos(pitch); pass ``max_tilt_deg=80`` to see that).
    """
    rolls = np.radians(np.arange(-max_tilt_deg, max_tilt_deg + 1e-9, step_deg))
    pitches = np.radians(np.arange(-max_tilt_deg, max_tilt_deg + 1e-9, step_deg))
    yaws = np.radians(np.arange(0.0, 360.0, step_deg))
    r, p, y = [a.ravel() for a in np.meshgrid(rolls, pitches, yaws, indexing="ij")]
    return euler_to_matrix(r, p, y)


@dataclass(frozen=True)
class AttitudeErrors:
    max_heading_deg: float
    rms_heading_deg: float
    max_heading_compass_only_deg: float
    max_tilt_deg: float
    rms_tilt_deg: float
    max_field_error_mgauss: float
    max_accel_error_mps2: float


def _level_from_accel(a_body: np.ndarray) -> np.ndarray:
    """Rotation body -> a levelled frame (yaw 0) from a still specific-force reading."""
    roll = np.arctan2(-a_body[:, 1], -a_body[:, 2])
    pitch = np.arctan2(a_body[:, 0], np.sqrt(a_body[:, 1] ** 2 + a_body[:, 2] ** 2))
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    L = np.zeros((len(roll), 3, 3))  # Ry(pitch) Rx(roll)
    L[:, 0, 0] = cp
    L[:, 0, 1] = sp * sr
    L[:, 0, 2] = sp * cr
    L[:, 1, 1] = cr
    L[:, 1, 2] = -sr
    L[:, 2, 0] = -sp
    L[:, 2, 1] = cp * sr
    L[:, 2, 2] = cp * cr
    return L


def _heading(v_level: np.ndarray) -> np.ndarray:
    return np.arctan2(v_level[:, 1], v_level[:, 0])


def _wrap_deg(x: np.ndarray) -> np.ndarray:
    return np.degrees((x + np.pi) % (2 * np.pi) - np.pi)


def body_vectors(grid: np.ndarray, field_ned_mgauss) -> tuple[np.ndarray, np.ndarray]:
    """The true specific force (m/s^2) and field (mGauss) in the body frame at each attitude of
    ``grid`` (M, 3, 3): what the raw-reading functions of :func:`attitude_errors` are given."""
    Ct = np.swapaxes(grid, 1, 2)
    return Ct @ np.array([0.0, 0.0, -G0]), Ct @ np.asarray(field_ned_mgauss, dtype=float)


def _signed_errors(raw_accel, raw_mag_sensor, accel_cal, compass_cal, field_ned_mgauss, C):
    f_body, B_body = body_vectors(C, field_ned_mgauss)
    a = fw.apply_accel(accel_cal, raw_accel(f_body))
    m = fw.apply_compass(compass_cal, raw_mag_sensor(B_body), sensor_frame=True)
    L_est = _level_from_accel(a)
    L_true = _level_from_accel(f_body)
    h_true = _heading((L_true @ B_body[..., None])[..., 0])
    dh = _wrap_deg(_heading((L_est @ m[..., None])[..., 0]) - h_true)
    dc = _wrap_deg(_heading((L_true @ m[..., None])[..., 0]) - h_true)
    return a, m, f_body, B_body, dh, dc


def max_errors_deg(raw_accel: np.ndarray, raw_mag_sensor: np.ndarray, accel_cal: fw.AccelCal,
                   compass_cal: fw.CompassCal, field_ned_mgauss, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Max heading and max tilt error over ``grid`` (M attitudes) for each of D truths at once:
    ``raw_accel`` / ``raw_mag_sensor`` (D, M, 3) are the raw readings of the D truths at the
    grid's specific force and field (:func:`body_vectors`).
    Returns (D,) arrays, equal to the last bit to ``attitude_errors``' ``max_heading_deg`` /
    ``max_tilt_deg`` truth by truth; what does not depend on the truth is computed once
    (:class:`GridErrors`, which evaluates many batches against one grid)."""
    return GridErrors(accel_cal, compass_cal, field_ned_mgauss, grid)(raw_accel, raw_mag_sensor)


class GridErrors:
    """:func:`max_errors_deg` for one set of written parameters, field and grid, called with
    batch after batch of truths: the grid's true specific force, field and heading once.

    The specific force does not depend on the heading, so a grid of every yaw at each roll and
    pitch holds few distinct ones (``f_unique``, 49 of the default grid's 1176):
    :meth:`at_unique` takes the accelerometer readings at those only and gives, to the last
    bit, what ``__call__`` gives from the readings at every attitude (the readings of equal
    forces are equal, and so is everything computed from them row by row)."""

    def __init__(self, accel_cal: fw.AccelCal, compass_cal: fw.CompassCal, field_ned_mgauss, grid: np.ndarray):
        self.accel_cal, self.compass_cal = accel_cal, compass_cal
        self.f_body, self.B_body = body_vectors(grid, field_ned_mgauss)
        self.L_true = _level_from_accel(self.f_body)
        self.h_true = _heading((self.L_true @ self.B_body[..., None])[..., 0])
        f_unique, index = np.unique(self.f_body, axis=0, return_inverse=True)
        self.f_unique, self.unique_index = f_unique, np.asarray(index).reshape(-1)

    def __call__(self, raw_accel: np.ndarray, raw_mag_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(max heading error, max tilt error) in degrees, (D,) each, of the D truths whose raw
        readings at the grid are ``raw_accel`` / ``raw_mag_sensor`` (D, M, 3)."""
        return self._errors(raw_accel, self.f_body, None, raw_mag_sensor)

    def at_unique(self, raw_accel: np.ndarray, raw_mag_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As ``__call__`` with the accelerometer readings (D, len(f_unique), 3) at the distinct
        specific forces ``f_unique`` only (the compass's still at every attitude)."""
        return self._errors(raw_accel, self.f_unique, self.unique_index, raw_mag_sensor)

    def compass_only(self, raw_mag_sensor: np.ndarray) -> np.ndarray:
        """Max heading error over the grid (deg, (D,)) of the D truths whose raw compass readings are
        ``raw_mag_sensor`` (D, M, 3), the attitude known (the compass's own error, as
        :func:`attitude_errors`' ``max_heading_compass_only_deg``)."""
        D, M = raw_mag_sensor.shape[:2]
        m = fw.apply_compass(self.compass_cal, raw_mag_sensor.reshape(-1, 3), sensor_frame=True).reshape(D, M, 3)
        dc = _wrap_deg(_heading((self.L_true[None] @ m[..., None])[..., 0].reshape(-1, 3)).reshape(D, M)
                       - self.h_true)
        return np.abs(dc).max(axis=1)

    def _errors(self, raw_accel: np.ndarray, f: np.ndarray, index: np.ndarray | None,
                raw_mag_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The arithmetic of :func:`attitude_errors` element by element; the dot product and
        the norm summed x + y + z in that order, as ``np.sum(axis=1)`` and ``np.linalg.norm``
        sum three terms, without full-length tiled copies of the grid."""
        D, K = raw_accel.shape[:2]
        M = raw_mag_sensor.shape[1]
        a = fw.apply_accel(self.accel_cal, raw_accel.reshape(-1, 3))
        m = fw.apply_compass(self.compass_cal, raw_mag_sensor.reshape(-1, 3), sensor_frame=True)
        L = _level_from_accel(a)
        if index is not None:
            L = L.reshape(D, K, 3, 3)[:, index].reshape(-1, 3, 3)
        dh = _wrap_deg(_heading((L @ m[..., None])[..., 0]).reshape(D, M) - self.h_true)
        a0, a1, a2 = a[:, 0].reshape(D, K), a[:, 1].reshape(D, K), a[:, 2].reshape(D, K)
        dot = a0 * f[:, 0] + a1 * f[:, 1] + a2 * f[:, 2]
        cos_t = dot / (np.sqrt(a0 * a0 + a1 * a1 + a2 * a2) * G0)
        tilt = np.degrees(np.arccos(np.clip(cos_t, -1.0, 1.0)))
        return np.abs(dh).max(axis=1), tilt.max(axis=1)


def heading_errors_deg(raw_accel: Callable[[np.ndarray], np.ndarray],
                       raw_mag_sensor: Callable[[np.ndarray], np.ndarray],
                       accel_cal: fw.AccelCal, compass_cal: fw.CompassCal, field_ned_mgauss,
                       grid: np.ndarray | None = None) -> np.ndarray:
    """Signed heading error (deg) at every attitude of ``grid`` (see :func:`attitude_errors`)."""
    C = attitude_grid() if grid is None else grid
    return _signed_errors(raw_accel, raw_mag_sensor, accel_cal, compass_cal, field_ned_mgauss, C)[4]


def attitude_errors(raw_accel: Callable[[np.ndarray], np.ndarray], raw_mag_sensor: Callable[[np.ndarray], np.ndarray],
                    accel_cal: fw.AccelCal, compass_cal: fw.CompassCal, field_ned_mgauss,
                    grid: np.ndarray | None = None) -> AttitudeErrors:
    """Errors of ``accel_cal``/``compass_cal`` against the truth over ``grid`` (body->NED).

    raw_accel(f_body (M, 3) m/s^2) -> board-frame raw accelerometer readings (M, 3);
    raw_mag_sensor(B_body (M, 3) mGauss) -> raw compass readings in the sensor's own frame
    (before COMPASS_ORIENT / AHRS_ORIENTATION), (M, 3).
    """
    C = attitude_grid() if grid is None else grid
    a, m, f_body, B_body, dh, dc = _signed_errors(raw_accel, raw_mag_sensor, accel_cal, compass_cal,
                                                  field_ned_mgauss, C)
    cos_t = np.sum(a * f_body, 1) / (np.linalg.norm(a, axis=1) * G0)
    tilt = np.degrees(np.arccos(np.clip(cos_t, -1.0, 1.0)))
    return AttitudeErrors(
        max_heading_deg=float(np.abs(dh).max()), rms_heading_deg=float(np.sqrt(np.mean(dh ** 2))),
        max_heading_compass_only_deg=float(np.abs(dc).max()), max_tilt_deg=float(tilt.max()),
        rms_tilt_deg=float(np.sqrt(np.mean(tilt ** 2))),
        max_field_error_mgauss=float(np.linalg.norm(m - B_body, axis=1).max()),
        max_accel_error_mps2=float(np.linalg.norm(a - f_body, axis=1).max()))
