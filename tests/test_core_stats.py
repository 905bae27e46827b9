"""core.stats: the chi-square/F tails (scipy.special's), the interval statistics and the numpy
neighbour test of holdout_folds."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.stats import chi2

from mavcal.core.accel_fit import holdout_folds
from mavcal.core.stats import chi2_sf
from mavcal.testing.numbers import assert_close, numbers_close


def test_tails_are_scipys_with_their_edges():
    """chi2_sf / f_sf are scipy.special's chdtrc / fdtrc (the argument order checked against
    scipy.stats), with the conventions the callers rely on: 1 at x <= 0, NaN without degrees of
    freedom or for a NaN statistic, 0 at infinity."""
    from scipy.stats import f as f_dist

    from mavcal.core.stats import f_sf

    rng = np.random.default_rng(0)
    for _ in range(200):
        k, d2 = int(rng.integers(1, 30)), float(rng.integers(3, 10**6))
        x = float(rng.gamma(1.0, 3.0 * k))
        assert numbers_close(chi2_sf(x, k), chi2.sf(x, k), rtol=1e-12, atol=0.0), (x, k)
        assert numbers_close(f_sf(x / k, k, d2), f_dist.sf(x / k, k, d2), rtol=1e-12, atol=0.0), (x, k, d2)
    for sf in (lambda x: chi2_sf(x, 3), lambda x: f_sf(x, 3, 10)):
        assert sf(0.0) == 1.0 and sf(-1.0) == 1.0 and sf(np.inf) == 0.0 and np.isnan(sf(np.nan))
    assert np.isnan(chi2_sf(1.0, 0)) and np.isnan(chi2_sf(1.0, -1)) and np.isnan(f_sf(1.0, 0, 10))
    assert chi2_sf(1e8, 5) == 0.0


def test_holdout_folds_neighbour_test_matches_kdtree():
    rng = np.random.default_rng(4)
    for n in (61, 150, 700):
        d = rng.normal(size=(n, 3)) * np.array([1.0, 1.0, 0.2])  # clustered: some lone directions
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        chord = 2.0 * np.sin(np.radians(30.0) / 2.0)
        pool = np.unique(np.round(np.linspace(0, n - 1, min(n, 300))).astype(int))
        expected = []
        for f in range(10):  # the former implementation: a k-d tree of the kept directions
            held = np.zeros(len(pool), dtype=bool)
            held[f::10] = True
            dist, _ = cKDTree(d[pool[~held]]).query(d[pool[held]], k=1, distance_upper_bound=chord)
            if np.isfinite(dist).any():
                expected.append((pool[~held].tolist(), pool[held][np.isfinite(dist)].tolist()))
        got = [(fit.tolist(), pred.tolist()) for fit, pred in holdout_folds(d)]
        assert got == expected
        assert sum(len(p) for _, p in expected) < len(pool)  # some lone directions are not predicted


def test_stats_subset_equals_the_statistics_of_the_subset():
    from mavcal.core.stats import interval_stats, stats_subset

    rng = np.random.default_rng(2)
    sets = [rng.normal(size=(int(rng.integers(3, 40)), 3)) * 0.01 + rng.normal(size=3) * 9.8 for _ in range(50)]
    full = interval_stats(sets, "accel_sets", per_interval=True, noise_floor=1e-4)
    plain = interval_stats(sets, "accel_sets", noise_floor=1e-4)
    for name in ("mu", "n", "scatter", "sigma_hat"):  # per_interval changes nothing else
        np.testing.assert_array_equal(getattr(full, name), getattr(plain, name))
    np.testing.assert_allclose(full.interval_scatter.sum(axis=0), full.scatter, rtol=1e-12, atol=1e-18)
    keep = [i for i in range(50) if i % 7]
    sub = stats_subset(full, keep, "accel_sets")
    ref = interval_stats([sets[i] for i in keep], "accel_sets", noise_floor=1e-4)
    np.testing.assert_allclose(sub.mu, ref.mu, rtol=1e-13)
    np.testing.assert_array_equal(sub.n, ref.n)
    np.testing.assert_allclose(sub.scatter, ref.scatter, rtol=1e-10, atol=1e-16)
    np.testing.assert_allclose(sub.sigma_hat, ref.sigma_hat, rtol=1e-10, atol=1e-16)
    assert sub.scale == pytest.approx(ref.scale, rel=1e-13)
    with pytest.raises(ValueError):
        stats_subset(plain, keep)


def test_pooled_scatter_is_the_deviations_product():
    """interval_stats' pooled scatter (XT XT^T of the (3, n) deviations, no (n, 3) copy) is the
    D^T D of the straightforward form, for intervals of any length (within 1e-9: two BLAS
    calls may sum in different orders on other kernels)."""
    from mavcal.core.stats import interval_stats

    rng = np.random.default_rng(5)
    for sizes in ([2, 3], [50] * 7, [1000, 20000, 3, 777]):
        sets = [rng.normal(loc=rng.uniform(-500, 500, 3), scale=rng.uniform(0.01, 30), size=(n, 3)) for n in sizes]
        st = interval_stats(sets, "sets")
        X = np.concatenate(sets)
        center = np.add.accumulate(X, axis=0)[-1] / len(X)  # the sequential sum, as mean(axis=0)
        mu = np.array([np.add.reduceat((X - center).T, np.cumsum([0] + sizes[:-1]), axis=1).T[k] / n
                       for k, n in enumerate(sizes)])
        D = np.concatenate([s - center - m for s, m in zip(sets, mu)])
        assert_close(st.scatter, D.T @ D)
