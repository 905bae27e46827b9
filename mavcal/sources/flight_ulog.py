"""The series of a flight that the in-flight compass stage needs, read from a PX4 ULog (``.ulg``).

Beside :mod:`mavcal.sources.flight_series` (the DataFlash ``.bin``), the same
:class:`~mavcal.sources.flight_series.FlightSeries`, marked ``autopilot="PX4"``:

* ``sensor_mag`` (each instance a compass): the **raw** reading (gauss -> mGauss, the sensor frame,
  before PX4's calibration) and its ``device_id``; PX4's corrected field is not read (the stage
  applies the calibration in force itself, PX4's in-flight model);
* ``vehicle_attitude`` (``q``, body to NED) -> roll, pitch, yaw;
* ``battery_status`` instance 0 (and 1) ``current_a``; the throttle: the length of
  ``vehicle_thrust_setpoint``'s ``xyz`` (else ``actuator_controls_0``'s throttle, PX4 up to 1.13);
* ``yaw_estimator_status``: the EKF-GSF yaw (``yaw_composite``, rad) and its 1-sigma
  (``sqrt(yaw_variance)``), compass-independent; a sample it calls invalid gets a large sigma;
* ``vehicle_gps_position`` / ``sensor_gps``: the median 3-D fix and the ground speed;
* whether it flew: ``vehicle_status.arming_state`` (2 armed), the thrust against
  ``hover_thrust_estimate``, the altitude (``-vehicle_local_position.z``);
* the parameters at the start.

A log whose raw compass is logged too slowly for the fit (under :data:`MIN_MAG_RATE_HZ`: PX4's
default logging profile) is refused in one line that says how to log it. Only this module (and
:mod:`mavcal.sources.ulog`) imports pyulog.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mavcal.errors import SourceError
from mavcal.sources.flight_series import CompassSeries, FlightEvidence, FlightSeries
from mavcal.sources.ulog import load_topics, start_us

__all__ = ["read_flight_ulog", "MIN_MAG_RATE_HZ", "TOPICS", "ARMING_STATE_ARMED"]

#: the slowest compass rate the in-flight fit takes (Hz): its delay between the current and the
#: field is sought over +-0.5 s, which needs two samples per half second at least
MIN_MAG_RATE_HZ = 4.0
#: PX4's ``vehicle_status.arming_state`` of an armed vehicle
ARMING_STATE_ARMED = 2
TOPICS = ["sensor_mag", "vehicle_attitude", "battery_status", "vehicle_thrust_setpoint", "actuator_controls_0",
          "yaw_estimator_status", "vehicle_gps_position", "sensor_gps", "vehicle_status", "hover_thrust_estimate",
          "vehicle_local_position"]


def _empty() -> np.ndarray:
    return np.zeros(0)


def _col(d, name: str) -> np.ndarray | None:
    v = d.data.get(name) if d is not None else None
    return None if v is None else np.asarray(v, dtype=np.float64)


def _rate_hz(t: np.ndarray) -> float:
    """The stream's rate: one over the median interval (a gap in the link does not lower it)."""
    d = np.diff(t)
    d = d[d > 0]
    return 1.0 / float(np.median(d)) if len(d) else 0.0


def _euler_deg(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Roll, pitch, yaw (deg, ZYX) of Hamilton quaternions ``(w, x, y, z)`` rotating body to NED."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.degrees(roll), np.degrees(pitch), np.degrees(yaw)


def read_flight_ulog(path: str | Path) -> FlightSeries:
    """Read the flight series of a PX4 ULog; :class:`SourceError` in one line when it lacks what the fit needs."""
    src = str(path)
    ulog = load_topics(src, TOPICS)
    t0 = start_us(ulog)
    topics: dict[str, list] = {}
    for d in ulog.data_list:
        topics.setdefault(d.name, []).append(d)
    for v in topics.values():
        v.sort(key=lambda d: d.multi_id)

    def first(name: str):
        return topics[name][0] if topics.get(name) else None

    def times(d) -> np.ndarray:
        t = np.asarray(d.data.get("timestamp_sample", d.data["timestamp"])).astype(np.int64)
        return (t - np.int64(t0)).astype(np.float64) / 1e6

    compasses = []
    for d in topics.get("sensor_mag", []):
        if not {"x", "y", "z", "timestamp"} <= set(d.data) or len(d.data["timestamp"]) < 2:
            continue
        t = times(d)
        order = np.argsort(t, kind="stable")
        raw = np.column_stack([_col(d, a) for a in "xyz"])[order] * 1000.0
        dev = _col(d, "device_id")
        ids = dev[dev > 0] if dev is not None else _empty()
        nan = np.full(raw.shape, np.nan)
        compasses.append(CompassSeries(int(d.multi_id), t[order], nan, nan.copy(), nan.copy(),
                                       np.isfinite(raw).all(axis=1), raw, int(ids[-1]) if len(ids) else None))
    if not compasses:
        raise SourceError(f"{src}: no sensor_mag topic (the raw compass readings): the in-flight stage needs them; "
                          "log them with SDLOG_PROFILE bit 2 (high rate)")
    slow = min(compasses, key=lambda c: _rate_hz(c.time_s))
    if _rate_hz(slow.time_s) < MIN_MAG_RATE_HZ:
        raise SourceError(f"{src}: sensor_mag {slow.instance} is logged at {_rate_hz(slow.time_s):.1f} Hz: the "
                          f"in-flight fit needs the raw compass at {MIN_MAG_RATE_HZ:.0f} Hz at least; log it with "
                          "SDLOG_PROFILE bit 2 (high rate)")
    att = first("vehicle_attitude")
    if att is None or "q[0]" not in att.data or len(att.data["timestamp"]) < 10:
        raise SourceError(f"{src}: no vehicle_attitude (no attitude logged)")
    q = np.column_stack([_col(att, f"q[{k}]") for k in range(4)])
    roll, pitch, yaw = _euler_deg(q)
    att_t = times(att)
    batteries: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for d in topics.get("battery_status", []):
        cur = _col(d, "current_a")
        if cur is not None and len(cur):
            batteries.setdefault(int(d.multi_id), (times(d), cur))
    cur_t, cur = batteries.get(0, (_empty(), _empty()))
    thr_t, thr, thr_msg = _throttle(first("vehicle_thrust_setpoint"), first("actuator_controls_0"), times)
    gt, gy, gs = _gsf(first("yaw_estimator_status"), times)
    lat, lon, gps_t, gps_spd = _gps(first("vehicle_gps_position") or first("sensor_gps"), times)
    params = {str(k): float(v) for k, v in ulog.initial_parameters.items()
              if isinstance(v, (int, float, np.integer, np.floating))}
    ev = _evidence(first("vehicle_status"), first("hover_thrust_estimate"), first("vehicle_local_position"),
                   thr_t, thr, gps_t, gps_spd, times)
    return FlightSeries(src, tuple(compasses), cur_t, cur, thr_t, thr, att_t, roll, pitch, yaw, gt, gy, gs, lat, lon,
                        params, ev, autopilot="PX4", battery_currents=batteries, throttle_message=thr_msg,
                        current_message="battery_status", gsf_message="yaw_estimator_status")


def _throttle(thrust, controls, times) -> tuple[np.ndarray, np.ndarray, str]:
    if thrust is not None and "xyz[0]" in thrust.data:
        xyz = np.column_stack([_col(thrust, f"xyz[{k}]") for k in range(3)])
        return times(thrust), np.linalg.norm(xyz, axis=1), "vehicle_thrust_setpoint"
    if controls is not None and "control[3]" in controls.data:
        return times(controls), np.asarray(_col(controls, "control[3]")), "actuator_controls_0"
    return _empty(), _empty(), "vehicle_thrust_setpoint"


def _gsf(d, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    yc, yv = _col(d, "yaw_composite"), _col(d, "yaw_variance")
    if d is None or yc is None or yv is None:
        return _empty(), _empty(), _empty()
    sigma = np.degrees(np.sqrt(np.clip(yv, 0.0, None)))
    valid = _col(d, "yaw_composite_valid")
    if valid is not None:
        sigma = np.where(valid > 0, sigma, 99.0)
    return times(d), np.degrees(yc), sigma


def _gps(d, times) -> tuple[float | None, float | None, np.ndarray, np.ndarray]:
    if d is None:
        return None, None, _empty(), _empty()
    if "latitude_deg" in d.data:
        lat, lon = _col(d, "latitude_deg"), _col(d, "longitude_deg")
    elif "lat" in d.data:
        lat, lon = _col(d, "lat"), _col(d, "lon")
        if np.asarray(d.data["lat"]).dtype.kind in "iu":
            lat, lon = lat / 1e7, lon / 1e7  # type: ignore[operator]
    else:
        return None, None, _empty(), _empty()
    assert lat is not None and lon is not None
    fix = _col(d, "fix_type")
    ok = np.isfinite(lat) & np.isfinite(lon) & ((lat != 0) | (lon != 0))
    if fix is not None:
        ok &= fix >= 3
    spd = _col(d, "vel_m_s")
    t = times(d)
    la = float(np.median(lat[ok])) if ok.any() else None
    lo = float(np.median(lon[ok])) if ok.any() else None
    return la, lo, t, spd if spd is not None else np.full(len(t), np.nan)


def _evidence(status, hover, local, thr_t, thr, gps_t, gps_spd, times) -> FlightEvidence:
    arm_t, armed = _empty(), np.zeros(0, dtype=bool)
    st = _col(status, "arming_state")
    if status is not None and st is not None and len(st):
        arm_t, armed = times(status), st == ARMING_STATE_ARMED
    hov = np.full(len(thr_t), np.nan)
    h = _col(hover, "hover_thrust")
    if hover is not None and h is not None and len(h) and len(thr_t):
        hov = np.interp(thr_t, times(hover), h)
    alt = np.full(len(thr_t), np.nan)
    z = _col(local, "z")
    if local is not None and z is not None and len(z) and len(thr_t):
        alt = -np.interp(thr_t, times(local), z)
    return FlightEvidence("PX4", arm_t, armed, 0, thr_t, thr, hov, alt, gps_t, gps_spd)
