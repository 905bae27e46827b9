"""Each compass judged on its fit with the primary accelerometer (:class:`PairFit`, fitted and mapped by
:mod:`mavcal.fits`): its held-out error, its 95 % heading bound (:mod:`mavcal.judging.quality`), its own
still intervals (:mod:`mavcal.coverage`) and its gates (:func:`mavcal.autopilot.gates.compass_gates`,
with its autopilot's limits): :func:`judge_compass`. The accelerometers' judging is beside it,
:mod:`mavcal.judging.accel`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

from mavcal.autopilot import gates as gates_mod
from mavcal.autopilot import model_for
from mavcal.autopilot.mapping import ParamMapping
from mavcal.core.types import Calibration
from mavcal.coverage import ACCEL_STATE_WORDS, REACH_FLOWN_TILT_DEG, ReachCoverage, sensor_coverages, within_reach
from mavcal.errors import MavcalError
from mavcal.fit_inputs import coverage_rule
from mavcal.judging.quality import holdout_rms
from mavcal.run import CalibrationRun, Options, Prepared
from mavcal.workers import Outcome

__all__ = ["PairFit", "judge_compass"]


@dataclass(frozen=True, eq=False)
class PairFit:
    """A pair's joint fit and mapping (what a worker sends back: no readings)."""

    used: list[int]
    cal: Calibration
    mapping: ParamMapping
    params_now: dict[str, float]
    warnings: list[str]
    reach: ReachCoverage | None = None  # poses within reach: what they identify (the accelerometer's Z scale held)
    accel_state: str = "calibrated"  # the primary accelerometer's calibration in force (coverage.accel_state)


def judge_compass(prep: Prepared, opts: Options, f: PairFit, holdout: list[Outcome], quality_out: Outcome
                  ) -> CalibrationRun | MavcalError:
    """The pair's run from its fit and its later jobs' outcomes (the held-out slices in order,
    the bounds): the held-out error, the compass gates."""
    bad = next((r for ok, r in holdout + [quality_out] if not ok), None)
    if bad is not None:
        return bad
    ho = holdout_rms([r for _, r in holdout]) if opts.holdout else (float("nan"), float("nan"))
    quality = replace(quality_out[1], holdout_accel_mps2=ho[0], holdout_mag_mgauss=ho[1])
    cal, cm, seg = f.cal, f.mapping.compass[0], prep.segmentation
    cov = sensor_coverages(seg, opts.accel_instance, coverage_rule(opts, seg), accels=[],
                           compasses=[opts.mag_instance])[0]
    if f.reach is not None:  # the rule of poses within reach identified it (else the fit was refused)
        cov = within_reach(cov, f.reach)
    model = model_for(prep.log)
    report = gates_mod.GateReport(tuple(gates_mod.compass_gates(
        cm, f.params_now, model=model, coverage=cov,
        heading_95_deg=quality.heading_95_deg, holdout_mgauss=ho[1], config=model.gate_config(opts.gates),
        fit_converged=cal.converged,
        fit_message=cal.certificate.reason if cal.certificate is not None and cal.certificate.reason else cal.message,
        fit_advice=gates_mod.FIT_ADVICE if f.reach is None else f.reach.refit_advice(),
        heading_advice=gates_mod.HEADING_ADVICE if f.reach is None else f.reach.heading_advice(f.accel_state))))
    warnings = list(f.warnings)
    steep = quality.heading_95_steep_deg
    if math.isfinite(steep) and steep > quality.heading_95_deg:  # within reach, the Z scale the factory's
        warnings.append(
            f"compass {opts.mag_instance}: the heading bound is over tilts up to {REACH_FLOWN_TILT_DEG:g} deg (the "
            f"poses'); flown steeper, the accelerometer's Z scale (kept: {ACCEL_STATE_WORDS[f.accel_state]}) "
            f"limits it: at 30 deg of tilt the heading error could reach {steep:.2f} deg (95 %); calibrate the "
            "accelerometer fully (its 6-side calibration) before flying steeper")
    return CalibrationRun(source=prep.log.source, log=prep.log, raw=prep.raw, segmentation=seg,
                          intervals_used=tuple(f.used), calibration=cal, mapping=f.mapping, quality=quality,
                          gates=report, params_before=f.params_now, warnings=tuple(dict.fromkeys(warnings)),
                          kept=f.reach.kept if f.reach is not None else ())
