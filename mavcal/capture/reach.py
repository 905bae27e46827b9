"""A capture within reach (``--max-tilt``, issues 27 and 37): its plan before the first fit, and
what its poses identify as they come (:func:`mavcal.coverage.reach_coverage`: the headings from a
provisional fit of the compass, its yaw mounting), said in the status, at the cap and in an abort."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mavcal.capture.progress import SensorProgress
from mavcal.coverage import MOUNTING_MIN_TILT_DEG, ReachCoverage, headings_text, reach_coverage
from mavcal.run import Options, Prepared

__all__ = ["ReachWatch", "reach_plan", "reach_plan_extended"]


def reach_tilts(max_tilt_deg: float) -> list[tuple[float, float]]:
    """(roll, pitch) deg: level, and tilted by half and all of ``max_tilt_deg`` towards the 8
    points (a corner: roll and pitch each t / sqrt(2), so the tilt stays within the limit)."""
    out = [(0.0, 0.0)]
    for t in (0.5 * max_tilt_deg, float(max_tilt_deg)):
        for k in range(8):
            a = np.radians(45.0 * k)
            out.append((round(float(t * np.sin(a)), 1), round(float(t * np.cos(a)), 1)))
    return out


def reach_plan(max_tilt_deg: float) -> list[tuple[float, float, float]]:
    """The plan before the first fit for a vehicle that cannot be turned over: turned to six
    headings 60 deg apart, level and tilted by ``max_tilt_deg`` nose up, rolled right, nose down,
    rolled left, then two corners."""
    t, d = float(max_tilt_deg), round(float(max_tilt_deg) / np.sqrt(2.0), 1)
    return [(0.0, 0.0, 0.0), (0.0, t, 60.0), (t, 0.0, 120.0), (0.0, 0.0, 180.0), (0.0, -t, 240.0),
            (-t, 0.0, 300.0), (d, d, 30.0), (-d, -d, 210.0)]


def reach_plan_extended(max_tilt_deg: float) -> list[tuple[float, float, float]]:
    """The plan before the first fit, when no fit comes: :func:`reach_plan`, then the same turned
    by 30, 15 and 45 deg (new headings between those held, never a pose asked for before)."""
    base = reach_plan(max_tilt_deg)
    return [(r, p, float((y + turn) % 360.0)) for turn in (0.0, 30.0, 15.0, 45.0) for r, p, y in base]


class ReachWatch:
    """What the poses within reach identify (None-safe: a capture without ``max_tilt_deg`` says nothing),
    computed once per new or changed interval."""

    def __init__(self, max_tilt_deg: float | None, options: Options) -> None:
        self.max_tilt_deg = max_tilt_deg
        self.options = options
        self._key: tuple[int, int] | None = None  # (intervals, pieces of the last) of the cached coverage
        self._cov: ReachCoverage | None = None

    def coverage(self, prep: Prepared, n: int) -> ReachCoverage | None:
        """:func:`mavcal.coverage.reach_coverage` of the primary compass's intervals (None without a
        tilt limit or intervals)."""
        if self.max_tilt_deg is None:
            return None
        ivs = prep.segmentation.intervals
        key = (n, len(ivs[-1].pieces_s) if ivs else 0)
        if key == self._key:
            return self._cov
        ai, mi = self.options.accel_instance, self.options.mag_instance
        used = [iv for iv in ivs if len(iv.mag_mgauss.get(mi, ())) >= 2 and len(iv.accel_mps2.get(ai, ())) >= 2]
        self._key, self._cov = key, None
        if used:
            g = np.array([iv.gravity_dir for iv in used]).reshape(-1, 3)
            means = np.array([iv.mag_mgauss[mi].mean(0) for iv in used]).reshape(-1, 3)
            self._cov = reach_coverage(g, means)
        return self._cov

    def _planned(self, n: int) -> bool:
        return self.max_tilt_deg is not None and n >= len(reach_plan(self.max_tilt_deg))

    def messages(self, prep: Prepared, n: int, done: bool) -> list[str]:
        """Once the plan's poses are held and the headings still fall short: the headings seen and
        those to add, in words a person can check."""
        r = self.coverage(prep, n) if self._planned(n) and not done else None
        return [f"poses within reach: {'; '.join(r.missing)}; {r.add}"] if r is not None and r.missing else []

    def mounting_abort(self, prep: Prepared, n: int, fitted: bool = False) -> str:
        """The reason to abort when, the plan's poses held, the compass's readings fit a turned yaw
        mounting that the fit could not take (``fitted``: the fit turned the compass and will write its
        orientation, issue 37): no fit of these poses with the mounting configured can be right ("" otherwise)."""
        r = self.coverage(prep, n) if self._planned(n) and not fitted else None
        return f"{r.mounting_text()}; then start again" if r is not None and r.mounting_text() else ""

    def cap_reason(self, prep: Prepared, n: int, progress: Sequence[SensorProgress]) -> str:
        """The reason of a capture within reach ended at its cap: what the poses gave."""
        r = self.coverage(prep, n)
        text = f"{n} poses: the most a capture within reach asks for (--max-poses)"
        bounds = [f"{p.sensor} {p.bound_deg:.2f} deg (target {p.target_deg:g})" for p in progress
                  if p.bound_deg is not None]
        if bounds:
            text += "; heading error bounds: " + ", ".join(bounds)
        if r is not None:
            text += f"; {r.n_field_directions} distinct heading(s)"
            if r.headings_deg:
                text += f" ({headings_text(r.headings_deg)} from the first pose's)"
            if r.missing:
                text += "; the compass is not identified: " + "; ".join(r.missing)
            if r.mounting_text():
                text += "; " + r.mounting_text()
        return text + "; the verdict follows"

    def spread_reason(self, spread: float, prep: Prepared, n: int) -> str:
        """Why the calibrated field magnitude differs between poses: within reach, a compass whose
        readings fit a turned mounting is said to be mounted rotated, not in a disturbance."""
        r = self.coverage(prep, n)
        said = f"the calibrated field magnitude differs by {100 * spread:.0f} % between poses"
        if r is not None and r.mounting_text():
            return f"{said}: {r.mounting_text()}; then start again"
        if r is not None and r.explained():  # a disturbance only when no candidate mounting explains the field
            return (f"{said} with the compass as configured, but a compass turned about the vertical explains its "
                    f"readings ({r.mounting_evidence}): the compass may be mounted rotated; check how it is mounted "
                    "and set its orientation (or tilt the vehicle further, at least "
                    f"{MOUNTING_MIN_TILT_DEG:g} deg, so that the tilts tell the turn), then start again")
        return (f"{said}: magnetic disturbance (steel, magnets, currents nearby); move to a clean place and start "
                "again" + (f" ({r.mounting_evidence})" if r is not None and r.mounting_evidence else ""))
