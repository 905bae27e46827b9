"""Read every IMU source an ArduPilot user has into an :class:`~mavcal.sources.types.ImuLog`.

Entry points
------------
:func:`read_log` reads a file: MAVLink telemetry log (``.tlog``), DataFlash log (binary
``.bin``/``.BIN``, binary or text ``.log``), or a CSV of accelerometer readings.
:func:`open_source` also takes a pymavlink device string (``udp:``, ``udpin:``, ``udpout:``,
``tcp:``, serial port) and captures from the live vehicle (see :mod:`mavcal.sources.live`).

Files are decoded with the vectorised decoders of :mod:`mavcal.sources.fast_tlog` and
:mod:`mavcal.sources.fast_dataflash`; ``fast=False`` uses pymavlink instead (reference,
and the only path for text DataFlash logs). Both paths produce the same intermediate
columns and go through the same assembly code, so their results are identical.

Units and conventions (what goes into :class:`SensorSeries`)
------------------------------------------------------------
* RAW_IMU / SCALED_IMU / SCALED_IMU2 / SCALED_IMU3: accel milli-g x 9.80665/1000 -> m/s^2,
  gyro mrad/s / 1000 -> rad/s, mag mGauss. Instance 0/0/1/2. RAW_IMU is preferred over
  SCALED_IMU for instance 0 (ArduPilot sends the same data in both). Samples whose accel
  and gyro are all exactly zero are dropped from accel/gyro (no IMU for that instance, e.g.
  SCALED_IMU2 on a single-IMU board); samples whose mag is all zero from mag (no compass).
* HIGHRES_IMU: float m/s^2, rad/s; mag is documented as gauss but ArduPilot before PR
  #32286 sent mGauss x 1000. Decided per log by the median field magnitude (> 100 "gauss"
  means the buggy unit) and converted to mGauss; the choice is stated in the warnings.
  Used for an instance only when no RAW_IMU/SCALED_IMU* carries it.
* DataFlash IMU/ACC/GYR (``I`` field) and old IMU2/IMU3/ACC1.. names; MAG (``I``) and old
  MAG2/MAG3; MAG extras ``ofs_mgauss`` (OfsX..), ``motor_ofs_mgauss`` (MOX..), ``health``.
  Time from TimeUS (or TimeMS in very old logs). IMU preferred over ACC/GYR.

Time base of tlogs
------------------
``time_s`` is the vehicle's boot time from the message (time_usec / time_boot_ms);
``log_time_s`` is the tlog receive timestamp (unix s). A vehicle reboot shows up as the boot
time falling back by more than 2 s; each boot segment after the first is shifted so that
it continues from the end of the previous one by the elapsed log (wall) time: ``time_s``
stays monotonic, equals the boot time in the first segment, and the shift is reported in
the warnings. Messages without a boot time (PARAM_VALUE, STATUSTEXT, COMMAND_*) are mapped
from their receive time onto this time base with the median (receive - boot) delay of the
IMU messages of their segment.
"""
from __future__ import annotations

import csv
import io
import logging
import re
from collections import Counter
from pathlib import Path
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from mavcal.core.constants import GRAVITY_MPS2
from mavcal.errors import MavcalError, SourceError
from mavcal.sources.types import ImuLog, LogEvent, ParamTimeline, SensorSeries

log = logging.getLogger(__name__)

G0 = GRAVITY_MPS2
MG_TO_MS2 = G0 / 1000.0
ProgressFn = Callable[[int, int], None]

#: MAVLink commands kept as LogEvents (calibration related)
CALIBRATION_COMMANDS = {
    241: "MAV_CMD_PREFLIGHT_CALIBRATION",
    242: "MAV_CMD_PREFLIGHT_SET_SENSOR_OFFSETS",
    246: "MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN",
    42006: "MAV_CMD_FIXED_MAG_CAL_YAW",
    42424: "MAV_CMD_DO_START_MAG_CAL",
    42425: "MAV_CMD_DO_ACCEPT_MAG_CAL",
    42426: "MAV_CMD_DO_CANCEL_MAG_CAL",
    42429: "MAV_CMD_ACCELCAL_VEHICLE_POS",
}
MAV_CMD_ACCELCAL_VEHICLE_POS = 42429

IMU_MESSAGES = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU")
TLOG_MESSAGES = IMU_MESSAGES + ("PARAM_VALUE", "STATUSTEXT", "COMMAND_LONG", "COMMAND_INT", "COMMAND_ACK",
                                "GPS_RAW_INT", "GLOBAL_POSITION_INT", "HOME_POSITION", "HEARTBEAT")
_SCALED_INSTANCE = {"RAW_IMU": 0, "SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}
DF_IMU_NAMES = ("IMU", "IMU2", "IMU3", "ACC", "ACC1", "ACC2", "ACC3", "GYR", "GYR1", "GYR2", "GYR3")
DF_MAG_NAMES = ("MAG", "MAG2", "MAG3")
DATAFLASH_MESSAGES = DF_IMU_NAMES + DF_MAG_NAMES + ("PARM", "MSG", "GPS", "ORGN", "POS")
PARAM_COMPONENTS = (1, 190)
_FIRMWARE_RE = re.compile(r"^((?:Ardu|APM:)\w*|Blimp|AP_Periph)\S*\s+V?\d+\.\d+\S*")
REBOOT_BACKSTEP_S = 2.0
HIGHRES_BUG_THRESHOLD = 100.0  # median |mag| in "gauss" above which the mGauss*1000 bug is assumed

Columns = Dict[str, Dict[str, np.ndarray]]


# --------------------------------------------------------------------------- helpers
def _text(v) -> str:
    if isinstance(v, (bytes, bytearray, np.bytes_)):
        return bytes(v).split(b"\0", 1)[0].decode("utf-8", errors="replace")
    return str(v).split("\0", 1)[0]


def _vec(c: Mapping[str, np.ndarray], names: Sequence[str]) -> np.ndarray:
    return np.column_stack([np.asarray(c[n], dtype=float) for n in names])


def _n(c: Optional[Mapping[str, np.ndarray]]) -> int:
    if not c:
        return 0
    for k, v in c.items():
        return len(v)
    return 0


def _any_nonzero(c: Mapping[str, np.ndarray], names: Sequence[str]) -> np.ndarray:
    """Per row: is any of the columns ``names`` non-zero."""
    out = np.asarray(c[names[0]]) != 0
    for n in names[1:]:
        out |= np.asarray(c[n]) != 0
    return out


def _take(c: Mapping[str, np.ndarray], mask) -> Dict[str, np.ndarray]:
    return {k: np.asarray(v)[mask] for k, v in c.items()}


def _build_timeline(names: Sequence[str], times: np.ndarray, values: np.ndarray) -> ParamTimeline:
    """ParamTimeline from parallel arrays; keeps only value changes, sorted by time."""
    if len(names) == 0:
        return ParamTimeline()
    names_arr = np.asarray(names, dtype=object)
    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    out: Dict[str, Tuple[np.ndarray, np.ndarray]] = {}
    order = np.argsort(times, kind="stable")
    groups: Dict[str, List[int]] = {}
    for i in order.tolist():
        groups.setdefault(names_arr[i], []).append(i)
    for name, idx in groups.items():
        if not name:
            continue
        t = times[idx]
        v = values[idx]
        keep = np.ones(len(v), dtype=bool)
        keep[1:] = ~((v[1:] == v[:-1]) | (np.isnan(v[1:]) & np.isnan(v[:-1])))
        out[name] = (t[keep], v[keep])
    return ParamTimeline(out)


def _dedupe_sorted(time_s: np.ndarray, *arrays) -> Tuple[np.ndarray, int]:
    """Index that sorts by time (stable) and drops repeated timestamps (duplicated packets)."""
    order = np.argsort(time_s, kind="stable")
    t = time_s[order]
    keep = np.ones(len(t), dtype=bool)
    keep[1:] = t[1:] != t[:-1]
    return order[keep], int((~keep).sum())


# --------------------------------------------------------------------------- tlog assembly
def _boot_time(name: str, c: Mapping[str, np.ndarray]) -> np.ndarray:
    if "time_boot_ms" in c:
        return np.asarray(c["time_boot_ms"], dtype=float) * 1e-3
    return np.asarray(c["time_usec"], dtype=float) * 1e-6


def _next_reboot(boot: np.ndarray, i0: int) -> Optional[int]:
    """First ``i > i0`` with ``boot[i] < max(boot[i0:i]) - REBOOT_BACKSTEP_S``, else None.

    Scans windows of doubling length, so that finding k reboots costs about the length of
    the log rather than k times it.
    """
    n = len(boot)
    i = i0 + 1
    prior = boot[i0]
    w = 4096
    while i < n:
        seg = boot[i:min(n, i + w)]
        runmax = np.empty_like(seg)
        runmax[0] = prior
        np.maximum(np.maximum.accumulate(seg[:-1]), prior, out=runmax[1:])
        drop = np.flatnonzero(seg < runmax - REBOOT_BACKSTEP_S)
        if len(drop):
            return i + int(drop[0])
        prior = max(prior, seg.max())
        i += len(seg)
        w *= 2
    return None


class _TimeBase:
    """Maps boot times and log times of a tlog onto one monotonic time base (see module doc)."""

    def __init__(self, index: np.ndarray, boot: np.ndarray, logt: np.ndarray) -> None:
        order = np.argsort(index, kind="stable")
        index, boot, logt = index[order], boot[order], logt[order]
        starts = [0]
        i0: Optional[int] = 0
        while True:
            i0 = _next_reboot(boot, i0)
            if i0 is None:
                break
            starts.append(i0)
        bounds = starts + [len(boot)]
        self.seg_index = np.array([index[s] for s in starts], dtype=np.int64)
        self.delay = np.zeros(len(starts))
        self.offset = np.zeros(len(starts))
        self.reboot_s = np.zeros(len(starts))  # just after the last IMU message of the boot before
        prev_end_time = None
        prev_end_log = None
        for k in range(len(starts)):
            a, b = bounds[k], bounds[k + 1]
            self.delay[k] = float(np.median(logt[a:b] - boot[a:b]))
            if k > 0:
                self.offset[k] = prev_end_time + (logt[a] - prev_end_log) - boot[a]
                self.reboot_s[k] = float(np.nextafter(prev_end_time, np.inf))
            seg_t = boot[a:b] + self.offset[k]
            prev_end_time = float(seg_t.max())
            prev_end_log = float(logt[a:b].max())
        self.reboots = len(starts) - 1

    def segment(self, index: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.seg_index, index, side="right") - 1, 0, len(self.seg_index) - 1)

    def from_boot(self, index: np.ndarray, boot: np.ndarray) -> np.ndarray:
        return boot + self.offset[self.segment(index)]

    def from_log(self, index: np.ndarray, logt: np.ndarray) -> np.ndarray:
        k = self.segment(index)
        return np.asarray(logt, dtype=float) - self.delay[k] + self.offset[k]


def assemble_tlog(cols: Columns, source: str, warnings: Sequence[str] = ()) -> ImuLog:
    """Build an ImuLog from tlog message columns (fast decoder or pymavlink).

    ``cols[name]`` holds the message fields plus ``_log_time_s``, ``_index`` (frame order),
    ``_sysid``, ``_compid``.
    """
    warns = list(warnings)
    present = {n: cols[n] for n in IMU_MESSAGES if _n(cols.get(n))}
    if not present:
        raise SourceError(f"no IMU messages (RAW_IMU, SCALED_IMU*, HIGHRES_IMU) in {source}")
    sys_counts = Counter()
    for c in present.values():
        ids, cnt = np.unique(np.asarray(c["_sysid"]), return_counts=True)
        for i, n in zip(ids.tolist(), cnt.tolist()):
            sys_counts[i] += n
    sysid = sys_counts.most_common(1)[0][0]
    other = sum(n for s, n in sys_counts.items() if s != sysid)
    if other:
        warns.append(f"ignored {other} IMU messages from other systems than sysid {sysid}")
    imu = {}
    for n, c in present.items():
        m = np.asarray(c["_sysid"]) == sysid
        if m.any():
            imu[n] = _take(c, m)
    # time base from all IMU messages of the vehicle
    tb = _TimeBase(np.concatenate([imu[n]["_index"] for n in imu]).astype(np.int64),
                   np.concatenate([_boot_time(n, imu[n]) for n in imu]),
                   np.concatenate([np.asarray(imu[n]["_log_time_s"], float) for n in imu]))
    if tb.reboots:
        warns.append(f"vehicle rebooted {tb.reboots} time(s) during the log; time_s of later boots is "
                     f"shifted by {', '.join(f'{o:+.3f}' for o in tb.offset[1:])} s to continue the log time")

    series: List[SensorSeries] = []
    taken = set()

    def add(sensor, inst, msg, t, v, lt, extra=None):
        if len(t) == 0 or (sensor, inst) in taken:
            return
        order, ndup = _dedupe_sorted(t)
        if ndup:
            warns.append(f"dropped {ndup} duplicated {msg} samples (same timestamp)")
        series.append(SensorSeries(sensor, inst, msg, t[order], v[order], lt[order],
                                   {k: a[order] for k, a in (extra or {}).items()}))
        taken.add((sensor, inst))

    for name in ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        c = imu.get(name)
        if c is None:
            continue
        if name == "SCALED_IMU" and "RAW_IMU" in imu:
            warns.append("SCALED_IMU not used: RAW_IMU carries the same instance 0")
            continue
        inst = _SCALED_INSTANCE[name]
        t = tb.from_boot(c["_index"], _boot_time(name, c))
        lt = np.asarray(c["_log_time_s"], float)
        acc = _vec(c, ("xacc", "yacc", "zacc"))
        gyr = _vec(c, ("xgyro", "ygyro", "zgyro"))
        mag = _vec(c, ("xmag", "ymag", "zmag"))
        # zero tests on the integer fields (same result as on the float copies, cheaper)
        has_imu = _any_nonzero(c, ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro"))
        has_mag = _any_nonzero(c, ("xmag", "ymag", "zmag"))
        nz = int((~has_imu).sum())
        if nz and has_imu.any():
            warns.append(f"dropped {nz} {name} samples with all-zero accel and gyro")
        elif nz:
            warns.append(f"{name}: accel and gyro are all zero (no IMU {inst + 1}); used its mag only")
        add("accel", inst, name, t[has_imu], acc[has_imu] * MG_TO_MS2, lt[has_imu])
        add("gyro", inst, name, t[has_imu], gyr[has_imu] / 1000.0, lt[has_imu])
        add("mag", inst, name, t[has_mag], mag[has_mag], lt[has_mag])

    c = imu.get("HIGHRES_IMU")
    if c is not None:
        t = tb.from_boot(c["_index"], _boot_time("HIGHRES_IMU", c))
        lt = np.asarray(c["_log_time_s"], float)
        inst_arr = np.asarray(c.get("id", np.zeros(len(t))), dtype=int)
        mag = _vec(c, ("xmag", "ymag", "zmag"))
        norm = np.linalg.norm(mag, axis=1)
        med = float(np.median(norm[norm > 0])) if (norm > 0).any() else 0.0
        if med > HIGHRES_BUG_THRESHOLD:
            mag_mg = mag / 1000.0
            warns.append(f"HIGHRES_IMU mag is in mGauss*1000 (ArduPilot bug before PR #32286; median |mag| "
                         f"{med:.0f}); converted to mGauss")
        else:
            mag_mg = mag * 1000.0
            if med > 0:
                warns.append(f"HIGHRES_IMU mag is in gauss (median |mag| {med:.3f}); converted to mGauss")
        for inst in np.unique(inst_arr).tolist():
            m = inst_arr == inst
            for sensor, v in (("accel", _vec(c, ("xacc", "yacc", "zacc"))),
                              ("gyro", _vec(c, ("xgyro", "ygyro", "zgyro"))), ("mag", mag_mg)):
                if (sensor, inst) in taken:
                    continue
                mm = m & ~(v == 0).all(axis=1) & np.isfinite(v).all(axis=1)
                add(sensor, inst, "HIGHRES_IMU", t[mm], v[mm], lt[mm])
    if not series:
        raise SourceError(f"no usable IMU samples in {source} (all IMU messages are empty)")
    series.sort(key=lambda s: ("accel", "gyro", "mag").index(s.sensor) * 100 + s.instance)

    # parameters
    params = ParamTimeline()
    pv = cols.get("PARAM_VALUE")
    if _n(pv):
        m = (np.asarray(pv["_sysid"]) == sysid) & np.isin(np.asarray(pv["_compid"]), PARAM_COMPONENTS)
        if (~m).sum():
            warns.append(f"ignored {int((~m).sum())} PARAM_VALUE from other systems/components")
        pv = _take(pv, m)
        if _n(pv):
            names = [_text(x) for x in pv["param_id"]]
            times = tb.from_log(np.asarray(pv["_index"], np.int64), pv["_log_time_s"])
            params = _build_timeline(names, times, np.asarray(pv["param_value"], dtype=np.float32).astype(float))

    # events
    events: List[LogEvent] = []
    st = cols.get("STATUSTEXT")
    firmware = None
    if _n(st):
        m = np.asarray(st["_sysid"]) == sysid
        st = _take(st, m)
        times = tb.from_log(np.asarray(st["_index"], np.int64), st["_log_time_s"])
        for t, text, sev in zip(times.tolist(), st["text"], np.asarray(st["severity"]).tolist()):
            txt = _text(text)
            events.append(LogEvent(float(t), "statustext", txt, int(sev)))
            if firmware is None and _FIRMWARE_RE.match(txt):
                firmware = txt
    for name in ("COMMAND_LONG", "COMMAND_INT"):
        cm = cols.get(name)
        if not _n(cm):
            continue
        cmd = np.asarray(cm["command"]).astype(int)
        m = np.isin(cmd, list(CALIBRATION_COMMANDS))
        cm = _take(cm, m)
        times = tb.from_log(np.asarray(cm["_index"], np.int64), cm["_log_time_s"])
        pnames = (["param1", "param2", "param3", "param4", "param5", "param6", "param7"] if name == "COMMAND_LONG"
                  else ["param1", "param2", "param3", "param4", "x", "y", "z"])
        pv_arr = _vec(cm, pnames) if _n(cm) else np.zeros((0, 7))
        for t, code, p in zip(times.tolist(), np.asarray(cm["command"]).astype(int).tolist(), pv_arr.tolist()):
            kind = "accelcal_pos" if code == MAV_CMD_ACCELCAL_VEHICLE_POS else "command"
            events.append(LogEvent(float(t), kind, CALIBRATION_COMMANDS[code], code, tuple(float(x) for x in p)))
    ack = cols.get("COMMAND_ACK")
    if _n(ack):
        cmd = np.asarray(ack["command"]).astype(int)
        ack = _take(ack, np.isin(cmd, list(CALIBRATION_COMMANDS)))
        times = tb.from_log(np.asarray(ack["_index"], np.int64), ack["_log_time_s"])
        for t, code, res in zip(times.tolist(), np.asarray(ack["command"]).astype(int).tolist(),
                                np.asarray(ack["result"]).astype(float).tolist()):
            events.append(LogEvent(float(t), "command_ack", CALIBRATION_COMMANDS[code], code, (res,)))
    events += [LogEvent(float(t), "reboot", "vehicle reboot") for t in tb.reboot_s[1:]]
    events.sort(key=lambda e: e.time_s)

    position = _tlog_position(cols, sysid)
    vehicle: Dict[str, object] = {"sysid": int(sysid)}
    hb = cols.get("HEARTBEAT")
    if _n(hb):
        m = (np.asarray(hb["_sysid"]) == sysid) & (np.asarray(hb["autopilot"]) != 8)
        if m.any():
            ci = Counter(zip(np.asarray(hb["autopilot"])[m].tolist(), np.asarray(hb["type"])[m].tolist()))
            (ap, vt), _ = ci.most_common(1)[0]
            vehicle["autopilot"] = int(ap)
            vehicle["vehicle_type"] = int(vt)
    if firmware:
        vehicle["firmware"] = firmware
    return ImuLog(source=source, kind="tlog", series=tuple(series), params=params, events=tuple(events),
                  position=position, vehicle=vehicle, warnings=tuple(warns))


def _tlog_position(cols: Columns, sysid: int) -> Optional[Tuple[float, float, float]]:
    hp = cols.get("HOME_POSITION")
    if _n(hp):
        m = (np.asarray(hp["_sysid"]) == sysid) & ((np.asarray(hp["latitude"]) != 0) | (np.asarray(hp["longitude"]) != 0))
        if m.any():
            i = np.flatnonzero(m)[-1]
            return (float(hp["latitude"][i]) * 1e-7, float(hp["longitude"][i]) * 1e-7, float(hp["altitude"][i]) * 1e-3)
    gps = cols.get("GPS_RAW_INT")
    if _n(gps):
        m = (np.asarray(gps["_sysid"]) == sysid) & (np.asarray(gps["fix_type"]) >= 3)
        if m.any():
            return (float(np.median(np.asarray(gps["lat"])[m])) * 1e-7, float(np.median(np.asarray(gps["lon"])[m])) * 1e-7,
                    float(np.median(np.asarray(gps["alt"])[m])) * 1e-3)
    gp = cols.get("GLOBAL_POSITION_INT")
    if _n(gp):
        m = (np.asarray(gp["_sysid"]) == sysid) & ((np.asarray(gp["lat"]) != 0) | (np.asarray(gp["lon"]) != 0))
        if m.any():
            return (float(np.median(np.asarray(gp["lat"])[m])) * 1e-7, float(np.median(np.asarray(gp["lon"])[m])) * 1e-7,
                    float(np.median(np.asarray(gp["alt"])[m])) * 1e-3)
    return None


# --------------------------------------------------------------------------- DataFlash assembly
def _df_time(c: Mapping[str, np.ndarray]) -> np.ndarray:
    if "TimeUS" in c:
        return np.asarray(c["TimeUS"], dtype=float) * 1e-6
    if "TimeMS" in c:
        return np.asarray(c["TimeMS"], dtype=float) * 1e-3
    raise SourceError("DataFlash message without TimeUS/TimeMS")


def _df_instances(name: str, c: Mapping[str, np.ndarray]):
    """Yield (instance, columns) of a DataFlash message (I field, or the digit in the name)."""
    if "I" in c:
        inst = np.asarray(c["I"]).astype(int)
        for i in np.unique(inst).tolist():
            yield i, _take(c, inst == i)
    else:
        digit = name[-1]
        if digit.isdigit():  # IMU2 -> 1, MAG3 -> 2, ACC1 -> 0
            yield int(digit) - 1, c
        else:
            yield 0, c


def assemble_dataflash(cols: Columns, source: str, warnings: Sequence[str] = ()) -> ImuLog:
    """Build an ImuLog from DataFlash message columns (fast decoder or DFReader)."""
    warns = list(warnings)
    series: List[SensorSeries] = []
    taken = set()

    def add(sensor, inst, msg, t, v, extra=None):
        if len(t) == 0 or (sensor, inst) in taken:
            return
        ok = np.isfinite(v).all(axis=1)
        if (~ok).any():
            warns.append(f"dropped {int((~ok).sum())} {msg} samples with non-finite values")
        order, ndup = _dedupe_sorted(t[ok])
        idx = np.flatnonzero(ok)[order]
        if ndup:
            warns.append(f"dropped {ndup} duplicated {msg}[{inst}] samples (same timestamp)")
        series.append(SensorSeries(sensor, inst, msg, t[idx], v[idx], None,
                                   {k: a[idx] for k, a in (extra or {}).items()}))
        taken.add((sensor, inst))

    for name in DF_IMU_NAMES:
        c = cols.get(name)
        if not _n(c):
            continue
        for inst, ci in _df_instances(name, c):
            t = _df_time(ci)
            if all(k in ci for k in ("AccX", "AccY", "AccZ")):
                add("accel", inst, name, t, _vec(ci, ("AccX", "AccY", "AccZ")))
            if all(k in ci for k in ("GyrX", "GyrY", "GyrZ")):
                add("gyro", inst, name, t, _vec(ci, ("GyrX", "GyrY", "GyrZ")))
    for name in DF_MAG_NAMES:
        c = cols.get(name)
        if not _n(c):
            continue
        for inst, ci in _df_instances(name, c):
            if not all(k in ci for k in ("MagX", "MagY", "MagZ")):
                continue
            extra = {}
            if all(k in ci for k in ("OfsX", "OfsY", "OfsZ")):
                extra["ofs_mgauss"] = _vec(ci, ("OfsX", "OfsY", "OfsZ"))
            if all(k in ci for k in ("MOX", "MOY", "MOZ")):
                extra["motor_ofs_mgauss"] = _vec(ci, ("MOX", "MOY", "MOZ"))
            if "Health" in ci:
                extra["health"] = np.asarray(ci["Health"], dtype=float)
            add("mag", inst, name, _df_time(ci), _vec(ci, ("MagX", "MagY", "MagZ")), extra)
    if not series:
        raise SourceError(f"no IMU data (IMU/ACC/GYR/MAG records) in {source}")
    series.sort(key=lambda s: ("accel", "gyro", "mag").index(s.sensor) * 100 + s.instance)

    # index -> time map for old records without TimeUS (PARM, MSG of firmware <= 3.x)
    timed = [(np.asarray(c["_index"]), _df_time(c)) for n, c in cols.items()
             if _n(c) and ("TimeUS" in c or "TimeMS" in c) and "_index" in c]
    if timed:
        t_idx = np.concatenate([a for a, _ in timed])
        t_val = np.concatenate([b for _, b in timed])
        o = np.argsort(t_idx, kind="stable")
        t_idx, t_val = t_idx[o], np.maximum.accumulate(t_val[o])
    else:
        t_idx, t_val = np.zeros(1, np.int64), np.zeros(1)

    def rec_time(c):
        if "TimeUS" in c or "TimeMS" in c:
            return _df_time(c)
        k = np.searchsorted(t_idx, np.asarray(c["_index"]), side="right") - 1
        return np.where(k >= 0, t_val[np.clip(k, 0, None)], t_val[0])

    params = ParamTimeline()
    pm = cols.get("PARM")
    if _n(pm):
        params = _build_timeline([_text(x) for x in pm["Name"]], rec_time(pm), np.asarray(pm["Value"], dtype=float))
    events: List[LogEvent] = []
    firmware = None
    msg = cols.get("MSG")
    if _n(msg):
        for t, text in zip(rec_time(msg).tolist(), msg["Message"]):
            txt = _text(text)
            events.append(LogEvent(float(t), "statustext", txt))
            if firmware is None and _FIRMWARE_RE.match(txt):
                firmware = txt
    events.sort(key=lambda e: e.time_s)
    vehicle: Dict[str, object] = {}
    if firmware:
        vehicle["firmware"] = firmware
    return ImuLog(source=source, kind="dataflash", series=tuple(series), params=params, events=tuple(events),
                  position=_df_position(cols), vehicle=vehicle, warnings=tuple(warns))


def _df_position(cols: Columns) -> Optional[Tuple[float, float, float]]:
    o = cols.get("ORGN")
    if _n(o) and all(k in o for k in ("Lat", "Lng", "Alt")):
        m = (np.asarray(o["Lat"]) != 0) | (np.asarray(o["Lng"]) != 0)
        if m.any():
            i = np.flatnonzero(m)[0]
            return (float(o["Lat"][i]), float(o["Lng"][i]), float(o["Alt"][i]))
    g = cols.get("GPS")
    if _n(g) and all(k in g for k in ("Lat", "Lng", "Alt", "Status")):
        m = np.asarray(g["Status"]) >= 3
        if "I" in g:
            m &= np.asarray(g["I"]) == 0
        if m.any():
            return (float(np.median(np.asarray(g["Lat"])[m])), float(np.median(np.asarray(g["Lng"])[m])),
                    float(np.median(np.asarray(g["Alt"])[m])))
    p = cols.get("POS")
    if _n(p) and all(k in p for k in ("Lat", "Lng", "Alt")):
        m = (np.asarray(p["Lat"]) != 0) | (np.asarray(p["Lng"]) != 0)
        if m.any():
            return (float(np.median(np.asarray(p["Lat"])[m])), float(np.median(np.asarray(p["Lng"])[m])),
                    float(np.median(np.asarray(p["Alt"])[m])))
    return None


# --------------------------------------------------------------------------- pymavlink reference readers
def pymavlink_tlog_columns(path: str, names: Sequence[str] = TLOG_MESSAGES) -> Tuple[Columns, List[str]]:
    """Columns of a tlog decoded by pymavlink ``recv_msg`` (reference for the fast decoder)."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(path, robust_parsing=True)
    rows: Dict[str, List[object]] = {n: [] for n in names}
    wanted = set(names)
    index = 0
    bad = 0
    try:
        while True:
            m = conn.recv_msg()
            if m is None:
                break
            index += 1
            typ = m.get_type()
            if typ == "BAD_DATA":
                bad += 1
                continue
            if typ in wanted:
                rows[typ].append((index - 1, m))
    finally:
        conn.close()
    cols: Columns = {}
    for n, lst in rows.items():
        if not lst:
            continue
        fields = lst[0][1].get_fieldnames()
        c = {f: np.array([getattr(m, f) for _, m in lst]) for f in fields}
        c["_log_time_s"] = np.array([m._timestamp for _, m in lst], dtype=float)
        c["_index"] = np.array([i for i, _ in lst], dtype=np.int64)
        c["_sysid"] = np.array([m.get_srcSystem() for _, m in lst])
        c["_compid"] = np.array([m.get_srcComponent() for _, m in lst])
        cols[n] = c
    warns = [f"skipped {bad} bad MAVLink data records (bad CRC or framing)"] if bad else []
    return cols, warns


def pymavlink_dataflash_columns(path: str, names: Sequence[str] = DATAFLASH_MESSAGES) -> Columns:
    """Columns of a DataFlash log (binary or text) decoded by pymavlink DFReader."""
    from pymavlink import DFReader

    with open(path, "rb") as fh:
        head = fh.read(2)
    reader = (DFReader.DFReader_binary(path, zero_time_base=True) if head == b"\xa3\x95"
              else DFReader.DFReader_text(path, zero_time_base=True))
    rows: Dict[str, List[object]] = {n: [] for n in names}
    index = 0
    while True:
        m = reader.recv_match(type=list(names))
        if m is None:
            break
        rows[m.get_type()].append((index, m))
        index += 1
    cols: Columns = {}
    for n, lst in rows.items():
        if not lst:
            continue
        fields = lst[0][1].get_fieldnames()
        c = {f: np.array([getattr(m, f) for _, m in lst]) for f in fields}
        c["_index"] = np.array([i for i, _ in lst], dtype=np.int64)
        cols[n] = c
    return cols


# --------------------------------------------------------------------------- CSV
def read_csv(path: str, *, rate_hz: float = 100.0) -> ImuLog:
    """Read a CSV of accelerometer (and optionally gyro/mag) readings.

    The header must name ``ax,ay,az`` (accel in g); optional ``gx,gy,gz`` (rad/s),
    ``mx,my,mz`` (mGauss) and a time column ``t``/``time``/``time_s``/``timestamp`` (s).
    Without a time column, samples are assumed evenly spaced at ``rate_hz`` (stated in the
    warnings).
    """
    if not rate_hz or not np.isfinite(rate_hz) or rate_hz <= 0:
        raise SourceError(f"invalid CSV sample rate {rate_hz!r}")
    with open(path, "r", newline="", errors="replace") as fh:
        text = fh.read()
    reader = csv.reader(io.StringIO(text))
    try:
        header = [h.strip().lower() for h in next(reader)]
    except StopIteration:
        raise SourceError(f"empty CSV file {path}") from None
    col = {h: i for i, h in enumerate(header)}
    if not all(k in col for k in ("ax", "ay", "az")):
        raise SourceError(f"CSV {path} has no ax,ay,az header (found: {','.join(header[:8])})")
    tcol = next((col[k] for k in ("time_s", "t", "time", "timestamp") if k in col), None)
    rows = []
    bad = 0
    for r in reader:
        if not r or all(not x.strip() for x in r):
            continue
        try:
            rows.append([float(x) if x.strip() else np.nan for x in r])
        except ValueError:
            bad += 1
    width = len(header)
    rows = [r for r in rows if len(r) >= width]
    if not rows:
        raise SourceError(f"CSV {path} has no numeric rows")
    a = np.array([r[:width] for r in rows], dtype=float)
    warns = []
    if bad:
        warns.append(f"skipped {bad} CSV rows that are not numbers")
    acc = a[:, [col["ax"], col["ay"], col["az"]]]
    ok = np.isfinite(acc).all(axis=1)
    if (~ok).sum():
        warns.append(f"skipped {int((~ok).sum())} CSV rows with missing accel values")
    if tcol is not None:
        t = a[:, tcol]
        ok &= np.isfinite(t)
    else:
        t = np.arange(len(a)) / float(rate_hz)
        warns.append(f"CSV has no time column: assumed {rate_hz:g} Hz")
    warns.append("CSV accel assumed in g (x 9.80665 -> m/s^2)")
    series = [SensorSeries("accel", 0, "CSV", t[ok], acc[ok] * G0)]
    if all(k in col for k in ("gx", "gy", "gz")):
        g = a[:, [col["gx"], col["gy"], col["gz"]]]
        m = ok & np.isfinite(g).all(axis=1)
        series.append(SensorSeries("gyro", 0, "CSV", t[m], g[m]))
        warns.append("CSV gyro assumed in rad/s")
    if all(k in col for k in ("mx", "my", "mz")):
        mg = a[:, [col["mx"], col["my"], col["mz"]]]
        m = np.isfinite(mg).all(axis=1) & (np.isfinite(t))
        series.append(SensorSeries("mag", 0, "CSV", t[m], mg[m]))
        warns.append("CSV mag assumed in mGauss")
    if len(series[0]) == 0:
        raise SourceError(f"CSV {path} has no usable accel rows")
    return ImuLog(source=str(path), kind="csv", series=tuple(series), warnings=tuple(warns))


# --------------------------------------------------------------------------- entry points
_LIVE_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:", "serial:", "mcast:")


def is_device(source: str) -> bool:
    """True for a pymavlink device string (network address or serial port), not a file."""
    s = str(source)
    if s.lower().startswith(_LIVE_PREFIXES):
        return True
    if s.startswith("/dev/") or re.match(r"^COM\d+$", s, re.I):
        return True
    return False


def _kind_of(path: Path) -> str:
    ext = path.suffix.lower()
    if ext == ".tlog":
        return "tlog"
    if ext == ".bin":
        return "dataflash"
    if ext == ".log":
        with open(path, "rb") as fh:
            head = fh.read(2)
        return "dataflash" if head == b"\xa3\x95" else "dataflash_text"
    if ext == ".csv":
        return "csv"
    raise SourceError(f"unknown log type '{path.suffix or path.name}' of {path}: expected .tlog, .bin, .log or .csv")


def read_log(path, *, progress: Optional[ProgressFn] = None, fast: bool = True, csv_rate_hz: float = 100.0,
             chunk_size: Optional[int] = None) -> ImuLog:
    """Read a log file into an :class:`ImuLog`.

    Parameters
    ----------
    path : str or Path
        ``.tlog``, ``.bin``/``.BIN``, ``.log`` (binary or text DataFlash) or ``.csv``.
    progress : callable(done_bytes, total_bytes) or None
        Progress callback for long reads (see :func:`mavcal.sources.progress.auto_progress`).
    fast : bool
        Use the vectorised decoders (default); ``False`` uses pymavlink (slow, reference).
    csv_rate_hz : float
        Assumed sample rate of a CSV without a time column.
    chunk_size : int, optional
        Bytes per read of the fast decoders.

    Raises
    ------
    SourceError
        Missing, empty, unreadable or corrupt file, unknown type, or no IMU data.
    """
    p = Path(path)
    src = str(path)
    if not p.exists():
        raise SourceError(f"no such file: {src}")
    if not p.is_file():
        raise SourceError(f"not a file: {src}")
    kind = _kind_of(p)
    if p.stat().st_size == 0:
        raise SourceError(f"empty file: {src}")
    kw = {"chunk_size": chunk_size} if chunk_size else {}
    try:
        if kind == "csv":
            return read_csv(src, rate_hz=csv_rate_hz)
        if kind == "tlog":
            if fast:
                from mavcal.sources.fast_tlog import decode_tlog

                cols, stats = decode_tlog(src, TLOG_MESSAGES, progress=progress, **kw)
                if stats.frames == 0:
                    raise SourceError(f"no MAVLink frames in {src}: not a tlog, or corrupt")
                for note in stats.notes():
                    log.debug("%s: %s", src, note)
                return assemble_tlog(cols, src, stats.warnings())
            cols, warns = pymavlink_tlog_columns(src)
            return assemble_tlog(cols, src, warns)
        if kind == "dataflash" and fast:
            from mavcal.sources.fast_dataflash import decode_dataflash

            cols, formats, stats = decode_dataflash(src, DATAFLASH_MESSAGES, progress=progress, **kw)
            if stats.records == 0:
                raise SourceError(f"no DataFlash records in {src}: not a DataFlash log, or corrupt")
            return assemble_dataflash(cols, src, stats.warnings())
        return assemble_dataflash(pymavlink_dataflash_columns(src), src)
    except MavcalError:
        raise
    except MemoryError:
        raise SourceError(f"out of memory reading {src}") from None
    except OSError as exc:
        raise SourceError(f"cannot read {src}: {exc.strerror or exc}") from None
    except Exception as exc:  # corrupt input that a parser did not anticipate: one line, no traceback
        log.debug("reading %s failed", src, exc_info=True)
        raise SourceError(f"cannot read {src}: corrupt or unsupported ({type(exc).__name__}: {exc})") from None


def open_source(source, *, baud: int = 115200, progress: Optional[ProgressFn] = None, fast: bool = True,
                csv_rate_hz: float = 100.0, duration_s: float = 10.0, heartbeat_timeout_s: float = 5.0,
                param_timeout_s: float = 30.0, rate_hz: float = 50.0) -> ImuLog:
    """Read a file or capture ``duration_s`` seconds from a live MAVLink device.

    ``source`` is a path (see :func:`read_log`) or a pymavlink device string
    (``udp:HOST:PORT``, ``udpin:``, ``udpout:``, ``tcp:HOST:PORT``, a serial port with
    ``baud``). For a device: connect, wait for a heartbeat (``LinkError`` after
    ``heartbeat_timeout_s``), fetch all parameters, stream IMU data at ``rate_hz`` and
    return the capture as an ImuLog of kind ``"live"``.
    """
    src = str(source)
    if is_device(src):
        from mavcal.sources.live import LiveSource

        with LiveSource(src, baud=baud, heartbeat_timeout_s=heartbeat_timeout_s) as live:
            live.fetch_params(timeout_s=param_timeout_s)
            live.start_streams(rate_hz=rate_hz)
            live.capture(duration_s)
            return live.snapshot()
    return read_log(src, progress=progress, fast=fast, csv_rate_hz=csv_rate_hz)
