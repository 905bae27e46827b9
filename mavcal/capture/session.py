"""Guided live capture: collect still poses, fit as they come, and say which pose to hold next.

A :class:`CaptureSession` is fed the readings a vehicle streams (``add``), and on every
``update`` it

1. finds the still intervals so far (:mod:`mavcal.segment`, on raw readings recovered with
   the vehicle's parameters, :mod:`mavcal.ardupilot.recover`);
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
4. stops when the predicted heading error bound reaches the target (default 0.5 deg,
   95 %), or aborts with the reason when the field is impossible (magnets, steel: field far
   outside ArduPilot's 185-875 mGauss, or calibrated field magnitudes that disagree between
   intervals).

It neither reads from nor writes to a vehicle; the ``capture`` command and the MAVProxy
module do that.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mavcal.ardupilot.rotations import euler_to_matrix
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.core.models import FORMS, MODEL_CHAIN, MODELS
from mavcal.core.refine import JointParams, JointProblem, Term
from mavcal.errors import MavcalError
from mavcal.pipeline import CalibrationRun, Options, Prepared, calibrate_prepared, prepare
from mavcal.segment import StillConfig
from mavcal.sources.types import ImuLog, ParamTimeline, SensorSeries

log = logging.getLogger(__name__)

G0 = GRAVITY_MPS2


@dataclass(frozen=True)
class CaptureConfig:
    """What the guided capture aims for and when it gives up."""

    target_heading_deg: float = 0.5  # stop when the 95 % heading error bound is below this
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


def euler_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """Body-to-NED rotation Rz(yaw) Ry(pitch) Rx(roll) from degrees (ArduPilot ``from_euler``)."""
    return euler_to_matrix(*np.radians([roll_deg, pitch_deg, yaw_deg]))


_POINTS = ["north", "north-east", "east", "south-east", "south", "south-west", "west", "north-west"]


def describe_pose(roll_deg: float, pitch_deg: float, yaw_deg: float) -> str:
    """Words a person holding the vehicle can follow, e.g. "nose down, rolled 45 deg left"."""
    C = euler_matrix(roll_deg, pitch_deg, yaw_deg)
    down_b = C.T @ np.array([0.0, 0.0, 1.0])  # the body direction that points down
    parts: list[str] = []
    ax = int(np.argmax(np.abs(down_b)))
    if ax == 2 and down_b[2] > 0.7:
        parts.append("level" if down_b[2] > 0.97 else "upright")
    elif ax == 2 and down_b[2] < -0.7:
        parts.append("upside down")
    elif ax == 0 and abs(down_b[0]) > 0.7:
        parts.append("nose down" if down_b[0] > 0 else "nose up")
    elif ax == 1 and abs(down_b[1]) > 0.7:
        parts.append("on its right side" if down_b[1] > 0 else "on its left side")
    # the finer tilts, from the angles
    pitch = float(pitch_deg)
    roll = float((roll_deg + 180) % 360 - 180)
    if "nose" not in parts[0] if parts else True:
        if 10 <= abs(pitch) < 80:
            parts.append(f"nose {'up' if pitch > 0 else 'down'} {abs(pitch):.0f} deg")
    if abs(pitch) < 80 and 10 <= abs(roll) <= 170 and "side" not in (parts[0] if parts else ""):
        parts.append(f"rolled {abs(roll):.0f} deg {'right' if roll > 0 else 'left'}")
    elif abs(pitch) >= 80 and 10 <= abs(roll) <= 170:
        parts.append(f"rolled {abs(roll):.0f} deg {'right' if roll > 0 else 'left'}")
    if not parts:
        parts.append("level")
    # heading: where the nose (or, when the nose is vertical, the top) points, magnetically
    ref = C @ np.array([1.0, 0.0, 0.0])
    what = "nose"
    if abs(ref[2]) > 0.8:
        ref, what = C @ np.array([0.0, 0.0, -1.0]), "top"
    hdg = np.degrees(np.arctan2(ref[1], ref[0])) % 360
    parts.append(f"{what} towards magnetic {_POINTS[int(((hdg + 22.5) % 360) // 45)]}")
    return ", ".join(parts)


def candidate_poses() -> list[tuple[float, float, float]]:
    """Attitudes a person can hold and name: roll, pitch and heading in 45 deg steps."""
    out = []
    for pitch in (-90, -45, 0, 45, 90):
        rolls = (0,) if abs(pitch) == 90 else (-135, -90, -45, 0, 45, 90, 135, 180)
        for roll in rolls:
            for yaw in range(0, 360, 45):
                out.append((float(roll), float(pitch), float(yaw)))
    return out


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


def _information(run: CalibrationRun, poses: Sequence[tuple[float, float, float]], n_samples: float):
    """Information of the intervals so far and of one more interval at each candidate pose.

    Both are Schur complements of the Gauss-Newton normal equations
    (:class:`mavcal.core.refine.JointProblem`) at the current estimate, the orientations
    marginalised; a candidate's means are predicted by the current model. Returns
    (S_cur (P, P), dS (K, P, P), problem, params).
    """
    cal = run.calibration
    spec = MODELS[cal.model]
    seg = run.segmentation
    ai, mi = run.mapping.accel[0].instance, run.mapping.compass[0].instance
    mu_a = np.array([seg.intervals[k].accel_mps2[ai].mean(0) for k in run.intervals_used])
    mu_m = np.array([seg.intervals[k].mag_mgauss[mi].mean(0) for k in run.intervals_used])
    n_a = np.array([seg.intervals[k].accel_mps2[ai].shape[0] for k in run.intervals_used], float)
    n_m = np.array([seg.intervals[k].mag_mgauss[mi].shape[0] for k in run.intervals_used], float)
    fa, fm = FORMS[spec.accel_form], FORMS[spec.mag_form]
    Sa, Sm = cal.accel.noise_cov, cal.mag.noise_cov

    def info(mua, mum, na, nm, R):
        prob = JointProblem([Term("accel", fa, mua, na, Sa), Term("mag", fm, mum, nm, Sm)])
        p = JointParams((cal.accel.gain, cal.mag.gain), (cal.accel.bias, cal.mag.bias), cal.h_z, R)
        _, Jg, Jr = prob.jacobians(p)
        Hgg = np.einsum("nmp,nmq->npq", Jg, Jg)
        Hgr = np.einsum("nmp,nmr->npr", Jg, Jr)
        Hrr = np.einsum("nmr,nms->nrs", Jr, Jr) + 1e-12 * np.eye(3)
        return Hgg - np.einsum("npr,nrs,nqs->npq", Hgr, np.linalg.inv(Hrr), Hgr), prob, p

    S_parts, prob, p = info(mu_a, mu_m, n_a, n_m, cal.orientations)
    pa, pm, R = _predicted(run, poses)
    nn = np.full(len(poses), float(n_samples))
    dS, _, _ = info(pa, pm, nn, nn, R)
    return S_parts.sum(axis=0), dS, prob, p


def _predicted(run: CalibrationRun, poses: Sequence[tuple[float, float, float]]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Accel and compass means (K, 3) the current model predicts at each pose, and the
    rotations (K, 3, 3) inertial (NED, magnetic) -> engine frame E."""
    cal = run.calibration
    board = run.mapping.accel[0].old.board_matrix @ run.mapping.accel[0].frame_rotation  # E -> body
    Cs = np.array([euler_matrix(*q) for q in poses])
    R = np.einsum("ji,nkj->nik", board, Cs)  # (board)^T C^T: inertial (NED, magnetic) -> E
    pa = (cal.accel.gain @ (R @ cal.gravity)[..., None])[..., 0] + cal.accel.bias
    pm = (cal.mag.gain @ (R @ cal.field)[..., None])[..., 0] + cal.mag.bias
    return pa, pm, R


def predicted_means(run: CalibrationRun, poses: Sequence[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) accel (m/s^2) and (K, 3) compass (mGauss) means the current fit predicts for a
    still interval at each pose (roll, pitch, magnetic yaw in degrees), in the frames of the
    recovered readings the fit used."""
    pa, pm, _ = _predicted(run, poses)
    return pa, pm


def heading_gradients(run: CalibrationRun, prob: JointProblem, p) -> np.ndarray:
    """d(heading error)/d(theta) at every attitude of the flight-envelope grid, (M, P).

    The written ArduPilot parameters are held fixed and the *truth* is moved away from the
    estimate along each global parameter (central differences), so ``g_k^T Cov g_k`` is the
    variance of the heading error at attitude k caused by the estimation uncertainty.
    """
    from mavcal.ardupilot.evaluate import attitude_grid, heading_errors_deg
    from mavcal.quality import truth_functions

    am, cm = run.mapping.accel[0], run.mapping.compass[0]
    grid = attitude_grid(step_deg=30.0)
    incl = np.radians(cm.inclination_deg)
    B_ned = cm.field_mgauss * np.array([np.cos(incl), 0.0, np.sin(incl)])
    R_A = am.old.board_matrix
    theta = prob.pack(p)
    sd = np.sqrt(np.maximum(np.diag(run.calibration.param_cov), 1e-300)) if run.calibration.param_cov is not None \
        else np.maximum(np.abs(theta), 1.0) * 1e-4
    G = np.empty((len(grid), len(theta)))
    for j in range(len(theta)):
        errs = []
        for sgn in (1.0, -1.0):
            th = theta.copy()
            th[j] += sgn * 1e-3 * sd[j]
            q = prob.unpack(th, p.R)
            ra, rm = truth_functions(q.gains[0], q.biases[0], q.gains[1], q.biases[1],
                                      np.array([1.0, 0.0, q.h_z]), R_A, cm.old.mount_matrix, cm.field_mgauss)
            errs.append(heading_errors_deg(ra, rm, am.new, cm.new, B_ned, grid))
        G[:, j] = (errs[0] - errs[1]) / (2e-3 * sd[j])
    return G


def pose_scores(run: CalibrationRun, poses: Sequence[tuple[float, float, float]], n_samples: float,
                criterion: str = "heading") -> np.ndarray:
    """Score of adding a still interval at each pose (higher is better).

    ``"heading"``: minus the largest, over the flight envelope, predicted heading-error
    variance g_k^T (S + dS)^-1 g_k (a minimax heading-error criterion; the mean did worse in
    ``benchmarks/capture_guidance.py``); ``"d-optimal"``: log det of the information (S + dS)
    of the global parameters.
    """
    S_cur, dS, prob, p = _information(run, poses, n_samples)
    scale = np.sqrt(np.maximum(np.diag(S_cur), 1e-300))
    D = 1.0 / scale
    M = (S_cur[None] + dS) * D[None, :, None] * D[None, None, :]
    if criterion == "d-optimal":
        sign, logdet = np.linalg.slogdet(M)
        return np.where(sign > 0, logdet, -np.inf)
    G = heading_gradients(run, prob, p) * D[None, :]  # in the scaled coordinates
    try:
        Minv = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        Minv = np.linalg.pinv(M)
    var = np.einsum("kp,npq,kq->nk", G, Minv, G)
    return -var.max(axis=1)


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
        heading = tilt = None
        model = None
        if run is not None and not aborted:
            heading, tilt, model = run.quality.heading_95_deg, run.quality.tilt_95_deg, run.calibration.model
            spread = _field_spread(run) if _paired(run) else 0.0
            if spread > cfg.max_field_spread and n >= n_min + 2:
                aborted = True
                reason = (f"the calibrated field magnitude differs by {100 * spread:.0f} % between poses: magnetic "
                          "disturbance (steel, magnets, currents nearby); move to a clean place and start again")
        done = False
        if aborted:
            done = True
        elif self._stopped:
            done, reason = True, self._stopped
        elif run is not None and heading is not None and heading <= cfg.target_heading_deg and n >= cfg.min_intervals:
            done, reason = True, f"heading error bound {heading:.2f} deg <= target {cfg.target_heading_deg} deg"
        elif n >= cfg.max_intervals:
            done, reason = True, f"{n} intervals: the maximum"
        advice = None
        if not done:
            messages += self._stall_check(n, still_now)
            advice = self.next_pose()
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
                           messages=tuple(messages))
        self._status = st
        return st

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

    def next_pose(self) -> PoseAdvice:
        """The most informative next pose (or the next of the initial plan before a fit).

        Never a pose already recorded (see ``CaptureConfig.repeat_deg``) nor one given up
        after a stall.
        """
        seg = self._prep.segmentation if self._prep else None
        dirs = np.array([iv.gravity_dir for iv in seg.intervals]) if seg and seg.intervals else np.zeros((0, 3))
        if not _paired(self._run) or len(dirs) < PLAN_FIRST:  # no fit yet, or no sensor of the pair accepted
            plan = [q for q in INITIAL_PLAN if q not in self._given_up] or INITIAL_PLAN
            for pose in plan:
                g = euler_matrix(*pose).T @ np.array([0.0, 0.0, 1.0])
                if not len(dirs) or np.max(dirs @ g) < np.cos(np.radians(30)):
                    return _advice(pose)
            return _advice(plan[len(dirs) % len(plan)])
        poses = candidate_poses()
        n_typ = float(np.median([len(self._run.segmentation.intervals[k].accel_mps2[self.options.accel_instance])
                                 for k in self._run.intervals_used]))
        scores = pose_scores(self._run, poses, n_typ, self.config.criterion)
        out = self._excluded(poses)
        if not out.all():
            scores = np.where(out, -np.inf, scores)
        k = int(np.argmax(scores))
        return _advice(poses[k], scores[k])

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
