"""The reference optimum the engine is scored against: scipy ``least_squares`` on the paper's
reduced cost J' (Eq. ``reduced_cost``), started at the truth in the paper's gauge.

Shared by ``paper_benchmark.py`` and ``stress_optimum.py`` so that both score against the
same cost. The parameters are (K_a upper triangle, b_a, K_m, b_m, h_z, one rotation vector per
interval applied to the true orientations); the residuals are the interval means' misfits
whitened by the noise covariances and weighted by sqrt(n), so J' = 2 * ``sol.cost``.
:func:`partial_cost` evaluates the same residuals at any parameters (e.g. a calibration's
returned ones), independently of mavcal's own residual code.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import least_squares

from mavcal.core.rotations import exp_so3

G = np.array([0.0, 0.0, -1.0])
_IU = np.triu_indices(3)


def unpack(x: np.ndarray, R0: np.ndarray):
    """(K_a, b_a, K_m, b_m, h_z, R) of a parameter vector."""
    Ka = np.zeros((3, 3))
    Ka[_IU] = x[:6]
    return Ka, x[6:9], x[9:18].reshape(3, 3), x[18:21], x[21], R0 @ exp_so3(x[22:].reshape(len(R0), 3))


def _weights(accel_sets, mag_sets, Sa, Sm):
    mu_a = np.array([x.mean(0) for x in accel_sets])
    mu_m = np.array([x.mean(0) for x in mag_sets])
    wa = np.sqrt(np.array([len(x) for x in accel_sets], float))[:, None]
    wm = np.sqrt(np.array([len(x) for x in mag_sets], float))[:, None]
    La = np.linalg.cholesky(np.linalg.inv(Sa)).T
    Lm = np.linalg.cholesky(np.linalg.inv(Sm)).T
    return mu_a, mu_m, wa, wm, La, Lm


def _residuals(Ka, ba, Km, bm, hz, R, w) -> np.ndarray:
    mu_a, mu_m, wa, wm, La, Lm = w
    ra = ((np.einsum("ij,njk,k->ni", Ka, R, G) + ba - mu_a) @ La.T) * wa
    rm = ((np.einsum("ij,njk,k->ni", Km, R, [1, 0, hz]) + bm - mu_m) @ Lm.T) * wm
    return np.concatenate([ra.ravel(), rm.ravel()])


def partial_cost(accel_sets: Sequence[np.ndarray], mag_sets: Sequence[np.ndarray], Sa: np.ndarray, Sm: np.ndarray,
                 K_a, b_a, K_m, b_m, h_z: float, R: np.ndarray) -> float:
    """J' (Eq. ``partial_cost``) of the readings at the given parameters with noise covariances Sa, Sm."""
    r = _residuals(K_a, b_a, K_m, b_m, h_z, R, _weights(accel_sets, mag_sets, Sa, Sm))
    return float(r @ r)


def least_squares_from_truth(accel_sets: Sequence[np.ndarray], mag_sets: Sequence[np.ndarray], truth,
                             Sa: np.ndarray, Sm: np.ndarray, *, tol: float = 1e-12, max_nfev: int | None = None):
    """(scipy result, R0): min J' from ``truth.in_paper_gauge()`` with noise covariances Sa, Sm."""
    K_a, b_a, K_m, b_m, h_z, R0 = truth.in_paper_gauge()
    w = _weights(accel_sets, mag_sets, Sa, Sm)
    x0 = np.concatenate([K_a[_IU], b_a, K_m.ravel(), b_m, [h_z], np.zeros(3 * len(R0))])

    def fun(x):
        return _residuals(*unpack(x, R0), w)

    sol = least_squares(fun, x0, method="trf", xtol=tol, ftol=tol, gtol=tol, max_nfev=max_nfev)
    return sol, R0
