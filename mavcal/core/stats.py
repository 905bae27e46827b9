"""Input validation and the sample statistics of the paper's Sec. IV.

For every still interval i the sample mean (Eq. ``mu_hat``) and, over all intervals, the
generalised-Bessel covariance (Eq. ``covariance_initial_estimation``)

    Sigma_hat = sum_i sum_j (v[i,j] - mu_hat[i]) (v[i,j] - mu_hat[i])^T / (sum_i Delta[i] - N).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mavcal.errors import EstimationError


@dataclass(frozen=True, eq=False)
class IntervalStats:
    """Sufficient statistics of one sensor's readings over N still intervals.

    mu : (N, 3) sample means mu_hat[i]
    n : (N,) sample counts Delta[i]
    scatter : (3, 3) within-interval scatter sum_i sum_j (v - mu_hat[i])(v - mu_hat[i])^T
    sigma_hat : (3, 3) Sigma_hat (Bessel-corrected, floored to stay positive definite)
    scale : float, typical magnitude of the readings (for tolerances)
    interval_scatter : (N, 3, 3) each interval's own scatter (``per_interval=True`` only), so
        that :func:`stats_subset` forms the statistics of any subset without the samples
    noise_floor : the floor the covariance was computed with
    """

    mu: np.ndarray
    n: np.ndarray
    scatter: np.ndarray
    sigma_hat: np.ndarray
    scale: float
    interval_scatter: np.ndarray | None = None
    noise_floor: float | None = None

    @property
    def total(self) -> int:
        return int(self.n.sum())


def _item(name: str, i: int) -> str:
    """Interval ``i`` of ``name``: ``accel_sets[3]`` for an argument's name, ``accelerometer 0,
    still interval 3`` for a sensor named in words."""
    return f"{name}[{i}]" if name.isidentifier() else f"{name}, still interval {i}"


def interval_stats(sets: Sequence[np.ndarray], name: str, *, noise_floor: float | None = None,
                   per_interval: bool = False) -> IntervalStats:
    """Validate one sensor's interval readings and compute their statistics.

    Parameters
    ----------
    sets : sequence of N arrays of shape (n_i, 3)
    name : "accel_sets" / "mag_sets", used in error messages
    noise_floor : optional lower bound on the noise standard deviation (e.g. the
        quantisation step / sqrt(12)); by default 1e-9 of the reading scale so that
        noise-free data still give a usable (positive-definite) weighting.
    per_interval : also keep each interval's scatter (for :func:`stats_subset`)
    """
    if isinstance(sets, np.ndarray) and sets.ndim == 3:
        sets = list(sets)
    try:
        seq = list(sets)
    except TypeError:
        raise EstimationError(f"{name} must be a sequence of (n_i, 3) arrays, one per still interval; "
                              f"got {type(sets).__name__}") from None
    if not seq:
        raise EstimationError(f"{name} is empty: pass one (n_i, 3) array of readings per still interval")
    arrays = []
    for i, s in enumerate(seq):
        try:
            a = np.asarray(s, dtype=float)
        except (TypeError, ValueError):
            raise EstimationError(f"{_item(name, i)} is not numeric") from None
        if a.ndim == 1 and a.shape[0] == 3:
            a = a[None, :]
        if a.ndim != 2 or a.shape[1] != 3:
            raise EstimationError(f"{_item(name, i)} must have shape (n_i, 3), got {a.shape}")
        if a.shape[0] < 2:
            raise EstimationError(f"{_item(name, i)} has {a.shape[0]} sample(s); every still interval needs at "
                                  "least 2 samples to estimate the noise (hold each pose longer)")
        arrays.append(a)
    moments = _moments(arrays, per_interval)
    if moments is None:
        bad = [i for i, a in enumerate(arrays) if not np.all(np.isfinite(a))]
        raise EstimationError(f"{_item(name, bad[0])} contains NaN/inf readings ({len(bad)} interval(s) affected); "
                              "drop them before calibrating")
    return _finish_stats(name, *moments, noise_floor)


def interval_means(sets: Sequence[np.ndarray]) -> np.ndarray:
    """(N, 3) the mean reading of each of the N (n_i, 3) arrays ``sets``: ``a.mean(axis=0)``
    to the last bit (the same sequential sum divided by n_i), without ``mean``'s per-call
    overhead (thousands of intervals on long logs)."""
    mus = [np.add.reduce(a, axis=0) / a.shape[0] if a.dtype == np.float64 else a.mean(axis=0) for a in sets]
    return np.array(mus) if mus else np.empty((0, 3))


_PRODUCTS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the distinct entries of a 3x3 scatter


def _moments(arrays: list[np.ndarray], per_interval: bool
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None] | None:
    """Means, counts, pooled scatter and (``per_interval``) each interval's scatter of the
    intervals ``arrays`` ((n_i, 3) each); None when a reading is NaN/inf.

    The arithmetic of the straightforward form (centre = mean of all readings, means by
    ``add.reduceat`` of the centred readings, ``D^T D`` of the deviations ``D`` as an (n, 3)
    array, per-interval products summed by ``add.reduceat``), to the last bit, on a
    coordinate-major copy (3, n): each column contiguous, the sums in place, no full-length
    temporary per step. The centre is the sequential sum of ``mean(axis=0)`` (a running sum
    of each coordinate, ``add.accumulate``); ``reduceat`` sums pairwise whatever the stride.
    """
    ns = np.array([a.shape[0] for a in arrays])
    XT = np.concatenate([a.T for a in arrays], axis=1)  # (3, n), each coordinate contiguous
    total = XT.shape[1]
    run = np.empty(total)
    center = np.array([np.add.accumulate(XT[k], out=run)[-1] for k in range(3)]) / total
    if not np.all(np.isfinite(center)) and not np.all(np.isfinite(XT)):  # finite readings have a finite sum
        return None
    n = ns.astype(float)
    starts = np.concatenate([[0], np.cumsum(ns)[:-1]])
    XT -= center[:, None]
    mu = np.add.reduceat(XT, starts, axis=1).T / n[:, None]
    for k in range(3):
        XT[k] -= np.repeat(mu[:, k], ns)  # the deviations v[i,j] - mu_hat[i]
    # sum_i sum_j (v[i,j] - mu_hat[i]) (v[i,j] - mu_hat[i])^T: D^T D of the deviations D, i.e.
    # XT XT^T (the same BLAS product, bit for bit, without an (n, 3) copy of D)
    scatter = XT @ XT.T
    each = None
    if per_interval:  # each interval's scatter, the 6 distinct products summed interval by interval
        each = np.empty((len(ns), 3, 3))
        for k, j in _PRODUCTS:
            each[:, k, j] = each[:, j, k] = np.add.reduceat(np.multiply(XT[k], XT[j], out=run), starts)
    return np.ascontiguousarray(mu + center), n, scatter, each  # C order, as downstream BLAS calls had it


def _finish_stats(name: str, mu: np.ndarray, n: np.ndarray, scatter: np.ndarray, each: np.ndarray | None,
                  noise_floor: float | None) -> IntervalStats:
    """Scale, the degeneracy checks and the floored Bessel-corrected covariance."""
    N = len(n)
    scale = float(np.median(np.linalg.norm(mu, axis=1)))
    spread = float(np.max(np.linalg.norm(mu - mu.mean(axis=0), axis=1))) if N > 1 else 0.0
    if not np.isfinite(scale) or (scale == 0.0 and spread == 0.0):
        raise EstimationError(f"{name} readings are all zero: the sensor sent no data")
    if spread <= 1e-9 * max(scale, 1e-300):
        raise EstimationError(f"{name}: the mean reading is the same in every interval (constant data); "
                              "the vehicle must be held still in different orientations")
    sigma = scatter / max(n.sum() - N, 1.0)  # generalised Bessel correction
    sigma = 0.5 * (sigma + sigma.T)
    ref = max(scale, spread)
    floor = (1e-9 * ref) if noise_floor is None else max(float(noise_floor), 1e-12 * ref)
    w, V = np.linalg.eigh(sigma)
    w = np.maximum(w, floor ** 2)
    sigma = (V * w) @ V.T
    return IntervalStats(mu=mu, n=n, scatter=scatter, sigma_hat=sigma, scale=ref, interval_scatter=each,
                         noise_floor=noise_floor)


def stats_subset(stats: IntervalStats, idx, name: str = "sets") -> IntervalStats:
    """The statistics of the intervals ``idx`` of ``stats`` (made with ``per_interval=True``):
    what :func:`interval_stats` gives for those intervals' readings (equal up to rounding:
    the scatter is summed interval by interval), in O(len(idx)) without the samples."""
    if stats.interval_scatter is None:
        raise ValueError("stats_subset needs interval_stats(..., per_interval=True)")
    idx = np.asarray(idx)
    each = stats.interval_scatter[idx]
    return _finish_stats(name, stats.mu[idx], stats.n[idx], each.sum(axis=0), each, stats.noise_floor)


# --- the chi-square and F tails: scipy.special's (benchmarks/results/scipy_tails.md) --------
# imported on first use: ``mavcal --help`` and the commands that fit nothing do not load scipy


def chi2_sf(x: float, k: float) -> float:
    """Survival function of the chi-square distribution with ``k`` degrees of freedom at ``x``
    (``scipy.special.chdtrc``); 1 for ``x <= 0``, NaN for ``k <= 0`` or a NaN ``x``."""
    x, k = float(x), float(k)
    if not (k > 0) or math.isnan(x):
        return float("nan")
    if x <= 0.0:
        return 1.0
    from scipy.special import chdtrc

    return float(chdtrc(k, x))


def f_sf(x: float, d1: float, d2: float) -> float:
    """Survival function of the F distribution with (d1, d2) degrees of freedom at ``x``
    (``scipy.special.fdtrc``); 1 for ``x <= 0``, NaN for a degree of freedom <= 0 or a NaN ``x``."""
    x, d1, d2 = float(x), float(d1), float(d2)
    if not (d1 > 0 and d2 > 0) or math.isnan(x):
        return float("nan")
    if x <= 0.0:
        return 1.0
    from scipy.special import fdtrc

    return float(fdtrc(d1, d2, x))
