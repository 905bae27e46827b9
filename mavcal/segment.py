"""Still intervals: where the vehicle was held still (the detector and its result).

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
   ``merge_gap_s``) are merged: the interval is the union of their spans, the motion
   between them is left out.
4. Samples of the other instances (accel and mag come at their own rates and times) are
   assigned to an interval by their time: those within half a sample period of one of its
   spans (one stillness mask for every sensor).

The window statistics are :mod:`mavcal.window_stats`'s; how the intervals' gravity directions
spread (the :class:`~mavcal.gravity_spread.Coverage` a :class:`Segmentation` carries) is
:mod:`mavcal.gravity_spread`'s.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mavcal.errors import SegmentationError
from mavcal.gravity_spread import Coverage, diagnose_coverage
from mavcal.sources.types import SensorSeries
from mavcal.window_stats import covered, gyro_still, norms, prefix_at, rolling_sd_max, same_times, window_sums

log = logging.getLogger(__name__)

__all__ = ["StillConfig", "StillInterval", "Segmentation", "find_still_intervals"]


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
    sample_period_s : accel-0 sample period (s).
    pieces_s : ((start_s, end_s), ...) the still spans the interval is made of, in time order:
        one, or several when returns to the same orientation within ``merge_gap_s`` were
        merged. Every sensor's samples lie within these spans (none from the motion between
        them).
    """

    start_s: float
    end_s: float
    accel_mps2: Mapping[int, np.ndarray]
    mag_mgauss: Mapping[int, np.ndarray]
    accel_dir: np.ndarray
    mag_dir: np.ndarray | None = None
    sample_period_s: float = 0.0
    pieces_s: tuple[tuple[float, float], ...] = ()

    @property
    def duration_s(self) -> float:
        """Time covered: last - first sample time + one sample period."""
        return float(self.end_s - self.start_s + self.sample_period_s)

    @property
    def gravity_dir(self) -> np.ndarray:
        """Unit gravity direction in the body frame (level = (0, 0, +1), FRD)."""
        return -self.accel_dir

    @property
    def n_accel(self) -> dict[int, int]:
        return {k: int(v.shape[0]) for k, v in self.accel_mps2.items()}

    @property
    def n_mag(self) -> dict[int, int]:
        return {k: int(v.shape[0]) for k, v in self.mag_mgauss.items()}


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

    intervals: tuple[StillInterval, ...]
    coverage: Coverage
    config: StillConfig
    sample_rate_hz: float
    window_samples: int
    used_gyro: bool
    used_mag: bool
    accel_instances: tuple[int, ...] = ()
    mag_instances: tuple[int, ...] = ()
    warnings: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.intervals)

    def accel_arrays(self, instance: int = 0) -> list[np.ndarray]:
        """Per interval the (n_i, 3) accel samples of ``instance`` (m/s^2)."""
        return [iv.accel_mps2.get(instance, np.empty((0, 3))) for iv in self.intervals]

    def mag_arrays(self, instance: int = 0) -> list[np.ndarray]:
        """Per interval the (n_i, 3) mag samples of ``instance`` (mGauss)."""
        return [iv.mag_mgauss.get(instance, np.empty((0, 3))) for iv in self.intervals]


# --------------------------------------------------------------------------- helpers

def _collect(data) -> tuple[list[SensorSeries], list[SensorSeries], list[SensorSeries]]:
    """accel, mag, gyro series of a RawImu, an ImuLog, or a sequence of SensorSeries."""
    if hasattr(data, "accel") and hasattr(data, "mag"):
        return list(data.accel), list(data.mag), list(getattr(data, "gyro", ()))
    series = list(data.series) if hasattr(data, "series") else list(data)
    by: dict[str, list[SensorSeries]] = {"accel": [], "mag": [], "gyro": []}
    for s in series:
        by[s.sensor].append(s)
    return by["accel"], by["mag"], by["gyro"]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.sqrt(v.dot(v))  # what np.linalg.norm computes for a 1-d float vector, without its overhead
    return v / n if n > 0 else v


def _angle_deg(a: np.ndarray | None, b: np.ndarray | None) -> float:
    if a is None or b is None:
        return 0.0
    return float(np.degrees(np.arccos(np.clip(np.dot(_unit(a), _unit(b)), -1.0, 1.0))))


# --------------------------------------------------------------------------- detection

def _still_windows(t: np.ndarray, acc: np.ndarray, gyro: tuple[np.ndarray, np.ndarray | SensorSeries] | None,
                   mag: tuple[np.ndarray, np.ndarray] | None, w: int, cfg: StillConfig) -> np.ndarray:
    """Per window start i (window = samples i..i+w-1 of accel 0): is the window still."""
    n = len(t)
    if n < w:
        return np.zeros(0, dtype=bool)
    ok = rolling_sd_max(acc, w) < cfg.accel_std_mps2
    t0, t1 = t[:n - w + 1], t[w - 1:]  # per window start i: t[i], t[i + w - 1]
    if gyro is not None:
        ok &= gyro_still(gyro[0], gyro[1], t0, t1, cfg.gyro_rad_s, w if same_times(gyro[0], t) else None)
    if mag is not None:
        cnt, s1, s2 = window_sums(mag[0], mag[1], t0, t1)
        m = s1 / np.maximum(cnt, 1)[:, None]
        var = np.maximum(s2 / np.maximum(cnt, 1)[:, None] - m * m, 0.0)
        # windows with < 2 mag samples carry no information: do not veto
        ok &= np.where(cnt >= 2, np.sqrt(var).max(axis=1) < cfg.mag_std_mgauss, True)
    if np.any(ok):
        norm = norms(acc)
        med = float(np.median(norm[covered(ok, w, n)], overwrite_input=True))  # the median of a copy
        bad = np.abs(norm - med) > cfg.accel_norm_tol * med
        del norm
        cb = np.zeros(n + 1, dtype=np.int32 if n < 2**31 else np.int64)  # bad samples before each index
        np.cumsum(bad, out=cb[1:])
        ok &= cb[w:] == cb[:n - w + 1]  # no bad sample in the window
    return ok


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[i0, i1) index ranges of True runs."""
    m = np.concatenate([[False], mask, [False]])
    return list(zip(np.flatnonzero(m[1:] & ~m[:-1]).tolist(), np.flatnonzero(~m[1:] & m[:-1]).tolist()))


@dataclass(frozen=True, eq=False)
class _Reference:
    """Accelerometer 0 (time-sorted, finite samples): the time base of the detector."""

    series: SensorSeries
    t: np.ndarray
    a: np.ndarray
    dt: float
    rate_hz: float
    w: int


def _reference(accel: Sequence[SensorSeries], cfg: StillConfig) -> _Reference:
    ref = min(accel, key=lambda s: s.instance)
    t, a = ref.time_s, ref.values
    if not (len(t) < 2 or bool(np.all(t[1:] >= t[:-1]))):  # sorted (no NaN): the stable sort is the identity
        order = np.argsort(t, kind="stable")
        t, a = t[order], a[order]
    if not np.isfinite(np.sum(a)):  # some value is not finite (else the sum is finite)
        good = np.isfinite(a).all(axis=1)
        t, a = t[good], a[good]
    dt_all = np.diff(t)
    pos = dt_all if (len(dt_all) and dt_all.min() > 0) else dt_all[dt_all > 0]  # (increasing: all of them)
    del dt_all
    dt = float(np.median(pos, overwrite_input=True)) if len(pos) else 1.0  # (pos is our own array)
    del pos
    rate = 1.0 / dt if dt > 0 else 0.0
    w = max(int(cfg.min_window_samples), int(round(cfg.window_s * rate)))
    return _Reference(ref, t, a, dt, rate, w)


def _sorted_finite(s: SensorSeries) -> tuple[np.ndarray, np.ndarray]:
    """Time-sorted (stable) times and values of the finite samples of ``s`` (the series' own
    arrays, no copy, when they are sorted and finite already: the usual case)."""
    t, v = s.time_s, s.values
    if len(t) > 1 and bool(np.any(t[1:] < t[:-1])):
        o = np.argsort(t, kind="stable")
        t, v = t[o], v[o]
    if np.isfinite(np.sum(v)):  # every value finite (a NaN or an infinity makes the sum non-finite)
        return t, v
    good = np.isfinite(v).all(axis=1)
    return (t, v) if good.all() else (t[good], v[good])


def _still_runs(ok: np.ndarray, w: int) -> list[tuple[int, int]]:
    """Sample ranges [s0, s1) covered by runs of consecutive still windows.

    Runs separated by a moving window overlap in samples: the later one starts where the
    earlier one ends."""
    runs: list[tuple[int, int]] = []
    for r0, r1 in _runs(ok):
        s0, s1 = int(r0), int(r1 - 1 + w)
        if runs and s0 < runs[-1][1]:
            s0 = runs[-1][1]
        if s1 > s0:
            runs.append((s0, s1))
    return runs


def _trimmed(runs: Sequence[tuple[int, int]], dt: float, cfg: StillConfig) -> list[tuple[int, int]]:
    """Runs less ``trim_s`` at each edge that still hold enough samples and time."""
    trim = int(np.floor(cfg.trim_s / dt + 1e-9)) if dt > 0 else 0
    spans: list[tuple[int, int]] = []
    for r0, r1 in runs:
        i0, i1 = r0 + trim, r1 - trim
        if i1 - i0 < cfg.min_samples or (i1 - i0) * dt < cfg.min_duration_s - 1e-9:
            continue
        spans.append((int(i0), int(i1)))
    return spans


class _Directions:
    """Sums of the accel-0 samples of each span and of the mag-0 samples within half a sample
    period of it (used to decide merges): the running sums at the span edges only, computed a
    chunk at a time (the values of full-length prefix sums, without holding them)."""

    def __init__(self, ref: _Reference, R_b: np.ndarray, mag: tuple[np.ndarray, np.ndarray] | None,
                 spans: Sequence[tuple[int, int]]) -> None:
        self.R_b = R_b
        edges = np.asarray(spans, dtype=np.int64).reshape(-1, 2)
        ia = np.unique(edges)
        ca = prefix_at(ref.a, ia)
        sums = ca[np.searchsorted(ia, edges[:, 1])] - ca[np.searchsorted(ia, edges[:, 0])]
        keys = [(i0, i1) for i0, i1 in edges.tolist()]
        self._accel = dict(zip(keys, sums))
        self._field: dict[tuple[int, int], np.ndarray] | None = None
        if mag is not None:
            half = ref.dt / 2
            j0 = np.searchsorted(mag[0], ref.t[edges[:, 0]] - half, side="left")
            j1 = np.searchsorted(mag[0], ref.t[edges[:, 1] - 1] + half, side="right")
            jm = np.unique(np.concatenate([j0, j1]))
            cm = prefix_at(mag[1], jm)
            self._field = dict(zip(keys, cm[np.searchsorted(jm, j1)] - cm[np.searchsorted(jm, j0)]))

    def accel_sum(self, i0: int, i1: int) -> np.ndarray:
        """Sum of the accel-0 samples [i0, i1) of a span."""
        return self._accel[(i0, i1)]

    def field_sum(self, i0: int, i1: int) -> np.ndarray | None:
        """Sum of the mag-0 samples within half a sample period of the span (None: no compass)."""
        return None if self._field is None else self._field[(i0, i1)]


def _field_angle_deg(a: np.ndarray | None, b: np.ndarray | None) -> float:
    """Angle between two field sums; 0 (no veto) when either has no samples."""
    if a is None or b is None or not np.any(a) or not np.any(b):
        return 0.0
    return _angle_deg(a, b)


def _merge(spans: Sequence[tuple[int, int]], t: np.ndarray, dirs: _Directions,
           cfg: StillConfig) -> list[list[tuple[int, int]]]:
    """Group neighbouring spans in the same orientation (gravity and field within
    ``merge_deg``, gap at most ``merge_gap_s``): one list of spans per interval.

    The spans of a group stay apart, so that the motion between them is in no sensor's
    samples; a span is compared with the still samples of the group so far (running sums,
    O(1) per span)."""
    groups: list[list[tuple[int, int]]] = []
    sums: list[tuple[np.ndarray, np.ndarray | None]] = []  # per group: accel-0 sum, mag-0 sum
    for sp in spans:
        a_sp, m_sp = dirs.accel_sum(*sp), dirs.field_sum(*sp)
        if groups:
            a_g, m_g = sums[-1]
            gap = t[sp[0]] - t[groups[-1][-1][1] - 1]
            if (gap <= cfg.merge_gap_s and _angle_deg(dirs.R_b @ a_g, dirs.R_b @ a_sp) < cfg.merge_deg
                    and _field_angle_deg(m_g, m_sp) < cfg.merge_deg):
                groups[-1].append(sp)
                sums[-1] = (a_g + a_sp, None if m_g is None or m_sp is None else m_g + m_sp)
                continue
        groups.append([sp])
        sums.append((a_sp, m_sp))
    return groups


def _pieces(vs: np.ndarray, i0: Sequence[int], i1: Sequence[int]) -> np.ndarray:
    """Rows ``vs[i0[k]:i1[k]]`` of every span k of an interval, in time order."""
    parts = [vs[a:b] for a, b in zip(i0, i1)]
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _intervals(groups: Sequence[Sequence[tuple[int, int]]], ref: _Reference,
               accels: Mapping[int, tuple[np.ndarray, np.ndarray] | None],
               mags: Mapping[int, tuple[np.ndarray, np.ndarray]], R_b: np.ndarray,
               mag0: int | None) -> list[StillInterval]:
    """The StillIntervals of the merged span groups. Every sensor keeps only the samples of
    the still spans of its group: the reference (None in ``accels``) its samples of the spans,
    the other accelerometers and the compasses theirs whose time (sorted) lies within half a
    sample period of a span (the same time mask for every sensor; one sorted search per
    sensor for all spans); the motion between merged spans is in no sensor's samples.

    The means are those of ``ndarray.mean`` (``add.reduce`` over the rows, divided by their
    count), the unit vectors those of :func:`_unit`."""
    t, a, dt = ref.t, ref.a, ref.dt
    edges = np.array([sp for spans in groups for sp in spans], dtype=np.int64).reshape(-1, 2)
    lo, hi = t[edges[:, 0]] - dt / 2, t[edges[:, 1] - 1] + dt / 2
    t_first, t_last = t[edges[:, 0]].tolist(), t[edges[:, 1] - 1].tolist()
    rows: dict[tuple[str, int], tuple[np.ndarray, list[int], list[int]]] = {
        ("a", inst): (tv[1], np.searchsorted(tv[0], lo, side="left").tolist(),
                      np.searchsorted(tv[0], hi, side="right").tolist())
        for inst, tv in accels.items() if tv is not None}
    rows.update({("m", inst): (vs, np.searchsorted(ts, lo, side="left").tolist(),
                               np.searchsorted(ts, hi, side="right").tolist())
                 for inst, (ts, vs) in mags.items()})
    keys = [("a", inst) if tv is not None else None for inst, tv in accels.items()]
    out: list[StillInterval] = []
    k0 = 0
    for spans in groups:
        k1 = k0 + len(spans)
        if len(spans) == 1:
            a_ref = a[spans[0][0]:spans[0][1]]
            cut = {key: vs[i0[k0]:i1[k0]] for key, (vs, i0, i1) in rows.items()}
        else:
            a_ref = np.concatenate([a[s0:s1] for s0, s1 in spans])
            cut = {key: _pieces(vs, i0[k0:k1], i1[k0:k1]) for key, (vs, i0, i1) in rows.items()}
        am = {inst: a_ref if key is None else cut[key] for inst, key in zip(accels, keys)}
        mm = {inst: cut["m", inst] for inst in mags}
        field = None
        if mag0 is not None and len(mm[mag0]):
            field = _unit(np.add.reduce(mm[mag0], axis=0) / len(mm[mag0]))
        pieces = tuple(zip(t_first[k0:k1], t_last[k0:k1]))
        out.append(StillInterval(pieces[0][0], pieces[-1][1], am, mm,
                                 _unit(R_b @ (np.add.reduce(a_ref, axis=0) / len(a_ref))), field, dt, pieces))
        k0 = k1
    return out


def find_still_intervals(data, config: StillConfig = StillConfig(),
                         board_rotation: np.ndarray | None = None) -> Segmentation:
    """Find the still intervals of a recording and diagnose their coverage.

    Parameters
    ----------
    data : RawImu, ImuLog, or sequence of SensorSeries
        Accel (m/s^2), mag (mGauss) and optional gyro (rad/s) series of any instances.
        Raw data from the autopilot model's ``recover_raw`` is the usual input.
        Non-finite samples (e.g. readings whose calibration was unknown) are left out.
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
    gyro = [s for s in gyro if len(s) and s.any_nonzero()]
    if not accel:
        raise SegmentationError("no accelerometer data: still intervals cannot be detected")
    if board_rotation is None:
        board_rotation = getattr(data, "board_rotation", None)
    R_b = np.eye(3) if board_rotation is None else np.asarray(board_rotation, dtype=float)
    ref = _reference(accel, cfg)
    g_ser = min(gyro, key=lambda s: s.instance) if (gyro and cfg.use_gyro) else None
    gy = (g_ser.time_s, g_ser) if g_ser is not None else None  # (its rates read a chunk at a time)
    mags = {s.instance: _sorted_finite(s) for s in mag}
    mag0 = min(mags) if mags else None
    mg = mags[mag0] if (cfg.use_mag and gy is None and mag0 is not None) else None
    ok = _still_windows(ref.t, ref.a, gy, mg, ref.w, cfg)
    runs = _still_runs(ok, ref.w)
    warnings: list[str] = []
    if len(ref.t) < ref.w:
        warnings.append(f"only {len(ref.t)} accelerometer samples ({len(ref.t) * ref.dt:.1f} s): too short for a "
                        f"{ref.w}-sample window")
    spans = _trimmed(runs, ref.dt, cfg)
    dirs = _Directions(ref, R_b, None if mag0 is None else mags[mag0], spans)
    groups = _merge(spans, ref.t, dirs, cfg)
    others = {s.instance: None if s is ref.series else _sorted_finite(s) for s in accel}
    intervals = _intervals(groups, ref, others, mags, R_b, mag0)
    return _finish(intervals, cfg, ref, gy is not None, mg is not None, accel, mag, warnings)


def _finish(intervals: list[StillInterval], cfg: StillConfig, ref: _Reference, used_gyro: bool, used_mag: bool,
            accel: Sequence[SensorSeries], mag: Sequence[SensorSeries], warnings: list[str]) -> Segmentation:
    """Diagnose coverage, collect the warnings and build the Segmentation."""
    cov = diagnose_coverage(np.array([iv.gravity_dir for iv in intervals]).reshape(-1, 3), cfg.cluster_deg)
    for s in mag:
        empty = sum(1 for iv in intervals if iv.mag_mgauss.get(s.instance, np.empty((0, 3))).shape[0] == 0)
        if empty:
            warnings.append(f"mag {s.instance}: no samples in {empty} of {len(intervals)} intervals")
    all_w = tuple(warnings) + cov.messages
    for m in all_w:
        log.info("%s", m)
    return Segmentation(tuple(intervals), cov, cfg, ref.rate_hz, ref.w, used_gyro, used_mag,
                        tuple(sorted(s.instance for s in accel)), tuple(sorted(s.instance for s in mag)), all_w)
