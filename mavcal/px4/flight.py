"""PX4's side of the in-flight compass stage: the power compensation as PX4 applies it.

Read in PX4's ``src/lib/sensor_calibration/Magnetometer.hpp`` (``Correct``) and
``src/modules/sensors/vehicle_magnetometer/VehicleMagnetometer.cpp`` (``UpdatePowerCompensation``)::

    mag = R · (S · ((s + power · COMP) - OFF))                  (gauss)

in the **sensor frame** (``COMP`` is added to the raw reading ``s`` before the offsets, the soft
iron ``S`` and the rotation ``R``), with ``COMP`` = ``CAL_MAGn_{X,Y,Z}COMP`` of the slot whose
``CAL_MAGn_ID`` is the device's, and ``power`` by ``CAL_MAG_COMP_TYP``: 2 (3) the current of
``battery_status`` instance 0 (1) in **kA** (``current_a * 0.001``), 1 the throttle (while
armed; ``actuator_controls_0`` throttle in PX4 up to 1.13, the length of ``vehicle_thrust_setpoint``
later), 0 none. ``ParametersUpdate`` takes ``COMP`` as it is, without the threshold that the
offsets and scales have (no detour needed to write it).

In the stage's form (:mod:`mavcal.autopilot.flight`: ``mag = A (b + o) + m x``, mGauss): ``b = s``
(``sensor_mag``, the raw reading), ``A = R S``, ``o = -1000 OFF`` and ``m = A c`` with ``c`` the
compensation per unit of the driver in mGauss: ``COMP`` itself per A (``1000 G/kA = 1 mGauss/A``:
the number is the same), ``1000 COMP`` per full throttle.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from mavcal.autopilot.flight import (
    COMPENSATION_CURRENT,
    COMPENSATION_OFF,
    COMPENSATION_THROTTLE,
    AsApplied,
    InForce,
)
from mavcal.px4 import params as pn
from mavcal.px4.firmware import mag_cal_from_params

if TYPE_CHECKING:
    from mavcal.sources.flight_series import CompassSeries

__all__ = ["Px4Flight", "COMP_TYPE_BATTERY1", "comp_per_unit", "comp_values"]

#: ``CAL_MAG_COMP_TYP`` 3: the current of battery_status instance 1
COMP_TYPE_BATTERY1 = 3


def comp_per_unit(kind: int) -> float:
    """mGauss of the raw reading per unit of ``COMP`` and of the driver: 1 per A (G/kA), 1000 per full throttle (G)."""
    return 1.0 if kind == COMPENSATION_CURRENT else 1000.0


def comp_values(A: np.ndarray, kind: int, mot_body_per_unit: np.ndarray) -> np.ndarray:
    """``COMP`` (sensor frame, G/kA or G) of a body-frame motor term ``m``: ``A^-1 m`` in PX4's unit."""
    return np.linalg.solve(np.asarray(A, float), np.asarray(mot_body_per_unit, float)) / comp_per_unit(kind)


class Px4Flight:
    """PX4's in-flight compass model (:class:`mavcal.autopilot.flight.FlightModel`): ``sensor_mag``
    logs the raw reading, so the calibration in force is applied here as PX4 does, with the
    parameters of the slot of the compass's device id."""

    name = "PX4"
    type_param = pn.MAG_COMP_TYPE
    sysid_params: tuple[str, ...] = ("MAV_SYS_ID",)

    def id_name(self, slot: int) -> str:
        return pn.mag_names(slot)["id"] if slot >= 0 else ""

    def motor_type(self, params: Mapping[str, float]) -> int | None:
        v = params.get(pn.MAG_COMP_TYPE)
        if v is None:
            return None
        k = int(round(float(v)))
        return COMPENSATION_CURRENT if k in (COMPENSATION_CURRENT, COMP_TYPE_BATTERY1) else (
            COMPENSATION_THROTTLE if k == COMPENSATION_THROTTLE else COMPENSATION_OFF)

    def battery_instance(self, params: Mapping[str, float]) -> int:
        v = params.get(pn.MAG_COMP_TYPE)
        return 1 if v is not None and int(round(float(v))) == COMP_TYPE_BATTERY1 else 0

    def in_force(self, params: Mapping[str, float], c: CompassSeries) -> InForce:
        dev = int(c.device_id or 0)
        cal = mag_cal_from_params(params, dev)
        missing: list[str] = []
        if cal.slot is None:
            missing.append(f"a CAL_MAGn_ID holding its device id {dev}" if dev else "its device id (sensor_mag)")
            comp = np.zeros(3)
            slot = -1
        else:
            n = pn.mag_names(cal.slot)
            need = [n["rot"], *n["ofs"], *n["scale"], *n["odiag"], *n["comp"], pn.board_names()[0]]
            missing += [x for x in need if x not in params]
            comp = np.array([float(params.get(x, 0.0)) for x in n["comp"]])
            slot = cal.slot
        A = cal.rotation @ cal.matrix
        kind = self.motor_type(params)
        mot = A @ (comp * comp_per_unit(kind or COMPENSATION_CURRENT))
        return InForce(c.instance, A, -1000.0 * np.asarray(cal.ofs_gauss, float), mot, tuple(missing), slot)

    def as_applied(self, f: InForce, c: CompassSeries, params: Mapping[str, float],
                   driver_time_s: np.ndarray, driver: np.ndarray) -> AsApplied:
        b = np.asarray(c.raw_mgauss, dtype=float)
        n = len(b)
        assert f.ofs_mgauss is not None
        o = np.tile(f.ofs_mgauss, (n, 1))
        kind = self.motor_type(params)
        if kind in (COMPENSATION_CURRENT, COMPENSATION_THROTTLE) and len(driver) > 1:
            x = np.interp(c.time_s, driver_time_s, driver)
            mo = x[:, None] * f.mot_per_unit[None, :]
        else:
            mo = np.zeros((n, 3))
        field = (f.A @ (b + o).T).T + mo
        return AsApplied(field, o, mo, b)

    def compass_in_use(self, params: Mapping[str, float], f: InForce) -> bool | None:
        if f.slot < 0:
            return None
        v = params.get(pn.mag_names(f.slot)["prio"])
        return None if v is None else float(v) > 0

    def param_values(self, f: InForce, kind: int, mot_per_unit: np.ndarray) -> dict[str, float]:
        if f.slot < 0:
            return {}
        comp = comp_values(f.A, kind, mot_per_unit)
        return {n: float(v) for n, v in zip(pn.mag_names(f.slot)["comp"], comp)}

    def type_values(self, kind: int, params: Mapping[str, float]) -> dict[str, float]:
        if kind == COMPENSATION_CURRENT and self.battery_instance(params) == 1:
            return {pn.MAG_COMP_TYPE: float(COMP_TYPE_BATTERY1)}
        return {pn.MAG_COMP_TYPE: float(kind)}
