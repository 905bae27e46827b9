"""What the live capture page shows, as plain JSON-ready values (no I/O, no server).

* :class:`LiveAttitude`: the vehicle's attitude *now* from its newest accelerometer and
  compass readings (gravity gives roll and pitch, the compass the magnetic heading; the
  readings as sent, i.e. corrected by the calibration in force), and whether it is moving or
  has been still for how long (the same thresholds as the still-interval detector).
* :func:`status_view`: a :class:`~mavcal.capture.session.CaptureStatus` as the page draws it:
  the pose to hold next as a body-to-NED (magnetic) rotation matrix, the sides that have faced
  down so far, and each sensor's bound against its target (heading for a compass, tilt for an
  accelerometer) from the session's latest fit.
* :func:`result_view`: the final fit as the page's verdict: per sensor accepted or not with
  the reasons, the next step, and the table of exactly the parameters that will be written
  (old -> new; a rejected sensor's rows marked "not written").
"""
from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from mavcal.autopilot.gates import GateConfig
from mavcal.capture.session import CaptureConfig, CaptureStatus, euler_matrix
from mavcal.determined import determined
from mavcal.segment import StillConfig
from mavcal.sources.types import SensorSeries

__all__ = ["LiveAttitude", "PageFeed", "status_view", "sensor_bounds", "result_view", "attitude_matrix"]

_MAX_SAMPLES = 512
#: the live heading uses the fit so far once its 95 % heading bound is below this (deg)
FIT_HEADING_MAX_DEG = 10.0  # per sensor kept for the live view (a few seconds at the fastest stream)


def attitude_matrix(accel_mps2: Sequence[float], mag_mgauss: Sequence[float] | None) -> np.ndarray | None:
    """Body (FRD) -> NED rotation with magnetic north, from one accelerometer and one compass
    reading (TRIAD: gravity first, then the compass's horizontal part); None when the
    accelerometer reads nothing. Without a usable compass the heading is taken as north."""
    f = np.asarray(accel_mps2, float)
    if not np.all(np.isfinite(f)) or np.linalg.norm(f) < 1.0:
        return None
    down = -f / np.linalg.norm(f)  # a still accelerometer reads minus gravity
    east = None
    if mag_mgauss is not None:
        m = np.asarray(mag_mgauss, float)
        e = np.cross(down, m)  # down x field = |B_north| east
        if np.all(np.isfinite(e)) and np.linalg.norm(e) > 1e-6 * max(np.linalg.norm(m), 1e-9):
            east = e / np.linalg.norm(e)
    if east is None:  # no compass (or the field straight down): any east perpendicular to down
        ref = np.array([1.0, 0.0, 0.0]) if abs(down[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        east = np.cross(down, ref)
        east /= np.linalg.norm(east)
    north = np.cross(east, down)
    return np.vstack([north, east, down])  # rows: NED axes in body coordinates, i.e. C (body -> NED)


class LiveAttitude:
    """The vehicle's attitude now and whether it is still, from the batches of a capture.

    ``feed`` is called with every received batch (the capture's thread), ``view`` from any
    thread (a lock guards the few samples kept).
    """

    def __init__(self, still: StillConfig | None = None, accel_instance: int = 0, mag_instance: int = 0) -> None:
        self.still = still or StillConfig()
        self.accel_instance, self.mag_instance = accel_instance, mag_instance
        self._lock = threading.Lock()
        self._acc: deque[tuple[float, np.ndarray]] = deque(maxlen=_MAX_SAMPLES)
        self._gyr: deque[tuple[float, np.ndarray]] = deque(maxlen=_MAX_SAMPLES)
        self._mag: deque[tuple[float, np.ndarray]] = deque(maxlen=_MAX_SAMPLES)
        self._still_since: float | None = None
        self._compass_cals: tuple[Any, Any] | None = None

    def use_compass_fit(self, old: Any, new: Any) -> None:
        """Correct the compass readings (sent corrected by ``old``, the calibration in force) by
        the fit so far (``new``) before taking the heading: the raw compass of an uncalibrated
        vehicle can be tens of degrees off. ``old``/``new``: :class:`~mavcal.autopilot.calform.CompassCal`."""
        with self._lock:
            self._compass_cals = (old, new)

    def feed(self, batch: Sequence[SensorSeries]) -> None:
        """File the newest readings of the capture's accelerometer, gyro and compass."""
        with self._lock:
            for s in batch:
                if not len(s):
                    continue
                want = self.mag_instance if s.sensor == "mag" else self.accel_instance
                dq = {"accel": self._acc, "gyro": self._gyr, "mag": self._mag}.get(s.sensor)
                if dq is None or s.instance != want:
                    continue
                vals = np.asarray(s.values, float)
                for t, v in zip(np.asarray(s.time_s, float)[-_MAX_SAMPLES:], vals[-_MAX_SAMPLES:]):
                    dq.append((float(t), v))
            self._track_still()

    def _window(self, dq: deque, span_s: float) -> np.ndarray:
        if not dq:
            return np.zeros((0, 3))
        t_end = dq[-1][0]
        return np.array([v for t, v in dq if t >= t_end - span_s])

    def _track_still(self) -> None:
        """Still now: over the last window, RMS gyro and accelerometer scatter below the
        detector's thresholds (without a gyro, the accelerometer alone)."""
        if not self._acc:
            return
        cfg = self.still
        a = self._window(self._acc, cfg.window_s)
        g = self._window(self._gyr, cfg.window_s)
        still = len(a) >= 2 and float(a.std(axis=0).max()) <= cfg.accel_std_mps2
        if still and len(g):
            still = float(np.sqrt(np.mean(np.sum(g * g, axis=1)))) <= cfg.gyro_rad_s
        t_now = self._acc[-1][0]
        if not still:
            self._still_since = None
        elif self._still_since is None:  # from when it is seen still: the ring fills from empty
            self._still_since = t_now

    def view(self) -> dict[str, Any] | None:
        """``{"C": 3x3 body->NED (magnetic), "still": bool, "still_s": s, "hold_s": s needed}``,
        or None before the first reading."""
        with self._lock:
            if not self._acc:
                return None
            a = self._window(self._acc, 0.3).mean(axis=0)
            m = self._window(self._mag, 0.3).mean(axis=0) if self._mag else None
            t_now = self._acc[-1][0]
            since = self._still_since
            cals = self._compass_cals
        if m is not None and cals is not None:
            from mavcal.autopilot.calform import apply_compass, undo_compass

            m = np.asarray(apply_compass(cals[1], undo_compass(cals[0], m, sensor_frame=True)), float).reshape(3)
        C = attitude_matrix(a, m)
        cfg = self.still
        return {"C": None if C is None else _r(C), "still": since is not None,
                "still_s": 0.0 if since is None else round(t_now - since, 2),
                "hold_s": round(cfg.min_duration_s + 2 * cfg.trim_s, 2), "compass": m is not None,
                "heading_source": "fit" if m is not None and cals is not None else "raw"}


def _r(a: Any, nd: int = 4) -> Any:
    """Rounded nested lists (small JSON)."""
    return np.round(np.asarray(a, float), nd).tolist()


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(float(x)) else float(x)


def sensor_bounds(run: Any, config: CaptureConfig) -> list[dict[str, Any]]:
    """Each sensor's 95 % bound against its target, from a fit's gates: a compass's heading
    bound against the capture's heading target, an accelerometer's tilt bound (its own fit)
    against the tilt gate's limit."""
    if run is None:
        return []
    tilt_target = float(getattr(config, "target_tilt_deg", None) or GateConfig().tilt_95_max_deg)
    out = []
    for sensor, gates in run.gates.by_sensor().items():
        for g in gates:
            if g.name == "heading uncertainty" and sensor.startswith("compass"):
                what, target = "heading", float(config.target_heading_deg)
            elif g.name == "tilt uncertainty" and sensor.startswith("accel"):
                what, target = "tilt", tilt_target
            else:
                continue
            bound = _finite(g.value)
            out.append({"sensor": sensor, "what": what, "bound_deg": bound, "target_deg": target,
                        "met": bound is not None and bound <= target, "determined": determined(what, bound)})
    return out


def _pose(p: Any) -> dict[str, Any] | None:
    if p is None:
        return None
    return {"C": _r(euler_matrix(p.roll_deg, p.pitch_deg, p.yaw_deg)), "words": p.words,
            "roll": p.roll_deg, "pitch": p.pitch_deg, "yaw": p.yaw_deg, "down": _r(p.gravity_body)}


def _progress_view(st: CaptureStatus, config: CaptureConfig, run: Any) -> list[dict[str, Any]]:
    """Each sensor's bound against its target: the status's own (``st.sensors``, the stop
    rule's view, when the session gives it), else from the fit's gates."""
    progress = getattr(st, "sensors", ()) or ()
    if not progress:
        return sensor_bounds(run, config)
    return [{"sensor": p.sensor, "what": p.kind, "bound_deg": _finite(p.bound_deg), "target_deg": float(p.target_deg),
             "met": bool(p.met), "blocked": p.blocked, "dropped": bool(p.dropped),
             "needs": p.needs, "determined": determined(p.kind, _finite(p.bound_deg))}
            for p in progress]


def status_view(st: CaptureStatus, config: CaptureConfig, run: Any = None) -> dict[str, Any]:
    """The page's view of one capture status (``run``: the session's latest fit, for the
    per-sensor bounds when the status has none of its own)."""
    return {"n": st.n_intervals, "finish_without": list(getattr(st, "offer_finish_without", ()) or ()),
            "advice_for": getattr(st, "advice_for", None), "still": st.still_now, "done": st.done,
            "aborted": st.aborted, "reason": st.reason, "messages": list(st.messages),
            "down_dirs": _r(st.gravity_dirs, 3), "next": _pose(st.next_pose), "heading_deg": _finite(st.heading_95_deg),
            "tilt_deg": _finite(st.tilt_95_deg), "target_deg": config.target_heading_deg,
            "min_poses": config.min_intervals, "max_poses": config.max_intervals,
            "max_tilt": getattr(config, "max_tilt_deg", None),
            "sensors": _progress_view(st, config, run)}


def result_view(run: Any, changes: dict[str, float], *, hints: dict[str, str] | None = None) -> dict[str, Any]:
    """The verdict: per sensor accepted or not (reasons; what to do), the next step, and the
    parameter table: every parameter of every sensor, old -> new, ``write`` True exactly for
    those in ``changes`` (what the Write button writes)."""
    from mavcal.report.text import format_value, next_step

    by_sensor = run.mapping.by_sensor()
    sensor_of = {n: s for s, names in by_sensor.items() for n in names}
    rejected = run.rejected_params()
    rows = []
    for name, new in sorted(run.mapping.new.items(), key=lambda kv: (sensor_of.get(kv[0], "~"), kv[0])):
        old = run.mapping.old.get(name)
        changed = old is None or np.float32(old) != np.float32(new)
        rows.append({"name": name, "sensor": sensor_of.get(name, ""), "old": format_value(old),
                     "new": format_value(new), "changed": bool(changed), "write": name in changes,
                     "why_not": rejected.get(name, "") if name not in changes else ""})
    verdicts = [{"sensor": v.sensor, "accepted": v.accepted, "reasons": list(v.reasons)} for v in run.verdicts]
    q = run.quality
    return {"verdicts": verdicts, "next_step": next_step(run, **(hints or {})), "params": rows,
            "n_write": sum(1 for r in rows if r["write"] and r["changed"]), "exit_code": run.exit_code,
            "heading_deg": _finite(q.heading_95_deg), "tilt_deg": _finite(q.tilt_95_deg),
            "heading_determined": determined("heading", _finite(q.heading_95_deg)),
            "tilt_determined": determined("tilt", _finite(q.tilt_95_deg))}


class PageFeed:
    """Turns a capture's batches and statuses into page state (``set``: e.g.
    :meth:`mavcal.capture.web.PageState.set`): the live attitude at most every
    ``live_every_s``, every status with the session's latest fit's per-sensor bounds."""

    def __init__(self, set_state: Any, config: CaptureConfig, accel_instance: int = 0, mag_instance: int = 0,
                 live_every_s: float = 0.1) -> None:
        import time

        self._clock = time.monotonic
        self.set_state = set_state
        self.config = config
        self.live = LiveAttitude(config.still, accel_instance, mag_instance)
        self.live_every_s = live_every_s
        self.session: Any = None
        self._last_live = float("-inf")
        self._fit_used: Any = None

    def batch(self, session: Any, batch: Sequence[SensorSeries]) -> None:
        """A received batch (the capture's thread)."""
        self.session = session
        self.live.feed(batch)
        now = self._clock()
        if now - self._last_live >= self.live_every_s:
            self._last_live = now
            self.set_state(live=self.live.view())

    def status(self, st: CaptureStatus, run: Any = None, finish: bool = False, skip: bool = False) -> None:
        """A capture status; ``run`` defaults to the session's latest fit. ``finish``: the page
        asked to finish without the sensors the status offers to leave out; the session is told
        (:meth:`~mavcal.capture.CaptureSession.finish_without`, when it has one) here, between
        two updates, so call it from the thread that updates the session. ``skip``: the page
        cannot hold the advised pose: the session advises another
        (:meth:`~mavcal.capture.CaptureSession.skip_pose`) and the status shows it."""
        if finish and getattr(st, "offer_finish_without", ()) and self.session is not None:
            finish_without = getattr(self.session, "finish_without", None)
            if finish_without is not None:
                finish_without(list(st.offer_finish_without))
        if skip and not st.done and self.session is not None and getattr(self.session, "skip_pose", None):
            self.session.skip_pose()
            st = self.session.status or st
        if run is None and self.session is not None:
            run = self.session.run
        if run is not None and run is not self._fit_used:
            self._fit_used = run
            self._use_fit(run)
        phase = "capturing" if not st.done else ("aborted" if st.aborted else "fitting")
        self.set_state(phase=phase, status=status_view(st, self.config, run), live=self.live.view())

    def _use_fit(self, run: Any) -> None:
        """The live heading from the compass as calibrated so far, once the fit's heading bound
        is below ``FIT_HEADING_MAX_DEG`` (an early fit can be worse than the raw compass)."""
        heading = _finite(run.quality.heading_95_deg)
        if heading is None or heading > FIT_HEADING_MAX_DEG:
            return
        for cm in run.mapping.compass:
            if cm.instance == self.live.mag_instance:
                self.live.use_compass_fit(cm.old, cm.new)
