"""Undo the calibration ArduPilot applied to logged IMU readings.

Logs carry *corrected* readings (RAW_IMU, SCALED_IMU2/3, DataFlash IMU/MAG). To calibrate
anew we need what the sensors measured before the correction in force at each sample
time. :func:`recover_raw` inverts the model of :mod:`mavcal.ardupilot.firmware` sample by
sample, with the parameter values in force at that sample's time (a parameter changed
mid-log counts from its change on).

Frames of the results:

* accelerometer: **board frame** (before AHRS_ORIENTATION; the frame of INS_ACCOFFS/SCAL);
* compass: **body frame after COMPASS_ORIENT (external) / AHRS_ORIENTATION (internal)**,
  the frame of COMPASS_OFS/DIA/ODI.

While ArduPilot's 6-position accelerometer calibration runs, the firmware skips the accel
offsets and scale (it still rotates by AHRS_ORIENTATION), so those samples are already
uncorrected: only the board rotation is undone there. The periods are found from the
events (MAV_CMD_PREFLIGHT_CALIBRATION with param5 = 1, the "Place vehicle ..." prompts,
ACCELCAL_VEHICLE_POS, and "Calibration successful/FAILED/cancelled") and their edges are
placed on the sample where the raw reading is continuous (the magnitude jump the
suspended correction makes, e.g. |a| 9.81 -> 10.42 m/s^2 with INS_ACCSCAL_Y = 0.942).
"""
from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot import param_history as ph
from mavcal.autopilot.mavlink import MAV_CMD_ACCELCAL_VEHICLE_POS, MAV_CMD_PREFLIGHT_CALIBRATION
from mavcal.autopilot.raw import ACCEL_FRAME, MAG_FRAME, RawImu, log_warnings_once
from mavcal.sources.types import ImuLog, LogEvent, ParamTimeline, SensorSeries

log = logging.getLogger(__name__)

__all__ = ["RawImu", "recover_raw", "find_accel_cal_periods", "ACCEL_FRAME", "MAG_FRAME", "log_warnings_once"]

ACCELCAL_POS_SUCCESS = 16777215
ACCELCAL_POS_FAILED = 16777216

_PROMPT = re.compile(r"place vehicle", re.I)
_END = re.compile(r"calibration (successful|failed|cancelled|canceled|timed out)", re.I)


# --------------------------------------------------------------------------- cal periods

def _event_windows(events: Sequence[LogEvent]) -> list[tuple[float, float, float]]:
    """(start_hint, end_hint, start_command) from events; end_hint = inf when no end seen."""
    evs = sorted(events, key=lambda e: e.time_s)
    out: list[tuple[float, float, float]] = []
    start: float | None = None
    cmd: float = np.nan
    for e in evs:
        is_cmd = (e.kind == "command" and e.code == MAV_CMD_PREFLIGHT_CALIBRATION
                  and len(e.params) >= 5 and int(round(e.params[4])) == 1)
        is_prompt = e.kind == "statustext" and bool(_PROMPT.search(e.text))
        is_pos = e.kind in ("accelcal_pos", "command") and e.code == MAV_CMD_ACCELCAL_VEHICLE_POS and bool(e.params)
        pos_val = int(round(e.params[0])) if is_pos else 0
        is_end = (e.kind == "statustext" and bool(_END.search(e.text))) or \
            (is_pos and pos_val in (ACCELCAL_POS_SUCCESS, ACCELCAL_POS_FAILED))
        if is_cmd:
            if start is None:
                cmd = e.time_s
        elif (is_prompt or (is_pos and 1 <= pos_val <= 6)) and start is None:
            start = e.time_s
        elif is_end and start is not None:
            out.append((start, e.time_s, cmd))
            start, cmd = None, np.nan
    if start is not None:
        out.append((start, np.inf, cmd))
    return out


def _best_split(u_before: np.ndarray, u_after: np.ndarray, min_step: float) -> int | None:
    """Index k where the interpretation switches (samples [:k] from ``u_before``, [k:] from
    ``u_after``) so that the raw sequence is continuous; None if no switch is visible.

    At the true switch the step between consecutive samples is the small true motion,
    while the step of the ``u_before`` sequence there contains the jump the suspended
    correction made. Elsewhere the cross step carries that jump. So the switch is where
    ``|u_after[k] - u_before[k-1]| - |u_before[k] - u_before[k-1]|`` is most negative;
    motion between consecutive samples cancels to first order. Only samples where the
    step is more than twice the change to the neighbouring samples are candidates (the
    firmware starts and ends its calibration while the vehicle is held still).
    """
    n = len(u_before)
    if n < 4:
        return None
    cross = np.linalg.norm(u_after[1:] - u_before[:-1], axis=1)      # index j -> split k = j + 1
    ref = np.linalg.norm(u_before[1:] - u_before[:-1], axis=1)
    cost = cross - ref
    # only where the step is clearly larger than the motion on either side (the firmware
    # starts and ends the calibration while the vehicle is held still)
    step = np.linalg.norm(u_after - u_before, axis=1)[1:]
    before = np.r_[np.inf, np.linalg.norm(np.diff(u_before, axis=0), axis=1)][:-1]   # k-2 -> k-1
    after = np.r_[np.linalg.norm(np.diff(u_after, axis=0), axis=1), np.inf][1:]      # k -> k+1
    ok = (np.maximum(before, after) < 0.5 * step) & (step > min_step)
    if not np.any(ok):
        return None
    cost = np.where(ok, cost, np.inf)
    k = int(np.argmin(cost))
    if cost[k] > -min_step:
        return None
    return k + 1


def find_accel_cal_periods(log_: ImuLog, margin_s: float = 4.0, min_step_mps2: float = 0.05
                           ) -> list[tuple[float, float]]:
    """Periods during which ArduPilot's 6-position accelerometer calibration ran.

    The events give an approximate start (first "Place vehicle" prompt, or the first
    ACCELCAL_VEHICLE_POS) and end ("Calibration successful/FAILED", or the SUCCESS/FAILED
    position value). Each edge is then moved, within ``margin_s`` of the event, to the
    sample of accelerometer 0 where the board-frame raw reading is continuous when the
    samples before are undone as corrected and those after as uncorrected (and the reverse
    at the end). When the correction makes no step larger than ``min_step_mps2``, the
    event time is kept.

    Returns
    -------
    list of (start_s, end_s): samples with ``start_s <= t < end_s`` were uncorrected.
    """
    wins = _event_windows(log_.events)
    if not wins:
        return []
    acc = log_.get("accel", 0)
    srt = acc is not None and _is_sorted(acc.time_s)  # once, not once per period
    min_step = float(min_step_mps2)
    out: list[tuple[float, float]] = []
    for start, end, cmd in wins:
        try:
            out.append(_refine_period(log_, acc, start, end, cmd, margin_s, min_step, srt))
        except (ValueError, np.linalg.LinAlgError):  # parameters that cannot be applied: keep the event times
            out.append((float(start), float(end if np.isfinite(end) else np.inf)))
    return out


def _refine_period(log_: ImuLog, acc: SensorSeries | None, start: float, end: float, cmd: float,
                   margin_s: float, min_step: float, srt: bool) -> tuple[float, float]:
    """One calibration period, its edges moved to where the raw readings are continuous
    (``srt``: the accelerometer's times are sorted)."""
    s_edge, e_edge = start, end
    if acc is not None and len(acc) > 2:
        t = acc.time_s
        if np.isfinite(end):
            e_edge = end
        else:
            e_edge = float(t[-1]) + 1e-6
        # start edge: corrected before, uncorrected after
        lo = start - margin_s if np.isnan(cmd) else max(start - margin_s, cmd)
        sel = _index_in(t, lo, start + margin_s, srt)
        if len(sel) > 1:
            p = log_.params
            cal_b = _accel_cal_at(p, 0, t[sel[0]])
            v = acc.values_at(sel)  # the rows near the edge only
            u_corr = fw.undo_accel(cal_b, v)
            u_raw = fw.undo_accel(cal_b, v, calibrating=True)
            if np.all(np.isfinite(u_corr)):
                k = _best_split(u_corr, u_raw, min_step)
                if k is not None:
                    s_edge = float(t[sel[k]])
        if np.isfinite(end):
            sel = _index_in(t, end - margin_s, end + margin_s, srt)
            if len(sel) > 1:
                cal_a = _accel_cal_at(log_.params, 0, t[sel[-1]])
                v = acc.values_at(sel)
                u_raw = fw.undo_accel(cal_a, v, calibrating=True)
                u_corr = fw.undo_accel(cal_a, v)
                if np.all(np.isfinite(u_corr)):
                    k = _best_split(u_raw, u_corr, min_step)
                    if k is not None:
                        e_edge = float(t[sel[k]])
    return (float(s_edge), float(e_edge))


def accel_cal_without_imu(log_: ImuLog, min_coverage: float = 0.2) -> list[tuple[float, float]]:
    """ArduPilot accelerometer calibrations (their prompts: "Place vehicle ...",
    ACCELCAL_VEHICLE_POS) during which the log holds IMU readings over less than
    ``min_coverage`` of the time, e.g. a ground station that stopped streaming RAW_IMU while
    the calibration ran. Each as (first prompt, end) in seconds; an unfinished calibration ends
    at the last event of the log."""
    evs = [e.time_s for e in log_.events]
    windows = _event_windows(log_.events)
    if not windows:
        return []
    accs = [s for s in log_.series if s.sensor == "accel" and len(s)]
    srt = [_is_sorted(s.time_s) for s in accs]
    periods: dict[int, float] = {}  # per series, once (not once per calibration): its median sample period
    out = []
    for start, end, _cmd in windows:
        stop = end if np.isfinite(end) else max(evs)
        if not stop > start:
            stop = start + 1.0
        covered = 0.0
        for k, s in enumerate(accs):
            n_in = _count_in(s.time_s, start, stop, srt[k])
            if n_in > 1:
                if k not in periods:
                    periods[k] = float(np.median(np.diff(s.time_s[np.isfinite(s.time_s)]))) if len(s) > 1 else 0.0
                covered = max(covered, min(n_in * periods[k], stop - start))
        if covered < min_coverage * (stop - start):
            out.append((float(start), float(stop)))
    return out


def _is_sorted(t: np.ndarray) -> bool:
    """Non-decreasing and free of NaN (so that a sorted search selects what a mask selects)."""
    return len(t) < 2 or bool(np.all(t[1:] >= t[:-1]))


def _range_in(t: np.ndarray, lo: float, hi: float, is_sorted: bool, *, closed_hi: bool) -> tuple[int, int] | None:
    """[i0, i1) of the samples with ``lo <= t < hi`` (``<= hi`` if ``closed_hi``) when ``t`` is
    sorted (two binary searches: no full-length mask per call), else None."""
    if not is_sorted:
        return None
    i0 = int(np.searchsorted(t, lo, side="left"))
    i1 = int(np.searchsorted(t, hi, side="right" if closed_hi else "left"))
    return i0, max(i0, i1)


def _count_in(t: np.ndarray, lo: float, hi: float, is_sorted: bool) -> int:
    """How many of ``t`` lie in [lo, hi)."""
    r = _range_in(t, lo, hi, is_sorted, closed_hi=False)
    return int(np.count_nonzero((t >= lo) & (t < hi))) if r is None else r[1] - r[0]


def _index_in(t: np.ndarray, lo: float, hi: float, is_sorted: bool) -> np.ndarray:
    """Indices of the samples with ``lo <= t <= hi``, in order."""
    r = _range_in(t, lo, hi, is_sorted, closed_hi=True)
    return np.nonzero((t >= lo) & (t <= hi))[0] if r is None else np.arange(r[0], r[1])


# --------------------------------------------------------------------------- helpers

def _accel_cal_at(params: ParamTimeline, instance: int, time_s: float,
                  missing: list[str] | None = None) -> fw.AccelCal:
    return fw.accel_cal_from_params(_values(params, _names_accel(instance), float(time_s)), instance, missing)


def _values(params: ParamTimeline, names: Sequence[str], time_s: float) -> dict[str, float]:
    """The values of ``names`` (those the log has) in force at ``time_s``."""
    return {n: float(v[0]) for n, v in params.values_at(names, time_s).items()}


def _names_accel(instance: int) -> list[str]:
    n: Mapping[str, Any] = fw.accel_param_names(instance)
    b: Mapping[str, Any] = fw.board_param_names()
    return list(n["ofs"]) + list(n["scale"]) + [b["orientation"]] + list(b["custom1"]) + list(b["custom2"])


def _names_compass(instance: int) -> list[str]:
    n: Mapping[str, Any] = fw.compass_param_names(instance)
    b: Mapping[str, Any] = fw.board_param_names()
    return (list(n["ofs"]) + list(n["dia"]) + list(n["odi"]) + [n["scale"], n["orient"], n["external"]]
            + [b["orientation"]] + list(b["custom1"]) + list(b["custom2"]))


@dataclass(frozen=True, eq=False)
class _Piece:
    """Samples [i0, i1) over which no parameter of a sensor changes (or becomes unknown)."""

    i0: int
    i1: int
    values: dict[str, float]
    unknown: tuple[str, ...]


def _pieces(params: ParamTimeline, known: Mapping[str, ph.KnownValues], cut: Sequence[str],
            extra: Sequence[str], t: np.ndarray) -> list[_Piece]:
    """Split ``t`` where any of ``cut`` changes or becomes (un)known; per piece the values in
    force of ``cut`` and ``extra`` (one vectorised lookup per name for all pieces)."""
    edges_t = [params.change_times(cut)] + [known[n].edges for n in cut if n in known]
    cuts = np.searchsorted(t, np.concatenate(edges_t), side="left")
    edges = np.unique(np.concatenate([[0, len(t)], cuts]).astype(np.int64))
    i0s, i1s = edges[:-1], edges[1:]
    ts = t[i0s]
    cols = {n: known[n].at(ts) for n in cut if n in known}
    cols.update(params.values_at([n for n in extra if n not in cols], ts))
    ok = {n: known[n].known(ts) for n in cut if n in known}
    out: list[_Piece] = []
    for j, (i0, i1) in enumerate(zip(i0s.tolist(), i1s.tolist())):
        unknown = tuple(n for n, m in ok.items() if not m[j])
        out.append(_Piece(i0, i1, {n: float(c[j]) for n, c in cols.items() if n not in unknown}, unknown))
    return out


def _record(used: dict[str, list[tuple[float, float]]], params: ParamTimeline, names: Sequence[str],
            t0: float, t1: float) -> None:
    """Add to ``used`` the values of ``names`` in force over [t0, t1] as (time, value) pairs."""
    for n in names:
        if n not in params:
            continue
        ts, vs = params.changes[n]
        pairs = used.get(n, []) + [(t0, float(params.value_at(n, t0)[0]))]
        pairs += [(float(tt), float(vv)) for tt, vv in zip(ts, vs) if t0 < tt <= t1]
        pairs.sort()
        merged: list[tuple[float, float]] = []
        for p in pairs:
            if not merged or merged[-1][1] != p[1]:
                merged.append(p)
        used[n] = merged


#: rows per call of the inverse models (their temporaries stay small: no full-length copies)
_CHUNK_ROWS = 1 << 16


def _undo_accel_into(out: np.ndarray, cal: fw.AccelCal, s: SensorSeries, i0: int,
                     calibrating: np.ndarray | None) -> None:
    """``out[i] = undo_accel(cal, v[i], calibrating=calibrating[i])`` (``None``: calibrating everywhere)
    for the readings ``v`` of ``s`` from row ``i0`` on, a chunk of rows at a time (the readings of
    a packed series are computed a chunk at a time too); each chunk computes only the
    interpretation its rows need (the same row-wise arithmetic, so the values are those of
    one call on all rows)."""
    scratch = np.empty((min(_CHUNK_ROWS, len(out)), 3))
    for i in range(0, len(out), _CHUNK_ROWS):
        j = min(i + _CHUNK_ROWS, len(out))
        v = s.values_at(slice(i0 + i, i0 + j))
        c = None if calibrating is None else calibrating[i:j]
        if c is None or c.all():
            out[i:j] = fw.undo_accel(cal, v, calibrating=True, out=scratch[:len(v)])
        elif not c.any():
            out[i:j] = fw.undo_accel(cal, v, out=scratch[:len(v)])
        else:
            out[i:j] = np.where(c[:, None], fw.undo_accel(cal, v, calibrating=True), fw.undo_accel(cal, v))


def _undo_compass_into(out: np.ndarray, cal: fw.CompassCal, s: SensorSeries, i0: int,
                       motor: np.ndarray | None) -> None:
    """``out = undo_compass(cal, v, motor)`` for the readings ``v`` of ``s`` from row ``i0`` on, a
    chunk of rows at a time (row-wise arithmetic; a packed series' readings computed a chunk at
    a time), each worked out in one reused (cached) buffer and copied once into ``out``, whose
    fresh pages are slow to touch more than once."""
    scratch = np.empty((min(_CHUNK_ROWS, len(out)), 3))
    for i in range(0, len(out), _CHUNK_ROWS):
        j = min(i + _CHUNK_ROWS, len(out))
        v = s.values_at(slice(i0 + i, i0 + j))
        out[i:j] = fw.undo_compass(cal, v, None if motor is None else motor[i:j], out=scratch[:len(v)])


def _in_periods(t: np.ndarray, periods: Sequence[tuple[float, float]]) -> np.ndarray:
    """Samples with ``a <= t < b`` for some period (a sorted ``t``: two searches per period)."""
    m = np.zeros(t.shape, dtype=bool)
    srt = bool(periods) and _is_sorted(t)
    for a, b in periods:
        r = _range_in(t, a, b, srt, closed_hi=False)
        if r is None:
            m |= (t >= a) & (t < b)
        else:
            m[r[0]:r[1]] = True
    return m


def _left_out(label: str, t: np.ndarray, mask: np.ndarray, pieces: Sequence[_Piece],
              known: Mapping[str, ph.KnownValues], params: ParamTimeline) -> str | None:
    """Warning for the samples ``mask`` left out because their parameters were unknown."""
    if not np.any(mask):
        return None
    idx = np.flatnonzero(mask)
    why: dict[str, list[str]] = {}   # reason -> parameter vectors (X/Y/Z share it)
    for p in pieces:
        if p.unknown and np.any(mask[p.i0:p.i1]):
            for n in p.unknown:
                names = why.setdefault(known[n].explain(float(t[p.i0]), params), [])
                short = n[:-2] + "_X/Y/Z" if n[-2:] in ("_X", "_Y", "_Z") else n
                if short not in names:
                    names.append(short)
    parts = [f"{', '.join(names)} {reason}" for reason, names in why.items()]
    return (f"{label}: {len(idx)} readings between {t[idx[0]]:.1f} and {t[idx[-1]]:.1f} s left out "
            f"(the calibration in force then is not known): " + "; ".join(parts[:4])
            + (f" (and {len(parts) - 4} more)" if len(parts) > 4 else ""))
# --------------------------------------------------------------------------- main

def recover_raw(log_: ImuLog, accel_cal_periods: Sequence[tuple[float, float]] | None = None,
                drop_zero_series: bool = True) -> RawImu:
    """Invert ArduPilot's correction of every accel and compass series of ``log_``.

    Each parameter set is applied to the whole span it is in force. A logged value counts
    only where it is known to be in force (:mod:`mavcal.ardupilot.param_history`): from
    the last event that could have changed it (a reboot, a calibration, a PARAM_SET)
    before it was first seen. Readings whose parameters are not known are left out (NaN
    values, ``extra["params_known"]`` 0) with a warning; outside an accel calibration.

    Parameters
    ----------
    log_ : ImuLog
        Readings as logged (corrected) and the parameter timeline (same time base).
    accel_cal_periods : sequence of (start_s, end_s), optional
        Override the detection of accelerometer-calibration periods
        (:func:`find_accel_cal_periods`).
    drop_zero_series : bool
        Drop series whose values are all exactly zero (SCALED_IMU2/3 accel of a vehicle
        without that IMU, a missing compass), with a warning.

    Returns
    -------
    RawImu
        Accel in m/s^2 (board frame), mag in mGauss (body frame after orientation).
    """
    warnings: list[str] = list()
    used: dict[str, list[tuple[float, float]]] = {}
    periods = list(find_accel_cal_periods(log_) if accel_cal_periods is None else accel_cal_periods)
    for a, b in periods:
        log.info("accelerometer calibration ran %.2f..%.2f s: offsets/scale not undone there", a, b)
    blind = accel_cal_without_imu(log_)
    for a, b in blind:
        warnings.append(f"the log holds an accelerometer calibration ({a:.1f}..{b:.1f} s: its 'Place vehicle' "
                        "prompts) but no IMU data during it (the ground station stopped streaming RAW_IMU?): "
                        "its poses cannot be used")
    events = sorted(ph.change_events(log_.events) + ph.accel_cal_events(periods), key=lambda e: e.time_s)
    accel_out: list[SensorSeries] = []
    missing: dict[str, tuple[str, ...]] = {}  # sensor -> names of its calibration in force the log lacks
    for inst in log_.instances("accel"):
        s = _usable(log_.get("accel", inst), "accel", drop_zero_series, warnings)
        if s is not None:
            accel_out.append(_recover_accel(log_.params, s, periods, events, used, warnings, missing))
    mag_out: list[SensorSeries] = []
    for inst in log_.instances("mag"):
        s = _usable(log_.get("mag", inst), "mag", drop_zero_series, warnings)
        if s is None:
            continue
        if inst >= fw.MAX_COMPASSES:
            warnings.append(f"mag {inst}: no parameter slot for compass {inst + 1}; readings treated as raw")
            missing[f"compass{inst}"] = ()
            mag_out.append(s)
            continue
        mag_out.append(_recover_mag(log_.params, s, events, used, warnings, missing))
    gyro = tuple(g for g in log_.series if g.sensor == "gyro" and len(g)
                 and not (drop_zero_series and not g.any_nonzero()))
    missing, origin = _in_force(log_, accel_out, mag_out, missing, warnings)
    log_warnings_once(log, warnings)
    return RawImu(
        source=log_.source,
        accel=tuple(accel_out),
        mag=tuple(mag_out),
        gyro=gyro,
        params_used={k: tuple(v) for k, v in used.items()},
        frames={"accel": ACCEL_FRAME, "mag": MAG_FRAME},
        warnings=tuple(warnings),
        accel_cal_periods=tuple((float(a), float(b)) for a, b in periods),
        board_rotation=_board_rotation(log_.params),
        accel_cal_without_imu=tuple(blind),
        cal_origin=origin,
        cal_missing=missing,
    )


def _in_force(log_: ImuLog, accel: Sequence[SensorSeries], mag: Sequence[SensorSeries],
              missing: dict[str, tuple[str, ...]], warnings: list[str]
              ) -> tuple[dict[str, tuple[str, ...]], dict[str, str]]:
    """(sensors whose calibration in force is not known with their missing names, where each
    sensor's came from): :attr:`RawImu.cal_missing` and :attr:`RawImu.cal_origin`."""
    origin = {f"accel{s.instance}": log_.origin_of(_names_accel(s.instance)) for s in accel}
    origin.update({f"compass{s.instance}": log_.origin_of(_names_compass(s.instance)) if s.instance < fw.MAX_COMPASSES
                   else "" for s in mag})
    if log_.kind == "csv":  # a CSV never carries parameters: its readings are raw by design, not a warning
        for w in [w for w in warnings if "readings treated as raw" in w]:
            warnings.remove(w)
            log.info("%s", w)
        return {}, {k: "raw readings (a CSV holds no calibration)" for k in origin}
    for sensor in missing:
        origin[sensor] = ""
    return missing, origin


def _usable(s: SensorSeries | None, sensor: str, drop_zero: bool, warnings: list[str]) -> SensorSeries | None:
    """The series, or None when it is empty or (``drop_zero``) all zero (with a warning)."""
    if s is None or len(s) == 0:
        return None
    if drop_zero and not s.any_nonzero():
        what = "no such IMU" if sensor == "accel" else "no such compass"
        warnings.append(f"{sensor} {s.instance} ({s.message}) is all zero ({what}); dropped")
        return None
    return s


def _with_known(s: SensorSeries, values: np.ndarray, extra: dict[str, np.ndarray], left_out: np.ndarray
                ) -> SensorSeries:
    """The recovered series; ``extra["params_known"]`` marks readings left out (NaN)."""
    if np.any(left_out):
        values[left_out] = np.nan  # ``values`` is the caller's own new array
        extra = {**extra, "params_known": (~left_out).astype(float)}
    return SensorSeries(s.sensor, s.instance, s.message, s.time_s, values, s.log_time_s, extra)


def _recover_accel(params: ParamTimeline, s: SensorSeries, periods: Sequence[tuple[float, float]],
                   events: Sequence[ph.ChangeEvent], used: dict[str, list[tuple[float, float]]],
                   warnings: list[str], not_known: dict[str, tuple[str, ...]]) -> SensorSeries:
    """Undo offsets/scale (outside accel-cal periods) and the board rotation of one IMU."""
    inst, t = s.instance, s.time_s
    an: Mapping[str, Any] = fw.accel_param_names(inst)
    bn: Mapping[str, Any] = fw.board_param_names()
    board = [bn["orientation"]] + list(bn["custom1"]) + list(bn["custom2"])
    have = [n for n in list(an["ofs"]) + list(an["scale"]) if n in params]
    names = _names_accel(inst) if have else board
    known = ph.known_table(params, names, events)
    out = np.empty((len(s), 3))
    calib = _in_periods(t, periods)
    left_out = np.zeros(len(t), dtype=bool)
    missing: list[str] = []
    pieces = _pieces(params, known, names, (), t)
    unusable: list[str] = []
    bad = np.zeros(len(t), dtype=bool)  # left out: parameters that cannot be applied
    for p in pieces:
        sl = slice(p.i0, p.i1)
        try:
            cal = fw.accel_cal_from_params(p.values, inst, missing if (have and not p.unknown) else None)
            cal.board_matrix  # noqa: B018 - raises for a rotation mavcal cannot apply
        except (ValueError, np.linalg.LinAlgError) as exc:  # a damaged or unsupported parameter value
            out[sl], left_out[sl], bad[sl] = np.nan, True, True
            unusable.append(f"{t[p.i0]:.1f} s: {exc}")
            continue
        if not have or set(p.unknown) & set(board):
            _undo_accel_into(out[sl], cal, s, p.i0, None)
            left_out[sl] = bool(p.unknown)
            continue
        if any(v == 0.0 for v in cal.scale) and not p.unknown:
            warnings.append(f"accel {inst}: scale parameter is zero (uncalibrated slot) from "
                            f"{t[p.i0]:.1f} s; those axes are NaN")
        c = calib[sl]
        # offsets/scale do not matter where the firmware skipped them (accel calibration)
        left_out[sl] = bool(p.unknown) & ~c
        _undo_accel_into(out[sl], cal, s, p.i0, c)
    if not have:
        no_board = "" if bn["orientation"] in params else " (and no AHRS_ORIENTATION: board frame = body frame)"
        warnings.append(f"accel {inst}: the log has no {an['ofs'][0][:-2]}/{an['scale'][0][:-2]} "
                        f"parameters; readings treated as raw" + no_board + "; the calibration in force is not "
                        "known, so its new values are not written")
        not_known[f"accel{inst}"] = tuple(n for n in _names_accel(inst)[:7] if n not in params)
        _record(used, params, [bn["orientation"]], float(t[0]), float(t[-1]))
    else:
        if missing:
            warnings.append(f"accel {inst}: missing {', '.join(sorted(set(missing)))}; the firmware's defaults "
                            "used to judge it, but the calibration in force is not known: not written")
            not_known[f"accel{inst}"] = tuple(sorted(set(missing)))
        _record(used, params, names, float(t[0]), float(t[-1]))
    w = _left_out(f"accel {inst}", t, left_out & ~bad, pieces, known, params)
    if w:
        warnings.append(w)
    warnings += _unusable_warning(f"accel {inst}", unusable)
    # (no calibration in the data, the usual case: zeros that need not be written)
    flags = calib.astype(float) if calib.any() else np.zeros(len(calib))
    return _with_known(s, out, {**dict(s.extra), "calibrating": flags}, left_out)


def _recover_mag(params: ParamTimeline, s: SensorSeries, events: Sequence[ph.ChangeEvent],
                 used: dict[str, list[tuple[float, float]]], warnings: list[str],
                 not_known: dict[str, tuple[str, ...]]) -> SensorSeries:
    """Undo the compass correction (offsets, soft iron, scale, motor offset) of one compass."""
    inst, t = s.instance, s.time_s
    cn: Mapping[str, Any] = fw.compass_param_names(inst)
    motor = s.extra.get("motor_ofs_mgauss")
    if motor is not None and np.asarray(motor).shape != (len(s), 3):
        motor = None
    if not [n for n in list(cn["ofs"]) + list(cn["dia"]) + [cn["scale"]] if n in params]:
        not_known[f"compass{inst}"] = tuple(n for n in _names_compass(inst)[:10] if n not in params)
        return _mag_without_params(s, cn, motor, warnings)
    names = _names_compass(inst)
    known = ph.known_table(params, names, events)
    out = np.empty((len(s), 3))
    left_out = np.zeros(len(t), dtype=bool)
    missing: list[str] = []
    pieces = _pieces(params, known, names, list(cn["mot"]), t)
    unusable: list[str] = []
    bad = np.zeros(len(t), dtype=bool)  # left out: parameters that cannot be applied
    for p in pieces:
        try:
            cal = fw.compass_cal_from_params(p.values, inst, None if p.unknown else missing)
            _undo_compass_into(out[p.i0:p.i1], cal, s, p.i0, None if motor is None else motor[p.i0:p.i1])
            left_out[p.i0:p.i1] = bool(p.unknown)
        except (ValueError, np.linalg.LinAlgError) as exc:  # e.g. a singular DIA/ODI matrix, unknown rotation
            out[p.i0:p.i1], left_out[p.i0:p.i1], bad[p.i0:p.i1] = np.nan, True, True
            unusable.append(f"{t[p.i0]:.1f} s: {exc}")
    missing = sorted(set(missing))
    if cn["scale"] in missing and not _has_compass_scale(params):  # a firmware before COMPASS_SCALE (4.0): 1
        missing.remove(cn["scale"])
        log.info("mag %d: the log has no COMPASS_SCALE parameter at all (a firmware before it): scale 1", inst)
    if missing:
        warnings.append(f"mag {inst}: missing {', '.join(missing)}; the firmware's defaults used to judge it, "
                        "but the calibration in force is not known: not written")
        not_known[f"compass{inst}"] = tuple(missing)
    _record(used, params, names, float(t[0]), float(t[-1]))
    warnings += _mag_param_warnings(params, inst, motor is None)
    w = _left_out(f"mag {inst}", t, left_out & ~bad, pieces, known, params)
    if w:
        warnings.append(w)
    warnings += _unusable_warning(f"mag {inst}", unusable)
    return _with_known(s, out, dict(s.extra), left_out)


def _has_compass_scale(params: ParamTimeline) -> bool:
    """Whether the log holds any COMPASS_SCALEn: a firmware without any (ArduPilot before 4.0) has
    no compass scale at all (1), which is not a default guessed for a missing value."""
    return any(fw.compass_param_names(k)["scale"] in params for k in range(fw.MAX_COMPASSES))


def _unusable_warning(label: str, unusable: Sequence[str]) -> list[str]:
    """Warning for readings left out because the parameters in force cannot be applied."""
    if not unusable:
        return []
    return [f"{label}: readings left out where the parameters in force cannot be undone (damaged log or "
            f"unsupported value): " + "; ".join(unusable[:3]) + (f" (and {len(unusable) - 3} more)"
                                                                 if len(unusable) > 3 else "")]


def _mag_without_params(s: SensorSeries, cn: Mapping[str, Any], motor: np.ndarray | None,
                        warnings: list[str]) -> SensorSeries:
    """A compass the log has no COMPASS parameters for: logged offsets if any, else as is."""
    ofs_logged = s.extra.get("ofs_mgauss")
    if ofs_logged is not None and np.asarray(ofs_logged).shape == (len(s), 3):
        warnings.append(f"mag {s.instance}: the log has no COMPASS parameters for this compass; "
                        f"used the logged MAG offsets (int16) and no matrix/scale to judge it; the calibration in "
                        "force is not known, so its new values are not written")
        out = s.values - np.asarray(ofs_logged)
        if motor is not None:
            out = out - motor
    else:
        warnings.append(f"mag {s.instance}: the log has no {cn['ofs'][0][:-2]}/DIA/ODI/SCALE parameters; "
                        "readings treated as raw; the calibration in force is not known, so its new values are not "
                        "written")
        out = s.values if s.packed is not None else np.array(s.values)  # (computed: a new array already)
    return SensorSeries("mag", s.instance, s.message, s.time_s, out, s.log_time_s, dict(s.extra))


def _mag_param_warnings(params: ParamTimeline, inst: int, no_motor_logged: bool) -> list[str]:
    """Motor compensation assumed zero; device id and priority id disagree."""
    cn: Mapping[str, Any] = fw.compass_param_names(inst)
    out: list[str] = []
    if no_motor_logged:
        motct = params.final(str(fw.board_param_names()["motct"]), 0) or 0
        mot = [params.final(n, 0) or 0 for n in cn["mot"]]
        if int(motct) != 0 and any(abs(x) > 0 for x in mot):
            out.append(f"mag {inst}: COMPASS_MOTCT={int(motct)} with non-zero {cn['mot'][0][:-2]} "
                       f"but no logged motor offset; motor compensation assumed zero "
                       f"(true when disarmed with zero throttle/current)")
    dev, prio = cn["dev_id"], cn["prio_id"]
    if dev in params and prio in params and params.final(dev) != params.final(prio):
        out.append(f"mag {inst}: {dev} != {prio} (compass order changed without a reboot?); "
                   f"parameters may belong to another compass")
    return out


def _board_rotation(params: ParamTimeline) -> np.ndarray | None:
    snap = params.snapshot()
    if fw.board_param_names()["orientation"] not in snap:
        return None
    try:
        return np.array(fw.accel_cal_from_params(snap, 0).board_matrix)
    except ValueError:  # custom rotation without its angles
        return None
