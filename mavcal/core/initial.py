"""Initial estimate of the paper's Sec. VI (adapted from Kok et al. 2012).

1. Per sensor, an ellipsoid through the interval means: with A symmetric,
   0 ~ mu^T A mu + b^T mu + c (Eq. ``eta_components``); the right singular vector of the
   smallest singular value of J (Eq. ``J_approx``) gives eta = [vec A, b, c] up to scale.
2. The scale alpha = (b^T A^-1 b / 4 - c)^-1, the bias b_s = -A^-1 b / 2, and the gain from
   K^-T K^-1 = alpha A by an (upper-triangular) Cholesky factor ~K_s
   (Eq. ``decomposition_problem``).
3. The accel-to-magnetometer rotation R and h_z from Eq. ``optimize_hz``, solved by
   Levenberg-Marquardt from a closed-form relaxation and, when that is not good enough,
   random restarts (uniformly random rotations, h_z ~ U[-1, 1]); R may be improper (det -1,
   a mirrored magnetometer): the problem cannot distinguish (R, h_z) from (-R, -h_z), so
   both are tried on the full cost. Then h_x = sqrt(1 - h_z^2),
   K_m = ~K_m R h_x, h_z <- h_z / h_x (normalisation g_z = -1, h_x = 1).
4. The orientation of each interval from the eigenvector of the smallest eigenvalue of B_i
   (Eq. ``rotation_approximation``), weighted by w_s = |K_s^T Sigma_s^-1 K_s|^(1/3).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavcal.core.rotations import exp_so3, quat_to_matrix, random_rotations, skew
from mavcal.errors import EstimationError

G_UNIT = np.array([0.0, 0.0, -1.0])
MAX_AXIS_RATIO = 20.0  # longest / shortest ellipsoid axis accepted from the quadric fit (else the sphere)


@dataclass(frozen=True, eq=False)
class Ellipsoid:
    """Result of the per-sensor ellipsoid fit: K (upper triangular) and bias b."""

    K: np.ndarray
    b: np.ndarray
    residual: float  # relative residual of the algebraic fit (smallest / largest singular value)


def _upper_cholesky(P_inv: np.ndarray) -> np.ndarray:
    """Upper-triangular K with K K^T = P_inv (P_inv positive definite)."""
    J = np.eye(3)[::-1]
    L = np.linalg.cholesky(J @ P_inv @ J)
    return J @ L @ J


def _nearest_pd(A: np.ndarray, rel: float = 1e-6) -> np.ndarray:
    A = 0.5 * (A + A.T)
    w, V = np.linalg.eigh(A)
    w = np.maximum(w, rel * max(np.max(np.abs(w)), 1e-300))
    return (V * w) @ V.T


def fit_ellipsoid(mu: np.ndarray, weights: np.ndarray | None = None) -> Ellipsoid:
    """Algebraic ellipsoid fit through the interval means (Sec. VI, Kok 2012).

    With fewer than 9 intervals the general quadric is not determined; then the fit is
    restricted to a sphere-like quadric (A = a I plus the bias), which the later steps refine.
    """
    mu = np.asarray(mu, dtype=float)
    N = mu.shape[0]
    center = mu.mean(axis=0)
    scale = np.sqrt(np.mean(np.sum((mu - center) ** 2, axis=1)))
    if scale <= 0:
        raise EstimationError("all interval means are identical: the orientations do not vary")
    x = (mu - center) / scale  # conditioning; undone below
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
    one = np.ones(N)
    if N >= 9:
        # symmetric A: unique entries a11, a12, a13, a22, a23, a33 (off-diagonals counted twice)
        Jm = np.stack([X * X, 2 * X * Y, 2 * X * Z, Y * Y, 2 * Y * Z, Z * Z, X, Y, Z, one], 1)
    else:
        Jm = np.stack([X * X + Y * Y + Z * Z, X, Y, Z, one], 1)
    if weights is not None:
        Jm = Jm * np.sqrt(np.asarray(weights, dtype=float))[:, None]
    _, sv, Vt = np.linalg.svd(Jm, full_matrices=False)
    eta = Vt[-1]
    if N >= 9:
        a11, a12, a13, a22, a23, a33 = eta[:6]
        A = np.array([[a11, a12, a13], [a12, a22, a23], [a13, a23, a33]])
        bv, c = eta[6:9], eta[9]
    else:
        A = eta[0] * np.eye(3)
        bv, c = eta[1:4], eta[4]
    try:
        Ainv_b = np.linalg.solve(A, bv)
    except np.linalg.LinAlgError:
        raise EstimationError("the interval means do not lie on an ellipsoid (degenerate orientations)") from None
    denom = 0.25 * bv @ Ainv_b - c
    if denom == 0 or not np.isfinite(denom):
        raise EstimationError("degenerate ellipsoid fit: the orientations do not span enough directions")
    alpha = 1.0 / denom
    w = np.linalg.eigvalsh(alpha * A)
    if N >= 9 and (w[0] <= 0 or w[-1] / w[0] > MAX_AXIS_RATIO ** 2):
        # not an ellipsoid (a hyperboloid through noisy points), or one with axes beyond MAX_AXIS_RATIO:
        # the quadric is not determined well enough; fall back to the sphere start
        return fit_sphere(mu)
    P = _nearest_pd(alpha * A)  # = K^-T K^-1 in the conditioned coordinates
    b_x = -0.5 * Ainv_b
    K_x = _upper_cholesky(np.linalg.inv(P))
    K = K_x * scale
    b = center + scale * b_x
    return Ellipsoid(K=K, b=b, residual=float(sv[-1] / sv[0]))


def fit_axis_ellipsoid(mu: np.ndarray) -> Ellipsoid:
    """Ellipsoid with axes along the sensor axes (A diagonal): 7 unknowns, so N >= 7 intervals.

    A second start for few intervals, where the general quadric (N >= 9) is not determined
    and the sphere cannot represent unequal scale factors. Falls back to the sphere when the
    fit is not an ellipsoid.
    """
    mu = np.asarray(mu, dtype=float)
    center = mu.mean(axis=0)
    scale = np.sqrt(np.mean(np.sum((mu - center) ** 2, axis=1)))
    x = (mu - center) / scale
    Jm = np.concatenate([x * x, x, np.ones((len(x), 1))], axis=1)
    _, sv, Vt = np.linalg.svd(Jm, full_matrices=False)
    a, bv, c = Vt[-1][:3], Vt[-1][3:6], Vt[-1][6]
    if np.any(a == 0):
        return fit_sphere(mu)
    cx = -0.5 * bv / a
    alpha = 1.0 / (np.sum(a * cx * cx) - c)
    w = alpha * a
    if not np.all(np.isfinite(w)) or np.min(w) <= 0 or np.max(w) / np.min(w) > MAX_AXIS_RATIO ** 2:
        return fit_sphere(mu)
    return Ellipsoid(K=np.diag(scale / np.sqrt(w)), b=center + scale * cx, residual=float(sv[-1] / sv[0]))


def fit_sphere(mu: np.ndarray) -> Ellipsoid:
    """Sphere through the interval means: K = r I, bias = centre (used by the reduced models)."""
    mu = np.asarray(mu, dtype=float)
    center = mu.mean(axis=0)
    scale = np.sqrt(np.mean(np.sum((mu - center) ** 2, axis=1)))
    x = (mu - center) / scale
    Jm = np.stack([np.sum(x * x, 1), x[:, 0], x[:, 1], x[:, 2], np.ones(len(x))], 1)
    _, sv, Vt = np.linalg.svd(Jm, full_matrices=False)
    a, bv, c = Vt[-1][0], Vt[-1][1:4], Vt[-1][4]
    if a == 0:
        raise EstimationError("degenerate sphere fit: the orientations do not span enough directions")
    cx = -0.5 * bv / a
    r2 = cx @ cx - c / a
    if r2 <= 0:
        r2 = np.mean(np.sum((x - cx) ** 2, 1))
    return Ellipsoid(K=np.sqrt(r2) * scale * np.eye(3), b=center + scale * cx, residual=float(sv[-1] / sv[0]))


def _relaxed_start(z_a: np.ndarray, z_m: np.ndarray, w: np.ndarray):
    """Closed-form start for Eq. ``optimize_hz``: relax R to any matrix M with |M|_F^2 = 3.

    h_z is eliminated (h_z = -sum w z_m^T M z_a / sum w); the smallest eigenvector of the
    remaining 9x9 quadratic form gives M up to sign; each sign is projected onto O(3).
    Exact for noise-free data with >= 9 well-spread intervals; otherwise just a start.
    """
    X = np.einsum("ni,nj->nij", z_m, z_a).reshape(len(w), 9)  # z_m^T M z_a = X . vec(M)
    xbar = (w @ X) / w.sum()
    D = (X - xbar) * np.sqrt(w)[:, None]
    _, V = np.linalg.eigh(D.T @ D)
    M = V[:, 0].reshape(3, 3)
    out = []
    for s in (1.0, -1.0):
        U, _, Vt = np.linalg.svd(s * M)
        out.append(U @ Vt)  # nearest orthogonal matrix (proper or improper)
    return np.array(out)


def _lm_rotation_hz(R, hz, z_a, z_m, w, iterations):
    """Batched Levenberg-Marquardt for Eq. ``optimize_hz`` from starts R (B, 3, 3), hz (B,)."""
    B = len(hz)
    sw = np.sqrt(w)
    za = z_a * sw[:, None]  # fold sqrt(w) into z_a (the residual is linear in z_a)
    lam = np.full(B, 1e-3)
    eye4 = np.eye(4)

    def cost(R, hz):
        r = sw[None] * hz[:, None] + np.einsum("nj,bjk,nk->bn", z_m, R, za, optimize=False)
        return r, np.einsum("bn,bn->b", r, r)

    r, c = cost(R, hz)
    ones = np.broadcast_to(sw[None, :, None], (B, len(sw), 1))
    for _ in range(iterations):
        u = z_m @ R  # (B, N, 3) = (R^T z_m)^T per start
        Jm = np.concatenate([np.cross(za[None], u), ones], axis=2)  # d r / d (delta, h_z)
        H = np.swapaxes(Jm, 1, 2) @ Jm
        gvec = (np.swapaxes(Jm, 1, 2) @ r[..., None])[..., 0]
        H = H + lam[:, None, None] * (eye4 * (1.0 + np.einsum("bii->bi", H)[:, :, None]))
        step = -np.linalg.solve(H, gvec[..., None])[..., 0]
        R_new = R @ exp_so3(step[:, :3])
        hz_new = hz + step[:, 3]
        r_new, c_new = cost(R_new, hz_new)
        ok = c_new < c
        dec = np.where(ok, c - c_new, 0.0)
        R = np.where(ok[:, None, None], R_new, R)
        hz = np.where(ok, hz_new, hz)
        r = np.where(ok[:, None], r_new, r)
        c = np.where(ok, c_new, c)
        lam = np.where(ok, lam * 0.1, lam * 10.0)
        if np.all(dec <= 1e-10 * (c + 1e-300)) and np.all(ok | (lam > 1e4)):
            break
    return R, hz, c


def search_rotation_hz(z_a: np.ndarray, z_m: np.ndarray, w: np.ndarray, rng: np.random.Generator,
                       restarts: int = 24, iterations: int = 30, accept_rms: float = 0.01):
    """Solve Eq. ``optimize_hz``: min_{R, h_z} 1/2 sum_i w_i (h_z + z_a[i]^T R^T z_m[i])^2.

    Levenberg-Marquardt from the two signs of a closed-form relaxation
    (:func:`_relaxed_start`). When that does not reach a residual consistent with noise
    (weighted RMS of h_z + z_a^T R^T z_m above ``accept_rms``), the paper's random restarts
    follow: ``restarts`` uniformly random rotations with h_z ~ U[-1, 1], vectorised.

    The cost is symmetric under (R, h_z) -> (-R, -h_z): every solution has an improper twin
    of equal cost (a mirrored magnetometer seeing the field with the opposite dip). This
    problem cannot tell them apart; the caller must compare both on the full cost
    (see :func:`mavcal.core.calibrate.initial_state`). Returns the proper (det R = +1)
    member (R, h_z, cost).
    """
    R0 = _relaxed_start(z_a, z_m, w)
    R0 = R0 * np.sign(np.linalg.det(R0))[:, None, None]
    hz0 = -np.einsum("nj,bjk,nk,n->b", z_m, R0, z_a, w) / w.sum()
    R, hz, c = _lm_rotation_hz(R0, hz0, z_a, z_m, w, iterations)
    k = int(np.argmin(c))
    if np.sqrt(c[k] / w.sum()) <= accept_rms or restarts <= 0:
        return R[k], float(hz[k]), float(c[k])
    Rr = random_rotations(restarts, rng)
    hzr = rng.uniform(-1.0, 1.0, restarts)
    Rr, hzr, cr = _lm_rotation_hz(Rr, hzr, z_a, z_m, w, iterations)
    R, hz, c = np.concatenate([R, Rr]), np.concatenate([hz, hzr]), np.concatenate([c, cr])
    k = int(np.argmin(c))
    return R[k], float(hz[k]), float(c[k])


def rotation_hz_minima(z_a: np.ndarray, z_m: np.ndarray, w: np.ndarray, rng: np.random.Generator,
                       restarts: int = 24, iterations: int = 30, limit: int = 3):
    """The distinct local minima of Eq. ``optimize_hz``, lowest first (at most ``limit``).

    The relaxed start and ``restarts`` random starts, each taken to its minimum; members of a
    (R, h_z) / (-R, -h_z) pair are merged (reported proper, det R = +1), and minima with the
    same h_z (to 1e-3) and R (to 1e-2) are one. With few or ill-spread intervals the lowest is
    not always the basin of the global optimum of the full cost; the others are the
    alternatives the caller's search tries. Returns a list of (R, h_z, cost).
    """
    R0 = _relaxed_start(z_a, z_m, w)
    R0 = R0 * np.sign(np.linalg.det(R0))[:, None, None]
    hz0 = -np.einsum("nj,bjk,nk,n->b", z_m, R0, z_a, w) / w.sum()
    Rs = np.concatenate([R0, random_rotations(restarts, rng)])
    hzs = np.concatenate([hz0, rng.uniform(-1.0, 1.0, restarts)])
    R, hz, c = _lm_rotation_hz(Rs, hzs, z_a, z_m, w, iterations)
    sign = np.sign(np.linalg.det(R))
    R, hz = R * sign[:, None, None], hz * sign
    out: list = []
    for k in np.argsort(c):
        if any(abs(hz[k] - h) < 1e-3 and np.abs(R[k] - Rk).max() < 1e-2 for Rk, h, _ in out):
            continue
        out.append((R[k], float(hz[k]), float(c[k])))
        if len(out) >= limit:
            break
    return out


def _f(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """f(x, y) of Eq. ``rotation_approximation`` for batches (..., 3) -> (..., 4, 4)."""
    z = np.zeros(x.shape[:-1])
    x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
    y1, y2, y3 = y[..., 0], y[..., 1], y[..., 2]
    return np.stack([
        np.stack([z, -y1, -y2, -y3], -1),
        np.stack([y1, z, -x3, x2], -1),
        np.stack([y2, x3, z, -x1], -1),
        np.stack([y3, -x2, x1, z], -1),
    ], -2)


def approximate_rotations(s_star: list, s_ref: list, weights: list) -> np.ndarray:
    """Orientations from the eigenvector of the minimum eigenvalue of B_i (Eq. ``rotation_approximation``).

    s_star : list over sensors of (N, 3) nominal values K_s^-1 (mu_s[i] - b_s)
    s_ref : list over sensors of (3,) inertial fields (g or h)
    weights : list of w_s

    The quaternion q = [w, x, y, z] solving f(s* + s^I, s* - s^I) q = 0 is the rotation
    with s* = R(q) s^I; for noisy data the least-squares q is the eigenvector of
    B_i = sum_s w_s A_s^T A_s with the smallest eigenvalue. Returns (N, 3, 3).
    """
    Bm = 0.0
    for ss, ref, w in zip(s_star, s_ref, weights):
        A = _f(ss + ref, ss - ref)
        Bm = Bm + w * np.einsum("nki,nkj->nij", A, A)
    _, V = np.linalg.eigh(Bm)
    q = V[:, :, 0]
    return quat_to_matrix(q)


def sensor_weight(K: np.ndarray, Sigma: np.ndarray) -> float:
    """w_s = |K_s^T Sigma_s^-1 K_s|^(1/3) (Eq. ``rotation_approximation``)."""
    return float(abs(np.linalg.det(K.T @ np.linalg.solve(Sigma, K))) ** (1.0 / 3.0))


__all__ = ["fit_ellipsoid", "fit_axis_ellipsoid", "fit_sphere", "search_rotation_hz", "rotation_hz_minima",
           "approximate_rotations",
           "sensor_weight", "G_UNIT", "Ellipsoid", "skew"]
