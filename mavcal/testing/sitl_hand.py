"""A scripted hand for the SITL vehicle: it holds the poses a guided capture advises.

The capture's advice reaches the hand as ``(n_intervals, (roll, pitch, yaw_magnetic) or None,
done)`` from a callable: :class:`StatusLines` turns the status lines ``mavcal capture`` prints
when piped (and the MAVProxy module prints) into that; an in-process capture can give its
:class:`~mavcal.capture.CaptureStatus` objects (:func:`advice_of_status`).

:class:`AdviceHand` turns :class:`~mavcal.testing.sitl.SitlVehicle` to each advised pose once the
pose it holds has been counted as an interval (yaw + the field's declination: the advice is
relative to magnetic north, the simulator's attitude to true north). With ``return_prob`` it
first comes back to the pose just counted, after a quick turn away (a person who moved too
soon), on a seeded coin per counted interval; when the advice does not change for
``patience_s`` it turns away and comes back to the advised pose.

:class:`ScheduleHand` holds a fixed list of poses instead (:data:`SPREAD_POSES`: every side
down, at different headings), for a recording without advice (``mavcal calibrate DEVICE``).
"""
from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["AdviceHand", "ScheduleHand", "SPREAD_POSES", "StatusLines", "parse_status_line", "advice_of_status",
           "Advice"]

Pose = tuple[float, float, float]
Advice = tuple[int, "Pose | None", bool]

_STATUS = re.compile(r"(\d+) intervals, \w+, heading (?:\S+ deg|not determined)"
                     r"(?:; next: .*\(roll (\S+) pitch (\S+) yaw (\S+) deg magnetic\)|: (done|ABORTED)|: )")


def parse_status_line(line: str) -> Advice | None:
    """``(n, pose or None, done)`` of one status line, or None if it is not one."""
    m = _STATUS.search(line)
    if m is None:
        return None
    n = int(m.group(1))
    if m.group(5):
        return n, None, True
    if m.group(2) is None:
        return n, None, False
    return n, (float(m.group(2)), float(m.group(3)), float(m.group(4))), False


def advice_of_status(st: Any) -> Advice:
    """The same from a :class:`mavcal.capture.CaptureStatus` (None: nothing yet)."""
    if st is None:
        return 0, None, False
    a = st.next_pose
    return st.n_intervals, (None if a is None else (a.roll_deg, a.pitch_deg, a.yaw_deg)), bool(st.done)


class StatusLines:
    """Collects a capture's output lines (from a reader thread: :meth:`follow`) and gives the
    latest status as advice."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._latest: Advice = (0, None, False)
        self._lock = threading.Lock()

    def add(self, line: str) -> None:
        a = parse_status_line(line)
        with self._lock:
            self.lines.append(line.rstrip("\n"))
            if a is not None:
                self._latest = a

    def follow(self, stream: Iterable[str]) -> threading.Thread:
        """Read ``stream`` (a subprocess's text pipe) to its end in a daemon thread."""
        def read() -> None:
            for line in stream:
                self.add(line)

        t = threading.Thread(target=read, name="sitl-status-lines", daemon=True)
        t.start()
        return t

    def __call__(self) -> Advice:
        with self._lock:
            return self._latest

    def text(self) -> str:
        with self._lock:
            return "\n".join(self.lines)


class AdviceHand(threading.Thread):
    """Moves ``sitl`` to each advised pose (see the module docstring). ``poses`` lists the poses
    held (true yaw), ``returns`` the quick returns to the pose just counted."""

    def __init__(self, sitl: Any, advice: Callable[[], Advice], *, return_prob: float = 0.0, seed: int = 0,
                 patience_s: float = 12.0, away_deg: float = 35.0, away_s: float = 0.6,
                 declination_deg: float | None = None) -> None:
        super().__init__(name="sitl-hand", daemon=True)
        self.sitl, self.advice = sitl, advice
        self.decl = sitl.declination_deg if declination_deg is None else declination_deg
        self.return_prob, self.rng = return_prob, np.random.default_rng(seed)
        self.patience_s, self.away_deg, self.away_s = patience_s, away_deg, away_s
        self.halt = threading.Event()
        self.poses: list[Pose] = []
        self.returns = 0
        self.error: BaseException | None = None

    def true_pose(self, pose: Pose) -> Pose:
        return pose[0], pose[1], pose[2] + self.decl

    def _away_and_back(self, pose: Pose) -> bool:
        """A quick turn away (no settling) and back to ``pose``; False when halted."""
        roll, pitch, yaw = pose
        self.sitl.set_pose(roll + self.away_deg, pitch, yaw + self.away_deg, settle=False)
        if self.halt.wait(self.away_s):
            return False
        self.sitl.set_pose(*pose)
        return not self.halt.is_set()

    def run(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # the test sees it (hand.error) instead of a silent thread
            self.error = exc

    def _run(self) -> None:
        held: Pose | None = None
        held_n: int | None = None
        tossed: set[int] = set()
        moved = time.monotonic()
        while not self.halt.is_set():
            n, pose, done = self.advice()
            if done:
                return
            new = held_n is None or n > held_n
            stale = time.monotonic() - moved > self.patience_s
            if pose is None or not (new or stale):
                self.halt.wait(0.05)
                continue
            if new and held is not None and n not in tossed:
                tossed.add(n)
                if self.rng.random() < self.return_prob:  # back to the pose just counted, then ask again
                    if not self._away_and_back(held) or self.halt.wait(1.0):
                        return
                    self.returns += 1
                    moved = time.monotonic()
                    continue
            target = self.true_pose(pose)
            if stale and not new and held is not None:
                if not self._away_and_back(target):
                    return
            else:
                self.sitl.set_pose(*target)
            self.poses.append(target)
            held, held_n, moved = target, n, time.monotonic()

    def stop(self) -> None:
        self.halt.set()
        if self.is_alive():
            self.join(timeout=30)


#: (roll, pitch, yaw true) in degrees: every side of the vehicle down at least once, headings
#: spread, so that both the accelerometer and the compass are identified
SPREAD_POSES: tuple[Pose, ...] = (
    (0, 0, 0), (0, 0, 180), (180, 0, 90), (90, 0, 0), (-90, 0, 180), (0, 85, 45), (0, -85, 225),
    (45, 45, 135), (-45, 30, 300), (135, -30, 30), (-135, 45, 200), (30, -60, 100), (150, 60, 260),
    (-60, -45, 330),
)


class ScheduleHand(threading.Thread):
    """Holds each of ``poses`` for ``hold_s`` once settled (the first for ``first_hold_s``, while
    the tool starts), then stays at the last one; ``finished`` is set after the last hold."""

    def __init__(self, sitl: Any, poses: Iterable[Pose] = SPREAD_POSES, *, hold_s: float = 2.0,
                 first_hold_s: float = 5.0) -> None:
        super().__init__(name="sitl-schedule-hand", daemon=True)
        self.sitl, self.schedule = sitl, list(poses)
        self.hold_s, self.first_hold_s = hold_s, first_hold_s
        self.halt, self.finished = threading.Event(), threading.Event()
        self.poses: list[Pose] = []
        self.error: BaseException | None = None

    def duration_s(self, settle_s: float = 2.0) -> float:
        """About how long the schedule takes."""
        return self.first_hold_s + (len(self.schedule) - 1) * (settle_s + self.hold_s) + settle_s

    def run(self) -> None:
        try:
            for i, pose in enumerate(self.schedule):
                self.sitl.set_pose(*pose)
                self.poses.append(pose)
                if self.halt.wait(self.first_hold_s if i == 0 else self.hold_s):
                    return
            self.finished.set()
        except BaseException as exc:
            self.error = exc

    def stop(self) -> None:
        self.halt.set()
        if self.is_alive():
            self.join(timeout=30)


@dataclass(frozen=True)
class GuidedCapture:
    """What :func:`run_guided_capture` saw: the CLI's exit code, stdout and status lines, the
    hand, the wall time, and how many PARAM_VALUEs the fixture had seen before the capture."""

    rc: int
    stdout: str
    status: StatusLines
    hand: AdviceHand
    took_s: float
    mark: int


def run_guided_capture(sitl: Any, workdir: Path, *, return_prob: float = 0.5, seed: int = 0,
                       timeout_s: float = 300.0, args: Iterable[str] = ()) -> GuidedCapture:
    """``mavcal capture --connect SITL --write --yes [args]`` in ``sitl``'s namespace with an
    :class:`AdviceHand` holding each advised pose (returning to the last one with probability
    ``return_prob``); the JSON report goes to ``workdir/run.json``, the backup to
    ``workdir/backup.param``. The CLI is killed after ``timeout_s`` (subprocess.TimeoutExpired)."""
    status = StatusLines()
    mark = len(sitl.param_values)
    t0 = time.monotonic()
    with open(workdir / "stdout.txt", "w+") as out:
        p = sitl.popen([sys.executable, "-m", "mavcal", "capture", "--connect", sitl.tool_device, "--write", "--yes",
                        "--json", str(workdir / "run.json"), "--backup", str(workdir / "backup.param"), *args],
                       stdout=out, stderr=subprocess.PIPE, text=True)
        reader = status.follow(p.stderr)
        hand = AdviceHand(sitl, status, return_prob=return_prob, seed=seed)
        hand.start()
        try:
            rc = p.wait(timeout=timeout_s)
        finally:
            hand.stop()
            reader.join(timeout=10)
        out.seek(0)
        stdout = out.read()
    return GuidedCapture(rc, stdout, status, hand, time.monotonic() - t0, mark)
