"""An accelerometer calibrated from its own still intervals alone (no compass).

The per-sensor verdict of an accelerometer must not depend on a compass's misfit
(issue 10): its held-out error and its tilt bound come from this fit, and an
accelerometer whose compass is rejected, absent or not wanted (``--accel-only``) is
written from it.

Model: the accelerometer half of the paper's reading model (Eq. ``sensor_reading_model``),
``u_i = K_a R_i g + b_a`` with ``g = [0, 0, -1]``. Without a compass only the gravity
direction ``v_i = R_i g`` of each interval is observed (two degrees of freedom), so the
unknowns are K_a (upper triangular, the same gauge as the joint fit, or diagonal: see below),
b_a and the v_i. Maximum likelihood on the
interval means weighted by ``n_i Sigma_a^-1`` (the paper's reduced cost J' restricted to
the accelerometer), solved by Levenberg-Marquardt from the core's ellipsoid start with the
v_i eliminated in closed form at each step (Schur complement: O(N) per iteration, where a dense solver over the
9 + 2N unknowns costs O(N^3)); the covariance of ``[K_a, b_a]`` is the inverse of that
reduced normal matrix (the marginal of the full one).

**Which form, and how uncertain** (issue 22: a capture of 8-14 poses must never reject a clean
accelerometer). The number of intervals does not say whether the data identify the
upper-triangular gain: poses that differ only in heading add intervals but no gravity
direction, and the ellipsoid's 9 parameters need 9 distinct directions in general position.
At 12 intervals the former rule (upper from 12 on) could meet 8-10 directions, a nearly
singular reduced normal matrix and a tilt bound of 59-88 deg. So the form is chosen as the
joint fit chooses its model (:func:`mavcal.core.calibrate`, Wald tests down the model chain):
the diagonal form is fitted, the upper-triangular one too from :data:`MIN_INTERVALS_UPPER`
intervals, and the upper one is used only when the likelihood-ratio test rejects the
diagonal one, ``chi2_sf(J'_diag - J'_upper, 3) <= FORM_ALPHA`` (the three cross-axis terms,
Wilks' theorem; the statistic needs no curvature at the upper fit, which is exactly what is
unreliable when its geometry is poor). The result says which form and why (``form_reason``).

Why ``FORM_ALPHA`` is 1e-4, not 1 %: with 10-11 intervals the upper form has 1-2 spare
equations and its cross-axis terms are barely identified, so once it is chosen the tilt bound
is about 2 deg and the tilt gate (0.5 deg) rejects the accelerometer. At 1 % a clean
accelerometer met that one capture in a hundred (CI saw it: a loopback capture of 10 poses,
accel2 rejected at 2.23 deg; simulated, 4 in 200 at 10 poses). At 1e-4: 0 in 200 at 10 and 14
poses. The price is power against small real cross-axis terms, which ArduPilot cannot hold
anyway (INS_ACCSCAL is diagonal): simulated with 10 and 14 poses, cross-axis terms of 0.06,
0.11 and 0.23 deg left the written values' true tilt error at most 0.12, 0.17 and 0.28 deg
whichever alpha chose the form, all under the 0.3 deg target (``benchmarks/accel_form.py``,
``benchmarks/results/accel_form.md``).

The covariance is the inverse Fisher information of the reduced cost J' (Cramer-Rao) with the
noise covariance measured from the scatter within the intervals (paper Eq.
``covariance_initial_estimation``, sum(n_i) - N degrees of freedom, floored at the
telemetry's quantisation noise step / sqrt(12), :func:`mavcal.core.stats.interval_stats`):
that is the covariance of a correct model. J'/dof measures a misfit between the intervals
(a vehicle not quite still, vibration), but with the few spare equations of a short capture
it is itself very uncertain (J' ~ chi2_dof: with 2 dof J'/dof exceeds 3.0 one time in 20 on
perfect data), so the covariance is inflated by J'/dof only when the chi2 goodness-of-fit
test rejects the model, ``chi2_sf(J', dof) <= MISFIT_ALPHA`` (a stated 1 % false-alarm
rate; a larger misfit always shows as the held-out error too). ``misfit_scale`` is the
factor used.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from mavcal.core.initial import fit_ellipsoid, fit_sphere
from mavcal.core.stats import IntervalStats, chi2_sf, interval_means, interval_stats, stats_subset
from mavcal.errors import EstimationError, InsufficientDataError

__all__ = ["AccelFit", "fit_accel", "holdout_accel_mps2", "holdout_folds", "pool_index", "MIN_INTERVALS_DIAG",
           "MIN_INTERVALS_UPPER", "FORM_ALPHA", "MISFIT_ALPHA", "candidate_information", "tilt_variances",
           "tilt_jacobians",
           "LOO_MAX_INTERVALS", "HOLDOUT_FOLDS", "HOLDOUT_POOL_MAX"]

G_UNIT = np.array([0.0, 0.0, -1.0])
MIN_INTERVALS_DIAG = 6  # 6 + 2N unknowns, 3N equations
MIN_INTERVALS_UPPER = 10  # 9 + 2N unknowns: from here the upper-triangular form is tried (1 spare equation)
FORM_ALPHA = 1e-4  # the upper-triangular form only when the likelihood-ratio test rejects the diagonal one (docstring)
MISFIT_ALPHA = 0.01  # the covariance inflated by J'/dof only when the chi2 test rejects the fit


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
    information: np.ndarray | None = None  # the reduced normal matrix S (unscaled Fisher information of [K, b])
    noise_cov: np.ndarray | None = None  # Sigma_a the weights used
    misfit_scale: float = 1.0  # the factor the covariance was inflated by (1: the chi2 test did not reject)
    form_reason: str = ""


_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_DIAG = ((0, 0), (1, 1), (2, 2))


def _tangent(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(v, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(v, e1)


def _gain(theta: np.ndarray, idx) -> np.ndarray:
    K = np.zeros((3, 3))
    for k, (i, j) in enumerate(idx):
        K[i, j] = theta[k]
    return K


def _basis(v: np.ndarray) -> np.ndarray:
    """(N, 2, 3): an orthonormal basis of the tangent plane at each unit vector v_i (vectorised
    :func:`_tangent`)."""
    a = np.where(np.abs(v[:, :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    e1 = np.cross(v, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(v, e1)], 1)


def _jacobians(K: np.ndarray, v: np.ndarray, basis: np.ndarray, idx, L_inv: np.ndarray,
               w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-interval Jacobian blocks of the weighted residuals ``w_i L^-1 (mu_i - K v_i - b)``:
    global (N, 3, P) over ``[K entries, b]`` and local (N, 3, 2) over the tangent step of v_i."""
    N = v.shape[0]
    Jg = np.empty((N, 3, len(idx) + 3))
    for m, (i, j) in enumerate(idx):
        Jg[:, :, m] = -w * L_inv[:, i][None, :] * v[:, j:j + 1]
    Jg[:, :, len(idx):] = -w[:, :, None] * L_inv[None]
    Jl = -w[:, :, None] * np.einsum("ab,nbc->nac", L_inv @ K, np.swapaxes(basis, 1, 2))
    return Jg, Jl


def _schur_step(Jg: np.ndarray, Jl: np.ndarray, r: np.ndarray, lam: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One damped Gauss-Newton step (Levenberg-Marquardt, ``lam`` on the diagonal) with the
    per-interval unknowns eliminated in closed form (Schur complement): O(N) work.

    Returns (global step, local steps (N, 2), the damped reduced normal matrix S)."""
    N, _, P = Jg.shape
    JgT = np.swapaxes(Jg, 1, 2)  # (N, P, 3)
    JlT = np.swapaxes(Jl, 1, 2)  # (N, 2, 3)
    A = Jg.reshape(-1, P).T @ Jg.reshape(-1, P)
    B = JgT @ Jl  # (N, P, 2)
    C = JlT @ Jl  # (N, 2, 2)
    gg = Jg.reshape(-1, P).T @ r.reshape(-1)
    gl = (JlT @ r[:, :, None])[:, :, 0]  # (N, 2)
    Cd = C + lam * C * np.eye(2)  # C_i + lam diag(C_i)
    Ci = np.linalg.inv(Cd)
    BCi = B @ Ci  # (N, P, 2)
    BCi_wide = BCi.transpose(1, 0, 2).reshape(P, 2 * N)  # [BCi_1 ... BCi_N]
    S = A + lam * np.diag(np.diag(A)) - BCi_wide @ B.transpose(0, 2, 1).reshape(2 * N, P)  # A - sum B C^-1 B^T
    rhs = -gg + BCi_wide @ gl.reshape(-1)
    dg = np.linalg.solve(S, rhs)
    dl = -(Ci @ (gl + (np.swapaxes(B, 1, 2) @ dg))[:, :, None])[:, :, 0]
    return dg, dl, S


def _solve_lm(theta: np.ndarray, v: np.ndarray, idx, resid, L_inv: np.ndarray, w: np.ndarray,
              max_iter: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Minimise the weighted squared residuals over ``theta`` = [K entries, b] and the unit
    vectors v_i (each moved in its tangent plane, then renormalised) by Levenberg-Marquardt
    with the Schur complement (:func:`_schur_step`). Returns (theta, v, S at the optimum, cost)."""
    r = resid(theta, v)
    cost = float(np.sum(r * r))
    lam = 1e-3
    for _ in range(max_iter):
        K = _gain(theta, idx)
        basis = _basis(v)
        Jg, Jl = _jacobians(K, v, basis, idx, L_inv, w)
        for _ in range(30):
            dg, dl, S = _schur_step(Jg, Jl, r, lam)
            th_new = theta + dg
            v_new = v + dl[:, :1] * basis[:, 0] + dl[:, 1:] * basis[:, 1]
            v_new /= np.linalg.norm(v_new, axis=1, keepdims=True)
            r_new = resid(th_new, v_new)
            c_new = float(np.sum(r_new * r_new))
            if c_new <= cost:
                break
            lam *= 4.0
        else:
            break
        small = (np.abs(dg).max() <= 1e-12 * (np.abs(theta).max() + 1e-12)
                 and (dl.size == 0 or np.abs(dl).max() <= 1e-12))
        done = cost - c_new <= 1e-12 * cost or small
        theta, v, r, cost = th_new, v_new, r_new, c_new
        lam = max(lam / 3.0, 1e-12)
        if done:
            break
    K = _gain(theta, idx)
    Jg, Jl = _jacobians(K, v, _basis(v), idx, L_inv, w)
    _, _, S = _schur_step(Jg, Jl, r, 0.0)
    return theta, v, S, cost


def fit_accel(accel_sets: Sequence[np.ndarray] | IntervalStats, *, noise_floor: float | None = None,
              form: str = "auto", start: AccelFit | None = None) -> AccelFit:
    """Fit one accelerometer from its still intervals alone (see the module docstring).

    ``form``: ``"upper"``, ``"diag"`` or ``"auto"``: the diagonal form unless, from
    :data:`MIN_INTERVALS_UPPER` intervals, the likelihood-ratio test rejects it for the
    upper-triangular one at :data:`FORM_ALPHA` (the module docstring); with ``start``,
    ``"auto"`` keeps the start's form (the refits of the held-out check keep the form chosen
    on all the intervals).
    ``start``: begin from this fit's K_a, b_a instead of the ellipsoid fit (the warm-started
    refits of :func:`holdout_accel_mps2`; the optimum is still that of these intervals).
    ``accel_sets`` may also be their :class:`~mavcal.core.stats.IntervalStats` (``noise_floor`` unused).
    Raises InsufficientDataError with fewer than :data:`MIN_INTERVALS_DIAG` intervals,
    EstimationError on degenerate orientations.
    """
    st = (accel_sets if isinstance(accel_sets, IntervalStats)
          else interval_stats(accel_sets, "accel_sets", noise_floor=noise_floor))
    N = st.mu.shape[0]
    if N < MIN_INTERVALS_DIAG:
        raise InsufficientDataError(f"{N} still interval(s): an accelerometer alone needs at least "
                                    f"{MIN_INTERVALS_DIAG} in different orientations")
    if form == "auto" and start is not None:
        form = start.form
    if form != "auto":
        return _fit_form(st, form, start)
    diag = _fit_form(st, "diag", None)
    if N < MIN_INTERVALS_UPPER:
        return replace(diag, form_reason=f"diagonal gain: {N} intervals (the upper-triangular form is tried from "
                                         f"{MIN_INTERVALS_UPPER})")
    try:
        upper = _fit_form(st, "upper", None)
    except (EstimationError, np.linalg.LinAlgError):
        return replace(diag, form_reason="diagonal gain: the intervals do not identify the upper-triangular form")
    lr = max(diag.cost - upper.cost, 0.0)
    p = chi2_sf(lr, 3)
    test = f"likelihood ratio chi2={lr:.3g} on 3 dof, p={p:.3g}"
    if p <= FORM_ALPHA:
        return replace(upper, form_reason=f"upper-triangular gain: the cross-axis terms are real ({test})")
    return replace(diag, form_reason=f"diagonal gain: the cross-axis terms are not distinguishable from zero ({test})")


def _fit_form(st: IntervalStats, form: str, start: AccelFit | None) -> AccelFit:
    """:func:`fit_accel` in one form (``"upper"`` or ``"diag"``)."""
    N = st.mu.shape[0]
    if form not in ("upper", "diag"):
        raise ValueError(f"form must be upper, diag or auto; got {form!r}")
    idx = _UPPER if form == "upper" else _DIAG
    if start is not None:
        K0, b0 = _gain(np.array([start.gain[i, j] for i, j in idx]), idx), np.asarray(start.bias, float)
    else:
        e = fit_ellipsoid(st.mu) if form == "upper" else fit_sphere(st.mu)
        K0 = np.asarray(e.K) if form == "upper" else np.diag(np.abs(np.diag(np.asarray(e.K))))
        b0 = np.asarray(e.b, float)
    v0 = (st.mu - b0) @ np.linalg.inv(K0).T
    if not np.all(np.isfinite(v0)) or np.any(np.linalg.norm(v0, axis=1) == 0):
        raise EstimationError("degenerate accelerometer start: the orientations do not span enough directions")
    v0 = v0 / np.linalg.norm(v0, axis=1, keepdims=True)
    L_inv = np.linalg.inv(np.linalg.cholesky(st.sigma_hat))
    w = np.sqrt(st.n)[:, None]

    def resid(theta: np.ndarray, v: np.ndarray) -> np.ndarray:
        return (st.mu - v @ _gain(theta, idx).T - theta[len(idx):]) @ L_inv.T * w

    theta0 = np.concatenate([[K0[i, j] for i, j in idx], b0])
    try:
        theta, v, S, cost = _solve_lm(theta0, v0, idx, resid, L_inv, w)
    except np.linalg.LinAlgError:
        raise EstimationError("singular accelerometer fit: the orientations do not span enough directions") from None
    K, b = _gain(theta, idx), theta[len(idx):]
    if np.any(np.diag(K) <= 0):
        raise EstimationError("the accelerometer fit reached a mirrored gain: the orientations do not span")
    dof = 3 * N - (theta0.size + 2 * N)
    scale = cost / dof if dof > 0 and cost > dof and chi2_sf(cost, dof) <= MISFIT_ALPHA else 1.0
    cov = np.linalg.pinv(S) * scale  # the marginal covariance of [K, b]: the Schur complement's inverse
    names = tuple(f"K_a[{i + 1}{j + 1}]" for i, j in idx) + ("b_a[x]", "b_a[y]", "b_a[z]")
    return AccelFit(gain=K, bias=b, form=form, param_names=names, param_cov=cov, directions=v, cost=cost,
                    dof=int(dof), n_intervals=N, information=S, noise_cov=np.array(st.sigma_hat, float),
                    misfit_scale=float(scale), form_reason=f"{'upper-triangular' if form == 'upper' else 'diagonal'} "
                                                          "gain (asked for)")


def _theta_jacobian(v: np.ndarray, idx) -> np.ndarray:
    """(M, 3, P): d(K v + b)/d[K entries, b] at each unit direction v (M, 3)."""
    J = np.zeros((len(v), 3, len(idx) + 3))
    for m, (i, j) in enumerate(idx):
        J[:, i, m] = v[:, j]
    J[:, :, len(idx):] = np.eye(3)
    return J


def candidate_information(fit: AccelFit, dirs: np.ndarray, n_samples: float) -> np.ndarray:
    """(K, P, P): the Fisher information about ``[K_a, b_a]`` one more still interval of
    ``n_samples`` readings would add at each unit gravity direction ``dirs`` (K, 3), in the
    fit's frame, its own direction marginalised (the Schur complement of :func:`_schur_step`
    for that interval alone), predicted at the current estimate with the fit's noise
    covariance. Added to ``fit.information`` it is the information after that interval
    (the design criterion of the guided capture, :func:`tilt_variances`)."""
    if fit.noise_cov is None:
        raise ValueError("the fit carries no noise covariance")
    idx = _UPPER if fit.form == "upper" else _DIAG
    v = np.asarray(dirs, float)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    L_inv = np.linalg.inv(np.linalg.cholesky(fit.noise_cov))
    w = np.full((len(v), 1), np.sqrt(float(n_samples)))
    Jg, Jl = _jacobians(fit.gain, v, _basis(v), idx, L_inv, w)
    JgT = np.swapaxes(Jg, 1, 2)
    B = JgT @ Jl  # (K, P, 2)
    C = np.swapaxes(Jl, 1, 2) @ Jl  # (K, 2, 2)
    return JgT @ Jg - B @ np.linalg.solve(C, np.swapaxes(B, 1, 2))


def tilt_jacobians(fit: AccelFit, dirs: np.ndarray) -> np.ndarray:
    """(M, 3, P): the tilt error (radians, as a vector perpendicular to the specific force) a
    change of the true ``[K_a, b_a]`` causes at each unit direction ``dirs`` (M, 3) of the
    specific force in the fit's frame, the written correction held at the estimate: the
    corrected reading moves by K_a^-1 (dK v + db) (to first order, in units of |v| = 1), and
    its part perpendicular to v is the tilt error."""
    idx = _UPPER if fit.form == "upper" else _DIAG
    v = np.asarray(dirs, float)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    perp = np.eye(3)[None] - v[:, :, None] * v[:, None, :]
    return perp @ np.linalg.inv(fit.gain)[None] @ _theta_jacobian(v, idx)


def tilt_variances(fit: AccelFit, envelope_dirs: np.ndarray, added: np.ndarray | None = None) -> np.ndarray:
    """The largest, over the specific-force directions ``envelope_dirs`` (M, 3; the flight
    envelope), predicted variance of the tilt error (rad^2, the trace of its 2 x 2 covariance)
    with the information ``fit.information`` plus each of ``added`` (K, P, P; e.g.
    :func:`candidate_information`): (K,), or (1,) without ``added``. The covariance is the
    inverse information times the fit's ``misfit_scale``, as its ``param_cov``."""
    if fit.information is None:
        raise ValueError("the fit carries no information matrix")
    S = np.asarray(fit.information)[None] + (np.zeros((1,) + fit.information.shape) if added is None else added)
    d = np.sqrt(np.maximum(np.diag(fit.information), 1e-300))  # scaled for the inversion
    M = S / d[None, :, None] / d[None, None, :]
    G = tilt_jacobians(fit, envelope_dirs) / d[None, None, :]  # (E, 3, P)
    try:
        Minv = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        Minv = np.linalg.pinv(M)
    var = np.einsum("eip,kpq,eiq->ke", G, Minv, G) * fit.misfit_scale
    return var.max(axis=1)


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
    """The readings ``K v + b`` (|v| = 1) nearest to each row of ``mu`` (M, 3): a few
    Gauss-Newton steps on every v at once, each row frozen once its step is below 1e-12."""
    mu = np.atleast_2d(mu)
    v = np.linalg.solve(K, (mu - b).T).T
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    active = np.ones(len(v), dtype=bool)
    for _ in range(10):
        if not active.any():
            break
        va = v[active]
        E = _basis(va)  # (m, 2, 3)
        J = np.einsum("ij,mcj->mic", K, E)  # (m, 3, 2)
        r = mu[active] - va @ K.T - b
        step = np.linalg.solve(np.swapaxes(J, 1, 2) @ J, (np.swapaxes(J, 1, 2) @ r[:, :, None]))[:, :, 0]
        va = va + step[:, :1] * E[:, 0] + step[:, 1:] * E[:, 1]
        v[active] = va / np.linalg.norm(va, axis=1, keepdims=True)
        idx = np.flatnonzero(active)
        active[idx[np.abs(step).max(axis=1) < 1e-12]] = False
    return v @ K.T + b


LOO_MAX_INTERVALS = 60  # up to this many intervals the held-out check leaves out one at a time
HOLDOUT_FOLDS = 10  # above it, K-fold with this K: ten refits whatever the interval count
HOLDOUT_POOL_MAX = 300  # ... over at most this many intervals, evenly spaced in the log


def holdout_folds(dirs: np.ndarray, *, cluster_deg: float = 30.0, loo_max: int = LOO_MAX_INTERVALS,
                  k: int = HOLDOUT_FOLDS, pool_max: int = HOLDOUT_POOL_MAX) -> list[tuple[np.ndarray, np.ndarray]]:
    """The refits of the held-out check: ``(fit, predicted)`` index arrays into the N intervals
    whose unit gravity directions are ``dirs`` (N, 3): refit on ``fit``, predict ``predicted``.

    Up to ``loo_max`` intervals: leave-one-out, every interval j predicted by a fit on all
    the others, when its direction is seen again in another interval (within
    ``cluster_deg``): leaving out the only pose on one side makes the rest extrapolate,
    which measures the pose plan rather than the fit.

    Above: ``k``-fold over a pool of at most ``pool_max`` intervals evenly spaced in the log
    (all of them up to ``pool_max``): fold f predicts the pool's intervals ``i % k == f``
    (those whose direction is seen in an interval the fold keeps) from a fit on the rest of
    the pool. The cost is ``k`` refits of at most ``pool_max`` intervals whatever N (where
    leave-one-out is N refits of N: quadratic). Why it keeps its meaning: every predicted
    interval is still predicted by a fit that never saw it, from at least
    ``loo_max (k-1)/k`` = 54 intervals, so the number is the same prediction error up to
    the fit's own share of it (O(p/N) of the interval scatter, a few per cent for 9-22
    parameters) and errs on the large side; the pool spans the whole log, so a disturbed
    stretch of it is sampled in proportion. The gates' thresholds keep their meaning.
    """
    N = len(dirs)
    cos_c = np.cos(np.radians(cluster_deg))
    if N <= loo_max:
        close = (dirs @ dirs.T) > cos_c
        every = np.arange(N)
        return [(np.delete(every, j), np.array([j])) for j in range(N) if close[j].sum() >= 2]
    pool = np.unique(np.round(np.linspace(0, N - 1, min(N, pool_max))).astype(int))
    out = []
    for f in range(k):
        held = np.zeros(len(pool), dtype=bool)
        held[f::k] = True
        fit, out_f = pool[~held], pool[held]
        pred = out_f[((dirs[out_f] @ dirs[fit].T) > cos_c).any(axis=1)]  # angle < cluster_deg to a kept one
        if pred.size:
            out.append((fit, pred))
    return out


def pool_index(folds: list[tuple[np.ndarray, np.ndarray]], N: int) -> tuple[np.ndarray, np.ndarray]:
    """The intervals any of ``folds`` uses (sorted) and, for each of the N, its position among
    them (-1 if unused): the held-out checks compute the statistics of this pool only."""
    pool = np.unique(np.concatenate([np.concatenate([fit, pred]) for fit, pred in folds]))
    at = np.full(N, -1)
    at[pool] = np.arange(len(pool))
    return pool, at


def holdout_accel_mps2(accel_sets: Sequence[np.ndarray], *, noise_floor: float | None = None,
                       form: str = "auto", cluster_deg: float = 30.0, start: AccelFit | None = None,
                       stats: IntervalStats | None = None) -> float:
    """RMS held-out error of the accelerometer alone (the reading units).

    As :func:`mavcal.judging.quality.holdout_errors`: each refit of :func:`holdout_folds`
    (leave-one-out up to :data:`LOO_MAX_INTERVALS` intervals, else :data:`HOLDOUT_FOLDS`-fold
    over at most :data:`HOLDOUT_POOL_MAX`) predicts intervals it never saw, each predicted
    mean compared with the nearest point of the refit's ellipsoid. NaN when no interval
    qualifies or too few remain.

    The K-fold refits start from a fit of all intervals (``start``, e.g. the
    :func:`fit_accel` the caller already has; else one of the statistics the folds draw on): each still
    minimises the cost of the intervals it keeps, the start only spares the ellipsoid fit and
    most LM iterations. Leave-one-out (small logs) starts from scratch as before.
    ``stats``: the :func:`interval_stats` of ``accel_sets`` with ``per_interval=True`` (e.g.
    the start's own): each fold's statistics are taken from them (:func:`stats_subset`),
    the same numbers as the pool's own where the pool is all N, equal up to rounding on
    longer logs (as in :func:`mavcal.judging.quality.holdout_errors`).
    ``form="auto"``: the form :func:`fit_accel` chooses on all the intervals (``start``'s when
    given); refits of fewer than :data:`MIN_INTERVALS_UPPER` intervals take the diagonal one.
    """
    sets = list(accel_sets)
    N = len(sets)
    if N - 1 < MIN_INTERVALS_DIAG:
        return float("nan")
    if form == "auto":  # the form chosen on all the intervals (the refits keep it where they can hold it)
        if start is None:
            try:
                start = fit_accel(stats if stats is not None else
                                  interval_stats([np.asarray(s, float) for s in sets], "accel_sets",
                                                 noise_floor=noise_floor))
            except (EstimationError, InsufficientDataError, np.linalg.LinAlgError):
                return float("nan")
        form = start.form if N - 1 >= MIN_INTERVALS_UPPER else "diag"
    mu = interval_means([np.asarray(s, float) for s in sets])
    dirs = mu / np.linalg.norm(mu, axis=1, keepdims=True)
    errs = []
    k_fold = N > LOO_MAX_INTERVALS
    folds = holdout_folds(dirs, cluster_deg=cluster_deg)
    if k_fold and folds:  # the pool's statistics once (each fold's from them), the start fitted once
        try:
            if stats is not None and stats.interval_scatter is not None:
                st, at = stats, np.arange(N)
            else:
                pool, at = pool_index(folds, N)
                st = interval_stats([sets[i] for i in pool], "accel_sets", noise_floor=noise_floor, per_interval=True)
            if start is None or start.form != form:
                start = fit_accel(st, form=form)
        except (EstimationError, InsufficientDataError, np.linalg.LinAlgError):
            return float("nan")
    for keep, pred in folds:
        try:
            f = (fit_accel(stats_subset(st, at[keep], "accel_sets"), form=form, start=start) if k_fold else
                 fit_accel([sets[i] for i in keep], noise_floor=noise_floor, form=form))
        except (EstimationError, InsufficientDataError, np.linalg.LinAlgError):
            continue
        errs += list(np.linalg.norm(mu[pred] - _nearest_on_ellipsoid(f.gain, f.bias, mu[pred]), axis=1))
    return float(np.sqrt(np.mean(np.square(errs)))) if errs else float("nan")
