"""core.stats.chi2_sf (no scipy.stats at import) and the numpy neighbour test of holdout_folds."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.stats import chi2

from mavcal.core.accel_fit import holdout_folds
from mavcal.core.stats import chi2_sf
from mavcal.testing.numbers import assert_close, numbers_close

DOFS = [1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 15, 20, 21, 22, 50, 99, 100, 101, 1000, 2769, 10000, 123457, 1e6]


@pytest.mark.parametrize("k", DOFS)
def test_chi2_sf_matches_scipy(k):
    xs = np.concatenate([k * np.linspace(0.01, 3.0, 120), k + np.sqrt(2 * k) * np.linspace(-8, 40, 120),
                         [1e-300, 1e-10, 1e-3, 0.5, 1.0, 2.0, 10.0, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8]])
    for x in xs[xs > 0]:
        ref = float(chi2.sf(x, k))
        got = chi2_sf(x, k)
        if ref > 1e-20:
            assert got == pytest.approx(ref, rel=1e-12), (k, x)
        elif ref > 1e-300:
            assert got == pytest.approx(ref, rel=2e-11), (k, x)  # the exponent's rounding: |ln p| * 1e-14
        else:
            assert 0.0 <= got < 1e-290, (k, x)


def test_chi2_sf_edges_and_printed_digits():
    assert chi2_sf(0.0, 3) == 1.0 and chi2_sf(-1.0, 3) == 1.0
    assert chi2_sf(np.inf, 3) == 0.0 and chi2_sf(1e8, 5) == 0.0
    assert np.isnan(chi2_sf(np.nan, 3))
    rng = np.random.default_rng(0)
    for _ in range(2000):  # the Wald p-values: scipy's to 1e-9 relative (printed with 3 digits)
        k = int(rng.integers(1, 10))
        W = float(rng.gamma(1.0, 3.0 * k))
        assert numbers_close(chi2_sf(W, k), chi2.sf(W, k), rtol=1e-9, atol=0.0), (W, k)


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


@pytest.mark.parametrize("d1", [1, 2, 3, 8, 23, 41, 128, 1000, 60000])
def test_f_sf_matches_scipy(d1):
    from scipy.stats import f as f_dist

    from mavcal.core.stats import f_sf
    for d2 in (3, 10, 50, 298, 4000, 1e5, 1e6, 1e7):
        for x in np.concatenate([np.linspace(0.02, 3.0, 25), np.linspace(1.0, 60.0, 40)]):
            ref = float(f_dist.sf(x, d1, d2))
            if ref > 1e-250:
                assert f_sf(x, d1, d2) == pytest.approx(ref, rel=1e-8 if d2 <= 1e5 else 1e-6), (x, d2)
    assert f_sf(0.0, d1, 10) == 1.0 and f_sf(np.inf, d1, 10) == 0.0 and np.isnan(f_sf(np.nan, d1, 10))
