"""Issue 11, the stages around the joint fit on long logs: the interval statistics, the
interval means, the held-out checks' statistics and the uncertainty draws computed with less
work, equal to what they gave before (the reference forms are spelled out here) within a
refactor's tolerance, 1e-9 relative (issue 23: not bit for bit, which depends on the BLAS
kernel and the CPU; mavcal.testing.numbers.assert_close)."""
from __future__ import annotations

import numpy as np
import pytest

from mavcal.core import calibrate as C
from mavcal.core.accel_fit import HOLDOUT_POOL_MAX, holdout_accel_mps2
from mavcal.core.reconstruct import estimate_orientations, orientations_from_means
from mavcal.core.stats import interval_means, interval_stats, stats_subset
from mavcal.errors import EstimationError
from mavcal.judging.quality import holdout_errors
from mavcal.sim.paper import simulate
from mavcal.testing.numbers import assert_close


def _reference_moments(sets):
    """interval_stats' sums as they were written before (the straightforward (n, 3) form)."""
    ns = [len(s) for s in sets]
    X = np.concatenate([np.asarray(s, dtype=float) for s in sets])
    n = np.array(ns, dtype=float)
    starts = np.concatenate([[0], np.cumsum(ns)[:-1]])
    center = X.mean(axis=0)
    Xc = X - center
    mu = np.add.reduceat(Xc, starts, axis=0) / n[:, None]
    D = Xc - np.repeat(mu, ns, axis=0)
    each = np.empty((len(ns), 3, 3))
    for k, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        each[:, k, j] = each[:, j, k] = np.add.reduceat(D[:, k] * D[:, j], starts)
    return mu + center, n, D.T @ D, each


def _random_sets(rng, n_sets, max_len, scale, offset, quantum=None):
    sets = [rng.normal(size=(int(rng.integers(2, max_len)), 3)) * scale + rng.normal(size=3) * offset
            for _ in range(n_sets)]
    return [np.round(s / quantum) * quantum for s in sets] if quantum else sets


@pytest.mark.parametrize("seed,n_sets,max_len,scale,offset,quantum", [
    (0, 2, 50, 1.0, 0.0, None), (1, 7, 9, 0.01, 9.8, None), (2, 40, 900, 0.3, 400.0, None),
    (3, 25, 600, 2.0, 300.0, 0.15), (4, 3, 20000, 0.05, 9.8, None),  # past numpy's 8192-element buffer
    (5, 300, 120, 1e-3, 1e4, 1e-3)])
def test_interval_stats_equal_the_straightforward_sums(seed, n_sets, max_len, scale, offset, quantum):
    rng = np.random.default_rng(seed)
    sets = _random_sets(rng, n_sets, max_len, scale, offset, quantum)
    mu, n, scatter, each = _reference_moments(sets)
    for per_interval in (True, False):
        st = interval_stats(sets, "accel_sets", per_interval=per_interval)
        assert_close(st.mu, mu)
        np.testing.assert_array_equal(st.n, n)  # counts
        assert_close(st.scatter, scatter)
        assert st.mu.flags["C_CONTIGUOUS"]  # the layout the fits' BLAS calls had (their rounding)
        if per_interval:
            assert_close(st.interval_scatter, each)
        else:
            assert st.interval_scatter is None
    # and the strided / integer inputs a caller may pass
    assert_close(interval_stats([np.asfortranarray(s) for s in sets], "a").mu, mu)


def test_interval_stats_still_name_the_interval_with_non_finite_readings():
    sets = [np.ones((5, 3)) + np.arange(3) * i for i in range(6)]
    sets[3] = sets[3].copy()
    sets[3][2, 1] = np.nan
    sets[5] = sets[5].copy()
    sets[5][0, 0] = np.inf
    with pytest.raises(EstimationError, match=r"accel_sets\[3\] contains NaN/inf readings \(2 interval"):
        interval_stats(sets, "accel_sets")


def test_interval_means_equal_numpy_mean():
    rng = np.random.default_rng(7)
    sets = _random_sets(rng, 200, 700, 0.5, 50.0)
    assert_close(interval_means(sets), np.array([s.mean(axis=0) for s in sets]))
    f32 = [s.astype(np.float32) for s in sets[:5]]
    assert_close(interval_means(f32), np.array([s.mean(axis=0) for s in f32]), rtol=1e-6)  # float32
    assert interval_means([]).shape == (0, 3)


def test_orientations_from_means_equal_estimate_orientations():
    sim = simulate(12, seed=4, samples=(50, 90))
    cal = C.calibrate(sim.accel_sets, sim.mag_sets, seed=0)
    test = simulate(8, seed=5, samples=(40, 70))
    R = estimate_orientations(cal, test.accel_sets, test.mag_sets)
    na = np.array([len(a) for a in test.accel_sets], dtype=float)
    nm = np.array([len(m) for m in test.mag_sets], dtype=float)
    R2 = orientations_from_means(cal, interval_means(test.accel_sets), na, interval_means(test.mag_sets), nm)
    assert_close(R2, R)
    with pytest.raises(EstimationError):
        orientations_from_means(cal, np.zeros((2, 3)), np.ones(2), np.zeros((3, 3)), np.ones(3))


def test_grid_errors_equal_attitude_errors_batch_after_batch():
    from mavcal.ardupilot import firmware as fw
    from mavcal.autopilot.evaluate import GridErrors, attitude_errors, attitude_grid, body_vectors, max_errors_deg

    rng = np.random.default_rng(11)
    grid = attitude_grid()
    B_ned = np.array([180.0, 10.0, 420.0])
    f_body, B_body = body_vectors(grid, B_ned)
    acal = fw.AccelCal(ofs_mps2=(0.1, -0.05, 0.2), scale=(1.01, 0.99, 1.0))
    ccal = fw.CompassCal(ofs_mgauss=(20.0, -10.0, 5.0), dia=(1.02, 0.98, 1.0), odi=(0.01, 0.0, -0.02))
    evaluate = GridErrors(acal, ccal, B_ned, grid)
    assert len(evaluate.f_unique) == 49 and len(grid) == 1176  # every yaw of 7 x 7 roll/pitch
    D = 5
    for _ in range(3):  # one evaluator, batch after batch
        Ka = [np.eye(3) + 0.02 * rng.normal(size=(3, 3)) for _ in range(D)]
        Km = [np.eye(3) + 0.02 * rng.normal(size=(3, 3)) for _ in range(D)]
        ba, bm = rng.normal(size=(D, 3)) * 0.2, rng.normal(size=(D, 3)) * 30.0
        raw_a = np.array([f_body @ Ka[k].T + ba[k] for k in range(D)])
        raw_m = np.array([B_body @ Km[k].T + bm[k] for k in range(D)])
        h, t = evaluate(raw_a, raw_m)
        h2, t2 = max_errors_deg(raw_a, raw_m, acal, ccal, B_ned, grid)
        raw_u = np.array([evaluate.f_unique @ Ka[k].T + ba[k] for k in range(D)])  # at the distinct forces only
        h3, t3 = evaluate.at_unique(raw_u, raw_m)
        assert_close(h3, h)
        assert_close(t3, t)
        for k in range(D):
            e = attitude_errors(lambda f, K=Ka[k], b=ba[k]: f @ K.T + b,
                                lambda B, K=Km[k], b=bm[k]: B @ K.T + b, acal, ccal, B_ned, grid)
            assert_close([h[k], h2[k], t[k], t2[k]], [e.max_heading_deg, e.max_heading_deg, e.max_tilt_deg,
                                                   e.max_tilt_deg])


def _sim(n: int, seed: int):
    sim = simulate(n, seed=seed, samples=(60, 90))
    return sim.accel_sets, sim.mag_sets


def test_k_fold_holdout_from_the_fit_statistics_equals_the_readings_when_the_pool_is_all():
    """N <= HOLDOUT_POOL_MAX: the refits' statistics taken from the fit's own (per interval) are
    the numbers computed from the readings, so the held-out errors are the same (within 1e-9)."""
    acc, mag = _sim(90, 3)
    cal = C.calibrate(acc, mag, seed=0)
    stats = (interval_stats(acc, "accel_sets", per_interval=True), interval_stats(mag, "mag_sets", per_interval=True))
    assert_close(holdout_errors(acc, mag, cal, stats=stats), holdout_errors(acc, mag, cal))
    assert_close(holdout_accel_mps2(acc, stats=stats[0]), holdout_accel_mps2(acc))


def test_k_fold_holdout_above_the_pool_takes_subsets_of_the_fit_statistics(monkeypatch):
    """N > HOLDOUT_POOL_MAX: no statistics are computed from the readings when the fit's are
    given (O(pool) per refit); the numbers equal those of the pool's own statistics up to
    rounding."""
    acc, mag = _sim(HOLDOUT_POOL_MAX + 30, 5)
    full = interval_stats(acc, "accel_sets", per_interval=True)
    ref = holdout_accel_mps2(acc)
    calls = []
    orig = interval_stats

    def spy(sets, *a, **kw):
        calls.append(len(list(sets)))
        return orig(sets, *a, **kw)

    monkeypatch.setattr("mavcal.core.accel_fit.interval_stats", spy)
    got = holdout_accel_mps2(acc, stats=full)
    assert calls == []
    assert np.isfinite(got) and got == pytest.approx(ref, rel=1e-6)
    sub = stats_subset(full, np.arange(0, len(acc), 3), "accel_sets")
    own = orig([acc[i] for i in range(0, len(acc), 3)], "accel_sets")
    np.testing.assert_allclose(sub.sigma_hat, own.sigma_hat, rtol=1e-10, atol=1e-18)


def _reference_draws(cal, n, rng):
    """sample_parameters as it was written before: one dict per draw, entry by entry."""
    from mavcal.core.models import MODELS
    from mavcal.core.uncertainty import parameter_vector

    theta = parameter_vector(cal)
    C = np.asarray(cal.param_cov)
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    draws = theta + rng.standard_normal((n, len(theta))) @ (V * np.sqrt(np.maximum(w, 0.0))).T
    spec = MODELS[cal.model]
    forms = {"K_a": spec.accel_form, "K_m": spec.mag_form}
    out = []
    for th in draws:
        d = {"K_a": np.array(cal.accel.gain), "b_a": np.array(cal.accel.bias), "K_m": np.array(cal.mag.gain),
             "b_m": np.array(cal.mag.bias), "h": np.array(cal.field)}
        for name, val in zip(cal.param_names, th):
            val = float(val)
            sym, lab = (name.split("[") + [""])[:2]
            lab = lab.rstrip("]")
            if name == "h_z":
                d["h"][2] = val
            elif sym in ("K_a", "K_m") and lab == "s":
                d[sym][:] = val * np.eye(3)
            elif sym in ("K_a", "K_m"):
                r, c = int(lab[0]) - 1, int(lab[1]) - 1
                d[sym][r, c] = val
                if forms[sym] == "sym":
                    d[sym][c, r] = val
            else:
                d[sym]["xyz".index(lab)] = val
        out.append(d)
    return out


@pytest.mark.parametrize("model", ["full", "diag-accel", "ardupilot", "offsets-scales"])
def test_sample_parameters_equal_the_draw_by_draw_assignment(model):
    from mavcal.core.uncertainty import sample_parameters

    sim = simulate(14, seed=2, samples=(50, 80))
    cal = C.calibrate(sim.accel_sets, sim.mag_sets, seed=0, model=model)
    got = sample_parameters(cal, 23, np.random.default_rng(9))
    ref = _reference_draws(cal, 23, np.random.default_rng(9))
    assert len(got) == len(ref) == 23
    for g, r in zip(got, ref):
        assert g.keys() == r.keys()
        for k in r:
            assert_close(g[k], r[k])
    assert sample_parameters(cal, 0, np.random.default_rng(9)) == []


def test_accel_tilt_bounds_equal_the_draw_by_draw_form():
    """The accelerometer's tilt bound from all its draws at once equals the former per-draw
    evaluation (spelled out here), within 1e-9."""
    from mavcal.ardupilot import firmware as fw
    from mavcal.ardupilot.mapping import map_accel
    from mavcal.autopilot.evaluate import attitude_grid
    from mavcal.autopilot.mapping import accel_frame
    from mavcal.core.accel_fit import fit_accel, sample_accel
    from mavcal.core.constants import GRAVITY_MPS2
    from mavcal.judging.quality import accel_tilt_bounds

    sim = simulate(20, seed=6, samples=(50, 80))
    fit = fit_accel(sim.accel_sets)
    am = map_accel(fit.gain, fit.bias, fw.AccelCal(board_orient=2), 0)
    f_body = np.swapaxes(attitude_grid()[::24], 1, 2) @ np.array([0.0, 0.0, -GRAVITY_MPS2])
    board = am.old.board_matrix

    def one(K, b):
        to_E = (board @ accel_frame(K)[2]).T
        a = fw.apply_accel(am.new, (f_body @ to_E.T / GRAVITY_MPS2) @ K.T + b)
        cos_t = np.sum(a * f_body, 1) / (np.linalg.norm(a, axis=1) * GRAVITY_MPS2)
        return float(np.degrees(np.arccos(np.clip(cos_t, -1.0, 1.0))).max())

    ts = [one(K, b) for K, b in sample_accel(fit, 57, np.random.default_rng(4))]
    assert_close(accel_tilt_bounds(fit, am, 57, 4), (float(np.percentile(ts, 95)), one(fit.gain, fit.bias)))
    assert_close(accel_tilt_bounds(fit, am, 0, 4), (one(fit.gain, fit.bias),) * 2)
