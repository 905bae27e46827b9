"""The mapping of a joint fit onto an autopilot's parameters: its result types and the steps every
autopilot shares.

An accelerometer's fit ``K_a, b_a`` maps onto the calibration form (:mod:`mavcal.autopilot.calform`)
the same way for every autopilot whose accelerometer correction is per-axis offsets and scales
(:func:`accel_mapping`): ``OFS = b_a``, ``S_j = g0 / |row_j(K_a)|``; ``A = diag(S) K_a / g0`` is then a
rotation up to the cross-axis terms; its polar factor P (engine frame E -> board) defines the board
frame, and the symmetric rest ``N = P^T A - I`` is what no per-axis form holds: reported as the
worst-case tilt (deg) and magnitude (m/s^2) error it causes.

A compass's fit ``K_m, b_m, h_z`` gives the correction of the fitted readings onto the body field,
``T = (|B| / |h|) R_A P K_m^-1`` (:func:`field_correction`), with |B| the World Magnetic Model's, a
given one, or none (:func:`field_magnitude`); how T is written is each autopilot's own.

The result types (:class:`AccelMapping`, :class:`CompassMapping`, :class:`ParamMapping`) say what
was decided; each autopilot's subclasses name the parameters (``params()``).
"""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from mavcal.autopilot.calform import AccelCal, CompassCal
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.errors import ParameterMappingError

log = logging.getLogger(__name__)

__all__ = ["AccelMapping", "CompassMapping", "G0", "NO_FIELD_SOURCE", "ParamMapping", "accel_frame",
           "accel_mapping", "combine", "field_correction", "field_magnitude", "merge_mappings", "old_values",
           "polar_left"]

G0 = GRAVITY_MPS2
NO_FIELD_SOURCE = ("not checked: no position in the log and no --location; the sensor's own scale kept "
                   "(COMPASS_SCALE unchanged, COMPASS_DIA normalised to geometric mean 1)")


def polar_left(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    """An accelerometer's new values in the common form and what they leave out; its autopilot's
    subclass names the parameters (``params()``).

    frame_rotation : (3, 3) P, engine frame E -> board frame.
    cross_axis : (3, 3) N = P^T diag(S) K_a / g0 - I, the part a per-axis form cannot hold.
    dropped_tilt_deg, dropped_magnitude_mps2 : worst case over all directions of gravity
    kept : the accelerometer keeps its current values (``new`` is ``old``) and has no parameter to
        write: poses within reach cannot identify it (:mod:`mavcal.coverage`)
    """

    instance: int
    old: AccelCal
    new: AccelCal
    frame_rotation: np.ndarray
    cross_axis: np.ndarray
    dropped_tilt_deg: float
    dropped_magnitude_mps2: float
    kept: bool = False

    def params(self) -> dict[str, float]:
        """The parameters to write (name -> value): its autopilot's subclass says."""
        raise NotImplementedError(f"{type(self).__name__} names no parameters")


@dataclass(frozen=True, eq=False)
class CompassMapping:
    """A compass's new values in the common form, the orientation decision and what is left out;
    its autopilot's subclass names the parameters (``params()``)."""

    instance: int
    old: CompassCal
    new: CompassCal
    external: bool
    field_mgauss: float
    field_source: str
    rotation: np.ndarray  # U: the estimated rotation between accel and compass axes (R_new R_old^T)
    rotation_deg: float
    orientation_note: str
    residual_rotation_deg: float  # what the written orientation leaves uncorrected
    custom_deg: tuple[float, float, float] | None = None
    extra_params: Mapping[str, float] = field(default_factory=dict)  # orientation, external, custom rotation...
    reboot_required: bool = False
    reboot_reason: str = "custom orientation"  # why, in words, when ``reboot_required``
    inclination_deg: float = float("nan")
    inclination_model_deg: float | None = None
    field_checked: bool = True  # False: no WMM/given magnitude, the sensor's own scale kept

    def params(self) -> dict[str, float]:
        """The parameters to write (name -> value): its autopilot's subclass says."""
        raise NotImplementedError(f"{type(self).__name__} names no parameters")


@dataclass(frozen=True, eq=False)
class ParamMapping:
    """Everything a mapping decided: new values, old values, notes."""

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


A = TypeVar("A", bound=AccelMapping)


def accel_mapping(cls: type[A], K_a: np.ndarray, b_a: np.ndarray, old: AccelCal, instance: int = 0, **extra) -> A:
    """The best per-axis representation (offsets, scales: the common form) of an accelerometer gain
    and bias (board frame), as ``cls`` (an autopilot's :class:`AccelMapping`, with ``extra`` fields)."""
    S, A_, P = accel_frame(K_a)
    if np.linalg.det(P) < 0:
        raise ParameterMappingError("the accelerometer gain is mirrored (det < 0): an axis of the IMU is "
                                    "inverted, check the board orientation and the IMU driver")
    N = P.T @ A_
    v = _unit_sphere()
    Nv = v @ N.T
    tilt = np.degrees(np.arccos(np.clip(np.sum(Nv * v, 1) / np.linalg.norm(Nv, axis=1), -1, 1)))
    mag = np.abs(np.linalg.norm(Nv, axis=1) - 1.0) * G0
    new = AccelCal(ofs_mps2=tuple(np.asarray(b_a, float)), scale=tuple(S), board_orient=old.board_orient,
                   custom_deg=old.custom_deg)
    return cls(instance, old, new, P, N - np.eye(3), float(tilt.max()), float(mag.max()), **extra)


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


def old_values(params: Mapping[str, float], names) -> dict[str, float | None]:
    return {n: (float(params[n]) if n in params else None) for n in names}


# --------------------------------------------------------------------------- one pair, several pairs

def field_magnitude(raw_mag_means: np.ndarray, old: CompassCal, *,
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
