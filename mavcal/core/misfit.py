"""Each sensor's misfit: the terms of the joint cost, the test of the noise model that the
reweighting acts on, chi2_s / dof_s per sensor, the name of the cost a fit minimises and the
parameter covariance inflated by the misfit (used by :mod:`mavcal.core.calibrate`'s
reweighting and result).

When to reweight (:func:`misfit_p`, ``REWEIGHT_P``). The reweighting moves a fit off the
paper's ML optimum (J', Eq. ``partial_cost``, with the sample covariances Sigma_hat), so it
acts only on evidence that the noise model is wrong, with a stated false-alarm rate: J' at
the optimum against its distribution under the model, p < 1e-6. The statistic is the *total*
J' because its distribution is known exactly in the locally linear model (chi2 with
dof = 3N - P, F with the estimated covariances: see :func:`misfit_p`), while a sensor's own
share chi2_s has no such reference: its expectation is the sensor's redundancy (the trace of
the residual projector over its 3N rows), which depends on the poses and is only approximated
by the heuristic share dof_s = 3N - P_s - 3N/2 of :func:`misfit_factors`. The former trigger,
chi2_s / dof_s > 4 for either sensor, therefore fired on clean data (issue 23: at N = 10 the
compass's share is 2 dof and about 1 clean run in 10 crossed it; at N = 15 it is 9.5). A
test of the total at 1e-6 fires on clean data in at most 1 fit in 10^6 (one test per fit, both
sensors together); once it has fired, the heuristic shares only *apportion* a misfit shown to
be real, and a sensor that fits its noise keeps f_s = 1.

When to widen the uncertainty (:func:`inflated_covariance`, ``INFLATE_P``). The parameter
covariance (and so the heading bound) is the inverse Fisher information at the noise
covariances the fit used (Eq. ``covariance_initial_estimation``, with the quantisation floor):
the covariance of a correct model. It is inflated by the misfit only when the same test
rejects the model at p <= 1 % (``INFLATE_P`` = :data:`mavcal.core.accel_fit.MISFIT_ALPHA`, the
accelerometer's own fit's rule), not on any J'/dof > 1: with the few spare equations of a
short capture J'/dof is itself very uncertain (chi2_dof / dof exceeds 3 one time in 20 with
2 dof on perfect data), and a bound widened by that chance makes the guided capture wait for
it. On clean data the bound is then widened in 1 fit in 100 (the stated false-alarm rate); a
real misfit (motion, a disturbed compass) is rejected far below 1 %, and widens the bound as
before.
"""
from __future__ import annotations

import numpy as np

from mavcal.core.accel_fit import MISFIT_ALPHA
from mavcal.core.certify import SAMPLE_COST
from mavcal.core.models import FORMS, ModelSpec
from mavcal.core.refine import JointParams, JointProblem, RefineResult, Term
from mavcal.core.stats import IntervalStats, f_sf

__all__ = ["joint_terms", "misfit_factors", "reweight_factors", "inflated_covariance", "misfit_p", "cost_name",
           "inflation",
           "REWEIGHT_P", "INFLATE_P"]

REWEIGHT_P = 1e-6  # the noise model is rejected (and the fit reweighted) only when J' has p below this
INFLATE_P = MISFIT_ALPHA  # the covariance widened by the misfit only when J' has p <= this (1 %)


def misfit_p(cost: float, dof: int, a: IntervalStats, m: IntervalStats) -> float:
    """p-value of J' (Eq. ``partial_cost``) at an optimum under the noise model: the F reference.

    With Gaussian noise of the covariances Sigma_s, the whitened residuals sqrt(Delta_i) L_s
    (K_s R_i s + b_s - mu_hat_s[i]) of all 6N equations (Eq. ``sensor_reading_model``) are
    independent unit normals, and the optimum projects them off the P + 3N directions the
    parameters move (locally linear), so J' ~ chi2(dof), dof = 3N - P, *whatever* share of it
    each sensor carries. Sigma_hat_s (Eq. ``covariance_initial_estimation``) is estimated from
    nu_s = sum_i Delta_s[i] - N degrees of freedom, independently of the means; a chi2 / dof
    over an independent chi2 / nu is an F, so J'/dof ~ F(dof, nu) (exact for a one-dimensional
    reading; for three, Hotelling's T^2 has nu - 2). nu = the smaller sensor's nu_s - 2, the
    heavier tail, i.e. the conservative side; a floored Sigma_hat (quantised readings) only
    lowers J'. Nonlinearity (the rotations) enters at second order in the noise.
    """
    nu = max(min(float(a.n.sum()) - a.n.shape[0], float(m.n.sum()) - m.n.shape[0]) - 2.0, 1.0)
    return f_sf(cost / dof, dof, nu) if dof > 0 else 1.0


def inflation(S: np.ndarray, s: IntervalStats) -> float:
    """trace(Sigma) / trace(Sigma_hat): 1.0 exactly when ``S`` is the sample covariance itself."""
    return 1.0 if S is s.sigma_hat else float(np.trace(S) / np.trace(s.sigma_hat))


def cost_name(Sa: np.ndarray, Sm: np.ndarray, a: IntervalStats, m: IntervalStats, method: str = "ncar") -> str:
    """Which cost a point with noise covariances (Sa, Sm) minimises, in words: ``SAMPLE_COST``,
    or J' with a sensor's Sigma inflated by the reweighting (x trace ratio), or the covariance
    refit of FCAR/DCAR."""
    if method in ("fcar", "dcar"):
        return f"J' with the {'diagonal ' if method == 'dcar' else ''}ML-refitted covariances ({method})"
    parts = [f"Sigma_{s} inflated x {f:.4g}" for s, f in (("a", inflation(Sa, a)), ("m", inflation(Sm, m)))
             if f != 1.0]
    return SAMPLE_COST if not parts else "J' with " + " and ".join(parts) + " (reweighted)"


def joint_terms(spec: ModelSpec, a: IntervalStats, m: IntervalStats, Sa, Sm) -> list[Term]:
    """The accelerometer's and magnetometer's terms of J' (paper Eq. ``partial_cost``) for ``spec``."""
    return [Term("accel", FORMS[spec.accel_form], a.mu, a.n, Sa),
            Term("mag", FORMS[spec.mag_form], m.mu, m.n, Sm)]


def misfit_factors(spec: ModelSpec, a: IntervalStats, m: IntervalStats, Sa, Sm, p: JointParams):
    """max(1, chi2_s / dof_s) per sensor; dof_s = the sensor's share 3N - P_s - 3N/2."""
    prob = JointProblem(joint_terms(spec, a, m, Sa, Sm))
    r = prob.residuals(p)
    N = r.shape[0]
    chi_a, chi_m = float(np.sum(r[:, :3] ** 2)), float(np.sum(r[:, 3:] ** 2))
    Pa = FORMS[spec.accel_form].size + 3
    Pm = FORMS[spec.mag_form].size + 3 + 1
    dof_a = max(3 * N - Pa - 1.5 * N, 1.0)
    dof_m = max(3 * N - Pm - 1.5 * N, 1.0)
    return max(1.0, chi_a / dof_a), max(1.0, chi_m / dof_m)


def reweight_factors(spec: ModelSpec, a: IntervalStats, m: IntervalStats, Sa, Sm, res: RefineResult
                     ) -> tuple[float, float, float] | None:
    """One round of the misfit reweighting's rule: (f_a, f_m, p) when J' at ``res`` rejects the
    noise model (``misfit_p`` < ``REWEIGHT_P``) and some sensor's share is above its dof
    (:func:`misfit_factors`); None when the round does not run."""
    if res.dof <= 0:
        return None
    p = misfit_p(res.cost, res.dof, a, m)
    if p >= REWEIGHT_P:
        return None
    fa, fm = misfit_factors(spec, a, m, Sa, Sm, res.params)
    if fa == 1.0 and fm == 1.0:  # no sensor's share is above its dof: nothing to apportion
        return None
    return fa, fm, p


def inflated_covariance(spec: ModelSpec, a: IntervalStats, m: IntervalStats, Sa, Sm, p: JointParams,
                         res: RefineResult) -> np.ndarray | None:
    """Parameter covariance honest about misfit, sensor by sensor.

    Only when J' at the point rejects the noise model, ``misfit_p(J', dof) <= INFLATE_P``
    (the F(dof, nu) reference of :func:`misfit_p`; 1 % false alarms on clean data, see the
    module's notes), each sensor whose weighted residuals exceed what its noise covariance
    explains (chi2_s / dof_s > 1, e.g. magnetic disturbance that differs between poses, or a
    vehicle not quite still) has its covariance inflated by that factor before the Fisher
    information is formed, so one sensor's misfit does not inflate (or hide in) the
    other's uncertainty. dof_s is the sensor's share 3N - P_s - 3N/2 of the degrees of freedom.
    Otherwise ``res.cov``, the inverse Fisher information at (Sa, Sm), as is.
    """
    if res.cov is None or res.dof <= 0 or misfit_p(res.cost, res.dof, a, m) > INFLATE_P:
        return res.cov
    fa, fm = misfit_factors(spec, a, m, Sa, Sm, p)
    if fa == 1.0 and fm == 1.0:
        return res.cov
    prob2 = JointProblem(joint_terms(spec, a, m, Sa * fa, Sm * fm))
    _, Jg, Jr = prob2.jacobians(p)
    cov = prob2.covariance(Jg, Jr)
    return res.cov * max(1.0, res.cost / res.dof) if cov is None else cov
