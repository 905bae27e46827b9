"""Whether a sensor's still intervals can identify its calibration: the one rule that
``mavcal segments`` reports and ``mavcal calibrate``'s gates apply.

An **accelerometer** is identified by the gravity directions of its intervals: its offsets
and per-axis scales (and cross-axis terms) need gravity seen from at least
:attr:`CoverageRule.min_orientations` distinct directions (clusters ``cluster_deg`` apart),
in at least :attr:`CoverageRule.min_intervals` intervals.

A **compass** is identified by the directions of Earth's field in its own frame. Each still
interval's orientation is pinned by the accelerometer only up to the heading, which the
fit estimates from the compass itself, so an interval in a new field direction adds two
equations, not three. The compass's own unknowns are 13 (a general 3 x 3 gain and
soft-iron matrix, which includes its rotation to the accelerometer, three offsets and the
field's dip), so 7 field directions determine it exactly and
:attr:`CoverageRule.min_field_directions` (8, as many as the full joint model needs
intervals) leave the spare equations that tell a fit from an accident of the data. The
same field direction seen twice adds nothing: a 6-position accelerometer calibration held
at one heading has 6. The same side held again at another heading (the vehicle turned
about the vertical) is a new field direction. The compass is paired with the primary
accelerometer, so its intervals must also hold enough gravity directions.

The field directions come from the raw compass means, centred on the sphere through them
(an algebraic least-squares fit; their mean when that is degenerate): the hard-iron offset
shifts every reading alike, so directions from that centre are the field's up to the soft
iron, far closer than the 20 deg clusters need.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from mavcal.core.headings import YAW_ORIENTATIONS, ProvisionalHeadings, provisional_headings
from mavcal.core.held import relaxed_headings, tilts_of
from mavcal.errors import MavcalError
from mavcal.gravity_spread import axis_label, count_clusters
from mavcal.segment import Segmentation

__all__ = ["CoverageRule", "SensorCoverage", "accel_coverage", "compass_coverage", "sensor_coverages",
           "field_directions", "UNIDENTIFIED_HEADING_DEG", "UNIDENTIFIED_TILT_DEG", "KeptParameter",
           "ReachCoverage", "reach_coverage", "segmentation_reach", "within_reach", "held_priors",
           "REACH_MAX_TILT_DEG", "REACH_FLOWN_TILT_DEG", "REACH_MIN_TILT_DEG",
           "REACH_MIN_FIELD_DIRECTIONS", "heading_gaps", "headings_text", "accel_state", "mounting_ratio",
           "HELD_ACCEL_SD", "ACCEL_STATE_WORDS"]

#: a 95 % heading bound this large says the poses did not identify the compass (a heading
#: error that may be anywhere in a half turn is no estimate at all)
UNIDENTIFIED_HEADING_DEG = 90.0
#: a 95 % tilt bound this large says the poses did not identify the accelerometer
UNIDENTIFIED_TILT_DEG = 45.0

#: the six sides, as body-frame gravity directions (FRD: +z down is level)
_SIDES = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], dtype=float)


@dataclass(frozen=True)
class CoverageRule:
    """How many distinct directions identify a sensor (defaults: mavcal's gates)."""

    min_intervals: int = 6
    min_orientations: int = 6
    min_field_directions: int = 8
    cluster_deg: float = 20.0


@dataclass(frozen=True)
class SensorCoverage:
    """What one sensor's still intervals can identify.

    ``n_field_directions`` is None for an accelerometer. ``missing``: what the data lacks, in
    words, the data's cause first (empty when identifiable); ``add``: which poses to add.
    """

    sensor: str
    identifiable: bool
    n_intervals: int
    n_orientations: int
    n_field_directions: int | None
    rule: CoverageRule
    missing: tuple[str, ...] = ()
    add: str = ""

    def text(self) -> str:
        """One line: the sensor, whether the coverage identifies it and, if not, why and what to add."""
        got = f"{self.n_intervals} interval(s), {self.n_orientations} gravity direction(s)"
        if self.n_field_directions is not None:
            got += f", {self.n_field_directions} field direction(s)"
        if self.identifiable:
            return f"{self.sensor}: can be identified ({got})"
        return f"{self.sensor}: cannot be identified ({got}): {'; '.join(self.missing)}; {self.add}"


def field_directions(mag_means: np.ndarray) -> np.ndarray:
    """Unit field directions (M, 3) of (N, 3) raw compass means, from the centre of the sphere
    through them (least squares |m|^2 = 2 c.m + k; their mean when degenerate); means that are
    not finite or sit at the centre are left out."""
    M = np.asarray(mag_means, dtype=float).reshape(-1, 3)
    M = M[np.isfinite(M).all(axis=1)]  # a mean of readings left out (NaN) is no direction
    if M.shape[0] == 0:
        return M
    centre = M.mean(axis=0)
    if M.shape[0] >= 4:
        A = np.c_[2.0 * M, np.ones(M.shape[0])]
        sv = np.linalg.svd(A, compute_uv=False)
        if sv[-1] > 1e-6 * sv[0]:
            centre = np.linalg.lstsq(A, (M ** 2).sum(axis=1), rcond=None)[0][:3]
    d = M - centre
    n = np.linalg.norm(d, axis=1)
    keep = n > 1e-9 * max(float(np.abs(M).max()), 1.0)  # a mean at the centre has no direction
    return d[keep] / n[keep, None]


def _finite(dirs: np.ndarray) -> np.ndarray:
    d = np.asarray(dirs, dtype=float).reshape(-1, 3)
    return d[np.isfinite(d).all(axis=1)]


def _missing_sides(gravity_dirs: np.ndarray) -> list[str]:
    """The six sides no gravity direction comes within 45 deg of, in words."""
    g = np.asarray(gravity_dirs, dtype=float).reshape(-1, 3)
    if g.shape[0] == 0:
        return [axis_label(s) for s in _SIDES]
    near = (g @ _SIDES.T).max(axis=0) >= np.cos(np.radians(45.0))
    return [axis_label(s) for s, ok in zip(_SIDES, near) if not ok]


def _gravity_missing(n: int, n_or: int, gravity_dirs: np.ndarray, r: CoverageRule) -> tuple[list[str], str]:
    missing = []
    if n_or < r.min_orientations:
        missing.append(f"only {n_or} distinct gravity direction(s), at least {r.min_orientations} needed "
                       "(too few orientations)")
    if n < r.min_intervals and not missing:
        missing.append(f"only {n} still interval(s), at least {r.min_intervals} needed")
    sides = _missing_sides(gravity_dirs)
    if sides:
        add = f"add poses: {', '.join(sides)}"
    elif n_or < r.min_orientations:
        add = "add poses tilted about 45 deg between the sides"
    else:
        add = "hold each pose still for 3-5 s"
    return missing, add


def accel_coverage(sensor: str, gravity_dirs: np.ndarray, rule: CoverageRule = CoverageRule()) -> SensorCoverage:
    """The rule for an accelerometer: its intervals' unit gravity directions (N, 3)."""
    g = _finite(gravity_dirs)
    n, n_or = g.shape[0], count_clusters(g, rule.cluster_deg) if g.shape[0] else 0
    missing, add = _gravity_missing(n, n_or, g, rule)
    return SensorCoverage(sensor, not missing, n, n_or, None, rule, tuple(missing), add if missing else "")


def compass_coverage(sensor: str, gravity_dirs: np.ndarray, mag_means: np.ndarray,
                     rule: CoverageRule = CoverageRule()) -> SensorCoverage:
    """The rule for a compass: its intervals' unit gravity directions (of the accelerometer it
    is paired with) and its raw mean readings, both (N, 3)."""
    g = _finite(gravity_dirs)
    n, n_or = g.shape[0], count_clusters(g, rule.cluster_deg) if g.shape[0] else 0
    f = field_directions(mag_means)
    n_f = count_clusters(f, rule.cluster_deg) if f.shape[0] else min(n, 1)  # all alike: one direction
    missing, add = _gravity_missing(n, n_or, g, rule)
    if n_f < rule.min_field_directions and not missing:  # the gravity directions first: the data's first cause
        k = rule.min_field_directions - n_f
        missing.append(f"only {n_f} distinct field direction(s), at least {rule.min_field_directions} needed "
                       "(too few headings)")
        turn = (f"add {k} or more poses at new headings (the same sides again, the vehicle turned about 90 deg "
                "about the vertical)")
        add = turn
    return SensorCoverage(sensor, not missing, n, n_or, n_f, rule, tuple(missing), add if missing else "")


def _has(d: dict, inst: int) -> bool:
    v = d.get(inst)
    return v is not None and v.shape[0] >= 2


def sensor_coverages(seg: Segmentation, accel_instance: int = 0, rule: CoverageRule = CoverageRule(),
                     accels: Sequence[int] | None = None, compasses: Sequence[int] | None = None
                     ) -> list[SensorCoverage]:
    """Every sensor's coverage, on the intervals its fit uses: an accelerometer's own intervals
    (>= 2 of its samples), a compass's intervals with >= 2 samples of it and of the
    accelerometer ``accel_instance`` it is paired with."""
    ivs = seg.intervals
    out = []
    for a in (seg.accel_instances if accels is None else accels):
        g = np.array([iv.gravity_dir for iv in ivs if _has(iv.accel_mps2, a)]).reshape(-1, 3)
        out.append(accel_coverage(f"accel{a}", g, rule))
    for m in (seg.mag_instances if compasses is None else compasses):
        used = [iv for iv in ivs if _has(iv.mag_mgauss, m) and _has(iv.accel_mps2, accel_instance)]
        g = np.array([iv.gravity_dir for iv in used]).reshape(-1, 3)
        means = np.array([iv.mag_mgauss[m].mean(axis=0) for iv in used]).reshape(-1, 3)
        out.append(compass_coverage(f"compass{m}", g, means, rule))
    return out


# --- poses within reach: a vehicle turned on the ground and tilted a little ---------------------

#: poses all within this tilt of level are "within reach" of a vehicle that cannot be turned over:
#: when they cannot identify the accelerometer, the compass is fitted with it held (mavcal.core.held)
REACH_MAX_TILT_DEG = 40.0
#: the compass's vertical soft-iron terms (and, without the World Magnetic Model's inclination, its
#: vertical offset) are seen only through the tilts: below this largest tilt they are not separated
REACH_MIN_TILT_DEG = 3.0
#: the attitudes a vehicle that cannot be turned over flies (a heavy multirotor or VTOL, a rover, a boat):
#: roll and pitch up to this, every heading; its heading and tilt bounds are over these
REACH_FLOWN_TILT_DEG = 15.0
#: distinct headings (clusters :data:`REACH_HEADING_DEG` apart on the circle the compass means
#: trace as the vehicle turns) the poses must hold: about 6 headings 60 deg apart
REACH_MIN_FIELD_DIRECTIONS = 5
REACH_HEADING_DEG = 40.0
#: a provisional fit of the compass (any yaw mounting) with an RMS residual at most this explains its
#: readings (a magnetic disturbance that moves the field between poses leaves tens of mGauss or more)
EXPLAINED_RMS_MGAUSS = 10.0

_BEYOND = "the vehicle on its side (gravity along X or Y) or upside down: the full capture without --max-tilt"


@dataclass(frozen=True)
class KeptParameter:
    """A parameter the poses cannot identify, kept at its current value and not written."""

    sensor: str  # "accel0", "compass1"
    what: str  # "Z scale", "X and Y offsets", ...
    why: str  # the poses' limit, in words
    pose: str  # which pose would identify it

    def text(self) -> str:
        return f"{self.sensor} {self.what} kept: {self.why} (would need {self.pose})"


@dataclass(frozen=True)
class ReachCoverage:
    """What poses within reach identify (any heading, tilts up to ``max_tilt_deg``).

    ``applies``: every pose is within :data:`REACH_MAX_TILT_DEG` of level and the gravity
    directions do not identify the accelerometer, so the fit of :mod:`mavcal.core.held` is
    the one to run; ``compass_identified``: enough headings and tilt for the compass's
    offsets and symmetric soft-iron terms; ``kept``: every parameter kept, with why and what
    pose would identify it; ``missing``/``add``: why the compass is not identified and what to add.
    """

    applies: bool
    max_tilt_deg: float
    n_field_directions: int
    compass_identified: bool
    kept: tuple[KeptParameter, ...] = ()
    missing: tuple[str, ...] = ()
    add: str = ""
    #: each pose's heading (deg, from the first pose's, clockwise seen from above) as the provisional
    #: fit of :func:`mavcal.core.headings.provisional_headings` sees it (empty when it did not fit)
    headings_deg: tuple[float, ...] = ()
    #: the yaw turn (deg) of the compass from its configured mounting that the tilts identify (0: as
    #: configured; None: not identified, see ``mounting_evidence``) and the evidence in words
    mounting_turn_deg: float | None = None
    mounting_evidence: str = ""
    #: the smallest RMS residual (mGauss) of the provisional fit over the yaw mountings tried (None: no fit)
    best_rms_mgauss: float | None = None

    def explained(self) -> bool:
        """Some yaw mounting of the compass explains its readings (the provisional fit's RMS residual at
        most :data:`EXPLAINED_RMS_MGAUSS`): a field that disagrees between poses is then no disturbance."""
        return self.best_rms_mgauss is not None and self.best_rms_mgauss <= EXPLAINED_RMS_MGAUSS

    def mounting_text(self) -> str:
        """What the poses say of the compass's mounting, for a verdict or an abort."""
        if self.mounting_turn_deg:
            o = next(k for k, v in YAW_ORIENTATIONS.items() if v == self.mounting_turn_deg)
            return (f"the compass may be mounted rotated: its readings fit a compass turned "
                    f"{self.mounting_turn_deg:.0f} deg about the vertical from its configured orientation best "
                    f"(COMPASS_ORIENT {o} if it is configured 0 now; {self.mounting_evidence}); check how it is "
                    "mounted and set its orientation")
        return ""

    def heading_advice(self, accel: str = "") -> str:
        """What to do when the heading bound of these poses is above its gate: the bound counts the
        uncertainty of the accelerometer calibration kept, which no pose within reach lowers (issue 37);
        ``accel``: the state of that calibration (:func:`accel_state`), named as the limit."""
        said = ACCEL_STATE_WORDS.get(accel)
        what = {"never": "calibrate the accelerometer (its full 6-side calibration: the scales; the offsets are fitted "
                         "here when the poses identify them)",
                "level": "calibrate the accelerometer fully (its 6-side calibration: the scales)",
                "reach": "calibrate the accelerometer fully (its 6-side calibration: the Z scale)",
                "inconsistent": "calibrate the accelerometer again (its full 6-side calibration)"}.get(
            accel, "calibrate the accelerometer (its full calibration, or at least a level calibration on level "
                   "ground)")
        return ("the limit is the accelerometer" + (f", {said}" if said else "") + ": within reach the bound counts "
                "the uncertainty of its calibration, which is kept (poses within reach do not identify it) and which "
                f"more poses do not lower once the bound stops falling: {what} and capture again, or write anyway "
                f"with --force; else turn the vehicle to headings between the {self.n_field_directions} recorded")

    def refit_advice(self) -> str:
        """What poses to add when the fit of these poses was not certified (a wrong basin not ruled
        out): headings between those recorded and tilts in new directions, the vehicle's reach kept."""
        return (f"turn the vehicle to headings between the {self.n_field_directions} recorded and tilt it in new "
                f"directions, as far as it can go (the largest tilt so far is {self.max_tilt_deg:.0f} deg)")

    def lines(self) -> list[str]:
        """The verdict in words, one line per fact (empty when the rule does not apply)."""
        if not self.applies:
            return []
        head = (f"poses within reach: tilts up to {self.max_tilt_deg:.1f} deg, {self.n_field_directions} distinct "
                "heading(s): ")
        if self.compass_identified:
            out = [head + "the compass's offsets and soft-iron terms are identified (fitted with the "
                   "accelerometer's offsets, and its X/Y scales unless it was calibrated; its Z scale held)"]
            if self.mounting_turn_deg:
                out.append(f"the compass's yaw mounting is identified by the tilts: turned "
                           f"{self.mounting_turn_deg:.0f} deg about the vertical from its configured orientation "
                           f"({self.mounting_evidence}); fitted so")
        else:
            out = [head + "the compass is not identified: " + "; ".join(self.missing) + f"; {self.add}"]
        return out + [k.text() for k in self.kept]


def _accel_kept(sensor: str, tilt: float) -> list[KeptParameter]:
    t = f"tilts up to {tilt:.0f} deg"
    g_xy = 9.80665 * np.sin(np.radians(tilt))
    return [
        KeptParameter(sensor, "Z scale", f"{t} cannot separate it from the Z offset (gravity stays within "
                      f"{100 * (1 - np.cos(np.radians(tilt))):.1f} % of its level value along Z; the Z offset is "
                      "fitted with the scale kept, so that the level reading is right)", _BEYOND),
        KeptParameter(sensor, "X and Y scales", f"{t} move X/Y by at most {g_xy:.2f} m/s^2 and give the scales only "
                      "as ratios to the Z scale, to about 1.5 %: kept when the accelerometer was calibrated (fitted "
                      "and written when it was only level-calibrated or never calibrated)", _BEYOND),
    ]


def _headings(gravity_dirs: np.ndarray, mag_means: np.ndarray) -> int:
    """Distinct headings among poses near level (:func:`_heading_count`)."""
    return _heading_count(gravity_dirs, mag_means)[0]


def _heading_count(gravity_dirs: np.ndarray, mag_means: np.ndarray) -> tuple[int, np.ndarray | None]:
    n, psi, _ = _heading_fit(gravity_dirs, mag_means)
    return n, psi


def _heading_fit(gravity_dirs: np.ndarray, mag_means: np.ndarray
                 ) -> tuple[int, np.ndarray | None, ProvisionalHeadings | None]:
    """Distinct headings among poses near level, in clusters :data:`REACH_HEADING_DEG` apart, and
    each pose's heading (deg, from the first pose's, growing as the vehicle turns clockwise seen
    from above; None when only the fallback counted): from a provisional fit of the compass
    (:func:`mavcal.core.headings.provisional_headings`: the offsets, scale, soft iron and dip
    fitted, the tilts the gravity directions give removed, each yaw mounting of the compass
    tried), so that neither offsets of any size nor a steep field's vertical share in a tilted
    pose's readings merge or split headings. When that fit fails (too few poses, no plausible
    field), the linear relaxation of the compass model (:func:`mavcal.core.held.relaxed_headings`)
    or the circle the raw means trace, whichever counts more (issue 37: both miscount ordinary
    offsets and soft iron beside a steep field)."""
    g = np.asarray(gravity_dirs, dtype=float).reshape(-1, 3)
    M = np.asarray(mag_means, dtype=float).reshape(-1, 3)
    ok = np.isfinite(g).all(axis=1) & np.isfinite(M).all(axis=1)
    g, M = g[ok], M[ok]
    if g.shape[0] < 3:
        return min(g.shape[0], 1), (np.zeros(g.shape[0]) if g.shape[0] == 1 else None), None
    try:
        T = tilts_of(-g)  # FRD gravity points down; the specific force up
    except MavcalError:
        T = None
    if T is not None:
        try:
            fit = provisional_headings(T, M, tuple(YAW_ORIENTATIONS))
            psi = fit.psi_rad
            n = count_clusters(np.c_[np.cos(psi), np.sin(psi), np.zeros(len(psi))], REACH_HEADING_DEG)
            return n, np.degrees(psi[0] - psi) % 360.0, fit  # the body sees the field turn the other way
        except (MavcalError, np.linalg.LinAlgError):
            pass
    if g.shape[0] < 4:
        return 1, None, None
    try:
        if T is None:
            raise MavcalError("upside down")
        psi = relaxed_headings(T, M)[0]
        n_relaxed = count_clusters(np.c_[np.cos(psi), np.sin(psi), np.zeros(len(psi))], REACH_HEADING_DEG)
    except (MavcalError, np.linalg.LinAlgError):
        n_relaxed = 1
    return max(n_relaxed, _circle_headings(M)), None, None


def heading_gaps(headings_deg: Sequence[float], step_deg: float = 60.0) -> list[float]:
    """Headings (deg, as ``headings_deg``) about ``step_deg`` apart that no heading seen comes within
    :data:`REACH_HEADING_DEG` of: where to turn the vehicle next, the largest gap first."""
    seen = np.asarray(headings_deg, dtype=float) % 360.0
    if seen.size == 0:
        return [0.0]
    cands = [(float(c), float(np.abs((seen - c + 180.0) % 360.0 - 180.0).min())) for c in np.arange(0.0, 360.0, 15.0)]
    out: list[float] = []
    for c, d in sorted(cands, key=lambda t: -t[1]):  # the farthest from every heading seen first
        if d >= REACH_HEADING_DEG and all(abs((c - o + 180.0) % 360.0 - 180.0) >= step_deg - 1e-9 for o in out):
            out.append(c)
    return out


def headings_text(headings_deg: Sequence[float]) -> str:
    """"0, 58, 121 deg": the distinct headings seen (within 10 deg merged), in order."""
    hs: list[float] = []
    for h in sorted(float(x) % 360.0 for x in headings_deg):
        if not hs or h - hs[-1] > 10.0:
            hs.append(h)
    if len(hs) > 1 and hs[0] + 360.0 - hs[-1] <= 10.0:
        hs.pop()
    return ", ".join(f"{h:.0f}" for h in hs) + " deg"


def _circle_headings(M: np.ndarray) -> int:
    """Distinct headings of compass means near a circle: their angles about its centre (an algebraic
    circle fit in the plane of their two largest spreads) in clusters :data:`REACH_HEADING_DEG`
    apart. Right at the smallest tilts, where the relaxation of :func:`_headings` is least
    determined; a tilt that moves the vertical field into the horizontal readings (15 deg and a
    steep field) merges headings here, which the relaxation then separates."""
    c = M - M.mean(axis=0)
    _, sv, Vt = np.linalg.svd(c, full_matrices=False)
    if sv[0] <= 1e-9 * max(float(np.abs(M).max()), 1.0):
        return 1
    xy = c @ Vt[:2].T
    centre = np.linalg.lstsq(np.c_[2.0 * xy, np.ones(len(xy))], (xy ** 2).sum(axis=1), rcond=None)[0][:2]
    d = xy - centre
    d = d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
    return count_clusters(np.c_[d, np.zeros(len(d))], REACH_HEADING_DEG)


def reach_coverage(gravity_dirs: np.ndarray, mag_means: np.ndarray, accels: Sequence[str] = ("accel0",),
                   compass: str = "compass0", rule: CoverageRule = CoverageRule()) -> ReachCoverage:
    """The rule for poses within reach: the (N, 3) unit gravity directions (body frame, level
    = +z) and raw compass means of a compass's intervals; ``accels``: the accelerometers whose
    parameters are then kept (named in ``kept``)."""
    g = _finite(gravity_dirs)
    if g.shape[0] == 0:
        return ReachCoverage(False, float("nan"), 0, False)
    tilt = float(np.degrees(np.arccos(np.clip(g[:, 2], -1.0, 1.0))).max())
    applies = tilt <= REACH_MAX_TILT_DEG and not accel_coverage("accel", g, rule).identifiable
    n_f, psi, fit = _heading_fit(gravity_dirs, mag_means)
    seen = () if psi is None else tuple(float(x) for x in psi)
    turn, evidence = _mounting(fit, tilt, g.shape[0])
    missing = []
    add = ""
    if n_f < REACH_MIN_FIELD_DIRECTIONS:
        missing.append(f"only {n_f} distinct heading(s), at least {REACH_MIN_FIELD_DIRECTIONS} needed "
                       f"{REACH_HEADING_DEG:g} deg apart (too few headings" +
                       (f"; headings seen, from the first pose's, turning clockwise: {headings_text(seen)})"
                        if seen else ")"))
        gaps = heading_gaps(seen)[:REACH_MIN_FIELD_DIRECTIONS - n_f] if seen else []
        add = (f"turn the vehicle to more headings: {', '.join(f'{h:.0f}' for h in sorted(gaps))} deg from the first "
               "pose's heading (clockwise seen from above)" if gaps else
               "turn the vehicle to more headings (about 60 deg apart, all the way round)")
    if tilt < REACH_MIN_TILT_DEG:
        missing.append(f"tilts up to {tilt:.1f} deg cannot separate the compass's vertical terms from its "
                       f"vertical offset (at least {REACH_MIN_TILT_DEG:g} deg needed)")
        add = (add + "; " if add else "") + ("tilt the vehicle a few degrees at some headings (one side on a "
                                             "block, a ramp)")
    kept = [k for a in accels for k in _accel_kept(a, tilt)] if applies else []
    if applies and not missing and not turn:  # a turn found is fitted and written (mavcal.fits), or kept there
        why = ("the tilts confirm the yaw mounting configured, its other turns fit worse" if turn == 0.0 else
               "turning about the vertical cannot tell a rotation of the compass from the heading, and the tilts "
               "did not tell the yaw mountings apart")
        kept.append(KeptParameter(compass, "orientation", f"{why} ({evidence})" if evidence else why, _BEYOND))
    return ReachCoverage(applies, tilt, n_f, applies and not missing, tuple(kept), tuple(missing), add, seen,
                         turn, evidence, min(fit.rms_mgauss.values()) if fit is not None and fit.rms_mgauss else None)


#: the yaw mounting is identified only from poses tilted at least this much (below it the vertical field
#: moves too little into the compass's X or Y axis to tell the turns apart)
MOUNTING_MIN_TILT_DEG = 8.0
#: the false-alarm rate of the choice of a yaw mounting over another (the configured one included): a
#: candidate is chosen only when its provisional fit's cost is lower than every other candidate's by a
#: factor that noise alone exceeds with at most this probability (:func:`mounting_ratio`)
MOUNTING_FALSE_ALARM = 1e-3
#: ... and never by less than this factor of the RMS residuals (the provisional fit is a model of the
#: compass, not its exact noise: its residual is not pure noise)
MOUNTING_EVIDENCE_RATIO = 3.0


def mounting_ratio(n_poses: int) -> float:
    """The factor of RMS residuals by which a yaw mounting must fit better than every other one to be
    chosen. The provisional fit of each candidate has the same unknowns (:mod:`mavcal.core.headings`:
    offsets, scale, dip, soft iron; d = 2N - 11 degrees of freedom, 2N - 5 with fewer than 5 poses);
    if two candidates fitted equally well in truth, the ratio of their costs would be F(d, d)
    distributed, so a candidate is chosen over another only when its cost ratio exceeds the
    ``1 - MOUNTING_FALSE_ALARM`` quantile of F(d, d): the probability that noise alone makes a wrong
    turn fit that much better (a false alarm) is at most :data:`MOUNTING_FALSE_ALARM`."""
    from scipy.stats import f as f_dist

    d = max(2 * n_poses - (11 if n_poses >= 5 else 5), 1)
    return max(MOUNTING_EVIDENCE_RATIO, float(np.sqrt(f_dist.isf(MOUNTING_FALSE_ALARM, d, d))))


def _mounting(fit: ProvisionalHeadings | None, tilt_deg: float, n_poses: int = 0) -> tuple[float | None, str]:
    """(the yaw turn of the compass identified, or None; the evidence in words)."""
    if fit is None or len(fit.rms_mgauss) < 2:
        return None, ""
    rms = fit.rms_mgauss
    best = fit.orientation
    runner = min(v for o, v in rms.items() if o != best)
    said = ", ".join(f"{YAW_ORIENTATIONS[o]:.0f} deg: {v:.1f}" for o, v in sorted(rms.items()))
    words = f"RMS residual of a provisional fit, mGauss, by turn: {said}"
    need = mounting_ratio(n_poses)
    if tilt_deg < MOUNTING_MIN_TILT_DEG or runner < need * rms[best]:
        return None, words + (f"; not told apart (tilts up to {tilt_deg:.0f} deg, at least "
                              f"{MOUNTING_MIN_TILT_DEG:g} deg and a {need:.2g}x margin needed)")
    return YAW_ORIENTATIONS[best], words + (f"; {runner / max(rms[best], 1e-12):.3g}x better than the next, "
                                            f"{need:.2g}x needed: false-alarm rate at most "
                                            f"{100 * MOUNTING_FALSE_ALARM:g} %")


def segmentation_reach(seg: Segmentation, accel_instance: int = 0, mag_instance: int | None = None,
                       rule: CoverageRule = CoverageRule(), accels: Sequence[int] | None = None
                       ) -> ReachCoverage | None:
    """:func:`reach_coverage` on the intervals a compass's fit uses (>= 2 samples of it and of
    accelerometer ``accel_instance``; ``mag_instance`` None: the first compass), naming
    ``accels`` (default: every accelerometer of the log) as kept; None when the rule does not
    apply (the poses identify the accelerometer, go beyond a small tilt, or there is no compass)."""
    mags = list(seg.mag_instances)
    if mag_instance is None:
        if not mags:
            return None
        mag_instance = mags[0]
    used = [iv for iv in seg.intervals if _has(iv.mag_mgauss, mag_instance) and _has(iv.accel_mps2, accel_instance)]
    if not used:
        return None
    g = np.array([iv.gravity_dir for iv in used]).reshape(-1, 3)
    means = np.array([iv.mag_mgauss[mag_instance].mean(axis=0) for iv in used]).reshape(-1, 3)
    names = [f"accel{a}" for a in (seg.accel_instances if accels is None else accels)]
    r = reach_coverage(g, means, names, f"compass{mag_instance}", rule)
    return r if r.applies else None


def within_reach(cov: SensorCoverage, reach: ReachCoverage) -> SensorCoverage:
    """A compass's coverage under the rule of poses within reach: identified when ``reach`` says
    so (one gravity direction and :data:`REACH_MIN_FIELD_DIRECTIONS` field directions suffice),
    else as ``cov`` says."""
    if not reach.compass_identified or not cov.sensor.startswith("compass"):
        return cov
    rule = replace(cov.rule, min_orientations=1, min_field_directions=REACH_MIN_FIELD_DIRECTIONS)
    return SensorCoverage(cov.sensor, True, cov.n_intervals, cov.n_orientations, reach.n_field_directions, rule)


#: the held accelerometer values' assumed 1-sigma errors (offset m/s^2, relative scale), by the state of
#: its calibration in force (:func:`accel_state`): a full calibration (offsets and scales set); a level
#: ("simple") calibration only (offsets set from one level pose, scales all exactly 1: the scales keep their
#: factory error, up to +-5 %, uniform: 2.9 % sd); never calibrated (offsets 0, scales 1: factory biases up
#: to 0.5 m/s^2, uniform: 0.29 m/s^2 sd, and scales up to +-5 %)
HELD_ACCEL_SD_CALIBRATED = (0.05, 0.005)
HELD_ACCEL_SD_LEVEL = (0.05, 0.03)
HELD_ACCEL_SD_DEFAULT = (0.3, 0.03)
#: "inconsistent": calibrated, but its X/Y scales contradicted by the poses (mavcal.fits): a level calibration's
#: prior at least
#: "reach": offsets and X/Y scales set by a fit of poses within reach, the Z scale the factory's: a level
#: calibration's prior (its X/Y scales known to about 1.5 % only, its Z scale not at all)
HELD_ACCEL_SD = {"calibrated": HELD_ACCEL_SD_CALIBRATED, "level": HELD_ACCEL_SD_LEVEL, "never": HELD_ACCEL_SD_DEFAULT,
                 "inconsistent": HELD_ACCEL_SD_LEVEL, "reach": HELD_ACCEL_SD_LEVEL}
#: the state of an accelerometer's calibration in force, in words (the verdict's)
ACCEL_STATE_WORDS = {
    "calibrated": "calibrated (offsets and scales set)",
    "level": "level-calibrated only (offsets set from a level pose, scales at 1: their factory error, up to "
             "+-5 %, remains)",
    "never": "never calibrated (offsets 0, scales 1: factory biases up to 0.5 m/s^2 and scales up to +-5 % "
             "remain)",
    "inconsistent": "calibrated, but its X/Y scales in force do not fit these poses (a calibration from another "
                    "board or vehicle, or a poor one)",
    "reach": "calibrated within reach only (offsets and X/Y scales from tilted poses, Z scale at 1: its factory "
             "error, up to +-5 %, remains)",
}


#: the World Magnetic Model's inclination error assumed, deg (1 sigma; its stated global error
#: is about 0.2 deg, local crustal anomalies add to it)
WMM_INCLINATION_SD_DEG = 0.5


def accel_state(ofs_mps2: Sequence[float], scale: Sequence[float]) -> str:
    """"calibrated", "level", "reach" or "never": the state of an accelerometer's calibration in force from
    its offsets and scales (ArduPilot's simple/level calibration sets the offsets and leaves every scale 1;
    a fit of poses within reach sets the X/Y scales and leaves the Z scale exactly 1, which a 6-side
    calibration, a fit of floats, does not)."""
    o, k = np.asarray(ofs_mps2, float), np.asarray(scale, float)
    if np.all(o == 0.0) and np.all(k == 1.0):
        return "never"
    if np.all(k == 1.0):
        return "level"
    return "reach" if k[2] == 1.0 else "calibrated"


def held_priors(K_a: np.ndarray, calibrated: bool | str, inclination_deg: float | None,
                scale_sd: float | None = None) -> dict[str, float]:
    """The prior standard deviations of the held parameters (engine names, :mod:`mavcal.core.held`):
    the accelerometer's diagonal gain ``K_a`` and offsets (``calibrated``: the state of its calibration
    in force, :func:`accel_state`; True / False: "calibrated" / "never") and the field dip
    h_z = tan(inclination) when held at the World Magnetic Model's ``inclination_deg``; ``scale_sd``: the
    scales' relative prior instead of the state's."""
    state = calibrated if isinstance(calibrated, str) else ("calibrated" if calibrated else "never")
    ofs, rel = HELD_ACCEL_SD[state]
    rel = rel if scale_sd is None else scale_sd
    out = {f"K_a[{j}{j}]": rel * abs(float(K_a[j - 1, j - 1])) for j in (1, 2, 3)}
    out.update({f"b_a[{c}]": ofs for c in "xyz"})
    if inclination_deg is not None:
        out["h_z"] = float(np.radians(WMM_INCLINATION_SD_DEG) / np.cos(np.radians(inclination_deg)) ** 2)
    return out
