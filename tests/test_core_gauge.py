import numpy as np

from mavcal.core.gauge import PY, canonical, mirror_twin
from mavcal.core.rotations import random_rotations


def _predict(K_a, K_m, h_z, R):
    g = np.array([0, 0, -1.0])
    h = np.array([1.0, 0, h_z])
    return (np.einsum("ij,njk,k->ni", K_a, R, g), np.einsum("ij,njk,k->ni", K_m, R, h))


def test_mirror_twin_and_reflection_predict_identical_readings():
    rng = np.random.default_rng(0)
    R = random_rotations(7, rng)
    K_a = np.triu(rng.normal(size=(3, 3))) + 3 * np.eye(3)
    K_m = rng.normal(size=(3, 3))
    a0, m0 = _predict(K_a, K_m, 0.7, R)
    K_m2, h2, R2 = mirror_twin(K_m, 0.7, R)
    a1, m1 = _predict(K_a, K_m2, h2, R2)
    np.testing.assert_allclose(a1, a0, atol=1e-12)
    np.testing.assert_allclose(m1, m0, atol=1e-12)
    assert np.linalg.det(K_m2) == -np.linalg.det(K_m) * 1.0 or np.isclose(np.linalg.det(K_m2), -np.linalg.det(K_m))
    a2, m2 = _predict(K_a @ PY, K_m @ PY, 0.7, PY @ R @ PY)
    np.testing.assert_allclose(a2, a0, atol=1e-12)
    np.testing.assert_allclose(m2, m0, atol=1e-12)


def test_canonical_has_positive_det_and_diagonal():
    rng = np.random.default_rng(1)
    R = random_rotations(5, rng)
    K_a = np.triu(rng.normal(size=(3, 3))) + 3 * np.eye(3)
    K_a[1, 1] = -2.0
    K_m = -np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    a0, m0 = _predict(K_a, K_m, -0.3, R)
    Ka, Km, hz, Rc, _ = canonical(K_a, K_m, -0.3, R)
    assert Ka[1, 1] > 0 and np.linalg.det(Km) > 0
    a1, m1 = _predict(Ka, Km, hz, Rc)
    np.testing.assert_allclose(a1, a0, atol=1e-12)
    np.testing.assert_allclose(m1, m0, atol=1e-12)
    assert np.allclose(np.linalg.det(Rc), 1.0)
