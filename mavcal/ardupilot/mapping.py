"""Map a joint calibration onto ArduPilot's parameters and say what cannot be represented.

Frames. The engine (:mod:`mavcal.core`) was given raw accelerometer readings in the
**board frame** and raw compass readings in the **body frame after the current mounting
rotation** R_old (COMPASS_ORIENT for an external compass, AHRS_ORIENTATION for an internal
one), see :mod:`mavcal.ardupilot.recover`. Its orientations live in a frame E fixed by the
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

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import (
    CUSTOM_1,
    CUSTOM_2,
    matrix_to_euler,
    nearest_rotation,
    rotation_angle_deg,
    rotation_matrix,
)
from mavcal.errors import ParameterMappingError

if TYPE_CHECKING:  # pragma: no cover
    from mavcal.core.types import Calibration

log = logging.getLogger(__name__)

G0 = fw.GRAVITY_MSS
CUST_ROT_ENABLE = "CUST_ROT_ENABLE"
NO_FIELD_SOURCE = ("not checked: no position in the log and no --location; the sensor's own scale kept "
                   "(COMPASS_SCALE unchanged, COMPASS_DIA normalised to geometric mean 1)")


def _polar_left(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T = S U with S symmetric positive semi-definite and U orthogonal."""
    W, s, Vt = np.linalg.svd(T)
    return (W * s) @ W.T, W @ Vt


def _polar_right_rotation(A: np.ndarray) -> np.ndarray:
    """Nearest orthogonal matrix to A (the U of A = U H)."""
    W, _, Vt = np.linalg.svd(A)
    return W @ Vt


def _unit_sphere(n: int = 1500) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


@dataclass(frozen=True, eq=False)
class AccelMapping:
    """INS_ACC* values for one IMU and what they leave out.

    frame_rotation : (3, 3) P, engine frame E -> board frame.
    cross_axis : (3, 3) N = P^T diag(S) K_a / g0 - I, the part ArduPilot cannot hold.
    dropped_tilt_deg, dropped_magnitude_mps2 : worst case over all directions of gravity
    kept : the accelerometer keeps its current values (``new`` is ``old``) and has no parameter to
        write: poses within reach cannot identify it (:mod:`mavcal.coverage`)
    """

    instance: int
    old: fw.AccelCal
    new: fw.AccelCal
    frame_rotation: np.ndarray
    cross_axis: np.ndarray
    dropped_tilt_deg: float
    dropped_magnitude_mps2: float
    kept: bool = False

    def params(self) -> dict[str, float]:
        return {} if self.kept else fw.accel_param_values(self.new, self.instance)


@dataclass(frozen=True, eq=False)
class CompassMapping:
    """COMPASS_* values for one compass, the orientation decision and what is left out."""

    instance: int
    old: fw.CompassCal
    new: fw.CompassCal
    external: bool
    field_mgauss: float
    field_source: str
    rotation: np.ndarray  # U: the estimated rotation between accel and compass axes (R_new R_old^T)
    rotation_deg: float
    orientation_note: str
    residual_rotation_deg: float  # what the written orientation leaves uncorrected
    custom_deg: tuple[float, float, float] | None = None
    extra_params: Mapping[str, float] = field(default_factory=dict)  # ORIENT, EXTERN, CUST_ROT...
    reboot_required: bool = False
    reboot_reason: str = "custom orientation"  # why, in words, when ``reboot_required``
    inclination_deg: float = float("nan")
    inclination_model_deg: float | None = None
    field_checked: bool = True  # False: no WMM/given magnitude, the sensor's own scale kept

    def params(self) -> dict[str, float]:
        out = fw.compass_param_values(self.new, self.instance)
        out.update(self.extra_params)
        return out


@dataclass(frozen=True, eq=False)
class ParamMapping:
    """Everything :func:`map_calibration` decided: new values, old values, notes."""

    accel: tuple[AccelMapping, ...]
    compass: tuple[CompassMapping, ...]
    new: Mapping[str, float]
    old: Mapping[str, float | None]
    notes: tuple[str, ...] = ()
    reboot_required: bool = False

    def by_sensor(self) -> dict[str, dict[str, float]]:
        """The new values per sensor (``accel0``, ``compass1``, ... as the gates name them)."""
        out = {f"accel{am.instance}": am.params() for am in self.accel}
        out.update({f"compass{cm.instance}": cm.params() for cm in self.compass})
        return out

    def restricted(self, sensors) -> dict[str, float]:
        """The new values of the given sensors only (names as :meth:`by_sensor`)."""
        keep = set(sensors)
        return {n: v for s, p in self.by_sensor().items() if s in keep for n, v in p.items()}

    def changed(self, rel: float = 1e-7) -> dict[str, float]:
        """Parameters whose new value differs from the old one (float32 comparison)."""
        out = {}
        for n, v in self.new.items():
            o = self.old.get(n)
            if o is None or np.float32(v) != np.float32(o):
                out[n] = v
        return out


def accel_frame(K_a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-axis scales S_j = g0 / |row_j(K_a)|, A = diag(S) K_a / g0 and its polar factor P
    (engine frame E -> board frame). Returns (S, A, P)."""
    K_a = np.asarray(K_a, dtype=float)
    S = G0 / np.linalg.norm(K_a, axis=1)
    A = S[:, None] * K_a / G0
    return S, A, _polar_right_rotation(A)


def map_accel(K_a: np.ndarray, b_a: np.ndarray, old: fw.AccelCal, instance: int = 0) -> AccelMapping:
    """Best per-axis ArduPilot representation of an accelerometer gain and bias (board frame)."""
    S, A, P = accel_frame(K_a)
    if np.linalg.det(P) < 0:
        raise ParameterMappingError("the accelerometer gain is mirrored (det < 0): an axis of the IMU is "
                                    "inverted, check the board orientation and the IMU driver")
    N = P.T @ A
    v = _unit_sphere()
    Nv = v @ N.T
    tilt = np.degrees(np.arccos(np.clip(np.sum(Nv * v, 1) / np.linalg.norm(Nv, axis=1), -1, 1)))
    mag = np.abs(np.linalg.norm(Nv, axis=1) - 1.0) * G0
    new = fw.AccelCal(ofs_mps2=tuple(np.asarray(b_a, float)), scale=tuple(S), board_orient=old.board_orient,
                      custom_deg=old.custom_deg)
    return AccelMapping(instance, old, new, P, N - np.eye(3), float(tilt.max()), float(mag.max()))


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


def field_correction(K_m: np.ndarray, h_z: float, frame_rotation: np.ndarray, board_rotation: np.ndarray,
                     field_mgauss: float | None,
                     inclination_model_deg: float | None = None) -> tuple[np.ndarray, float]:
    """``T = (|B| / |h|) R_A P K_m^-1``, the correction of the fitted compass readings onto the body
    field (``|B|`` 1 when ``field_mgauss`` is None), and the estimated inclination (deg).

    Raises ParameterMappingError for mirrored compass axes: det T < 0, or a field dip of the other
    sign than the World Magnetic Model's (``inclination_model_deg``, when beyond 10 deg)."""
    h_norm = float(np.sqrt(1.0 + h_z * h_z))
    B = field_mgauss if field_mgauss is not None else 1.0
    T = (B / h_norm) * np.asarray(board_rotation) @ np.asarray(frame_rotation) @ np.linalg.inv(K_m)
    if np.linalg.det(T) < 0:
        raise ParameterMappingError("the compass axes are mirrored relative to the accelerometer (det < 0): "
                                    "two axes swapped or one inverted in the wiring or the driver")
    incl = float(np.degrees(np.arctan2(h_z, 1.0)))
    if inclination_model_deg is not None and abs(inclination_model_deg) > 10 and incl * inclination_model_deg < 0:
        raise ParameterMappingError(
            f"the estimated field dip is {incl:.1f} deg but the World Magnetic Model gives "
            f"{inclination_model_deg:.1f} deg here: the compass axes appear mirrored (two axes swapped or "
            "one inverted in the wiring or the driver), which still poses cannot correct")
    return T, incl


def map_compass(K_m: np.ndarray, b_m: np.ndarray, h_z: float, frame_rotation: np.ndarray, old: fw.CompassCal,
                params: Mapping[str, float], *, instance: int = 0,
                field_mgauss: float | None, field_source: str, board_rotation: np.ndarray, orient_tol_deg: float = 1.0,
                allow_custom: bool = True, force_external: bool = False,
                inclination_model_deg: float | None = None) -> CompassMapping:
    """ArduPilot compass parameters for an estimated K_m, b_m (see the module docstring);
    ``field_mgauss`` None keeps the sensor's own scale (COMPASS_SCALE unchanged, DIA with
    geometric mean 1)."""
    names = fw.compass_param_names(instance)
    checked = field_mgauss is not None
    T, incl = field_correction(K_m, h_z, frame_rotation, board_rotation, field_mgauss, inclination_model_deg)
    S, U = _polar_left(T)
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
    return CompassMapping(instance=instance, old=old, new=new, external=external or force_external,
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


def old_values(params: Mapping[str, float], names) -> dict[str, float | None]:
    return {n: (float(params[n]) if n in params else None) for n in names}


# --------------------------------------------------------------------------- one pair, several pairs

def field_magnitude(raw_mag_means: np.ndarray, old: fw.CompassCal, *,
                    location: Sequence[float] | None = None, field_mgauss: float | None = None,
                    location_source: str = "") -> tuple[float | None, str, float | None]:
    """The field magnitude |B| to scale the compass to: (mGauss or None, source in words,
    WMM inclination deg or None).

    The World Magnetic Model at ``location`` (lat, lon[, alt]) when known and no
    ``field_mgauss`` is given (``location_source``, e.g. "vehicle GPS", is named in the words);
    else ``field_mgauss``; else None: the sensor keeps its own
    scale and the absolute field strength is not checked (still intervals do not determine
    |B|, and the calibration in force is what is being replaced). ``raw_mag_means`` and
    ``old`` are kept for the signature's sake.
    """
    incl = None
    if location is not None:
        loc = tuple(location)
        try:
            from mavcal.sources.wmm import field_at
            _, incl, intensity = field_at(loc[0], loc[1], loc[2] if len(loc) > 2 else 0.0)
        except Exception as exc:  # pragma: no cover - tables missing
            log.warning("World Magnetic Model unavailable: %s", exc)
            intensity = None
        if field_mgauss is None and intensity:
            where = f"{location_source} " if location_source else ""
            return float(intensity), f"World Magnetic Model at {where}{loc[0]:.4f}, {loc[1]:.4f}", incl
    if field_mgauss is not None:
        return float(field_mgauss), "given", incl
    return None, NO_FIELD_SOURCE, incl


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


def combine(accel: Sequence[AccelMapping], compass: Sequence[CompassMapping], params: Mapping[str, float],
            notes: Sequence[str] = ()) -> ParamMapping:
    """One :class:`ParamMapping` of per-sensor mappings (any of them may be empty);
    ``params`` gives the old values."""
    new: dict[str, float] = {}
    for am in accel:
        new.update(am.params())
    for cm in compass:
        new.update(cm.params())
    return ParamMapping(accel=tuple(accel), compass=tuple(compass), new=new, old=old_values(params, new),
                        notes=tuple(notes), reboot_required=any(c.reboot_required for c in compass))


def merge_mappings(primary: ParamMapping, others: Sequence[ParamMapping],
                   params: Mapping[str, float]) -> ParamMapping:
    """One :class:`ParamMapping` for several pairs: the primary pair's, plus every other
    accelerometer and compass calibrated (each other pair contributes the instance that
    is not the primary's). ``params`` gives the old values no pair recorded."""
    ai, mi = primary.accel[0].instance, primary.compass[0].instance
    accel = list(primary.accel) + [m.accel[0] for m in others if m.accel[0].instance != ai]
    compass = list(primary.compass) + [m.compass[0] for m in others if m.compass[0].instance != mi]
    new: dict[str, float] = {}
    for am in accel:
        new.update(am.params())
    for cm in compass:
        new.update(cm.params())
    old: dict[str, float | None] = {}
    for m in (primary, *others):
        old.update(m.old)
    old = {n: old.get(n, params.get(n)) for n in new}
    notes = list(primary.notes) + [f"compass {c.instance}: {c.orientation_note}" for c in compass[1:]]
    return ParamMapping(accel=tuple(accel), compass=tuple(compass), new=new, old=old, notes=tuple(notes),
                        reboot_required=any(c.reboot_required for c in compass))
