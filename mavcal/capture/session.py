"""Guided live capture: collect still poses, fit as they come, and say which pose to hold next.

A :class:`CaptureSession` is fed the readings a vehicle streams (``add``), and on every
``update`` it

1. finds the still intervals so far (:mod:`mavcal.segment`, on raw readings recovered with
   the vehicle's parameters, the autopilot model's ``recover_raw``);
2. fits the calibration once enough intervals exist, with its 95 % heading and tilt error
   bounds (:mod:`mavcal.pipeline`);
3. proposes the **next pose**: among candidate attitudes (roll and pitch in 45 degree
   steps, four headings) the one whose still interval most reduces the predicted heading
   error: the Fisher information of the global parameters (orientations marginalised,
   :mod:`mavcal.core.refine` gives the Jacobians) plus that of the candidate interval,
   inverted, and propagated to the heading error over the flight envelope: the pose that
   minimises the *largest* predicted heading-error variance wins, which is what the stop
   rule measures (``criterion="d-optimal"`` maximises log det of the information
   instead). Until six intervals exist a fixed plan (the six faces) is used;
4. stops when every sensor that will be written meets its target (:mod:`mavcal.capture.progress`):
   every compass's 95 % heading bound (default 0.5 deg) and every accelerometer's own tilt
   bound (default 0.3 deg); the advice goes to the sensor furthest from its target; a sensor
   that cannot get there is named with the reason (``CaptureStatus.sensors``,
   ``offer_finish_without``) and :meth:`CaptureSession.finish_without` drops it from the rule;
   it aborts with the reason when the field is impossible (magnets, steel: field far outside
   ArduPilot's 185-875 mGauss, or calibrated field magnitudes of the primary compass that
   disagree between intervals).

It neither reads from nor writes to a vehicle; the ``capture`` command and the MAVProxy
module do that.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mavcal.capture.poses import (
    candidate_poses,
    describe_pose,
    euler_matrix,
    heading_variances,
    pose_scores,
    predicted_means,
)
from mavcal.capture.progress import SensorProgress, measure, pair_run, stop_reason, tilt_pose_variances
from mavcal.capture.reach import ReachWatch, reach_plan, reach_plan_extended
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.core.models import MODEL_CHAIN, MODELS
from mavcal.errors import MavcalError
from mavcal.pipeline import CalibrationRun, Options, Prepared, calibrate_prepared, prepare
from mavcal.segment import StillConfig
from mavcal.sources.types import ImuLog, ParamTimeline, SensorSeries

log = logging.getLogger(__name__)

G0 = GRAVITY_MPS2


@dataclass(frozen=True)
class CaptureConfig:
    """What the guided capture aims for and when it gives up."""

    target_heading_deg: float = 0.5  # stop when every compass's 95 % heading error bound is below this
    target_tilt_deg: float = 0.3  # ... and every accelerometer's own 95 % tilt bound (its gate: 0.5)
    min_intervals: int = 8  # never stop with fewer still intervals
    max_intervals: int = 40
    abort_field_mgauss: tuple[float, float] = (60.0, 2500.0)  # "far outside" ArduPilot's 185-875
    max_field_spread: float = 0.25  # calibrated |field| differing by more than this between intervals
    still: StillConfig = StillConfig(min_duration_s=1.0)
    uncertainty_draws: int = 150
    criterion: str = "heading"  # or "d-optimal"
    # a candidate whose predicted accel and compass directions are both within this of a
    # recorded interval's is that pose again: never advised (held again it only adds samples to
    # that pose, or merges into the last interval when the hand is back within merge_gap_s)
    repeat_deg: float = 15.0
    # advices in a row without a new interval: then the advised pose is given up (the next best
    # one is advised) and the status says what is wrong
    stall_advices: int = 30
    # a sensor whose bound has not improved by 10 % over this many new intervals is said to be
    # unable to reach its target (the person may finish without it)
    stuck_poses: int = 6
    # a vehicle that cannot be turned over: only poses tilted at most this far from level (any
    # heading) are advised; the accelerometers then keep their calibration (None: no limit)
    max_tilt_deg: float | None = None
    # ... and then the capture ends at this many intervals (or max_intervals, the smaller) with a verdict:
    # poses within reach add little after the plan and the advice's first rounds (issue 37)
    max_intervals_reach: int = 25


@dataclass(frozen=True)
class PoseAdvice:
    """A pose to hold: Euler angles (deg, ArduPilot 3-2-1) relative to *magnetic* north."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    words: str
    gravity_body: tuple[float, float, float]  # where gravity points in the body frame (FRD)
    score: float = 0.0

    def matrix(self) -> np.ndarray:
        return euler_matrix(self.roll_deg, self.pitch_deg, self.yaw_deg)


@dataclass(frozen=True)
class CaptureStatus:
    """One screen of capture state."""

    time_s: float
    still_now: bool
    n_intervals: int
    gravity_dirs: tuple[tuple[float, float, float], ...]
    heading_95_deg: float | None
    tilt_95_deg: float | None
    model: str | None
    next_pose: PoseAdvice | None
    done: bool
    reason: str
    aborted: bool = False
    field_mgauss: float | None = None  # raw (as read, before any calibration) |field| of the last interval
    messages: tuple[str, ...] = ()
    field_calibrated_mgauss: float | None = None  # the same with the current fit applied (None before a fit)
    sensors: tuple[SensorProgress, ...] = ()  # every sensor's bound against its target (the stop rule)
    advice_for: str | None = None  # the sensor the next pose is advised for (the furthest from its target)
    offer_finish_without: tuple[str, ...] = ()  # sensors that cannot reach their target: finish without them?


#: poses within reach: a compass bound that fell by less than this fraction over this many new
#: intervals is at the floor set by the kept accelerometer (CaptureSession._reach_floor)
REACH_PLATEAU = 0.10
REACH_PLATEAU_POSES = 3

#: said when the advice repeats a pose: every candidate was held or given up
ALL_HELD = ("every candidate pose has been held (or given up): the most informative one is advised again, as "
            "more samples there still lower the bound")

# the plan before the first fit (and until PLAN_FIRST intervals): six faces, then two diagonals
PLAN_FIRST = 6
INITIAL_PLAN = [(0, 0, 0), (-90, 0, 90), (90, 0, 180), (0, -90, 270), (0, 90, 0), (180, 0, 90),
                (45, 45, 45), (-135, -45, 225)]


def _advice(pose, score=0.0) -> PoseAdvice:
    r, p, y = pose
    C = euler_matrix(r, p, y)
    g = C.T @ np.array([0.0, 0.0, 1.0])
    return PoseAdvice(float(r), float(p), float(y), describe_pose(r, p, y), (float(g[0]), float(g[1]), float(g[2])),
                      float(score))


class CaptureSession:
    """State of one guided capture (see the module docstring).

    Parameters
    ----------
    params : mapping name -> value
        The vehicle's parameters (the calibration in force on the readings).
    config : CaptureConfig
    options : pipeline.Options (instances, field magnitude, location, gates...)
    position : (lat, lon, alt) or None, for the World Magnetic Model
    """

    def __init__(self, params: Mapping[str, float], config: CaptureConfig = CaptureConfig(),
                 options: Options | None = None, *, position=None, source: str = "live") -> None:
        self.params = {k: float(v) for k, v in params.items()}
        self.config = config
        base = options or Options()
        from dataclasses import replace
        self.options = replace(base, still=config.still, uncertainty_draws=config.uncertainty_draws, holdout=False)
        self.position = position
        #: where ``position`` came from, named in the report (e.g. "vehicle GPS"; set with it)
        self.position_source = ""
        self.source = source
        self._chunks: dict[tuple[str, int, str], list[tuple[np.ndarray, np.ndarray]]] = {}
        self._run: CalibrationRun | None = None
        self._run_n = 0
        self._prep: Prepared | None = None
        self._status: CaptureStatus | None = None
        self._stopped: str | None = None
        self.poses_advised: list[PoseAdvice] = []
        self._pieces = 0  # pieces of the last interval at the last update (a merge adds one)
        self._n_seen = 0  # intervals at the last update
        self._since_new = 0  # advices since the interval count last grew
        self._given_up: list[tuple[float, float, float]] = []  # poses advised through a stall
        self.stalls = 0
        self._history: dict[str, list[tuple[int, float | None]]] = {}  # sensor -> [(intervals, bound)]
        self._dropped: dict[str, str] = {}  # sensor -> why the capture finishes without it
        self._progress: tuple[SensorProgress, ...] = ()
        self._floors: dict[str, float] = {}  # poses within reach: compass -> the bound's floor reached
        self._all_held = False  # the last advice repeats a pose: every candidate was held or given up
        self._reach = ReachWatch(config.max_tilt_deg, self.options)  # poses within reach: what they identify

    # ------------------------------------------------------------------ data in
    def add(self, batch: Sequence[SensorSeries]) -> None:
        """Append a batch of readings (SensorSeries of any sensors/instances) as received."""
        for s in batch:
            if len(s):
                self._chunks.setdefault((s.sensor, s.instance, s.message), []).append(
                    (np.asarray(s.time_s), np.asarray(s.values)))

    def snapshot(self) -> ImuLog:
        """Everything received so far as an :class:`ImuLog` (parameters held constant)."""
        series = []
        for (sensor, inst, msg), chunks in sorted(self._chunks.items()):
            t = np.concatenate([c[0] for c in chunks])
            v = np.concatenate([c[1] for c in chunks])
            series.append(SensorSeries(sensor, inst, msg, t, v))
        t0 = min((float(s.time_s[0]) for s in series), default=0.0)
        params = ParamTimeline({k: (np.array([t0 - 1.0]), np.array([v])) for k, v in self.params.items()})
        return ImuLog(self.source, "live", tuple(series), params, (), self.position,
                      position_source=self.position_source)

    def stop(self, reason: str = "stopped by the user") -> None:
        self._stopped = reason

    def finish_without(self, sensors: Sequence[str] | None = None) -> tuple[str, ...]:
        """Drop ``sensors`` (default: those that cannot reach their target, ``offer_finish_without``
        of the last status) from the stop rule: the capture then stops when the others meet
        their targets (at the next :meth:`update` if they already do). They are still fitted
        and judged at the end: a rejected one keeps its current values. Returns those dropped."""
        by_name = {p.sensor: p for p in self._progress}
        names = list(sensors) if sensors is not None else [p.sensor for p in self._progress
                                                           if p.blocked and not p.dropped]
        for name in names:
            p = by_name.get(name)
            self._dropped[name] = p.blocked if p is not None else ""
        return tuple(names)

    def skip_pose(self) -> PoseAdvice:
        """"Can't do this one": the pose advised last is given up (never advised again) and
        another is advised in its place (also added to ``poses_advised``)."""
        last = self._status.next_pose if self._status is not None else None  # the pose shown
        if last is None and self.poses_advised:
            last = self.poses_advised[-1]
        if last is not None:
            self._given_up.append((last.roll_deg, last.pitch_deg, last.yaw_deg))
            log.info("capture: the person cannot hold %s; advising another pose", last.words)
        advice = self.next_pose(self._advice_target() if self._run is not None else None)
        self.poses_advised.append(advice)
        if self._status is not None:
            from dataclasses import replace
            self._status = replace(self._status, next_pose=advice)
        return advice

    @property
    def run(self) -> CalibrationRun | None:
        """The latest fit (None before enough intervals)."""
        return self._run

    @property
    def status(self) -> CaptureStatus | None:
        return self._status

    # ------------------------------------------------------------------ the loop body
    def update(self) -> CaptureStatus:
        """Segment, fit when a new interval appeared, advise the next pose, decide to stop."""
        cfg = self.config
        log_ = self.snapshot()
        if not log_.series or log_.get("accel", self.options.accel_instance) is None:
            st = CaptureStatus(0.0, False, 0, (), None, None, None, _advice(INITIAL_PLAN[0]), False,
                               "waiting for IMU data")
            self._status = st
            return st
        prep = prepare(log_, self.options)
        self._prep = prep
        seg = prep.segmentation
        ivs = seg.intervals
        t_last = max(float(s.time_s[-1]) for s in log_.series)
        still_now = bool(ivs) and ivs[-1].end_s >= t_last - 3.0 / max(seg.sample_rate_hz, 1.0) - cfg.still.trim_s
        messages: list[str] = []
        aborted, reason = False, ""
        # impossible fields: raw field magnitude of every interval
        mi = self.options.mag_instance
        fields = [float(np.linalg.norm(iv.mag_mgauss[mi].mean(0))) for iv in ivs if mi in iv.mag_mgauss and
                  len(iv.mag_mgauss[mi])]
        lo, hi = cfg.abort_field_mgauss
        bad = [f for f in fields if not lo <= f <= hi]
        if bad:
            aborted = True
            reason = (f"impossible magnetic field: {bad[-1]:.0f} mGauss in a still interval (Earth's field is "
                      f"185-875 mGauss): a magnet or steel is next to the compass; move away and start again")
        n = len(ivs)
        n_min = MODELS[MODEL_CHAIN[-1]].min_intervals
        pieces = len(ivs[-1].pieces_s) if ivs else 0
        merged = n == self._n_seen and pieces > self._pieces
        self._pieces = pieces
        if merged:  # a return to the last pose: its interval changed (more still samples), not the count
            messages.append(f"the pose held was the same as interval {n}'s and followed it within "
                            f"{cfg.still.merge_gap_s:g} s: it was merged into that interval, not counted as a new "
                            "one; hold the advised pose")
        if not aborted and n >= n_min and (self._run is None or n != self._run_n or merged):
            try:
                self._run = calibrate_prepared(prep, self.options)
                self._run_n = n
            except MavcalError as exc:
                messages.append(f"no fit yet: {exc}")
        run = self._run
        heading = tilt = model = None
        if run is not None and not aborted:
            heading, tilt, model = run.quality.heading_95_deg, run.quality.tilt_95_deg, run.calibration.model
            spread = _field_spread(run) if _paired(run) else 0.0
            if spread > cfg.max_field_spread and n >= n_min + 2:
                aborted, reason = True, self._reach.spread_reason(spread, prep, n)
        if not aborted and (turned := self._reach.mounting_abort(prep, n, _orientation_fitted(run))):
            aborted, reason = True, turned
        progress = self._progress = self._measure(run if not aborted else None, prep, n)
        done, reason, offer = self._stop_rule(run, n, aborted, reason)
        messages += [] if aborted else self._reach.messages(prep, n, done)
        advice, target = None, None
        if not done:
            messages += self._stall_check(n, still_now)
            target = self._advice_target() if self._run is not None and n >= PLAN_FIRST else None
            advice = self.next_pose()
            messages += [ALL_HELD] if self._all_held else []
            messages += [f"{p.sensor} cannot reach its target: {p.blocked}; finish without it (it keeps its current "
                         "values if it is rejected) or keep holding poses" for p in progress if p.sensor in offer]
            messages += [f"{p.sensor}'s bound is at its target but the poses do not identify it yet: {p.needs}"
                         for p in progress if p.needs and not p.dropped and p.bound_deg is not None
                         and p.bound_deg <= p.target_deg]
        if advice is not None:
            self.poses_advised.append(advice)
        st = CaptureStatus(time_s=t_last, still_now=still_now, n_intervals=n,
                           gravity_dirs=tuple((float(iv.gravity_dir[0]), float(iv.gravity_dir[1]),
                                               float(iv.gravity_dir[2])) for iv in ivs),
                           heading_95_deg=heading, tilt_95_deg=tilt, model=model, next_pose=advice, done=done,
                           reason=reason or ("still: keep holding" if still_now else "move to the next pose"),
                           aborted=aborted, field_mgauss=fields[-1] if fields else None,
                           field_calibrated_mgauss=_calibrated_field(run, ivs[-1]) if _paired(run) and ivs
                           else None,
                           messages=tuple(messages), sensors=progress, advice_for=target,
                           offer_finish_without=() if done else offer)
        self._status = st
        return st

    def _stop_rule(self, run: CalibrationRun | None, n: int, aborted: bool, reason: str
                   ) -> tuple[bool, str, tuple[str, ...]]:
        """(done, reason, the sensors that cannot reach their target) from ``self._progress``:
        done when aborted, stopped, every sensor not dropped meets its target (at
        ``min_intervals`` at least) or at ``max_intervals``."""
        cfg = self.config
        remaining = [p for p in self._progress if not p.dropped]
        offer = tuple(p.sensor for p in remaining if p.blocked and not p.met)
        if aborted:
            return True, reason, offer
        if self._stopped:
            return True, self._stopped + (f" (without {', '.join(offer)}: cannot reach the target)" if offer
                                          else ""), offer
        kept = {p.sensor for p in remaining}
        # met includes calibrate's coverage rule (SensorProgress.needs: its failed data gates)
        if run is not None and n >= cfg.min_intervals and remaining and all(p.met for p in remaining):
            floors = [f"{s} {b:.2f} deg" for s, b in self._floors.items() if s in kept]
            return True, stop_reason(self._progress) + (
                f"; poses within reach: the bound has reached its floor ({', '.join(floors)}: the kept "
                "accelerometer's uncertainty, which more poses do not lower)" if floors else ""), offer
        if n >= cfg.max_intervals:
            return True, f"{n} intervals: the maximum", offer
        if cfg.max_tilt_deg is not None and n >= cfg.max_intervals_reach:
            assert self._prep is not None
            return True, self._reach.cap_reason(self._prep, n, self._progress), offer
        if offer and all(p.met or p.sensor in offer for p in remaining):
            reason = (f"every other sensor has reached its target; {', '.join(offer)} cannot: finish without "
                      f"{'it' if len(offer) == 1 else 'them'} or keep holding poses")
        return False, reason, offer

    def _measure(self, run: CalibrationRun | None, prep: Prepared, n: int) -> tuple[SensorProgress, ...]:
        """Every sensor's bound against its target (:func:`mavcal.capture.progress.measure`)."""
        cfg = self.config
        progress = measure(run, prep, self.options, targets={"tilt": cfg.target_tilt_deg,
                                                             "heading": cfg.target_heading_deg},
                           history=self._history, n=n, min_intervals=cfg.min_intervals,
                           stuck_poses=cfg.stuck_poses, spread_max=cfg.max_field_spread, dropped=list(self._dropped))
        from dataclasses import replace
        if cfg.max_tilt_deg is not None:  # poses within reach: the accelerometers keep their calibration
            progress = tuple(self._reach_floor(p, n) for p in progress if p.kind != "tilt")
        return tuple(replace(p, blocked=p.blocked or self._dropped[p.sensor]) if p.dropped else p for p in progress)

    def _reach_floor(self, p: SensorProgress, n: int) -> SensorProgress:
        """Poses within reach: a compass's bound has a floor the poses cannot lower (the kept
        accelerometer's uncertainty, :mod:`mavcal.core.held`). Once at least ``min_intervals``
        are held, the bound is within the heading gate and it fell by less than
        :data:`REACH_PLATEAU` over the last :data:`REACH_PLATEAU_POSES` new intervals, it has
        reached that floor: its target becomes the bound (met), and the stop reason says so."""
        from dataclasses import replace
        h = [(k, b) for k, b in self._history.get(p.sensor, []) if b is not None]
        gate = self.options.gates.heading_95_max_deg
        if p.met or p.bound_deg is None or n < self.config.min_intervals or p.bound_deg > gate:
            return p
        before = [b for k, b in h if k <= n - REACH_PLATEAU_POSES]
        if not before or p.bound_deg < (1.0 - REACH_PLATEAU) * min(before):
            return p
        self._floors[p.sensor] = p.bound_deg
        return replace(p, target_deg=float(np.ceil(p.bound_deg * 100.0) / 100.0), blocked="")

    def _advice_target(self) -> str | None:
        """The sensor furthest from its target (bound / target) among those not met, not dropped
        and able to get there; else among those that cannot (they may yet); None when all are met."""
        todo = [p for p in self._progress if not p.met and not p.dropped]
        can = [p for p in todo if not p.blocked] or todo
        return max(can, key=lambda p: p.distance).sensor if can else None

    def _stall_check(self, n: int, still_now: bool) -> list[str]:
        """Count advices since the interval count last grew; after ``stall_advices`` of them give
        the advised pose up (the next advice is another one) and say what is wrong."""
        if n > self._n_seen:
            self._n_seen, self._since_new = n, 0
            return []
        self._n_seen = n
        self._since_new += 1
        if self._since_new < self.config.stall_advices or not self.poses_advised:
            return []
        last = self.poses_advised[-1]
        self._given_up.append((last.roll_deg, last.pitch_deg, last.yaw_deg))
        self._since_new = 0
        self.stalls += 1
        why = ("the vehicle was held still but no new interval came: the pose held is one already recorded, or it "
               "was not held within the still thresholds" if still_now else
               "the vehicle was never still long enough: hold it completely still")
        log.info("capture stalled at %d intervals: %s", n, why)
        return [f"no new still interval for {self.config.stall_advices} advices ({why}); advising another pose "
                f"instead of {last.words}"]

    def next_pose(self, target: str | None = None) -> PoseAdvice:
        """The most informative next pose, or the next of the initial plan before a fit.

        The pose that most lowers the largest predicted bound / target ratio among the sensors
        (those that can reach their target, not dropped; or ``target`` alone): the sensor
        furthest from its target leads, and of the poses about as good for it the one that helps
        the others most (the smallest mean ratio) wins. A compass's predicted bound is its bound
        now times sqrt(predicted / current worst heading variance) (:func:`heading_variances` on
        its fit with the primary accelerometer), an accelerometer's the same with its own tilt
        variance (:func:`mavcal.capture.progress.tilt_pose_variances`). ``criterion="d-optimal"``:
        the primary pair's :func:`pose_scores`. Never a pose already recorded (see
        ``CaptureConfig.repeat_deg``) nor one given up after a stall.
        """
        self._all_held = False
        seg = self._prep.segmentation if self._prep else None
        dirs = np.array([iv.gravity_dir for iv in seg.intervals]) if seg and seg.intervals else np.zeros((0, 3))
        reach = self.config.max_tilt_deg
        if not _paired(self._run) or len(dirs) < PLAN_FIRST:  # no fit yet, or no sensor of the pair accepted
            if reach is not None:  # every pose near level: the plan by the count of intervals, never cycled
                plan = [q for q in reach_plan_extended(reach) if q not in self._given_up] or reach_plan(reach)
                return _advice(plan[min(len(dirs), len(plan) - 1)])
            plan = [q for q in INITIAL_PLAN if q not in self._given_up] or INITIAL_PLAN
            for pose in plan:
                g = euler_matrix(*pose).T @ np.array([0.0, 0.0, 1.0])
                if not len(dirs) or np.max(dirs @ g) < np.cos(np.radians(30)):
                    return _advice(pose)
            return _advice(plan[len(dirs) % len(plan)])
        poses = candidate_poses(reach)
        n_typ = float(np.median([len(self._run.segmentation.intervals[k].accel_mps2[self.options.accel_instance])
                                 for k in self._run.intervals_used]))
        out = self._excluded(poses)
        self._all_held = bool(out.all())
        ratios = self._predicted_ratios(poses, n_typ, target) if self.config.criterion == "heading" else []
        if ratios:
            R = np.array(ratios)  # (sensors, K)
            worst, mean = R.max(axis=0), R.mean(axis=0)
            if not out.all():
                worst = np.where(out, np.inf, worst)
            near = np.flatnonzero(worst <= worst.min() * (1.0 + 1e-3))
            k = int(near[int(np.argmin(mean[near]))])
            return _advice(poses[k], -float(worst[k]))
        scores = pose_scores(self._run, poses, n_typ, self.config.criterion)
        if not out.all():
            scores = np.where(out, -np.inf, scores)
        k = int(np.argmax(scores))
        return _advice(poses[k], scores[k])

    def _predicted_ratios(self, poses: Sequence[tuple[float, float, float]], n: float,
                          target: str | None) -> list[np.ndarray]:
        """(K,) predicted bound / target after one more interval at each pose, for every sensor
        the advice serves (``target`` alone when given; else those not dropped, with a bound, and
        able to reach their target unless none of those still misses it)."""
        assert self._run is not None
        have = [p for p in self._progress if not p.dropped and p.bound_deg is not None]
        if target is not None:
            have = [p for p in have if p.sensor == target]
        elif any(not p.met and not p.blocked for p in have):
            have = [p for p in have if not p.blocked]
        out = []
        for p in have:
            if p.kind == "tilt":
                got = tilt_pose_variances(self._run, int(p.sensor[5:]), poses, n)
            else:
                r = pair_run(self._run, int(p.sensor[7:]))
                got = heading_variances(r, poses, n) if r is not None else None
            if got is not None and got[0] > 0 and p.bound_deg is not None:
                out.append(p.bound_deg / p.target_deg * np.sqrt(np.maximum(got[1], 0.0) / got[0]))
        return out

    def _excluded(self, poses: Sequence[tuple[float, float, float]]) -> np.ndarray:
        """(K,) bool: the candidate repeats a recorded interval (predicted accel and compass
        means both within ``repeat_deg`` of its means) or was given up after a stall."""
        assert self._run is not None and self._prep is not None
        ivs = self._prep.segmentation.intervals
        ai, mi = self._run.mapping.accel[0].instance, self._run.mapping.compass[0].instance
        rec = [(iv.accel_mps2[ai].mean(0), iv.mag_mgauss[mi].mean(0)) for iv in ivs
               if len(iv.accel_mps2.get(ai, ())) and len(iv.mag_mgauss.get(mi, ()))]
        out = np.array([q in self._given_up for q in poses])
        if not rec:
            return out
        pa, pm = predicted_means(self._run, poses)
        mu_a = np.array([r[0] for r in rec])
        mu_m = np.array([r[1] for r in rec])
        if self.config.max_tilt_deg is not None:  # poses within reach: every accel mean is near level, and a
            cal = self._run.calibration  # large hard iron makes raw compass means alike: compare the field itself
            assert cal is not None
            pm, mu_m = (np.linalg.solve(cal.mag.gain, (x - cal.mag.bias).T).T for x in (pm, mu_m))
        cos_r = np.cos(np.radians(self.config.repeat_deg))

        def cos(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            x = x / np.linalg.norm(x, axis=1, keepdims=True)
            y = y / np.linalg.norm(y, axis=1, keepdims=True)
            return x @ y.T

        return out | np.any((cos(pa, mu_a) >= cos_r) & (cos(pm, mu_m) >= cos_r), axis=1)

    def result(self, options: Options | None = None, *, progress=None) -> CalibrationRun:
        """The final fit with the full quality analysis (held-out errors, more draws);
        ``progress`` as :func:`mavcal.pipeline.calibrate_prepared` takes it."""
        if self._prep is None:
            self.update()
        if self._prep is None or not self._prep.segmentation.intervals:
            from mavcal.errors import InsufficientDataError
            raise InsufficientDataError("no still intervals captured")
        return calibrate_prepared(self._prep, options or Options(still=self.config.still,
                                                                  accel_instance=self.options.accel_instance,
                                                                  mag_instance=self.options.mag_instance,
                                                                  location=self.options.location,
                                                                  field_mgauss=self.options.field_mgauss),
                                  progress=progress)


def _orientation_fitted(run: CalibrationRun | None) -> bool:
    """True when ``run`` writes a new orientation of its primary compass (a turn the tilts identified)."""
    return _paired(run) and any(k.endswith("ORIENT") for k in run.mapping.compass[0].extra_params)  # type: ignore[union-attr]


def _paired(run: CalibrationRun | None) -> bool:
    """True when ``run`` maps the primary pair: an accelerometer and a compass. A fit of a few
    poses may reject both (e.g. the compass's dip against the World Magnetic Model at the
    vehicle's position, and the accelerometer's own fit): it gives no advice then."""
    return run is not None and bool(run.mapping.accel) and bool(run.mapping.compass)


def _calibrated_field(run: CalibrationRun, iv) -> float | None:
    """|field| (mGauss) of interval ``iv``'s mean compass reading with the fit applied:
    |K_m^-1 (m - b_m)| scaled from the model's field (1, 0, h_z) to the mapped magnitude."""
    mi = run.mapping.compass[0].instance
    m = iv.mag_mgauss.get(mi)
    if m is None or not len(m):
        return None
    cal = run.calibration
    z = np.linalg.solve(cal.mag.gain, m.mean(0) - cal.mag.bias)
    return float(np.linalg.norm(z) / np.linalg.norm(cal.field) * run.mapping.compass[0].field_mgauss)


def _field_spread(run: CalibrationRun) -> float:
    """Relative spread (max - min) / mean of the calibrated field magnitude over the intervals."""
    cal = run.calibration
    seg = run.segmentation
    mi = run.mapping.compass[0].instance
    mus = np.array([seg.intervals[k].mag_mgauss[mi].mean(0) for k in run.intervals_used])
    z = np.linalg.solve(cal.mag.gain, (mus - cal.mag.bias).T).T
    r = np.linalg.norm(z, axis=1)
    return float((r.max() - r.min()) / r.mean())


def coverage_map(gravity_dirs: Sequence[Sequence[float]], width: int = 36, height: int = 9) -> str:
    """A coarse text map of the covered gravity directions (body frame), for a terminal.

    Columns: azimuth of gravity in the body x-y plane (-180..180 deg, 0 = nose down);
    rows: elevation from "top down" (+90, upside down) to "bottom down" (-90, level).
    ``#`` marks a covered cell, ``.`` an empty one.
    """
    grid = [["." for _ in range(width)] for _ in range(height)]
    for g in gravity_dirs:
        x, y, z = g
        az = np.degrees(np.arctan2(y, x))
        el = np.degrees(np.arcsin(np.clip(-z, -1, 1)))
        c = int((az + 180) / 360 * (width - 1) + 0.5)
        r = int((90 - el) / 180 * (height - 1) + 0.5)
        for dc in (-1, 0, 1):
            grid[r][(c + dc) % width] = "#"
    lines = ["upside down " + "".join(grid[0])]
    lines += [" " * 12 + "".join(row) for row in grid[1:-1]]
    lines.append("level       " + "".join(grid[-1]))
    return "\n".join(lines)
