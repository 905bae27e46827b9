"""The joint fit with some parameters held at given values: what poses within reach identify.

A vehicle that cannot be turned over (a heavy multirotor, a rover, a boat) can be turned to
any heading and tilted a little. Its still intervals then see gravity only within a small
cap of directions: the accelerometer's Z scale cannot be told from its Z offset, nor an X/Y
offset from a tilt of the whole frame, so the accelerometer keeps its current calibration.
The compass still sees the field from every heading, and the small tilts move the field's
vertical component, so its offsets and its symmetric soft-iron matrix are identified; where
the World Magnetic Model gives the inclination at the vehicle's position, the field dip h_z
is held at it, which separates the vertical offset from the vertical terms at the smallest
tilts (see :mod:`mavcal.coverage` for the rule that decides which case a recording is).

The cost is the paper's J' (Eq. ``partial_cost``) of the ``ardupilot`` model
(:mod:`mavcal.core.models`: diagonal K_a, symmetric K_m) with the held parameters fixed:

    J'(theta_f, R) = sum_s sum_i Delta_s[i] (K_s R_i s^I + b_s - mu_hat_s[i])^T Sigma_s^-1 (...)

minimised over the free parameters theta_f and every orientation R_i. Holding coordinates
leaves the structure of :class:`mavcal.core.refine.JointProblem` intact (the same residuals,
the Jacobian's free columns), so the same Levenberg-Marquardt reaches the exact optimum of
this cost and :func:`mavcal.core.certify.certificate` certifies it (zero gradient, positive
definite exact Hessian on the free coordinates).

Uncertainty. The held values are not known to be right: each gets a prior standard
deviation (given by the caller), and the free parameters follow a held error as the fit
would (d theta_f / d theta_h = -S_ff^-1 S_fh, S the Fisher information with the
orientations eliminated), so the covariance of all parameters is

    C = [[S_ff^-1 + A P A^T, A P], [P A^T, P]],   A = -S_ff^-1 S_fh,  P = diag(prior_sd^2)

and the heading and tilt bounds drawn from it count the held values' uncertainty.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from mavcal.core.certify import SAMPLE_COST, certificate
from mavcal.core.headings import provisional_headings
from mavcal.core.initial import G_UNIT
from mavcal.core.misfit import INFLATE_P, REWEIGHT_P, cost_name, inflation, joint_terms, misfit_p, reweight_factors
from mavcal.core.models import FORMS, MODELS
from mavcal.core.refine import (
    JointParams,
    JointProblem,
    RefineResult,
    Term,
    gauss_newton_blocks,
    schur_complement,
)
from mavcal.core.stats import IntervalStats, chi2_sf
from mavcal.core.types import Calibration, SensorModel
from mavcal.errors import EstimationError, InsufficientDataError

__all__ = ["HeldProblem", "calibrate_held", "turn_compass", "turned_stats", "held_covariance", "relaxed_headings",
           "tilts_of", "HELD_MODEL", "TURNED_MODEL", "WEAK_P"]

HELD_MODEL = "ardupilot"  # diagonal K_a (ArduPilot's INS_ACC*), symmetric K_m (COMPASS_DIA/ODI)
WEAK_P = 1e-3  # a single start with a chi2 p-value below this is not trusted (as the full fit's search)
WEAK_DOF = 6  # ... nor one with fewer degrees of freedom
REWEIGHT_ROUNDS = 6  # refits at most once the noise model is rejected (as mavcal.core.calibrate)


class HeldProblem(JointProblem):
    """The cost of a :class:`JointProblem` with the global parameters not in ``free`` held at
    ``values`` (a full parameter vector in the base problem's order): its parameter vector is
    the free entries, its Jacobian the free columns."""

    def __init__(self, terms: Sequence[Term], free: np.ndarray, values: np.ndarray):
        super().__init__(terms)
        full = JointProblem(terms)
        free = np.asarray(free, dtype=bool)
        if free.shape != (full.P,) or not free.any():
            raise EstimationError(f"a held fit needs a mask of the {full.P} parameters with at least one free")
        self.base = full
        self.free = np.flatnonzero(free)
        self.columns = self.free
        self._values = np.array(values, dtype=float)
        self.P = len(self.free)
        self.names = tuple(full.names[k] for k in self.free)

    def pack(self, p: JointParams) -> np.ndarray:
        return self.base.pack(p)[self.free]

    def unpack(self, theta: np.ndarray, R: np.ndarray) -> JointParams:
        full = self._values.copy()
        full[self.free] = theta
        return self.base.unpack(full, R)

    def jacobians(self, p: JointParams):
        r, Jg, Jr = self.base.jacobians(p)
        return r, Jg[:, :, self.free], Jr


def _rotation_from_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector ``a`` to the unit vector ``b`` (b not -a)."""
    v = np.cross(a, b)
    c = float(a @ b)
    V = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + V + V @ V / (1.0 + c)


def _rotz(phi: float) -> np.ndarray:
    c, s = np.cos(phi), np.sin(phi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def tilts_of(u: np.ndarray) -> np.ndarray:
    """T_i with T_i g = u_i for unit specific-force directions ``u`` (N, 3) in the body frame
    (g = [0, 0, -1]: level is (0, 0, -1)); InsufficientDataError when a pose is upside down."""
    u = np.asarray(u, dtype=float).reshape(-1, 3)
    u = u / np.linalg.norm(u, axis=1)[:, None]
    if np.any(u @ G_UNIT < 0.0):
        raise InsufficientDataError("a still interval is upside down for the held accelerometer model: "
                                    "the fit of poses within reach needs the vehicle upright")
    return np.array([_rotation_from_to(G_UNIT, ui) for ui in u])


def relaxed_headings(T: np.ndarray, mag_means: np.ndarray, h_z: float | None = None
                     ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """The linear relaxation of the compass model (Eq. ``sensor_reading_model`` with K_m = s I)
    given each pose's tilt T_i: mu_m[i] = T_i [c_i, d_i, u] + b (c_i = s cos psi_i, d_i = s sin
    psi_i, u = s h_z), solved by least squares (u fixed at s h_z when ``h_z`` is given). Returns
    (headings psi_i (N,), s, b (3,), h_z)."""
    M = np.asarray(mag_means, dtype=float).reshape(-1, 3)
    N = T.shape[0]

    def solve(u_known: float | None):
        A = np.zeros((3 * N, 2 * N + 3 + (0 if u_known is not None else 1)))
        y = M.reshape(-1).copy()
        for i in range(N):
            A[3 * i:3 * i + 3, 2 * i] = T[i][:, 0]
            A[3 * i:3 * i + 3, 2 * i + 1] = T[i][:, 1]
            A[3 * i:3 * i + 3, 2 * N:2 * N + 3] = np.eye(3)
            if u_known is None:
                A[3 * i:3 * i + 3, -1] = T[i][:, 2]
            else:
                y[3 * i:3 * i + 3] -= u_known * T[i][:, 2]
        return np.linalg.lstsq(A, y, rcond=None)[0]

    def scale(x: np.ndarray) -> float:
        v = float(np.median(np.linalg.norm(x[:2 * N].reshape(N, 2), axis=1)))
        if not np.isfinite(v) or v <= 0:
            raise EstimationError("the compass readings do not turn with the heading (constant data?); "
                                  "turn the vehicle to new headings")
        return v

    if h_z is None:  # the dip: at small tilts u is nearly confounded with b_z, so it is scanned, not solved for
        best: tuple[float, np.ndarray, float] | None = None
        for incl in range(-80, 81, 10):
            hz_k = float(np.tan(np.radians(incl)))
            x = solve(None)
            for _ in range(2):  # u = s h_z with the scale of the previous solve
                x = solve(scale(x) * hz_k)
            s_k = scale(x)
            A_res = M.reshape(-1) - _relaxed_prediction(T, x, s_k * hz_k)
            r = float(A_res @ A_res)
            if best is None or r < best[0]:
                best = (r, x, hz_k)
        assert best is not None
        _, x, hz = best
    else:
        hz = float(h_z)
        x = solve(None)
        x = solve(scale(x) * hz)
    cd = x[:2 * N].reshape(N, 2)
    return np.arctan2(cd[:, 1], cd[:, 0]), scale(x), x[2 * N:2 * N + 3], hz


def _relaxed_prediction(T: np.ndarray, x: np.ndarray, u: float) -> np.ndarray:
    """The readings (3N,) the relaxation's solution ``x`` (c_i, d_i, b) and ``u`` predict."""
    N = T.shape[0]
    cd = x[:2 * N].reshape(N, 2)
    return (T[:, :, 0] * cd[:, :1] + T[:, :, 1] * cd[:, 1:] + T[:, :, 2] * u + x[2 * N:2 * N + 3]).reshape(-1)


def _start(a: IntervalStats, m: IntervalStats, K_a, b_a, h_z: float | None) -> JointParams:
    """A start in closed form: K_m = s I and the headings of :func:`relaxed_headings` with the
    tilts of the held accelerometer."""
    T = tilts_of(np.linalg.solve(K_a, (a.mu - b_a).T).T)
    psi, s, b_m, hz = relaxed_headings(T, m.mu, h_z)
    R = np.array([T[i] @ _rotz(float(psi[i])) for i in range(T.shape[0])])
    return JointParams((np.asarray(K_a, float), s * np.eye(3)), (np.asarray(b_a, float), b_m), hz, R)


def held_covariance(prob: HeldProblem, p: JointParams, prior_sd: np.ndarray, scale: float = 1.0
                    ) -> np.ndarray | None:
    """Covariance of *all* the base problem's parameters at ``p`` (module docstring): the free
    ones' inverse Fisher information (times ``scale``, a misfit's inflation) plus the held
    ones' priors ``prior_sd`` (one per base parameter; the free entries unused), carried into
    the free ones as the fit carries them."""
    base = prob.base
    _, Jg, Jr = base.jacobians(p)
    Hgg, Hgr, Hrr = gauss_newton_blocks(Jg, Jr, blas=base.blas)
    try:
        S = schur_complement(Hgg, Hgr, np.linalg.inv(Hrr), blas=base.blas)
        f = prob.free
        h = np.setdiff1d(np.arange(base.P), f)
        Cff = np.linalg.inv(S[np.ix_(f, f)]) * scale
        A = -np.linalg.solve(S[np.ix_(f, f)], S[np.ix_(f, h)])
    except np.linalg.LinAlgError:
        return None
    Ph = np.diag(np.asarray(prior_sd, float)[h] ** 2)
    C = np.zeros((base.P, base.P))
    C[np.ix_(f, f)] = Cff + A @ Ph @ A.T
    C[np.ix_(f, h)] = A @ Ph
    C[np.ix_(h, f)] = (A @ Ph).T
    C[np.ix_(h, h)] = Ph
    C = 0.5 * (C + C.T)
    return C if np.all(np.isfinite(C)) else None


def calibrate_held(a: IntervalStats, m: IntervalStats, K_a: np.ndarray, b_a: np.ndarray, *,
                   held: Sequence[str], prior_sd: Mapping[str, float], h_z: float | None = None,
                   reason: str = "", max_iter: int = 200) -> Calibration:
    """The exact ML optimum of J' (``ardupilot`` model) with the parameters named in ``held``
    fixed (``K_a`` and ``b_a``: the accelerometer's held model, diagonal; ``h_z``: the field
    dip to hold, e.g. tan(inclination) of the World Magnetic Model, when "h_z" is held), every
    other parameter and every orientation free; certified and with the covariance of all
    parameters, the held ones' ``prior_sd`` (by name) counted (module docstring).

    The accelerometer's held values pin each interval's tilt; the start is the closed-form
    relaxation of :func:`_start`. Raises InsufficientDataError when the free parameters are not
    identified (a singular Fisher information)."""
    spec = MODELS[HELD_MODEL]
    if "h_z" in held and h_z is None:
        raise EstimationError("h_z is held but no value was given for it")
    terms = joint_terms(spec, a, m, a.sigma_hat, m.sigma_hat)
    full = JointProblem(terms)
    unknown = [n for n in held if n not in full.names]
    if unknown:
        raise EstimationError(f"unknown parameter(s) to hold: {', '.join(unknown)}")
    p0 = _start(a, m, K_a, b_a, h_z if "h_z" in held else None)
    free = np.array([n not in held for n in full.names])
    values = full.pack(p0)
    prob = HeldProblem(terms, free, values)
    if 3 * a.mu.shape[0] < prob.P:
        raise InsufficientDataError(f"{a.mu.shape[0]} still intervals cannot identify the {prob.P} free parameters "
                                    f"(3N >= {prob.P} needed); add poses at new headings")
    p1 = _provisional_start(a, m, K_a, b_a, h_z if "h_z" in held else None)
    fits = [prob.solve(q, max_iter=max_iter) for q in _starts(p0) + ([] if p1 is None else [p1])]
    # the proper branch: with the accelerometer's frame held, det K_m < 0 is a mirrored compass (its twin
    # (K_m D, -h_z), D = diag(1, 1, -1), predicts nearly the same readings when the tilts are small)
    fits = [r for r in fits if np.linalg.det(r.params.gains[1]) > 0] or fits
    res = min(fits, key=lambda r: r.cost)
    costs = (float(res.cost),) + tuple(float(r.cost) for r in fits if r is not res)
    if res.cov is None:
        raise InsufficientDataError("the poses do not identify the compass parameters fitted (singular Fisher "
                                    "information); turn the vehicle to more headings and tilt it a little")
    agree = sum(1 for c in costs if abs(c - costs[0]) <= 1e-7 * max(costs[0], 1e-300))
    note = ""
    if res.dof < WEAK_DOF or (chi2_sf(res.cost, res.dof) < WEAK_P and agree < 2):
        note = (f"chi2/dof = {res.cost / max(res.dof, 1):.3g} on {res.dof} degrees of freedom, {agree} of "
                f"{len(costs)} starts reached it: a wrong basin cannot be ruled out")
    res, prob, Sa, Sm, evidence = _reweight(res, prob, spec, a, m, free, values)
    name = cost_name(Sa, Sm, a, m)
    cert = certificate(prob, res.params, res.cost, costs, note, cost_name=name, start_cost_name=SAMPLE_COST)
    scale = (max(1.0, res.cost / res.dof) if res.dof > 0 and misfit_p(res.cost, res.dof, a, m) <= INFLATE_P
             else 1.0)
    sd = np.array([float(prior_sd.get(n, 0.0)) for n in full.names])
    cov = held_covariance(prob, res.params, sd, scale)
    if evidence:
        reason += (f"; {evidence}: the readings scatter more than their noise (motion in the intervals or magnetic "
                   f"disturbance?), so the returned point is the optimum of {name}")
    return _calibration(res, full, cov, cert, (Sa, Sm), a, m, tuple(held), reason)


def _provisional_start(a: IntervalStats, m: IntervalStats, K_a, b_a, h_z: float | None) -> JointParams | None:
    """A second start, from the headings of a provisional fit of the compass
    (:func:`mavcal.core.headings.provisional_headings`: offsets, scale, soft iron and dip fitted
    with each pose's tilt removed; issue 37), where the relaxation of :func:`_start` is far off
    (large offsets and soft iron beside a steep field); None when that fit fails."""
    try:
        T = tilts_of(np.linalg.solve(K_a, (a.mu - b_a).T).T)
        fit = provisional_headings(T, m.mu)
    except (EstimationError, InsufficientDataError, np.linalg.LinAlgError):
        return None
    hz = fit.h_z if h_z is None else float(h_z)
    R = np.array([T[i] @ _rotz(float(fit.psi_rad[i])) for i in range(T.shape[0])])
    return JointParams((np.asarray(K_a, float), fit.s_mgauss * np.eye(3)), (np.asarray(b_a, float), fit.b_mgauss),
                       hz, R)


def _starts(p0: JointParams) -> list[JointParams]:
    """The closed-form start and the same with every heading turned by 90, 180 and 270 deg: the
    costs they reach tell the optimum's basin from another (the headings are the cost's
    non-convex part once the held accelerometer fixes the tilts)."""
    return [p0] + [JointParams(p0.gains, p0.biases, p0.h_z, p0.R @ _rotz(k * np.pi / 2.0)) for k in (1, 2, 3)]


def _reweight(res: RefineResult, prob: HeldProblem, spec, a: IntervalStats, m: IntervalStats, free: np.ndarray,
              values: np.ndarray):
    """Each sensor's noise covariance inflated by its misfit and the fit repeated, only while J'
    rejects the noise model at p < ``REWEIGHT_P`` (the rule and the factors of
    :func:`mavcal.core.calibrate._reweight`, :mod:`mavcal.core.misfit`). Returns (result,
    problem, Sigma_a, Sigma_m, the evidence in words or "")."""
    Sa, Sm = a.sigma_hat, m.sigma_hat
    evidence = ""
    for _ in range(REWEIGHT_ROUNDS):
        step = reweight_factors(spec, a, m, Sa, Sm, res)
        if step is None:
            break
        fa, fm, p = step
        evidence = evidence or f"J' was {res.cost:.6g} on {res.dof} dof, p={p:.3g} < {REWEIGHT_P:g}"
        Sa, Sm = Sa * fa, Sm * fm
        prob = HeldProblem(joint_terms(spec, a, m, Sa, Sm), free, values)
        res = prob.solve(res.params, max_iter=200)
    return res, prob, Sa, Sm, evidence


def _calibration(res: RefineResult, full: JointProblem, cov, cert, S: tuple[np.ndarray, np.ndarray],
                 a: IntervalStats, m: IntervalStats, held: tuple[str, ...], reason: str) -> Calibration:
    p = res.params
    Sa, Sm = S
    converged = bool(res.converged and cert.certified)
    msg = (f"{HELD_MODEL} model with {', '.join(held)} held: J'={res.cost:.6g} after {res.iterations} "
           "refinement iterations" + ("" if res.converged else " (refinement did not reach its tolerance)"))
    if not cert.certified:
        msg += f"; not certified as the optimum: {cert.reason}"
    return Calibration(
        accel=SensorModel(p.gains[0], p.biases[0], Sa, "accel"),
        mag=SensorModel(p.gains[1], p.biases[1], Sm, "mag"),
        gravity=G_UNIT.copy(), field=np.array([1.0, 0.0, p.h_z]), orientations=p.R, cost=float(res.cost),
        iterations=int(res.iterations), converged=converged, message=msg, method="ncar", model=HELD_MODEL,
        model_reason=reason, param_names=full.names, param_cov=cov, n_accel=a.n, n_mag=m.n,
        refine_iterations=int(res.iterations), dof=int(res.dof), certificate=cert, held=held,
        noise_inflation=(inflation(Sa, a), inflation(Sm, m)), cost_name=cost_name(Sa, Sm, a, m))


def turned_stats(m: IntervalStats, Q: np.ndarray) -> IntervalStats:
    """The compass's statistics of the readings turned by ``Q`` (Q mu_hat[i], Q Sigma Q^T): those of
    a compass whose yaw mounting is ``Q`` from the one the readings were recovered with."""
    Q = np.asarray(Q, dtype=float)
    sc = None if m.interval_scatter is None else np.einsum("ij,njk,lk->nil", Q, m.interval_scatter, Q)
    return replace(m, mu=m.mu @ Q.T, scatter=Q @ m.scatter @ Q.T, sigma_hat=Q @ m.sigma_hat @ Q.T,
                   interval_scatter=sc)


#: the model of a held fit turned back by :func:`turn_compass`: the accelerometer's diagonal held values
#: and a general compass matrix (K_m = Q^T K', a symmetric matrix turned)
TURNED_MODEL = "diag-accel"
FORMS_FULL_LABELS = FORMS[MODELS[TURNED_MODEL].mag_form].labels  # K_m[11], K_m[12], ... all nine


def turn_compass(cal: Calibration, Q: np.ndarray) -> Calibration:
    """A held fit of the readings turned by ``Q`` (:func:`turned_stats`: K', b' of the ``ardupilot``
    model) expressed for the readings themselves: K_m = Q^T K', b_m = Q^T b', Sigma_m = Q^T Sigma' Q,
    the covariance carried through that linear map (model :data:`TURNED_MODEL`, K_m general), so that
    the mapping finds the turn Q as the compass's rotation (and writes it as its orientation) and the
    bounds draw the same compasses as the fit's covariance."""
    from mavcal.core.uncertainty import param_value

    Q = np.asarray(Q, dtype=float)
    names = tuple([n for n in cal.param_names if n.startswith(("K_a", "b_a"))]
                  + [f"K_m[{lab}]" for lab in FORMS_FULL_LABELS] + ["b_m[x]", "b_m[y]", "b_m[z]", "h_z"])

    def new_theta(theta: np.ndarray) -> np.ndarray:  # the held model's parameters (K_a diagonal, K_m symmetric)
        K_a, b_a, K_m, b_m, h_z = np.zeros((3, 3)), np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0
        for name, v in zip(cal.param_names, theta):
            if name == "h_z":
                h_z = float(v)
                continue
            sym, lab = name.rstrip("]").split("[")
            if sym in ("K_a", "K_m"):
                K = K_a if sym == "K_a" else K_m
                r, c = int(lab[0]) - 1, int(lab[1]) - 1
                K[r, c] = K[c, r] = v
            else:
                (b_a if sym == "b_a" else b_m)["xyz".index(lab)] = v
        return np.array([param_value(K_a, b_a, Q.T @ K_m, Q.T @ b_m, h_z, n) for n in names])

    theta = np.array([param_value(cal.accel.gain, cal.accel.bias, cal.mag.gain, cal.mag.bias, cal.h_z, n)
                      for n in cal.param_names])
    J = np.array([new_theta(e) for e in np.eye(len(theta))]).T  # linear: theta' = J theta
    cov = None if cal.param_cov is None else J @ np.asarray(cal.param_cov) @ J.T
    mag = replace(cal.mag, gain=Q.T @ cal.mag.gain, bias=Q.T @ cal.mag.bias, noise_cov=Q.T @ cal.mag.noise_cov @ Q)
    return replace(cal, mag=mag, param_names=names, param_cov=cov, model=TURNED_MODEL)

