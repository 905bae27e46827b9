"""When a logged parameter value is known to be in force.

A log shows a parameter value only when it was sent (PARAM_VALUE) or logged (PARM). The
value seen is known to be in force from that moment back to the last event that could
have changed it, and up to the next such event:

* a reboot (the tlog time base restarts; the compass order may change with it);
* an onboard compass calibration report or accept (``Mag(n) good/bad orientation``,
  MAV_CMD_DO_ACCEPT_MAG_CAL, MAV_CMD_FIXED_MAG_CAL_YAW) and, bounding it from before,
  its start (MAV_CMD_DO_START_MAG_CAL, MAV_CMD_PREFLIGHT_CALIBRATION param2 = 1);
* the end of an onboard accelerometer calibration (the periods of
  :func:`mavcal.ardupilot.recover.find_accel_cal_periods`; during them the firmware
  ignores the accel offsets/scale, so their value does not matter there), a simple accel
  calibration (MAV_CMD_PREFLIGHT_CALIBRATION param5 = 4), MAV_CMD_PREFLIGHT_SET_SENSOR_OFFSETS;
* a PARAM_SET of that parameter (LogEvent kind ``"param_set"``), or the PARAM_VALUE
  showing it changed (a new entry in its :class:`ParamTimeline`).

So, per parameter with sightings ``t_0 < t_1 < ...`` (value changes): ``v_0`` is known
from the last event at or before ``t_0`` (from the start of the log when there is none);
``v_{k-1}`` is known up to the first event after ``t_{k-1}`` that could have changed it
(``start`` events do not end it), and ``v_k`` from the last event before ``t_k`` (``t_k``
itself when there is none). Between those bounds the value is unknown: readings there
cannot be un-corrected and are left out.
"""
from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.mavlink import MAV_CMD, MAV_CMD_PREFLIGHT_CALIBRATION
from mavcal.sources.types import LogEvent, ParamTimeline

__all__ = ["ChangeEvent", "KnownValues", "change_events", "known_values", "accel_cal_events", "scope_of"]

_MAG_REPORT = re.compile(r"^Mag\((\d)\) (good|bad) orientation", re.I)
_ALL = -1  # instance wildcard of a scope


@dataclass(frozen=True)
class ChangeEvent:
    """An event that could have changed calibration parameters.

    scope : "accel", "compass" or "all"; instance: the sensor instance it concerns
    (-1 = every instance of the scope); name: a single parameter (PARAM_SET) or "";
    start: True when it only starts something whose result comes later (a calibration
    start): the old value holds until a later event.
    """

    time_s: float
    scope: str
    instance: int = _ALL
    name: str = ""
    start: bool = False
    why: str = ""


def _mask_instances(mask: float) -> list[int]:
    m = int(round(mask))
    return [_ALL] if m == 0 else [k for k in range(fw.MAX_COMPASSES) if m & (1 << k)]


def _command_events(e: LogEvent) -> list[ChangeEvent]:
    p = list(e.params) + [0.0] * 7
    t, code = float(e.time_s), int(e.code)
    if e.kind == "command" and code == MAV_CMD_PREFLIGHT_CALIBRATION:
        out = []
        if int(round(p[1])) == 1:
            out.append(ChangeEvent(t, "compass", start=True, why="compass calibration started"))
        if int(round(p[4])) == 4:
            out.append(ChangeEvent(t, "accel", why="simple accelerometer calibration"))
        return out
    if code == MAV_CMD["MAV_CMD_PREFLIGHT_SET_SENSOR_OFFSETS"] and e.kind == "command":
        scope = {1: "accel", 2: "compass"}.get(int(round(p[0])))
        return [] if scope is None else [ChangeEvent(t, scope, why="MAV_CMD_PREFLIGHT_SET_SENSOR_OFFSETS")]
    if code == MAV_CMD["MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN"] and e.kind == "command" and int(round(p[0])) in (1, 3):
        return [ChangeEvent(t, "all", why="reboot command")]
    if code == MAV_CMD["MAV_CMD_DO_START_MAG_CAL"]:
        return [ChangeEvent(t, "compass", k, start=True, why="compass calibration started")
                for k in _mask_instances(p[0] if e.kind == "command" else 0)]
    if code in (MAV_CMD["MAV_CMD_DO_ACCEPT_MAG_CAL"], MAV_CMD["MAV_CMD_FIXED_MAG_CAL_YAW"]):
        mask = p[0] if e.kind == "command" and code == MAV_CMD["MAV_CMD_DO_ACCEPT_MAG_CAL"] else 0
        return [ChangeEvent(t, "compass", k, why="compass calibration accepted") for k in _mask_instances(mask)]
    return []


def change_events(events: Iterable[LogEvent]) -> list[ChangeEvent]:
    """The events of a log that could have changed calibration parameters (the accel
    calibration itself excepted: see :func:`accel_cal_events`)."""
    out: list[ChangeEvent] = []
    for e in events:
        if e.kind == "reboot":
            out.append(ChangeEvent(float(e.time_s), "all", why="vehicle reboot"))
        elif e.kind == "param_set" and e.text:
            out.append(ChangeEvent(float(e.time_s), "all", name=e.text, why=f"PARAM_SET {e.text}"))
        elif e.kind == "statustext":
            m = _MAG_REPORT.search(e.text)
            if m:
                out.append(ChangeEvent(float(e.time_s), "compass", int(m.group(1)),
                                       why=f"compass calibration report \"{e.text.strip()}\""))
        elif e.kind in ("command", "command_ack"):
            out += _command_events(e)
    return sorted(out, key=lambda c: c.time_s)


def accel_cal_events(periods: Sequence[tuple[float, float]]) -> list[ChangeEvent]:
    """End of each onboard accelerometer calibration: where INS_ACC* may change."""
    return [ChangeEvent(float(b), "accel", why="onboard accelerometer calibration")
            for _, b in periods if np.isfinite(b)]


def scope_of(name: str) -> tuple[str, int]:
    """(scope, instance) of a calibration parameter name; ("all", -1) for board-wide names."""
    for k in range(fw.MAX_COMPASSES):
        n: Mapping[str, Any] = fw.compass_param_names(k)
        if name in list(n["ofs"]) + list(n["dia"]) + list(n["odi"]) + list(n["mot"]) + [
                n["scale"], n["orient"], n["external"]]:
            return "compass", k
    for i in range(fw.MAX_IMUS):
        a: Mapping[str, Any] = fw.accel_param_names(i)
        if name in list(a["ofs"]) + list(a["scale"]):
            return "accel", i
    return "all", _ALL


def _concerns(ev: ChangeEvent, name: str, scope: tuple[str, int]) -> bool:
    if ev.name:
        return ev.name == name
    if ev.scope == "all":
        return True
    if scope[0] == "all":   # board-wide names change only by a reboot or a PARAM_SET
        return False
    return ev.scope == scope[0] and (ev.instance == _ALL or ev.instance == scope[1])


@dataclass(frozen=True, eq=False)
class KnownValues:
    """Value ``value[k]`` of one parameter is known in force for ``start_s[k] <= t < end_s[k]``;
    ``why[k]`` / ``why_end[k]`` name the events that bound the span (``""`` if none)."""

    name: str
    start_s: np.ndarray
    end_s: np.ndarray
    value: np.ndarray
    why: tuple[str, ...]
    why_end: tuple[str, ...] = ()

    def known(self, time_s: np.ndarray) -> np.ndarray:
        """(n,) bool: a value is known at each of ``time_s``."""
        t = np.asarray(time_s, dtype=float)
        k = np.clip(np.searchsorted(self.start_s, t, side="right") - 1, 0, len(self.start_s) - 1)
        return (t >= self.start_s[k]) & (t < self.end_s[k])

    def explain(self, time_s: float, params: ParamTimeline) -> str:
        """Why the value is not known at ``time_s``, in words (without the name)."""
        ts = params.changes[self.name][0]
        if time_s < self.start_s[0]:
            return (f"first seen at {ts[0]:.1f} s, after a {self.why[0]} at {self.start_s[0]:.1f} s "
                    f"that could have changed it")
        k = int(np.clip(np.searchsorted(self.start_s, time_s, side="right") - 1, 0, len(ts) - 2))
        return (f"changed somewhere between {self.end_s[k]:.1f} s ({self.why_end[k] or 'its sighting'}) and "
                f"{self.start_s[k + 1]:.1f} s ({self.why[k + 1] or 'its sighting'})")

    def at(self, time_s: np.ndarray) -> np.ndarray:
        """Values at ``time_s``; NaN where not known."""
        t = np.asarray(time_s, dtype=float)
        k = np.clip(np.searchsorted(self.start_s, t, side="right") - 1, 0, len(self.start_s) - 1)
        ok = (t >= self.start_s[k]) & (t < self.end_s[k])
        return np.where(ok, self.value[k], np.nan)

    @property
    def edges(self) -> np.ndarray:
        e = np.concatenate([self.start_s, self.end_s])
        return np.unique(e[np.isfinite(e)])


def known_values(params: ParamTimeline, name: str, events: Sequence[ChangeEvent]) -> KnownValues | None:
    """Spans over which each logged value of ``name`` is known (None if never seen)."""
    if name not in params:
        return None
    ts, vs = params.changes[name]
    scope = scope_of(name)
    evs = [e for e in events if _concerns(e, name, scope)]
    et = np.array([e.time_s for e in evs], dtype=float)
    n = len(ts)
    start, end = np.empty(n), np.full(n, np.inf)
    why: list[str] = [""] * n
    why_end: list[str] = [""] * n
    before = np.flatnonzero(et <= ts[0])
    if len(before):
        last = before[-1]
        start[0] = ts[0] if evs[last].start else et[last]
        why[0] = evs[last].why
    else:
        start[0] = -np.inf
    for k in range(1, n):
        gap = np.flatnonzero((et > ts[k - 1]) & (et < ts[k]))
        ends = [j for j in gap if not evs[j].start]
        # the old value holds up to the first event that could have changed it (a started
        # calibration only when nothing later reports its result); the new one from the
        # last such event on, or from its sighting when that event only started something
        end[k - 1] = et[ends[0]] if ends else (et[gap[0]] if len(gap) else ts[k])
        if len(gap):
            why_end[k - 1] = evs[ends[0] if ends else gap[0]].why
        start[k] = ts[k] if (not len(gap) or evs[gap[-1]].start) else et[gap[-1]]
        if len(gap):
            why[k] = evs[gap[-1]].why
        end[k - 1] = min(end[k - 1], start[k])
    return KnownValues(name, start, end, np.asarray(vs, dtype=float), tuple(why), tuple(why_end))


def known_table(params: ParamTimeline, names: Sequence[str], events: Sequence[ChangeEvent]
                ) -> dict[str, KnownValues]:
    """:func:`known_values` of every name of ``names`` the log has."""
    out: dict[str, KnownValues] = {}
    for n in names:
        kv = known_values(params, n, events)
        if kv is not None:
            out[n] = kv
    return out
