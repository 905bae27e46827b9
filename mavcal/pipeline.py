"""From a log or a live link to ArduPilot parameters: read -> raw recovery -> still
intervals -> joint calibration -> mapping -> quality -> gates.

:func:`calibrate_source` is what ``mavcal calibrate``, the capture command and the
MAVProxy module call. It never writes to a vehicle (that is :mod:`mavcal.link.writer`).
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

import mavcal
from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot import gates as gates_mod
from mavcal.ardupilot.evaluate import attitude_errors, attitude_grid
from mavcal.ardupilot.mapping import (
    AccelMapping,
    CompassMapping,
    ParamMapping,
    accel_frame,
    map_accel,
    map_compass,
)
from mavcal.ardupilot.recover import RawImu, recover_raw
from mavcal.core.types import Calibration
from mavcal.core.uncertainty import sample_parameters
from mavcal.errors import InsufficientDataError, MavcalError, SourceError
from mavcal.segment import Segmentation, StillConfig, find_still_intervals
from mavcal.sources.types import ImuLog

log = logging.getLogger(__name__)

G0 = fw.GRAVITY_MSS
REPORT_FORMAT = "mavcal report v1"


@dataclass(frozen=True)
class Options:
    """Everything :func:`calibrate_source` can be told (all optional)."""

    still: StillConfig = StillConfig()
    method: str = "ncar"
    tol: float = 1e-4
    model: str = "auto"
    seed: int = 0
    accel_instance: int = 0  # the primary pair: the board frame and the quality numbers
    mag_instance: int = 0
    all_instances: bool = True  # also every other IMU (with compass 0) and compass (with IMU 0)
    field_mgauss: Optional[float] = None
    location: Optional[Tuple[float, float, float]] = None
    orient_tol_deg: float = 1.0
    allow_custom: bool = True
    force_external: bool = False
    untruncate: bool = True
    uncertainty_draws: int = 200
    holdout: bool = True
    gates: gates_mod.GateConfig = gates_mod.GateConfig()


@dataclass(frozen=True)
class Quality:
    """How good the result is, in the units a pilot cares about."""

    heading_95_deg: float  # 95 % bound of the max heading error over the flight envelope
    tilt_95_deg: float
    heading_nominal_deg: float  # what the dropped terms alone cause (at the estimate)
    tilt_nominal_deg: float
    holdout_accel_mps2: float  # RMS leave-one-interval-out reconstruction error
    holdout_mag_mgauss: float
    chi2_dof: float


@dataclass(frozen=True, eq=False)
class CalibrationRun:
    """Everything one run produced."""

    source: str
    log: ImuLog
    raw: RawImu
    segmentation: Segmentation
    intervals_used: Tuple[int, ...]
    calibration: Calibration
    mapping: ParamMapping
    quality: Quality
    gates: gates_mod.GateReport
    params_before: Dict[str, float]
    warnings: Tuple[str, ...] = ()
    others: Tuple["CalibrationRun", ...] = ()  # the fits of the other instances (all_instances)

    @property
    def accepted(self) -> bool:
        return self.gates.passed

    def to_json(self) -> dict:
        return run_to_json(self)


# --------------------------------------------------------------------------- steps

def _field_magnitude(opts: Options, log_: ImuLog, raw_mag_means: np.ndarray, old: fw.CompassCal):
    """(|B| mGauss, source words, WMM inclination or None)."""
    incl = None
    loc = opts.location or log_.position
    if loc is not None:
        try:
            from mavcal.sources.wmm import field_at
            _, incl, intensity = field_at(loc[0], loc[1], loc[2] if len(loc) > 2 else 0.0)
        except Exception as exc:  # pragma: no cover - tables missing
            log.warning("World Magnetic Model unavailable: %s", exc)
            intensity = None
        if opts.field_mgauss is None and intensity:
            return float(intensity), f"World Magnetic Model at {loc[0]:.4f}, {loc[1]:.4f}", incl
    if opts.field_mgauss is not None:
        return float(opts.field_mgauss), "given", incl
    cur = fw.apply_compass(old, raw_mag_means, sensor_frame=False)
    return float(np.mean(np.linalg.norm(cur, axis=1))), "kept from the current calibration (no position)", incl


def _truth_functions(K_a, b_a, K_m, b_m, h, board_rot, R_old, field_norm):
    """Raw-reading functions of a sensor model in the engine frame (for error propagation)."""
    _, _, P = accel_frame(K_a)
    to_E = (board_rot @ P).T  # body -> E
    h_norm = float(np.linalg.norm(h))

    def raw_accel(f_body):
        return (f_body @ to_E.T / G0) @ K_a.T + b_a

    def raw_mag(B_body):
        b = (B_body @ to_E.T) * (h_norm / field_norm) @ K_m.T + b_m
        return b @ R_old  # R_old^T b, the sensor frame

    return raw_accel, raw_mag


def quality_of(cal: Calibration, am: AccelMapping, cm: CompassMapping, board_rot: np.ndarray,
               draws: int, seed: int, holdout: Tuple[float, float]) -> Quality:
    grid = attitude_grid()
    incl = np.radians(cm.inclination_deg)
    B_ned = cm.field_mgauss * np.array([np.cos(incl), 0.0, np.sin(incl)])
    R_old = cm.old.mount_matrix

    def errs(d):
        ra, rm = _truth_functions(d["K_a"], d["b_a"], d["K_m"], d["b_m"], d["h"], board_rot, R_old, cm.field_mgauss)
        return attitude_errors(ra, rm, am.new, cm.new, B_ned, grid)

    nominal = errs({"K_a": cal.accel.gain, "b_a": cal.accel.bias, "K_m": cal.mag.gain, "b_m": cal.mag.bias,
                    "h": cal.field})
    hs, ts = [], []
    for d in sample_parameters(cal, draws, np.random.default_rng(seed)):
        e = errs(d)
        hs.append(e.max_heading_deg)
        ts.append(e.max_tilt_deg)
    chi2 = cal.cost / cal.dof if cal.dof > 0 else float("nan")
    return Quality(heading_95_deg=float(np.percentile(hs, 95)) if hs else nominal.max_heading_deg,
                   tilt_95_deg=float(np.percentile(ts, 95)) if ts else nominal.max_tilt_deg,
                   heading_nominal_deg=nominal.max_heading_deg, tilt_nominal_deg=nominal.max_tilt_deg,
                   holdout_accel_mps2=holdout[0], holdout_mag_mgauss=holdout[1], chi2_dof=float(chi2))


def holdout_errors(acc: Sequence[np.ndarray], mag: Sequence[np.ndarray], cal: Calibration,
                   opts: Options, noise_floor, cluster_deg: float = 30.0) -> Tuple[float, float]:
    """RMS leave-one-interval-out error: refit without interval j, predict j's means.

    Only intervals whose gravity direction is seen again in another interval (within
    ``cluster_deg``) are held out: leaving out the only pose on one side makes the rest
    extrapolate, which measures the pose plan rather than the fit. NaN when none qualifies.
    """
    from mavcal.core.models import MODELS

    N = len(acc)
    if N - 1 < MODELS[cal.model].min_intervals:
        return float("nan"), float("nan")
    dirs = np.array([a.mean(0) for a in acc])
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    close = (dirs @ dirs.T) > np.cos(np.radians(cluster_deg))
    ea, em = [], []
    for j in range(N):
        if close[j].sum() < 2:
            continue
        keep = [i for i in range(N) if i != j]
        try:
            cj = mavcal.calibrate([acc[i] for i in keep], [mag[i] for i in keep], method=opts.method, tol=opts.tol,
                                  seed=opts.seed, model=cal.model, noise_floor=noise_floor)
        except mavcal.MavcalError:
            continue
        R = mavcal.estimate_orientations(cj, [acc[j]], [mag[j]])[0]
        pa = cj.accel.gain @ R @ cj.gravity + cj.accel.bias
        pm = cj.mag.gain @ R @ cj.field + cj.mag.bias
        ea.append(np.linalg.norm(acc[j].mean(0) - pa))
        em.append(np.linalg.norm(mag[j].mean(0) - pm))
    if not ea:
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(np.square(ea)))), float(np.sqrt(np.mean(np.square(em))))


@dataclass(frozen=True, eq=False)
class Prepared:
    """A log read, de-truncated, raw-recovered and segmented (the input of the fit)."""

    log: ImuLog
    raw: RawImu
    segmentation: Segmentation
    quantization: Dict[Tuple[str, int], float]
    warnings: Tuple[str, ...]


def prepare(source, options: Options = Options(), *, progress=None) -> Prepared:
    """Read (path, device string or ImuLog), undo integer truncation, recover raw readings
    and find the still intervals."""
    from mavcal.sources import open_source
    from mavcal.sources.quantization import quantization_step, untruncate_log

    opts = options
    log_ = source if isinstance(source, ImuLog) else open_source(str(source), progress=progress)
    warnings: List[str] = list(log_.warnings)
    steps = {(s.sensor, s.instance): quantization_step(s) for s in log_.series}
    if opts.untruncate:
        log_, _ = untruncate_log(log_)
    raw = recover_raw(log_)
    warnings += list(raw.warnings)
    seg = find_still_intervals(raw, opts.still)
    warnings += list(seg.warnings)
    return Prepared(log_, raw, seg, steps, tuple(warnings))


def calibrate_source(source, options: Options = Options(), *, progress=None) -> CalibrationRun:
    """Run the whole chain on a log path, a device string or an already read :class:`ImuLog`."""
    return calibrate_prepared(prepare(source, options, progress=progress), options)


def calibrate_prepared(prep: Prepared, options: Options = Options()) -> CalibrationRun:
    """The fit, mapping, quality and gates for a :class:`Prepared` recording.

    With ``options.all_instances`` every other accelerometer is calibrated jointly with
    compass ``mag_instance`` and every other compass jointly with accelerometer
    ``accel_instance`` (so all compasses are expressed in the primary IMU's board frame);
    their parameters and gates join the primary pair's. An instance without enough data
    is skipped with a warning.
    """
    primary = _calibrate_pair(prep, options)
    if not options.all_instances:
        return primary
    from dataclasses import replace as _replace

    ai, mi = options.accel_instance, options.mag_instance
    pairs = [(a, mi) for a in prep.raw.accel_instances() if a != ai] + \
            [(ai, m) for m in prep.raw.mag_instances() if m != mi]
    others, warnings = [], list(primary.warnings)
    for a, m in pairs:
        try:
            others.append(_calibrate_pair(prep, _replace(options, accel_instance=a, mag_instance=m, holdout=False)))
        except MavcalError as exc:
            warnings.append(f"accelerometer {a} / compass {m} not calibrated: {exc}")
    if not others:
        return _replace(primary, warnings=tuple(warnings))
    accel = list(primary.mapping.accel) + [r.mapping.accel[0] for r in others if r.mapping.accel[0].instance != ai]
    compass = list(primary.mapping.compass) + [r.mapping.compass[0] for r in others
                                               if r.mapping.compass[0].instance != mi]
    new, old = {}, {}
    for mp in accel:
        new.update(mp.params())
    for mp in compass:
        new.update(mp.params())
    for r in (primary,) + tuple(others):
        old.update(r.mapping.old)
    old = {n: old.get(n, primary.params_before.get(n)) for n in new}
    notes = list(primary.mapping.notes) + [f"compass {c.instance}: {c.orientation_note}" for c in compass[1:]]
    mapping = ParamMapping(accel=tuple(accel), compass=tuple(compass), new=new, old=old, notes=tuple(notes),
                           reboot_required=any(c.reboot_required for c in compass))
    gates = list(primary.gates.gates)
    for r in others:
        a, m = r.mapping.accel[0].instance, r.mapping.compass[0].instance
        for g in r.gates.gates:
            if g.sensor == f"accel{a}" and a != ai or g.sensor == f"compass{m}" and m != mi:
                gates.append(g)
            elif g.sensor == "data":
                gates.append(gates_mod.Gate(f"data (accel{a}+compass{m})", g.name, g.ok, g.value, g.limit, g.reason))
    return _replace(primary, mapping=mapping, gates=gates_mod.GateReport(tuple(gates)), others=tuple(others),
                    warnings=tuple(dict.fromkeys(warnings)))


def _calibrate_pair(prep: Prepared, options: Options) -> CalibrationRun:
    """The fit of one accelerometer/compass pair."""
    opts = options
    log_, raw, seg, steps = prep.log, prep.raw, prep.segmentation, prep.quantization
    warnings: List[str] = list(prep.warnings)
    ai, mi = opts.accel_instance, opts.mag_instance
    used = [k for k, iv in enumerate(seg.intervals)
            if iv.accel_mps2.get(ai, np.empty((0, 3))).shape[0] >= 2 and iv.mag_mgauss.get(mi, np.empty((0, 3))).shape[0] >= 2]
    if not used:
        if raw.get("accel", ai) is None:
            raise SourceError(f"{log_.source}: no accelerometer {ai} data")
        if raw.get("mag", mi) is None:
            raise SourceError(f"{log_.source}: no compass {mi} data")
        raise InsufficientDataError(f"{log_.source}: no still intervals found ({len(seg.intervals)} detected, none "
                                    "with both sensors); " + "; ".join(seg.coverage.messages))
    from mavcal.core.models import MODEL_CHAIN, MODELS
    n_min = MODELS[MODEL_CHAIN[-1]].min_intervals
    if len(used) < n_min:
        why = "; ".join(seg.coverage.messages) or f"{seg.coverage.n_orientations} distinct orientation(s)"
        raise InsufficientDataError(
            f"{log_.source}: {len(used)} still interval(s) with accelerometer {ai} and compass {mi} data; at least "
            f"{n_min} in different orientations are needed ({MODELS['full'].min_intervals} for the full model): {why}")
    acc = [seg.intervals[k].accel_mps2[ai] for k in used]
    mag = [seg.intervals[k].mag_mgauss[mi] for k in used]
    qa, qm = steps.get(("accel", ai), 0.0), steps.get(("mag", mi), 0.0)
    noise_floor = (qa / np.sqrt(12) if qa else None, qm / np.sqrt(12) if qm else None)
    cal = mavcal.calibrate(acc, mag, method=opts.method, tol=opts.tol, seed=opts.seed, model=opts.model,
                           noise_floor=noise_floor)
    params_now = log_.params.snapshot()
    if not params_now:
        warnings.append("the log has no parameters: readings were taken as raw and the old values are unknown")
    old_a = fw.accel_cal_from_params(params_now, ai)
    old_c = fw.compass_cal_from_params(params_now, mi)
    R_A = old_a.board_matrix
    mag_means = np.array([m.mean(0) for m in mag])
    field_norm, field_src, incl_model = _field_magnitude(opts, log_, mag_means, old_c)
    am = map_accel(cal.accel.gain, cal.accel.bias, old_a, ai)
    cm = map_compass(cal.mag.gain, cal.mag.bias, cal.h_z, am.frame_rotation, old_c, params_now, instance=mi,
                     field_mgauss=field_norm, field_source=field_src, board_rotation=R_A,
                     orient_tol_deg=opts.orient_tol_deg, allow_custom=opts.allow_custom,
                     force_external=opts.force_external, inclination_model_deg=incl_model)
    new = {**am.params(), **cm.params()}
    old = {n: (float(params_now[n]) if n in params_now else None) for n in new}
    notes = [cm.orientation_note]
    if am.dropped_tilt_deg > 0.01:
        notes.append(f"accelerometer cross-axis terms ArduPilot cannot hold: up to {am.dropped_tilt_deg:.3f} deg tilt, "
                     f"{am.dropped_magnitude_mps2:.3f} m/s^2")
    mapping = ParamMapping(accel=(am,), compass=(cm,), new=new, old=old, notes=tuple(notes),
                           reboot_required=cm.reboot_required)
    ho = holdout_errors(acc, mag, cal, opts, noise_floor) if opts.holdout else (float("nan"), float("nan"))
    quality = quality_of(cal, am, cm, R_A, opts.uncertainty_draws, opts.seed, ho)
    report = gates_mod.check(mapping, params_now, n_intervals=len(used), n_orientations=seg.coverage.n_orientations,
                             heading_95_deg=quality.heading_95_deg, tilt_95_deg=quality.tilt_95_deg,
                             holdout_accel_mps2=0.0 if np.isnan(ho[0]) else ho[0],
                             holdout_mag_mgauss=0.0 if np.isnan(ho[1]) else ho[1], config=opts.gates)
    return CalibrationRun(source=log_.source, log=log_, raw=raw, segmentation=seg, intervals_used=tuple(used),
                          calibration=cal, mapping=mapping, quality=quality, gates=report, params_before=params_now,
                          warnings=tuple(dict.fromkeys(warnings)))


# --------------------------------------------------------------------------- report

def _f(x):
    if isinstance(x, (np.floating, float)):
        return None if not np.isfinite(x) else float(x)
    if isinstance(x, np.ndarray):
        return [_f(v) for v in x.tolist()] if x.ndim else _f(float(x))
    if isinstance(x, (list, tuple)):
        return [_f(v) for v in x]
    return x


def run_to_json(run: CalibrationRun) -> dict:
    cal = run.calibration
    q = run.quality
    am, cm = run.mapping.accel[0], run.mapping.compass[0]
    seg = run.segmentation
    return {
        "format": REPORT_FORMAT,
        "mavcal_version": mavcal.__version__,
        "source": run.source,
        "accepted": run.accepted,
        "parameters": {n: {"old": _f(run.mapping.old.get(n)), "new": _f(v),
                           "changed": bool(run.mapping.old.get(n) is None or np.float32(v) != np.float32(run.mapping.old[n]))}
                       for n, v in sorted(run.mapping.new.items())},
        "reboot_required": run.mapping.reboot_required,
        "quality": {k: _f(v) for k, v in q.__dict__.items()},
        "gates": [{"sensor": g.sensor, "name": g.name, "ok": g.ok, "value": _f(g.value), "limit": g.limit,
                   "reason": g.reason} for g in run.gates.gates],
        "dropped": {
            "accel_cross_axis": _f(am.cross_axis), "accel_tilt_deg": am.dropped_tilt_deg,
            "accel_magnitude_mps2": am.dropped_magnitude_mps2,
            "compass_residual_rotation_deg": cm.residual_rotation_deg,
            "compass_motor_compensation": "unchanged (still poses cannot observe it)",
        },
        "compass": {"instance": cm.instance, "external": cm.external, "orientation": cm.orientation_note,
                    "rotation_deg": cm.rotation_deg, "field_mgauss": cm.field_mgauss, "field_source": cm.field_source,
                    "inclination_deg": cm.inclination_deg, "inclination_model_deg": _f(cm.inclination_model_deg),
                    "inclination_difference_deg": (None if cm.inclination_model_deg is None
                                                   else cm.inclination_deg - cm.inclination_model_deg)},
        "calibration": {"model": cal.model, "model_reason": cal.model_reason, "method": cal.method,
                        "cost": cal.cost, "dof": cal.dof, "converged": cal.converged, "message": cal.message,
                        "K_a": _f(cal.accel.gain), "b_a": _f(cal.accel.bias), "K_m": _f(cal.mag.gain),
                        "b_m": _f(cal.mag.bias), "field": _f(cal.field),
                        "accel_noise_std": _f(np.sqrt(np.diag(cal.accel.noise_cov))),
                        "mag_noise_std": _f(np.sqrt(np.diag(cal.mag.noise_cov)))},
        "intervals": [{"index": k, "start_s": iv.start_s, "end_s": iv.end_s, "duration_s": iv.duration_s,
                       "samples_accel": iv.n_accel, "samples_mag": iv.n_mag, "gravity_dir": _f(iv.gravity_dir),
                       "used": k in run.intervals_used} for k, iv in enumerate(seg.intervals)],
        "coverage": {"n_intervals": seg.coverage.n_intervals, "n_orientations": seg.coverage.n_orientations,
                     "largest_empty_cap_deg": seg.coverage.largest_empty_cap_deg, "status": seg.coverage.status,
                     "messages": list(seg.coverage.messages)},
        "instances": {"accel": am.instance, "compass": cm.instance,
                      "accel_present": list(run.raw.accel_instances()), "compass_present": list(run.raw.mag_instances()),
                      "accel_calibrated": [{"instance": a.instance, "offsets_mps2": _f(np.array(a.new.ofs_mps2)),
                                            "scales": _f(np.array(a.new.scale)), "dropped_tilt_deg": a.dropped_tilt_deg}
                                           for a in run.mapping.accel],
                      "compass_calibrated": [{"instance": c.instance, "external": c.external,
                                              "offsets_mgauss": _f(np.array(c.new.ofs_mgauss)),
                                              "orientation": c.orientation_note, "rotation_deg": c.rotation_deg,
                                              "residual_rotation_deg": c.residual_rotation_deg}
                                             for c in run.mapping.compass],
                      "pairs": [{"accel": r.mapping.accel[0].instance, "compass": r.mapping.compass[0].instance,
                                 "model": r.calibration.model, "heading_95_deg": r.quality.heading_95_deg,
                                 "tilt_95_deg": r.quality.tilt_95_deg} for r in (run,) + tuple(run.others)]},
        "raw_recovery": {"frames": dict(run.raw.frames), "accel_cal_periods": _f(run.raw.accel_cal_periods),
                         "params_used": {k: _f(v) for k, v in run.raw.params_used.items()}},
        "notes": list(run.mapping.notes),
        "warnings": list(run.warnings),
    }


def write_report(run: CalibrationRun, path) -> None:
    with open(path, "w") as f:
        json.dump(run_to_json(run), f, indent=1)
