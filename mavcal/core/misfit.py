"""Each sensor's misfit: the terms of the joint cost, chi2_s / dof_s per sensor, and the
parameter covariance inflated by it (used by :mod:`mavcal.core.calibrate`'s reweighting and
result)."""
from __future__ import annotations

import numpy as np

from mavcal.core.models import FORMS, ModelSpec
from mavcal.core.refine import JointParams, JointProblem, RefineResult, Term
from mavcal.core.stats import IntervalStats

__all__ = ["joint_terms", "misfit_factors", "inflated_covariance"]


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


def inflated_covariance(spec: ModelSpec, a: IntervalStats, m: IntervalStats, Sa, Sm, p: JointParams,
                         res: RefineResult) -> np.ndarray | None:
    """Parameter covariance honest about misfit, sensor by sensor.

    When a sensor's weighted residuals exceed what its noise covariance explains
    (chi2_s / dof_s > 1, e.g. magnetic disturbance that differs between poses, or a
    vehicle not quite still), its covariance is inflated by that factor before the Fisher
    information is formed, so one sensor's misfit does not inflate (or hide in) the
    other's uncertainty. dof_s is the sensor's share 3N - P_s - 3N/2 of the degrees of freedom.
    """
    if res.cov is None or res.dof <= 0:
        return res.cov
    fa, fm = misfit_factors(spec, a, m, Sa, Sm, p)
    if fa == 1.0 and fm == 1.0:
        return res.cov
    prob2 = JointProblem(joint_terms(spec, a, m, Sa * fa, Sm * fm))
    _, Jg, Jr = prob2.jacobians(p)
    cov = prob2.covariance(Jg, Jr)
    return res.cov * max(1.0, res.cost / res.dof) if cov is None else cov
