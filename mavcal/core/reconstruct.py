"""Orientations of new still intervals with a calibration held fixed, and the paper's
reconstruction error (Sec. VIII): :func:`estimate_orientations`, :func:`reconstruction_error`
(also importable from :mod:`mavcal.core.calibrate`); :func:`orientations_from_means` when the
interval means are already known."""
from __future__ import annotations

import numpy as np

from mavcal.core import steps
from mavcal.core.stats import IntervalStats, interval_means
from mavcal.core.types import Calibration
from mavcal.errors import EstimationError

__all__ = ["estimate_orientations", "orientations_from_means", "reconstruction_error"]


def _means(sets, name: str) -> tuple[np.ndarray, np.ndarray]:
    seq = list(sets)
    if not seq:
        raise EstimationError(f"{name} is empty")
    xs = []
    for i, s in enumerate(seq):
        x = np.asarray(s, dtype=float)
        if x.ndim == 1:
            x = x[None]
        if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 1:
            raise EstimationError(f"{name}[{i}] must have shape (n_i, 3), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise EstimationError(f"{name}[{i}] contains NaN/inf readings")
        xs.append(x)
    return interval_means(xs), np.array([x.shape[0] for x in xs], dtype=float)


def estimate_orientations(calibration: Calibration, accel_sets, mag_sets) -> np.ndarray:
    """Orientations (M, 3, 3) of new still intervals with the calibration held fixed.

    The paper's test-set procedure (Sec. VIII): the approximation of Eq.
    ``rotation_approximation``, then direct minimisation of Eq. ``rotation_estimation``.
    """
    mu_a, n_a = _means(accel_sets, "accel_sets")
    mu_m, n_m = _means(mag_sets, "mag_sets")
    return orientations_from_means(calibration, mu_a, n_a, mu_m, n_m)


def orientations_from_means(calibration: Calibration, mu_a: np.ndarray, n_a: np.ndarray, mu_m: np.ndarray,
                            n_m: np.ndarray) -> np.ndarray:
    """:func:`estimate_orientations` of M intervals given by their mean readings ``mu_a``,
    ``mu_m`` (M, 3) and sample counts ``n_a``, ``n_m`` (M,) (the same result, to the bit, as
    from the readings whose :func:`~mavcal.core.stats.interval_means` they are)."""
    if len(mu_a) != len(mu_m):
        raise EstimationError("accel_sets and mag_sets must have the same number of intervals")
    c = calibration
    a = IntervalStats(mu_a, n_a, np.zeros((3, 3)), c.accel.noise_cov, 1.0)
    m = IntervalStats(mu_m, n_m, np.zeros((3, 3)), c.mag.noise_cov, 1.0)
    st = steps.State(c.accel.gain, c.accel.bias, c.mag.gain, c.mag.bias, c.h_z, np.zeros((len(mu_a), 3, 3)),
                     c.accel.noise_cov, c.mag.noise_cov)
    st = steps.rotations_approx(st, a, m)
    st = steps.rotations_direct(st, a, m, iterations=50, tol=1e-15)
    return st.R


def reconstruction_error(calibration: Calibration, truth=None, *, orientations=None, mu_accel=None,
                         mu_mag=None, noise_cov_accel=None, noise_cov_mag=None, n_accel=None,
                         n_mag=None) -> tuple[float, float]:
    """The paper's delta_s (Eq. ``distance``) for both sensors: (delta_a, delta_m).

    delta_s = sqrt( sum_i Delta[i] (mu_s[i] - mu_breve_s[i])^T Sigma_s^-1 (...) / sum_i Delta[i] )

    mu_s[i] are the *true* means and Sigma_s the *true* covariance (from ``truth``, e.g. a
    :class:`mavcal.sim.Truth`, or given explicitly); mu_breve_s[i] = K_s R_i s^I + b_s is
    rebuilt from the calibration with ``orientations`` (default: the calibration's own,
    i.e. the training set; for a test set pass :func:`estimate_orientations`).
    """
    if truth is not None:
        mu_accel = truth.mu_accel if mu_accel is None else mu_accel
        mu_mag = truth.mu_mag if mu_mag is None else mu_mag
        noise_cov_accel = truth.noise_cov_accel if noise_cov_accel is None else noise_cov_accel
        noise_cov_mag = truth.noise_cov_mag if noise_cov_mag is None else noise_cov_mag
        n_accel = truth.n_accel if n_accel is None else n_accel
        n_mag = truth.n_mag if n_mag is None else n_mag
    if mu_accel is None or mu_mag is None or noise_cov_accel is None or noise_cov_mag is None:
        raise EstimationError("reconstruction_error needs the true means and covariances (truth=...)")
    R = calibration.orientations if orientations is None else np.asarray(orientations, dtype=float)
    c = calibration
    out = []
    for mu, Sigma, n, sm, f in ((mu_accel, noise_cov_accel, n_accel, c.accel, c.gravity),
                                (mu_mag, noise_cov_mag, n_mag, c.mag, c.field)):
        mu = np.asarray(mu, dtype=float)
        if mu.shape != (R.shape[0], 3):
            raise EstimationError(f"true means of shape {mu.shape} do not match {R.shape[0]} orientations")
        n = np.ones(len(mu)) if n is None else np.asarray(n, dtype=float)
        rec = (sm.gain @ (R @ f)[..., None])[..., 0] + sm.bias
        d = mu - rec
        q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(Sigma), d)
        out.append(float(np.sqrt(np.sum(n * q) / np.sum(n))))
    return out[0], out[1]
