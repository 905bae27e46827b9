"""Map a joint calibration onto ArduPilot's parameters and say what cannot be represented.

Frames. The engine (:mod:`mavcal.core`) was given raw accelerometer readings in the
**board frame** and raw compass readings in the **body frame after the current mounting
rotation** R_old (COMPASS_ORIENT for an external compass, AHRS_ORIENTATION for an internal
one), see ArduPilot's raw recovery (``recover``). Its orientations live in a frame E fixed by the
upper-triangular K_a.

Accelerometer (INS_ACCnOFFS, INS_ACCnSCAL; corrected = R_A (S o (u - OFS))):
    OFS = b_a;  S_j = g0 / |row_j(K_a)|   (the per-axis scale that makes each axis read g0)
    A = diag(S) K_a / g0 is then a rotation up to the cross-axis terms; its polar factor
    P (E -> board) defines the board frame, and the symmetric rest N = P^T A - I is what
    ArduPilot cannot represent (no off-diagonal accel terms): reported as the worst-case
    tilt (deg) and magnitude (m/s^2) error it causes.

Compass (COMPASS_OFSn, DIAn, ODIn, SCALEn, ORIENTn; corrected = M k (R_new s + OFS)):
    with |B| the field magnitude (World Magnetic Model or given) and |h| = |[1, 0, h_z]|,
    the correction that maps the raw field onto the body field is
        T = (|B| / |h|) R_A P K_m^-1 ,      OFS = -R_x b_m
    and T = S U (left polar decomposition): S symmetric -> M k (DIA/ODI and SCALE), U the
    rotation between accelerometer and compass axes -> R_x = U, R_new = U R_old.
    External compass: R_new becomes COMPASS_ORIENT: the nearest standard rotation when
    within ``orient_tol_deg``, else a custom rotation (CUST_ROTn, orientation 101/102,
    reboot needed) when the firmware has it. Internal compass: the rotation follows
    AHRS_ORIENTATION and cannot be set alone; U is reported (angle, heading effect), and
    ``force_external`` writes COMPASS_EXTERNn = 2 so that COMPASS_ORIENTn applies.

Still intervals do not determine |B|. Without a position or a given magnitude the
sensor keeps its own scale, as ArduPilot's own calibrator does: COMPASS_SCALE unchanged and
COMPASS_DIA normalised to geometric mean 1 (``field_checked`` False: the absolute field
strength was not checked). It is never taken from the calibration in force. A mirrored
compass cannot be told from an inverted field dip (:mod:`mavcal.core.gauge`), so the
estimated inclination is compared with the
World Magnetic Model when the position is known.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.mapping import (
    AccelMapping,
    CompassMapping,
    ParamMapping,
    accel_mapping,
    field_correction,
    field_magnitude,
    old_values,
    polar_left,
)
from mavcal.autopilot.rotations import (
    CUSTOM_1,
    CUSTOM_2,
    matrix_to_euler,
    nearest_rotation,
    rotation_angle_deg,
    rotation_matrix,
)

if TYPE_CHECKING:  # pragma: no cover
    from mavcal.core.types import Calibration


__all__ = ["ArduPilotAccelMapping", "ArduPilotCompassMapping", "CUST_ROT_ENABLE", "map_accel", "map_compass",
           "map_calibration"]

CUST_ROT_ENABLE = "CUST_ROT_ENABLE"


@dataclass(frozen=True, eq=False)
class ArduPilotAccelMapping(AccelMapping):
    """:class:`~mavcal.autopilot.mapping.AccelMapping` written as INS_ACC* (offsets, scales) for one IMU;
    ``cross_axis`` is the part ArduPilot cannot hold (no off-diagonal accelerometer terms)."""

    def params(self) -> dict[str, float]:
        return {} if self.kept else fw.accel_param_values(self.new, self.instance)


@dataclass(frozen=True, eq=False)
class ArduPilotCompassMapping(CompassMapping):
    """:class:`~mavcal.autopilot.mapping.CompassMapping` written as COMPASS_* for one compass (with the
    orientation, external and custom rotation values in ``extra_params``)."""

    def params(self) -> dict[str, float]:
        out = fw.compass_param_values(self.new, self.instance)
        out.update(self.extra_params)
        return out


def map_accel(K_a: np.ndarray, b_a: np.ndarray, old: fw.AccelCal, instance: int = 0) -> ArduPilotAccelMapping:
    """Best per-axis ArduPilot representation of an accelerometer gain and bias (board frame)."""
    return accel_mapping(ArduPilotAccelMapping, K_a, b_a, old, instance)


def _custom_slot(params: Mapping[str, float], current: int) -> int | None:
    names = fw.board_param_names()
    if CUST_ROT_ENABLE not in params and not any(n in params for n in names["custom1"]):
        return None  # firmware without AP_CustomRotations
    if current in (CUSTOM_1, CUSTOM_2):
        return current
    board = int(round(params.get(names["orientation"], 0) or 0))
    used = {board}
    for k in range(fw.MAX_COMPASSES):
        o = params.get(fw.compass_param_names(k)["orient"])
        if o is not None:
            used.add(int(round(o)))
    for slot in (CUSTOM_2, CUSTOM_1):
        if slot not in used:
            return slot
    return None


def map_compass(K_m: np.ndarray, b_m: np.ndarray, h_z: float, frame_rotation: np.ndarray, old: fw.CompassCal,
                params: Mapping[str, float], *, instance: int = 0,
                field_mgauss: float | None, field_source: str, board_rotation: np.ndarray, orient_tol_deg: float = 1.0,
                allow_custom: bool = True, force_external: bool = False,
                inclination_model_deg: float | None = None) -> ArduPilotCompassMapping:
    """ArduPilot compass parameters for an estimated K_m, b_m (see the module docstring);
    ``field_mgauss`` None keeps the sensor's own scale (COMPASS_SCALE unchanged, DIA with
    geometric mean 1)."""
    names = fw.compass_param_names(instance)
    checked = field_mgauss is not None
    T, incl = field_correction(K_m, h_z, frame_rotation, board_rotation, field_mgauss, inclination_model_deg)
    S, U = polar_left(T)
    R_old = old.mount_matrix
    ext_param = params.get(names["external"])
    external = bool(ext_param) if ext_param is not None else old.orient != int(round(
        params.get(fw.board_param_names()["orientation"], 0) or 0))
    extra: dict[str, float] = {}
    custom = None
    reboot = False
    rot_deg = rotation_angle_deg(np.eye(3), U)
    if external or force_external:
        R_new = U @ R_old
        enum, err = nearest_rotation(R_new)
        if err <= orient_tol_deg:
            R_used, orient = rotation_matrix(enum), enum
            note = (f"orientation {enum}" + (" (unchanged)" if enum == old.orient else f" (was {old.orient})")
                    + f", {err:.2f} deg from the estimate (tolerance {orient_tol_deg:g} deg)")
        else:
            slot = _custom_slot(params, old.orient) if allow_custom else None
            if slot is not None:
                r, p, y = matrix_to_euler(R_new)
                custom = (float(np.degrees(r)), float(np.degrees(p)), float(np.degrees(y)))
                bn = fw.board_param_names()
                cnames = bn["custom1" if slot == CUSTOM_1 else "custom2"]
                for n, v in zip(cnames, custom):
                    extra[n] = v
                extra[CUST_ROT_ENABLE] = 1.0
                R_used, orient, reboot = R_new, slot, True
                note = (f"custom orientation {slot} (roll {custom[0]:.2f}, pitch {custom[1]:.2f}, "
                        f"yaw {custom[2]:.2f} deg): the nearest standard one ({enum}) is {err:.2f} deg away; "
                        "reboot needed")
            else:
                R_used, orient = rotation_matrix(enum), enum
                note = (f"orientation {enum}, {err:.2f} deg from the estimate: the firmware has no custom "
                        "rotations, the rest stays uncorrected")
        if orient != old.orient or force_external:
            extra[names["orient"]] = float(orient)
        if force_external and not external:
            extra[names["external"]] = 2.0
            note += "; forced external (COMPASS_EXTERN = 2) so that COMPASS_ORIENT applies"
        R_x = R_used @ R_old.T
    else:
        R_x = np.eye(3)
        orient = old.orient
        note = (f"internal compass: follows AHRS_ORIENTATION, its {rot_deg:.2f} deg misalignment to the "
                "accelerometer cannot be set alone (calibrate --force-external writes it as COMPASS_ORIENT)")
    X = T @ R_x.T  # = M k, symmetric if R_x = U
    Mk = 0.5 * (X + X.T)
    residual = rotation_angle_deg(R_x, U)
    M, k, implied = _split_scale(Mk, old.scale if not checked else None)
    field_mgauss = field_mgauss if field_mgauss is not None else implied
    ofs = -(R_x @ np.asarray(b_m, float))
    new = fw.CompassCal(ofs_mgauss=tuple(ofs), dia=(M[0, 0], M[1, 1], M[2, 2]), odi=(M[0, 1], M[0, 2], M[1, 2]),
                        scale=k, orient=orient, external=external or force_external, custom_deg=custom, mot=old.mot)
    return ArduPilotCompassMapping(instance=instance, old=old, new=new, external=external or force_external,
                          field_mgauss=float(field_mgauss), field_source=field_source, rotation=U,
                          rotation_deg=float(rot_deg), orientation_note=note, residual_rotation_deg=float(residual),
                          custom_deg=custom, extra_params=extra, reboot_required=reboot, inclination_deg=incl,
                          inclination_model_deg=inclination_model_deg, field_checked=checked)


def _split_scale(Mk: np.ndarray, keep_scale: float | None) -> tuple[np.ndarray, float, float]:
    """M k = Mk: (M, k, the field magnitude implied for a unit field). ``keep_scale`` None:
    k = det(Mk)^(1/3) (1 outside ArduPilot's range); else k = ``keep_scale`` (COMPASS_SCALE
    unchanged) and M's diagonal has geometric mean 1."""
    if keep_scale is None:
        k = float(np.linalg.det(Mk)) ** (1.0 / 3.0) if np.linalg.det(Mk) > 0 else 1.0
        if not (fw.COMPASS_MIN_SCALE <= k <= fw.COMPASS_MAX_SCALE):
            k = 1.0
        return Mk / k, k, k
    d = np.abs(np.diag(Mk))
    gm = float(np.prod(d)) ** (1.0 / 3.0) if np.all(d > 0) else 1.0
    k = float(keep_scale)
    k_eff = k if fw.COMPASS_MIN_SCALE <= k <= fw.COMPASS_MAX_SCALE else 1.0
    return Mk / gm, k, k_eff / gm


# --------------------------------------------------------------------------- one pair, several pairs

def map_calibration(cal: Calibration, params: Mapping[str, float], raw_mag_means: np.ndarray, *,
                    accel_instance: int = 0, mag_instance: int = 0,
                    location: Sequence[float] | None = None, field_mgauss: float | None = None,
                    orient_tol_deg: float = 1.0, allow_custom: bool = True,
                    force_external: bool = False, location_source: str = "") -> ParamMapping:
    """The :class:`ParamMapping` of one accelerometer/compass pair fitted jointly.

    ``params`` are the vehicle's current parameters (the old calibration and the mounting);
    ``raw_mag_means`` the (N, 3) raw compass interval means (for the field magnitude when
    neither ``location`` nor ``field_mgauss`` gives it, see :func:`field_magnitude`).
    """
    old_a = fw.accel_cal_from_params(params, accel_instance)
    old_c = fw.compass_cal_from_params(params, mag_instance)
    field_norm, field_src, incl_model = field_magnitude(np.asarray(raw_mag_means, float), old_c, location=location,
                                                        field_mgauss=field_mgauss, location_source=location_source)
    am = map_accel(cal.accel.gain, cal.accel.bias, old_a, accel_instance)
    cm = map_compass(cal.mag.gain, cal.mag.bias, cal.h_z, am.frame_rotation, old_c, params, instance=mag_instance,
                     field_mgauss=field_norm, field_source=field_src, board_rotation=old_a.board_matrix,
                     orient_tol_deg=orient_tol_deg, allow_custom=allow_custom, force_external=force_external,
                     inclination_model_deg=incl_model)
    new = {**am.params(), **cm.params()}
    notes = [cm.orientation_note]
    if am.dropped_tilt_deg > 0.01:
        notes.append(f"accelerometer cross-axis terms ArduPilot cannot hold: up to {am.dropped_tilt_deg:.3f} deg tilt, "
                     f"{am.dropped_magnitude_mps2:.3f} m/s^2")
    return ParamMapping(accel=(am,), compass=(cm,), new=new, old=old_values(params, new), notes=tuple(notes),
                        reboot_required=cm.reboot_required)
