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
from typing import TYPE_CHECKING

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.flight import (
    COMPENSATION_CURRENT,
    COMPENSATION_OFF,
    COMPENSATION_THROTTLE,
    AsApplied,
    InForce,
)

if TYPE_CHECKING:
    from mavcal.sources.flight_series import CompassSeries

__all__ = ["COMPENSATION_CURRENT", "COMPENSATION_OFF", "COMPENSATION_THROTTLE", "ArduPilotFlight", "in_force",
           "raw_field", "motor_type", "motor_param_values", "compass_in_use", "MOTCT"]

MOTCT = "COMPASS_MOTCT"


def in_force(params: Mapping[str, float], instance: int) -> InForce:
    """Compass ``instance``'s calibration in force as the log tells it (``A = M(DIA, ODI) · SCALE``;
    the offsets are logged per sample in ``MAG``, so ``ofs_mgauss`` is None)."""
    missing: list[str] = []
    cal = fw.compass_cal_from_params(params, instance, missing)
    names = fw.compass_param_names(instance)["mot"]
    mot = np.array([float(params.get(n, 0.0)) for n in names])
    missing += [n for n in names if n not in params]
    A = np.asarray(cal.matrix, dtype=float) * float(cal.k)
    return InForce(instance, A, None, mot, tuple(missing), instance)


def raw_field(f: InForce, field_mgauss: np.ndarray, ofs_mgauss: np.ndarray, motor_ofs_mgauss: np.ndarray) -> np.ndarray:
    """The raw body-frame field (before offsets) of logged samples: ``A^-1 (mag - MO) - OFS_logged``
    (``A = M(DIA, ODI) · SCALE``, see ``fw.undo_compass``)."""
    d = np.asarray(field_mgauss, dtype=float) - np.asarray(motor_ofs_mgauss, dtype=float)
    return np.linalg.solve(f.A, d.T).T - np.asarray(ofs_mgauss, dtype=float)


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


class ArduPilotFlight:
    """ArduPilot's in-flight compass model (:class:`mavcal.autopilot.flight.FlightModel`): the
    ``MAG`` message logs the corrected field, the offsets and the motor offset, so the raw field
    is recovered from the log with only ``DIA``, ``ODI`` and ``SCALE`` from the parameters (a tlog
    logs the corrected field alone: the offsets and the motor compensation are then those in
    force); the motor term ``COMPASS_MOTn`` is added in the body frame, as fitted."""

    name = "ArduPilot"
    type_param = MOTCT
    #: SYSID_THISMAV became MAV_SYSID in ArduPilot 4.7 (GCS_MAVLink's MAV_ namespace)
    sysid_params: tuple[str, ...] = ("MAV_SYSID", "SYSID_THISMAV")

    def id_name(self, slot: int) -> str:
        return fw.compass_param_names(slot)["dev_id"] if slot >= 0 else ""

    def motor_type(self, params: Mapping[str, float]) -> int | None:
        return motor_type(params)

    def battery_instance(self, params: Mapping[str, float]) -> int:
        return 0

    def in_force(self, params: Mapping[str, float], c: CompassSeries) -> InForce:
        return in_force(params, c.instance)

    def as_applied(self, f: InForce, c: CompassSeries, params: Mapping[str, float],
                   driver_time_s: np.ndarray, driver: np.ndarray) -> AsApplied:
        ofs, mo = c.ofs_mgauss, c.motor_ofs_mgauss
        n = len(c.time_s)
        if not np.isfinite(ofs).all():  # not logged (a tlog): the offsets in force
            ofs = np.tile([float(params.get(x, 0.0)) for x in offset_names(f.slot)], (n, 1))
        if not np.isfinite(mo).all():  # not logged: the compensation in force at the driver's values
            kind = motor_type(params)
            if kind in (COMPENSATION_CURRENT, COMPENSATION_THROTTLE) and len(driver) > 1:
                mo = np.interp(c.time_s, driver_time_s, driver)[:, None] * f.mot_per_unit[None, :]
            else:
                mo = np.zeros((n, 3))
        return AsApplied(c.field_mgauss, ofs, mo, raw_field(f, c.field_mgauss, ofs, mo))

    def compass_in_use(self, params: Mapping[str, float], f: InForce) -> bool | None:
        return compass_in_use(params, f.instance)

    def param_values(self, f: InForce, kind: int, mot_per_unit: np.ndarray) -> dict[str, float]:
        return motor_param_values(f.slot, mot_per_unit)

    def type_values(self, kind: int, params: Mapping[str, float]) -> dict[str, float]:
        return motor_type_value(kind)
