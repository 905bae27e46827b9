"""The in-flight stage end to end: a flight log -> one :class:`CompassResult` per compass.

Per compass: the calibration in force undone as logged (:mod:`mavcal.ardupilot.flight`), the
reference (:mod:`mavcal.flight.reference`), the fit (:mod:`mavcal.flight.fit`) and the verdict
(:mod:`mavcal.flight.verdict`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mavcal.autopilot import flight as apf
from mavcal.errors import InsufficientDataError
from mavcal.flight.airborne import judge_flight
from mavcal.flight.fit import CompassFit, FitInput, fit_compass
from mavcal.flight.reference import heading_offset_deg, reference_at
from mavcal.flight.verdict import ROTATION_WRONG_DEG, Verdict, judge
from mavcal.sources.flight_series import CompassSeries, FlightSeries, read_flight_series

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


#: a battery current below this (A) is no current sensor's reading
NEGATIVE_CURRENT_A = -1.0
#: a battery current spanning less than this (A) over the log never varied
MIN_CURRENT_SPAN_A = 0.5


def no_current_sensor(s: FlightSeries) -> str:
    """Why the log has no usable current sensor ("" when it has one)."""
    c = s.current_a[np.isfinite(s.current_a)] if len(s.current_a) else s.current_a
    if len(c) <= 10:
        return "no battery current logged (BAT)"
    if float(np.median(c)) < NEGATIVE_CURRENT_A:
        return f"no current sensor: the battery current reads {float(np.median(c)):.1f} A (negative)"
    if float(np.ptp(c)) < MIN_CURRENT_SPAN_A:
        return f"no current sensor: the battery current never varies ({float(np.median(c)):.1f} A throughout)"
    return ""


def run_flight(path: str | Path, *, yaw: str = "ekf", driver: str = "auto") -> FlightResult:
    return analyse(read_flight_series(path), yaw=yaw, driver=driver)


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
        raise InsufficientDataError(f"{s.source}: no throttle logged (CTUN)")
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


def _no_independent_yaw(against_ekf: dict[int, float]) -> str:
    """What is said without a compass-independent yaw: no rotation verdict, how far the compasses
    disagree with each other (each against the EKF yaw, which is fused from them)."""
    spread = ""
    if len(against_ekf) > 1:
        d = _disagreement_deg(against_ekf)
        spread = (f"; the compasses' headings disagree by up to {d:.0f} deg ("
                  + ", ".join(f"compass{i} {v:+.0f}" for i, v in sorted(against_ekf.items()))
                  + " deg against the EKF yaw, which is fused from them)")
    return ("no compass-independent yaw in this log (no converged EKF-GSF yaw, XKY0): "
            "a wrong rotation is not judged" + spread)


def _heading_checks(s: FlightSeries, c: CompassSeries, f: apf.InForce, fit: CompassFit, dt: np.ndarray, dx: np.ndarray
                    ) -> tuple[bool, float, float, float] | None:
    """The rotation check against the compass-independent yaw where it has converged (else the
    EKF's), on the field corrected as fitted (offsets and interference bend single headings, not
    all of them): (the yaw is the GSF's, the heading offset on the offsets in force, the RMS
    heading error as logged, as fitted); None with too few samples."""
    gref = reference_at(s, c.time_s, "gsf") if len(s.gsf_time_s) > 10 else reference_at(s, c.time_s, "ekf")
    gk = gref.valid & c.healthy
    if gk.sum() < 30:
        return None
    x = np.interp(c.time_s[gk] - fit.delay_s, dt, dx)
    mag = (c.field_mgauss[gk] + (f.matrix_times_scale @ (fit.ofs_mgauss - c.ofs_mgauss[gk]).T).T
           - c.motor_ofs_mgauss[gk] + x[:, None] * fit.mot_per_unit)
    _, _, after = heading_offset_deg(gref.R[gk], mag, gref.B0_ned_mgauss)
    # the rotation on the offsets in force: a rotated compass bends the fitted ones
    off = heading_offset_deg(gref.R[gk], c.field_mgauss[gk] - c.motor_ofs_mgauss[gk] + x[:, None] * fit.mot_per_unit,
                             gref.B0_ned_mgauss)[0]
    before = heading_offset_deg(gref.R[gk], c.field_mgauss[gk], gref.B0_ned_mgauss)[2]
    return gref.yaw_source == "gsf", off, before, after


def analyse(s: FlightSeries, *, yaw: str = "ekf", driver: str = "auto") -> FlightResult:
    _require_flight(s)
    motct = apf.motor_type(s.params)
    kind, dt, dx, warnings = _driver(s, motct, driver)
    kind_code = apf.COMPENSATION_CURRENT if kind == "current" else apf.COMPENSATION_THROTTLE
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
            f = apf.in_force(s.params, c.instance)
        except ValueError as exc:  # an instance the firmware does not have (a damaged log)
            warnings.append(f"compass{c.instance}: left out: {exc}")
            continue
        info[c.instance] = f
        ref = reference_at(s, c.time_s, yaw)
        yaw_source, field_source, B0 = ref.yaw_source, ref.field_source, ref.B0_ned_mgauss
        keep = ref.valid & c.healthy
        if keep.sum() < 30:
            continue
        raw = apf.raw_field(f, c.field_mgauss[keep], c.ofs_mgauss[keep], c.motor_ofs_mgauss[keep])
        ofs_force = np.median(c.ofs_mgauss[keep], axis=0)
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
        checked = _heading_checks(s, c, f, fit, dt, dx)
        if checked is not None:
            independent, off, before, after = checked
            if independent:
                rotation[c.instance] = off
                gsf_err[c.instance] = (before, after)
            elif np.isfinite(off):
                against_ekf[c.instance] = off
    if not fits:
        raise InsufficientDataError(f"{s.source}: no compass has enough samples in flight with a known attitude")
    rot_ref = "gsf" if rotation else "none"
    if not rotation:
        warnings.append(_no_independent_yaw(against_ekf))
    verdicts = judge(fits, kind, {i: info[i].missing for i in fits},
                     {i: np.median(next(c for c in s.compasses if c.instance == i).ofs_mgauss, axis=0) for i in fits},
                     {i: (info[i].mot_per_unit if motct == kind_code else np.zeros(3)) for i in fits}, rotation)
    split = _disagreement_deg(against_ekf) if not rotation else 0.0
    if split > ROTATION_WRONG_DEG:  # one of them is turned, and no independent yaw says which: none written
        why = (f"the compasses' headings disagree by {split:.0f} deg and no compass-independent yaw (XKY0) "
               "says which is right")
        verdicts = {i: replace(v, accepted=False, not_written_because=v.not_written_because or why)
                    for i, v in verdicts.items()}
    for c in s.compasses:
        if c.instance not in fits:
            continue
        f = info[c.instance]
        results.append(CompassResult(c.instance, fits[c.instance], verdicts[c.instance], f.missing,
                                     apf.compass_in_use(s.params, c.instance),
                                     np.median(c.ofs_mgauss, axis=0), f.mot_per_unit,
                                     gsf_err.get(c.instance, (float("nan"), float("nan")))))
    return FlightResult(s.source, kind, motct, yaw_source, field_source, B0, tuple(results), tuple(warnings),
                        rot_ref)


def param_values(r: FlightResult) -> dict[str, float]:
    """The parameters to write: the driver type and the motor compensation of the accepted compasses."""
    out: dict[str, float] = {}
    kind = apf.COMPENSATION_CURRENT if r.driver_kind == "current" else apf.COMPENSATION_THROTTLE
    for c in r.compasses:
        if c.fit is not None and c.verdict.accepted:
            out.update(apf.motor_param_values(c.instance, c.fit.mot_per_unit))
    if out:
        out.update(apf.motor_type_value(kind))
    return out
