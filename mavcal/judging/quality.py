"""Quality stage: how good a calibration is, in the units a pilot cares about.

* :func:`truth_functions`: raw-reading functions of an estimated sensor model (the
  paper's Eq. ``sensor_reading_model``, ``u = K R g + b``) in the engine frame, so that
  the written parameters (in the common form, :mod:`mavcal.autopilot.calform`) can be judged against it;
* :func:`quality_of`: the 95 % bounds of the heading and tilt error over the flight
  envelope, propagating the parameter covariance (draws of
  :func:`mavcal.core.uncertainty.sample_parameters`);
* :func:`holdout_errors`: the held-out reconstruction error (leave-one-interval-out, K-fold
  on long logs);
* :func:`accel_tilt_bounds`: an accelerometer's own 95 % tilt bound, from its fit alone
  (:mod:`mavcal.core.accel_fit`), so that no compass's misfit enters its verdict.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mavcal.autopilot import calform as fw
from mavcal.autopilot.evaluate import GridErrors, attitude_errors, attitude_grid
from mavcal.autopilot.mapping import AccelMapping, CompassMapping, accel_frame
from mavcal.core.accel_fit import AccelFit, holdout_folds, pool_index, sample_accel
from mavcal.core.calibrate import calibrate
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.core.models import MODELS
from mavcal.core.reconstruct import orientations_from_means
from mavcal.core.stats import IntervalStats, interval_means, interval_stats, stats_subset
from mavcal.core.types import Calibration
from mavcal.core.uncertainty import sample_parameters
from mavcal.errors import MavcalError

log = logging.getLogger(__name__)

__all__ = ["Quality", "quality_of", "truth_functions", "holdout_errors", "holdout_part", "holdout_rms",
           "HoldoutPart", "accel_tilt_bounds"]

RawFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Quality:
    """How good the result is, in the units a pilot cares about."""

    heading_95_deg: float  # 95 % bound of the max heading error over the flight envelope
    tilt_95_deg: float
    heading_nominal_deg: float  # what the dropped terms alone cause (at the estimate)
    tilt_nominal_deg: float
    holdout_accel_mps2: float  # RMS held-out reconstruction error (holdout_errors)
    holdout_mag_mgauss: float
    chi2_dof: float
    #: within reach with an accelerometer whose Z scale is the factory's (level-calibrated, never calibrated or
    #: contradicted): the 95 % heading bound over tilts up to 30 deg, beyond the poses', through the
    #: accelerometer's tilt or with the attitude known, whichever is worse (NaN: not computed)
    heading_95_steep_deg: float = float("nan")


def truth_functions(K_a: np.ndarray, b_a: np.ndarray, K_m: np.ndarray, b_m: np.ndarray, h: np.ndarray,
                    board_rot: np.ndarray, R_old: np.ndarray, field_norm: float) -> tuple[RawFn, RawFn]:
    """Raw-reading functions of a sensor model in the engine frame (for error propagation).

    Returns ``(raw_accel(f_body m/s^2), raw_mag(B_body mGauss))``: the readings
    ``K_a R g + b_a`` and ``K_m R h + b_m`` (paper Eq. ``sensor_reading_model``) for a
    specific force / field given in the body frame, the compass ones in its sensor frame
    (``R_old^T``), the field scaled from ``field_norm`` to the model's ``|h|``.
    """
    _, _, P = accel_frame(K_a)
    to_E = (board_rot @ P).T  # body -> E
    h_norm = float(np.linalg.norm(h))

    def raw_accel(f_body: np.ndarray) -> np.ndarray:
        return (f_body @ to_E.T / GRAVITY_MPS2) @ K_a.T + b_a

    def raw_mag(B_body: np.ndarray) -> np.ndarray:
        b = (B_body @ to_E.T) * (h_norm / field_norm) @ K_m.T + b_m
        return b @ R_old  # R_old^T b, the sensor frame

    return raw_accel, raw_mag


def _max_tilt_deg(K_a: np.ndarray, b_a: np.ndarray, written: fw.AccelCal, board_rot: np.ndarray,
                  f_body: np.ndarray) -> np.ndarray:
    """Largest angle between the specific force ``f_body`` (M, 3) and what ``written`` makes of
    the readings ``K_a R g + b_a`` (paper Eq. ``sensor_reading_model``) of that force, for each
    of D accelerometer models ``K_a`` (D, 3, 3), ``b_a`` (D, 3) at once: (D,) degrees, each
    to the last bit what the model alone gives (row-by-row arithmetic, the dot product and norm
    summed x + y + z in that order as ``np.sum(axis=1)`` and ``np.linalg.norm`` do)."""
    D, M = len(K_a), len(f_body)
    to_E_T = np.empty((D, 3, 3))
    for k in range(D):
        to_E_T[k] = board_rot @ accel_frame(K_a[k])[2]  # (engine -> body)^T
    raw = (f_body @ to_E_T / GRAVITY_MPS2) @ np.swapaxes(K_a, 1, 2) + b_a[:, None]
    a = fw.apply_accel(written, raw.reshape(-1, 3))
    a0, a1, a2 = a[:, 0].reshape(D, M), a[:, 1].reshape(D, M), a[:, 2].reshape(D, M)
    cos_t = (a0 * f_body[:, 0] + a1 * f_body[:, 1] + a2 * f_body[:, 2]) / (
        np.sqrt(a0 * a0 + a1 * a1 + a2 * a2) * GRAVITY_MPS2)
    return np.degrees(np.arccos(np.clip(cos_t, -1.0, 1.0))).max(axis=1)


def accel_tilt_bounds(fit: AccelFit, am: AccelMapping, draws: int, seed: int) -> tuple[float, float]:
    """(95 % bound, nominal) of the max tilt error over the flight envelope of the written
    accelerometer values ``am.new``, against ``draws`` samples of the accelerometer's own fit
    (tilt does not depend on heading: one yaw of the grid suffices)."""
    grid = attitude_grid()
    C = grid[::int(round(360 / 15))]  # yaw 0 of every roll/pitch
    f_body = np.swapaxes(C, 1, 2) @ np.array([0.0, 0.0, -GRAVITY_MPS2])
    board = am.old.board_matrix
    nominal = float(_max_tilt_deg(fit.gain[None], np.asarray(fit.bias, float)[None], am.new, board, f_body)[0])
    sampled = sample_accel(fit, draws, np.random.default_rng(seed))
    if not sampled:
        return nominal, nominal
    ts = _max_tilt_deg(np.array([K for K, _ in sampled]), np.array([b for _, b in sampled]), am.new, board, f_body)
    return float(np.percentile(ts, 95)), nominal


def quality_of(cal: Calibration, am: AccelMapping, cm: CompassMapping, board_rot: np.ndarray,
               draws: int, seed: int, holdout: tuple[float, float], max_tilt_deg: float = 45.0,
               attitude_known: bool = False) -> Quality:
    """Heading/tilt error bounds of the written parameters ``am``/``cm`` against ``cal``
    and ``draws`` samples of its parameter distribution, over the attitudes flown (roll and
    pitch up to ``max_tilt_deg``, every heading); ``holdout`` is :func:`holdout_errors`'
    (accel m/s^2, compass mGauss). ``attitude_known``: each draw's heading error is the larger of
    the one through the accelerometer's tilt and the compass's own (the attitude known, as an
    autopilot flying has it from its filter)."""
    grid = attitude_grid(max_tilt_deg=max_tilt_deg)
    incl = np.radians(cm.inclination_deg)
    B_ned = cm.field_mgauss * np.array([np.cos(incl), 0.0, np.sin(incl)])
    R_old = cm.old.mount_matrix

    def errs(d):
        ra, rm = truth_functions(d["K_a"], d["b_a"], d["K_m"], d["b_m"], d["h"], board_rot, R_old, cm.field_mgauss)
        return attitude_errors(ra, rm, am.new, cm.new, B_ned, grid)

    nominal = errs({"K_a": cal.accel.gain, "b_a": cal.accel.bias, "K_m": cal.mag.gain, "b_m": cal.mag.bias,
                    "h": cal.field})
    hs, ts = _draw_maxima(sample_parameters(cal, draws, np.random.default_rng(seed)), am, cm, board_rot, B_ned, grid,
                          attitude_known)
    chi2 = cal.cost / cal.dof if cal.dof > 0 else float("nan")
    return Quality(heading_95_deg=float(np.percentile(hs, 95)) if hs else nominal.max_heading_deg,
                   tilt_95_deg=float(np.percentile(ts, 95)) if ts else nominal.max_tilt_deg,
                   heading_nominal_deg=nominal.max_heading_deg, tilt_nominal_deg=nominal.max_tilt_deg,
                   holdout_accel_mps2=holdout[0], holdout_mag_mgauss=holdout[1], chi2_dof=float(chi2))


DRAW_CHUNK = 16  # draws evaluated together: fewer calls, arrays still small enough for the cache


def _draw_maxima(draws: list[dict], am: AccelMapping, cm: CompassMapping, board_rot: np.ndarray,
                 B_ned: np.ndarray, grid: np.ndarray, attitude_known: bool = False) -> tuple[list[float], list[float]]:
    """Max heading and max tilt error over ``grid`` for every draw: what
    :func:`mavcal.autopilot.evaluate.attitude_errors` gives draw by draw (to the last bit),
    ``DRAW_CHUNK`` draws at a time by :class:`mavcal.autopilot.evaluate.GridErrors` (the grid's
    truth once for all chunks, the accelerometer's readings at its distinct specific forces)."""
    max_errors = GridErrors(am.new, cm.new, B_ned, grid)
    f_unique, B_body = max_errors.f_unique, max_errors.B_body
    hs: list[float] = []
    ts: list[float] = []
    for c0 in range(0, len(draws), DRAW_CHUNK):
        chunk = draws[c0:c0 + DRAW_CHUNK]
        raw_a = np.empty((len(chunk), len(f_unique), 3))
        raw_m = np.empty((len(chunk), len(B_body), 3))
        for k, d in enumerate(chunk):
            ra, rm = truth_functions(d["K_a"], d["b_a"], d["K_m"], d["b_m"], d["h"], board_rot,
                                     cm.old.mount_matrix, cm.field_mgauss)
            raw_a[k], raw_m[k] = ra(f_unique), rm(B_body)
        h, t = max_errors.at_unique(raw_a, raw_m)
        if attitude_known:
            h = np.maximum(h, max_errors.compass_only(raw_m))
        hs += [float(x) for x in h]
        ts += [float(x) for x in t]
    return hs, ts


def holdout_errors(acc: Sequence[np.ndarray], mag: Sequence[np.ndarray], cal: Calibration, *,
                   method: str = "ncar", tol: float = 1e-4, seed: int = 0,
                   noise_floor: tuple[float | None, float | None] = (None, None),
                   cluster_deg: float = 30.0, stats: tuple[IntervalStats, IntervalStats] | None = None
                   ) -> tuple[float, float]:
    """RMS held-out error: refit without some intervals, predict their means
    (:func:`holdout_part` of all the refits, then :func:`holdout_rms`)."""
    return holdout_rms([holdout_part(acc, mag, cal, method=method, tol=tol, seed=seed, noise_floor=noise_floor,
                                     cluster_deg=cluster_deg, stats=stats)])


HoldoutPart = tuple[list[float], list[float]] | None  # the accel and compass errors of some refits


def holdout_rms(parts: Sequence[HoldoutPart]) -> tuple[float, float]:
    """The RMS accel (m/s^2) and compass (mGauss) held-out errors of :func:`holdout_part`'s
    parts, given in order (all of them: then the number is :func:`holdout_errors`', to the
    bit); NaN when the check could not run or predicted nothing."""
    if not parts or any(p is None for p in parts):
        return float("nan"), float("nan")
    ea = [e for p in parts if p is not None for e in p[0]]
    em = [e for p in parts if p is not None for e in p[1]]
    if not ea:
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(np.square(ea)))), float(np.sqrt(np.mean(np.square(em))))


def holdout_part(acc: Sequence[np.ndarray], mag: Sequence[np.ndarray], cal: Calibration, *,
                 part: tuple[int, int] = (0, 1), method: str = "ncar", tol: float = 1e-4, seed: int = 0,
                 noise_floor: tuple[float | None, float | None] = (None, None),
                 cluster_deg: float = 30.0, stats: tuple[IntervalStats, IntervalStats] | None = None
                 ) -> HoldoutPart:
    """The held-out errors of the ``k``-th of ``K`` consecutive slices of the refits
    (``part = (k, K)``; the default is all of them), so that the refits can run in separate
    processes; None when the check cannot run (too few intervals, no interval whose pose
    recurs). :func:`holdout_rms` of all the parts is the held-out error.

    The refits are :func:`mavcal.core.accel_fit.holdout_folds`': leave-one-interval-out up
    to :data:`~mavcal.core.accel_fit.LOO_MAX_INTERVALS` intervals, else
    :data:`~mavcal.core.accel_fit.HOLDOUT_FOLDS`-fold over at most
    :data:`~mavcal.core.accel_fit.HOLDOUT_POOL_MAX` intervals evenly spaced in the log, so
    the cost is bounded (ten refits of at most that many intervals) where leave-one-out
    would be one refit of N per interval (its docstring says why the number keeps its
    meaning). Only intervals whose gravity direction is seen again in an interval the refit
    keeps (within ``cluster_deg``) are predicted: leaving out the only pose on one side
    makes the rest extrapolate, which measures the pose plan rather than the fit. NaN when
    none qualifies. The prediction is the paper's model ``K R_j g + b`` (Eq.
    ``sensor_reading_model``) with R_j estimated from interval j alone.

    Every refit, leave-one-out or K-fold, is warm-started from ``cal``
    (``calibrate(..., start=cal)``: no search, at its point when it converged, i.e. also its
    orientations of the kept intervals (``start_orientations``: the same optimum as from
    orientations computed afresh, to the refinement's tolerance), then the
    joint refinement on the kept intervals alone, its LM bounded: 100 iterations per run,
    no 2000-iteration extension), from statistics computed once for all intervals
    (:func:`~mavcal.core.stats.stats_subset`). This keeps the held-out meaning: each refit
    still minimises the cost of the intervals it keeps, never seeing the ones it predicts;
    the start only selects the basin, the one the full fit found (a fit from scratch on
    all but one of the same poses lands in it too, at 10-30 times the cost: the same
    optimum, the same digits). A refit whose LM stops at its bound before converging (a
    fit that does not converge from scratch either, e.g. a disturbed compass) is still a
    prediction from data that excluded the predicted interval, near that data's optimum;
    the unbounded search would spend seconds per interval polishing it to digits the
    gate does not read.

    ``stats``: the accelerometer's and compass's :func:`~mavcal.core.stats.interval_stats` of
    these intervals with ``per_interval=True`` (e.g. the fit's own): each refit's statistics
    are then taken from them (:func:`~mavcal.core.stats.stats_subset`, O(pool)) instead of
    from the readings. Where the refits use all N intervals (N <= ``HOLDOUT_POOL_MAX``) these
    are the same numbers; on longer logs they equal the pool's own statistics up to rounding
    (the means centred on all the readings rather than the pool's, the scatter summed
    interval by interval).
    """

    N = len(acc)
    if N - 1 < MODELS[cal.model].min_intervals:
        return None
    acc = [np.asarray(a, dtype=float) for a in acc]
    mag = [np.asarray(m, dtype=float) for m in mag]
    mu_a = interval_means(acc)  # each interval's mean once (the directions, the predictions' targets)
    dirs = mu_a / np.linalg.norm(mu_a, axis=1, keepdims=True)
    ea, em = [], []
    folds = holdout_folds(dirs, cluster_deg=cluster_deg)
    if not folds:
        return None
    try:
        sa, sm, at = _refit_stats(acc, mag, folds, noise_floor, stats)
    except MavcalError:
        return None
    k, K = part
    own_R = cal.n_intervals == N and cal.converged  # cal is these N intervals' optimum: its R_i start the refits
    for keep, pred in folds[k * len(folds) // K:(k + 1) * len(folds) // K]:
        try:
            cj = calibrate(stats_subset(sa, at[keep], "accel_sets"), stats_subset(sm, at[keep], "mag_sets"),
                           method=method, tol=tol, seed=seed, model=cal.model, start=cal,
                           start_orientations=cal.orientations[keep] if own_R else None)
        except MavcalError:
            continue
        mu_m = interval_means([mag[j] for j in pred])
        Rs = orientations_from_means(cj, mu_a[pred], np.array([len(acc[j]) for j in pred], dtype=float),
                                     mu_m, np.array([len(mag[j]) for j in pred], dtype=float))
        pa = cj.accel.gain @ Rs @ cj.gravity + cj.accel.bias  # K R_j g + b, interval by interval
        pm = cj.mag.gain @ Rs @ cj.field + cj.mag.bias
        ea += [np.linalg.norm(d) for d in mu_a[pred] - pa]  # a vector norm each (its own rounding)
        em += [np.linalg.norm(d) for d in mu_m - pm]
    return ea, em


def _refit_stats(acc: list[np.ndarray], mag: list[np.ndarray], folds: list[tuple[np.ndarray, np.ndarray]],
                 noise_floor: tuple[float | None, float | None],
                 stats: tuple[IntervalStats, IntervalStats] | None) -> tuple[IntervalStats, IntervalStats, np.ndarray]:
    """The statistics the refits of ``folds`` take their subsets from, and the position of each
    of the N intervals in them: ``stats`` (all N) when given with their per-interval scatter,
    else those of the pool of intervals the folds use, computed from the readings."""
    N = len(acc)
    if stats is not None and stats[0].interval_scatter is not None and stats[1].interval_scatter is not None:
        return stats[0], stats[1], np.arange(N)
    pool, at = pool_index(folds, N)
    sa = interval_stats([acc[i] for i in pool], "accel_sets", noise_floor=noise_floor[0], per_interval=True)
    sm = interval_stats([mag[i] for i in pool], "mag_sets", noise_floor=noise_floor[1], per_interval=True)
    return sa, sm, at
