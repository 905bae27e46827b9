"""Joint refinement of all parameters: the exact optimum of the cost, and its uncertainty.

The paper's block steps (Sec. VII) converge linearly and slowly near the optimum. After
them, a Levenberg-Marquardt iteration on *all* parameters at once (gains, biases, h_z and
every orientation) minimises the same partial cost J' (Eq. ``partial_cost``)

    J' = sum_s sum_i Delta_s[i] (K_s R_i s^I + b_s - mu_hat_s[i])^T Sigma_s^-1 (...)

with an analytic Jacobian. The orientations enter through a local rotation vector
(R_i <- R_i exp([d_i]x)), and the normal equations are solved with a Schur complement that
eliminates the 3x3 block of each interval, so one iteration costs O(N).

At the optimum, (J^T J)^-1 restricted to the global parameters (orientations marginalised
by the same Schur complement) is the Gauss-Newton approximation of the inverse Fisher
information, since J'/2 is the negative log-likelihood up to a constant.

Any number of sensors can share the orientations (the multi-sensor fit); magnetometers
share the field h = [1, 0, h_z], accelerometers the gravity g = [0, 0, -1].

Two kernels compute the same sums: ``einsum`` (the default, whose results small fits
reproduce bit for bit) and BLAS matrix products (:func:`blas_kernels`), several times faster
at hundreds of intervals and equal up to rounding; :func:`mavcal.core.calibrate.calibrate`
uses the latter on its large-N path only.
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np

from mavcal.core.initial import G_UNIT
from mavcal.core.models import FORMS, GainForm
from mavcal.core.rotations import exp_so3, skew

_BLAS = ContextVar("mavcal_refine_blas", default=False)
_EYE3 = np.eye(3)


@contextmanager
def blas_kernels() -> Iterator[None]:
    """Within this context, new :class:`JointProblem` s form J^T J and its Schur complement
    with BLAS matrix products instead of ``einsum``: the same sums in another order (equal
    up to rounding), several times faster at large N."""
    token = _BLAS.set(True)
    try:
        yield
    finally:
        _BLAS.reset(token)


@dataclass(frozen=True, eq=False)
class Term:
    """One sensor in the joint problem."""

    kind: str  # "accel" or "mag"
    form: GainForm
    mu: np.ndarray  # (N, 3)
    n: np.ndarray  # (N,)
    Sigma: np.ndarray  # (3, 3)
    name: str = ""

    @property
    def whiten(self) -> np.ndarray:
        """L with L^T L = Sigma^-1."""
        return np.linalg.cholesky(np.linalg.inv(self.Sigma)).T


@dataclass(frozen=True, eq=False)
class JointParams:
    gains: tuple[np.ndarray, ...]  # per term, (3, 3)
    biases: tuple[np.ndarray, ...]  # per term, (3,)
    h_z: float
    R: np.ndarray  # (N, 3, 3)


@dataclass(frozen=True, eq=False)
class RefineResult:
    params: JointParams
    cost: float
    iterations: int
    converged: bool
    cov: np.ndarray | None  # global parameter covariance (unscaled (J^T J)^-1)
    names: tuple[str, ...]
    dof: int
    # (J', dof, p, the cost's name, model) that first rejected the noise model and made the fit
    # reweight its noise covariances (:func:`mavcal.core.calibrate._reweight`); None when none did
    misfit: tuple[float, int, float, str, str] | None = None


class JointProblem:
    """Residuals and Jacobians of J' for a list of sensor terms sharing orientations."""

    def __init__(self, terms: Sequence[Term]):
        self.terms = list(terms)
        self.blas = _BLAS.get()
        self.N = self.terms[0].mu.shape[0]
        self.has_mag = any(t.kind == "mag" for t in self.terms)
        self.L = [t.whiten for t in self.terms]
        self.sn = [np.sqrt(t.n) for t in self.terms]
        # parts of the Jacobian that do not change with the parameters (computed once, the same
        # expressions): rows (k, i) of L E_k, the bias block L sqrt(n), [g]x of the accelerometer's field
        self._LB = [(L @ t.form.basis).reshape(3 * t.form.size, 3) for t, L in zip(self.terms, self.L)]
        self._Lsn = [L[None] * sn[:, None, None] for L, sn in zip(self.L, self.sn)]
        self._skew_g = skew(G_UNIT)
        self.sizes = [t.form.size + 3 for t in self.terms]
        self.P = sum(self.sizes) + (1 if self.has_mag else 0)
        names: list[str] = []
        for t in self.terms:
            sym = "K_a" if t.kind == "accel" else "K_m"
            bsym = "b_a" if t.kind == "accel" else "b_m"
            tag = t.name
            names += [f"{sym}{tag}[{lab}]" for lab in t.form.labels]
            names += [f"{bsym}{tag}[{k}]" for k in "xyz"]
        if self.has_mag:
            names.append("h_z")
        self.names = tuple(names)
        # the problem whose full parameter vector this one's columns are taken from, and which
        # (None: all); :class:`mavcal.core.held.HeldProblem` holds the others at given values
        self.base: JointProblem = self
        self.columns: np.ndarray | None = None

    # parameter vector <-> structured parameters
    def pack(self, p: JointParams) -> np.ndarray:
        parts = []
        for t, K, b in zip(self.terms, p.gains, p.biases):
            parts += [t.form.from_matrix(K), np.asarray(b, float)]
        if self.has_mag:
            parts.append(np.array([p.h_z]))
        return np.concatenate(parts)

    def unpack(self, theta: np.ndarray, R: np.ndarray) -> JointParams:
        gains, biases, k = [], [], 0
        for t in self.terms:
            gains.append(t.form.to_matrix(theta[k:k + t.form.size]))
            k += t.form.size
            biases.append(theta[k:k + 3].copy())
            k += 3
        h_z = float(theta[k]) if self.has_mag else 0.0
        return JointParams(tuple(gains), tuple(biases), h_z, R)

    def _fields(self, h_z: float):
        return [G_UNIT if t.kind == "accel" else np.array([1.0, 0.0, h_z]) for t in self.terms]

    def residuals(self, p: JointParams) -> np.ndarray:
        """Whitened, sqrt(Delta)-weighted residuals, shape (N, 3 * n_terms)."""
        if self.blas:
            return self._residuals_blas(p)
        out = []
        for t, K, b, f, L, sn in zip(self.terms, p.gains, p.biases, self._fields(p.h_z), self.L, self.sn):
            pred = (K @ (p.R @ f)[..., None])[..., 0] + b
            out.append(((pred - t.mu) @ L.T) * sn[:, None])
        return np.concatenate(out, axis=1)

    def _residuals_blas(self, p: JointParams) -> np.ndarray:
        """:meth:`residuals` by 2-D matrix products over all intervals at once."""
        N = self.N
        R2 = p.R.reshape(3 * N, 3)
        out = []
        for t, K, b, f, L, sn in zip(self.terms, p.gains, p.biases, self._fields(p.h_z), self.L, self.sn):
            pred = (R2 @ f).reshape(N, 3) @ K.T + b
            out.append(((pred - t.mu) @ L.T) * sn[:, None])
        return np.concatenate(out, axis=1)

    def _jacobians_blas(self, p: JointParams):
        """:meth:`jacobians` by 2-D matrix products over all intervals at once (equal up to rounding)."""
        N, P = self.N, self.P
        m = 3 * len(self.terms)
        Jg = np.zeros((N, m, P))
        Jr = np.empty((N, m, 3))
        r = np.empty((N, m))
        R2 = p.R.reshape(3 * N, 3)
        col = 0
        for s, (t, K, b, f, L, sn) in enumerate(zip(self.terms, p.gains, p.biases, self._fields(p.h_z),
                                                     self.L, self.sn)):
            rows = slice(3 * s, 3 * s + 3)
            v = (R2 @ f).reshape(N, 3)
            r[:, rows] = ((v @ K.T + b - t.mu) @ L.T) * sn[:, None]
            k = t.form.size
            LB = self._LB[s]  # rows (k, i): (L E_k)[i, :]
            Jg[:, rows, col:col + k] = ((v @ LB.T).reshape(N, k, 3) * sn[:, None, None]).transpose(0, 2, 1)
            col += k
            Jg[:, rows, col:col + 3] = self._Lsn[s]
            col += 3
            LK = L @ K
            if t.kind == "mag":
                Jg[:, rows, P - 1] = (p.R[:, :, 2] @ LK.T) * sn[:, None]
            RF = (R2 @ (self._skew_g if t.kind == "accel" else skew(f))).reshape(N, 3, 3)  # R_n [f]x
            Jr[:, rows, :] = -(RF.transpose(0, 2, 1).reshape(3 * N, 3) @ LK.T).reshape(N, 3, 3).transpose(0, 2, 1) \
                * sn[:, None, None]
        return r, Jg, Jr

    def jacobians(self, p: JointParams):
        """(r, Jg, Jr): residuals (N, m), global Jacobian (N, m, P), rotation Jacobian (N, m, 3)."""
        if self.blas:
            return self._jacobians_blas(p)
        N, P = self.N, self.P
        m = 3 * len(self.terms)
        Jg = np.zeros((N, m, P))
        Jr = np.empty((N, m, 3))
        r = np.empty((N, m))
        col = 0
        for s, (t, K, b, f, L, sn) in enumerate(zip(self.terms, p.gains, p.biases, self._fields(p.h_z),
                                                     self.L, self.sn)):
            rows = slice(3 * s, 3 * s + 3)
            v = p.R @ f  # (N, 3)
            r[:, rows] = ((((K @ v[..., None])[..., 0] + b) - t.mu) @ L.T) * sn[:, None]
            Ev = np.einsum("kij,nj->nik", t.form.basis, v)  # (N, 3, k)
            Jg[:, rows, col:col + t.form.size] = (L @ Ev) * sn[:, None, None]
            col += t.form.size
            Jg[:, rows, col:col + 3] = L[None] * sn[:, None, None]
            col += 3
            LK = L @ K
            if t.kind == "mag":
                Jg[:, rows, P - 1] = (LK @ p.R[:, :, 2:3])[..., 0] * sn[:, None]
            Jr[:, rows, :] = -(LK @ p.R @ skew(f)) * sn[:, None, None]
        return r, Jg, Jr

    def solve(self, p0: JointParams, *, max_iter: int = 100, rtol: float = 1e-13,
              covariance: bool = True) -> RefineResult:
        """Levenberg-Marquardt with a Schur complement over the orientation blocks."""
        theta = self.pack(p0)
        p = self.unpack(theta, p0.R)
        r, Jg, Jr = self.jacobians(p)
        cost = float(np.sum(r * r))
        lam = 1e-4
        converged = False
        it = 0
        for it in range(1, max_iter + 1):  # noqa: B007 (the count is returned)
            Hgg, Hgr, Hrr = gauss_newton_blocks(Jg, Jr, blas=self.blas)
            gg, gr = gradient_blocks(Jg, Jr, r, blas=self.blas)
            improved = False
            # what every trial's damped system takes from this iteration's blocks
            dgg, drr, wide_gr = np.diag(Hgg), np.einsum("nii->ni", Hrr)[:, :, None], _wide(Hgr) if self.blas else None
            for trial in range(12):
                Dg = dgg * lam + 1e-300
                Drr = Hrr + lam * drr * _EYE3
                try:
                    Hrr_inv = inv3(Drr) if self.blas else np.linalg.inv(Drr)
                except np.linalg.LinAlgError:
                    lam *= 10.0
                    continue
                S, rhs = _reduced_system(Hgg + np.diag(Dg), Hgr, Hrr_inv, gg, gr, self.blas, wide_gr)
                try:
                    dth = -np.linalg.solve(S, rhs)
                except np.linalg.LinAlgError:
                    lam *= 10.0
                    continue
                dr = _local_steps(Hgr, Hrr_inv, gr, dth, self.blas)
                th_new = theta + dth
                p_new = self.unpack(th_new, p.R @ exp_so3(dr))
                r_new = self.residuals(p_new)
                c_new = float(np.sum(r_new * r_new))
                if np.isfinite(c_new) and c_new <= cost:
                    dec = cost - c_new
                    theta, p, cost = th_new, p_new, c_new
                    lam = max(lam * 0.1, 1e-12)
                    improved = True
                    break
                if (self.blas and trial == 0 and lam <= 1e-3
                        and _model_decrease(Hgg, Hgr, Hrr, gg, gr, dth, dr) <= rtol * max(cost, 1e-300)):
                    break  # a nearly Gauss-Newton step failed and promised nothing: at the optimum (to rounding)
                lam *= 10.0
            if not improved:
                converged = True  # no descent direction left: at the optimum (to rounding)
                break
            r, Jg, Jr = self.jacobians(p)
            if dec <= rtol * max(cost, 1e-300) or cost == 0.0:
                converged = True
                break
        cov = self.covariance(Jg, Jr) if covariance else None
        dof = 3 * len(self.terms) * self.N - 3 * self.N - self.P
        return RefineResult(params=p, cost=cost, iterations=it, converged=converged, cov=cov,
                            names=self.names, dof=dof)

    def covariance(self, Jg: np.ndarray, Jr: np.ndarray) -> np.ndarray | None:
        """(J^T J)^-1 on the global parameters, orientations marginalised (Schur complement)."""
        Hgg, Hgr, Hrr = gauss_newton_blocks(Jg, Jr, blas=self.blas)
        try:
            Hrr_inv = inv3(Hrr) if self.blas else np.linalg.inv(Hrr)
            cov = np.linalg.inv(schur_complement(Hgg, Hgr, Hrr_inv, blas=self.blas))
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(cov)):
            return None
        return 0.5 * (cov + cov.T)


def gauss_newton_blocks(Jg: np.ndarray, Jr: np.ndarray, *, blas: bool = False
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of J^T J with one 3x3 orientation block per interval: ``Hgg`` (P, P), ``Hgr``
    (N, P, 3), ``Hrr`` (N, 3, 3), from the Jacobians of :meth:`JointProblem.jacobians`
    (``blas``: by matrix products, see :func:`blas_kernels`)."""
    if blas:
        J2 = Jg.reshape(-1, Jg.shape[2])
        return J2.T @ J2, np.swapaxes(Jg, 1, 2) @ Jr, np.swapaxes(Jr, 1, 2) @ Jr
    return (np.einsum("nmp,nmq->pq", Jg, Jg), np.einsum("nmp,nmr->npr", Jg, Jr),
            np.einsum("nmr,nms->nrs", Jr, Jr))


def gradient_blocks(Jg: np.ndarray, Jr: np.ndarray, r: np.ndarray, *, blas: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
    """J^T r split as the global part (P,) and one 3-vector per interval (N, 3)."""
    if blas:
        return Jg.reshape(-1, Jg.shape[2]).T @ r.reshape(-1), (np.swapaxes(Jr, 1, 2) @ r[:, :, None])[:, :, 0]
    return np.einsum("nmp,nm->p", Jg, r), np.einsum("nmr,nm->nr", Jr, r)


def _wide(X: np.ndarray) -> np.ndarray:
    """(N, P, 3) -> (P, 3N): [X_1 ... X_N] side by side, for one BLAS product over all n."""
    return X.transpose(1, 0, 2).reshape(X.shape[1], -1)


def schur_complement(Hgg: np.ndarray, Hgr: np.ndarray, Hrr_inv: np.ndarray, *, blas: bool = False) -> np.ndarray:
    """Hgg - sum_n Hgr_n Hrr_n^-1 Hgr_n^T: the global block with the orientations eliminated."""
    if blas:
        return Hgg - _wide(Hgr @ Hrr_inv) @ _wide(Hgr).T
    return Hgg - np.einsum("npr,nrs,nqs->pq", Hgr, Hrr_inv, Hgr)


def _reduced_system(Hgg, Hgr, Hrr_inv, gg, gr, blas: bool, wide_gr: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The Schur complement S of the (damped) ``Hgg`` and the right-hand side
    gg - sum_n Hgr_n Hrr_n^-1 gr_n of one LM step (``wide_gr``: ``_wide(Hgr)`` when already made)."""
    if blas:
        W = _wide(Hgr @ Hrr_inv)
        return Hgg - W @ (_wide(Hgr) if wide_gr is None else wide_gr).T, gg - W @ gr.reshape(-1)
    HgrHi = np.einsum("npr,nrs->nps", Hgr, Hrr_inv)
    return Hgg - np.einsum("nps,nqs->pq", HgrHi, Hgr), gg - np.einsum("nps,ns->p", HgrHi, gr)


def inv3(A: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 3x3 matrices (N, 3, 3) by the adjugate (LinAlgError if singular)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    adj = np.empty_like(A)
    adj[:, 0, 0], adj[:, 1, 0], adj[:, 2, 0] = e * i - f * h, f * g - d * i, d * h - e * g
    adj[:, 0, 1], adj[:, 1, 1], adj[:, 2, 1] = c * h - b * i, a * i - c * g, b * g - a * h
    adj[:, 0, 2], adj[:, 1, 2], adj[:, 2, 2] = b * f - c * e, c * d - a * f, a * e - b * d
    det = a * adj[:, 0, 0] + b * adj[:, 1, 0] + c * adj[:, 2, 0]
    if not np.all(np.isfinite(det)) or np.any(det == 0.0):
        raise np.linalg.LinAlgError("singular 3x3 block")
    return adj / det[:, None, None]


def _model_decrease(Hgg, Hgr, Hrr, gg, gr, dth, dr) -> float:
    """Decrease of the cost r^T r that the Gauss-Newton model predicts for the step (dth, dr):
    -(2 g^T delta + delta^T J^T J delta), with the arrow-shaped blocks of J^T J."""
    quad = dth @ Hgg @ dth + 2.0 * np.sum((dth @ Hgr) * dr) + np.sum(dr * (Hrr @ dr[:, :, None])[:, :, 0])
    return float(-2.0 * (gg @ dth + np.sum(gr * dr)) - quad)


def _local_steps(Hgr, Hrr_inv, gr, dth, blas: bool) -> np.ndarray:
    """The orientation steps -Hrr_n^-1 (gr_n + Hgr_n^T dth) given the global step."""
    if blas:
        return -(Hrr_inv @ (gr + dth @ Hgr)[:, :, None])[:, :, 0]
    return -np.einsum("nrs,ns->nr", Hrr_inv, gr + np.einsum("npr,p->nr", Hgr, dth))


def refit_covariances(problem: JointProblem, p: JointParams, scatters: Sequence[np.ndarray],
                      diagonal: bool) -> list[np.ndarray]:
    """ML noise covariances of Eq. ``covariance_estimation`` for every term."""
    out = []
    for t, K, b, f, S in zip(problem.terms, p.gains, p.biases, problem._fields(p.h_z), scatters):
        rr = (K @ (p.R @ f)[..., None])[..., 0] + b - t.mu
        C = (S + np.einsum("ni,nj,n->ij", rr, rr, t.n)) / t.n.sum()
        C = 0.5 * (C + C.T)
        if diagonal:
            C = np.diag(np.diag(C))
        scale = max(np.linalg.norm(t.mu, axis=1).max(), 1e-300)
        w, V = np.linalg.eigh(C)
        out.append((V * np.maximum(w, (1e-12 * scale) ** 2)) @ V.T)
    return out


__all__ = ["Term", "JointParams", "JointProblem", "RefineResult", "refit_covariances", "FORMS", "blas_kernels",
           "gauss_newton_blocks", "gradient_blocks", "schur_complement"]
