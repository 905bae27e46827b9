"""A PX4 recording from a known truth, as the ULog reader would give it (tests of :mod:`mavcal.px4`).

The vehicle is held still in poses (:data:`mavcal.testing.simlog.DEFAULT_POSES_DEG`) and turned
between them. The raw sensors, in their own frames (``R_acc`` / ``R_mag`` = the rotations PX4 is
told, sensor -> body)::

    accel  u = D (R_acc^T f_body) + b            (m/s^2; D upper triangular)
    mag    s = M (R_mag^T B_body) + o            (mGauss; M symmetric soft iron)

are logged as ``sensor_accel`` / ``sensor_mag`` with their device ids, beside the PX4 parameters
of a calibration in force (which a raw topic does not depend on). :func:`truth_errors` scores
written ``CAL_*`` values against the truth with PX4's own equations (:mod:`mavcal.px4.firmware`).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.px4 import params as pn
from mavcal.px4.firmware import accel_cal_from_params, mag_cal_from_params
from mavcal.sources.types import ImuLog, ParamTimeline, SensorSeries
from mavcal.testing.simlog import DEFAULT_POSES_DEG

__all__ = ["Px4Truth", "simulate_px4", "truth_errors", "SITL_ACCEL_ID", "SITL_MAG_ID", "FIELD_NED_MGAUSS"]

SITL_ACCEL_ID = 1310988  # the PX4 simulator's device ids (bus type 4, simulation: internal)
SITL_MAG_ID = 197388
EXTERNAL_MAG_ID = 0x0A1E03  # an I2C-style id on bus type 3 (UAVCAN): external
#: Earth's field in NED, mGauss (Zurich, roughly: 215 N, 10 E, 430 D)
FIELD_NED_MGAUSS = (215.0, 10.0, 430.0)


@dataclass(frozen=True)
class Px4Truth:
    """The raw sensor errors and the PX4 parameters in force of a simulated recording."""

    D: np.ndarray = field(default_factory=lambda: np.eye(3))
    b_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    M: np.ndarray = field(default_factory=lambda: np.eye(3))
    o_mgauss: np.ndarray = field(default_factory=lambda: np.zeros(3))
    params: Mapping[str, float] = field(default_factory=dict)
    accel_id: int = SITL_ACCEL_ID
    mag_id: int = SITL_MAG_ID
    mag_external: bool = False
    #: the physical mag rotation (sensor -> body) when it differs from what PX4 is told (None: the same)
    mag_rotation: np.ndarray | None = None


def random_truth(seed: int, *, board_rot: int = 0, mag_rot: int | None = None, cross: float = 0.0) -> Px4Truth:
    """Random sensor errors (scales +-5 %, accel offsets 0.3 m/s^2, cross-axis terms up to ``cross``
    (which PX4 cannot hold), soft iron 10 %, hard iron 150 mGauss) and a non-trivial calibration in
    force in slot 0."""
    rng = np.random.default_rng(seed)
    D = np.diag(1 + rng.uniform(-0.05, 0.05, 3)) + np.triu(rng.uniform(-cross, cross, (3, 3)), 1)
    A = rng.uniform(-0.08, 0.08, (3, 3))
    M = np.diag(1 + rng.uniform(-0.1, 0.1, 3)) + 0.5 * (A + A.T) - np.diag(np.diag(0.5 * (A + A.T)))
    an, mn = pn.accel_names(0), pn.mag_names(0)
    p: dict[str, float] = {pn.board_names()[0]: float(board_rot), an["id"]: float(SITL_ACCEL_ID),
                           mn["id"]: float(EXTERNAL_MAG_ID if mag_rot is not None else SITL_MAG_ID),
                           an["rot"]: -1.0, mn["rot"]: float(mag_rot if mag_rot is not None else -1),
                           an["prio"]: 50.0, mn["prio"]: 50.0}
    for n in pn.board_names()[1]:
        p[n] = 0.0
    for names, vals in ((an["ofs"], rng.uniform(-0.2, 0.2, 3)), (an["scale"], 1 + rng.uniform(-0.03, 0.03, 3)),
                        (mn["ofs"], rng.uniform(-0.1, 0.1, 3)), (mn["scale"], 1 + rng.uniform(-0.05, 0.05, 3)),
                        (mn["odiag"], rng.uniform(-0.02, 0.02, 3)), (mn["custom"], np.zeros(3))):
        p.update({n: float(v) for n, v in zip(names, vals)})
    return Px4Truth(D, rng.uniform(-0.3, 0.3, 3), M, rng.uniform(-150, 150, 3), p,
                    mag_id=EXTERNAL_MAG_ID if mag_rot is not None else SITL_MAG_ID, mag_external=mag_rot is not None)


def _rotations(truth: Px4Truth) -> tuple[np.ndarray, np.ndarray]:
    ra = accel_cal_from_params(truth.params, truth.accel_id).rotation
    rm = mag_cal_from_params(truth.params, truth.mag_id, truth.mag_external).rotation
    return np.asarray(ra), np.asarray(truth.mag_rotation if truth.mag_rotation is not None else rm)


def raw_at(truth: Px4Truth, attitudes: Rotation) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free raw accel (m/s^2) and mag (mGauss) at body->NED ``attitudes``."""
    Ra, Rm = _rotations(truth)
    f_body = attitudes.inv().apply(np.array([0.0, 0.0, -GRAVITY_MPS2]))
    B_body = attitudes.inv().apply(np.asarray(FIELD_NED_MGAUSS))
    return f_body @ Ra @ truth.D.T + truth.b_mps2, B_body @ Rm @ truth.M.T + truth.o_mgauss


def simulate_px4(truth: Px4Truth, *, rate_hz: float = 50.0, hold_s: float = 4.0, move_s: float = 1.5,
                 noise: tuple[float, float] = (0.01, 0.5), seed: int = 0,
                 poses_deg=DEFAULT_POSES_DEG) -> ImuLog:
    """An :class:`ImuLog` of the ULog reader's shape (kind "ulog") for ``truth``."""
    rng = np.random.default_rng(seed)
    rots = Rotation.from_matrix(np.array([euler_to_matrix(*np.radians(p)) for p in poses_deg]))
    period = hold_s + move_s
    t = np.arange(0.0, len(poses_deg) * period - move_s, 1.0 / rate_hz)
    k = np.minimum((t // period).astype(int), len(poses_deg) - 1)
    frac = np.clip((t - k * period - hold_s) / move_s, 0.0, 1.0)
    quats = rots.as_quat()[k]
    gyro = np.zeros((len(t), 3))
    for i in np.unique(k[frac > 0]):
        sel = (k == i) & (frac > 0)
        s = 0.5 - 0.5 * np.cos(np.pi * frac[sel])
        pair = Slerp([0.0, 1.0], Rotation.concatenate([rots[i], rots[i + 1]]))
        quats[sel] = pair(s).as_quat()
        rotvec = (rots[i].inv() * rots[i + 1]).as_rotvec()
        gyro[sel] = rotvec * (0.5 * np.pi * np.sin(np.pi * frac[sel]) / move_s)[:, None]
    att = Rotation.from_quat(quats)
    acc, mag = raw_at(truth, att)
    acc = acc + rng.normal(0, noise[0], acc.shape)
    mag = mag + rng.normal(0, noise[1], mag.shape)
    gyro = gyro + rng.normal(0, 0.002, gyro.shape)
    n = len(t)
    series = (SensorSeries("accel", 0, "sensor_accel", t, acc, extra={"device_id": np.full(n, truth.accel_id)}),
              SensorSeries("gyro", 0, "sensor_gyro", t, gyro, extra={"device_id": np.full(n, truth.accel_id)}),
              SensorSeries("mag", 0, "sensor_mag", t, mag, extra={"device_id": np.full(n, truth.mag_id)}))
    params = ParamTimeline({k: (np.array([0.0]), np.array([float(v)])) for k, v in truth.params.items()})
    return ImuLog(source="simulated PX4", kind="ulog", series=series, params=params,
                  position=(47.3977, 8.5456, 488.0), vehicle={"autopilot": 12})


def truth_errors(truth: Px4Truth, new_params: Mapping[str, float], *, n: int = 500, seed: int = 1) -> dict[str, float]:
    """Worst heading (deg) and tilt (deg) errors, and accel / mag magnitude errors, of PX4's own
    correction with ``new_params`` (merged over the parameters in force) at ``n`` random attitudes
    within 60 deg of level; plus the mag offset error in gauss."""
    rng = np.random.default_rng(seed)
    p = dict(truth.params)
    p.update(new_params)
    ca = accel_cal_from_params(p, truth.accel_id)
    cm = mag_cal_from_params(p, truth.mag_id, truth.mag_external)
    eul = np.column_stack([rng.uniform(-60, 60, n), rng.uniform(-60, 60, n), rng.uniform(-180, 180, n)])
    att = Rotation.from_euler("ZYX", eul[:, ::-1], degrees=True)
    raw_a, raw_m = raw_at(truth, att)
    a, m = ca.correct(raw_a), cm.correct(raw_m)
    f_true = att.inv().apply(np.array([0.0, 0.0, -GRAVITY_MPS2]))
    B_true = att.inv().apply(np.asarray(FIELD_NED_MGAUSS))
    cos_t = np.sum(a * f_true, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(f_true, axis=1)
    tilt = np.degrees(np.arccos(np.clip(cos_t, -1, 1)))
    # heading: the field's horizontal direction in the true level frame vs the corrected one
    h_true = att.apply(B_true)
    h_est = att.apply(m)
    head = np.degrees(np.arctan2(h_est[:, 1], h_est[:, 0]) - np.arctan2(h_true[:, 1], h_true[:, 0]))
    head = (head + 180) % 360 - 180
    ofs_err = np.linalg.norm(np.asarray(cm.ofs_gauss) * 1000.0 - truth.o_mgauss) / 1000.0  # both sensor frame
    return {"heading_deg": float(np.abs(head).max()), "tilt_deg": float(tilt.max()),
            "accel_mag_mps2": float(np.abs(np.linalg.norm(a, axis=1) - GRAVITY_MPS2).max()),
            "field_mgauss": float(np.abs(np.linalg.norm(m, axis=1) - np.linalg.norm(FIELD_NED_MGAUSS)).max()),
            "mag_offset_gauss": float(ofs_err)}
