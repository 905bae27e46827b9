"""The series of a flight that the in-flight compass stage needs, read from a MAVLink telemetry log
(``.tlog``) as far as it carries them.

An ArduPilot tlog carries each compass's **corrected** field (``RAW_IMU`` compass 0,
``SCALED_IMU2`` / ``SCALED_IMU3`` compasses 1 and 2: offsets, soft iron, scale and the motor
compensation applied), the attitude (``ATTITUDE``), the battery current (``SYS_STATUS``, else
``BATTERY_STATUS``; -1 cA is "no sensor"), the throttle (``VFR_HUD``), the GPS (``GPS_RAW_INT``), the
arming state (``HEARTBEAT``) and the parameters the ground station read (``PARAM_VALUE``). What it
does not carry: the offsets and the motor offset the firmware applied (the stage takes them from
the parameters in force, ArduPilot's in-flight model), the EKF-GSF yaw (no rotation verdict),
the hover throttle. Times are the tlog's receive times (s from the first message): one link's
delay on every series.

Refused in one line, naming what is missing: no compass field, a compass field slower than
:data:`MIN_MAG_RATE_HZ` (the ground station's stream rate), no attitude, and a PX4 tlog (its
``SCALED_IMU`` carries the raw field without the device id that says which calibration slot is
its: the stage reads a PX4 flight from its ULog).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mavcal.errors import SourceError
from mavcal.sources.fast_tlog import decode_tlog
from mavcal.sources.flight_series import CompassSeries, FlightEvidence, FlightSeries
from mavcal.sources.flight_ulog import MIN_MAG_RATE_HZ

__all__ = ["read_flight_tlog", "MESSAGES", "MIN_MAG_RATE_HZ"]

MESSAGES = ("HEARTBEAT", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE", "SYS_STATUS", "BATTERY_STATUS",
            "VFR_HUD", "GPS_RAW_INT", "PARAM_VALUE")
_COMPASS_MESSAGES = ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")  # compass 0, 1, 2 (ArduPilot's GCS_MAVLink)
_MAV_AUTOPILOT_PX4 = 12
_MAV_MODE_FLAG_SAFETY_ARMED = 128
_GCS_TYPES = (6,)  # MAV_TYPE_GCS


def _empty() -> np.ndarray:
    return np.zeros(0)


def _rate_hz(t: np.ndarray) -> float:
    """The stream's rate: one over the median interval (a gap in the link does not lower it)."""
    d = np.diff(t)
    d = d[d > 0]
    return 1.0 / float(np.median(d)) if len(d) else 0.0


def _vehicle(cols: dict[str, dict[str, np.ndarray]]) -> int | None:
    """The system id whose compass messages are most numerous (the vehicle, not a ground station)."""
    ids: list[np.ndarray] = [cols[m]["_sysid"] for m in _COMPASS_MESSAGES if m in cols and len(cols[m]["_sysid"])]
    if not ids:
        return None
    v, n = np.unique(np.concatenate(ids), return_counts=True)
    return int(v[np.argmax(n)])


def _of(cols, name: str, sysid: int) -> dict[str, np.ndarray] | None:
    c = cols.get(name)
    if c is None or not len(c.get("_sysid", ())):
        return None
    m = np.asarray(c["_sysid"]) == sysid
    if not m.any():
        return None
    return {k: np.asarray(v)[m] for k, v in c.items()}


def read_flight_tlog(path: str | Path) -> FlightSeries:
    """Read the flight series of a tlog; :class:`SourceError` in one line naming what it lacks."""
    src = str(path)
    try:
        cols, _ = decode_tlog(src, MESSAGES)
    except (OSError, ValueError) as exc:
        raise SourceError(f"{src}: cannot read: {exc}") from None
    sysid = _vehicle(cols)
    if sysid is None:
        raise SourceError(f"{src}: no compass field in this tlog (no RAW_IMU, SCALED_IMU2 or SCALED_IMU3): the "
                          "in-flight stage needs the compasses at a few Hz")
    hb = _of(cols, "HEARTBEAT", sysid)
    if hb is not None and np.any(np.asarray(hb["autopilot"]) == _MAV_AUTOPILOT_PX4):
        raise SourceError(f"{src}: a PX4 tlog: its compass messages do not say which calibration slot is each "
                          "compass's (no device id); give the flight's ULog (.ulg)")
    t0 = min(float(np.min(c["_log_time_s"])) for c in cols.values() if len(c.get("_log_time_s", ())))
    compasses = []
    for k, name in enumerate(_COMPASS_MESSAGES):
        c = _of(cols, name, sysid)
        if c is None:
            continue
        mag = np.column_stack([np.asarray(c[a], dtype=np.float64) for a in ("xmag", "ymag", "zmag")])
        if not np.any(mag):
            continue  # the message is sent for its IMU: no compass k
        t = np.asarray(c["_log_time_s"], dtype=np.float64) - t0
        rate = _rate_hz(t)
        if rate < MIN_MAG_RATE_HZ:
            raise SourceError(f"{src}: compass{k}'s field ({name}) is logged at {rate:.1f} Hz: the in-flight fit "
                              f"needs it at {MIN_MAG_RATE_HZ:.0f} Hz at least (raise the ground station's RAW_SENS "
                              "stream rate), or give the flight's .bin")
        nan = np.full(mag.shape, np.nan)
        compasses.append(CompassSeries(k, t, mag, nan, nan.copy(), np.ones(len(t), dtype=bool)))
    if not compasses:
        raise SourceError(f"{src}: no compass field in this tlog (its IMU messages carry zeros)")
    att = _of(cols, "ATTITUDE", sysid)
    if att is None or len(att["roll"]) < 10:
        raise SourceError(f"{src}: no ATTITUDE messages (no attitude logged)")
    at = np.asarray(att["_log_time_s"], dtype=np.float64) - t0
    deg = [np.degrees(np.asarray(att[a], dtype=np.float64)) for a in ("roll", "pitch", "yaw")]
    cur_t, cur, cur_msg = _current(cols, sysid, t0)
    hud = _of(cols, "VFR_HUD", sysid)
    thr_t = np.asarray(hud["_log_time_s"], dtype=np.float64) - t0 if hud is not None else _empty()
    thr = np.asarray(hud["throttle"], dtype=np.float64) / 100.0 if hud is not None else _empty()
    alt = np.asarray(hud["alt"], dtype=np.float64) if hud is not None else _empty()
    lat = lon = None
    gps = _of(cols, "GPS_RAW_INT", sysid)
    gps_t, gps_spd = _empty(), _empty()
    if gps is not None:
        ok = np.asarray(gps["fix_type"]) >= 3
        if ok.any():
            lat = float(np.median(np.asarray(gps["lat"], float)[ok])) / 1e7
            lon = float(np.median(np.asarray(gps["lon"], float)[ok])) / 1e7
        gps_t = np.asarray(gps["_log_time_s"], dtype=np.float64) - t0
        v = np.asarray(gps["vel"], dtype=np.float64)
        gps_spd = np.where(v == 65535, np.nan, v / 100.0)
    arm_t, armed = _empty(), np.zeros(0, dtype=bool)
    if hb is not None:
        arm_t = np.asarray(hb["_log_time_s"], dtype=np.float64) - t0
        armed = (np.asarray(hb["base_mode"]).astype(int) & _MAV_MODE_FLAG_SAFETY_ARMED) != 0
    ev = FlightEvidence("", arm_t, armed, 0, thr_t, thr, np.full(len(thr_t), np.nan), alt, gps_t, gps_spd)
    return FlightSeries(src, tuple(compasses), cur_t, cur, thr_t, thr, at, deg[0], deg[1], deg[2],
                        _empty(), _empty(), _empty(), lat, lon, _params(cols, sysid), ev,
                        throttle_message="VFR_HUD", current_message=cur_msg,
                        gsf_message="which a tlog does not carry")


def _current(cols, sysid: int, t0: float) -> tuple[np.ndarray, np.ndarray, str]:
    """The battery current (A; -1 cA, "no sensor", kept as -0.01 A) of SYS_STATUS, else BATTERY_STATUS id 0."""
    for name in ("SYS_STATUS", "BATTERY_STATUS"):
        c = _of(cols, name, sysid)
        if c is None or "current_battery" not in c:
            continue
        keep = np.ones(len(c["current_battery"]), dtype=bool)
        if name == "BATTERY_STATUS" and "id" in c:
            keep = np.asarray(c["id"]) == 0
        if keep.any():
            return (np.asarray(c["_log_time_s"], dtype=np.float64)[keep] - t0,
                    np.asarray(c["current_battery"], dtype=np.float64)[keep] / 100.0, name)
    return _empty(), _empty(), "SYS_STATUS"


def _params(cols, sysid: int) -> dict[str, float]:
    """The parameters the ground station read (the first value of each name)."""
    pv = _of(cols, "PARAM_VALUE", sysid)
    out: dict[str, float] = {}
    if pv is None:
        return out
    for n, v in zip(pv["param_id"], pv["param_value"]):
        name = bytes(n).split(b"\0", 1)[0].decode("ascii", "replace")
        if name and np.isfinite(v):
            out.setdefault(name, float(v))
    return out
