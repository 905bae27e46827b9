"""ArduPilot rotation enum: conventions, table values, inverse, nearest match."""
import numpy as np
import pytest

from mavcal.autopilot import rotations as rot


def test_yaw_90_maps_x_to_y():
    R = rot.rotation_matrix(2)
    np.testing.assert_allclose(R @ [1.0, 2.0, 3.0], [-2.0, 1.0, 3.0], atol=1e-15)


def test_roll_90_and_pitch_90():
    # roll 90: y -> z ; pitch 90: x -> -z (right-handed rotations about x and y)
    np.testing.assert_allclose(rot.rotation_matrix(16) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(rot.rotation_matrix(24) @ [1, 0, 0], [0, 0, -1], atol=1e-15)


def test_all_matrices_are_proper_rotations():
    for k in range(44):
        R = rot.rotation_matrix(k)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_known_duplicates_and_solo_rotation():
    np.testing.assert_allclose(rot.rotation_matrix(26), rot.rotation_matrix(14), atol=1e-12)
    np.testing.assert_allclose(rot.rotation_matrix(27), rot.rotation_matrix(10), atol=1e-12)
    r, p, y = rot.ROTATIONS[38]
    assert (r, p, y) == (90.0, 68.8, 293.3)
    # ArduPilot hard-codes this matrix (vector3.cpp); its rows, rounded to 4 decimals
    expected = np.array([[0.1430, 0.3688, -0.9184],
                         [-0.3321, -0.8563, -0.3955],
                         [-0.9323, 0.3616, 0.0]])
    np.testing.assert_allclose(rot.rotation_matrix(38), expected, atol=2e-4)


def test_euler_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(50):
        a = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi])
        R = rot.euler_to_matrix(*a)
        np.testing.assert_allclose(rot.matrix_to_euler(R), a, atol=1e-12)


def test_custom_rotation_needs_angles():
    with pytest.raises(ValueError):
        rot.rotation_matrix(101)
    R = rot.rotation_matrix(101, custom=(0, 0, 90))
    np.testing.assert_allclose(R, rot.rotation_matrix(2), atol=1e-12)
    with pytest.raises(ValueError):
        rot.rotation_matrix(100)
    with pytest.raises(ValueError):
        rot.rotation_matrix(44)


def test_nearest_rotation():
    for k in range(44):
        if k in rot.AUTO_ROTATION_SKIP:
            continue
        small = rot.euler_to_matrix(0.01, -0.02, 0.015)
        best, err = rot.nearest_rotation(small @ rot.rotation_matrix(k))
        assert best == k
        assert 0 < err < 3
    # duplicates resolve to the canonical value; near-identity to NONE not PITCH_7
    assert rot.nearest_rotation(rot.rotation_matrix(26))[0] == 14
    assert rot.nearest_rotation(rot.euler_to_matrix(0, np.radians(3), 0))[0] == 0
    best, angle_deg = rot.nearest_rotation(rot.rotation_matrix(41), include_skipped=True)
    assert best == 41 and angle_deg == pytest.approx(0.0, abs=1e-5)  # arccos near 1: 1 ulp is ~1e-6 deg
