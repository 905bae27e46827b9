"""Issue 37, items 1 and 4: a compass's yaw mounting from the tilts of poses within reach, chosen
over the configured one only past a stated false-alarm rate; the state of the accelerometer's
calibration in force (full, level-only, never) and what its verdict says."""
from __future__ import annotations

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import euler_to_matrix, rotation_matrix
from mavcal.coverage import (
    HELD_ACCEL_SD,
    MOUNTING_FALSE_ALARM,
    ReachCoverage,
    accel_state,
    held_priors,
    mounting_ratio,
    reach_coverage,
)

#: the capture's plan within reach (15 deg), then three poses more (mavcal.capture.reach.reach_plan)
POSES = [(0, 0, 0), (0, 15, 60), (15, 0, 120), (0, 0, 180), (0, -15, 240), (-15, 0, 300), (10.6, 10.6, 30),
         (-10.6, -10.6, 210), (10.6, -10.6, 90), (-10.6, 10.6, 270), (0, 15, 330)]


def _means(rng, orient: int, dip_deg: float, ofs, dia, odi, noise=0.3):
    """Gravity directions (body, level = +z) and compass means (sensor frame) of the poses."""
    B = 500.0 * np.array([np.cos(np.radians(dip_deg)), 0.0, np.sin(np.radians(dip_deg))])
    M = fw.soft_iron_matrix(dia, odi)
    R = rotation_matrix(orient)
    g, m = [], []
    for r, p, y in POSES:
        C = euler_to_matrix(*np.radians([r, p, y]))  # body -> NED
        g.append(C.T @ np.array([0.0, 0.0, 1.0]))
        m.append(((C.T @ B) @ np.linalg.inv(M).T - np.asarray(ofs)) @ R + rng.normal(0.0, noise, 3))
    return np.array(g), np.array(m)


def _vehicle(seed: int):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    ofs = d / np.linalg.norm(d) * rng.uniform(100.0, 600.0)
    return rng, ofs, rng.uniform(0.9, 1.1, 3), rng.uniform(-0.05, 0.05, 3), rng.choice([-66.0, -17.0, 40.0, 70.0])


def test_the_threshold_is_an_f_test_at_the_stated_false_alarm_rate():
    from scipy.stats import f

    for n in (8, 11, 16, 25):
        d = 2 * n - 11
        assert mounting_ratio(n) >= 3.0
        assert f.sf(mounting_ratio(n) ** 2, d, d) <= MOUNTING_FALSE_ALARM * (1 + 1e-9)


def test_a_compass_mounted_as_configured_is_never_called_turned():
    """Over random vehicles (offsets 100-600 mGauss, soft iron 0.9-1.1 / +-0.05, dips from -66 to 70 deg)
    mounted as configured: no false alarm (and the mounting is confirmed on most)."""
    turned, confirmed = 0, 0
    for seed in range(16):
        rng, ofs, dia, odi, dip = _vehicle(seed)
        r = reach_coverage(*_means(rng, 0, dip, ofs, dia, odi))
        turned += bool(r.mounting_turn_deg)
        confirmed += r.mounting_turn_deg == 0.0
    assert turned == 0
    assert confirmed >= 12, confirmed


@pytest.mark.parametrize("orient", [2, 6])
def test_a_compass_turned_is_found(orient):
    for seed in (100, 101, 102):
        rng, ofs, dia, odi, dip = _vehicle(seed)
        r = reach_coverage(*_means(rng, orient, dip, ofs, dia, odi))
        assert r.mounting_turn_deg == {2: 90.0, 6: 270.0}[orient], (dip, r.mounting_evidence)
        assert "false-alarm rate at most 0.1 %" in r.mounting_evidence
        assert not any(k.what == "orientation" for k in r.kept)  # fitted and written, not kept
        assert any(f"turned {r.mounting_turn_deg:.0f} deg" in line for line in r.lines())


def test_a_field_some_turn_explains_is_no_disturbance():
    r = ReachCoverage(True, 4.0, 6, True, best_rms_mgauss=0.8, mounting_evidence="RMS ...")
    assert r.explained() and not ReachCoverage(True, 4.0, 6, True, best_rms_mgauss=40.0).explained()


def test_the_state_of_the_accelerometer_and_its_prior():
    assert accel_state((0, 0, 0), (1, 1, 1)) == "never"
    assert accel_state((0.1, -0.05, 0.3), (1, 1, 1)) == "level"
    assert accel_state((0.1, -0.05, 0.3), (0.99, 1.01, 1.002)) == "calibrated"
    # X/Y scales set, the Z scale exactly 1: what a fit of poses within reach writes (its Z scale the factory's)
    assert accel_state((0.1, -0.05, 0.3), (0.99, 1.01, 1.0)) == "reach"
    K = np.diag([9.8, 9.8, 9.8])
    for state in ("calibrated", "level", "never"):
        p = held_priors(K, state, None)
        assert p["b_a[x]"] == HELD_ACCEL_SD[state][0] and p["K_a[11]"] == pytest.approx(9.8 * HELD_ACCEL_SD[state][1])
    assert HELD_ACCEL_SD["never"][0] >= 0.5 / np.sqrt(3) and HELD_ACCEL_SD["never"][1] >= 0.05 / np.sqrt(3) - 1e-9
    r = ReachCoverage(True, 15.0, 6, True)
    never = r.heading_advice("never")
    assert "never calibrated" in never and "6-side calibration" in never
    assert "level-calibrated only" in r.heading_advice("level") and "6-side" in r.heading_advice("level")
