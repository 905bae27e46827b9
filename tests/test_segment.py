"""Still intervals: simulated poses, 2 Hz data, SITL dance windows, coverage diagnosis and
every real log (intervals or a clear reason)."""
import json
from pathlib import Path

import numpy as np
import pytest

from mavcal.ardupilot.recover import recover_raw
from mavcal.errors import MavcalError, SegmentationError
from mavcal.gravity_spread import diagnose_coverage
from mavcal.segment import StillConfig, find_still_intervals
from mavcal.sources import read_log
from mavcal.sources.types import SensorSeries
from mavcal.testing.simlog import AccelErrorTruth, MagTruth, SimConfig, simulate_session

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REAL = SHARED / "data" / "real"
SITL = SHARED / "sitl_logs"

CFG = SimConfig(accels=(AccelErrorTruth((0.2, -0.1, 0.1), (1.01, 0.98, 1.0)),),
                mags=(MagTruth((50.0, -20.0, 80.0)), MagTruth((5.0, 5.0, 5.0))), seed=3)


def _series(sim, rate_div=1):
    t = sim.accel_time_s[0][::rate_div]
    out = [SensorSeries("accel", 0, "sim", t, sim.accel_raw_mps2[0][::rate_div]),
           SensorSeries("gyro", 0, "sim", t, sim.gyro_rad_s[0][::rate_div])]
    for k, m in enumerate(sim.mag_raw_mgauss):
        out.append(SensorSeries("mag", k, "sim", sim.mag_time_s[k][::rate_div], m[::rate_div]))
    return out


def _matches(intervals, windows, frac=0.7):
    hit = 0
    for t0, t1 in windows:
        ov = max([(min(t1, iv.end_s) - max(t0, iv.start_s)) / (t1 - t0) for iv in intervals] + [0])
        hit += ov > frac
    return hit


@pytest.fixture(scope="module")
def sim():
    return simulate_session(CFG)


def test_finds_every_simulated_pose(sim):
    seg = find_still_intervals(_series(sim))
    assert _matches(seg.intervals, sim.still_windows_s) == len(CFG.poses_deg)
    assert len(seg) == len(CFG.poses_deg)
    assert seg.used_gyro and seg.coverage.status == "ok"
    assert seg.coverage.n_orientations >= 12
    for iv, R in zip(seg.intervals, sim.attitudes):
        # gravity (NED down) seen in the body frame
        assert np.degrees(np.arccos(np.clip(iv.gravity_dir @ (R.T @ [0, 0, 1]), -1, 1))) < 3
        assert iv.n_mag[0] == iv.n_accel[0] and iv.n_mag[1] > 0
    arrays = seg.accel_arrays(0)
    assert len(arrays) == len(seg) and all(a.shape[1] == 3 for a in arrays)


def test_without_gyro_uses_mag_and_accel(sim):
    seg = find_still_intervals([s for s in _series(sim) if s.sensor != "gyro"])
    assert not seg.used_gyro and seg.used_mag
    assert _matches(seg.intervals, sim.still_windows_s) == len(CFG.poses_deg)


def test_two_hertz_data(sim):
    seg = find_still_intervals(_series(sim, rate_div=25))  # 50 Hz -> 2 Hz
    assert seg.window_samples == 3
    assert _matches(seg.intervals, sim.still_windows_s, frac=0.5) == len(CFG.poses_deg)


def test_thresholds_are_used(sim):
    seg = find_still_intervals(_series(sim), StillConfig(accel_std_mps2=1e-4))
    assert len(seg) == 0 and seg.coverage.status == "insufficient"
    assert "no still intervals" in seg.coverage.messages[0]
    with pytest.raises(ValueError):
        StillConfig(window_s=0)


def test_coverage_diagnosis_in_words():
    one = diagnose_coverage(np.tile([0, 0, 1.0], (10, 1)))
    assert one.n_orientations == 1 and one.status == "insufficient"
    assert any("single orientation" in m for m in one.messages)
    ang = np.radians(np.arange(0, 360, 30))
    plane = diagnose_coverage(np.column_stack([np.cos(ang), np.sin(ang), 0 * ang]))
    assert plane.min_eigenvalue < 0.01 and any("one plane" in m for m in plane.messages)
    few = diagnose_coverage(np.vstack([np.eye(3), -np.eye(3)]))
    assert few.n_orientations == 6 and few.status == "reduced"
    assert any("needs >= 8 intervals" in m for m in few.messages)
    assert few.min_eigenvalue == pytest.approx(1 / 3)
    assert few.largest_empty_cap_deg == pytest.approx(54.7, abs=1.5)


def test_no_accel_is_an_error():
    with pytest.raises(SegmentationError):
        find_still_intervals([SensorSeries("mag", 0, "x", [0.0, 1.0], np.zeros((2, 3)))])


@pytest.mark.parametrize("name", ["sitl01", "sitl02"])
def test_sitl_dance_windows_are_found(name):
    truth = json.loads((SITL / f"{name}.truth.json").read_text()) if (SITL / f"{name}.truth.json").exists() \
        else pytest.skip("no SITL logs")
    raw = recover_raw(read_log(SITL / f"{name}.tlog"))
    seg = find_still_intervals(raw)
    unix = raw.accel[0].time_s[0] > 1e9
    wins = [((w["still_start_unix_usec"] / 1e6, w["still_end_unix_usec"] / 1e6) if unix
             else (w["still_start_boot_ms"] / 1e3, w["still_end_boot_ms"] / 1e3)) for w in truth["dance"]["windows"]]
    assert _matches(seg.intervals, wins, frac=0.9) == len(wins)
    assert seg.coverage.status == "ok" and len(seg) <= len(wins) + 1


# name -> (min intervals, expected status or None, words expected in the diagnosis)
REAL_EXPECT = {
    "00000124.BIN": (8, "ok", None),
    "2024-04-05 09-19-03.tlog": (8, "ok", None),
    "2023-05-17 12-18-48.tlog": (6, "reduced", "needs >= 8"),
    "2024-04-05 09-36-27.tlog": (3, "reduced", "poorly spread"),
    "flight.tlog": (1, "insufficient", "single orientation"),
    "log171.bin": (1, "insufficient", "single orientation"),
    "00000-2021-12-02_13-34-15.bin": (1, "insufficient", "single orientation"),
    "test.BIN": (0, "insufficient", "too short"),
    "acc_log.csv": (1, None, None),
}


@pytest.mark.parametrize("name", sorted(REAL_EXPECT))
def test_every_real_log_gives_intervals_or_a_reason(name):
    path = REAL / name
    if not path.exists():
        pytest.skip(f"{path} not available")
    try:
        raw = recover_raw(read_log(path))
    except MavcalError as exc:  # unreadable: the error itself is the diagnosis
        pytest.fail(f"{name}: {exc}")
    seg = find_still_intervals(raw)
    n_min, status, words = REAL_EXPECT[name]
    assert len(seg) >= n_min
    if status:
        assert seg.coverage.status == status
    if words:
        assert any(words in w for w in seg.warnings), seg.warnings
    if len(seg) == 0:
        assert seg.warnings  # says why


def test_axis_labels_follow_frd():
    from mavcal.gravity_spread import axis_label

    assert axis_label(np.array([0.0, 0.0, 1.0])) == "level"
    assert axis_label(np.array([1.0, 0.0, 0.0])) == "nose down"  # the nose (+x) faces the ground
    assert axis_label(np.array([-1.0, 0.0, 0.0])) == "nose up"
    assert axis_label(np.array([0.0, 1.0, 0.0])) == "on its right side"
    assert axis_label(np.array([0.0, 0.0, -1.0])) == "on its back"


EXPECTED = Path(__file__).resolve().parent / "data" / "still_intervals_sitl.json"
BUNDLED = Path(__file__).resolve().parents[1] / "sitl_logs"


@pytest.mark.parametrize("name", ["sitl01.tlog", "sitl02.tlog"])
def test_bundled_logs_give_the_recorded_intervals(name):
    """Bounds, sample counts and directions recorded with the per-interval-mask detector
    before it was made linear: the faster one must find exactly the same."""
    path = BUNDLED / name
    if not path.exists():
        pytest.skip(f"{path} not available")
    expect = json.loads(EXPECTED.read_text())[name]
    seg = find_still_intervals(recover_raw(read_log(str(path))))
    got = [[iv.start_s, iv.end_s, {str(k): v for k, v in iv.n_accel.items()},
            {str(k): v for k, v in iv.n_mag.items()}, list(iv.accel_dir)] for iv in seg.intervals]
    assert len(got) == len(expect)
    for g, e in zip(got, expect):
        assert g[0] == pytest.approx(e[0], abs=1e-6) and g[1] == pytest.approx(e[1], abs=1e-6)
        assert g[2] == e[2] and g[3] == e[3]
        np.testing.assert_allclose(g[4], e[4], atol=1e-8)


def test_coverage_clusters_in_order_like_the_leader_rule():
    rng = np.random.default_rng(1)
    g = rng.normal(size=(500, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    centers = []
    for v in g:   # the rule, one vector at a time
        if not any(v @ c >= np.cos(np.radians(20.0)) for c in centers):
            centers.append(v)
    cov = diagnose_coverage(g, 20.0)
    assert cov.n_orientations == len(centers)
    cap = np.degrees(np.arccos(np.clip((_sphere_points() @ g.T).max(axis=1), -1, 1))).max()
    assert cov.largest_empty_cap_deg == pytest.approx(cap)


def _sphere_points(n: int = 2000) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


def _return_to_pose_log(rate=50.0, mag_rate=20.0):
    """Still 4 s, a 1 s excursion (0.5 s out at 120 deg/s about x, 0.5 s back), still 4 s
    in the same pose: accel 0 and 1 (at their own times), mag 0 and 1, gyro. Returns the
    series and the excursion (t0, t1)."""
    rng = np.random.default_rng(5)
    g = np.array([0.0, 0.0, -9.80665])
    B = np.array([200.0, 20.0, 420.0])

    def rot_x(th):
        c, s = np.cos(th), np.sin(th)
        return np.array([[1, 0, 0], [0, c, s], [0, -s, c]])

    def angle(t):  # radians about x; 0 while still
        w = np.radians(120.0)
        return np.where((t >= 4) & (t < 4.5), w * (t - 4), np.where((t >= 4.5) & (t < 5), w * (5 - t), 0.0))

    def rate_x(t):
        w = np.radians(120.0)
        return np.where((t >= 4) & (t < 4.5), w, np.where((t >= 4.5) & (t < 5), -w, 0.0))

    series = []
    for inst, off in ((0, 0.0), (1, 0.37 / rate)):
        t = np.arange(0, 9, 1 / rate) + off
        a = np.array([rot_x(th) @ g for th in angle(t)]) + rng.normal(0, 0.01, (len(t), 3))
        series.append(SensorSeries("accel", inst, "sim", t, a))
        if inst == 0:
            gy = np.column_stack([rate_x(t), 0 * t, 0 * t]) + rng.normal(0, 0.001, (len(t), 3))
            series.append(SensorSeries("gyro", 0, "sim", t, gy))
    for inst, bias in ((0, np.array([30.0, -10.0, 5.0])), (1, np.zeros(3))):
        t = np.arange(0, 9, 1 / mag_rate) + 0.013 * (inst + 1)
        m = np.array([rot_x(th) @ B for th in angle(t)]) + bias + rng.normal(0, 1.0, (len(t), 3))
        series.append(SensorSeries("mag", inst, "sim", t, m))
    return series, (4.0, 5.0)


def test_a_quick_return_merges_and_no_sensor_keeps_the_motion():
    """A return to the same pose within merge_gap_s is one interval (two pieces), and every
    sensor (not only accel 0) keeps only the samples of the still spans."""
    series, (m0, m1) = _return_to_pose_log()
    seg = find_still_intervals(series)
    assert len(seg) == 1
    iv = seg.intervals[0]
    assert len(iv.pieces_s) == 2
    (a0, a1), (b0, b1) = iv.pieces_s
    assert a1 < m0 and b0 > m1  # the motion lies between the pieces
    still = {s.sensor + str(s.instance): s for s in series}
    for key, arr in (("accel0", iv.accel_mps2[0]), ("accel1", iv.accel_mps2[1]),
                     ("mag0", iv.mag_mgauss[0]), ("mag1", iv.mag_mgauss[1])):
        s = still[key]
        in_motion = (s.time_s >= m0) & (s.time_s < m1)
        vals = s.values[~in_motion]
        # every kept sample is one of the still samples, and the mean is the still mean
        assert all(np.any(np.all(vals == row, axis=1)) for row in arr), key
        mean_still = vals.mean(axis=0)
        scale = 9.80665 if key.startswith("accel") else 470.0
        assert np.linalg.norm(arr.mean(axis=0) - mean_still) < 0.01 * scale, key
    # the same stillness mask for all: counts in proportion to the rates
    assert abs(iv.n_accel[1] - iv.n_accel[0]) <= 2
    assert abs(iv.n_mag[0] - iv.n_accel[0] * 20 / 50) <= 4 and abs(iv.n_mag[1] - iv.n_mag[0]) <= 2


def test_merging_stays_linear_in_the_number_of_returns():
    """Many quick returns to one pose: one interval, its pieces in order, no moving sample."""
    base, _ = _return_to_pose_log()
    reps = 40
    series = []
    for s in base:  # the 9 s pattern repeated; each repetition ends and starts still
        t = np.concatenate([s.time_s + 9.0 * k for k in range(reps)])
        series.append(SensorSeries(s.sensor, s.instance, "sim", t, np.tile(s.values, (reps, 1))))
    seg = find_still_intervals(series)
    assert len(seg) == 1
    iv = seg.intervals[0]
    assert len(iv.pieces_s) == reps + 1  # the still end of one repetition joins the next one's start
    starts = np.array([p[0] for p in iv.pieces_s])
    assert np.all(np.diff(starts) > 0)
    t_mag = np.concatenate([base[-1].time_s + 9.0 * k for k in range(reps)])
    moving = ((t_mag % 9.0) >= 4.0) & ((t_mag % 9.0) < 5.0)
    assert iv.n_mag[1] <= int((~moving).sum())
