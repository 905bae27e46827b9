"""Every sensor's progress in a guided capture: its 95 % bound against its target, and
whether it can get there (the stop rule of issue 22).

The capture stops only when every sensor that will be written meets its target: every
accelerometer's own tilt bound (:mod:`mavcal.core.accel_fit`, the bound its verdict is judged
on) ``<= CaptureConfig.target_tilt_deg`` and every compass's heading bound (its fit with the
primary accelerometer) ``<= CaptureConfig.target_heading_deg``. The next pose is advised for
the sensor furthest from its target (largest bound / target): a compass by the heading
criterion of :func:`mavcal.capture.poses.pose_scores` on its own pair's fit, an
accelerometer by :func:`tilt_pose_scores`.

A sensor that cannot get there is said with the reason, and the person may finish without it
(:meth:`mavcal.capture.CaptureSession.finish_without`; it is then judged as it is and, if
rejected, keeps its current values):

* one of its values is outside ArduPilot's limits (offsets, scales, soft iron, field, device id)
  while its bound says the values are known (within :data:`KNOWN_FACTOR` of its target): more
  poses do not change the sensor;
* a compass whose calibrated field magnitude differs between poses by more than
  ``CaptureConfig.max_field_spread``: a disturbance near it (the primary compass aborts the
  capture instead, as before);
* its bound has not improved by 10 % over the last ``CaptureConfig.stuck_poses`` new intervals
  (or it has no fit at all for that long): the poses do not identify it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mavcal.autopilot.evaluate import attitude_grid
from mavcal.autopilot.gates import reason_text
from mavcal.autopilot.mapping import accel_frame
from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.core.accel_fit import candidate_information, tilt_variances
from mavcal.run import CalibrationRun, Options, Prepared

__all__ = ["SensorProgress", "expected_sensors", "measure", "pair_run", "tilt_pose_scores", "tilt_pose_variances",
           "stop_reason",
           "HARD_GATES", "IMPROVEMENT", "KNOWN_FACTOR"]

#: gates that more poses cannot pass: the sensor's values against ArduPilot's limits
HARD_GATES = ("offsets", "scales", "diagonal", "off-diagonal", "field", "device id")
#: a bound that falls by less than this fraction over ``stuck_poses`` new intervals is stuck
IMPROVEMENT = 0.10
#: a sensor's values count against ArduPilot's limits once its bound is within this factor of
#: its target (an unidentified fit, e.g. at 8 poses, can have any values)
KNOWN_FACTOR = 4.0


@dataclass(frozen=True)
class SensorProgress:
    """One sensor's bound against its target, as the stop rule and the advice see it.

    ``kind`` is ``"tilt"`` (an accelerometer, its own fit) or ``"heading"`` (a compass, with the
    primary accelerometer); ``bound_deg`` the 95 % bound now (None before it has a fit);
    ``blocked`` why it cannot reach its target ("" when it can); ``dropped`` True once the
    person chose to finish without it; ``needs`` what calibrate's coverage rule still asks of
    its poses (a failed gate with cause "data", e.g. too few distinct field directions; "" when
    the poses identify it): a bound under its target does not meet it while the poses do not
    identify the sensor, as the stop rule and the final verdict agree."""

    sensor: str
    kind: str
    bound_deg: float | None
    target_deg: float
    blocked: str = ""
    dropped: bool = False
    needs: str = ""

    @property
    def met(self) -> bool:
        return self.bound_deg is not None and self.bound_deg <= self.target_deg and not self.needs

    @property
    def distance(self) -> float:
        """bound / target (inf without a bound): the advice goes to the largest."""
        return float("inf") if self.bound_deg is None else self.bound_deg / self.target_deg


def expected_sensors(prep: Prepared, options: Options) -> list[str]:
    """The sensors a fit of this recording judges and may write (accelerometers first)."""
    raw = prep.raw
    out: list[str] = []
    for kind, label, insts, primary in (("accel", "accel", raw.accel_instances(), options.accel_instance),
                                        ("compass", "compass", raw.mag_instances(), options.mag_instance)):
        if options.sensors not in ("both", kind):
            continue
        if options.sensors == kind and options.only_instances is not None:
            insts = [i for i in insts if i in options.only_instances]
        elif not options.all_instances:
            insts = [i for i in insts if i == primary]
        out += [f"{label}{i}" for i in insts]
    return out


def pair_run(run: CalibrationRun, compass: int) -> CalibrationRun | None:
    """The fit of compass ``compass`` with the primary accelerometer (the run itself for the
    primary compass), or None when it has none."""
    ai = run.mapping.accel[0].instance if run.mapping.accel else None
    for r in (run,) + tuple(run.others):
        if r.calibration is None or not r.mapping.compass:
            continue
        if r.mapping.compass[0].instance == compass and (r is run or r.mapping.accel[0].instance == ai):
            return r
    return None


def _field_spread(r: CalibrationRun) -> float:
    """Relative spread (max - min) / mean of the calibrated field magnitude over ``r``'s intervals."""
    cal, seg = r.calibration, r.segmentation
    assert cal is not None
    mi = r.mapping.compass[0].instance
    mus = np.array([seg.intervals[k].mag_mgauss[mi].mean(0) for k in r.intervals_used])
    z = np.linalg.solve(cal.mag.gain, (mus - cal.mag.bias).T).T
    m = np.linalg.norm(z, axis=1)
    return float((m.max() - m.min()) / m.mean())


def _blocked(sensor: str, run: CalibrationRun, spread_max: float, primary_compass: int, known: bool) -> str:
    """Why ``sensor`` cannot reach its target whatever the poses ("" if nothing says so).
    ``known``: its values are known well enough (bound within :data:`KNOWN_FACTOR` of its
    target) for a value outside ArduPilot's limits to be the sensor's, not the fit's."""
    hard = [g for g in run.gates.gates if g.sensor == sensor and not g.ok and g.name in HARD_GATES]
    if hard and known:
        return f"{reason_text(hard[0])}; more poses do not change that"
    if sensor.startswith("compass") and int(sensor[7:]) != primary_compass:
        r = pair_run(run, int(sensor[7:]))
        if r is not None and r.calibration is not None:
            spread = _field_spread(r)
            if spread > spread_max:
                return (f"its calibrated field magnitude differs by {100 * spread:.0f} % between poses: magnetic "
                        "disturbance near it (steel, magnets, currents) that more poses cannot remove")
    return ""


def _stuck(history: Sequence[tuple[int, float | None]], n: int, poses: int, target: float) -> str:
    """The bound's history ``(intervals, bound)`` says it is not getting to ``target``."""
    recent = [b for k, b in history if k > n - poses]
    before = [b for k, b in history if k <= n - poses]
    if not before:
        return ""
    if all(b is None for b in recent):
        return f"it has had no fit over the last {poses} poses"
    best_recent = min(b for b in recent if b is not None)
    best_before = min((b for b in before if b is not None), default=float("inf"))
    if best_recent > target and best_recent > (1.0 - IMPROVEMENT) * best_before:
        return (f"its bound has not improved over the last {poses} poses ({best_recent:.2f} deg, target "
                f"{target:g} deg): the poses do not identify it")
    return ""


def measure(run: CalibrationRun | None, prep: Prepared, options: Options, *, targets: dict[str, float],
            history: dict[str, list[tuple[int, float | None]]], n: int, min_intervals: int, stuck_poses: int,
            spread_max: float, dropped: Sequence[str] = ()) -> tuple[SensorProgress, ...]:
    """Every expected sensor's :class:`SensorProgress` from the capture's latest fit ``run``
    (``targets``: ``{"tilt": deg, "heading": deg}``). ``history`` (sensor -> [(intervals,
    bound)]) is extended with this fit's bounds when ``n`` is new to it."""
    gates = {(g.sensor, g.name): g.value for g in run.gates.gates} if run is not None else {}
    needs: dict[str, str] = {}
    for g in run.gates.failures() if run is not None else ():
        if g.cause == "data":
            needs.setdefault(g.sensor, reason_text(g))
    out = []
    for s in expected_sensors(prep, options):
        kind = "tilt" if s.startswith("accel") else "heading"
        v = gates.get((s, f"{kind} uncertainty"))
        bound = float(v) if v is not None and np.isfinite(v) else None
        h = history.setdefault(s, [])
        if run is not None and (not h or h[-1][0] != n):
            h.append((n, bound))
        why = ""
        if run is not None and n >= min_intervals:
            known = bound is not None and bound <= KNOWN_FACTOR * targets[kind]
            why = _blocked(s, run, spread_max, options.mag_instance, known) or _stuck(h, n, stuck_poses, targets[kind])
            if why and bound is None:
                said = [w for w in run.warnings if _names(w, s)]
                why = f"{why} ({said[0]})" if said else why
        out.append(SensorProgress(s, kind, bound, targets[kind], why, s in dropped, needs.get(s, "")))
    return tuple(out)


def _names(text: str, sensor: str) -> bool:
    """``text`` (a warning) is about ``sensor`` ("accelerometer 2 ...", "compass 1 ...")."""
    kind, i = ("accelerometer", sensor[5:]) if sensor.startswith("accel") else ("compass", sensor[7:])
    return f"{kind} {i} " in text or f"{kind} {i}:" in text


def stop_reason(progress: Sequence[SensorProgress]) -> str:
    """The reason of a capture every remaining sensor of which met its target."""
    parts = []
    for kind, what in (("heading", "compass"), ("tilt", "accelerometer")):
        met = [p for p in progress if p.kind == kind and not p.dropped and p.bound_deg is not None]
        if met:
            worst = max(met, key=lambda p: p.bound_deg or 0.0)
            parts.append(f"{kind} error bound {worst.bound_deg:.2f} deg <= target {worst.target_deg:g} deg on every "
                         f"{what} (worst: {worst.sensor})")
    dropped = [p for p in progress if p.dropped]
    text = " and ".join(parts) or "every sensor at its target"
    if dropped:
        text += "; finished without " + "; ".join(f"{p.sensor} ({p.blocked or 'the person chose to'})" for p in dropped)
    return text


def tilt_pose_scores(run: CalibrationRun, accel: int, poses: Sequence[tuple[float, float, float]],
                     n_samples: float) -> np.ndarray | None:
    """Score of adding a still interval at each pose for accelerometer ``accel``'s own tilt
    bound (higher is better): minus the largest, over the flight envelope (roll and pitch within
    45 deg), predicted tilt-error variance with that interval's information added
    (:func:`tilt_pose_variances`). None when the accelerometer has no own fit."""
    got = tilt_pose_variances(run, accel, poses, n_samples)
    return None if got is None else -got[1]


def tilt_pose_variances(run: CalibrationRun, accel: int, poses: Sequence[tuple[float, float, float]],
                        n_samples: float) -> tuple[float, np.ndarray] | None:
    """The largest, over the flight envelope (roll and pitch within 45 deg), predicted
    tilt-error variance of accelerometer ``accel``'s own fit now, and (K,) with one more
    interval at each pose (:func:`mavcal.core.accel_fit.tilt_variances`,
    :func:`~mavcal.core.accel_fit.candidate_information`: the Fisher information of its own fit,
    its orientation marginalised). None when the accelerometer has no own fit."""
    fit = dict(run.accel_fits).get(accel)
    am = next((m for m in run.mapping.accel if m.instance == accel), None)
    if fit is None or am is None or fit.information is None or fit.noise_cov is None:
        return None
    to_E = (am.old.board_matrix @ accel_frame(fit.gain)[2]).T  # body -> the fit's frame
    down = np.array([0.0, 0.0, -1.0])  # the specific force at rest points up: -gravity in NED
    cand = np.array([to_E @ euler_to_matrix(*np.radians(q)).T @ down for q in poses])
    C = attitude_grid(step_deg=15.0)
    env = (to_E @ (np.swapaxes(C[::24], 1, 2) @ down).T).T  # yaw 0 of every roll/pitch: tilt does not see heading
    return float(tilt_variances(fit, env)[0]), tilt_variances(fit, env, candidate_information(fit, cand, n_samples))
