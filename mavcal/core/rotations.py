"""Small batched rotation helpers (numpy only, vectorised over a leading axis)."""
from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x for v of shape (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (..., 3) -> rotation matrices (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    th2 = np.einsum("...i,...i->...", w, w)
    small = th2 < 1e-12
    th = np.sqrt(th2)
    any_small = bool(small.any())  # rarely: the series branch is only worked out when needed
    safe = np.where(small, 1.0, th) if any_small else th
    a = np.sin(safe) / safe
    b = (1.0 - np.cos(safe)) / (safe * safe)
    if any_small:
        a = np.where(small, 1.0 - th2 / 6.0, a)
        b = np.where(small, 0.5 - th2 / 24.0, b)
    K = skew(w)
    out = K * a[..., None, None] + (K @ K) * b[..., None, None]
    out[..., 0, 0] += 1.0
    out[..., 1, 1] += 1.0
    out[..., 2, 2] += 1.0
    return out


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternions (..., 4) -> rotation matrices (..., 3, 3)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniformly random rotations (Shoemake's method, as in Kuffner 2004). -> (n, 3, 3)."""
    u1, u2, u3 = rng.random((3, n))
    q = np.stack([
        np.sqrt(u1) * np.cos(2 * np.pi * u3),
        np.sqrt(1 - u1) * np.sin(2 * np.pi * u2),
        np.sqrt(1 - u1) * np.cos(2 * np.pi * u2),
        np.sqrt(u1) * np.sin(2 * np.pi * u3),
    ], -1)
    return quat_to_matrix(q)


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (..., 3, 3) in the Frobenius sense (det +1)."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def angle_between_deg(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Rotation angle of R1^T R2 in degrees (batched)."""
    c = (np.trace(np.swapaxes(R1, -1, -2) @ R2, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
