"""The paper's fit, Secs. VI-VII: a start state from the per-sensor closed-form fits, the R/h_z
search and the orientation approximation (:func:`initial_state`, one per distinct minimum:
:func:`initial_states`), and the block steps iterated until J_{k-1} - J_k < gamma or handed to the
joint refinement (:func:`run_block_steps`). :mod:`mavcal.core.calibrate` drives them.
"""
from __future__ import annotations

import numpy as np

from mavcal.core import steps
from mavcal.core.initial import (
    fit_axis_ellipsoid,
    fit_ellipsoid,
    fit_sphere,
    rotation_hz_minima,
    search_rotation_hz,
)
from mavcal.core.stats import IntervalStats
from mavcal.errors import EstimationError

__all__ = ["initial_state", "initial_states", "run_block_steps"]


def initial_state(a: IntervalStats, m: IntervalStats, rng: np.random.Generator, *,
                  accel_form: str = "upper", restarts: int = 24, sphere: bool = False,
                  shape: str = "quadric") -> steps.State:
    """Sec. VI: closed-form gains and biases, the R/h_z search, the orientation approximation.

    ``shape`` of the per-sensor fits: "quadric", the general quadric of Eq. ``J_approx``
    (needs N >= 9 intervals; falls back to a sphere when it is not a well-conditioned
    ellipsoid); "axes", an ellipsoid with axes along the sensor axes (N >= 7); "sphere"
    (``sphere=True`` is the same). The other shapes are the extra starts of the search.
    """
    z_a, z_m, ea, em = _normalised(a, m, accel_form, "sphere" if sphere else shape)
    R, h_z, _ = search_rotation_hz(z_a, z_m, a.n + m.n, rng, restarts=restarts)
    return _state_from(a, m, ea, em, R, h_z)


def _normalised(a: IntervalStats, m: IntervalStats, accel_form: str, shape: str):
    """Per-sensor closed-form fits of the given shape and the normalised readings z_s."""
    N = a.mu.shape[0]
    if (shape == "quadric" and N < 9) or (shape == "axes" and N < 7):
        shape = "sphere"
    fit = {"quadric": fit_ellipsoid, "axes": fit_axis_ellipsoid, "sphere": fit_sphere}[shape]
    ea = fit(a.mu) if (accel_form == "upper" or shape == "axes") else fit_sphere(a.mu)
    em = fit(m.mu)
    z_a = np.linalg.solve(ea.K, (a.mu - ea.b).T).T
    z_m = np.linalg.solve(em.K, (m.mu - em.b).T).T
    return z_a, z_m, ea, em


def _state_from(a: IntervalStats, m: IntervalStats, ea, em, R: np.ndarray, h_z: float) -> steps.State:
    """Normalisation h_x = 1 of a (R, h_z) solution and the orientation approximation."""
    # R is the proper member of the (R, h_z) / (-R, -h_z) pair: the canonical mirror twin
    h_z = float(np.clip(h_z, -0.999999, 0.999999))
    h_x = np.sqrt(1.0 - h_z * h_z)
    st = steps.State(K_a=ea.K, b_a=ea.b, K_m=em.K @ R * h_x, b_m=em.b, h_z=h_z / h_x,
                     R=np.zeros((a.mu.shape[0], 3, 3)), Sigma_a=a.sigma_hat, Sigma_m=m.sigma_hat)
    return steps.rotations_approx(st, a, m)


def initial_states(a: IntervalStats, m: IntervalStats, rng: np.random.Generator, *, accel_form: str = "upper",
                   restarts: int = 24, shape: str = "quadric", limit: int = 3) -> list[steps.State]:
    """One initial state per distinct minimum of the R/h_z search (:func:`rotation_hz_minima`)."""
    z_a, z_m, ea, em = _normalised(a, m, accel_form, shape)
    return [_state_from(a, m, ea, em, R, h_z)
            for R, h_z, _ in rotation_hz_minima(z_a, z_m, a.n + m.n, rng, restarts=restarts, limit=limit)]


def run_block_steps(st: steps.State, a: IntervalStats, m: IntervalStats, method: str, tol: float,
                    max_iter: int, handoff_rate: float | None = None,
                    on_iteration=None) -> tuple[steps.State, int, str]:
    """Sec. VII: iterate rotation, bias/field, gain (and covariance) steps until J_{k-1} - J_k < tol.

    With ``handoff_rate`` (used when the joint refinement follows), the steps also stop once
    they converge linearly slower than that rate (J_{k-1} - J_k > rate (J_{k-2} - J_{k-1})):
    from there Levenberg-Marquardt reaches the optimum in a few iterations, where the block
    steps would need hundreds. Returns (state, iterations, how): how is "gamma", "handoff"
    or "limit". ``on_iteration(k, state, J, dJ, checked)`` is called after every iteration
    (``checked`` is False on the iteration where the approximation was abandoned, when the
    stop rule is not evaluated); benchmarks use it to stop at many gammas in one run.
    """
    refit = method in ("fcar", "dcar")
    cost = steps.complete_cost if refit else steps.partial_cost
    approx = method != "ncdr"
    J_prev = cost(st, a, m)
    dJ_prev = np.inf
    for k in range(1, max_iter + 1):
        st = steps.rotations_approx(st, a, m) if approx else steps.rotations_direct(st, a, m)
        st = steps.bias_field_step(st, a, m)
        st = steps.gain_step(st, a, m)
        if refit:
            st = steps.covariance_step(st, a, m, diagonal=(method == "dcar"))
        J = cost(st, a, m)
        if not np.isfinite(J):
            raise EstimationError("the block steps diverged (non-finite cost); the data may not fit the "
                                  "linear sensor model (sensor saturation, magnetic disturbance?)")
        dJ = J_prev - J
        if on_iteration is not None:
            on_iteration(k, st, J, dJ, not (approx and J > J_prev))
        if approx and J > J_prev:
            approx = False  # the approximation stopped helping: direct minimisation from now on
            if handoff_rate is not None:
                return st, k, "handoff"
        elif dJ < tol:
            return st, k, "gamma"
        elif handoff_rate is not None and k >= 3 and dJ > handoff_rate * dJ_prev:
            return st, k, "handoff"
        J_prev, dJ_prev = J, max(dJ, 0.0)
    return st, max_iter, "limit"
