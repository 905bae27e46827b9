"""Headings of poses within reach counted from what cannot be wrong (issue 37): a provisional
fit of the compass (offsets, scale, soft iron and dip fitted, the tilts the accelerometer gives
removed, each yaw mounting tried) counts the headings the vehicle was actually held at, over a
grid of offsets up to ArduPilot's COMPASS_OFFS_MAX (1800 mGauss), soft iron with diagonals
0.8-1.2 and off-diagonals up to 0.1 (twice the usual 0.9-1.1 and 0.05), sites from the equator
to a 75 deg dip, accelerometers never calibrated and compasses mounted at any yaw rotation."""
from __future__ import annotations

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import rotation_matrix
from mavcal.capture import euler_matrix
from mavcal.core.headings import provisional_headings
from mavcal.core.held import tilts_of
from mavcal.coverage import REACH_HEADING_DEG, _headings, reach_coverage
from mavcal.gravity_spread import count_clusters

G0 = 9.80665

#: pose sets (roll, pitch, yaw deg): the advised plan, and poses at only 1, 2, 3 headings
PLANS = {
    "plan, 6 headings": [(0, 0, 0), (0, 15, 60), (15, 0, 120), (0, 0, 180), (0, -15, 240), (-15, 0, 300),
                         (10.6, 10.6, 30), (-10.6, -10.6, 210)],
    "2 headings": [(0, 0, 0), (0, 15, 0), (15, 0, 0), (0, 0, 180), (0, -15, 180), (-15, 0, 180), (10.6, 10.6, 0)],
    "3 headings": [(0, 0, 0), (0, 15, 120), (15, 0, 240), (0, 0, 0), (0, -15, 120), (-15, 0, 240), (10.6, 10.6, 0)],
    "1 heading": [(0, 0, 90), (0, 15, 90), (15, 0, 90), (0, -15, 90), (-15, 0, 90)],
    "4 headings at 5 deg": [(0, 0, 0), (0, 5, 90), (5, 0, 180), (0, -5, 270), (-5, 0, 0)],
}


def _means(poses, ofs, dia, odi, incl_deg, orient, acc_bias, acc_scale, rng, field=550.0, noise=3.0):
    """Interval means: gravity directions (FRD, level +z) of a raw accelerometer and raw compass
    means (its sensor frame) as ArduPilot's conventions state the errors (CompassTruth, AccelCalTruth)."""
    i = np.radians(incl_deg)
    B = field * np.array([np.cos(i), 0.0, np.sin(i)])
    Msi = fw.soft_iron_matrix(dia, odi)
    R = rotation_matrix(orient)
    g, m = [], []
    for q in poses:
        C = euler_matrix(*q)
        a = (C.T @ np.array([0.0, 0.0, -G0])) / np.asarray(acc_scale) + np.asarray(acc_bias)
        g.append(-a / np.linalg.norm(a))
        m.append(R.T @ (np.linalg.solve(Msi, C.T @ B) - np.asarray(ofs)) + rng.uniform(-noise, noise, 3) / np.sqrt(20))
    return np.array(g), np.array(m)


def _held(poses) -> int:
    y = np.radians([q[2] for q in poses])
    return count_clusters(np.c_[np.cos(y), np.sin(y), np.zeros(len(y))], REACH_HEADING_DEG)


def _cases(seed: int, n: int):
    rng = np.random.default_rng(seed)
    for k in range(n):
        yield dict(ofs=rng.uniform(-1800, 1800, 3) * (1.0 if k % 2 else 0.25),  # up to COMPASS_OFFS_MAX
                   dia=rng.uniform(0.8, 1.2, 3), odi=rng.uniform(-0.1, 0.1, 3),  # 2x typical
                   incl_deg=float(rng.choice([0.0, 20.0, -45.0, -66.0, 66.0, 75.0, -75.0])),
                   orient=int(rng.choice([0, 2, 4, 6])),
                   acc_bias=rng.uniform(-0.5, 0.5, 3), acc_scale=rng.uniform(0.95, 1.05, 3), rng=rng)


@pytest.mark.parametrize("plan", sorted(PLANS))
def test_the_count_equals_the_headings_held(plan):
    poses = PLANS[plan]
    want = _held(poses)
    wrong = []
    for case in _cases(len(plan), 12):
        g, m = _means(poses, **case)
        got = _headings(g, m)
        if got != want:
            wrong.append((got, {k: np.round(v, 3) for k, v in case.items() if k != "rng"}))
    assert not wrong, f"held {want} headings: {wrong}"


def test_the_issue_vehicle_counts_its_six_headings():
    """The reproduction of issue 37: SIM_MAG1_OFS (-134, 117.1, -198.7), DIA (1.038, 1.0616, 0.9742),
    ODI (0.0135, 0.0012, 0.0085) at CMAC's -66 deg dip, the accelerometer as SITL's errors leave it."""
    poses = PLANS["plan, 6 headings"]
    g, m = _means(poses, (-134.0, 117.1, -198.7), (1.038, 1.0616, 0.9742), (0.0135, 0.0012, 0.0085), -65.8, 0,
                  (-0.021, 0.005, -0.431), (0.9716, 0.9736, 1.0294), np.random.default_rng(1), field=580.0)
    assert _headings(g, m) == 6
    r = reach_coverage(g, m)
    assert r.n_field_directions == 6 and r.compass_identified, r.lines()


@pytest.mark.parametrize("orient", [0, 2, 4, 6])
def test_the_yaw_mounting_is_found_from_15_deg_tilts(orient):
    g, m = _means(PLANS["plan, 6 headings"], (300.0, -200.0, 100.0), (1.03, 0.98, 1.0), (0.01, -0.01, 0.02), -66.0,
                  orient, (0.05, -0.05, 0.1), (1.0, 1.0, 1.0), np.random.default_rng(orient))
    fit = provisional_headings(tilts_of(-g), m, (0, 2, 4, 6))
    assert fit.orientation == orient, fit.rms_mgauss
    others = [v for o, v in fit.rms_mgauss.items() if o != orient]
    assert min(others) > 3.0 * fit.rms_mgauss[orient], fit.rms_mgauss
    rel = np.degrees(-(fit.psi_rad - fit.psi_rad[0])) % 360.0
    want = np.array([q[2] for q in PLANS["plan, 6 headings"]], float)
    err = (rel - want + 180.0) % 360.0 - 180.0
    assert np.abs(err).max() < 5.0, rel
