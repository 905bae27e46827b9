"""The discrete gauge symmetries of the model and the canonical representative.

Besides the continuous gauge fixed by the paper (g_z = -1, h_x = 1, K_a upper triangular),
two discrete symmetries leave every predicted reading unchanged:

* a reflection of the inertial y axis, P = diag(1, -1, 1): K_a -> K_a P, K_m -> K_m P,
  R_i -> P R_i P (P fixes g and h);
* the *mirror twin*: K_m -> -K_m, h_z -> -h_z, R_i -> R_i Rz(180 deg). Since
  Rz(180) [1, 0, -h_z] = -[1, 0, h_z], the magnetometer readings are identical. So still
  poses alone cannot tell a mirrored magnetometer (det K_m < 0) from a normal one seeing
  a field of the opposite dip. mavcal reports the twin with det K_m > 0; the ArduPilot
  stage compares the dip with the World Magnetic Model to detect a mirrored compass.

Not symmetries, but the discrete *branches* a local search cannot cross: the still poses fix
the magnetometer frame relative to the field only through a sign ambiguity of the initial
estimate (the ellipsoid fit gives K_m up to an orthogonal factor, the R/h_z search picks one
of several near-equal minima when the data are few or ill-spread). :func:`branches` lists
the alternatives K_m D, h_z -> +-h_z for the diagonal sign matrices D, modulo the mirror twin
((D, h_z) ~ (-D, -h_z)): 7 starts besides the point itself.

The canonical representative has K_a[1, 1] > 0 (and K_a[0, 0], K_a[2, 2] > 0 follow from
the Cholesky start) and det K_m > 0.
"""
from __future__ import annotations

import numpy as np

RZ180 = np.diag([-1.0, -1.0, 1.0])
PY = np.diag([1.0, -1.0, 1.0])
PX = np.diag([-1.0, 1.0, 1.0])
_BRANCH_D = (("", np.eye(3)), ("Rz(180)", RZ180), ("Px", PX), ("Py", PY))


def mirror_twin(K_m: np.ndarray, h_z: float, R: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The other member of the mirror-twin pair (see module docstring)."""
    return -np.asarray(K_m), -float(h_z), np.asarray(R) @ RZ180


def canonical(K_a, K_m, h_z, R, extra_gains=()):
    """Canonical representative: K_a[1, 1] > 0 and det K_m > 0.

    ``extra_gains`` (other sensors' gains in a multi-sensor fit, as (kind, K) pairs) are
    transformed along. Returns (K_a, K_m, h_z, R, extra_gains).
    """
    K_a, K_m, R = np.asarray(K_a), np.asarray(K_m), np.asarray(R)
    extra = [(k, np.asarray(K)) for k, K in extra_gains]
    if K_a[1, 1] < 0:
        K_a, K_m, R = K_a @ PY, K_m @ PY, PY @ R @ PY
        extra = [(k, K @ PY) for k, K in extra]
    if np.linalg.det(K_m) < 0:
        K_m, h_z, R = -K_m, -h_z, R @ RZ180
        extra = [(k, -K if k == "mag" else K) for k, K in extra]
    return K_a, K_m, float(h_z), R, tuple(extra)


def branches(K_m: np.ndarray, h_z: float) -> tuple[tuple[str, np.ndarray, float], ...]:
    """The 7 discrete alternatives (label, K_m D, +-h_z) to (K_m, h_z); see the module docstring."""
    out = []
    for label, D in _BRANCH_D:
        for sign in (1.0, -1.0):
            if label or sign < 0:
                name = " ".join(x for x in (f"K_m {label}" if label else "", "-h_z" if sign < 0 else "") if x)
                out.append((name, np.asarray(K_m) @ D, sign * float(h_z)))
    return tuple(out)
