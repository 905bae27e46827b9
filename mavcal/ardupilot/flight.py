"""ArduPilot's side of the in-flight compass stage: the calibration in force as logged, undone;
``COMPASS_MOTCT`` and the ``COMPASS_MOTn_*`` names of the motor compensation.

ArduPilot's compass model (``AP_Compass_Backend::correct_field``; the field is rotated into the
body frame first)::

    mag = M(DIA, ODI) · ((raw + OFS) · SCALE) + MOT · x

with ``x`` the battery current in A (``COMPASS_MOTCT`` 2) or the throttle 0..1 (1), and the
logged ``MAG`` carrying ``mag`` (``MagX..``), the offsets applied (``OfsX..``) and the motor
offset added (``MOX..`` = ``MOT · x``). So the raw field is recovered from the log itself with
only ``DIA``, ``ODI`` and ``SCALE`` from the parameters in force.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mavcal.ardupilot import firmware as fw

__all__ = ["COMPENSATION_CURRENT", "COMPENSATION_THROTTLE", "InForce", "in_force", "raw_field", "motor_type",
           "motor_param_values", "compass_in_use"]

COMPENSATION_OFF, COMPENSATION_THROTTLE, COMPENSATION_CURRENT = 0, 1, 2
MOTCT = "COMPASS_MOTCT"


@dataclass(frozen=True)
class InForce:
    """Compass ``instance``'s calibration in force as the log tells it; ``missing``: the
    parameters the log does not carry (their firmware defaults were assumed)."""

    instance: int
    cal: fw.CompassCal
    missing: tuple[str, ...]
    mot_per_unit: np.ndarray  # (3,) COMPASS_MOTn in force (mGauss per A or per full throttle)

    @property
    def matrix_times_scale(self) -> np.ndarray:
        """``M(DIA, ODI) · SCALE``: what multiplies ``raw + OFS`` (3x3)."""
        return np.asarray(self.cal.matrix, dtype=float) * float(self.cal.k)


def in_force(params: Mapping[str, float], instance: int) -> InForce:
    missing: list[str] = []
    cal = fw.compass_cal_from_params(params, instance, missing)
    names = fw.compass_param_names(instance)["mot"]
    mot = np.array([float(params.get(n, 0.0)) for n in names])
    missing += [n for n in names if n not in params]
    return InForce(instance, cal, tuple(missing), mot)


def raw_field(f: InForce, field_mgauss: np.ndarray, ofs_mgauss: np.ndarray, motor_ofs_mgauss: np.ndarray) -> np.ndarray:
    """The raw body-frame field (before offsets) of logged samples: ``M^-1 (mag - MO) / SCALE - OFS_logged``."""
    cal = fw.CompassCal(ofs_mgauss=(0.0, 0.0, 0.0), dia=f.cal.dia, odi=f.cal.odi, scale=f.cal.scale,
                        orient=f.cal.orient, external=f.cal.external, custom_deg=f.cal.custom_deg)
    return fw.undo_compass(cal, field_mgauss, motor_ofs_mgauss) - np.asarray(ofs_mgauss, dtype=float)


def motor_type(params: Mapping[str, float]) -> int | None:
    """``COMPASS_MOTCT`` in force (None when the log does not carry it)."""
    v = params.get(MOTCT)
    return None if v is None else int(round(float(v)))


def compass_in_use(params: Mapping[str, float], instance: int) -> bool | None:
    v = params.get(fw.compass_param_names(instance)["use"])
    return None if v is None else bool(int(round(float(v))))


def motor_param_values(instance: int, mot_per_unit: np.ndarray) -> dict[str, float]:
    """``COMPASS_MOTn_X/Y/Z`` of compass ``instance``."""
    names = fw.compass_param_names(instance)["mot"]
    return {n: float(v) for n, v in zip(names, mot_per_unit)}


def motor_type_value(kind: int) -> dict[str, float]:
    return {MOTCT: float(kind)}


def offset_names(instance: int) -> tuple[str, str, str]:
    return fw.compass_param_names(instance)["ofs"]
