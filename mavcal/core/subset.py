"""A deterministic, orientation-diverse subset of still intervals (the large-N search).

:func:`mavcal.core.calibrate.calibrate` looks for the basin of the global optimum on at most
:data:`mavcal.core.calibrate.SUBSET_N` intervals when a log has hundreds to thousands of
them, then refines on all of them. What the search needs from the subset is every distinct
pose the log holds (the orientations identify the ellipsoids and the accel-to-magnetometer
rotation), then a fair share of the whole log: so first farthest-point sampling on the
gravity and field directions, then intervals evenly spaced in the log; and its cost must
have the shape of the cost of all N, so each chosen interval carries the counts of the
intervals nearest to it (:func:`subset_weights`): a pose held for half the log weighs half.
"""
from __future__ import annotations

import numpy as np

from mavcal.core.initial import fit_sphere
from mavcal.errors import EstimationError

__all__ = ["diverse_subset", "subset_weights", "DIVERSE_SHARE", "SAME_POSE"]

DIVERSE_SHARE = 0.5  # at most this share of the subset is chosen for diversity, the rest evenly spaced
SAME_POSE = 0.05  # farthest-point sampling stops when every interval is this close (in direction) to a chosen one


def _directions(mu: np.ndarray) -> np.ndarray:
    """Unit directions of the readings about the centre of their sphere fit (the bias of a
    magnetometer can be as large as the field, so the raw means would not do)."""
    try:
        centre = fit_sphere(mu).b
    except (EstimationError, np.linalg.LinAlgError):
        centre = mu.mean(axis=0)
    d = mu - centre
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(n > 0, n, 1.0)


def _features(mu_a: np.ndarray, mu_m: np.ndarray) -> np.ndarray:
    return np.hstack([_directions(np.asarray(mu_a, float)), _directions(np.asarray(mu_m, float))])


def subset_weights(mu_a: np.ndarray, mu_m: np.ndarray, n: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Sample counts for the subset ``idx`` that make it weigh the poses as the whole log does
    (a coreset): every interval's count goes to the nearest chosen interval in gravity and
    field direction (each chosen one keeps its own), then the counts are scaled to the
    subset's own total, so its chi2 keeps the subset's statistics while its cost has the
    shape of the cost of all N (where some poses are held far longer than others)."""
    X = _features(mu_a, mu_m)
    n = np.asarray(n, float)
    owner = np.empty(len(n), dtype=int)
    for c0 in range(0, len(n), 4096):  # nearest chosen interval, in blocks (bounded memory)
        Xb = X[c0:c0 + 4096]
        owner[c0:c0 + len(Xb)] = np.argmin(((Xb[:, None, :] - X[idx][None]) ** 2).sum(-1), axis=1)
    owner[idx] = np.arange(len(idx))
    w = np.bincount(owner, weights=n, minlength=len(idx))
    return w * (n[idx].sum() / w.sum())


def diverse_subset(mu_a: np.ndarray, mu_m: np.ndarray, k: int) -> np.ndarray:
    """Sorted indices of at most ``k`` of the N intervals whose sample means are ``mu_a``,
    ``mu_m`` (N, 3): farthest-point sampling on the concatenated unit gravity and field
    directions (from interval 0; up to ``DIVERSE_SHARE * k`` intervals, fewer when every
    interval is within ``SAME_POSE`` of a chosen one), then the rest of the ``k`` evenly
    spaced in the log among those not chosen. All N when N <= k. Deterministic."""
    N = len(mu_a)
    if N <= k:
        return np.arange(N)
    X = _features(mu_a, mu_m)
    chosen = [0]
    dist = np.linalg.norm(X - X[0], axis=1)
    for _ in range(int(DIVERSE_SHARE * k) - 1):
        j = int(np.argmax(dist))
        if dist[j] <= SAME_POSE:
            break
        chosen.append(j)
        dist = np.minimum(dist, np.linalg.norm(X - X[j], axis=1))
    rest = np.setdiff1d(np.arange(N), chosen)
    spread = rest[np.unique(np.round(np.linspace(0, len(rest) - 1, k - len(chosen))).astype(int))]
    return np.sort(np.concatenate([np.array(chosen, dtype=int), spread]))
