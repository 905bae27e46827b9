"""The in-flight stage end to end: a flight log -> one :class:`CompassResult` per compass.

Per compass: the calibration in force undone as logged (the autopilot's in-flight model,
:mod:`mavcal.autopilot.flight`, from the registry: ArduPilot's or PX4's), the
reference (:mod:`mavcal.flight.reference`), the fit (:mod:`mavcal.flight.fit`) and the verdict
(:mod:`mavcal.flight.verdict`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mavcal.autopilot import flight as apf
from mavcal.autopilot import model_named
from mavcal.errors import InsufficientDataError
from mavcal.flight.airborne import judge_flight
from mavcal.flight.fit import CompassFit, FitInput, fit_compass
from mavcal.flight.reference import heading_offset_deg, reference_at
from mavcal.flight.verdict import ROTATION_WRONG_DEG, Verdict, judge
from mavcal.sources.flight_logs import read_flight_log
from mavcal.sources.flight_series import FlightSeries

__all__ = ["CompassResult", "FlightResult", "run_flight", "analyse"]


@dataclass(frozen=True)
class CompassResult:
    instance: int
    fit: CompassFit | None
    verdict: Verdict
    missing_params: tuple[str, ...]
    in_use: bool | None
    ofs_in_force_mgauss: np.ndarray
    mot_in_force: np.ndarray
    gsf_heading_err_deg: tuple[float, float]  # RMS against the EKF-GSF yaw: as logged, as fitted (NaN: no GSF)
    compensation: dict[str, float] = field(default_factory=dict)  # its parameters as fitted (written if accepted)
    id_name: str = ""  # the parameter holding its device id ("": none known)


@dataclass(frozen=True)
class FlightResult:
    source: str
    driver_kind: str  # "current" or "throttle"
    motct_in_force: int | None
    yaw_source: str
    field_source: str
    B0_ned_mgauss: np.ndarray
    compasses: tuple[CompassResult, ...]
    warnings: tuple[str, ...]
    rotation_reference: str = "gsf"  # "gsf": the rotation judged against the compass-independent yaw; "none"
    autopilot: str = "ArduPilot"
    type_values: dict[str, float] = field(default_factory=dict)  # the parameter selecting the driver, as fitted
    identity: dict[str, float] = field(default_factory=dict)  # the log's system id and compass device ids
    sysid_param: str = ""  # which of ``identity`` is the system id


#: a battery current below this (A) is no current sensor's reading
NEGATIVE_CURRENT_A = -1.0
#: a battery current spanning less than this (A) over the log never varied
MIN_CURRENT_SPAN_A = 0.5


def no_current_sensor(s: FlightSeries) -> str:
    """Why the log has no usable current sensor ("" when it has one)."""
    c = s.current_a[np.isfinite(s.current_a)] if len(s.current_a) else s.current_a
    if len(c) <= 10:
        return f"no battery current logged ({s.current_message})"
    if float(np.median(c)) < NEGATIVE_CURRENT_A:
        return f"no current sensor: the battery current reads {float(np.median(c)):.1f} A (negative)"
    if float(np.ptp(c)) < MIN_CURRENT_SPAN_A:
        return f"no current sensor: the battery current never varies ({float(np.median(c)):.1f} A throughout)"
    return ""


def run_flight(path: str | Path, *, yaw: str = "ekf", driver: str = "auto") -> FlightResult:
    return analyse(read_flight_log(path), yaw=yaw, driver=driver)


def _current(s: FlightSeries, battery: int) -> FlightSeries:
    """``s`` with the current of battery ``battery`` (the one the firmware compensates with) as its current."""
    if battery == 0 or battery not in s.battery_currents:
        return s
    t, a = s.battery_currents[battery]
    return replace(s, current_time_s=t, current_a=a)


def _in_force_driver(s: FlightSeries, motct: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The series the compensation in force was driven by (empty when none is in force)."""
    if motct == apf.COMPENSATION_CURRENT:
        return s.current_time_s, s.current_a
    if motct == apf.COMPENSATION_THROTTLE:
        return s.throttle_time_s, s.throttle
    return np.zeros(0), np.zeros(0)


def _driver(s: FlightSeries, params_motct: int | None, driver: str) -> tuple[str, np.ndarray, np.ndarray, list[str]]:
    warn: list[str] = []
    no_sensor = no_current_sensor(s)
    if driver == "auto":
        if params_motct == apf.COMPENSATION_THROTTLE:
            driver = "throttle"
        elif not no_sensor:
            driver = "current"
        else:  # the throttle only when asked (or in force): a fit against it is not what the firmware uses
            raise InsufficientDataError(f"{s.source}: {no_sensor}; --driver throttle fits against the throttle")
    if driver == "current":
        if no_sensor:
            raise InsufficientDataError(f"{s.source}: {no_sensor}; --driver throttle fits against the throttle")
        return "current", s.current_time_s, s.current_a, warn
    if no_sensor:
        warn.append(f"{no_sensor}: the interference is fitted against the throttle")
    if len(s.throttle) < 10:
        raise InsufficientDataError(f"{s.source}: no throttle logged ({s.throttle_message})")
    return "throttle", s.throttle_time_s, s.throttle, warn


def _require_flight(s: FlightSeries) -> None:
    """A log without a flight (armed and airborne, :mod:`mavcal.flight.airborne`) is refused."""
    if s.evidence is None:  # not read from a log: a synthetic flight
        return
    flight = judge_flight(s.evidence)
    if not flight.flew:
        raise InsufficientDataError(f"{s.source}: no flight in this log: nothing to say about the compasses in "
                                    f"flight ({flight.why}; the stage needs a flight, armed and airborne)")


def _disagreement_deg(against_ekf: dict[int, float]) -> float:
    """The largest heading difference between two compasses (deg; 0 with fewer than two)."""
    return max((abs(float(np.angle(np.exp(1j * np.radians(a - b)), deg=True)))
                for a in against_ekf.values() for b in against_ekf.values()), default=0.0)


def _no_independent_yaw(against_ekf: dict[int, float], gsf_message: str = "XKY0") -> str:
    """What is said without a compass-independent yaw: no rotation verdict, how far the compasses
    disagree with each other (each against the EKF yaw, which is fused from them)."""
    spread = ""
    if len(against_ekf) > 1:
        d = _disagreement_deg(against_ekf)
        spread = (f"; the compasses' headings disagree by up to {d:.0f} deg ("
                  + ", ".join(f"compass{i} {v:+.0f}" for i, v in sorted(against_ekf.items()))
                  + " deg against the EKF yaw, which is fused from them)")
    return (f"no compass-independent yaw in this log (no converged EKF-GSF yaw, {gsf_message}): "
            "a wrong rotation is not judged" + spread)


def _heading_checks(s: FlightSeries, c, a: apf.AsApplied, f: apf.InForce, fit: CompassFit, ref, dt: np.ndarray,
                    dx: np.ndarray) -> tuple[str, float, tuple[float, float]] | None:
    """The rotation check against the compass-independent yaw where it has converged (else the
    reference's yaw), on the field corrected as fitted (offsets and interference bend single
    headings, not all of them): (the yaw's source, the mean heading offset with the offsets in force
    (a rotated compass bends the fitted ones), the RMS heading error as logged and as fitted);
    None with too few samples."""
    gref = reference_at(s, c.time_s, "gsf") if len(s.gsf_time_s) > 10 else ref
    gk = gref.valid & c.healthy
    if gk.sum() < 30:
        return None
    x = np.interp(c.time_s[gk] - fit.delay_s, dt, dx)
    mag = (a.field_mgauss[gk] + (f.A @ (fit.ofs_mgauss - a.ofs_mgauss[gk]).T).T
           - a.motor_ofs_mgauss[gk] + x[:, None] * fit.mot_per_unit)
    after = heading_offset_deg(gref.R[gk], mag, gref.B0_ned_mgauss)[2]
    off = heading_offset_deg(gref.R[gk], a.field_mgauss[gk] - a.motor_ofs_mgauss[gk] + x[:, None] * fit.mot_per_unit,
                             gref.B0_ned_mgauss)[0]
    before = heading_offset_deg(gref.R[gk], a.field_mgauss[gk], gref.B0_ned_mgauss)[2]
    return gref.yaw_source, off, (before, after)


def analyse(s: FlightSeries, *, yaw: str = "ekf", driver: str = "auto") -> FlightResult:
    _require_flight(s)
    model = model_named(s.autopilot).flight()
    s = _current(s, model.battery_instance(s.params))
    motct = model.motor_type(s.params)
    kind, dt, dx, warnings = _driver(s, motct, driver)
    kind_code = apf.kind_code(kind)
    ft, fx = _in_force_driver(s, motct)
    applied: dict[int, apf.AsApplied] = {}
    results: list[CompassResult] = []
    yaw_source = field_source = "-"
    B0 = np.zeros(3)
    fits: dict[int, CompassFit] = {}
    info: dict[int, apf.InForce] = {}
    rotation: dict[int, float] = {}
    gsf_err: dict[int, tuple[float, float]] = {}
    against_ekf: dict[int, float] = {}  # heading minus the EKF yaw's (not independent: fused from the compasses)
    for c in s.compasses:
        try:
            f = model.in_force(s.params, c)
        except ValueError as exc:  # an instance the firmware does not have (a damaged log)
            warnings.append(f"compass{c.instance}: left out: {exc}")
            continue
        info[c.instance] = f
        a = applied[c.instance] = model.as_applied(f, c, s.params, ft, fx)
        ref = reference_at(s, c.time_s, yaw)
        yaw_source, field_source, B0 = ref.yaw_source, ref.field_source, ref.B0_ned_mgauss
        keep = ref.valid & c.healthy
        if keep.sum() < 30:
            continue
        raw = a.raw_mgauss[keep]
        ofs_force = np.median(a.ofs_mgauss[keep], axis=0)
        # the compensation in force applies to the driver the firmware uses; another driver: none of it
        mot_force = f.mot_per_unit if motct == kind_code else np.zeros(3)
        inp = FitInput(c.time_s[keep], raw, f.matrix_times_scale, ref.R[keep], dt, dx, kind, ref.B0_ned_mgauss,
                       ofs_force, mot_force, sigma_B_mgauss=0.03 * float(np.linalg.norm(ref.B0_ned_mgauss))
                       if ref.field_source == "wmm" else 500.0)
        try:
            fit = fits[c.instance] = fit_compass(inp)
        except ValueError as exc:
            warnings.append(f"compass{c.instance}: {exc}")
            continue
        checked = _heading_checks(s, c, a, f, fit, ref, dt, dx)
        if checked is not None:
            source, off, before_after = checked
            if source == "gsf":
                rotation[c.instance], gsf_err[c.instance] = off, before_after
            elif np.isfinite(off):
                against_ekf[c.instance] = off
    if not fits:
        raise InsufficientDataError(f"{s.source}: no compass has enough samples in flight with a known attitude")
    rot_ref = "gsf" if rotation else "none"
    if not rotation:
        warnings.append(_no_independent_yaw(against_ekf, s.gsf_message))
    verdicts = judge(fits, kind, {i: info[i].missing for i in fits},
                     {i: np.median(applied[i].ofs_mgauss, axis=0) for i in fits},
                     {i: (info[i].mot_per_unit if motct == kind_code else np.zeros(3)) for i in fits}, rotation)
    split = _disagreement_deg(against_ekf) if not rotation else 0.0
    if split > ROTATION_WRONG_DEG:  # one of them is turned, and no independent yaw says which: none written
        why = (f"the compasses' headings disagree by {split:.0f} deg and no compass-independent yaw ({s.gsf_message}) "
               "says which is right")
        verdicts = {i: replace(v, accepted=False, not_written_because=v.not_written_because or why)
                    for i, v in verdicts.items()}
    for c in s.compasses:
        if c.instance not in fits:
            continue
        f = info[c.instance]
        results.append(CompassResult(c.instance, fits[c.instance], verdicts[c.instance], f.missing,
                                     model.compass_in_use(s.params, f),
                                     np.median(applied[c.instance].ofs_mgauss, axis=0), f.mot_per_unit,
                                     gsf_err.get(c.instance, (float("nan"), float("nan"))),
                                     model.param_values(f, kind_code, fits[c.instance].mot_per_unit),
                                     model.id_name(f.slot)))
    sysid = next((n for n in model.sysid_params if n in s.params), "")
    ident = [sysid] + [c.id_name for c in results if c.id_name]
    return FlightResult(s.source, kind, motct, yaw_source, field_source, B0, tuple(results), tuple(warnings),
                        rot_ref, model.name, model.type_values(kind_code, s.params),
                        {n: float(s.params[n]) for n in ident if n in s.params}, sysid)


def param_values(r: FlightResult) -> dict[str, float]:
    """The parameters to write: the driver type and the motor compensation of the accepted compasses."""
    out: dict[str, float] = {}
    for c in r.compasses:
        if c.fit is not None and c.verdict.accepted:
            out.update(c.compensation)
    if out:
        out.update(r.type_values)
    return out
