"""An accelerometer calibrated from its own still intervals alone (no compass).

The per-sensor verdict of an accelerometer must not depend on a compass's misfit
(issue 10): its held-out error and its tilt bound come from this fit, and an
accelerometer whose compass is rejected, absent or not wanted (``--accel-only``) is
written from it.

Model: the accelerometer half of the paper's reading model (Eq. ``sensor_reading_model``),
``u_i = K_a R_i g + b_a`` with ``g = [0, 0, -1]``. Without a compass only the gravity
direction ``v_i = R_i g`` of each interval is observed (two degrees of freedom), so the
unknowns are K_a (upper triangular: the same gauge as the joint fit; diagonal with fewer
than :data:`MIN_INTERVALS_UPPER` intervals), b_a and the v_i. Maximum likelihood on the
interval means weighted by ``n_i Sigma_a^-1`` (the paper's reduced cost J' restricted to
the accelerometer), solved by Gauss-Newton/trust region from the core's ellipsoid start.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from mavcal.core.initial import fit_ellipsoid, fit_sphere
from mavcal.core.stats import interval_stats
from mavcal.errors import EstimationError, InsufficientDataError

__all__ = ["AccelFit", "fit_accel", "holdout_accel_mps2", "MIN_INTERVALS_DIAG", "MIN_INTERVALS_UPPER"]

G_UNIT = np.array([0.0, 0.0, -1.0])
MIN_INTERVALS_DIAG = 6  # 6 + 2N unknowns, 3N equations
MIN_INTERVALS_UPPER = 12  # 9 + 2N unknowns; 3 spare equations at least


@dataclass(frozen=True, eq=False)
class AccelFit:
    """K_a (upper triangular or diagonal), b_a (same units as the readings), the covariance
    of ``[K_a entries..., b_a]`` (``param_names``), the gravity directions v_i (engine frame)."""

    gain: np.ndarray
    bias: np.ndarray
    form: str  # "upper" or "diag"
    param_names: tuple[str, ...]
    param_cov: np.ndarray
    directions: np.ndarray
    cost: float
    dof: int
    n_intervals: int


_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_DIAG = ((0, 0), (1, 1), (2, 2))


def _tangent(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(v, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(v, e1)


def _unpack(theta: np.ndarray, idx, v0: np.ndarray, basis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    K = np.zeros((3, 3))
    for k, (i, j) in enumerate(idx):
        K[i, j] = theta[k]
    b = theta[len(idx):len(idx) + 3]
    ab = theta[len(idx) + 3:].reshape(-1, 2)
    v = v0 + ab[:, :1] * basis[:, 0] + ab[:, 1:] * basis[:, 1]
    return K, b, v / np.linalg.norm(v, axis=1, keepdims=True)


def fit_accel(accel_sets: Sequence[np.ndarray], *, noise_floor: float | None = None,
              form: str = "auto") -> AccelFit:
    """Fit one accelerometer from its still intervals alone (see the module docstring).

    Raises InsufficientDataError with fewer than :data:`MIN_INTERVALS_DIAG` intervals,
    EstimationError on degenerate orientations.
    """
    st = interval_stats(accel_sets, "accel_sets", noise_floor=noise_floor)
    N = st.mu.shape[0]
    if N < MIN_INTERVALS_DIAG:
        raise InsufficientDataError(f"{N} still interval(s): an accelerometer alone needs at least "
                                    f"{MIN_INTERVALS_DIAG} in different orientations")
    if form == "auto":
        form = "upper" if N >= MIN_INTERVALS_UPPER else "diag"
    idx = _UPPER if form == "upper" else _DIAG
    e = fit_ellipsoid(st.mu) if form == "upper" else fit_sphere(st.mu)
    K0 = np.asarray(e.K) if form == "upper" else np.diag(np.abs(np.diag(np.asarray(e.K))))
    b0 = np.asarray(e.b, float)
    v0 = (st.mu - b0) @ np.linalg.inv(K0).T
    if not np.all(np.isfinite(v0)) or np.any(np.linalg.norm(v0, axis=1) == 0):
        raise EstimationError("degenerate accelerometer start: the orientations do not span enough directions")
    v0 = v0 / np.linalg.norm(v0, axis=1, keepdims=True)
    basis = np.array([np.stack(_tangent(v)) for v in v0])  # (N, 2, 3)
    L_inv = np.linalg.inv(np.linalg.cholesky(st.sigma_hat))
    w = np.sqrt(st.n)[:, None]

    def resid(theta: np.ndarray) -> np.ndarray:
        K, b, v = _unpack(theta, idx, v0, basis)
        return ((st.mu - v @ K.T - b) @ L_inv.T * w).ravel()

    theta0 = np.concatenate([[K0[i, j] for i, j in idx], b0, np.zeros(2 * N)])
    res = least_squares(resid, theta0, method="lm" if 3 * N >= theta0.size else "trf", xtol=1e-12, ftol=1e-12)
    K, b, v = _unpack(res.x, idx, v0, basis)
    if np.any(np.diag(K) <= 0):
        raise EstimationError("the accelerometer fit reached a mirrored gain: the orientations do not span")
    cost = float(np.sum(res.fun ** 2))
    dof = 3 * N - theta0.size
    scale = max(1.0, cost / dof) if dof > 0 else 1.0
    cov = np.linalg.pinv(res.jac.T @ res.jac)[:len(idx) + 3, :len(idx) + 3] * scale
    names = tuple(f"K_a[{i + 1}{j + 1}]" for i, j in idx) + ("b_a[x]", "b_a[y]", "b_a[z]")
    return AccelFit(gain=K, bias=b, form=form, param_names=names, param_cov=cov, directions=v, cost=cost,
                    dof=int(dof), n_intervals=N)


def sample_accel(fit: AccelFit, n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` draws ``(K_a, b_a)`` of the fit's parameter distribution (Gaussian, its covariance)."""
    idx = _UPPER if fit.form == "upper" else _DIAG
    mean = np.concatenate([[fit.gain[i, j] for i, j in idx], fit.bias])
    out = []
    for th in rng.multivariate_normal(mean, fit.param_cov, size=n, method="eigh"):
        K = np.zeros((3, 3))
        for k, (i, j) in enumerate(idx):
            K[i, j] = th[k]
        out.append((K, th[len(idx):]))
    return out


def _nearest_on_ellipsoid(K: np.ndarray, b: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """The reading ``K v + b`` (|v| = 1) nearest to ``mu`` (a few Gauss-Newton steps on v)."""
    v = np.linalg.solve(K, mu - b)
    v /= np.linalg.norm(v)
    for _ in range(10):
        e1, e2 = _tangent(v)
        J = K @ np.stack([e1, e2], 1)
        step = np.linalg.lstsq(J, mu - K @ v - b, rcond=None)[0]
        v = v + step[0] * e1 + step[1] * e2
        v /= np.linalg.norm(v)
        if np.abs(step).max() < 1e-12:
            break
    return K @ v + b


def holdout_accel_mps2(accel_sets: Sequence[np.ndarray], *, noise_floor: float | None = None,
                       form: str = "auto", cluster_deg: float = 30.0) -> float:
    """RMS leave-one-interval-out error of the accelerometer alone (the reading units).

    As :func:`mavcal.quality.holdout_errors`, only intervals whose gravity direction is
    seen again in another interval (within ``cluster_deg``) are held out; the refit without
    interval j predicts j's mean as the nearest point of its ellipsoid. NaN when no interval
    qualifies or too few remain.
    """
    sets = list(accel_sets)
    N = len(sets)
    if N - 1 < MIN_INTERVALS_DIAG:
        return float("nan")
    if form == "auto":
        form = "upper" if N - 1 >= MIN_INTERVALS_UPPER else "diag"
    mu = np.array([np.asarray(s, float).mean(0) for s in sets])
    dirs = mu / np.linalg.norm(mu, axis=1, keepdims=True)
    close = (dirs @ dirs.T) > np.cos(np.radians(cluster_deg))
    errs = []
    for j in range(N):
        if close[j].sum() < 2:
            continue
        try:
            f = fit_accel([sets[i] for i in range(N) if i != j], noise_floor=noise_floor, form=form)
        except (EstimationError, InsufficientDataError, np.linalg.LinAlgError):
            continue
        errs.append(np.linalg.norm(mu[j] - _nearest_on_ellipsoid(f.gain, f.bias, mu[j])))
    return float(np.sqrt(np.mean(np.square(errs)))) if errs else float("nan")
