"""Still intervals: where the vehicle was held still, and whether they can calibrate.

The joint calibration needs the mean accelerometer and magnetometer readings of many
still poses. :func:`find_still_intervals` finds them in a recording:

1. The reference time base is accelerometer 0 (its sample rate sets the window length:
   at least ``min_window_samples`` samples, so 2 Hz tlogs get a 1.5 s window).
2. Sliding windows are "still" when the gyro RMS rate is below ``gyro_rad_s`` (where a
   gyro with non-zero data exists), the largest per-axis accel standard deviation is
   below ``accel_std_mps2``, the largest per-axis mag standard deviation below
   ``mag_std_mgauss`` (when no gyro), and |a| is within ``accel_norm_tol`` of the median
   still |a|. A run of consecutive still windows covers a run of still samples (an
   isolated still window in noisy motion only covers one window length).
3. Runs of still samples, less ``trim_s`` at each edge, that last ``min_duration_s``
   and hold ``min_samples`` samples are intervals; adjacent intervals in the same
   orientation (gravity and field directions within ``merge_deg``, gap below
   ``merge_gap_s``) are merged.
4. Samples of the other instances (accel and mag come at their own rates and times) are
   assigned to an interval by their time.

The diagnosis counts distinct gravity directions (clusters ``cluster_deg`` apart),
measures how they span the sphere (smallest eigenvalue of the scatter of unit gravity
vectors: 1/3 for a perfect spread, 0 when all lie in a plane; the largest empty spherical
cap) and says in words what the data cannot identify.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Tuple

import numpy as np

from mavcal.errors import SegmentationError
from mavcal.sources.types import SensorSeries

log = logging.getLogger(__name__)

__all__ = ["StillConfig", "StillInterval", "Coverage", "Segmentation", "find_still_intervals",
           "diagnose_coverage", "FULL_MODEL_MIN_INTERVALS", "axis_label"]

#: Intervals the full joint model needs (the paper's initial estimate and Wald tests).
FULL_MODEL_MIN_INTERVALS = 8


@dataclass(frozen=True)
class StillConfig:
    """Thresholds of the still-interval detector (defaults suit hand-held data).

    Attributes
    ----------
    window_s : sliding-window length in seconds (lengthened to ``min_window_samples``).
    min_window_samples : fewest samples in a window (matters for 2-10 Hz tlogs).
    gyro_rad_s : RMS angular rate over a window below which it is still.
    accel_std_mps2 : largest per-axis accel standard deviation in a still window.
    mag_std_mgauss : largest per-axis mag standard deviation in a still window (only
        used when there is no gyro).
    accel_norm_tol : |a| within this fraction of the median still |a|.
    min_duration_s : shortest interval (duration = samples x sample period).
    min_samples : fewest accel-0 samples in an interval.
    trim_s : time cut from each edge of a still run (the settling after a move).
    merge_deg, merge_gap_s : merge neighbouring intervals whose gravity and field
        directions differ less than ``merge_deg`` and that are less than ``merge_gap_s``
        apart.
    cluster_deg : gravity directions closer than this count as one orientation.
    use_gyro, use_mag : set False to ignore a sensor for stillness.
    """

    window_s: float = 1.0
    min_window_samples: int = 3
    gyro_rad_s: float = 0.1
    accel_std_mps2: float = 0.2
    mag_std_mgauss: float = 10.0
    accel_norm_tol: float = 0.15
    min_duration_s: float = 1.5
    min_samples: int = 3
    trim_s: float = 0.2
    merge_deg: float = 5.0
    merge_gap_s: float = 3.0
    cluster_deg: float = 20.0
    use_gyro: bool = True
    use_mag: bool = True

    def __post_init__(self) -> None:
        for n in ("window_s", "gyro_rad_s", "accel_std_mps2", "mag_std_mgauss", "accel_norm_tol", "cluster_deg"):
            if not getattr(self, n) > 0:
                raise ValueError(f"{n} must be > 0, got {getattr(self, n)!r}")
        for n in ("min_duration_s", "trim_s", "merge_deg", "merge_gap_s"):
            if getattr(self, n) < 0:
                raise ValueError(f"{n} must be >= 0, got {getattr(self, n)!r}")
        if self.min_samples < 1 or self.min_window_samples < 2:
            raise ValueError("min_samples must be >= 1 and min_window_samples >= 2")


@dataclass(frozen=True, eq=False)
class StillInterval:
    """One still interval.

    Attributes
    ----------
    start_s, end_s : time of the first and last accel-0 sample in it (seconds, the time
        base of the input series).
    accel_mps2 : mapping instance -> (n, 3) samples, m/s^2 (frame of the input: board
        frame for recovered raw data).
    mag_mgauss : mapping instance -> (n, 3) samples, mGauss.
    accel_dir : (3,) unit mean specific force of accel 0 in the body frame (what the
        accelerometer reads: level = (0, 0, -1)); gravity points the other way.
    mag_dir : (3,) unit mean field of mag 0 (body frame) or None.
    """

    start_s: float
    end_s: float
    accel_mps2: Mapping[int, np.ndarray]
    mag_mgauss: Mapping[int, np.ndarray]
    accel_dir: np.ndarray
    mag_dir: Optional[np.ndarray] = None
    sample_period_s: float = 0.0

    @property
    def duration_s(self) -> float:
        """Time covered: last - first sample time + one sample period."""
        return float(self.end_s - self.start_s + self.sample_period_s)

    @property
    def gravity_dir(self) -> np.ndarray:
        """Unit gravity direction in the body frame (level = (0, 0, +1), FRD)."""
        return -self.accel_dir

    @property
    def n_accel(self) -> Dict[int, int]:
        return {k: int(v.shape[0]) for k, v in self.accel_mps2.items()}

    @property
    def n_mag(self) -> Dict[int, int]:
        return {k: int(v.shape[0]) for k, v in self.mag_mgauss.items()}


@dataclass(frozen=True, eq=False)
class Coverage:
    """How well the intervals' gravity directions can identify a calibration.

    Attributes
    ----------
    n_intervals, n_orientations : counts (orientations = gravity clusters).
    scatter_eigenvalues : (3,) ascending eigenvalues of mean(g g^T) over the intervals.
    largest_empty_cap_deg : radius of the largest spherical cap with no gravity direction.
    status : "ok", "reduced" (usable with a reduced model) or "insufficient".
    messages : tuple of str, what is missing, in words.
    """

    n_intervals: int
    n_orientations: int
    scatter_eigenvalues: np.ndarray
    largest_empty_cap_deg: float
    status: str
    messages: Tuple[str, ...] = ()

    @property
    def min_eigenvalue(self) -> float:
        return float(self.scatter_eigenvalues[0])


@dataclass(frozen=True, eq=False)
class Segmentation:
    """Result of :func:`find_still_intervals`.

    Attributes
    ----------
    intervals : tuple of StillInterval, in time order.
    coverage : Coverage
    config : StillConfig
    sample_rate_hz : rate of accel 0.
    window_samples : sliding-window length actually used.
    used_gyro, used_mag : whether those sensors decided stillness.
    accel_instances, mag_instances : instances present in the intervals.
    warnings : tuple of str (coverage messages plus input problems).
    """

    intervals: Tuple[StillInterval, ...]
    coverage: Coverage
    config: StillConfig
    sample_rate_hz: float
    window_samples: int
    used_gyro: bool
    used_mag: bool
    accel_instances: Tuple[int, ...] = ()
    mag_instances: Tuple[int, ...] = ()
    warnings: Tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.intervals)

    def accel_arrays(self, instance: int = 0) -> List[np.ndarray]:
        """Per interval the (n_i, 3) accel samples of ``instance`` (m/s^2)."""
        return [iv.accel_mps2.get(instance, np.empty((0, 3))) for iv in self.intervals]

    def mag_arrays(self, instance: int = 0) -> List[np.ndarray]:
        """Per interval the (n_i, 3) mag samples of ``instance`` (mGauss)."""
        return [iv.mag_mgauss.get(instance, np.empty((0, 3))) for iv in self.intervals]


# --------------------------------------------------------------------------- helpers

def _collect(data) -> Tuple[List[SensorSeries], List[SensorSeries], List[SensorSeries]]:
    """accel, mag, gyro series of a RawImu, an ImuLog, or a sequence of SensorSeries."""
    if hasattr(data, "accel") and hasattr(data, "mag"):
        return list(data.accel), list(data.mag), list(getattr(data, "gyro", ()))
    series = list(data.series) if hasattr(data, "series") else list(data)
    by = {"accel": [], "mag": [], "gyro": []}  # type: Dict[str, List[SensorSeries]]
    for s in series:
        by[s.sensor].append(s)
    return by["accel"], by["mag"], by["gyro"]


def _rolling(x: np.ndarray, w: int) -> Tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of (n, d) x over windows x[i:i+w], i = 0..n-w."""
    c1 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x * x, axis=0)])
    s1 = c1[w:] - c1[:-w]
    s2 = c2[w:] - c2[:-w]
    m = s1 / w
    var = np.maximum(s2 / w - m * m, 0.0)
    return m, np.sqrt(var)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def _angle_deg(a: Optional[np.ndarray], b: Optional[np.ndarray]) -> float:
    if a is None or b is None:
        return 0.0
    return float(np.degrees(np.arccos(np.clip(np.dot(_unit(a), _unit(b)), -1.0, 1.0))))


def axis_label(gravity_dir: np.ndarray) -> str:
    """Words for a body-frame gravity direction (FRD): "level", "on its back", "nose down"..."""
    g = np.asarray(gravity_dir, dtype=float)
    k = int(np.argmax(np.abs(g)))
    # gravity points along the body axis that faces the ground: +x down = nose down,
    # +y (right wing) down = on its right side, +z down = level
    names = {(2, 1): "level", (2, -1): "on its back", (0, 1): "nose down", (0, -1): "nose up",
             (1, 1): "on its right side", (1, -1): "on its left side"}
    name = names[(k, int(np.sign(g[k])))]
    tilt = np.degrees(np.arccos(np.clip(abs(g[k]), -1, 1)))
    return name if tilt < 15 else f"{name} (+{tilt:.0f} deg)"


def _fibonacci_sphere(n: int = 2000) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


_SPHERE = _fibonacci_sphere()


# --------------------------------------------------------------------------- coverage

def diagnose_coverage(gravity_dirs: np.ndarray, cluster_deg: float = 20.0) -> Coverage:
    """Coverage of a set of unit gravity directions (one per interval).

    Parameters
    ----------
    gravity_dirs : (N, 3) array, any frame (the measures are rotation invariant).
    cluster_deg : directions closer than this are one orientation.
    """
    g = np.asarray(gravity_dirs, dtype=float).reshape(-1, 3)
    n = g.shape[0]
    msgs: List[str] = []
    if n == 0:
        return Coverage(0, 0, np.zeros(3), 180.0, "insufficient",
                        ("no still intervals were found: the vehicle never stayed still long enough "
                         "(or the thresholds are too strict)",))
    g = g / np.linalg.norm(g, axis=1, keepdims=True)
    centers: List[np.ndarray] = []
    cos_c = np.cos(np.radians(cluster_deg))
    for v in g:
        if not any(np.dot(v, c) >= cos_c for c in centers):
            centers.append(v)
    n_or = len(centers)
    ev = np.sort(np.linalg.eigvalsh(g.T @ g / n))
    cap = float(np.degrees(np.arccos(np.clip(np.max(_SPHERE @ g.T, axis=1), -1, 1))).max())
    if n < FULL_MODEL_MIN_INTERVALS:
        msgs.append(f"{n} still interval{'s' if n != 1 else ''}: the full joint model needs "
                    f">= {FULL_MODEL_MIN_INTERVALS} intervals; a reduced model will be used")
    if n_or == 1:
        msgs.append("a single orientation: gravity was seen from one direction only, which identifies "
                    "neither accelerometer offsets/scales nor the compass soft iron; hold the vehicle "
                    "in at least 6 different poses (each face down)")
    elif n_or == 2:
        msgs.append("only 2 distinct orientations: offsets and scales cannot be separated; "
                    "add poses with each face down")
    elif ev[0] < 0.02:
        msgs.append("the gravity directions lie in one plane (the vehicle was turned about a single "
                    "axis): the scale and offset along that axis cannot be identified; add poses "
                    "with that axis up and down")
    elif ev[0] < 0.08:
        msgs.append(f"gravity directions are poorly spread (smallest scatter eigenvalue {ev[0]:.3f}, "
                    f"ideal 0.333); add poses that fill the gap")
    if n_or > 1 and cap > 100:
        msgs.append(f"a large part of the sphere of gravity directions is empty (cap of {cap:.0f} deg); "
                    f"results will be poorly constrained there")
    if n_or <= 2 or n < 4:
        status = "insufficient"
    elif n < FULL_MODEL_MIN_INTERVALS or ev[0] < 0.08 or n_or < 6:
        status = "reduced"
    else:
        status = "ok"
    if status == "reduced" and n_or < 6 and n >= FULL_MODEL_MIN_INTERVALS and ev[0] >= 0.08:
        msgs.append(f"only {n_or} distinct orientations (clusters {cluster_deg:.0f} deg apart); "
                    f"at least 6 are recommended")
    return Coverage(n, n_or, ev, cap, status, tuple(msgs))


# --------------------------------------------------------------------------- detection

def _still_windows(t: np.ndarray, acc: np.ndarray, gyro: Optional[Tuple[np.ndarray, np.ndarray]],
                   mag: Optional[Tuple[np.ndarray, np.ndarray]], w: int, cfg: StillConfig) -> np.ndarray:
    """Per window start i (window = samples i..i+w-1 of accel 0): is the window still."""
    n = len(t)
    if n < w:
        return np.zeros(0, dtype=bool)
    _, sd = _rolling(acc, w)
    ok = sd.max(axis=1) < cfg.accel_std_mps2
    starts = np.arange(n - w + 1)
    t0, t1 = t[starts], t[starts + w - 1]
    if gyro is not None:
        tg, vg = gyro
        c = np.concatenate([[0.0], np.cumsum(np.sum(vg * vg, axis=1))])
        i0 = np.searchsorted(tg, t0, side="left")
        i1 = np.searchsorted(tg, t1, side="right")
        cnt = i1 - i0
        ms = np.where(cnt > 0, (c[i1] - c[i0]) / np.maximum(cnt, 1), 0.0)
        ok &= np.sqrt(ms) < cfg.gyro_rad_s
    if mag is not None:
        tm, vm = mag
        c1 = np.vstack([np.zeros((1, 3)), np.cumsum(vm, axis=0)])
        c2 = np.vstack([np.zeros((1, 3)), np.cumsum(vm * vm, axis=0)])
        i0 = np.searchsorted(tm, t0, side="left")
        i1 = np.searchsorted(tm, t1, side="right")
        cnt = (i1 - i0)[:, None]
        m = (c1[i1] - c1[i0]) / np.maximum(cnt, 1)
        var = np.maximum((c2[i1] - c2[i0]) / np.maximum(cnt, 1) - m * m, 0.0)
        # windows with < 2 mag samples carry no information: do not veto
        ok &= np.where(cnt[:, 0] >= 2, np.sqrt(var).max(axis=1) < cfg.mag_std_mgauss, True)
    norm = np.linalg.norm(acc, axis=1)
    if np.any(ok):
        cand = np.zeros(n, dtype=bool)
        for s in starts[ok]:
            cand[s:s + w] = True
        med = float(np.median(norm[cand]))
        bad = np.abs(norm - med) > cfg.accel_norm_tol * med
        cb = np.concatenate([[0], np.cumsum(bad)])
        ok &= (cb[starts + w] - cb[starts]) == 0
    return ok


def _runs(mask: np.ndarray) -> List[Tuple[int, int]]:
    """[i0, i1) index ranges of True runs."""
    m = np.concatenate([[False], mask, [False]])
    d = np.diff(m.astype(int))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def find_still_intervals(data, config: StillConfig = StillConfig(),
                         board_rotation: Optional[np.ndarray] = None) -> Segmentation:
    """Find the still intervals of a recording and diagnose their coverage.

    Parameters
    ----------
    data : RawImu, ImuLog, or sequence of SensorSeries
        Accel (m/s^2), mag (mGauss) and optional gyro (rad/s) series of any instances.
        Raw data from :func:`mavcal.ardupilot.recover.recover_raw` is the usual input.
    config : StillConfig
    board_rotation : (3, 3) array, optional
        Rotation from the accel frame to the body frame (R_A of AHRS_ORIENTATION for
        recovered board-frame accel) used for ``accel_dir``. Default: taken from
        ``data.board_rotation`` if it has one, else identity.

    Returns
    -------
    Segmentation

    Raises
    ------
    SegmentationError
        No accelerometer data at all.
    """
    cfg = config
    accel, mag, gyro = _collect(data)
    accel = [s for s in accel if len(s)]
    mag = [s for s in mag if len(s)]
    gyro = [s for s in gyro if len(s) and np.any(s.values != 0.0)]
    warnings: List[str] = []
    if not accel:
        raise SegmentationError("no accelerometer data: still intervals cannot be detected")
    if board_rotation is None:
        board_rotation = getattr(data, "board_rotation", None)
    R_b = np.eye(3) if board_rotation is None else np.asarray(board_rotation, dtype=float)
    ref = min(accel, key=lambda s: s.instance)
    order = np.argsort(ref.time_s, kind="stable")
    t = ref.time_s[order]
    a = ref.values[order]
    good = np.all(np.isfinite(a), axis=1)
    t, a = t[good], a[good]
    dt_all = np.diff(t)
    dt = float(np.median(dt_all[dt_all > 0])) if np.any(dt_all > 0) else 1.0
    rate = 1.0 / dt if dt > 0 else 0.0
    w = max(int(cfg.min_window_samples), int(round(cfg.window_s * rate)))
    g_ser = next((s for s in sorted(gyro, key=lambda s: s.instance)), None) if cfg.use_gyro else None
    gy = (g_ser.time_s, g_ser.values) if g_ser is not None else None
    m_ser = min(mag, key=lambda s: s.instance) if mag else None
    mg = None
    if cfg.use_mag and gy is None and m_ser is not None:
        mo = np.argsort(m_ser.time_s, kind="stable")
        mg = (m_ser.time_s[mo], m_ser.values[mo])
    ok = _still_windows(t, a, gy, mg, w, cfg)
    # a still run = consecutive still windows; it covers their samples. Runs separated by a
    # moving window overlap in samples: the later one starts where the earlier one ends.
    runs: List[Tuple[int, int]] = []
    for r0, r1 in _runs(ok):
        s0, s1 = int(r0), int(r1 - 1 + w)
        if runs and s0 < runs[-1][1]:
            s0 = runs[-1][1]
        if s1 > s0:
            runs.append((s0, s1))
    still = np.zeros(len(t), dtype=bool)
    for s0, s1 in runs:
        still[s0:s1] = True
    if len(t) < w:
        warnings.append(f"only {len(t)} accelerometer samples ({len(t) * dt:.1f} s): too short for a "
                        f"{w}-sample window")
    trim = int(np.floor(cfg.trim_s / dt + 1e-9)) if dt > 0 else 0
    spans: List[Tuple[int, int]] = []
    for i0, i1 in runs:
        i0, i1 = i0 + trim, i1 - trim
        if i1 - i0 < cfg.min_samples or (i1 - i0) * dt < cfg.min_duration_s - 1e-9:
            continue
        spans.append((int(i0), int(i1)))

    def mean_dir(i0: int, i1: int) -> np.ndarray:
        return _unit(R_b @ a[i0:i1].mean(axis=0))

    def mag_dir(t0: float, t1: float) -> Optional[np.ndarray]:
        if m_ser is None:
            return None
        sel = (m_ser.time_s >= t0 - dt / 2) & (m_ser.time_s <= t1 + dt / 2)
        if not np.any(sel):
            return None
        return _unit(m_ser.values[sel].mean(axis=0))

    # merge neighbours in the same orientation
    merged: List[Tuple[int, int]] = []
    for sp in spans:
        if merged:
            p0, p1 = merged[-1]
            gap = t[sp[0]] - t[p1 - 1]
            if (gap <= cfg.merge_gap_s and _angle_deg(mean_dir(*merged[-1]), mean_dir(*sp)) < cfg.merge_deg
                    and _angle_deg(mag_dir(t[p0], t[p1 - 1]), mag_dir(t[sp[0]], t[sp[1] - 1])) < cfg.merge_deg):
                merged[-1] = (p0, sp[1])
                continue
        merged.append(sp)

    intervals: List[StillInterval] = []
    for i0, i1 in merged:
        t0, t1 = float(t[i0]), float(t[i1 - 1])
        lo, hi = t0 - dt / 2, t1 + dt / 2
        am: Dict[int, np.ndarray] = {}
        for s in accel:
            if s is ref:
                # merged spans may contain the still-mask gap between two runs: keep still samples
                idx = np.arange(i0, i1)
                am[s.instance] = a[idx[still[idx]]] if np.any(~still[idx]) else a[i0:i1]
            else:
                sel = (s.time_s >= lo) & (s.time_s <= hi) & np.all(np.isfinite(s.values), axis=1)
                am[s.instance] = s.values[sel]
        mm: Dict[int, np.ndarray] = {}
        for s in mag:
            sel = (s.time_s >= lo) & (s.time_s <= hi)
            mm[s.instance] = s.values[sel]
        intervals.append(StillInterval(t0, t1, am, mm, mean_dir(i0, i1), mag_dir(t0, t1), dt))

    cov = diagnose_coverage(np.array([iv.gravity_dir for iv in intervals]).reshape(-1, 3), cfg.cluster_deg)
    for s in mag:
        empty = sum(1 for iv in intervals if iv.mag_mgauss.get(s.instance, np.empty((0, 3))).shape[0] == 0)
        if empty:
            warnings.append(f"mag {s.instance}: no samples in {empty} of {len(intervals)} intervals")
    all_w = tuple(warnings) + cov.messages
    for m in all_w:
        log.info("%s", m)
    return Segmentation(tuple(intervals), cov, cfg, rate, w, gy is not None, mg is not None,
                        tuple(sorted(s.instance for s in accel)), tuple(sorted(s.instance for s in mag)),
                        all_w)
