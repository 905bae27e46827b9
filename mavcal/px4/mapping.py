"""Map a joint calibration onto PX4's ``CAL_ACC<n>_*`` / ``CAL_MAG<n>_*`` and say what cannot be held.

The engine was given raw accelerometer readings in the sensor frame and raw magnetometer
readings ``R_old s`` (PX4's ``recover``), the frames every autopilot's mapping takes, so
the accelerometer is mapped by :func:`mavcal.autopilot.mapping.accel_mapping` (PX4's accelerometer
correction ``R ((u - OFF) * SCALE)`` is the common per-axis form): ``OFF = b_a``, ``SCALE_j = g0 / |row_j(K_a)|``,
the cross-axis terms PX4 cannot hold reported as tilt.

Magnetometer (``m = R_new S (s - OFF)``, OFF in gauss): with ``T = (|B| / |h|) R_A P K_m^-1`` the
correction of the fitted readings (``R_old s``) onto the body field,

    ``R_new S = T R_old``  (right polar decomposition: rotation U, symmetric rest),
    ``OFF = R_old^T b_m / 1000`` gauss.

External magnetometer: ``R_new`` is the writable rotation (``CAL_MAGn_ROT`` 0..40, after the level
adjustment) nearest to U when within ``orient_tol_deg``, else the custom Euler angles (``ROT`` 100,
``CAL_MAGn_ROLL/PITCH/YAW``) when the firmware has them. Internal magnetometer: ``R_new`` is the
board rotation (PX4 forces ``ROT`` -1), the misalignment U leaves is reported. ``S = sym(R_new^T T R_old)``.
Without a known field magnitude the sensor keeps its own scale (S's diagonal with geometric mean 1).
A sensor without a slot gets the first free one, with its device id in ``_ID``.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from mavcal.autopilot.mapping import (
    AccelMapping,
    CompassMapping,
    ParamMapping,
    accel_mapping,
    combine,
    field_correction,
    field_magnitude,
)
from mavcal.autopilot.rotations import rotation_angle_deg
from mavcal.errors import ParameterMappingError
from mavcal.px4 import params as pn
from mavcal.px4.firmware import Px4AccelCal, Px4MagCal, board_level_deg
from mavcal.px4.rotations import euler_deg, nearest_rotation, sensor_rotation

if TYPE_CHECKING:  # pragma: no cover
    from mavcal.core.types import Calibration

__all__ = ["Px4AccelMapping", "Px4CompassMapping", "map_accel_px4", "map_compass_px4", "map_calibration_px4"]


def _slot(params: Mapping[str, float], kind: str, cal: Px4AccelCal | Px4MagCal, notes: list[str]) -> tuple[int, bool]:
    if cal.slot is not None:
        return cal.slot, False
    free = pn.free_slot(params, kind)
    ids = [(pn.accel_names if kind == "accel" else pn.mag_names)(k)["id"] for k in range(pn.MAX_SLOTS)]
    if free is None and not any(n in params for n in ids):  # no slot at all in the parameters: not known
        notes.append(f"{kind} device {cal.device_id}: the parameters hold no calibration slot (the calibration in "
                     "force is not known): shown in slot 0, never written")
        return 0, True
    if free is None:
        raise ParameterMappingError(f"{kind} device {cal.device_id} has no calibration slot and every "
                                    f"CAL_{'ACC' if kind == 'accel' else 'MAG'}n_ID is taken: clear one first")
    notes.append(f"{kind} device {cal.device_id} had no calibration slot: slot {free} given to it")
    return free, True


@dataclass(frozen=True, eq=False)
class Px4AccelMapping(AccelMapping):
    """:class:`~mavcal.autopilot.mapping.AccelMapping` written as ``CAL_ACC<slot>_*``."""

    slot: int = 0
    device_id: int = 0
    new_slot: bool = False

    def params(self) -> dict[str, float]:
        n = pn.accel_names(self.slot)
        out = {name: float(v) for name, v in zip(n["ofs"], self.new.ofs_mps2)}
        out.update({name: float(v) for name, v in zip(n["scale"], self.new.scale)})
        if self.new_slot:
            out[n["id"]] = float(self.device_id)
        return out


@dataclass(frozen=True, eq=False)
class Px4CompassMapping(CompassMapping):
    """:class:`~mavcal.autopilot.mapping.CompassMapping` written as ``CAL_MAG<slot>_*``; ``old``/``new``
    are the common forms of ``px4_old``/``px4_new`` (for the shared quality and gate stages)."""

    slot: int = 0
    device_id: int = 0
    new_slot: bool = False
    px4_old: Px4MagCal | None = None
    px4_new: Px4MagCal | None = None

    def params(self) -> dict[str, float]:
        c = self.px4_new
        assert c is not None
        n = pn.mag_names(self.slot)
        out = {name: float(v) for name, v in zip(n["ofs"], c.ofs_gauss)}
        out.update({name: float(v) for name, v in zip(n["scale"], c.scale)})
        out.update({name: float(v) for name, v in zip(n["odiag"], c.odiag)})
        out.update(self.extra_params)
        if self.new_slot:
            out[n["id"]] = float(self.device_id)
        return out


def map_accel_px4(K_a: np.ndarray, b_a: np.ndarray, old: Px4AccelCal, params: Mapping[str, float],
                  instance: int = 0, notes: list[str] | None = None) -> Px4AccelMapping:
    """``CAL_ACC<slot>_{X,Y,Z}OFF`` = b_a and ``_{X,Y,Z}SCALE`` for one accelerometer."""
    slot, new_slot = _slot(params, "accel", old, notes if notes is not None else [])
    am = accel_mapping(Px4AccelMapping, K_a, b_a, old.ardupilot_form(), instance, slot=slot, device_id=old.device_id,
                       new_slot=new_slot)
    bad = [s for s in am.new.scale if not pn.SCALE_RANGE[0] <= s <= pn.SCALE_RANGE[1]]
    if bad:
        raise ParameterMappingError(f"accelerometer {instance}: scale {bad[0]:.3f} outside PX4's "
                                    f"{pn.SCALE_RANGE[0]}..{pn.SCALE_RANGE[1]}")
    return am


@dataclass(frozen=True)
class _Rot:
    R: np.ndarray
    value: int
    custom: tuple[float, float, float] | None
    note: str
    extra: dict[str, float] = field(default_factory=dict)


def _choose_rotation(U: np.ndarray, old: Px4MagCal, params: Mapping[str, float], slot: int,
                     orient_tol_deg: float, allow_custom: bool) -> _Rot:
    level = board_level_deg(params)
    names = pn.mag_names(slot)
    if not old.external:
        off = rotation_angle_deg(U, old.rotation)
        return _Rot(old.rotation, old.rot_value, None, f"internal magnetometer: follows SENS_BOARD_ROT, its {off:.2f} "
                    "deg misalignment to the accelerometer cannot be set alone")
    value, err = nearest_rotation(U, level)
    if err <= orient_tol_deg:
        extra = {names["rot"]: float(value)} if value != old.rot_value else {}
        was = " (unchanged)" if value == old.rot_value else f" (was {old.rot_value})"
        return _Rot(sensor_rotation(value, level), value, None, f"CAL_MAG{slot}_ROT {value}{was}, {err:.2f} deg from "
                    f"the estimate (tolerance {orient_tol_deg:g} deg)", extra)
    if allow_custom and all(n in params for n in names["custom"]):
        L = sensor_rotation(0, level)
        custom = euler_deg(L.T @ U)
        extra = {names["rot"]: float(pn.ROT_CUSTOM)}
        extra.update({n: float(v) for n, v in zip(names["custom"], custom)})
        return _Rot(L @ sensor_rotation(pn.ROT_CUSTOM, (0, 0, 0), custom), pn.ROT_CUSTOM, custom,
                    f"custom rotation (roll {custom[0]:.2f}, pitch {custom[1]:.2f}, yaw {custom[2]:.2f} deg): the "
                    f"nearest standard one ({value}) is {err:.2f} deg away", extra)
    return _Rot(sensor_rotation(value, level), value, None,
                f"CAL_MAG{slot}_ROT {value}, {err:.2f} deg from the estimate: no custom rotation, the rest stays "
                "uncorrected", {names["rot"]: float(value)} if value != old.rot_value else {})


def _polar_rotation(X: np.ndarray) -> np.ndarray:
    W, _, Vt = np.linalg.svd(X)
    return W @ Vt


def map_compass_px4(K_m: np.ndarray, b_m: np.ndarray, h_z: float, frame_rotation: np.ndarray, old: Px4MagCal,
                    params: Mapping[str, float], *, instance: int, field_mgauss: float | None, field_source: str,
                    board_rotation: np.ndarray, orient_tol_deg: float = 1.0, allow_custom: bool = True,
                    inclination_model_deg: float | None = None, notes: list[str] | None = None) -> Px4CompassMapping:
    """``CAL_MAG<slot>_*`` for an estimated K_m, b_m (see the module docstring)."""
    slot, new_slot = _slot(params, "mag", old, notes if notes is not None else [])
    checked = field_mgauss is not None
    B = field_mgauss if field_mgauss is not None else 1.0
    T, incl = field_correction(K_m, h_z, frame_rotation, board_rotation, field_mgauss, inclination_model_deg)
    R_old = old.rotation
    X = T @ R_old  # = R_new S
    U = _polar_rotation(X)
    rot = _choose_rotation(U, old, params, slot, orient_tol_deg, allow_custom)
    S = rot.R.T @ X
    S = 0.5 * (S + S.T)
    implied = B
    if not checked:
        gm = float(np.prod(np.abs(np.diag(S)))) ** (1.0 / 3.0)
        S, implied = S / gm, 1.0 / gm
    off_gauss = (R_old.T @ np.asarray(b_m, float)) / 1000.0
    bad = [d for d in np.diag(S) if not pn.SCALE_RANGE[0] <= d <= pn.SCALE_RANGE[1]]
    if bad:
        raise ParameterMappingError(f"magnetometer {instance}: soft-iron scale {bad[0]:.3f} outside PX4's "
                                    f"{pn.SCALE_RANGE[0]}..{pn.SCALE_RANGE[1]}")
    new = Px4MagCal(old.device_id, slot, tuple(off_gauss), (S[0, 0], S[1, 1], S[2, 2]), (S[0, 1], S[0, 2], S[1, 2]),
                    rot.R, rot.value, old.external, rot.custom)
    residual = rotation_angle_deg(rot.R, U)
    return Px4CompassMapping(
        instance=instance, old=old.ardupilot_form(), new=new.ardupilot_form(), external=old.external,
        field_mgauss=float(implied if not checked else B), field_source=field_source, rotation=U @ R_old.T,
        rotation_deg=rotation_angle_deg(U, R_old), orientation_note=rot.note, residual_rotation_deg=residual,
        custom_deg=rot.custom, extra_params=rot.extra, inclination_deg=incl,
        inclination_model_deg=inclination_model_deg, field_checked=checked, slot=slot, device_id=old.device_id,
        new_slot=new_slot, px4_old=old, px4_new=new)


def map_calibration_px4(cal: Calibration, params: Mapping[str, float], old_a: Px4AccelCal, old_m: Px4MagCal, *,
                        accel_instance: int = 0, mag_instance: int = 0, location: Sequence[float] | None = None,
                        field_mgauss: float | None = None, orient_tol_deg: float = 1.0, allow_custom: bool = True,
                        force_external: bool = False, location_source: str = "") -> ParamMapping:
    """The :class:`ParamMapping` of one accelerometer/magnetometer pair of a PX4 vehicle."""
    notes: list[str] = []
    field_norm, field_src, incl_model = field_magnitude(np.zeros((0, 3)), old_m.ardupilot_form(), location=location,
                                                        field_mgauss=field_mgauss, location_source=location_source)
    am = map_accel_px4(cal.accel.gain, cal.accel.bias, old_a, params, accel_instance, notes)
    cm = map_compass_px4(cal.mag.gain, cal.mag.bias, cal.h_z, am.frame_rotation, old_m, params, instance=mag_instance,
                         field_mgauss=field_norm, field_source=field_src, board_rotation=old_a.rotation,
                         orient_tol_deg=orient_tol_deg, allow_custom=allow_custom, inclination_model_deg=incl_model,
                         notes=notes)
    if force_external and not old_m.external:
        notes.append("PX4 decides from the bus whether a magnetometer is external: --force-external has no effect")
    notes.insert(0, cm.orientation_note)
    if am.dropped_tilt_deg > 0.01:
        notes.append(f"accelerometer cross-axis terms PX4 cannot hold: up to {am.dropped_tilt_deg:.3f} deg tilt, "
                     f"{am.dropped_magnitude_mps2:.3f} m/s^2")
    return combine([am], [cm], params, notes)
