"""The calibration driver: :func:`calibrate` from the paper's fit (:mod:`mavcal.core.paper_fit`) to the
certified optimum (search, refinement, model selection, certificate, large N), and
:func:`estimate_orientations`, :func:`reconstruction_error`.

Pipeline of :func:`calibrate` (paper section in brackets):

1. sample means and generalised-Bessel covariances [IV, Eqs. ``mu_hat``,
   ``covariance_initial_estimation``];
2. initial estimate [VI]: ellipsoid fits, scale, bias, Cholesky gains, the random-restart
   search for the accel-to-magnetometer rotation and h_z, normalisation g_z = -1, h_x = 1,
   orientations from the eigenvector of B_i;
3. block steps [VII] in one of the paper's four variants until J_{k-1} - J_k < gamma:
   ``ncdr`` (no covariance refit, direct rotations), ``ncar`` (no covariance refit,
   approximated rotations until the cost rises, then direct), ``fcar`` / ``dcar`` (full /
   diagonal covariance refit, approximated rotations);
4. beyond the paper: a joint Levenberg-Marquardt refinement of all parameters to the exact
   optimum of the cost, with the parameter covariance (:mod:`mavcal.core.refine`);
5. beyond the paper: when one start is weak evidence (the refinement did not converge,
   fewer than ``WEAK_DOF`` degrees of freedom, or a chi2 the noise does not explain), a
   deterministic search: every distinct minimum of the R/h_z search for each initial shape
   (quadric, axis-aligned ellipsoid, sphere), then the 7 discrete branches K_m D, +-h_z of
   the best fit (:func:`mavcal.core.gauge.branches`); before the covariance reweighting, which
   would otherwise hide a wrong basin's misfit;
6. model selection: when the intervals cannot identify the full model, or Wald tests on
   the full fit show that a simpler model explains the data as well, a reduced model
   (:mod:`mavcal.core.models`) is fitted and ``Calibration.model_reason`` says why;
7. a certificate (:mod:`mavcal.core.certify`, ``Calibration.certificate``): zero gradient,
   a positive definite exact Hessian (saddles are left along negative curvature first) and
   what the search showed; without it ``converged`` is False and ``message`` says why.

Large N (above ``LARGE_N`` intervals): steps 2-5 run on a deterministic subset of
``SUBSET_N`` (:func:`mavcal.core.subset.diverse_subset`: every distinct pose first, then
intervals evenly spaced in the log; :func:`~mavcal.core.subset.subset_weights` weigh its poses
as the whole log does); from the subset's optimum, the orientations of all N
and steps 4, 6, 7 with the reweighting on all N: the ML optimum of *all* the data at O(N)
cost (the search alone is ~30 fits). The global-optimum guarantee holds because the search
only has to find the basin, and the basins are set by the poses, which the subset keeps; the
other intervals add terms that agree on the same minimum and only sharpen it, so the
refinement from the subset's optimum converges to the full optimum, certified there (zero
gradient, positive definite exact Hessian on all N; the start costs compared are the
subset's). Tested against the exhaustive path in ``tests/test_large_n.py``. LM runs over more
than ``LARGE_N`` intervals are bounded to ``LM_WORK`` interval-iterations (:func:`_lm_budget`).

Diagnosis behind 5-7 (benchmarks/stress_optimum.py, 2050 runs before the change): 19 runs
ended above the optimum, 6 of them claiming convergence: the quadric start fell back to a
sphere for ellipsoids with axes beyond 4:1 (large off-diagonal gains; now 20:1), N = 8 fits
started in the basin of the lowest R/h_z minimum when the optimum lies in another's, and
the reweighting then inflated the noise covariance until the wrong basin's chi2 looked normal.
"""
from __future__ import annotations

import logging
from contextvars import ContextVar
from dataclasses import replace

import numpy as np

from mavcal.core import steps
from mavcal.core.certify import SAMPLE_COST, certificate, escape_saddle
from mavcal.core.gauge import branches, canonical
from mavcal.core.initial import G_UNIT
from mavcal.core.misfit import (
    REWEIGHT_P,
    cost_name,
    inflated_covariance,
    inflation,
    joint_terms,
    misfit_p,
    reweight_factors,
)
from mavcal.core.models import FORMS, MODEL_CHAIN, MODELS, ModelSpec, choose_model
from mavcal.core.paper_fit import initial_state, initial_states, run_block_steps
from mavcal.core.reconstruct import estimate_orientations, reconstruction_error
from mavcal.core.refine import JointParams, JointProblem, RefineResult, blas_kernels, refit_covariances
from mavcal.core.stats import IntervalStats, chi2_sf, interval_stats
from mavcal.core.subset import diverse_subset, subset_weights
from mavcal.core.types import Calibration, OptimumCertificate, SensorModel
from mavcal.core.uncertainty import REDUCTIONS, transform_cov, wald
from mavcal.errors import EstimationError, InsufficientDataError

log = logging.getLogger(__name__)

__all__ = ["calibrate", "estimate_orientations", "reconstruction_error", "initial_state", "initial_states",
           "run_block_steps", "METHODS", "LARGE_N", "SUBSET_N"]

METHODS = ("ncdr", "ncar", "fcar", "dcar")
WALD_ALPHA = 0.01  # a simpler model is accepted when its Wald test has p > 1 %
COPLANAR_LIMIT = 0.02  # smallest/largest singular value of the centred accel means


def _check_geometry(a: IntervalStats, m: IntervalStats) -> None:
    """Refuse orientations that cannot identify an ellipsoid (all about one axis)."""
    for stats, what in ((a, "gravity"), (m, "magnetic field")):
        c = stats.mu - stats.mu.mean(axis=0)
        sv = np.linalg.svd(c, compute_uv=False)
        if sv[0] <= 0:
            raise EstimationError(f"the {what} reading is the same in every interval (constant data); "
                                  "hold the vehicle still in different orientations")
        if sv[-1] / sv[0] < COPLANAR_LIMIT:
            raise EstimationError(
                f"the intervals do not span orientations: the {what} directions lie in one plane "
                f"(spread ratio {sv[-1] / sv[0]:.3g}), as when every pose is a rotation about one axis; "
                "add poses tilted about another axis (nose up/down and rolled left/right)")


def _stats(accel_sets, mag_sets, noise_floor) -> tuple[IntervalStats, IntervalStats]:
    """The interval statistics of both sensors (given as such, e.g. :func:`mavcal.core.stats.stats_subset`
    of the held-out refits, or computed from the readings)."""
    nf_a, nf_m = (noise_floor if isinstance(noise_floor, (tuple, list)) else (noise_floor, noise_floor))
    if isinstance(accel_sets, IntervalStats) and isinstance(mag_sets, IntervalStats):
        a, m = accel_sets, mag_sets
    else:
        a = interval_stats(accel_sets, "accel_sets", noise_floor=nf_a)
        m = interval_stats(mag_sets, "mag_sets", noise_floor=nf_m)
    if a.mu.shape[0] != m.mu.shape[0]:
        raise EstimationError(f"accel_sets has {a.mu.shape[0]} intervals but mag_sets has {m.mu.shape[0]}; "
                              "give both sensors' readings for the same still intervals")
    return a, m


# --- joint refinement per model ------------------------------------------------------------

LM_MORE_ITER = 2000  # LM iterations granted after the first 100 did not converge
LARGE_N = 200  # above this many intervals: the search on a subset, the refinement on all (module docstring)
SUBSET_N = 60  # ... of this many intervals
LM_WORK = 10_000  # above LARGE_N, one LM run gets at most this many iterations x intervals


SUBSET_LM_ITER = 40  # LM iterations per run in the subset search (it ranks basins; all N refine after)
_LM_CAP: ContextVar[int | None] = ContextVar("mavcal_lm_cap", default=None)


def _lm_budget(N: int, wanted: int) -> int:
    """LM iterations for one run over N intervals: ``wanted`` up to ``LARGE_N`` intervals
    (small fits unchanged), above at most ``LM_WORK / N`` (at least ``BRANCH_PROBE_ITER``), so
    that a fit that does not converge costs O(LM_WORK), not O(N) x 2000 iterations; within the
    large-N path's subset search at most ``SUBSET_LM_ITER``."""
    cap = _LM_CAP.get()
    if cap is not None:
        wanted = min(wanted, cap)
    return wanted if N <= LARGE_N else min(wanted, max(BRANCH_PROBE_ITER, LM_WORK // N))


def _refine(spec: ModelSpec, st: steps.State, a: IntervalStats, m: IntervalStats, method: str,
            tol: float, max_lm: int = 100) -> tuple[RefineResult, np.ndarray, np.ndarray]:
    """LM to the exact optimum; for fcar/dcar alternate with the ML covariance refit."""
    Sa, Sm = st.Sigma_a, st.Sigma_m
    max_lm = _lm_budget(a.mu.shape[0], max_lm)
    fa, fm = FORMS[spec.accel_form], FORMS[spec.mag_form]
    p = JointParams((fa.project(st.K_a), fm.project(st.K_m)), (st.b_a, st.b_m), st.h_z, st.R)
    refit = method in ("fcar", "dcar")
    total_it = 0
    for _ in range(50 if refit else 1):
        prob = JointProblem(joint_terms(spec, a, m, Sa, Sm))
        res = prob.solve(p, max_iter=max_lm)
        total_it += res.iterations
        p = res.params
        if not refit:
            break
        Sa_new, Sm_new = refit_covariances(prob, p, [a.scatter, m.scatter], diagonal=(method == "dcar"))
        stn = steps.State(p.gains[0], p.biases[0], p.gains[1], p.biases[1], p.h_z, p.R, Sa, Sm)
        J_old = steps.complete_cost(stn, a, m)
        J_new = steps.complete_cost(replace(stn, Sigma_a=Sa_new, Sigma_m=Sm_new), a, m)
        Sa, Sm = Sa_new, Sm_new
        if J_old - J_new < 1e-3 * tol:
            break
    if refit:  # final covariance of the parameters at the final Sigma
        prob = JointProblem(joint_terms(spec, a, m, Sa, Sm))
        res = prob.solve(p, max_iter=_lm_budget(a.mu.shape[0], 100))
        total_it += res.iterations
    res = RefineResult(res.params, res.cost, total_it, res.converged, res.cov, res.names, res.dof)
    return res, Sa, Sm


WEAK_DOF = 6  # fewer degrees of freedom than this (N <= 9, full model): many near-exact-fit minima
WEAK_P = 1e-3  # chi2 p-value below which the fit is suspected to sit in a wrong basin


def _weak_evidence(res: RefineResult) -> str:
    """Why one start is not enough for this fit ("" when the single start is trusted).

    A fit from one start is trusted when the refinement converged, the residuals are what
    the noise explains (chi2 p-value >= WEAK_P) and there are enough degrees of freedom
    (>= WEAK_DOF) for a wrong basin to show as misfit.
    """
    if not res.converged:
        return "the refinement did not converge"
    if res.dof < WEAK_DOF:
        return f"only {res.dof} degrees of freedom"
    if chi2_sf(res.cost, res.dof) < WEAK_P:
        return f"chi2/dof = {res.cost / res.dof:.3g}"
    return ""


BRANCH_PROBE_ITER = 20  # LM iterations a branch start gets before it must beat the best fit so far


def _branch_fits(spec: ModelSpec, res: RefineResult, Sa, Sm, a, m, method, tol):
    """LM from the 7 discrete branches of ``res`` (:func:`mavcal.core.gauge.branches`).

    Each branch is probed with ``BRANCH_PROBE_ITER`` LM iterations at fixed covariances; only
    a branch that gets below ``res`` is refined to convergence (a wrong branch typically
    stalls far above, and would otherwise cost the full iteration budget).
    """
    p = res.params
    prob = JointProblem(joint_terms(spec, a, m, Sa, Sm))
    out = []
    for _, K_m, h_z in branches(p.gains[1], p.h_z):
        st = steps.State(p.gains[0], p.biases[0], K_m, p.biases[1], h_z, p.R, Sa, Sm)
        st = steps.rotations_approx(st, a, m)
        try:
            probe = prob.solve(JointParams((st.K_a, st.K_m), (st.b_a, st.b_m), st.h_z, st.R),
                               max_iter=BRANCH_PROBE_ITER, covariance=False)
            if probe.cost >= res.cost:
                out.append((probe, Sa, Sm))
                continue
            q = probe.params
            out.append(_refine(spec, replace(st, K_a=q.gains[0], b_a=q.biases[0], K_m=q.gains[1], b_m=q.biases[1],
                                             h_z=q.h_z, R=q.R), a, m, method, tol))
        except (np.linalg.LinAlgError, EstimationError):
            continue
    return out


def _search(spec: ModelSpec, a, m, method, tol, max_iter, rng, restarts, out):
    """Deterministic multi-start, then every branch of the best.

    Starts: for each initial shape (quadric, axis-aligned ellipsoid, sphere), every distinct
    minimum of the R/h_z search (up to 3); then the 7 discrete branches of the best fit.

    Returns (best fit as (res, Sa, Sm, block_it, block_conv), J' reached from every start, the
    chosen one first).
    """
    # the starts are compared at the initial covariances (J' of NCAR/NCDR); a covariance refit
    # (FCAR/DCAR) is applied to the winner only
    smethod = "ncar" if method in ("fcar", "dcar") else method
    if smethod != method:
        out = _fit_model_once(spec, a, m, smethod, tol, max_iter, rng, restarts, None, True, "quadric")
    fits = [out]
    N = a.mu.shape[0]
    shapes = [s for s, n_min in (("quadric", 9), ("axes", 7), ("sphere", 0)) if N >= n_min]
    for shape in shapes:
        try:
            inits = initial_states(a, m, rng, accel_form=spec.accel_form, restarts=restarts, shape=shape)
        except (np.linalg.LinAlgError, EstimationError):
            continue
        for st in inits[1:] if shape == shapes[0] else inits:  # the default start is the first shape's best
            try:
                fits.append(_fit_model_once(spec, a, m, smethod, tol, max_iter, rng, restarts, None, True, shape,
                                            init=st))
            except (np.linalg.LinAlgError, EstimationError):
                continue
    best = min(fits, key=lambda f: f[0].cost)
    for res, Sa, Sm in _branch_fits(spec, best[0], best[1], best[2], a, m, smethod, tol):
        fits.append((res, Sa, Sm, best[3], best[4]))
    k = min(range(len(fits)), key=lambda i: (fits[i][0].cost, not fits[i][0].converged))
    others = tuple(float(f[0].cost) for i, f in enumerate(fits) if i != k)
    res, Sa, Sm, block_it, block_conv = fits[k]
    if smethod != method:
        p = res.params
        st = steps.State(p.gains[0], p.biases[0], p.gains[1], p.biases[1], p.h_z, p.R, Sa, Sm)
        res, Sa, Sm = _refine(spec, st, a, m, method, tol)
    return (res, Sa, Sm, block_it, block_conv), (float(fits[k][0].cost),) + others


def _fit_model(spec: ModelSpec, a, m, method, tol, max_iter, rng, restarts, start=None, refine=True,
               more_iter: int = LM_MORE_ITER):
    """Fit one model; when one start is not evidence enough, from a deterministic set of starts.

    With few intervals, or a fit that does not converge or fits worse than the noise explains,
    the fit is repeated from the other initial estimate (sphere vs quadric) and from the 7
    discrete branches of the best result (:func:`mavcal.core.gauge.branches`); the lowest
    J' wins. Returns (res, Sa, Sm, block_it, block_conv, start_costs); ``start_costs`` are
    the J' (at the initial noise covariances) reached from each start, the chosen one first.
    ``more_iter``: LM iterations granted when the first ones did not converge (bounded further
    at large N by :func:`_lm_budget`).
    """
    out = _fit_model_once(spec, a, m, method, tol, max_iter, rng, restarts, start, refine, "quadric")
    if not refine:
        return out
    costs: tuple[float, ...] = (float(out[0].cost),)
    if start is None and _weak_evidence(out[0]):
        out, costs = _search(spec, a, m, method, tol, max_iter, rng, restarts, out)
    if not out[0].converged and more_iter > 0:  # ill-conditioned (e.g. nearly coplanar poses): LM needs more
        res, Sa, Sm, block_it, block_conv = out
        p = res.params
        st = steps.State(p.gains[0], p.biases[0], p.gains[1], p.biases[1], p.h_z, p.R, Sa, Sm)
        more, Sa, Sm = _refine(spec, st, a, m, method, tol, max_lm=more_iter)
        out = (replace(more, iterations=res.iterations + more.iterations), Sa, Sm, block_it, block_conv)
    return _reweight(spec, a, m, method, tol, out) + (costs,)


REWEIGHT_ROUNDS = 6  # refits at most, once the noise model is rejected


def _reweight(spec: ModelSpec, a, m, method, tol, out):
    """Refit with each sensor's noise covariance inflated by its misfit, when J' shows the noise
    model is wrong.

    The noise covariance comes from the scatter *within* intervals; disturbances that differ
    *between* intervals (magnetic fields that change with the pose, a hand that is not quite
    still, noise correlated in time) are not in it, and one badly fitting sensor then
    dominates the shared orientations and distorts the other. Iterating Sigma_s <- f_s Sigma_s
    (f_s = max(1, chi2_s / dof_s), :func:`misfit_factors`) and refitting weights each sensor
    by how well it actually fits (a scalar version of the paper's covariance refit).

    Only on evidence: a round runs only while J' rejects the noise model at p < ``REWEIGHT_P``
    = 1e-6 (:func:`mavcal.core.misfit.misfit_p`; the reasoning is in :mod:`mavcal.core.misfit`),
    so on data that fit their noise model the result stays the optimum of J' with the sample
    covariances in all but 1 fit in 10^6. When it runs, the result names the cost it minimises
    (:func:`mavcal.core.misfit.cost_name`) and ``RefineResult.misfit`` keeps the evidence.
    """
    res, Sa, Sm, block_it, block_conv = out
    evidence = res.misfit
    for _ in range(REWEIGHT_ROUNDS):
        step = reweight_factors(spec, a, m, Sa, Sm, res)
        if step is None:
            break
        fa, fm, p = step
        if evidence is None:
            evidence = (float(res.cost), int(res.dof), float(p), cost_name(Sa, Sm, a, m, method), spec.name)
        Sa, Sm = Sa * fa, Sm * fm
        q = res.params
        st = steps.State(q.gains[0], q.biases[0], q.gains[1], q.biases[1], q.h_z, q.R, Sa, Sm)
        prev = res
        res, Sa, Sm = _refine(spec, st, a, m, method, tol)
        res = replace(res, iterations=res.iterations + prev.iterations)
    return replace(res, misfit=evidence), Sa, Sm, block_it, block_conv


def _fit_model_once(spec: ModelSpec, a, m, method, tol, max_iter, rng, restarts, start, refine, shape,
                    init: steps.State | None = None):
    """Fit one model: the paper's algorithm for ``full``, a reduced start + LM otherwise.

    ``start``: a state to refine directly (no block steps); ``init``: an initial state to use
    instead of :func:`~mavcal.core.paper_fit.initial_state` (the search's alternatives).
    """
    block_it, block_conv = 0, True
    if start is not None:
        st = start
    elif spec.name == "full":
        st = init if init is not None else initial_state(a, m, rng, restarts=restarts, shape=shape)
        st, block_it, how = run_block_steps(st, a, m, method, tol, max_iter,
                                            handoff_rate=0.5 if refine else None)
        block_conv = how != "limit"
        if not refine:
            return st, block_it, block_conv
    else:
        st = init if init is not None else initial_state(a, m, rng, accel_form=spec.accel_form,
                                                         restarts=restarts, shape=shape)
        if method == "ncdr":
            st = steps.rotations_direct(st, a, m)
    res, Sa, Sm = _refine(spec, st, a, m, method, tol)
    return res, Sa, Sm, block_it, block_conv


def _check_args(method: str, tol, model: str, accel_sets) -> str:
    """Validate the options and the interval count before any statistics are computed."""
    method = str(method).lower()
    if method not in METHODS:
        raise EstimationError(f"method must be one of {', '.join(METHODS)}; got {method!r}")
    if not (isinstance(tol, (int, float)) and np.isfinite(tol) and tol > 0):
        raise EstimationError(f"tol (the stop condition gamma) must be a positive number; got {tol!r}")
    if model != "auto" and model not in MODELS:
        raise EstimationError(f"model must be 'auto' or one of {', '.join(MODELS)}; got {model!r}")
    try:
        n_given = len(accel_sets)
    except TypeError:
        n_given = None
    if n_given is not None and 0 < n_given < MODELS[MODEL_CHAIN[-1]].min_intervals:
        raise InsufficientDataError(
            f"{n_given} still interval(s) cannot identify even the simplest model (offsets and scales need "
            f"{MODELS[MODEL_CHAIN[-1]].min_intervals}; the full joint model needs {MODELS['full'].min_intervals}); "
            "hold the vehicle still in more orientations")
    return method


def _paper_path(spec: ModelSpec, a, m, method, tol, max_iter, rng, restarts):
    """refine=False: the paper's algorithm alone, its end point scored as a RefineResult."""
    if spec.name != "full":
        raise EstimationError("refine=False runs the paper's algorithm, which fits the full model only; "
                              f"{a.mu.shape[0]} intervals call for the {spec.name} model")
    st, block_it, block_conv = _fit_model(spec, a, m, method, tol, max_iter, rng, restarts, refine=False)
    prob = JointProblem(joint_terms(spec, a, m, st.Sigma_a, st.Sigma_m))
    p = JointParams((st.K_a, st.K_m), (st.b_a, st.b_m), st.h_z, st.R)
    r, Jg, Jr = prob.jacobians(p)
    res = RefineResult(p, float(np.sum(r * r)), 0, True, prob.covariance(Jg, Jr), prob.names,
                       3 * a.mu.shape[0] - prob.P)
    return res, st.Sigma_a, st.Sigma_m, block_it, block_conv


def _select_model(spec: ModelSpec, res: RefineResult, Sa, Sm, a, m, method, tol, max_iter, rng, restarts):
    """Wald tests down MODEL_CHAIN; refit the simplest accepted model. Returns (spec, res, Sa, Sm, note)."""
    chain = MODEL_CHAIN[MODEL_CHAIN.index(spec.name):]
    scale = max(1.0, res.cost / max(res.dof, 1))
    chosen, tests = spec, []
    cons: list = []
    for nxt in chain[1:]:
        if (spec.accel_form == "diag" and nxt == "diag-accel") or (spec.mag_form == "sym" and nxt == "ardupilot"):
            continue
        cons = cons + REDUCTIONS[nxt]
        W, k, pval = wald(res, cons, scale)
        tests.append(f"{nxt}: Wald chi2={W:.3g} on {k} dof, p={pval:.3g}")
        if pval <= WALD_ALPHA:
            break
        chosen = MODELS[nxt]
    if chosen is spec:
        return spec, res, Sa, Sm, (f"; simpler models are rejected ({tests[0]})" if tests else "")
    p = res.params
    start = steps.State(p.gains[0], p.biases[0], p.gains[1], p.biases[1], p.h_z, p.R, Sa, Sm)
    res2, Sa, Sm, _, _, _ = _fit_model(chosen, a, m, method, tol, max_iter, rng, restarts, start=start)
    if res.misfit is not None:  # the evidence that first rejected the noise model: the full fit's
        res2 = replace(res2, misfit=res.misfit)
    note = f"; the simpler {chosen.name} model explains the data as well ({'; '.join(tests)}), so it was used"
    return chosen, replace(res2, iterations=res.iterations + res2.iterations), Sa, Sm, note


def _escape_saddles(spec: ModelSpec, res: RefineResult, Sa, Sm, a, m, method, tol) -> RefineResult:
    """Leave saddles of J' (where Gauss-Newton stops) along negative curvature and refine again."""
    for _ in range(3):
        prob = JointProblem(joint_terms(spec, a, m, Sa, Sm))
        q = escape_saddle(prob, res.params, res.cost)
        if q is None:
            break
        st = steps.State(q.gains[0], q.biases[0], q.gains[1], q.biases[1], q.h_z, q.R, Sa, Sm)
        new, _, _ = _refine(spec, st, a, m, "ncar" if method in ("fcar", "dcar") else method, tol)
        if new.cost >= res.cost:
            break
        res = replace(new, iterations=res.iterations + new.iterations)
    return res


def _certify(spec: ModelSpec, res: RefineResult, Sa, Sm, a, m, costs, search_dof: int | None = None,
             names: tuple[str, str] = (SAMPLE_COST, SAMPLE_COST)) -> OptimumCertificate:
    """Local evidence at the final point plus what the search showed (see :mod:`mavcal.core.certify`).

    Global evidence: a single start is trusted only when :func:`_weak_evidence` found nothing
    wrong (else the search ran). After a search, the best start is trusted when its chi2 is
    what the noise explains, or, with enough degrees of freedom (misfit from disturbances
    in real data), when at least two starts reached it; with few degrees of freedom and a
    misfit the data cannot tell a wrong basin from a bad model, so nothing is certified.
    ``search_dof``: the degrees of freedom of the subset the search ran on (large N), when
    ``costs`` are that subset's. ``names``: (the cost the returned point minimises, at
    (Sa, Sm); the cost ``costs`` were compared at): the local evidence is for the first.
    """
    prob = JointProblem(joint_terms(spec, a, m, Sa, Sm))
    note = ""
    dof = res.dof if search_dof is None else search_dof
    if len(costs) > 1:
        best = costs[0]
        agree = sum(1 for c in costs if abs(c - best) <= 1e-7 * max(best, 1e-300))
        misfit = dof > 0 and chi2_sf(best, dof) < WEAK_P
        if misfit and (dof < WEAK_DOF or agree < 2):
            note = (f"the best of {len(costs)} starts leaves chi2/dof = {best / max(dof, 1):.3g} "
                    f"({agree} start(s) reached it, {dof} degrees of freedom): a wrong basin cannot be ruled out")
    return certificate(prob, res.params, res.cost, costs, note, cost_name=names[0], start_cost_name=names[1])


def _result(spec: ModelSpec, res: RefineResult, Sa, Sm, a, m, method, reason, block_it, block_conv,
            cert: OptimumCertificate | None = None) -> Calibration:
    """Canonical gauge, covariance, message, and the frozen Calibration."""
    p = res.params
    K_a, K_m, h_z, R, _ = canonical(p.gains[0], p.gains[1], p.h_z, p.R)
    if K_a[1, 1] != p.gains[0][1, 1] or h_z != p.h_z:  # gauge changed: same fit, same covariance up to signs
        res = replace(res, cov=transform_cov(res, p, K_a, K_m, h_z))
    p = JointParams((K_a, K_m), p.biases, h_z, R)
    cov = inflated_covariance(spec, a, m, Sa, Sm, p, res)
    converged = bool(block_conv and res.converged)
    msg = (f"{spec.name} model, {method}: J'={res.cost:.6g} after {block_it} block iterations and "
           f"{res.iterations} joint refinement iterations"
           + ("" if converged else " (block steps hit the iteration limit)" if not block_conv else
              " (refinement did not reach its tolerance)"))
    if cert is not None:
        msg += f"; {cert.starts} start(s)"
        if not cert.certified:
            converged = False
            msg += f"; not certified as the global optimum: {cert.reason}"
    name = cost_name(Sa, Sm, a, m, method)
    if name != SAMPLE_COST and method in ("ncar", "ncdr"):
        why = "the weights of the calibration it started from"
        if res.misfit is not None:
            J0, dof0, p0, name0, model0 = res.misfit
            why = (f"{model0} model: {name0} was {J0:.6g} on {dof0} dof, p={p0:.3g} < {REWEIGHT_P:g}: the readings "
                   "scatter more than their noise (motion in the intervals or magnetic disturbance?)")
        msg += f"; the returned point is the optimum of {name}, not of {SAMPLE_COST} ({why})"
    if res.dof > 0 and misfit_p(res.cost, res.dof, a, m) < REWEIGHT_P:
        msg += (f"; chi2/dof = {res.cost / res.dof:.3g}: the readings scatter more than the noise explains "
                "(motion in the intervals or magnetic disturbance?)")
    log.info(msg)
    return Calibration(
        accel=SensorModel(p.gains[0], p.biases[0], Sa, "accel"),
        mag=SensorModel(p.gains[1], p.biases[1], Sm, "mag"),
        gravity=G_UNIT.copy(), field=np.array([1.0, 0.0, p.h_z]), orientations=p.R,
        cost=float(res.cost), iterations=int(block_it + res.iterations), converged=converged, message=msg,
        method=method, model=spec.name, model_reason=reason, param_names=res.names, param_cov=cov,
        n_accel=a.n, n_mag=m.n, block_iterations=int(block_it), refine_iterations=int(res.iterations),
        dof=int(res.dof), certificate=cert, noise_inflation=(inflation(Sa, a), inflation(Sm, m)), cost_name=name)


def calibrate(accel_sets, mag_sets, *, method: str = "ncar", tol: float = 1e-4, seed: int | None = None,
              model: str = "auto", max_iter: int = 1000, restarts: int = 24,
              noise_floor=None, refine: bool = True, start: Calibration | None = None,
              start_orientations: np.ndarray | None = None) -> Calibration:
    """Joint maximum-likelihood calibration of an accelerometer and a magnetometer.

    Above ``LARGE_N`` intervals the search runs on a subset of ``SUBSET_N`` (see the module
    docstring), the refinement on all of them.

    Parameters
    ----------
    accel_sets, mag_sets : sequences of N arrays of shape (n_i, 3)
        Readings of each still interval (the two sensors may have different counts); or
        both their :class:`~mavcal.core.stats.IntervalStats` (``noise_floor`` then unused).
    method : {"ncar", "ncdr", "fcar", "dcar"}
        The paper's variant of the block steps (Sec. VIII): NCAR is the paper's best.
    tol : float
        The paper's stop condition gamma: the block steps stop when J_{k-1} - J_k < tol.
    seed : int, optional
        Seed of the random restarts of the initial rotation search.
    model : {"auto", "full", "diag-accel", "ardupilot", "offsets-scales"}
        "auto" fits the most general model the data identify and reduces it when Wald
        tests show a simpler model explains the data as well.
    noise_floor : float or (float, float), optional
        Lower bound on the noise standard deviation per sensor (e.g. quantisation step /
        sqrt(12) for integer telemetry).
    refine : bool
        True (default): hand over from the block steps to the joint refinement, which
        reaches the exact optimum. False: the paper's algorithm alone (full model only),
        stopping exactly by J_{k-1} - J_k < tol; used to reproduce the paper's experiments.
    start : Calibration, optional
        Refine from this calibration's parameters instead of searching (the warm-started
        refits of the held-out check): orientations of these intervals from its parameters,
        then the joint refinement, reweighting and model selection on these intervals alone,
        so the result is still the optimum of *this* data's cost; the start only selects the
        basin. ``model`` should be the start's model. Nothing is searched, so the result
        has no ``certificate`` (``converged`` says whether the refinement converged).
        Above ``LARGE_N`` intervals the refit begins at the start's noise weights
        (``start.noise_inflation``, see :func:`_start_weights`).
    start_orientations : (N, 3, 3) array, optional
        With ``start``: these intervals' orientations in the start's frame, e.g. the start's
        own ``orientations`` of the intervals a held-out refit keeps. The refinement then
        begins at the start's point itself (next to this data's optimum) instead of
        computing each R_i from the start's parameters; the optimum reached is the same (to
        the refinement's tolerance, rtol 1e-13 on J').

    Returns
    -------
    Calibration
        Gains, biases and noise covariances of both sensors, the normalised fields, the
        orientations, J' at the optimum, iteration counts, the fitted model and the reason
        it was chosen, and the covariance of the global parameters.

    Raises
    ------
    EstimationError
        NaN/inf, wrong shapes, intervals with fewer than 2 samples, constant data,
        orientations that do not span (all about one axis).
    InsufficientDataError
        Fewer intervals than the requested (or any) model can identify.
    """
    method = _check_args(method, tol, model, accel_sets)
    a, m = _stats(accel_sets, mag_sets, noise_floor)
    rng = np.random.default_rng(seed)
    spec, reason = choose_model(model, a.mu.shape[0])
    _check_geometry(a, m)
    if not refine:
        if start is not None:
            raise EstimationError("start= refines from a calibration; it needs refine=True")
        res, Sa, Sm, block_it, block_conv = _paper_path(spec, a, m, method, tol, max_iter, rng, restarts)
        return _result(spec, res, Sa, Sm, a, m, method, reason, block_it, block_conv)
    opts = (method, tol, max_iter, rng, restarts)
    if start is not None or a.mu.shape[0] > LARGE_N:
        with blas_kernels():  # the same sums by BLAS: equal up to rounding, several times faster at large N
            return _large_n(spec, reason, a, m, opts, model, start, start_orientations)
    fit = _fit_model(spec, a, m, method, tol, max_iter, rng, restarts)
    return _finish(spec, reason, a, m, opts, model, fit)


def _finish(spec: ModelSpec, reason: str, a, m, opts, model: str, fit, search_dof: int | None = None,
            certify: bool = True, start_name: str | None = None) -> Calibration:
    """Model selection, certificate (leaving a saddle first) and the Calibration of a fit
    ``(res, Sa, Sm, block_it, block_conv, start_costs)``; ``search_dof``: the degrees of
    freedom the start costs were reached with when not those of ``res`` (a subset search).
    ``certify=False`` (warm-started refits, which search nothing): no certificate. ``start_name``:
    the cost the start costs were compared at (default: :func:`_start_cost_name`)."""
    method, tol, max_iter, rng, restarts = opts
    res, Sa, Sm, block_it, block_conv, costs = fit
    start_name = start_name or _start_cost_name(len(costs), a, m, method)
    if model == "auto" and res.cov is not None:
        spec, res2, Sa, Sm, note = _select_model(spec, res, Sa, Sm, a, m, method, tol, max_iter, rng, restarts)
        if res2 is not res:  # reduced model, started from the full model's optimum
            costs, search_dof = (float(res2.cost),), None
            start_name = cost_name(Sa, Sm, a, m, method)
        res, reason = res2, reason + note
    if not certify:
        return _result(spec, res, Sa, Sm, a, m, method, reason, block_it, block_conv)
    names = (cost_name(Sa, Sm, a, m, method), start_name)
    cert = _certify(spec, res, Sa, Sm, a, m, costs, search_dof, names)
    if cert.min_hessian_eig < 0:  # stopped at a saddle: leave it and certify again
        res = _escape_saddles(spec, res, Sa, Sm, a, m, method, tol)
        cert = _certify(spec, res, Sa, Sm, a, m, costs, search_dof, names)
    return _result(spec, res, Sa, Sm, a, m, method, reason, block_it, block_conv, cert)


def _start_cost_name(n_starts: int, a, m, method: str) -> str:
    """The cost :func:`_fit_model`'s start costs are of: before any reweighting, the sample
    covariances (a search compares its starts with NCAR even for FCAR/DCAR), or, for one
    FCAR/DCAR start, its covariance refit."""
    return SAMPLE_COST if method in ("ncar", "ncdr") or n_starts > 1 else cost_name(a.sigma_hat, m.sigma_hat, a, m,
                                                                                      method)


def _subset_stats(s: IntervalStats, idx: np.ndarray, n: np.ndarray) -> IntervalStats:
    """The statistics of intervals ``idx`` weighted by the counts ``n`` (:func:`subset_weights`),
    keeping the pooled noise covariance of all (the scatter scaled to the subset's dof)."""
    scatter = s.scatter * ((n.sum() - len(idx)) / max(s.n.sum() - len(s.n), 1.0))
    return IntervalStats(mu=s.mu[idx], n=n, scatter=scatter, sigma_hat=s.sigma_hat, scale=s.scale)


def _large_n(spec: ModelSpec, reason: str, a: IntervalStats, m: IntervalStats, opts, model: str,
             start: Calibration | None, start_R: np.ndarray | None = None) -> Calibration:
    """Search on a subset (or take ``start``), then refine, reweight, select and certify on all N
    (see the module docstring)."""
    method, tol, max_iter, rng, restarts = opts
    N = a.mu.shape[0]
    search_dof = None
    if start is None:
        idx = diverse_subset(a.mu, m.mu, SUBSET_N)
        n_s = subset_weights(a.mu, m.mu, a.n + m.n, idx)  # both sensors' counts: the poses' weights
        a_s = _subset_stats(a, idx, n_s * (a.n[idx].sum() / n_s.sum()))
        m_s = _subset_stats(m, idx, n_s * (m.n[idx].sum() / n_s.sum()))
        token = _LM_CAP.set(SUBSET_LM_ITER)
        try:
            res_s, _, _, block_it, block_conv, costs = _fit_model(spec, a_s, m_s, method, tol, max_iter, rng,
                                                                  restarts)  # every LM run capped by _LM_CAP
        finally:
            _LM_CAP.reset(token)
        p = res_s.params
        K_a, b_a, K_m, b_m, h_z = p.gains[0], p.biases[0], p.gains[1], p.biases[1], p.h_z
        search_dof = res_s.dof if len(costs) > 1 else None
        Sa, Sm = a.sigma_hat, m.sigma_hat  # as the exhaustive path: the reweighting's end point is the same
        reason += (f"; the search for the global optimum ran on {len(idx)} of the {N} intervals "
                   f"(orientation-diverse, then evenly spaced), the refinement on all {N}")
    else:
        c = start
        K_a, b_a, K_m, b_m, h_z = c.accel.gain, c.accel.bias, c.mag.gain, c.mag.bias, c.h_z
        Sa, Sm = _start_weights(c, a, m, method)
        block_it, block_conv = 0, True
        reason += "; refined from a given calibration (no search)"
    if start is not None and start_R is not None:
        st = steps.State(K_a, b_a, K_m, b_m, h_z, _checked_orientations(start_R, N), Sa, Sm)
    else:
        st = steps.State(K_a, b_a, K_m, b_m, h_z, np.zeros((N, 3, 3)), Sa, Sm)
        st = steps.rotations_direct(steps.rotations_approx(st, a, m), a, m)  # each R_i optimal given the start
    res, Sa, Sm, _, _, _ = _fit_model(spec, a, m, method, tol, max_iter, rng, restarts, start=st,
                                      more_iter=LM_MORE_ITER if start is None else 0)
    if start is not None:
        costs = (float(res.cost),)
    subset = None if start is not None else f"{_start_cost_name(len(costs), a, m, method)} of the search subset"
    return _finish(spec, reason, a, m, opts, model, (res, Sa, Sm, block_it, block_conv, costs), search_dof,
                   certify=start is None, start_name=subset)


def _checked_orientations(R, N: int) -> np.ndarray:
    R = np.asarray(R, dtype=float)
    if R.shape != (N, 3, 3) or not np.all(np.isfinite(R)):
        raise EstimationError(f"start_orientations must be {N} finite 3x3 rotations (one per interval); "
                              f"got shape {R.shape}")
    return R


def _start_weights(c: Calibration, a: IntervalStats, m: IntervalStats, method: str) -> tuple[np.ndarray, np.ndarray]:
    """The noise covariances a refit from ``c`` starts at. Above ``LARGE_N`` (LM runs of at most
    ``LM_WORK / N`` iterations): these intervals' Sigma_hat inflated as ``c``'s were
    (``c.noise_inflation``; NCAR/NCDR, whose Sigma is Sigma_hat times the reweighting factors).
    Begun at the raw Sigma_hat, a sensor the reweighting had tamed (a disturbed compass)
    dominates the first run, walks the orientations away and spends the budget (275
    intervals: 40 wasted LM iterations per refit). :func:`_reweight` still runs on the refit's
    own residuals. Up to ``LARGE_N``: Sigma_hat, as before."""
    if a.mu.shape[0] <= LARGE_N:
        return a.sigma_hat, m.sigma_hat
    fa, fm = c.noise_inflation if method in ("ncar", "ncdr") else (1.0, 1.0)
    return (a.sigma_hat if fa == 1.0 else a.sigma_hat * fa), (m.sigma_hat if fm == 1.0 else m.sigma_hat * fm)
