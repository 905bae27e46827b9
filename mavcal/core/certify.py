"""Evidence that a fit is the global optimum of J' (Eq. ``partial_cost``), or why it may not be.

Two kinds of evidence, both in the gauge-fixed coordinates of :mod:`mavcal.core.refine`
(gains in their model's form, biases, h_z, and a local rotation vector per interval,
R_i <- R_i exp([d_i]x); g = [0, 0, -1], h_x = 1, so the continuous gauge is gone):

* **local optimality**: the gradient of J' is ~0, measured scale-free as the Gauss-Newton
  decrement g^T (J^T J)^-1 g (the cost decrease a Gauss-Newton step predicts), and the
  *exact* Hessian (Gauss-Newton part plus the analytic second-order terms of the residuals;
  checked against finite differences of the gradient in the tests) is positive definite. Its
  arrow structure (each orientation couples only with itself and the globals) keeps it O(N). Positive
  definiteness is checked on the orientation blocks and on their Schur complement, the
  Hessian of the profile cost min_R J'(theta, R); ``min_hessian_eig`` is the smallest
  eigenvalue of that profile Hessian relative to its Gauss-Newton approximation (the
  generalised eigenproblem H v = lambda (J^T J) v: 1 for a linear problem, ~1 at a
  small-residual optimum, <= 0 at a saddle).
* **global agreement**: the fit is repeated from every discrete branch of the model that
  the continuous search cannot cross (see :mod:`mavcal.core.calibrate`); the best of these
  deterministic starts must not beat the returned point.
"""
from __future__ import annotations

import numpy as np

from mavcal.core.refine import JointParams, JointProblem, gauss_newton_blocks, gradient_blocks, schur_complement
from mavcal.core.rotations import exp_so3, skew
from mavcal.core.types import OptimumCertificate

GRAD_TOL = 1e-8  # Gauss-Newton decrement allowed, relative to 1 + J'
EIG_TOL = 1e-9  # smallest scaled profile-Hessian eigenvalue that counts as positive
AGREE_RTOL = 1e-9  # another start beating the returned cost by more than this refutes it
SAMPLE_COST = "J' with the sample covariances"  # the paper's J' (Eq. partial_cost) with Sigma_hat


def _gradient(prob: JointProblem, theta: np.ndarray, R: np.ndarray) -> np.ndarray:
    """d J' / d (theta, d_1, ..., d_N) at (theta, R), (P + 3N,)."""
    r, Jg, Jr = prob.jacobians(prob.unpack(theta, R))
    return 2.0 * np.concatenate([np.einsum("nmp,nm->p", Jg, r), np.einsum("nmr,nm->nr", Jr, r).ravel()])


def _second_order(prob: JointProblem, p: JointParams, r: np.ndarray):
    """sum_k r_k d^2 r_k in arrow form (Sgg (P, P), Sgr (N, P, 3), Srr (N, 3, 3)), analytically.

    Per interval and sensor the residual is r = sqrt(Delta) L (K R exp([d]x) f + b - mu); with
    w = sqrt(Delta) L^T r and y = R^T K^T w the non-zero second derivatives are
    d-d: 1/2 (y_b f_a + y_a f_b) - delta_ab y.f; d-K_k: -w^T E_k R [f]x; d-h_z: -w^T K R [e_z]x;
    K_k-h_z: w^T E_k R e_z (gains enter linearly, biases affinely).
    """
    N, P = prob.N, prob.P
    Sgg = np.zeros((P, P))
    Sgr = np.zeros((N, P, 3))
    Srr = np.zeros((N, 3, 3))
    ez_x = skew(np.array([0.0, 0.0, 1.0]))
    col = 0
    for s_, (t, K, f, L, sn) in enumerate(zip(prob.terms, p.gains, prob._fields(p.h_z), prob.L, prob.sn)):
        w = (r[:, 3 * s_:3 * s_ + 3] @ L) * sn[:, None]  # (N, 3) = sqrt(n) L^T r
        y = np.einsum("nji,kj,nk->ni", p.R, K, w, optimize=prob.blas)  # R^T K^T w
        yf = y @ f
        Srr += 0.5 * (y[:, None, :] * f[None, :, None] + y[:, :, None] * f[None, None, :])
        Srr -= yf[:, None, None] * np.eye(3)
        Rfx = p.R @ skew(f)  # (N, 3, 3)
        Sgr[:, col:col + t.form.size, :] -= np.einsum("ni,kij,njb->nkb", w, t.form.basis, Rfx, optimize=prob.blas)
        if t.kind == "mag":
            Sgr[:, P - 1, :] -= np.einsum("ni,ij,njb->nb", w, K, p.R @ ez_x, optimize=prob.blas)
            v = np.einsum("ni,kij,nj->k", w, t.form.basis, p.R[:, :, 2], optimize=prob.blas)
            Sgg[col:col + t.form.size, P - 1] += v
            Sgg[P - 1, col:col + t.form.size] += v
        col += t.form.size + 3
    return Sgg, Sgr, Srr


def exact_hessian_blocks(prob: JointProblem, p: JointParams):
    """Exact Hessian of J' in arrow form: 2 (J^T J + sum_k r_k d^2 r_k).

    Returns (Hgg (P, P), Hgr (N, P, 3), Hrr (N, 3, 3)): each orientation couples only with
    itself and the global parameters. A problem with parameters held at given values
    (``prob.columns``, :class:`mavcal.core.held.HeldProblem`) gets the blocks of its free
    parameters: held coordinates are constants, so its Hessian is the full one's sub-block.
    """
    base = prob.base
    r, Jg, Jr = base.jacobians(p)
    Sgg, Sgr, Srr = _second_order(base, p, r)
    Ggg, Ggr, Grr = gauss_newton_blocks(Jg, Jr, blas=base.blas)
    Hgg = 2.0 * (Ggg + Sgg)
    Hgr = 2.0 * (Ggr + Sgr)
    Hrr = 2.0 * (Grr + Srr)
    c = prob.columns
    if c is not None:
        Hgg, Hgr = Hgg[np.ix_(c, c)], Hgr[:, c, :]
    return Hgg, Hgr, Hrr


def exact_hessian_fd(prob: JointProblem, p: JointParams):
    """The same blocks by forward differences of the analytic gradient (P + 3 evaluations; for tests)."""
    theta = prob.pack(p)
    P, N = prob.P, prob.N
    g0 = _gradient(prob, theta, p.R)
    Hgg = np.empty((P, P))
    Hgr = np.empty((N, P, 3))
    Hrr = np.empty((N, 3, 3))
    for k in range(P):
        h = 1e-6 * max(1.0, abs(theta[k]))
        t = theta.copy()
        t[k] += h
        dg = (_gradient(prob, t, p.R) - g0) / h
        Hgg[:, k] = dg[:P]
        Hgr[:, k, :] = dg[P:].reshape(N, 3)
    for j in range(3):
        w = np.zeros((N, 3))
        w[:, j] = 1e-6
        dg = (_gradient(prob, theta, p.R @ exp_so3(w)) - g0) / 1e-6
        Hrr[:, :, j] = dg[P:].reshape(N, 3)
    return 0.5 * (Hgg + Hgg.T), Hgr, 0.5 * (Hrr + np.swapaxes(Hrr, 1, 2))


def local_evidence(prob: JointProblem, p: JointParams) -> tuple[float, float, str]:
    """(Gauss-Newton decrement, smallest scaled profile-Hessian eigenvalue, failure reason or "")."""
    r, Jg, Jr = prob.jacobians(p)
    cost = float(np.sum(r * r))
    # Gauss-Newton decrement with the Schur complement over the orientation blocks
    Ggg, Ggr, Grr = gauss_newton_blocks(Jg, Jr, blas=prob.blas)
    gg, gr = gradient_blocks(Jg, Jr, r, blas=prob.blas)
    try:
        Grr_inv = np.linalg.inv(Grr)
        S = schur_complement(Ggg, Ggr, Grr_inv, blas=prob.blas)
        rhs = gg - np.einsum("npr,nrs,ns->p", Ggr, Grr_inv, gr, optimize=prob.blas)
        dec = float(rhs @ np.linalg.solve(S, rhs) + np.einsum("nr,nrs,ns->", gr, Grr_inv, gr, optimize=prob.blas))
    except np.linalg.LinAlgError:
        return np.inf, -np.inf, "the Gauss-Newton matrix is singular: the parameters are not identified"
    Hgg, Hgr, Hrr = exact_hessian_blocks(prob, p)
    if np.any(np.linalg.eigvalsh(Hrr)[:, 0] <= 0):
        return dec, -np.inf, "an orientation is at a saddle or maximum of J' (exact Hessian block not positive)"
    Hp = schur_complement(Hgg, Hgr, np.linalg.inv(Hrr), blas=prob.blas)
    try:  # relative to the Gauss-Newton profile Hessian 2 S: 1 for a linear problem, <= 0 at a saddle
        Li = np.linalg.inv(np.linalg.cholesky(2.0 * S))
        lam = float(np.linalg.eigvalsh(Li @ Hp @ Li.T)[0])
    except np.linalg.LinAlgError:
        return dec, -np.inf, "the Gauss-Newton matrix is not positive definite: the parameters are not identified"
    if not np.isfinite(dec) or dec > GRAD_TOL * (1.0 + cost):
        return dec, lam, f"the gradient is not zero (Gauss-Newton decrement {dec:.3g} at J'={cost:.6g})"
    if lam <= EIG_TOL:
        return dec, lam, f"the exact Hessian is not positive definite (smallest scaled eigenvalue {lam:.3g})"
    return dec, lam, ""


def _profile_min_eig(prob: JointProblem, p: JointParams):
    """Smallest eigenpair of the exact profile Hessian relative to Gauss-Newton: (lambda, v, Hgr, Hrr)."""
    r, Jg, Jr = prob.jacobians(p)
    Ggg = np.einsum("nmp,nmq->pq", Jg, Jg)
    Ggr = np.einsum("nmp,nmr->npr", Jg, Jr)
    Grr = np.einsum("nmr,nms->nrs", Jr, Jr)
    S = Ggg - np.einsum("npr,nrs,nqs->pq", Ggr, np.linalg.inv(Grr), Ggr)
    Hgg, Hgr, Hrr = exact_hessian_blocks(prob, p)
    Hp = Hgg - np.einsum("npr,nrs,nqs->pq", Hgr, np.linalg.inv(Hrr), Hgr)
    Li = np.linalg.inv(np.linalg.cholesky(2.0 * S))
    lam, V = np.linalg.eigh(Li @ Hp @ Li.T)
    return float(lam[0]), Li.T @ V[:, 0], Hgr, Hrr


def escape_saddle(prob: JointProblem, p: JointParams, cost: float) -> JointParams | None:
    """A point of lower J' along the direction of negative curvature, or None.

    Gauss-Newton type methods (this package's LM, scipy's least_squares) stop wherever the
    gradient vanishes, also at a saddle of J' whose negative curvature J^T J cannot see. Along
    the eigenvector v of the profile Hessian's negative eigenvalue (orientations following,
    d_i = -Hrr_i^-1 Hrg_i v), steps of both signs and several lengths are tried.
    """
    try:
        lam, v, Hgr, Hrr = _profile_min_eig(prob, p)
    except np.linalg.LinAlgError:
        return None
    if lam >= 0:
        return None
    dr = -np.einsum("nrs,nps,p->nr", np.linalg.inv(Hrr), Hgr, v)
    theta = prob.pack(p)
    best, best_cost = None, cost
    for t in (4.0, 2.0, 1.0, 0.5, 0.25, 0.1, -0.1, -0.25, -0.5, -1.0, -2.0, -4.0):
        q = prob.unpack(theta + t * v, p.R @ exp_so3(t * dr))
        c = float(np.sum(prob.residuals(q) ** 2))
        if np.isfinite(c) and c < best_cost:
            best, best_cost = q, c
    return best


def certificate(prob: JointProblem, p: JointParams, cost: float, start_costs: tuple[float, ...],
                note: str | None = None, *, cost_name: str = SAMPLE_COST,
                start_cost_name: str | None = None) -> OptimumCertificate:
    """Combine the local evidence at ``p`` with the costs reached from the other starts.

    ``prob`` is the cost ``p`` minimises (its noise covariances), named ``cost_name``: the
    local evidence is for that cost, at the returned point. ``start_costs`` are of
    ``start_cost_name`` (default: the same cost): a search compares its basins before any
    reweighting (:func:`mavcal.core.calibrate._reweight`), so after a reweighting the returned
    point is the search's best basin followed to the optimum of the reweighted cost, and the
    two names differ.
    """
    dec, lam, why = local_evidence(prob, p)
    best_other = min(start_costs[1:], default=np.inf)
    reasons = [why] if why else []
    if best_other < start_costs[0] * (1.0 - AGREE_RTOL):
        reasons.append(f"another start reached a lower J' ({best_other:.8g} < {start_costs[0]:.8g}): "
                       "the returned point is a local minimum")
    if note:
        reasons.append(note)
    global_ok = len(reasons) == (1 if why else 0)
    return OptimumCertificate(starts=len(start_costs), start_costs=tuple(float(c) for c in start_costs),
                              grad_decrement=float(dec), min_hessian_eig=float(lam), local_ok=not why,
                              global_ok=global_ok, reason="; ".join(reasons), cost=float(cost), cost_name=cost_name,
                              start_cost_name=cost_name if start_cost_name is None else start_cost_name)


__all__ = ["OptimumCertificate", "SAMPLE_COST", "certificate", "escape_saddle", "local_evidence",
           "exact_hessian_blocks", "exact_hessian_fd"]
