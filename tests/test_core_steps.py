"""Each block step of Sec. VII against a brute-force minimisation of the same cost."""
import numpy as np
import pytest
from scipy.optimize import minimize

from mavcal import sim
from mavcal.core import steps
from mavcal.core.calibrate import initial_state
from mavcal.core.rotations import exp_so3
from mavcal.core.stats import interval_stats


@pytest.fixture(scope="module")
def problem():
    d = sim.simulate(8, seed=21, samples=(30, 40))
    a = interval_stats(d.accel_sets, "a")
    m = interval_stats(d.mag_sets, "m")
    st = initial_state(a, m, np.random.default_rng(0))
    # perturb so that every step has something to do
    rng = np.random.default_rng(1)
    st = steps.State(st.K_a + np.triu(rng.normal(size=(3, 3))) * 0.01, st.b_a + 0.01, st.K_m * 1.01,
                     st.b_m - 0.01, st.h_z + 0.01, st.R @ exp_so3(rng.normal(size=(8, 3)) * 0.01),
                     st.Sigma_a, st.Sigma_m)
    return d, a, m, st


def test_stats_match_the_bessel_formula(problem):
    d, a, m, _ = problem
    mus = np.array([x.mean(0) for x in d.accel_sets])
    S = sum((x - x.mean(0)).T @ (x - x.mean(0)) for x in d.accel_sets)
    np.testing.assert_allclose(a.mu, mus, rtol=1e-12)
    np.testing.assert_allclose(a.sigma_hat, S / (sum(len(x) for x in d.accel_sets) - 8), rtol=1e-9)


def _brute(fun, x0):
    r = minimize(fun, x0, method="BFGS", options={"gtol": 1e-10, "maxiter": 5000})
    return r.x, r.fun


def test_bias_field_step_is_the_gls_minimiser(problem):
    _, a, m, st = problem
    out = steps.bias_field_step(st, a, m)

    def J(x):  # g_z, b_a, h_x, h_z, b_m free, gains fixed
        s2 = steps.State(-x[0] * st.K_a, x[1:4], x[4] * st.K_m, x[6:9], x[5] / x[4], st.R, st.Sigma_a, st.Sigma_m)
        return steps.partial_cost(s2, a, m)

    x0 = np.concatenate([[-1.0], st.b_a, [1.0, st.h_z], st.b_m])
    _, fbest = _brute(J, x0)
    assert steps.partial_cost(out, a, m) == pytest.approx(fbest, rel=1e-6)
    assert steps.partial_cost(out, a, m) <= steps.partial_cost(st, a, m)


def test_gain_step_is_the_gls_minimiser(problem):
    _, a, m, st = problem
    out = steps.gain_step(st, a, m)
    iu = np.triu_indices(3)

    def J(x):
        Ka = np.zeros((3, 3))
        Ka[iu] = x[:6]
        s2 = steps.State(Ka, st.b_a, x[6:].reshape(3, 3), st.b_m, st.h_z, st.R, st.Sigma_a, st.Sigma_m)
        return steps.partial_cost(s2, a, m)

    _, fbest = _brute(J, np.concatenate([st.K_a[iu], st.K_m.ravel()]))
    assert steps.partial_cost(out, a, m) == pytest.approx(fbest, rel=1e-6)
    assert np.allclose(np.tril(out.K_a, -1), 0)


def test_direct_rotation_step_minimises_each_interval(problem):
    _, a, m, st = problem
    out = steps.rotations_direct(st, a, m, iterations=50, tol=1e-16)

    def J(x):
        return steps.partial_cost(steps.State(st.K_a, st.b_a, st.K_m, st.b_m, st.h_z,
                                              st.R @ exp_so3(x.reshape(-1, 3)), st.Sigma_a, st.Sigma_m), a, m)

    _, fbest = _brute(J, np.zeros(3 * len(st.R)))
    assert steps.partial_cost(out, a, m) == pytest.approx(fbest, rel=1e-7)


def test_rotation_approximation_is_exact_without_noise():
    from mavcal.core.initial import approximate_rotations
    from mavcal.core.rotations import random_rotations

    R = random_rotations(20, np.random.default_rng(3))
    g, h = np.array([0, 0, -1.0]), np.array([1.0, 0, 0.6])
    est = approximate_rotations([R @ g, R @ h], [g, h], [1.0, 2.0])
    np.testing.assert_allclose(est, R, atol=1e-12)


def test_covariance_step_matches_the_sample_formula(problem):
    d, a, m, st = problem
    out = steps.covariance_step(st, a, m, diagonal=False)
    pred = (st.K_a @ (st.R @ np.array([0, 0, -1.0]))[..., None])[..., 0] + st.b_a
    res = np.concatenate([x - pred[i] for i, x in enumerate(d.accel_sets)])
    np.testing.assert_allclose(out.Sigma_a, res.T @ res / len(res), rtol=1e-8)
    diag = steps.covariance_step(st, a, m, diagonal=True)
    np.testing.assert_allclose(diag.Sigma_a, np.diag(np.diag(res.T @ res / len(res))), rtol=1e-8)
    # the covariance refit lowers the complete cost
    assert steps.complete_cost(out, a, m) <= steps.complete_cost(st, a, m)


def test_rotation_hz_search_returns_the_proper_twin_of_a_mirrored_magnetometer():
    from mavcal.core.initial import search_rotation_hz
    from mavcal.core.rotations import random_rotations

    rng = np.random.default_rng(9)
    Ri = random_rotations(12, rng)
    Q = -random_rotations(1, rng)[0]  # improper
    h = np.array([0.8, 0, 0.6])
    z_a = Ri @ np.array([0, 0, -1.0])
    z_m = (Q @ Ri @ h)
    R, hz, c = search_rotation_hz(z_a, z_m, np.ones(12), rng)
    # the cost cannot distinguish (Q, h_z) from (-Q, -h_z): the proper member is returned
    assert np.linalg.det(R) > 0 and c < 1e-16
    assert hz == pytest.approx(-0.6, abs=1e-9)
    np.testing.assert_allclose(-R, Q, atol=1e-8)
