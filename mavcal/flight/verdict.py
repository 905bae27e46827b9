"""The verdict on each compass in flight, in words a person can act on.

* **Interference** as compassmot measures it (ArduCopter ``compassmot.cpp``: the motor
  compensation vector's length times the current, as a percentage of the Earth field), here at
  the flight's highest current (or full throttle): below 30 % ok, 30-60 % grey, above 60 %
  bad (ArduPilot's compassmot guidance). The interference *left* is the same with the
  compensation in force subtracted.
* **Wrong in flight** (a compass disagreeing with the reference, and so with the good ones):
  a rotation (its heading differs from the compass-independent yaw, the EKF-GSF's, by more
  than :data:`ROTATION_WRONG_DEG` on average over every heading: a wrong orientation or board
  rotation; its offsets are then not judged, being bent by it; never judged against the EKF's
  yaw, which is fused from the compasses); a constant offset its calibration lacks (the fitted
  offsets differ from those in force by more than :data:`OFFSET_WRONG_MGAUSS` and, on one axis
  at least, by more than :data:`Z_WRONG` standard deviations); a slope with current the others
  lack (the interference left, each axis shrunk by :data:`Z_WRONG` standard deviations, above
  60 % while another compass's is below 30 %). Each test's false-alarm rate under the fit's
  noise model is at most :data:`FALSE_ALARM` per compass (the union bound over the 3 axes); the
  rotation's threshold is 6.7 times the largest 1-sigma the GSF yaw is admitted with (3 deg).
* **Accepted** (its motor compensation goes into ``--param-out``): the motor term was
  identified, the calibration in force is known, and the compass is not wrong by offset or
  rotation (a fit against a wrongly calibrated compass would hide the cause).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mavcal.flight.fit import CompassFit

__all__ = ["Verdict", "judge", "OK_PCT", "BAD_PCT", "OFFSET_WRONG_MGAUSS", "ROTATION_WRONG_DEG", "FALSE_ALARM",
           "Z_WRONG", "pct_text"]

OK_PCT, BAD_PCT = 30.0, 60.0
OFFSET_WRONG_MGAUSS = 40.0
ROTATION_WRONG_DEG = 20.0
#: the false-alarm rate of each WRONG test, per compass, under the fit's noise model: a term is
#: called different from the one in force only if one of its 3 axes is beyond Z_WRONG standard
#: deviations (two-sided, the union bound over the axes: 3 x 2 x (1 - Phi(Z_WRONG)) <= FALSE_ALARM,
#: whatever the axes' correlation)
FALSE_ALARM = 0.001
Z_WRONG = 3.588  # Phi^-1(1 - FALSE_ALARM / 6)
Z95 = 1.959963984540054


def pct_text(x: float) -> str:
    """A percentage as printed: never '-0'."""
    v = round(abs(float(x))) if abs(float(x)) < 0.5 else round(float(x))
    return f"{v:.0f}"


@dataclass(frozen=True)
class Verdict:
    interference_pct: float
    interference_left_pct: float
    level: str  # "ok", "grey", "bad"
    wrong: bool
    causes: tuple[str, ...]  # why it is wrong
    advice: tuple[str, ...]
    accepted: bool
    not_written_because: str
    offset_lack_mgauss: np.ndarray
    rotation_deg: float
    summary: str


def _level(pct: float) -> str:
    return "ok" if pct < OK_PCT else ("grey" if pct <= BAD_PCT else "bad")


def judge(fits: Mapping[int, CompassFit], driver_kind: str, missing: Mapping[int, tuple[str, ...]],
          ofs_in_force: Mapping[int, np.ndarray], mot_in_force: Mapping[int, np.ndarray] | None = None,
          heading_offset_deg: Mapping[int, float] | None = None) -> dict[int, Verdict]:
    """The verdicts of the fitted compasses; ``heading_offset_deg``: each compass's mean heading
    minus the compass-independent yaw's (:func:`mavcal.flight.reference.heading_offset_deg`)."""
    unit = "mGauss/A" if driver_kind == "current" else "mGauss per full throttle"
    at = "the highest current" if driver_kind == "current" else "full throttle"
    pct: dict[int, float] = {}
    left: dict[int, float] = {}
    for i, f in fits.items():
        B = float(np.linalg.norm(f.B_ned_mgauss)) or 1.0
        xmax = abs(f.driver_max) if driver_kind == "current" else 1.0
        pct[i] = float(np.linalg.norm(f.mot_per_unit)) * xmax / B * 100.0
        before = np.zeros(3) if mot_in_force is None else np.asarray(mot_in_force[i])
        left[i] = float(np.linalg.norm(f.mot_per_unit - before)) * xmax / B * 100.0
    out: dict[int, Verdict] = {}
    for i, f in fits.items():
        causes: list[str] = []
        advice: list[str] = []
        rot = float((heading_offset_deg or {}).get(i, 0.0))
        rotated = abs(rot) > ROTATION_WRONG_DEG
        if rotated:
            causes.append(f"its heading is {rot:+.0f} deg off the compass-independent yaw at every heading: "
                          "a wrong rotation (its orientation or the board's)")
            advice.append("check how it is mounted and its orientation parameter, calibrate it again; or disable it")
        lack = f.ofs_mgauss - np.asarray(ofs_in_force[i]) if f.fitted_ofs else np.zeros(3)
        nlack = float(np.linalg.norm(lack))
        sd = np.asarray(f.ofs_bound95_mgauss, dtype=float) / Z95
        beyond = bool(np.any(np.abs(lack) > Z_WRONG * sd)) and bool(np.all(np.isfinite(sd)))
        if not rotated and f.fitted_ofs and nlack > OFFSET_WRONG_MGAUSS and beyond:
            causes.append(f"a constant {nlack:.0f} mGauss offset in flight that its calibration lacks "
                          f"(offsets {_v(f.ofs_mgauss)} fit the flight, {_v(ofs_in_force[i])} are in force)")
            advice.append("calibrate it again away from metal, or take the fitted offsets; if it keeps "
                          "disagreeing, disable it")
        others = [left[j] for j in fits if j != i]
        before = np.zeros(3) if mot_in_force is None else np.asarray(mot_in_force[i], dtype=float)
        msd = np.asarray(f.mot_bound95_per_unit, dtype=float) / Z95
        shrunk = np.maximum(np.abs(f.mot_per_unit - before) - Z_WRONG * msd, 0.0)  # its lower bound, axis by axis
        xmax_i = abs(f.driver_max) if driver_kind == "current" else 1.0
        left_low = float(np.linalg.norm(shrunk)) * xmax_i / (float(np.linalg.norm(f.B_ned_mgauss)) or 1.0) * 100.0
        if f.fitted_mot and left_low > BAD_PCT and others and min(others) < OK_PCT:
            causes.append(f"a slope with {driver_kind} of {np.linalg.norm(f.mot_per_unit):.2f} {unit} that the "
                          f"other compass{'es' if len(others) > 1 else ''} lack "
                          f"({pct_text(left[i])} % of the field left "
                          f"uncompensated at {at})")
            advice.append("move it away from the power wires (or twist them), or write the fitted compensation")
        lvl = _level(pct[i])
        wrong = bool(causes)
        why_not = ""
        if missing.get(i):
            why_not = "the calibration in force is unknown (not in the log: " + ", ".join(missing[i][:4]) + ")"
        elif not f.fitted_mot:
            why_not = (f"the {driver_kind} barely varied in this flight (span {f.driver_span:.3g}): "
                       "the motor term is not identified, kept as in force")
        elif any(c.startswith(("a constant", "its heading is")) for c in causes):
            why_not = "the compass is wrong in flight beyond its motor interference"
        accepted = not why_not
        if lvl != "ok" and not wrong:
            advice.append("write the fitted compensation (--param-out)" if lvl == "grey" else
                          "move the compass away from the power wires or twist them, then write the compensation")
        mot_txt = (f"motor term fit {_v(f.mot_per_unit, 2)} +- {_v(f.mot_bound95_per_unit, 2)} {unit}"
                   if f.fitted_mot else "motor term not identified (kept)")
        summary = (f"interference {pct_text(pct[i])} % of the field at {at} ({lvl}), "
                   f"{pct_text(left[i])} % left with the compensation in force; {mot_txt}; "
                   f"delay {round(f.delay_s, 2) + 0.0:+.2f} s; "
                   f"heading error against the EKF yaw {f.heading_err_before_deg:.1f} -> "
                   f"{f.heading_err_after_deg:.1f} deg")
        out[i] = Verdict(pct[i], left[i], lvl, wrong, tuple(causes), tuple(advice), accepted, why_not, lack, rot,
                         summary)
    return out


def _v(x, nd: int = 0) -> str:
    return "(" + ", ".join(f"{float(v):.{nd}f}" for v in x) + ")"
