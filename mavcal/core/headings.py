"""The headings of poses within reach from a provisional fit of the compass: what cannot be wrong
whatever the offsets, soft iron and dip (issue 37).

Each still interval's tilt T_i is given by the accelerometer (:func:`mavcal.core.held.tilts_of`),
its heading psi_i is not. The compass model of the paper (Eq. ``sensor_reading_model``) with
K_m = s Q^T, Q a rotation of the compass about the vertical axis (its mounting, one of ArduPilot's
yaw rotations 0, 2, 4, 6), reads

    mu_m[i] = s Q^T T_i Rz(psi_i) [1, 0, h_z]^T + b_m

so the field in the levelled frame, v_i = T_i^T Q (mu_m[i] - b_m) / s, is Rz(psi_i) [1, 0, h_z]:
its horizontal part has unit length and its vertical part is h_z. Given (b_m, s, h_z) each
heading is in closed form, psi_i = atan2(v_iy, v_ix) (variable projection), and the residuals
s (|v_i,xy| - 1) and s (v_iz - h_z) are minimised over the five (b_m, s, h_z) alone, from
several starts (the dip scanned from the equator to 80 deg either way; b_m from the circle the
readings trace), for each candidate Q. The headings then come from the tilts and a field of
the right shape, not from the raw means: an offset of any size is fitted, not assumed away,
and a tilt's share of the vertical field is removed before the heading is read.

Then, from the best start of each candidate and with at least :data:`SOFT_IRON_MIN_POSES` poses,
K_m = s Q^T (I + E) Q with E symmetric (the ``ardupilot`` model's soft iron) is fitted as well, E
held near zero by a weak prior (:data:`_SOFT_IRON_SD`) so that few poses stay posed: soft iron
twice the usual (diagonals 0.8-1.2, off-diagonals 0.1) beside a 75 deg dip then moves a heading
by a few degrees at most. A fit whose field is no Earth field (:data:`PLAUSIBLE_FIELD_MGAUSS`,
:data:`PLAUSIBLE_DIP_DEG`) is not taken. The headings are good enough to count headings
:data:`mavcal.coverage.REACH_HEADING_DEG` apart and to tell a compass's yaw mounting from 10-15 deg
tilts, which is all this fit is for; the calibration itself is :func:`mavcal.core.held.calibrate_held`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from mavcal.errors import InsufficientDataError

__all__ = ["ProvisionalHeadings", "provisional_headings", "YAW_ORIENTATIONS"]

#: ArduPilot's rotations about the vertical axis (ROTATION_NONE, YAW_90, YAW_180, YAW_270): deg
YAW_ORIENTATIONS: dict[int, float] = {0: 0.0, 2: 90.0, 4: 180.0, 6: 270.0}
_DIPS_DEG = tuple(range(-80, 81, 20))
#: a fit whose field is outside these (mGauss; Earth's is 220-670 at the surface, a compass's scale may be
#: 25 % off) or steeper than this dip is no Earth field: small tilts let a huge vertical field and offset
#: explain any few poses, and such a fit is not taken
PLAUSIBLE_FIELD_MGAUSS = (150.0, 1000.0)
PLAUSIBLE_DIP_DEG = 85.0


def _plausible(x: np.ndarray) -> bool:
    f = x[3] * np.hypot(1.0, x[4])
    return (bool(np.all(np.isfinite(x))) and x[3] > 0 and PLAUSIBLE_FIELD_MGAUSS[0] <= f <= PLAUSIBLE_FIELD_MGAUSS[1]
            and abs(x[4]) <= np.tan(np.radians(PLAUSIBLE_DIP_DEG)))


@dataclass(frozen=True)
class ProvisionalHeadings:
    """The provisional fit's headings and what it fitted.

    ``psi_rad``: each pose's heading (N,), up to a common turn; ``orientation``: the yaw rotation
    (ArduPilot's number) of the candidate that fits best; ``rms_mgauss``: each candidate's RMS
    residual (mGauss) by orientation; ``b_mgauss``, ``s_mgauss``, ``h_z``: the best fit."""

    psi_rad: np.ndarray
    orientation: int
    rms_mgauss: dict[int, float]
    b_mgauss: np.ndarray
    s_mgauss: float
    h_z: float


def _rotz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _levelled(x: np.ndarray, T: np.ndarray, QM: np.ndarray) -> np.ndarray:
    """v_i = T_i^T (Q mu_m[i] - Q b_m) / s for x = (Q b_m (3), s, h_z)."""
    d = (QM - x[:3]) / x[3]
    return np.einsum("nji,nj->ni", T, d)


def _residuals(x: np.ndarray, T: np.ndarray, QM: np.ndarray) -> np.ndarray:
    v = _levelled(x, T, QM)
    return x[3] * np.concatenate([np.hypot(v[:, 0], v[:, 1]) - 1.0, v[:, 2] - x[4]])


#: the soft-iron stage's prior: a deviation of K_m / s from the identity by this (relative) costs as much
#: as one reading off by :data:`_PRIOR_NOISE_MGAUSS` (keeps the fit posed when the poses cannot tell)
_SOFT_IRON_SD = 0.1
_PRIOR_NOISE_MGAUSS = 3.0
#: poses from which the soft iron is fitted (2 equations a pose, 11 unknowns)
SOFT_IRON_MIN_POSES = 5
_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _soft(k: np.ndarray) -> np.ndarray:
    E = np.zeros((3, 3))
    for v, (i, j) in zip(k, _SYM):
        E[i, j] = E[j, i] = v
    return np.eye(3) + E


def _residuals_soft(x: np.ndarray, T: np.ndarray, QM: np.ndarray) -> np.ndarray:
    """As :func:`_residuals` with K_m = s Q^T (I + E) Q, E symmetric (x[5:11]), and its prior."""
    d = np.linalg.solve(_soft(x[5:]), (QM - x[:3]).T).T / x[3]
    v = np.einsum("nji,nj->ni", T, d)
    return np.concatenate([x[3] * np.hypot(v[:, 0], v[:, 1]) - x[3], x[3] * (v[:, 2] - x[4]),
                           _PRIOR_NOISE_MGAUSS * x[5:] / _SOFT_IRON_SD])


def _ring(M: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of the circle the points (N, 3) trace (an algebraic fit in the
    plane of their two largest spreads; their mean and spread when that is degenerate)."""
    c0 = M.mean(axis=0)
    c = M - c0
    _, sv, Vt = np.linalg.svd(c, full_matrices=False)
    r0 = float(np.sqrt(np.mean((c ** 2).sum(axis=1))))
    if len(M) < 3 or sv[0] <= 1e-9 * max(float(np.abs(M).max()), 1.0):
        return c0, max(r0, 1.0)
    xy = c @ Vt[:2].T
    A = np.c_[2.0 * xy, np.ones(len(xy))]
    sol = np.linalg.lstsq(A, (xy ** 2).sum(axis=1), rcond=None)[0]
    centre = sol[:2]
    r2 = sol[2] + centre @ centre
    if not np.all(np.isfinite(sol)) or r2 <= 0:
        return c0, max(r0, 1.0)
    return c0 + centre @ Vt[:2], float(np.sqrt(r2))


def provisional_headings(T: np.ndarray, mag_means: np.ndarray,
                         orientations: tuple[int, ...] = (0,)) -> ProvisionalHeadings:
    """The headings (module docstring) of poses with tilts ``T`` (N, 3, 3), body from levelled,
    as :func:`mavcal.core.held.tilts_of` gives them) and raw compass means ``mag_means`` (N, 3,
    mGauss), fitting each yaw rotation in ``orientations`` (ArduPilot's numbers, keys of
    :data:`YAW_ORIENTATIONS`) and keeping the best. InsufficientDataError with fewer than 3 poses."""
    T = np.asarray(T, dtype=float).reshape(-1, 3, 3)
    M = np.asarray(mag_means, dtype=float).reshape(-1, 3)
    if M.shape[0] < 3:
        raise InsufficientDataError("a provisional compass fit needs at least 3 poses")
    rms: dict[int, float] = {}
    best: tuple[float, int, np.ndarray] | None = None
    z = np.array([0.0, 0.0, 1.0])
    for o in orientations:
        Q = _rotz(YAW_ORIENTATIONS[o])  # compass -> body
        QM = M @ Q.T
        centre, r = _ring(QM)
        fit: tuple[float, np.ndarray] | None = None
        for dip in _DIPS_DEG:  # K_m = s Q^T: the basin, from every dip
            h = float(np.tan(np.radians(dip)))
            x0 = np.r_[centre - r * h * z, r, h]
            try:
                res = least_squares(_residuals, x0, args=(T, QM), method="lm", max_nfev=200)
            except (ValueError, np.linalg.LinAlgError):
                continue
            if not _plausible(res.x):
                continue
            c = float(res.fun @ res.fun)
            if fit is None or c < fit[0]:
                fit = (c, res.x)
        if fit is None:
            continue
        x1 = np.r_[fit[1], np.zeros(6)]  # then the symmetric soft iron, from that basin, when the poses are
        try:  # enough for its 6 more unknowns (with fewer, it bends a few poses' headings together)
            if M.shape[0] < SOFT_IRON_MIN_POSES:
                raise ValueError("too few poses")
            res = least_squares(_residuals_soft, x1, args=(T, QM), method="lm", max_nfev=400)
            if _plausible(res.x):
                fit = (float(res.fun @ res.fun), res.x)
        except (ValueError, np.linalg.LinAlgError):
            pass
        rms[o] = float(np.sqrt(fit[0] / (2 * M.shape[0])))
        if best is None or fit[0] < best[0]:
            best = (fit[0], o, fit[1])
    if best is None:
        raise InsufficientDataError("the provisional compass fit did not converge")
    _, o, x = best
    Q = _rotz(YAW_ORIENTATIONS[o])
    K = _soft(x[5:]) if len(x) > 5 else np.eye(3)
    d = np.linalg.solve(K, (M @ Q.T - x[:3]).T).T / x[3]
    v = np.einsum("nji,nj->ni", T, d)
    return ProvisionalHeadings(np.arctan2(v[:, 1], v[:, 0]), o, rms, Q.T @ x[:3], float(x[3]), float(x[4]))
