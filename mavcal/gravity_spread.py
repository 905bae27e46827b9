"""How the still intervals' gravity directions spread over the sphere: how many orientations
(clusters ``cluster_deg`` apart), the smallest eigenvalue of the scatter of unit gravity vectors
(1/3 for a perfect spread, 0 when all lie in a plane), the largest empty spherical cap, and what
the data cannot identify, in words (:func:`diagnose_coverage`); and words for one direction
(:func:`axis_label`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Coverage", "FULL_MODEL_MIN_INTERVALS", "SPHERE", "SPHERE_ROWS", "axis_label", "count_clusters",
           "diagnose_coverage", "largest_empty_cap_deg"]

#: Intervals the full joint model needs (the paper's initial estimate and Wald tests).
FULL_MODEL_MIN_INTERVALS = 8


@dataclass(frozen=True, eq=False)
class Coverage:
    """How well the intervals' gravity directions can identify a calibration.

    Attributes
    ----------
    n_intervals, n_orientations : counts (orientations = gravity clusters).
    scatter_eigenvalues : (3,) ascending eigenvalues of mean(g g^T) over the intervals.
    largest_empty_cap_deg : radius of the largest spherical cap with no gravity direction.
    status : "ok", "reduced" (usable with a reduced model) or "insufficient".
    messages : tuple of str, what is missing, in words.
    """

    n_intervals: int
    n_orientations: int
    scatter_eigenvalues: np.ndarray
    largest_empty_cap_deg: float
    status: str
    messages: tuple[str, ...] = ()

    @property
    def min_eigenvalue(self) -> float:
        return float(self.scatter_eigenvalues[0])


def axis_label(gravity_dir: np.ndarray) -> str:
    """Words for a body-frame gravity direction (FRD): "level", "on its back", "nose down"..."""
    g = np.asarray(gravity_dir, dtype=float)
    k = int(np.argmax(np.abs(g)))
    # gravity points along the body axis that faces the ground: +x down = nose down,
    # +y (right wing) down = on its right side, +z down = level
    names = {(2, 1): "level", (2, -1): "on its back", (0, 1): "nose down", (0, -1): "nose up",
             (1, 1): "on its right side", (1, -1): "on its left side"}
    name = names[(k, int(np.sign(g[k])))]
    tilt = np.degrees(np.arccos(np.clip(abs(g[k]), -1, 1)))
    return name if tilt < 15 else f"{name} (+{tilt:.0f} deg)"


def _fibonacci_sphere(n: int = 2000) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


SPHERE = _fibonacci_sphere()

def count_clusters(g: np.ndarray, cluster_deg: float) -> int:
    """Leader clustering of unit vectors in their order: a vector starts a new cluster when
    no earlier cluster leader is within ``cluster_deg``. The first unassigned vector is
    always a leader, and it claims every later vector within reach, so each pass is one
    vectorised product (passes = clusters, bounded by how many caps fit on the sphere)."""
    cos_c = np.cos(np.radians(cluster_deg))
    free = np.ones(g.shape[0], dtype=bool)
    n = 0
    while True:
        idx = np.flatnonzero(free)
        if idx.size == 0:
            return n
        lead = idx[0]
        n += 1
        free[idx[g[idx] @ g[lead] >= cos_c]] = False
        free[lead] = False


#: grid points per product in :func:`largest_empty_cap_deg`: a (400, 128) block is 400 kB and
#: small enough for BLAS to run it on one thread (no thread start-up on a loaded machine)
SPHERE_ROWS = 400


def largest_empty_cap_deg(g: np.ndarray, chunk: int = 128) -> float:
    """Radius (deg) of the largest spherical cap without any of the unit vectors ``g``
    (over a fixed Fibonacci grid; memory bounded by ``chunk`` vectors and
    :data:`SPHERE_ROWS` grid points at a time: every product is a row of the one with all the
    grid points, the same values)."""
    best = np.full(SPHERE.shape[0], -np.inf)
    for k in range(0, g.shape[0], chunk):
        gk = g[k:k + chunk].T
        for r in range(0, SPHERE.shape[0], SPHERE_ROWS):
            b = best[r:r + SPHERE_ROWS]
            np.maximum(b, np.max(SPHERE[r:r + SPHERE_ROWS] @ gk, axis=1), out=b)
    return float(np.degrees(np.arccos(np.clip(best, -1, 1))).max())


def diagnose_coverage(gravity_dirs: np.ndarray, cluster_deg: float = 20.0) -> Coverage:
    """Coverage of a set of unit gravity directions (one per interval).

    Parameters
    ----------
    gravity_dirs : (N, 3) array, any frame (the measures are rotation invariant).
    cluster_deg : directions closer than this are one orientation.
    """
    g = np.asarray(gravity_dirs, dtype=float).reshape(-1, 3)
    n = g.shape[0]
    msgs: list[str] = []
    if n == 0:
        return Coverage(0, 0, np.zeros(3), 180.0, "insufficient",
                        ("no still intervals were found: the vehicle never stayed still long enough "
                         "(or the thresholds are too strict)",))
    g = g / np.linalg.norm(g, axis=1, keepdims=True)
    n_or = count_clusters(g, cluster_deg)
    ev = np.sort(np.linalg.eigvalsh(g.T @ g / n))
    cap = largest_empty_cap_deg(g)
    if n < FULL_MODEL_MIN_INTERVALS:
        msgs.append(f"{n} still interval{'s' if n != 1 else ''}: the full joint model needs "
                    f">= {FULL_MODEL_MIN_INTERVALS} intervals; with fewer only a reduced model can be fitted")
    if n_or == 1:
        msgs.append("a single orientation: gravity was seen from one direction only, which identifies "
                    "neither accelerometer offsets/scales nor the compass soft iron; hold the vehicle "
                    "in at least 6 different poses (each face down)")
    elif n_or == 2:
        msgs.append("only 2 distinct orientations: offsets and scales cannot be separated; "
                    "add poses with each face down")
    elif ev[0] < 0.02:
        msgs.append("the gravity directions lie in one plane (the vehicle was turned about a single "
                    "axis): the scale and offset along that axis cannot be identified; add poses "
                    "with that axis up and down")
    elif ev[0] < 0.08:
        msgs.append(f"gravity directions are poorly spread (smallest scatter eigenvalue {ev[0]:.3f}, "
                    f"ideal 0.333); add poses that fill the gap")
    if n_or > 1 and cap > 100:
        msgs.append(f"a large part of the sphere of gravity directions is empty (cap of {cap:.0f} deg); "
                    f"results will be poorly constrained there")
    if n_or <= 2 or n < 4:
        status = "insufficient"
    elif n < FULL_MODEL_MIN_INTERVALS or ev[0] < 0.08 or n_or < 6:
        status = "reduced"
    else:
        status = "ok"
    if status == "reduced" and n_or < 6 and n >= FULL_MODEL_MIN_INTERVALS and ev[0] >= 0.08:
        msgs.append(f"only {n_or} distinct orientations (clusters {cluster_deg:.0f} deg apart); "
                    f"at least 6 are recommended")
    return Coverage(n, n_or, ev, cap, status, tuple(msgs))
