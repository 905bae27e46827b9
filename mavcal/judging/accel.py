"""Each accelerometer judged on its own fit (:func:`mavcal.core.accel_fit.fit_accel`): its
held-out error, which values are written (its joint fit's with the primary compass, or its
own), its tilt bounds and its gates; and the accelerometers calibrated alone, for a log
without compass data. :mod:`mavcal.fits` runs the own fits (:func:`accel_own`) beside the
pairs' and calls :func:`judge_accels` once the primary pair's verdict is known. The compasses'
judging is beside it, :mod:`mavcal.judging.compass`.
"""
from __future__ import annotations

from mavcal.autopilot import gates as gates_mod
from mavcal.autopilot import model_for
from mavcal.autopilot.mapping import AccelMapping, combine
from mavcal.core.accel_fit import AccelFit, fit_accel, holdout_accel_mps2
from mavcal.coverage import sensor_coverages
from mavcal.errors import EstimationError, InsufficientDataError, MavcalError, SourceError
from mavcal.fit_inputs import (
    StatsCache,
    accel_sets,
    coverage_rule,
    noise_floor,
    stats_of,
    wanted_instances,
    with_blind_cal,
)
from mavcal.judging.quality import Quality, accel_tilt_bounds
from mavcal.run import STAGE_FIT, CalibrationRun, Options, Prepared
from mavcal.sources.progress import report
from mavcal.workers import Outcome, WorkerDiedError

__all__ = ["accel_own", "judge_accel", "judge_accels", "accel_only", "died_gate"]


def died_gate(sensor: str, exc: WorkerDiedError) -> gates_mod.Gate:
    """A sensor whose fit's worker process died (out of memory?): rejected, with the reason."""
    return gates_mod.Gate(sensor, "fit", False, 0.0, "yes", f"no result: {exc}")


def accel_own(prep: Prepared, opts: Options, a: int, stats: StatsCache) -> tuple[list[int], AccelFit, float]:
    """Accelerometer ``a``'s own fit: (intervals used, fit, held-out error)."""
    used, acc = accel_sets(prep, a)
    try:
        st = stats_of(prep, stats, "accel", a, used)
        fit = fit_accel(st)
    except (InsufficientDataError, EstimationError) as exc:
        raise with_blind_cal(prep, exc) from None
    ho = (holdout_accel_mps2(acc, noise_floor=noise_floor(prep, "accel", a), start=fit, stats=st) if opts.holdout
          else float("nan"))
    return used, fit, ho


def judge_accels(prep: Prepared, opts: Options, runs: list[CalibrationRun], own: list[tuple[int, Outcome]],
                 warnings: list[str]) -> tuple[list[AccelMapping], list[tuple[int, AccelFit]], list[gates_mod.Gate]]:
    """Every accelerometer judged on its own fit (``own``: each one's :func:`accel_own`
    outcome), written from its joint fit with compass ``opts.mag_instance`` (in ``runs``, the
    primary first) when that compass is accepted."""
    mi = opts.mag_instance
    mi_ok = all(g.ok for g in runs[0].gates.gates)
    joint = {r.mapping.accel[0].instance: r for r in runs if r.mapping.compass[0].instance == mi}
    # a joint fit not certified as the optimum is never written (the primary's fails its compass's gate)
    unconverged = {a for a, r in joint.items() if r.calibration is not None and not r.calibration.converged}
    accels: list[AccelMapping] = []
    fits: list[tuple[int, AccelFit]] = []
    gates: list[gates_mod.Gate] = []
    for a, (ok, res) in own:
        try:
            if not ok:
                raise res
            use_joint = a in joint and mi_ok and a not in unconverged
            am, ag, fit, _, _ = judge_accel(prep, opts, a, joint[a].mapping.accel[0] if use_joint else None, res,
                                            warnings)
        except MavcalError as exc:
            warnings.append(f"accelerometer {a} not calibrated: {exc}")
            if isinstance(exc, WorkerDiedError):
                gates.append(died_gate(f"accel{a}", exc))
            continue
        accels.append(am)
        fits.append((a, fit))
        gates += ag
        if a in joint and not mi_ok and all(g.ok for g in ag):  # (a rejected one is not written at all)
            warnings.append(f"accelerometer {a} written from its own fit: compass {mi}, its joint partner, "
                            "was rejected")
        elif a in joint and a in unconverged and all(g.ok for g in ag):
            warnings.append(f"accelerometer {a} written from its own fit: its joint fit with compass {mi} is not "
                            "certified as the optimum")
    return accels, fits, gates


def judge_accel(prep: Prepared, opts: Options, a: int, joint: AccelMapping | None,
                own: tuple[list[int], AccelFit, float], warnings: list[str] | None = None):
    """Accelerometer ``a`` on its own fit (``own``, :func:`accel_own`): written values
    (``joint``'s when given, else its own), gates, (tilt 95 %, nominal) and held-out error.

    The joint fit's values are written only when they agree with the accelerometer's own
    data: their nominal tilt error against the own fit within the own fit's 95 % tilt bound
    of its own values. A joint fit with few spare equations can reach a point its
    accelerometer's data do not support (seen at 8 intervals: scales 0.79-0.90 from a full
    model with 2 spare equations, own fit 0.99-1.03); then the own values are written and
    ``warnings`` says why (issue 22)."""
    used, fit, ho = own
    mine = (model_for(prep.log).map_accel(fit.gain, fit.bias, prep.log.params.snapshot(), a)
            if joint is None or warnings is not None else None)
    am = joint if joint is not None else mine
    assert am is not None
    tilt = accel_tilt_bounds(fit, am, opts.uncertainty_draws, opts.seed)
    if joint is not None and mine is not None:
        own_tilt = accel_tilt_bounds(fit, mine, opts.uncertainty_draws, opts.seed)
        if tilt[1] > own_tilt[0]:
            assert warnings is not None
            warnings.append(f"accelerometer {a} written from its own fit: its joint fit's values are "
                            f"{tilt[1]:.3g} deg of tilt off its own data, beyond their 95 % bound of "
                            f"{own_tilt[0]:.3g} deg")
            am, tilt = mine, own_tilt
    cov = sensor_coverages(prep.segmentation, opts.accel_instance, coverage_rule(opts, prep.segmentation),
                           accels=[a], compasses=[])[0]
    gates = gates_mod.accel_gates(am, tilt_95_deg=tilt[0], holdout_mps2=ho,
                                  config=model_for(prep.log).gate_config(opts.gates), coverage=cov)
    return am, gates, fit, tilt, ho


def accel_only(prep: Prepared, opts: Options, warnings: list[str], progress=None) -> CalibrationRun:
    """Every wanted accelerometer calibrated from its own intervals alone."""
    params_now = prep.log.params.snapshot()
    accels, gates, fits = [], [], []
    quality = None
    first_used: tuple[int, ...] = ()
    wanted = wanted_instances(prep.raw.accel_instances(), opts, "accel")
    if not wanted:
        raise SourceError(f"{prep.log.source}: no accelerometer data")
    errors = []
    for k, a in enumerate(wanted):
        report(progress, STAGE_FIT, k, len(wanted))
        try:
            am, ag, fit, tilt, ho = judge_accel(prep, opts, a, None, accel_own(prep, opts, a, {}))
        except MavcalError as exc:
            errors.append(exc)
            warnings.append(f"accelerometer {a} not calibrated: {exc}")
            continue
        accels.append(am)
        gates += ag
        fits.append((a, fit))
        if quality is None:
            quality = Quality(float("nan"), tilt[0], float("nan"), tilt[1], ho, float("nan"),
                              fit.cost / fit.dof if fit.dof > 0 else float("nan"))
            first_used = tuple(accel_sets(prep, a)[0])
    report(progress, STAGE_FIT, len(wanted), len(wanted))
    if quality is None:
        raise errors[0]
    if not params_now:
        warnings.append("the log has no parameters: readings were taken as raw and the old values are unknown")
    mapping = combine(accels, [], params_now, [f"accelerometer {am.instance} calibrated alone (no compass)"
                                               for am in accels])
    return CalibrationRun(source=prep.log.source, log=prep.log, raw=prep.raw, segmentation=prep.segmentation,
                          intervals_used=first_used, calibration=None, mapping=mapping, quality=quality,
                          gates=gates_mod.GateReport(tuple(gates)), params_before=params_now,
                          warnings=tuple(dict.fromkeys(list(prep.warnings) + warnings)), accel_fits=tuple(fits))
