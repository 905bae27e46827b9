"""Issue 11: the faster kernels of ``prepare`` give the library's values.

The inverse models skip LAPACK/BLAS for a diagonal soft-iron matrix and a signed-permutation
board rotation, and the segmentation computes its sums, norms and products in other layouts
and blocks. Every shortcut is compared here with the straightforward expression it replaces
(``np.linalg.solve``, ``a @ R``, one ``cumsum``, ``np.linalg.norm``, ``ndarray.mean``),
including the values where a shortcut could differ: zeros, NaN and infinities, one-row calls.
The values agree within 1e-9 relative at each row's scale, NaN and infinities exactly where
the reference has them (issue 23: not byte for byte, since what LAPACK/BLAS give in the last
bit depends on the kernel OpenBLAS picks for the CPU); boolean results (which windows are
still) exactly.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import mavcal.gravity_spread as spread_mod
import mavcal.window_stats as stats_mod
from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.recover import recover_raw
from mavcal.segment import find_still_intervals
from mavcal.sources.reader import read_log
from mavcal.sources.types import SensorSeries
from mavcal.testing.numbers import array_differences, assert_close

SITL = Path(__file__).resolve().parents[1] / "sitl_logs"
SPECIAL = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 5e-324, -5e-324, 1e308])


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and array_differences(a, b, axis=-1 if a.ndim else None) is None


def _ref_undo_compass(cal: fw.CompassCal, c, motor=None) -> np.ndarray:
    """The inverse compass model as one library solve (the former implementation)."""
    c = np.asarray(c, dtype=float)
    if motor is not None:
        c = c - motor
    b = np.linalg.solve(cal.matrix, c.reshape(-1, 3).T).T.reshape(c.shape) / cal.k
    return b - np.asarray(cal.ofs_mgauss)


def _ref_undo_accel(cal: fw.AccelCal, a, calibrating: bool = False) -> np.ndarray:
    """The inverse accelerometer model as one matrix product (the former implementation)."""
    u = np.asarray(a, dtype=float) @ cal.board_matrix
    if calibrating:
        return u
    s = np.asarray(cal.scale)
    u = np.where(s != 0.0, u / np.where(s != 0.0, s, 1.0), np.nan)
    return u + np.asarray(cal.ofs_mps2)


def _readings(rng: np.random.Generator, n: int, p_special: float) -> np.ndarray:
    v = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 300.0])
    if rng.random() < 0.5:
        v = np.round(v)  # integer telemetry: many +0
    m = rng.random((n, 3)) < p_special
    v[m] = rng.choice(SPECIAL, size=int(m.sum()))
    return v


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_compass_inverse_is_the_library_solve():
    rng = np.random.default_rng(7)
    for trial in range(400):
        n = int(rng.choice([1, 2, 3, 7, 16, 17, 100, 5000]))
        v = _readings(rng, n, float(rng.choice([0.0, 1e-3, 0.05, 0.3])))
        kind = trial % 4  # DIA unset (identity), DIA without ODI, DIA = 1, full matrix
        dia = np.zeros(3) if kind == 0 else (np.ones(3) if kind == 2 else rng.normal(1.0, 0.05, 3))
        odi = rng.normal(0.0, 0.02, 3) if kind == 3 else np.zeros(3)
        cal = fw.CompassCal(ofs_mgauss=rng.normal(0, 50, 3), dia=dia, odi=odi,
                            scale=float(rng.choice([1.0, 1.2, 0.0])))
        motor = _readings(rng, n, 0.01) if trial % 3 == 0 else None
        ref = _ref_undo_compass(cal, v, motor)
        assert _same(fw.undo_compass(cal, v, motor), ref), (trial, cal)
        out = np.empty((n, 3))
        assert fw.undo_compass(cal, v, motor, out=out) is out and _same(out, ref)
    one = np.array([3.0, -0.0, 7.0])  # a single vector (one right-hand side: LAPACK's other path)
    cal = fw.CompassCal(dia=(0.97, 1.02, 0.99))
    assert _same(fw.undo_compass(cal, one), _ref_undo_compass(cal, one))


def test_singular_soft_iron_matrix_still_raises():
    cal = fw.CompassCal(dia=(1.0, 0.0, 1.0))  # DIA set with a zero: singular
    with pytest.raises(np.linalg.LinAlgError):
        fw.undo_compass(cal, np.ones((10, 3)))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("orient", [0, 2, 4, 8, 12, 16, 24, 101])
def test_accel_inverse_is_the_matrix_product(orient):
    rng = np.random.default_rng(orient)
    custom = (10.0, -20.0, 30.0) if orient == 101 else None
    for trial in range(120):
        n = int(rng.choice([1, 2, 5, 64, 3000]))
        v = _readings(rng, n, float(rng.choice([0.0, 1e-3, 0.05, 0.3])))
        scale = rng.normal(1.0, 0.02, 3)
        if trial % 10 == 0:
            scale[1] = 0.0  # an unused slot: NaN on that axis
        cal = fw.AccelCal(ofs_mps2=rng.normal(0, 0.2, 3), scale=scale, board_orient=orient, custom_deg=custom)
        for calibrating in (False, True):
            ref = _ref_undo_accel(cal, v, calibrating)
            assert _same(fw.undo_accel(cal, v, calibrating), ref), (orient, trial, calibrating)
            out = np.empty((n, 3))
            assert fw.undo_accel(cal, v, calibrating, out=out) is out and _same(out, ref)
    vec = np.array([-0.0, 9.81, np.nan])
    cal = fw.AccelCal(board_orient=orient, custom_deg=custom)
    assert _same(fw.undo_accel(cal, vec), _ref_undo_accel(cal, vec))


def test_out_must_fit_and_not_overlap():
    v = np.ones((10, 3))
    with pytest.raises(ValueError):
        fw.undo_accel(fw.AccelCal(), v, out=np.empty((9, 3)))
    with pytest.raises(ValueError):
        fw.undo_accel(fw.AccelCal(), v, out=v)
    with pytest.raises(ValueError):
        fw.undo_compass(fw.CompassCal(), v, out=np.empty((10, 3), dtype=np.float32))


def test_recovered_log_is_the_library_inverse():
    """recover_raw on a real SITL log: each compass and accelerometer is the former one-call
    inverse with the parameters in force (one parameter set over the whole log here)."""
    log = read_log(SITL / "sitl01.tlog")
    raw = recover_raw(log)
    for s in raw.mag:
        cal = fw.compass_cal_from_params(log.params.snapshot(), s.instance)
        assert _same(s.values, _ref_undo_compass(cal, log.get("mag", s.instance).values))
    for s in raw.accel:
        cal = fw.accel_cal_from_params(log.params.snapshot(), s.instance)
        assert _same(s.values, _ref_undo_accel(cal, log.get("accel", s.instance).values))


def test_gyro_windows_by_index_equal_the_sorted_search(monkeypatch):
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.015, 0.025, 5000))
    g = rng.normal(0, 0.05, size=(5000, 3))
    for w in (3, 50, 400):
        t0, t1 = t[:len(t) - w + 1], t[w - 1:]
        for chunk in (64, 1 << 14):
            monkeypatch.setattr(stats_mod, "CHUNK", chunk)
            searched = stats_mod.gyro_still(t, g, t0, t1, 0.0866)
            assert _same(stats_mod.gyro_still(t, g, t0, t1, 0.0866, w), searched)
            assert 0 < searched.sum() < len(searched)  # the threshold splits the windows
    assert stats_mod.same_times(t, t.copy())
    assert not stats_mod.same_times(t, np.r_[t[:10], t[9], t[11:]])  # a repeated time
    assert not stats_mod.same_times(t, t[:-1])


def test_prefix_sums_norms_and_cap_equal_the_full_length_expressions(monkeypatch):
    rng = np.random.default_rng(9)
    x = rng.normal(9.0, 0.3, size=(3000, 3))
    idx = np.unique(rng.integers(0, 3001, 200))
    full = np.vstack([np.zeros((1, 3)), np.cumsum(x, axis=0)])
    for chunk in (37, 1 << 14):
        monkeypatch.setattr(stats_mod, "CHUNK", chunk)
        assert _same(stats_mod.prefix_at(x, idx), full[idx])
        assert _same(stats_mod.norms(x), np.linalg.norm(x, axis=1))
    for n in (1, 5, 127, 128, 129, 1395):
        g = rng.normal(size=(n, 3))
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        best = np.full(len(spread_mod.SPHERE), -np.inf)
        for k in range(0, n, 128):  # the former products: every grid point at once
            np.maximum(best, np.max(spread_mod.SPHERE @ g[k:k + 128].T, axis=1), out=best)
        ref = float(np.degrees(np.arccos(np.clip(best, -1, 1))).max())
        assert_close(spread_mod.largest_empty_cap_deg(g), ref)


def test_interval_directions_are_the_mean_and_norm_of_their_samples():
    raw = recover_raw(read_log(SITL / "sitl02.tlog"))
    seg = find_still_intervals(raw)
    R_b = np.eye(3) if raw.board_rotation is None else raw.board_rotation
    assert len(seg) > 5
    for iv in seg.intervals:
        a = R_b @ iv.accel_mps2[0].mean(axis=0)
        assert _same(iv.accel_dir, a / np.linalg.norm(a))
        m = iv.mag_mgauss[0].mean(axis=0)
        assert _same(iv.mag_dir, m / np.linalg.norm(m))


def test_nonzero_check_reads_like_the_full_comparison():
    late = np.zeros((1000, 3))
    late[900, 2] = 1e-300  # the first non-zero value far down
    for x in (np.zeros((500, 3)), np.full((500, 3), -0.0), late, np.full((3, 3), np.nan), np.ones((2, 3))):
        assert SensorSeries("gyro", 0, "X", np.zeros(len(x)), x).any_nonzero() == bool(np.any(x != 0.0))
