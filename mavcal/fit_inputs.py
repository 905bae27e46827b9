"""What one recording's fits take from the prepared recording (:mod:`mavcal.fits`,
:mod:`mavcal.judging`): each sensor's readings in each still interval, the noise floor of
its telemetry quantisation, its interval statistics computed once per run, the coverage rule of
the gates, and the refusal's reason when the log holds calibration prompts without IMU data.
"""
from __future__ import annotations

import numpy as np

from mavcal.core.stats import IntervalStats, interval_stats
from mavcal.coverage import CoverageRule
from mavcal.errors import InsufficientDataError, MavcalError, SourceError
from mavcal.run import Options, Prepared
from mavcal.segment import Segmentation

__all__ = ["StatsCache", "sets", "noise_floor", "stats_of", "accel_sets", "wanted_instances", "coverage_rule",
           "blind_cal", "with_blind_cal"]

#: the run's interval statistics: (kind, instance, intervals used) -> statistics
StatsCache = dict[tuple[str, int, tuple[int, ...]], IntervalStats]


def sets(prep: Prepared, kind: str, inst: int, used: list[int]) -> list[np.ndarray]:
    """The readings of sensor ``kind`` ``inst`` in each still interval ``used``."""
    ivs = prep.segmentation.intervals
    return [ivs[k].accel_mps2[inst] if kind == "accel" else ivs[k].mag_mgauss[inst] for k in used]


def noise_floor(prep: Prepared, kind: str, inst: int) -> float | None:
    """The noise of the sensor's telemetry quantisation, step / sqrt(12) (None when not quantised)."""
    q = prep.quantization.get((kind, inst), 0.0)
    return q / np.sqrt(12) if q else None


def stats_of(prep: Prepared, cache: StatsCache, kind: str, inst: int, used: list[int]) -> IntervalStats:
    """The interval statistics (:func:`mavcal.core.stats.interval_stats`, per interval too) of
    sensor ``kind`` ``inst`` over the intervals ``used``, computed once per run: the pairs of
    one accelerometer or compass, its own fit and the held-out checks share them (the same
    numbers, to the bit, as each computing them from the readings)."""
    key = (kind, inst, tuple(used))
    if key not in cache:
        who = f"{'accelerometer' if kind == 'accel' else 'compass'} {inst}"  # a person's words, not the API's
        cache[key] = interval_stats(sets(prep, kind, inst, used), who,
                                    noise_floor=noise_floor(prep, kind, inst), per_interval=True)
    return cache[key]


def accel_sets(prep: Prepared, a: int) -> tuple[list[int], list[np.ndarray]]:
    """The still intervals with accelerometer ``a``'s readings (at least 2 samples) and those
    readings; SourceError/InsufficientDataError when it has none."""
    none = np.empty((0, 3))
    used = [k for k, iv in enumerate(prep.segmentation.intervals) if iv.accel_mps2.get(a, none).shape[0] >= 2]
    if prep.raw.get("accel", a) is None:
        raise SourceError(f"{prep.log.source}: no accelerometer {a} data")
    if not used:
        raise InsufficientDataError(f"{prep.log.source}: no still interval with accelerometer {a} data; "
                                    + "; ".join(list(prep.segmentation.coverage.messages) + blind_cal(prep)))
    return used, sets(prep, "accel", a, used)


def wanted_instances(instances, opts: Options, kind: str) -> list[int]:
    """The instances of sensor ``kind`` to calibrate: all of them, or ``opts.only_instances``."""
    inst = list(instances)
    if opts.sensors == kind and opts.only_instances is not None:
        inst = [i for i in inst if i in opts.only_instances]
    return inst


def coverage_rule(opts: Options, seg: Segmentation) -> CoverageRule:
    """The coverage rule (:mod:`mavcal.coverage`) of ``opts``' gates, with the segmentation's
    orientation clusters: what ``calibrate`` applies and ``segments`` reports."""
    c = opts.gates
    return CoverageRule(min_intervals=c.min_intervals, min_orientations=min(c.min_intervals, 6),
                        min_field_directions=c.min_field_directions, cluster_deg=seg.config.cluster_deg)


def blind_cal(prep: Prepared) -> list[str]:
    """The refusal's reason when the log holds calibration prompts but no IMU data during them."""
    return [f"the log holds ArduPilot's accelerometer calibration ({a:.1f}..{b:.1f} s: 'Place vehicle' prompts) "
            "but no IMU data during it (the ground station stopped streaming RAW_IMU?), so its poses are lost; "
            "record the IMU stream while calibrating" for a, b in prep.raw.accel_cal_without_imu]


def with_blind_cal(prep: Prepared, exc: MavcalError) -> MavcalError:
    """``exc``, or (when the log holds calibration prompts without IMU data) an
    InsufficientDataError that gives that reason as well."""
    return InsufficientDataError("; ".join([str(exc)] + blind_cal(prep))) if blind_cal(prep) else exc
