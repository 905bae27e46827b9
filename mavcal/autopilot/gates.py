"""Quality gates applied before anything is written, per sensor, with reasons in words.

The autopilot's own limits (:class:`GateConfig`'s defaults are ArduPilot's: AP_Compass arming
checks and CompassCalibrator::fit_acceptable, AccelCalibrator: compass offset length <= its
offset limit (default 1800 mGauss), 0.2 < DIA < 5, |ODI| < 1, field 185-875 mGauss; accelerometer
offsets <= 3.5 m/s^2 per axis, scales 0.8-1.2; each model's ``gate_config`` puts in its own, and
its ``compass_offset_max`` and ``compass_slot_gate`` read the vehicle's). Ours: enough intervals
and orientations, held-out reconstruction error, parameter uncertainty (95 % heading and tilt
error bounds).

The data come first: when the still intervals cannot identify a sensor (too few gravity
directions, too few field directions, i.e. headings, for a compass: the rule of
:mod:`mavcal.coverage`, which ``mavcal segments`` reports too; or a 95 % bound so wide that
nothing was identified), its verdict gives that cause alone. Gates that would name a
disturbance (steel, magnets, currents) say so only when the data would have sufficed; they
are still in the report (:attr:`GateReport.gates`).

Every accelerometer and compass gets its own gates and its own verdict
(:meth:`GateReport.verdicts`): an accelerometer is judged on its own fit (tilt bound,
held-out error), a compass on its fit with the accelerometer it is paired with (heading
bound, held-out error); nothing of one sensor's misfit enters another's verdict.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mavcal.autopilot.verdicts import (  # noqa: F401  (re-exported: the gates' vocabulary is the neutral layer's)
    CAUSE_IN_FORCE,
    EARTH_FIELD_MGAUSS,
    YES_NO_GATES,
    Gate,
    GateReport,
    SensorVerdict,
    reason_text,
)
from mavcal.coverage import UNIDENTIFIED_HEADING_DEG, UNIDENTIFIED_TILT_DEG
from mavcal.determined import bound_value_words, determined


class CompassLimits(Protocol):
    """What the compass gates ask of an autopilot's model (:class:`mavcal.autopilot.model.AutopilotModel`)."""

    def compass_offset_max(self, params: Mapping[str, float]) -> float: ...

    def compass_slot_gate(self, params: Mapping[str, float], instance: int) -> tuple[float, str, str] | None: ...


@dataclass(frozen=True)
class GateConfig:
    """The gates' thresholds. The autopilot's own limits default to ArduPilot's (the values of its
    limits table, which ``apply``/``restore`` check too; a test holds them equal); another
    autopilot's model puts in its own (``gate_config``). The rest are mavcal's."""

    accel_offset_max_mps2: float = 3.5
    accel_scale_range: tuple[float, float] = (0.8, 1.2)
    compass_offset_max_mgauss: float | None = None  # None: the model's offset limit of the vehicle
    dia_range: tuple[float, float] = (0.2, 5.0)
    odi_max: float = 1.0
    field_range_mgauss: tuple[float, float] = (185.0, 875.0)
    min_intervals: int = 6
    min_field_directions: int = 8  # a compass's distinct field directions (mavcal.coverage)
    heading_95_max_deg: float = 2.0
    tilt_95_max_deg: float = 0.5
    holdout_accel_max_mps2: float = 0.15
    holdout_mag_max_mgauss: float = 15.0
    #: whose limits the offset, scale, soft-iron and field gates are, in the reasons' words (each
    #: autopilot's model names its own in ``gate_config``: "ArduPilot's")
    limits_of: str = "the autopilot's"
    #: the autopilot whose field range the field gate applies
    autopilot: str = "the autopilot"
    #: what the compass offset limit is called in the reasons
    offset_limit_name: str = "the offset limit"


def _adder(gates: list[Gate]):
    def add(sensor: str, name: str, ok, value, limit: str, reason: str, cause: str = "") -> None:
        """Record a gate; NaN means it did not run (never rejects); the reason is kept only when it failed."""
        v = float(value)
        ran = bool(np.isfinite(v))
        ok = bool(ok) or not ran
        gates.append(Gate(sensor, name, ok, v, limit, "" if ok else reason, ran, "" if ok else cause))
    return add


def _data_gates(add, s: str, n_intervals: int, n_orientations: int, c: GateConfig, coverage=None) -> bool:
    """The gates of the data (:mod:`mavcal.coverage`'s rule when ``coverage``, a
    :class:`~mavcal.coverage.SensorCoverage`, is given); True when the data identify the sensor."""
    if coverage is None:
        add(s, "intervals", n_intervals >= c.min_intervals, n_intervals, f">= {c.min_intervals}",
            f"only {n_intervals} still intervals: hold the vehicle still in more orientations", "data")
        add(s, "orientations", n_orientations >= min(c.min_intervals, 6), n_orientations, ">= 6 distinct",
            f"only {n_orientations} distinct orientations: add poses on every side", "data")
        return n_intervals >= c.min_intervals and n_orientations >= min(c.min_intervals, 6)
    r, add_text = coverage.rule, f": {coverage.add}" if coverage.add else ""
    add(s, "orientations", coverage.n_orientations >= r.min_orientations, coverage.n_orientations,
        f">= {r.min_orientations} distinct gravity directions",
        f"only {coverage.n_orientations} distinct gravity directions: too few orientations to identify {s}"
        f"{add_text}", "data")
    add(s, "intervals", coverage.n_intervals >= r.min_intervals, coverage.n_intervals, f">= {r.min_intervals}",
        f"only {coverage.n_intervals} still intervals{add_text}", "data")
    if coverage.n_field_directions is not None:
        add(s, "field directions", coverage.n_field_directions >= r.min_field_directions,
            coverage.n_field_directions, f">= {r.min_field_directions} distinct",
            f"only {coverage.n_field_directions} distinct field directions: too few headings to identify {s}"
            f"{add_text}", "data")
    return bool(coverage.identifiable)


def accel_gates(am, *, n_intervals: int = 0, n_orientations: int = 0, tilt_95_deg: float, holdout_mps2: float,
                config: GateConfig = GateConfig(), coverage=None) -> list[Gate]:
    """The gates of one accelerometer (:class:`~mavcal.autopilot.mapping.AccelMapping`): its own
    values, its own still intervals (``coverage``, a :class:`~mavcal.coverage.SensorCoverage`,
    or the counts), and the tilt bound and held-out error of its own fit."""
    gates: list[Gate] = []
    add, c = _adder(gates), config
    s = f"accel{am.instance}"
    _offsets_gate(add, s, am, c)
    _scales_gate(add, s, am, c)
    enough = _data_gates(add, s, n_intervals, n_orientations, c, coverage)
    if enough and tilt_95_deg >= UNIDENTIFIED_TILT_DEG:
        add(s, "tilt uncertainty", False, tilt_95_deg, f"<= {c.tilt_95_max_deg} deg (95 %)",
            f"the poses do not identify {s}: its tilt error is {bound_value_words('tilt', tilt_95_deg)}; add "
            "poses on every side, each held still for 3-5 s", "data")
    else:
        add(s, "tilt uncertainty", tilt_95_deg <= c.tilt_95_max_deg, tilt_95_deg,
            f"<= {c.tilt_95_max_deg} deg (95 %)",
            f"the tilt error {_could_reach('tilt', tilt_95_deg)}: add still poses, each held longer")
    add(s, "held-out error", holdout_mps2 <= c.holdout_accel_max_mps2, holdout_mps2,
        f"<= {c.holdout_accel_max_mps2} m/s^2",
        f"a pose left out of the accelerometer's own fit is predicted {holdout_mps2:.3f} m/s^2 off: the vehicle "
        "moved during the intervals; hold each pose still and record again")
    return gates


def _offsets_gate(add, s: str, am, c: GateConfig) -> None:
    ofs = float(np.abs(np.asarray(am.new.ofs_mps2)).max())
    add(s, "offsets", ofs <= c.accel_offset_max_mps2, ofs, f"<= {c.accel_offset_max_mps2} m/s^2",
        f"accelerometer offset {ofs:.2f} m/s^2 is beyond {c.limits_of} limit: a damaged IMU, "
        "or readings that are not in m/s^2")


def _scales_gate(add, s: str, am, c: GateConfig) -> None:
    sc = np.asarray(am.new.scale)
    lo, hi = c.accel_scale_range
    worst = float(sc[np.argmax(np.abs(sc - 1))])
    add(s, "scales", np.all((sc >= lo) & (sc <= hi)), worst, f"{lo}-{hi}",
        f"accelerometer scale {sc.min():.3f}..{sc.max():.3f} is outside {c.limits_of} {lo}-{hi}: check the IMU "
        "and that the vehicle was still")


def reach_accel_gates(am, *, level_tilt_95_deg: float, limit_deg: float, partner: str, partner_ok: bool,
                      config: GateConfig = GateConfig()) -> list[Gate]:
    """The gates of an accelerometer whose offsets (and X/Y scales) poses within reach fitted (its Z
    scale kept, :mod:`mavcal.fits`) jointly with the compass ``partner``: that compass accepted (the two
    are one fit), the offset and scale limits, and the 95 % bound of the level tilt error its fitted
    offsets leave against ``limit_deg`` (what the calibration in force is assumed to leave, made smaller
    by the fit's required gain)."""
    gates: list[Gate] = []
    add, s = _adder(gates), f"accel{am.instance}"
    add(s, "joint compass", partner_ok, float(partner_ok), f"{partner} accepted",
        f"its offsets were fitted with {partner}, which was rejected: they are written only with it (its values "
        "are right only with them)", "data")
    _offsets_gate(add, s, am, config)
    _scales_gate(add, s, am, config)
    add(s, "level tilt uncertainty", level_tilt_95_deg <= limit_deg, level_tilt_95_deg,
        f"<= {limit_deg:.2f} deg (95 %)",
        f"the level tilt error of its fitted offsets {_could_reach('tilt', level_tilt_95_deg)}: not better than the "
        "calibration in force; hold each pose still longer", "data")
    return gates


def _could_reach(kind: str, bound_deg: float) -> str:
    """"could reach 0.62 deg (95 %)", or "is not determined (95 % bound above 90 deg)"."""
    if determined(kind, bound_deg):
        return f"could reach {bound_deg:.2f} deg (95 %)"
    return f"is {bound_value_words(kind, bound_deg)}"


#: what to do when a fit is not certified (the capture of full poses; poses within reach say their own)
FIT_ADVICE = "record more, better spread poses"
#: what to do when the heading bound is above its gate (poses within reach say their own)
HEADING_ADVICE = "more poses at different headings needed, or steel and magnets nearby disturbed the field"


def compass_gates(cm, params: Mapping[str, float], *, model: CompassLimits, n_intervals: int = 0,
                  n_orientations: int = 0,
                  heading_95_deg: float, holdout_mgauss: float, config: GateConfig = GateConfig(),
                  fit_converged: bool = True, fit_message: str = "", coverage=None,
                  fit_advice: str = FIT_ADVICE, heading_advice: str = HEADING_ADVICE) -> list[Gate]:
    """The gates of one compass (:class:`~mavcal.autopilot.mapping.CompassMapping`) of ``model``'s
    autopilot: its own values, and the heading bound and held-out error of its fit with the accelerometer it is
    paired with. The field gate runs only when the field strength is known (WMM or given).
    A joint fit without evidence that it reached the global optimum (``fit_converged`` False,
    :class:`mavcal.core.types.OptimumCertificate`) rejects the compass with the engine's reason:
    users write these numbers into a vehicle."""
    gates: list[Gate] = []
    add, c = _adder(gates), config
    s = f"compass{cm.instance}"
    omax = c.compass_offset_max_mgauss or model.compass_offset_max(params)
    ol = float(np.linalg.norm(cm.new.ofs_mgauss))
    add(s, "offsets", ol <= omax, ol, f"<= {omax:g} mGauss ({c.offset_limit_name})",
        f"compass offset length {ol:.0f} mGauss exceeds {c.offset_limit_name}: a magnet or steel near the compass, "
        "or a magnetised part; move it away and record again")
    dia = np.asarray(cm.new.dia)
    worst = float(dia[np.argmax(np.abs(dia - 1))])
    add(s, "diagonal", np.all((dia > c.dia_range[0]) & (dia < c.dia_range[1])), worst,
        f"{c.dia_range[0]}-{c.dia_range[1]}",
        f"soft-iron diagonal {np.round(dia, 3)} outside {c.limits_of} range: steel or currents near the compass")
    odi = float(np.abs(np.asarray(cm.new.odi)).max())
    add(s, "off-diagonal", odi < c.odi_max, odi, f"< {c.odi_max}",
        "soft-iron off-diagonal too large: steel or currents near the compass distort the field")
    f = cm.field_mgauss
    if cm.field_checked:
        lo, hi = c.field_range_mgauss
        add(s, "field", lo <= f <= hi, f, f"{lo:g}-{hi:g} mGauss",
            f"field magnitude {f:.0f} mGauss is outside {c.autopilot}'s range: check --location")
    else:  # not scaled to a known field: the compass's own scale must still measure an Earth-like field
        lo, hi = EARTH_FIELD_MGAUSS
        add(s, "field", lo <= f <= hi, f, f"{lo:g}-{hi:g} mGauss (Earth's field anywhere)",
            f"the compass measures a field of {f:.0f} mGauss, which is nowhere on Earth: readings not in mGauss, "
            "a strong disturbance or a poor fit; give --location or --field-mgauss to check it")
    add(s, "converged", fit_converged, 1.0 if fit_converged else 0.0, "certified as the global optimum",
        f"the fit is not certified as the global optimum: {fit_message or 'no reason given'}; {fit_advice}")
    slot = model.compass_slot_gate(params, cm.instance)
    if slot is not None:
        add(s, "device id", False, *slot)
    enough = _data_gates(add, s, n_intervals, n_orientations, c, coverage)
    if enough and heading_95_deg >= UNIDENTIFIED_HEADING_DEG:
        add(s, "heading uncertainty", False, heading_95_deg, f"<= {c.heading_95_max_deg} deg (95 %)",
            f"the poses do not identify {s}: its heading error is {bound_value_words('heading', heading_95_deg)}; "
            "add poses at new headings (the same sides again, the vehicle turned about 90 deg about the vertical)",
            "data")
    else:
        add(s, "heading uncertainty", heading_95_deg <= c.heading_95_max_deg, heading_95_deg,
            f"<= {c.heading_95_max_deg} deg (95 %)",
            f"the heading error {_could_reach('heading', heading_95_deg)}: {heading_advice}")
    add(s, "held-out error", holdout_mgauss <= c.holdout_mag_max_mgauss, holdout_mgauss,
        f"<= {c.holdout_mag_max_mgauss} mGauss",
        f"a pose left out of the fit is predicted {holdout_mgauss:.1f} mGauss off: magnetic disturbance (steel, "
        "magnets, currents) differs between poses; record away from it")
    return gates
