"""A synthetic flight for the in-flight compass stage: a :class:`FlightSeries` made from
ArduPilot's compass model with known interference, offsets and calibration in force.

Each compass sees ``b = R^T B + s x - o_true`` (``s``: the interference per unit of the driver,
as SITL's ``SIM_MAG_MOT``; ``o_true``: the offsets that cancel its hard iron) plus white noise,
and logs what the firmware reports with the calibration in force (``OFS``, ``MOT``):
``mag = b + OFS + MOT x`` (DIA 1, ODI 0, SCALE 1). So the right ``COMPASS_MOT`` is ``-s`` and
the right ``COMPASS_OFS`` is ``o_true``.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mavcal.sources.flight_series import CompassSeries, FlightSeries

__all__ = ["SynthCompass", "synth_flight"]


@dataclass(frozen=True)
class SynthCompass:
    interference: tuple[float, float, float] = (0.0, 0.0, 0.0)  # s, mGauss per A
    ofs_true: tuple[float, float, float] = (5.0, 13.0, -18.0)
    ofs_in_force: tuple[float, float, float] = (5.0, 13.0, -18.0)
    mot_in_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_rotation_deg: float = 0.0  # mounted turned about z unlike its orientation in force


def _R(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    r, p, y = np.radians(roll), np.radians(pitch), np.radians(yaw)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.empty((len(roll), 3, 3))
    R[:, 0] = np.column_stack([cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy])
    R[:, 1] = np.column_stack([cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy])
    R[:, 2] = np.column_stack([-sp, sr * cp, cr * cp])
    return R


def synth_flight(compasses: Sequence[SynthCompass], *, seed: int = 0, duration_s: float = 150.0, rate_hz: float = 10.0,
                 current_max_a: float = 40.0, noise_mgauss: float = 2.0,
                 lat_lon: tuple[float, float] = (-35.363, 149.165), params: dict[str, float] | None = None,
                 field_ned: Sequence[float] | None = None) -> FlightSeries:
    """A flight of ``duration_s`` with turns through every heading, tilts up to ~20 deg, and a
    current between 0 and ``current_max_a`` (0 for a constant-current flight)."""
    from mavcal.sources.wmm import field_ned as wmm_ned

    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    yaw = (t * 360.0 / 40.0 + 20 * np.sin(t / 7.0)) % 360.0
    roll = 15 * np.sin(t / 3.1 + 1.0) * np.sin(t / 11.0)
    pitch = 12 * np.sin(t / 4.3) * np.cos(t / 13.0)
    cur = current_max_a * np.clip(0.5 + 0.45 * np.sin(t / 5.0) * np.sin(t / 17.0 + 0.5), 0.0, 1.0)
    R = _R(roll, pitch, yaw)
    B = np.asarray(field_ned, float) if field_ned is not None else wmm_ned(*lat_lon)
    body = np.einsum("nji,j->ni", R, B)
    p: dict[str, float] = {"COMPASS_MOTCT": 2.0}
    series = []
    for i, c in enumerate(compasses):
        s = "" if i == 0 else str(i + 1)
        p.update({f"COMPASS_OFS{s}_{a}": v for a, v in zip("XYZ", c.ofs_in_force)})
        p.update({f"COMPASS_MOT{s}_{a}": v for a, v in zip("XYZ", c.mot_in_force)})
        p.update({f"COMPASS_DIA{s}_{a}": 1.0 for a in "XYZ"})
        p.update({f"COMPASS_ODI{s}_{a}": 0.0 for a in "XYZ"})
        p.update({f"COMPASS_SCALE{s}": 1.0, f"COMPASS_ORIENT{s}": 0.0, f"COMPASS_USE{s}": 1.0})
        p["COMPASS_EXTERNAL" if i == 0 else f"COMPASS_EXTERN{i + 1}"] = 1.0
        a = np.radians(c.yaw_rotation_deg)
        Q = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        b = (Q @ body.T).T + cur[:, None] * np.asarray(c.interference) - np.asarray(c.ofs_true)
        b = b + rng.normal(0.0, noise_mgauss, b.shape)
        mo = cur[:, None] * np.asarray(c.mot_in_force)
        mag = np.round(b + np.asarray(c.ofs_in_force) + mo)
        series.append(CompassSeries(i, t.copy(), mag, np.tile(np.asarray(c.ofs_in_force, float), (len(t), 1)),
                                    np.round(mo), np.ones(len(t), bool)))
    p.update(params or {})
    return FlightSeries("synthetic", tuple(series), t.copy(), cur, t.copy(), cur / max(current_max_a, 1e-9) * 0.6,
                        t.copy(), roll, pitch, yaw, t.copy(), yaw.copy(), np.full(len(t), 1.0),
                        lat_lon[0], lat_lon[1], {k: v for k, v in p.items() if v is not None})
