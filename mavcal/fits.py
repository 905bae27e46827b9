"""The fits of one prepared recording, sensor by sensor, handed to the judging: the orchestration.

Every compass is fitted jointly with the primary accelerometer (:func:`mavcal.core.calibrate.calibrate`)
and mapped onto its autopilot's parameters (the model's ``map_calibration``), then judged
(:mod:`mavcal.judging.compass`: held-out error, heading bound, gates); every accelerometer is
judged on its own fit (:mod:`mavcal.judging.accel`). What the
fits take from the recording (readings, noise floors, the interval statistics computed once)
is :mod:`mavcal.fit_inputs`. The fits are independent of each other, so :func:`fit_recording` hands them to worker
processes (:class:`mavcal.workers.ForkPool`, ``Options.workers``); with one worker they run
here, in the same order, with the same results to the bit.
"""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import numpy.random  # noqa: F401  (loaded here, before the fit workers fork, not once in each of them)
from scipy.stats import chi2

from mavcal.autopilot import gates as gates_mod
from mavcal.autopilot import model_for
from mavcal.autopilot.mapping import AccelMapping, combine, field_magnitude
from mavcal.autopilot.model import AutopilotModel
from mavcal.autopilot.rotations import euler_to_matrix, nearest_rotation
from mavcal.core.accel_fit import HOLDOUT_FOLDS
from mavcal.core.calibrate import calibrate
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.core.held import calibrate_held, turn_compass, turned_stats
from mavcal.core.models import MODEL_CHAIN, MODELS
from mavcal.core.stats import IntervalStats, interval_means
from mavcal.core.types import Calibration
from mavcal.coverage import (
    ACCEL_STATE_WORDS,
    HELD_ACCEL_SD,
    REACH_FLOWN_TILT_DEG,
    WMM_INCLINATION_SD_DEG,
    KeptParameter,
    ReachCoverage,
    accel_state,
    held_priors,
    segmentation_reach,
)
from mavcal.errors import EstimationError, InsufficientDataError, MavcalError, SourceError
from mavcal.fit_inputs import (
    StatsCache,
    accel_sets,
    blind_cal,
    coverage_rule,
    noise_floor,
    sets,
    stats_of,
    wanted_instances,
    with_blind_cal,
)
from mavcal.judging.accel import accel_only, accel_own, died_gate, judge_accels
from mavcal.judging.compass import PairFit, judge_compass
from mavcal.judging.quality import holdout_part, quality_of
from mavcal.memory import release_free_memory
from mavcal.run import STAGE_FIT, CalibrationRun, Options, Prepared
from mavcal.segment import Segmentation
from mavcal.sources.progress import report
from mavcal.workers import ForkPool, Outcome, WorkerDiedError

log = logging.getLogger(__name__)

__all__ = ["fit_recording", "refusal_verdicts", "reach_of"]


_REACH_NOTE = ("poses within reach (tilts up to {:.1f} deg): the compasses are fitted with the primary "
               "accelerometer's offsets, and its X/Y scales unless it was calibrated (written with an accepted "
               "compass when the poses identify them); its Z scale and the other accelerometers are kept; no "
               "held-out check")


def fit_recording(prep: Prepared, options: Options = Options(), *, progress=None) -> CalibrationRun:
    """:func:`mavcal.pipeline.calibrate_prepared` (its docstring says what it does).

    Independent jobs, in ``options.workers`` processes (or here, one after the other): every
    pair's joint fit and mapping and every accelerometer's own fit, and, as soon as a pair's
    fit is done, its held-out refits (in ``workers`` slices) and its uncertainty bounds (a
    worker never waits for the slowest fit of a round). The gates and the accelerometers'
    verdicts, which need the primary pair's, are decided here at the end.
    """
    opts, warnings = _resolve(prep, options)
    if opts.sensors == "accel":
        return accel_only(prep, opts, warnings, progress)
    ai = opts.accel_instance
    reach = reach_of(prep, opts)
    if reach is not None:  # poses within reach: the accelerometers are kept, the compasses fitted with them held
        opts = replace(opts, holdout=False)
        warnings.append(_REACH_NOTE.format(reach.max_tilt_deg))
    pairs = [(ai, opts.mag_instance)] + [(a, m) for a, m in _other_pairs(prep, opts) if reach is None or a == ai]
    jobs = [opts] + [replace(opts, accel_instance=a, mag_instance=m, holdout=opts.holdout and a == ai)
                     for a, m in pairs[1:]]
    insts = prep.raw.accel_instances() if opts.sensors == "both" and reach is None else []
    stats: StatsCache = {}
    first = [("pair", j, o) for j, o in enumerate(jobs)] + [("accel", j, (opts, a)) for j, a in enumerate(insts)]
    got: dict[tuple[str, int], Outcome] = {}  # ("pair" | "accel" | "quality", j) -> outcome
    slices: dict[int, list[tuple[int, Outcome]]] = {j: [] for j in range(len(jobs))}  # pair j's held-out slices
    with ForkPool((prep, stats), opts.workers) as pool:
        K = pool.workers
        release_free_memory()  # what reading and preparing freed: before the statistics' temporaries
        if K > 1:
            _prefill_stats(prep, jobs, stats, bool(insts))
            release_free_memory()  # theirs, before the workers fork (they would copy the free pages they reuse)

        def then(item: tuple[str, int, tuple], outcome: Outcome) -> list[tuple[str, int, tuple]]:
            kind, j, arg = item
            if kind == "holdout":
                slices[j].append((arg[2][0], outcome))
                return []
            got[kind, j] = outcome
            if kind != "pair":
                return []
            ok, f = outcome
            if not ok and j == 0:  # the primary pair cannot be fitted: nothing to report
                raise f
            o = jobs[j]
            S = _holdout_slices(K)
            return ([("quality", j, (o, f))] + [("holdout", j, (o, f, (k, S))) for k in range(S) if o.holdout]
                    if ok else [])

        n = len(first) + len(jobs) * (_holdout_slices(K) + 1)  # at most: every pair's held-out slices and bounds
        pool.run(_job, first, then, done=lambda k: report(progress, STAGE_FIT, k, n))
    release_free_memory()  # the fits' working memory (run here with one worker), before the report's
    runs: list[CalibrationRun | MavcalError] = []
    for j, o in enumerate(jobs):
        ok, r = got["pair", j]
        runs.append(judge_compass(prep, o, r, [h for _, h in sorted(slices[j], key=lambda kh: kh[0])],
                                 got["quality", j]) if ok else r)
    if isinstance(runs[0], MavcalError):
        raise runs[0]
    primary = runs[0]
    warnings += list(primary.warnings)
    others, died = [], []
    for (a, m), r in zip(pairs[1:], runs[1:]):
        if isinstance(r, MavcalError):
            warnings.append(f"accelerometer {a} / compass {m} not calibrated: {r}")
            if isinstance(r, WorkerDiedError) and a == ai:
                died.append(died_gate(f"compass{m}", r))
        else:
            others.append(r)
    compass_runs = [primary] + [r for r in others if r.mapping.accel[0].instance == ai]
    gates = [g for r in compass_runs for g in r.gates.gates] + died
    compasses = [r.mapping.compass[0] for r in compass_runs]
    accels, fits, accel_gates = judge_accels(prep, opts, [primary] + others,
                                              [(a, got["accel", j]) for j, a in enumerate(insts)], warnings)
    report(progress, STAGE_FIT, n, n)
    accels, kept, reach_gates = _within_reach_parts(prep, opts, reach, primary, compass_runs, accels)
    notes = list(primary.mapping.notes) + [f"compass {c.instance}: {c.orientation_note}" for c in compasses[1:]]
    mapping = combine(accels, compasses, primary.params_before, notes)
    return replace(primary, mapping=mapping, gates=gates_mod.GateReport(tuple(accel_gates + reach_gates + gates)),
                   others=tuple(others), warnings=tuple(dict.fromkeys(warnings)), accel_fits=tuple(fits), kept=kept)


def _within_reach_parts(prep: Prepared, opts: Options, reach: ReachCoverage | None, primary: CalibrationRun,
                        compass_runs: list[CalibrationRun], accels: list[AccelMapping]):
    """(accelerometer mappings, kept parameters, accelerometer gates) of a run: for poses within
    reach, the primary accelerometer with its scales kept and its offsets fitted, and every compass's
    and accelerometer's kept parameters. The offsets and the compass are one fit: the offsets are
    rejected with their compass (and written with it under --force, the compass being right only
    with them)."""
    if reach is None:
        return accels, (), []
    kept = tuple(k for r in compass_runs for k in r.kept if k.sensor.startswith("compass")) \
        + tuple(k for k in primary.kept if k.sensor.startswith("accel"))
    am = primary.mapping.accel[0]
    if am.kept:
        return [am], kept, []
    cal = primary.calibration
    assert cal is not None
    state = accel_state(am.old.ofs_mps2, am.old.scale)
    level_95 = _level_tilt_95_deg(offsets_sd_mps2(cal))
    gates = gates_mod.reach_accel_gates(am, level_tilt_95_deg=level_95,
                                        limit_deg=_level_tilt_95_deg(HELD_ACCEL_SD[state][0] / REACH_OFFSETS_GAIN),
                                        partner=f"compass{opts.mag_instance}",
                                        partner_ok=all(g.ok for g in primary.gates.gates),
                                        config=model_for(prep.log).gate_config(opts.gates))
    return [am], kept, gates


def _level_tilt_95_deg(sd_mps2: float) -> float:
    """The 95 % bound of the level tilt error (deg) an X/Y offset error of ``sd_mps2`` (1 sigma, any
    horizontal direction) leaves: chi2 with 2 degrees of freedom."""
    return float(np.degrees(np.sqrt(CHI2_2_95) * sd_mps2 / GRAVITY_MPS2))


def _holdout_slices(workers: int) -> int:
    """Slices a pair's held-out refits are cut into: with workers, at least two per worker (small
    jobs even out the workers' loads; a slice costs ~2 ms more than its refits) and, where it
    can, a divisor of :data:`~mavcal.core.accel_fit.HOLDOUT_FOLDS`, so that the K-fold check's
    slices hold the same number of refits (5 for 2 workers: 2 folds each)."""
    if workers == 1:
        return 1
    return next((s for s in range(2 * workers, HOLDOUT_FOLDS + 1) if HOLDOUT_FOLDS % s == 0), 2 * workers)


def _prefill_stats(prep: Prepared, jobs: list[Options], stats: StatsCache, accels: bool) -> None:
    """Every interval statistic the fit jobs will ask for, computed here before the workers
    fork: each is computed once (not once per worker) and its full-length working arrays
    are this process's, not one more copy per worker. A job whose data are refused raises
    that itself, later."""
    wanted = []
    for o in jobs:
        try:
            used = _intervals_of_pair(prep, o.accel_instance, o.mag_instance, o)
        except MavcalError:
            continue
        wanted += [("accel", o.accel_instance, used), ("mag", o.mag_instance, used)]
    if accels:
        for a in prep.raw.accel_instances():
            try:
                wanted.append(("accel", a, accel_sets(prep, a)[0]))
            except MavcalError:
                continue
    for kind, inst, used in wanted:
        try:
            stats_of(prep, stats, kind, inst, used)
        except MavcalError:
            continue


_Shared = tuple[Prepared, StatsCache]  # what the fit jobs share (inherited by forked workers)


def _job(shared: _Shared, item: tuple[str, int, tuple]):
    """One fit job of :func:`fit_recording` (``item``: kind, pair or accelerometer index, arguments):
    a pair's joint fit and mapping (:func:`_fit_pair`), an accelerometer's own fit
    (:func:`mavcal.judging.accel.accel_own`), a slice of a pair's held-out refits
    (:func:`mavcal.judging.quality.holdout_part`) or a pair's uncertainty bounds
    (:func:`mavcal.judging.quality.quality_of`, the held-out numbers left NaN)."""
    prep, stats = shared
    kind, _, arg = item
    if kind == "pair":
        return _fit_pair(prep, arg, stats)  # type: ignore[arg-type]
    if kind == "accel":
        opts, a = arg
        return accel_own(prep, opts, a, stats)
    if kind == "holdout":
        o, f, part = arg
        ai, mi = o.accel_instance, o.mag_instance
        return holdout_part(sets(prep, "accel", ai, f.used), sets(prep, "mag", mi, f.used), f.cal, part=part,
                            method=o.method, tol=o.tol, seed=o.seed,
                            noise_floor=(noise_floor(prep, "accel", ai), noise_floor(prep, "mag", mi)),
                            stats=(stats_of(prep, stats, "accel", ai, f.used),
                                   stats_of(prep, stats, "mag", mi, f.used)))
    o, f = arg
    am, cm = f.mapping.accel[0], f.mapping.compass[0]
    q = quality_of(f.cal, am, cm, am.old.board_matrix, o.uncertainty_draws, o.seed, (float("nan"), float("nan")),
                   **({} if f.reach is None else {"max_tilt_deg": REACH_FLOWN_TILT_DEG}))
    if f.reach is None or f.accel_state == "calibrated":
        return q
    # the Z scale kept at the factory's (3 %): what it leaves beyond the poses' tilts, for the verdict to say
    steep = quality_of(f.cal, am, cm, am.old.board_matrix, o.uncertainty_draws, o.seed, (float("nan"), float("nan")),
                       max_tilt_deg=REACH_STEEP_TILT_DEG, attitude_known=True)
    return replace(q, heading_95_steep_deg=steep.heading_95_deg)


def _other_pairs(prep: Prepared, opts: Options) -> list[tuple[int, int]]:
    """The accelerometer/compass pairs fitted besides the primary one (``opts.all_instances``)."""
    ai, mi = opts.accel_instance, opts.mag_instance
    pairs: list[tuple[int, int]] = []
    if opts.all_instances:
        if opts.sensors == "both":
            pairs += [(a, mi) for a in prep.raw.accel_instances() if a != ai]
        pairs += [(ai, m) for m in wanted_instances(prep.raw.mag_instances(), opts, "compass") if m != mi]
    return pairs


def _resolve(prep: Prepared, options: Options) -> tuple[Options, list[str]]:
    """The options as they apply to this log (a log without compass: accelerometers alone)."""
    opts, warnings = options, []
    if opts.sensors not in ("both", "accel", "compass"):
        raise MavcalError(f"sensors must be both, accel or compass; got {opts.sensors!r}")
    if opts.sensors == "both" and not prep.raw.mag_instances():
        warnings.append("the log has no compass data: the accelerometers were calibrated alone")
        opts = replace(opts, sensors="accel", only_instances=None)
    if opts.sensors in ("accel", "compass") and opts.only_instances is not None:
        have = prep.raw.accel_instances() if opts.sensors == "accel" else prep.raw.mag_instances()
        missing = [i for i in opts.only_instances if i not in have]
        if missing:
            raise SourceError(f"{prep.log.source}: no {opts.sensors} {', '.join(map(str, missing))} data "
                              f"(the log has {opts.sensors} {', '.join(map(str, have)) or 'none'})")
        first = opts.only_instances[0]
        opts = replace(opts, **({"accel_instance": first} if opts.sensors == "accel" else {"mag_instance": first}))
    return opts, warnings


def refusal_verdicts(prep: Prepared, error: Exception, options: Options = Options()
                     ) -> tuple[gates_mod.SensorVerdict, ...]:
    """A verdict for every sensor with data of a recording that could not be calibrated at all
    (``error``: the refusal): each rejected, with how many still intervals it has and ``error``."""
    seg, raw, none = prep.segmentation, prep.raw, np.empty((0, 3))
    ai = options.accel_instance
    out = []
    for kind, label, insts in (("accel", "accel", raw.accel_instances()), ("compass", "compass",
                                                                           raw.mag_instances())):
        if options.sensors not in ("both", kind):
            continue
        for i in wanted_instances(insts, options, kind):
            if kind == "accel":
                used = [iv for iv in seg.intervals if iv.accel_mps2.get(i, none).shape[0] >= 2]
                what = f"accelerometer {i} data"
            else:
                used = [iv for iv in seg.intervals if iv.mag_mgauss.get(i, none).shape[0] >= 2
                        and iv.accel_mps2.get(ai, none).shape[0] >= 2]
                what = f"compass {i} and accelerometer {ai} data"
            dirs = np.array([iv.gravity_dir for iv in used]).reshape(-1, 3)
            first = (f"not calibrated: {len(used)} still interval(s) with {what}, in "
                     f"{_n_orientations(dirs, seg) if len(used) else 0} distinct orientation(s)")
            out.append(gates_mod.SensorVerdict(f"{label}{i}", False, tuple(dict.fromkeys([first, str(error)]))))
    return tuple(out)


def _n_orientations(dirs: np.ndarray, seg: Segmentation) -> int:
    """Distinct gravity directions among ``dirs`` (greedy clusters of the segmentation's size)."""
    if len(dirs) == len(seg.intervals):
        return seg.coverage.n_orientations
    cos_c = np.cos(np.radians(30.0))
    centres: list[np.ndarray] = []
    for d in dirs:
        if not any(float(d @ c) > cos_c for c in centres):
            centres.append(d)
    return len(centres)


def _intervals_of_pair(prep: Prepared, ai: int, mi: int, opts: Options = Options()) -> list[int]:
    """The still intervals holding samples of both accelerometer ``ai`` and compass ``mi``;
    InsufficientDataError/SourceError when too few for any model (saying how many ``opts``'
    gates accept: never fewer than the poses the coverage messages ask for)."""
    log_, raw, seg = prep.log, prep.raw, prep.segmentation
    none = np.empty((0, 3))
    used = [k for k, iv in enumerate(seg.intervals)
            if iv.accel_mps2.get(ai, none).shape[0] >= 2 and iv.mag_mgauss.get(mi, none).shape[0] >= 2]
    if not used:
        if raw.get("accel", ai) is None:
            raise SourceError(f"{log_.source}: no accelerometer {ai} data")
        if raw.get("mag", mi) is None:
            raise SourceError(f"{log_.source}: no compass {mi} data")
        raise InsufficientDataError(f"{log_.source}: no still intervals found ({len(seg.intervals)} detected, none "
                                    "with both sensors); " + "; ".join(list(seg.coverage.messages) + blind_cal(prep)))
    n_min = MODELS[MODEL_CHAIN[-1]].min_intervals
    if len(used) < n_min:
        why = "; ".join(blind_cal(prep) + list(seg.coverage.messages)) \
            or f"{seg.coverage.n_orientations} distinct orientation(s)"
        need = max(n_min, coverage_rule(opts, seg).min_orientations)  # what a verdict accepts, not a fit's least
        raise InsufficientDataError(
            f"{log_.source}: {len(used)} still interval(s) with accelerometer {ai} and compass {mi} data; at least "
            f"{need} in different orientations are needed ({MODELS['full'].min_intervals} for the full model): {why}")
    return used


def _fit_pair(prep: Prepared, opts: Options, stats: StatsCache) -> PairFit:
    """calibrate -> map for one accelerometer/compass pair (``stats``: the run's interval
    statistics, :func:`mavcal.fit_inputs.stats_of`)."""
    log_ = prep.log
    warnings: list[str] = list(prep.warnings)
    ai, mi = opts.accel_instance, opts.mag_instance
    used = _intervals_of_pair(prep, ai, mi, opts)
    params_now = log_.params.snapshot()
    reach = reach_of(prep, opts)
    model = model_for(log_)
    # poses within reach hold the accelerometer: its state in force sets its prior and the advice
    state = "calibrated" if reach is None else _accel_state_of(model, params_now, ai)
    turn = None if reach is None else reach_turn(model, reach, params_now, ai, mi)
    if reach is not None and reach.mounting_turn_deg and turn is None and reach.compass_identified:
        reach = replace(reach, kept=reach.kept + (KeptParameter(
            f"compass{mi}", "orientation", f"{reach.mounting_text()} (its orientation cannot be written here: an "
            "internal compass follows AHRS_ORIENTATION)", "COMPASS_EXTERN set for an external compass"),))
    try:
        sa, sm = stats_of(prep, stats, "accel", ai, used), stats_of(prep, stats, "mag", mi, used)
        if reach is None:
            cal = calibrate(sa, sm, method=opts.method, tol=opts.tol, seed=opts.seed, model=opts.model)
        elif turn is None:
            cal, state = _fit_within_reach(prep, opts, reach, sa, sm, params_now)
        else:  # the compass turned as the tilts say (issue 37): fitted so, its orientation then written
            cal, state = _fit_within_reach(prep, opts, reach, sa, turned_stats(sm, turn), params_now)
            cal = turn_compass(cal, turn)
    except (InsufficientDataError, EstimationError) as exc:
        raise with_blind_cal(prep, exc) from None
    if reach is not None and state != "calibrated":
        sd = HELD_ACCEL_SD[state]
        if "K_a[11]" not in cal.held:  # its X/Y scales fitted from the poses, its Z scale kept
            what = (f"{ACCEL_STATE_WORDS[state]}: its X/Y scales and offsets are fitted from the poses (X/Y scales to "
                    f"{100 * scales_sd(cal):.1f} %, 1 sigma), its Z scale kept; the heading and tilt bounds carry "
                    f"the Z scale's uncertainty ({100 * sd[1]:g} %, 1 sigma)")
        else:
            what = (f"{ACCEL_STATE_WORDS[state]}; the heading and tilt bounds carry that uncertainty (1 sigma: "
                    f"offsets {sd[0]:g} m/s^2, scales {100 * sd[1]:g} %"
                    + (" or the discrepancy, if larger)" if state == "inconsistent" else ")"))
        reach = replace(reach, kept=reach.kept + (KeptParameter(
            f"accel{ai}", "calibration in force", what, "its full calibration: " + _BEYOND_WORDS),))
    if not params_now:
        warnings.append("the log has no parameters: readings were taken as raw and the old values are unknown")
    if reach is not None:  # the segmentation's "too few orientations" is what the reduced fit answers
        warnings = [w for w in warnings if w not in prep.segmentation.coverage.messages]
    mapping = model_for(log_).map_calibration(
        cal, params_now, interval_means(sets(prep, "mag", mi, used)), accel_instance=ai, mag_instance=mi,
        location=opts.location or log_.position, location_source="" if opts.location else log_.position_source,
        field_mgauss=opts.field_mgauss, orient_tol_deg=opts.orient_tol_deg, allow_custom=opts.allow_custom,
        force_external=opts.force_external)
    if reach is not None:  # the accelerometer keeps its scales, exactly; its offsets are the fit's (if identified)
        am = mapping.accel[0]
        fitted = "b_a[x]" not in cal.held
        new = replace(am.old, ofs_mps2=tuple(float(x) for x in cal.accel.bias)) if fitted else am.old
        if "K_a[11]" not in cal.held:  # the X/Y scales fitted (K_a = diag(g / scale)), the Z scale kept
            K = np.diag(cal.accel.gain)
            new = replace(new, scale=(GRAVITY_MPS2 / float(K[0]), GRAVITY_MPS2 / float(K[1]), new.scale[2]))
            reach = replace(reach, kept=tuple(k for k in reach.kept if not (k.sensor == f"accel{ai}"
                                                                            and k.what == "X and Y scales")))
        am = replace(am, new=new, frame_rotation=np.eye(3), cross_axis=np.zeros((3, 3)), dropped_tilt_deg=0.0,
                     dropped_magnitude_mps2=0.0, kept=not fitted)
        mapping = combine([am], mapping.compass, params_now, mapping.notes)
        if not fitted:
            reach = replace(reach, kept=reach.kept + (KeptParameter(
                f"accel{ai}", "offsets", f"these poses do not identify them {REACH_OFFSETS_GAIN:g} times better than "
                "the calibration in force is known (the model's reason says how well)", _OFFSETS_POSE),))
    return PairFit(used, cal, mapping, params_now, warnings, reach, state)


def reach_of(prep: Prepared, opts: Options) -> ReachCoverage | None:
    """What the poses identify when they are all within reach (:func:`mavcal.coverage.segmentation_reach`)
    for the compass ``opts.mag_instance`` paired with accelerometer ``opts.accel_instance``; None
    when the rule does not apply (the poses identify the accelerometer, or go beyond a small tilt; a
    PX4 recording: the held accelerometer is read in ArduPilot's terms, so PX4 takes the full fit)."""
    if opts.sensors == "accel" or not model_for(prep.log).holds_accel_within_reach:
        return None
    seg = prep.segmentation
    accels = prep.raw.accel_instances() if opts.sensors == "both" else []
    return segmentation_reach(seg, opts.accel_instance, opts.mag_instance, coverage_rule(opts, seg), accels)


_BEYOND_WORDS = "the vehicle on each side and upside down (the full capture without --max-tilt)"
_OFFSETS_POSE = "tilts in more directions at several headings, each held still longer; or " + _BEYOND_WORDS
CHI2_2_95 = 5.991464547107979  # the 95 % point of chi2 with 2 degrees of freedom
#: within reach with a factory Z scale, the heading bound is also given over tilts up to this (deg): what a vehicle
#: flown steeper than its poses were held meets (REACH_FLOWN_TILT_DEG is the bound the gate judges)
REACH_STEEP_TILT_DEG = 30.0


def _accel_state_of(model: AutopilotModel, params: dict[str, float], instance: int) -> str:
    """The state of accelerometer ``instance``'s calibration in force (:func:`mavcal.coverage.accel_state`)."""
    a = model.accel_cal(params, instance)
    return accel_state(a.ofs_mps2, a.scale)


def reach_turn(model: AutopilotModel, reach: ReachCoverage, params_now: dict[str, float], accel_instance: int,
               mag_instance: int) -> np.ndarray | None:
    """The yaw turn (3 x 3, compass -> body, from its configured mounting) of a compass whose turn the
    tilts identify (:attr:`mavcal.coverage.ReachCoverage.mounting_turn_deg`, not 0), when its orientation
    can be written: an external compass (its own orientation applies) whose turned mounting is a standard
    orientation; None otherwise (the verdict then says it may be mounted rotated)."""
    if not reach.mounting_turn_deg or not reach.compass_identified:
        return None
    old = model.compass_cal(params_now, mag_instance)
    board = model.accel_cal(params_now, accel_instance).board_orient
    if not (old.external if old.external is not None else old.orient != board):
        return None
    Q = euler_to_matrix(0.0, 0.0, np.radians(reach.mounting_turn_deg))
    return Q if nearest_rotation(Q @ old.mount_matrix)[1] <= 1.0 else None


#: poses within reach fit the accelerometer's offsets (issue 37: the tilts at several headings tell a body-fixed
#: offset from the tilt of each pose, through gravity's constant magnitude and the compass's view of the tilt);
#: they are written when the fit knows them at least this many times better than the calibration in force is
#: assumed to be known (:data:`mavcal.coverage.HELD_ACCEL_SD` by its state), else held as before
REACH_OFFSETS_GAIN = 2.0


def _fit_within_reach(prep: Prepared, opts: Options, reach: ReachCoverage, sa: IntervalStats, sm: IntervalStats,
                      params_now: dict[str, float]) -> tuple[Calibration, str]:
    """The compass fitted with the accelerometer's offsets (:func:`mavcal.core.held.calibrate_held`): its
    scales held at its current calibration when it is calibrated (and the poses do not contradict them),
    else its X/Y scales fitted too when the poses identify them (:func:`_fit_free_scales`); the offsets
    held too when the poses do not identify them to :data:`REACH_OFFSETS_GAIN` times the prior of the
    calibration in force (or the fit with them free fails). The field dip is fitted; when the position
    is known and the tilts determine the dip less well than the World Magnetic Model knows it
    (:data:`mavcal.coverage.WMM_INCLINATION_SD_DEG`), it is held at the model's inclination instead.
    Returns the fit and the state of the calibration in force (:func:`mavcal.coverage.accel_state`, or
    "inconsistent": calibrated, but its X/Y scales contradicted by the poses, :func:`_scales_contradicted`)."""
    if not reach.compass_identified:
        raise InsufficientDataError(f"{prep.log.source}: poses within reach (tilts up to {reach.max_tilt_deg:.1f} "
                                    f"deg): {'; '.join(reach.missing)}; {reach.add}")
    model = model_for(prep.log)
    old = model.accel_cal(params_now, opts.accel_instance)
    if old.board_orient != 0:
        raise InsufficientDataError(f"{prep.log.source}: poses within reach need AHRS_ORIENTATION 0 (the fit holds "
                                    "the accelerometer in the board frame); capture the six sides instead")
    scale = np.asarray(old.scale, float)
    K_a, b_a = np.diag(GRAVITY_MPS2 / scale), np.asarray(old.ofs_mps2, float)
    state = accel_state(b_a, scale)  # the held values' prior: full, level-only or no calibration
    if state != "calibrated":  # a level calibration's or the factory's scales: the poses know them better
        free = _fit_free_scales(prep, opts, sa, sm, K_a, b_a, state, params_now, reach)
        if free is not None:
            return free, state
    cal = _fit_held_scales(prep, opts, sa, sm, K_a, b_a, state, params_now, reach)
    note, sd = _scales_contradicted(sa, sm, K_a, b_a, cal, state)
    if not note:
        return cal, state
    # the scales in force contradicted: the poses' own, when they know them, else held with a wider prior
    state = "inconsistent"
    free = _fit_free_scales(prep, opts, sa, sm, K_a, b_a, state, params_now, reach, note + "; ")
    if free is not None:
        return free, state
    incl = float(np.degrees(np.arctan(cal.h_z))) if "h_z" in cal.held else None
    return calibrate_held(sa, sm, K_a, b_a, held=list(cal.held), prior_sd=held_priors(K_a, state, incl, scale_sd=sd),
                          h_z=cal.h_z if "h_z" in cal.held else None,
                          reason=cal.model_reason + f"; {note}: their prior widened to {100 * sd:.1f} %"), state


def _fit_held_scales(prep: Prepared, opts: Options, sa: IntervalStats, sm: IntervalStats, K_a: np.ndarray,
                     b_a: np.ndarray, state: str, params_now: dict[str, float], reach: ReachCoverage) -> Calibration:
    """The fit with every scale held, the offsets fitted (held too when not identified, :data:`REACH_OFFSETS_GAIN`)."""
    # only K_a[33] + b_a[z] (the level reading) is identified along Z: b_a[z] is fitted with K_a[33] held
    scales = [f"K_a[{j}{j}]" for j in (1, 2, 3)]
    why = (f"poses within reach (tilts up to {reach.max_tilt_deg:.1f} deg, {reach.n_field_directions} distinct "
           "headings): the accelerometer's scales held at its current calibration, ")
    limit = HELD_ACCEL_SD[state][0] / REACH_OFFSETS_GAIN
    try:
        cal = _held_dip_fit(prep, opts, sa, sm, K_a, b_a, scales, state, params_now, why + "its offsets fitted, ")
        sd = offsets_sd_mps2(cal)
        if sd <= limit:
            return cal
        note = (f"its X/Y offsets held too: the poses determine them to {sd:.3f} m/s^2 (1 sigma), not within "
                f"{limit:g} m/s^2, ")
    except (InsufficientDataError, EstimationError) as exc:
        note = f"its X/Y offsets held too: the fit with them free failed ({exc}), "
    return _held_dip_fit(prep, opts, sa, sm, K_a, b_a, scales + ["b_a[x]", "b_a[y]"], state, params_now, why + note)


#: poses within reach fit the X/Y scales of an accelerometer whose scales in force are a level calibration's or
#: the factory's (1), or contradicted by the poses, when the fit knows them at least this many times better than
#: those are assumed to be known (3 %, :data:`mavcal.coverage.HELD_ACCEL_SD`); else they are held
REACH_SCALES_GAIN = 1.5


def _fit_free_scales(prep: Prepared, opts: Options, sa: IntervalStats, sm: IntervalStats, K_a: np.ndarray,
                     b_a: np.ndarray, state: str, params_now: dict[str, float], reach: ReachCoverage,
                     before: str = "") -> Calibration | None:
    """The fit with the X/Y scales and the offsets free, the Z scale held with its prior (issue 37): the
    X/Y-to-Z ratios the tilts see, which a wrong Z scale shifts by half its error (carried). None when
    it fails, is not certified with positive gains, or does not identify the scales to
    :data:`REACH_SCALES_GAIN` times their prior or the offsets to :data:`REACH_OFFSETS_GAIN` times theirs."""
    why = (before + f"poses within reach (tilts up to {reach.max_tilt_deg:.1f} deg, {reach.n_field_directions} "
           "distinct headings): the accelerometer's Z scale held at its current calibration, its X/Y scales and "
           "offsets fitted, ")
    try:
        cal = _held_dip_fit(prep, opts, sa, sm, K_a, b_a, ["K_a[33]"], state, params_now, why)
    except (InsufficientDataError, EstimationError):
        return None
    gains = np.diag(cal.accel.gain)[:2]
    ofs_ok = offsets_sd_mps2(cal) <= HELD_ACCEL_SD[state][0] / REACH_OFFSETS_GAIN
    if not cal.converged or np.any(gains <= 0.0) or not ofs_ok:
        return None
    return cal if scales_sd(cal) <= HELD_ACCEL_SD[state][1] / REACH_SCALES_GAIN else None


def scales_sd(cal: Calibration) -> float:
    """The largest relative standard deviation of a held fit's accelerometer X/Y scales (inf when held or
    their covariance is unknown)."""
    names = cal.param_names
    if cal.param_cov is None or "K_a[11]" in cal.held:
        return float("inf")
    out = 0.0
    for j in (1, 2):
        k = names.index(f"K_a[{j}{j}]")
        out = max(out, float(np.sqrt(max(cal.param_cov[k, k], 0.0))) / abs(float(cal.accel.gain[j - 1, j - 1])))
    return out


#: the false-alarm rate of calling an accelerometer's X/Y scales in force inconsistent with poses within reach
SCALES_FALSE_ALARM = 1e-3


def _scales_contradicted(sa: IntervalStats, sm: IntervalStats, K_a: np.ndarray, b_a: np.ndarray, cal: Calibration,
                         state: str) -> tuple[str, float]:
    """A calibrated accelerometer's held X/Y scales tested against the poses (issue 37): the same fit with
    K_a[11], K_a[22] free (K_a[33] and the rest held as in ``cal``, their priors counted), and the
    difference d of the free values from the held ones weighed by its covariance C (the free fit's plus
    the held values' prior): d^T C^-1 d is chi2 with 2 degrees of freedom when the calibration in force is
    within its prior. Returns ("", 0) when it is not beyond the chi2 point of :data:`SCALES_FALSE_ALARM`
    (or the poses cannot test it), else the finding in words and the relative prior the held scales
    deserve instead: a level calibration's, or the discrepancy when larger."""
    if state != "calibrated":
        return "", 0.0
    held = [h for h in cal.held if h not in ("K_a[11]", "K_a[22]")]
    incl = float(np.degrees(np.arctan(cal.h_z))) if "h_z" in held else None
    try:
        free = calibrate_held(sa, sm, K_a, b_a, held=held, prior_sd=held_priors(K_a, state, incl),
                              h_z=cal.h_z if "h_z" in held else None)
    except (InsufficientDataError, EstimationError):
        return "", 0.0
    if free.param_cov is None or not free.converged or np.any(np.diag(free.accel.gain)[:2] <= 0.0):
        return "", 0.0  # no certified optimum of the proper sign (tiny tilts): the poses cannot test them
    k = [free.param_names.index(n) for n in ("K_a[11]", "K_a[22]")]
    K = np.diag(K_a)[:2]
    d = np.diag(free.accel.gain)[:2] - K
    C = free.param_cov[np.ix_(k, k)] + np.diag((HELD_ACCEL_SD[state][1] * K) ** 2)
    z2 = float(d @ np.linalg.solve(C, d))
    if z2 <= float(chi2.isf(SCALES_FALSE_ALARM, 2)):
        return "", 0.0
    pct = ", ".join(f"{c} {100 * x:+.1f} %" for c, x in zip("XY", np.diag(free.accel.gain)[:2] / K - 1.0))
    note = (f"its X/Y scales in force do not fit these poses (K_a[11], K_a[22] fitted {pct} off them, chi2 "
            f"{z2:.1f} on 2 dof, false-alarm rate {SCALES_FALSE_ALARM:g})")
    return note, max(HELD_ACCEL_SD["inconsistent"][1], float(np.abs(d / K).max()))


def offsets_sd_mps2(cal: Calibration) -> float:
    """The largest standard deviation of a held fit's accelerometer X/Y offsets (any direction in the
    horizontal plane, m/s^2): inf when they were held or their covariance is unknown."""
    names = cal.param_names
    if cal.param_cov is None or "b_a[x]" in cal.held or "b_a[x]" not in names:
        return float("inf")
    k = [names.index("b_a[x]"), names.index("b_a[y]")]
    return float(np.sqrt(max(np.linalg.eigvalsh(cal.param_cov[np.ix_(k, k)]).max(), 0.0)))


def _held_dip_fit(prep: Prepared, opts: Options, sa: IntervalStats, sm: IntervalStats, K_a: np.ndarray,
                  b_a: np.ndarray, held: list[str], state: str, params_now: dict[str, float], why: str) -> Calibration:
    """:func:`mavcal.core.held.calibrate_held` with ``held`` fixed, the field dip fitted, or held at the World
    Magnetic Model's inclination when the tilts determine it less well than the model knows it."""
    model = model_for(prep.log)
    cal = calibrate_held(sa, sm, K_a, b_a, held=held, prior_sd=held_priors(K_a, state, None),
                         reason=why + "the field dip estimated from the tilts")
    loc = opts.location or prep.log.position
    if loc is None:
        return replace(cal, model_reason=cal.model_reason + " (no position known)")
    incl = field_magnitude(np.empty((0, 3)), model.compass_cal(params_now, opts.mag_instance),
                           location=loc)[2]
    sd_incl = _inclination_sd_deg(cal)
    if incl is None or sd_incl <= WMM_INCLINATION_SD_DEG:
        return replace(cal, model_reason=cal.model_reason + f" (to {sd_incl:.2f} deg, closer than the World "
                       f"Magnetic Model's {WMM_INCLINATION_SD_DEG:g} deg)")
    return calibrate_held(sa, sm, K_a, b_a, held=held + ["h_z"], prior_sd=held_priors(K_a, state, incl),
                          h_z=float(np.tan(np.radians(incl))),
                          reason=why + f"the field dip at the World Magnetic Model's inclination {incl:.2f} deg (the "
                          f"tilts determine it only to {sd_incl:.2f} deg)")


def _inclination_sd_deg(cal: Calibration) -> float:
    """The standard deviation of a fit's field dip, as an inclination in degrees (inf when unknown)."""
    if cal.param_cov is None or "h_z" not in cal.param_names:
        return float("inf")
    k = cal.param_names.index("h_z")
    sd_hz = float(np.sqrt(max(cal.param_cov[k, k], 0.0)))
    return float(np.degrees(sd_hz / (1.0 + cal.h_z ** 2)))
