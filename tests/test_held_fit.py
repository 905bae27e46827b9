"""The fit of what poses within reach identify (:mod:`mavcal.core.held`): the exact ML optimum
of its own cost, certified, with the held parameters' uncertainty counted in the covariance."""
import numpy as np
import pytest
from scipy.optimize import least_squares

from mavcal.core.held import HeldProblem, calibrate_held
from mavcal.core.misfit import joint_terms
from mavcal.core.models import MODELS
from mavcal.core.refine import JointParams, JointProblem
from mavcal.core.rotations import exp_so3
from mavcal.core.stats import interval_stats

HELD_ACCEL = ["K_a[11]", "K_a[22]", "K_a[33]", "b_a[x]", "b_a[y]", "b_a[z]"]
PRIOR = {"K_a[11]": 0.098, "K_a[22]": 0.098, "K_a[33]": 0.098, "b_a[x]": 0.1, "b_a[y]": 0.1, "b_a[z]": 0.1,
         "h_z": 0.02}


def _rotz(p):
    c, s = np.cos(p), np.sin(p)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _small_tilts(seed: int, n: int = 12, tilt_deg: float = 15.0, headings: int | None = None):
    """Still intervals of a vehicle turned to n headings and tilted up to ``tilt_deg`` (the
    ardupilot model: diagonal K_a, symmetric K_m), 100 samples each."""
    rng = np.random.default_rng(seed)
    K_a = np.diag(9.81 * (1.0 + rng.normal(0.0, 0.01, 3)))
    b_a = rng.normal(0.0, 0.1, 3)
    E = rng.normal(0.0, 0.03, (3, 3))
    K_m = 300.0 * (np.eye(3) + 0.5 * (E + E.T))
    b_m = rng.normal(0.0, 60.0, 3)
    h_z = np.tan(np.radians(60.0))
    R = []
    for i in range(n):
        ax = rng.normal(size=3)
        ax[2] = 0.0
        ax /= np.linalg.norm(ax)
        k = headings or n
        tilt = exp_so3((np.radians(tilt_deg) * rng.uniform(0.3, 1.0) * ax)[None])[0]
        R.append(tilt @ _rotz(2 * np.pi * (i % k) / k))
    R = np.array(R)
    g, h = np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, h_z])
    acc = [K_a @ (Ri @ g) + b_a + rng.normal(0.0, 0.02, (100, 3)) for Ri in R]
    mag = [K_m @ (Ri @ h) + b_m + rng.normal(0.0, 2.0, (100, 3)) for Ri in R]
    return (interval_stats(acc, "a", per_interval=True), interval_stats(mag, "m", per_interval=True),
            (K_a, b_a, K_m, b_m, h_z, R))


@pytest.mark.parametrize("seed,hold_hz", [(1, True), (2, False), (3, True)])
def test_held_fit_is_the_ml_optimum_of_its_cost(seed, hold_hz):
    """scipy's least_squares from the truth, over the free parameters and the orientations
    alone, reaches the optimum calibrate_held returns (cost and parameters)."""
    a, m, (K_a, b_a, K_m, b_m, h_z, R0) = _small_tilts(seed)
    held = HELD_ACCEL + (["h_z"] if hold_hz else [])
    cal = calibrate_held(a, m, K_a, b_a, held=held, prior_sd=PRIOR, h_z=h_z)
    assert cal.converged and cal.certificate is not None and cal.certificate.certified
    terms = joint_terms(MODELS["ardupilot"], a, m, a.sigma_hat, m.sigma_hat)
    full = JointProblem(terms)
    truth = JointParams((K_a, K_m), (b_a, b_m), h_z, R0)
    free = np.array([n not in held for n in full.names])
    prob = HeldProblem(terms, free, full.pack(truth))
    N = len(R0)

    def fun(x):
        return prob.residuals(prob.unpack(x[:prob.P], R0 @ exp_so3(x[prob.P:].reshape(N, 3)))).ravel()

    sol = least_squares(fun, np.concatenate([prob.pack(truth), np.zeros(3 * N)]), xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, method="lm")
    J_scipy = float(np.sum(sol.fun ** 2))
    assert cal.cost == pytest.approx(J_scipy, rel=1e-8)
    np.testing.assert_allclose(cal.mag.gain, prob.unpack(sol.x[:prob.P], R0).gains[1], rtol=0, atol=1e-5)
    np.testing.assert_allclose(cal.mag.bias, prob.unpack(sol.x[:prob.P], R0).biases[1], rtol=0, atol=1e-4)
    # the held values are the given ones, exactly
    np.testing.assert_array_equal(cal.accel.gain, K_a)
    np.testing.assert_array_equal(cal.accel.bias, b_a)
    assert cal.held == tuple(held)
    if hold_hz:
        assert cal.h_z == h_z


def test_held_covariance_counts_the_priors():
    """The held parameters carry their prior variance; the free ones are wider than their
    inverse Fisher information alone (the held errors move them), and the truth lies within
    a few standard deviations of the estimate."""
    a, m, (K_a, b_a, K_m, b_m, h_z, _) = _small_tilts(4)
    held = HELD_ACCEL + ["h_z"]
    cal = calibrate_held(a, m, K_a, b_a, held=held, prior_sd=PRIOR, h_z=h_z)
    sd = dict(zip(cal.param_names, np.sqrt(np.diag(cal.param_cov))))
    for n in held:
        assert sd[n] == pytest.approx(PRIOR[n], rel=1e-12)
    no_prior = calibrate_held(a, m, K_a, b_a, held=held, prior_sd={}, h_z=h_z)
    sd0 = dict(zip(no_prior.param_names, np.sqrt(np.diag(no_prior.param_cov))))
    assert all(sd[n] >= sd0[n] for n in ("b_m[x]", "b_m[y]", "b_m[z]"))
    assert sd["b_m[x]"] > 1.5 * sd0["b_m[x]"]  # a 0.1 m/s^2 accel offset is a 0.6 deg tilt: it moves the offsets
    z = (cal.mag.bias - b_m) / np.array([sd["b_m[x]"], sd["b_m[y]"], sd["b_m[z]"]])
    assert np.all(np.abs(z) < 4.0)
