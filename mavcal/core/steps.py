"""Block-coordinate optimisation steps of the paper's Sec. VII, and the cost functions.

State: K_a (upper triangular), b_a, K_m (full), b_m, h_z, orientations R_i, and the noise
covariances Sigma_a, Sigma_m. With g = [0, 0, -1], h = [1, 0, h_z]:

* partial cost J' (Eq. ``partial_cost``): sum_i sum_s Delta_s[i] mu~^T Sigma_s^-1 mu~,
  mu~ = K_s R_i s^I + b_s - mu_hat_s[i];
* complete cost J (Eq. ``complete_cost``), written with the sufficient statistics:
  sum_s [ n_s ln|Sigma_s| + tr(Sigma_s^-1 S_s) + sum_i Delta_s[i] mu~^T Sigma_s^-1 mu~ ],
  S_s = within-interval scatter, n_s = sum_i Delta_s[i].

Steps (one iteration = all four, in this order):
1. orientations: the approximation of Eq. ``rotation_approximation`` or a direct
   minimisation of Eq. ``rotation_estimation`` (Sec. VII-A);
2. biases and fields by GLS (Sec. VII-B), then the renormalisation g_z = -1, h_x = 1;
3. gains by GLS, K_a upper triangular, K_m full (Sec. VII-C);
4. (FCAR/DCAR only) the ML covariance of Eq. ``covariance_estimation``, full or diagonal.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mavcal.core.initial import G_UNIT, approximate_rotations, sensor_weight
from mavcal.core.rotations import exp_so3, skew
from mavcal.core.stats import IntervalStats


@dataclass(frozen=True, eq=False)
class State:
    K_a: np.ndarray
    b_a: np.ndarray
    K_m: np.ndarray
    b_m: np.ndarray
    h_z: float
    R: np.ndarray  # (N, 3, 3)
    Sigma_a: np.ndarray
    Sigma_m: np.ndarray

    @property
    def h(self) -> np.ndarray:
        return np.array([1.0, 0.0, self.h_z])


def residual_means(st: State, a: IntervalStats, m: IntervalStats):
    """mu~_s[i] = K_s R_i s^I + b_s - mu_hat_s[i] for both sensors, (N, 3) each."""
    ra = (st.K_a @ (st.R @ G_UNIT)[..., None])[..., 0] + st.b_a - a.mu
    rm = (st.K_m @ (st.R @ st.h)[..., None])[..., 0] + st.b_m - m.mu
    return ra, rm


def _quad(r: np.ndarray, n: np.ndarray, Sigma: np.ndarray) -> float:
    W = np.linalg.inv(Sigma)
    return float(np.einsum("ni,ij,nj,n->", r, W, r, n))


def partial_cost(st: State, a: IntervalStats, m: IntervalStats) -> float:
    """J' of Eq. ``partial_cost`` with the covariances held in the state."""
    ra, rm = residual_means(st, a, m)
    return _quad(ra, a.n, st.Sigma_a) + _quad(rm, m.n, st.Sigma_m)


def complete_cost(st: State, a: IntervalStats, m: IntervalStats) -> float:
    """J of Eq. ``complete_cost`` from the sufficient statistics."""
    out = partial_cost(st, a, m)
    for S, stats in ((st.Sigma_a, a), (st.Sigma_m, m)):
        out += stats.total * np.linalg.slogdet(S)[1] + float(np.trace(np.linalg.solve(S, stats.scatter)))
    return out


# --- step 1: orientations ------------------------------------------------------------------

def rotations_approx(st: State, a: IntervalStats, m: IntervalStats) -> State:
    """Eq. ``rotation_approximation`` with the current parameters."""
    sa = np.linalg.solve(st.K_a, (a.mu - st.b_a).T).T
    sm = np.linalg.solve(st.K_m, (m.mu - st.b_m).T).T
    w = [sensor_weight(st.K_a, st.Sigma_a), sensor_weight(st.K_m, st.Sigma_m)]
    return replace(st, R=approximate_rotations([sa, sm], [G_UNIT, st.h], w))


def rotations_direct(st: State, a: IntervalStats, m: IntervalStats, iterations: int = 10,
                     tol: float = 1e-12) -> State:
    """Minimise Eq. ``rotation_estimation`` for every interval (vectorised Gauss-Newton).

    The paper uses gradient descent on a quaternion; Gauss-Newton on a local rotation
    vector (R_i <- R_i exp([d]x)) minimises the same per-interval cost and converges in a
    few steps. Each interval's step is accepted only if its cost decreases.
    """
    La = np.linalg.cholesky(np.linalg.inv(st.Sigma_a)).T  # W = La^T La
    Lm = np.linalg.cholesky(np.linalg.inv(st.Sigma_m)).T
    sa, sm = np.sqrt(a.n)[:, None, None], np.sqrt(m.n)[:, None, None]
    Ma, Mm = La @ st.K_a, Lm @ st.K_m
    ya = (a.mu - st.b_a) @ La.T
    ym = (m.mu - st.b_m) @ Lm.T
    Ga, Gh = skew(G_UNIT), skew(st.h)

    def res(R):
        ra = ((Ma @ (R @ G_UNIT)[..., None])[..., 0] - ya) * sa[..., 0]
        rm = ((Mm @ (R @ st.h)[..., None])[..., 0] - ym) * sm[..., 0]
        return np.concatenate([ra, rm], axis=1)

    R = st.R
    r = res(R)
    c = np.einsum("ni,ni->n", r, r)
    lam = np.full(len(R), 1e-6)
    for _ in range(iterations):
        Ja = -(Ma @ R @ Ga) * sa
        Jm = -(Mm @ R @ Gh) * sm
        J = np.concatenate([Ja, Jm], axis=1)  # (N, 6, 3)
        H = np.einsum("nki,nkj->nij", J, J)
        g = np.einsum("nki,nk->ni", J, r)
        H = H + lam[:, None, None] * np.eye(3) * (1.0 + np.einsum("nii->ni", H)[:, :, None])
        d = -np.linalg.solve(H, g[..., None])[..., 0]
        R_new = R @ exp_so3(d)
        r_new = res(R_new)
        c_new = np.einsum("ni,ni->n", r_new, r_new)
        ok = c_new < c
        R = np.where(ok[:, None, None], R_new, R)
        r = np.where(ok[:, None], r_new, r)
        dc = np.where(ok, c - c_new, 0.0)
        c = np.where(ok, c_new, c)
        lam = np.where(ok, lam * 0.1, lam * 10.0)
        if np.all(dc <= tol * (1.0 + c)):
            break
    return replace(st, R=R)


# --- step 2: biases and fields (GLS) -------------------------------------------------------

def _gls(X: np.ndarray, y: np.ndarray, n: np.ndarray, W: np.ndarray) -> np.ndarray:
    """beta = (sum_i n_i X_i^T W X_i)^-1 sum_i n_i X_i^T W y_i for X (N, 3, p), y (N, 3)."""
    WX = W @ X
    A = np.einsum("nkp,nkq,n->pq", X, WX, n)
    rhs = np.einsum("nkp,nk,n->p", WX, y, n)
    return np.linalg.solve(A, rhs)


def bias_field_step(st: State, a: IntervalStats, m: IntervalStats) -> State:
    """GLS for [g_z, b_a] and [h_x, h_z, b_m] (Sec. VII-B), then g_z = -1, h_x = 1."""
    N = len(st.R)
    I3 = np.broadcast_to(np.eye(3), (N, 3, 3))
    Xa = np.concatenate([(st.K_a @ st.R[:, :, 2:3]), I3], axis=2)  # K_a R_i e_z, I
    ba = _gls(Xa, a.mu, a.n, np.linalg.inv(st.Sigma_a))
    g_z, b_a = ba[0], ba[1:]
    Xm = np.concatenate([st.K_m @ st.R[:, :, 0:1], st.K_m @ st.R[:, :, 2:3], I3], axis=2)
    bm = _gls(Xm, m.mu, m.n, np.linalg.inv(st.Sigma_m))
    h_x, h_z, b_m = bm[0], bm[1], bm[2:]
    return replace(st, K_a=-g_z * st.K_a, b_a=b_a, K_m=h_x * st.K_m, b_m=b_m, h_z=float(h_z / h_x))


# --- step 3: gains (GLS) -------------------------------------------------------------------

_UPPER = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def gain_step(st: State, a: IntervalStats, m: IntervalStats) -> State:
    """GLS for K_a (upper triangular, 6 entries) and K_m (full) (Sec. VII-C)."""
    va = st.R @ G_UNIT  # (N, 3) = R_i g
    N = len(va)
    G = np.zeros((N, 3, 6))
    for k, (r, c) in enumerate(_UPPER):
        G[:, r, k] = va[:, c]
    kvec = _gls(G, a.mu - st.b_a, a.n, np.linalg.inv(st.Sigma_a))
    K_a = np.zeros((3, 3))
    for k, (r, c) in enumerate(_UPPER):
        K_a[r, c] = kvec[k]
    # K_m full: with one W for all intervals the GLS reduces to weighted least squares,
    # K_m = (sum n_i y_i v_i^T)(sum n_i v_i v_i^T)^-1.
    vm = st.R @ st.h
    y = m.mu - st.b_m
    Cyv = np.einsum("ni,nj,n->ij", y, vm, m.n)
    Cvv = np.einsum("ni,nj,n->ij", vm, vm, m.n)
    K_m = np.linalg.solve(Cvv.T, Cyv.T).T
    return replace(st, K_a=K_a, K_m=K_m)


# --- step 4: covariances -------------------------------------------------------------------

def covariance_step(st: State, a: IntervalStats, m: IntervalStats, diagonal: bool) -> State:
    """Eq. ``covariance_estimation`` (no Bessel correction), full or diagonal."""
    ra, rm = residual_means(st, a, m)
    out = []
    for r, stats in ((ra, a), (rm, m)):
        S = (stats.scatter + np.einsum("ni,nj,n->ij", r, r, stats.n)) / stats.total
        S = 0.5 * (S + S.T)
        if diagonal:
            S = np.diag(np.diag(S))
        floor = (1e-12 * stats.scale) ** 2
        w, V = np.linalg.eigh(S)
        out.append((V * np.maximum(w, floor)) @ V.T)
    return replace(st, Sigma_a=out[0], Sigma_m=out[1])
