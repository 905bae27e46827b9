"""The series of a flight that the in-flight compass stage needs, read from a DataFlash .bin.

One pass of the vectorised decoder (:mod:`mavcal.sources.fast_dataflash`) over ``MAG``,
``BAT``, ``ATT``, ``XKY0``, ``GPS``, ``CTUN``, ``PARM``, ``ARM``, ``EV``, ``MSG`` and ``FMTU``; the result is
plain numpy columns with units in their names (:class:`FlightSeries`). Nothing here knows what
a parameter means: the parameters are the first logged value of each name.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mavcal.errors import SourceError
from mavcal.sources.fast_dataflash import decode_dataflash

__all__ = ["CompassSeries", "FlightEvidence", "FlightSeries", "read_flight_series"]

MESSAGES = ("MAG", "BAT", "ATT", "XKY0", "GPS", "CTUN", "PARM", "ARM", "EV", "MSG", "FMTU")
#: the ``EV`` ids of ArduPilot's ``LogEvent`` that arm and disarm (``AP_Logger``: ARMED 10,
#: DISARMED 11, AUTO_ARMED 15) and that the land detector raises (NOT_LANDED 28, LAND_COMPLETE 18)
EV_ARMED, EV_DISARMED, EV_AUTO_ARMED, EV_LAND_COMPLETE, EV_NOT_LANDED = 10, 11, 15, 18, 28


@dataclass(frozen=True)
class CompassSeries:
    """One compass as logged (``MAG`` with instance ``I``): the corrected field the firmware used
    (body frame, mGauss), the offsets it applied and the motor offset it added. A PX4 log holds
    the raw reading instead (``raw_mgauss``, the sensor frame, and the ``device_id`` its calibration
    slot is found by); its corrected field, offsets and motor offset are then NaN (not logged)."""

    instance: int
    time_s: np.ndarray
    field_mgauss: np.ndarray  # (n, 3)
    ofs_mgauss: np.ndarray  # (n, 3)
    motor_ofs_mgauss: np.ndarray  # (n, 3)
    healthy: np.ndarray  # (n,) bool
    raw_mgauss: np.ndarray | None = None  # (n, 3) the raw reading (PX4's sensor_mag), None when not logged
    device_id: int | None = None


@dataclass(frozen=True)
class FlightEvidence:
    """What the log says about whether the vehicle flew: the firmware's name (``MSG``), the
    arming records (``ARM`` ``ArmState`` or ``EV``: ``arm_time_s`` / ``armed`` pairs, in time
    order), the land detector's events, the throttle against the hover throttle (``CTUN``
    ``ThO``, ``ThH``), the altitude (``CTUN`` ``Alt``, m) and the GPS ground speed (m/s)."""

    firmware: str
    arm_time_s: np.ndarray
    armed: np.ndarray  # (n,) bool
    not_landed_events: int
    ctun_time_s: np.ndarray
    throttle_out: np.ndarray
    hover_throttle: np.ndarray
    alt_m: np.ndarray
    gps_time_s: np.ndarray
    gps_speed_ms: np.ndarray


@dataclass(frozen=True)
class FlightSeries:
    """What a flight log says, on the log's time base (seconds since boot)."""

    source: str
    compasses: tuple[CompassSeries, ...]
    current_time_s: np.ndarray
    current_a: np.ndarray  # battery 0
    throttle_time_s: np.ndarray
    throttle: np.ndarray  # 0..1 (CTUN ThO)
    att_time_s: np.ndarray
    roll_deg: np.ndarray
    pitch_deg: np.ndarray
    yaw_deg: np.ndarray  # EKF yaw (uses the compasses)
    gsf_time_s: np.ndarray
    gsf_yaw_deg: np.ndarray  # EKF-GSF yaw estimator (XKY0 core 0), independent of the compasses
    gsf_yaw_sigma_deg: np.ndarray
    lat_deg: float | None
    lon_deg: float | None
    params: dict[str, float] = field(default_factory=dict)
    evidence: FlightEvidence | None = None  # None: not read from a log (a synthetic flight)
    autopilot: str = "ArduPilot"  # whose model the compasses follow (mavcal.autopilot.NAMES)
    battery_currents: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # more batteries: (t, A)
    throttle_message: str = "CTUN"  # where the throttle and the current are read from (said when missing)
    current_message: str = "BAT"
    gsf_message: str = "XKY0"


def _t(cols: dict[str, np.ndarray]) -> np.ndarray:
    return np.asarray(cols["TimeUS"], dtype=np.float64) * 1e-6


def _need(path: str | Path, name: str, cols: dict[str, np.ndarray], fields: tuple[str, ...]) -> None:
    """A message the stage reads must carry these fields: else one line naming what is missing."""
    lack = [f for f in fields if f not in cols]
    if lack:
        old = " (an older log: its messages are timed in TimeMS; the in-flight stage reads logs timed in TimeUS)" \
            if "TimeUS" in lack and "TimeMS" in cols else ""
        raise SourceError(f"{path}: {name} has no {', '.join(lack)}{old}")


def _col(cols: dict[str, np.ndarray] | None, *names: str) -> np.ndarray | None:
    if cols is None:
        return None
    for n in names:
        if n in cols:
            return np.asarray(cols[n], dtype=np.float64)
    return None


def _empty() -> np.ndarray:
    return np.zeros(0)


def read_flight_series(path: str | Path) -> FlightSeries:
    """Read the flight series of a DataFlash ``.bin``; :class:`SourceError` when it has no MAG or attitude."""
    p = Path(path)
    if not p.is_file():
        raise SourceError(f"{path}: no such file")
    if p.suffix.lower() not in (".bin", ".log") and not _looks_dataflash(p):
        raise SourceError(f"{path}: not a DataFlash .bin, a PX4 .ulg or a .tlog (the logs the in-flight stage reads)")
    try:
        cols, formats, _ = decode_dataflash(str(p), MESSAGES)
    except (OSError, ValueError) as exc:
        raise SourceError(f"{path}: cannot read: {exc}") from None
    mag = cols.get("MAG")
    att = cols.get("ATT")
    if mag is None or not any(len(v) for v in mag.values()):
        raise SourceError(f"{path}: no MAG messages (no compass logged)")
    _need(path, "MAG", mag, ("TimeUS", "MagX", "MagY", "MagZ", "OfsX", "OfsY", "OfsZ"))
    if att is None or not any(len(v) for v in att.values()):
        raise SourceError(f"{path}: no ATT messages (no attitude logged)")
    _need(path, "ATT", att, ("TimeUS", "Roll", "Pitch", "Yaw"))
    if len(att["TimeUS"]) < 10:
        raise SourceError(f"{path}: too few ATT messages ({len(att['TimeUS'])}: no attitude logged)")
    for name in ("BAT", "CTUN", "XKY0", "GPS", "ARM", "EV"):
        if name in cols and "TimeUS" not in cols[name]:
            del cols[name]  # an optional message without a time: as if not logged
    inst = np.asarray(mag.get("I", np.zeros(len(mag["TimeUS"]), dtype=np.uint8)))
    compasses = []
    for i in np.unique(inst):
        m = inst == i
        def v3(a: str, b: str, c: str, m: np.ndarray = m) -> np.ndarray:
            return np.column_stack([np.asarray(mag[k], dtype=np.float64)[m] for k in (a, b, c)])
        health = np.asarray(mag["Health"])[m].astype(bool) if "Health" in mag else np.ones(int(m.sum()), bool)
        mot = v3("MOX", "MOY", "MOZ") if all(k in mag for k in ("MOX", "MOY", "MOZ")) else np.zeros((int(m.sum()), 3))
        compasses.append(CompassSeries(int(i), _t(mag)[m], v3("MagX", "MagY", "MagZ"), v3("OfsX", "OfsY", "OfsZ"),
                                       mot, health))
    bat = cols.get("BAT")
    if bat is not None and len(bat["TimeUS"]) and "Curr" in bat:
        inst_b = bat.get("Inst", bat.get("Instance", np.zeros(len(bat["TimeUS"]))))
        b0 = np.asarray(inst_b) == 0
        cur_t, cur = _t(bat)[b0], np.asarray(bat["Curr"], dtype=np.float64)[b0]
    else:
        cur_t, cur = _empty(), _empty()
    ctun = cols.get("CTUN")
    if ctun is not None and "ThO" in ctun:
        thr_t, thr = _t(ctun), np.asarray(ctun["ThO"], dtype=np.float64)
    else:
        thr_t, thr = _empty(), _empty()
    xky = cols.get("XKY0")
    if xky is not None and len(xky["TimeUS"]) and all(k in xky for k in ("YC", "YCS")):
        c0 = np.asarray(xky.get("C", np.zeros(len(xky["TimeUS"])))) == 0
        gt, gy, gs = _t(xky)[c0], np.asarray(xky["YC"], float)[c0], np.asarray(xky["YCS"], float)[c0]
        per_deg = _yaw_unit_deg(cols, formats, "XKY0", "YC")
        if per_deg is None:  # the unit is not logged: no compass-independent yaw rather than a wrong one
            gt, gy, gs = _empty(), _empty(), _empty()
        else:
            gy, gs = gy * per_deg, gs * per_deg
    else:
        gt, gy, gs = _empty(), _empty(), _empty()
    lat = lon = None
    gps = cols.get("GPS")
    if gps is not None and len(gps["TimeUS"]) and all(k in gps for k in ("Status", "Lat", "Lng")):
        ok = np.asarray(gps["Status"]) >= 3
        if ok.any():
            lat = float(np.median(np.asarray(gps["Lat"], float)[ok]))
            lon = float(np.median(np.asarray(gps["Lng"], float)[ok]))
    params: dict[str, float] = {}
    parm = cols.get("PARM")
    if parm is not None and "Name" in parm and "Value" in parm:
        for n, v in zip(parm["Name"], parm["Value"]):
            name = n.split(b"\0", 1)[0].decode("ascii", "replace")
            params.setdefault(name, float(v))
    return FlightSeries(str(path), tuple(compasses), cur_t, cur, thr_t, thr, _t(att),
                        np.asarray(att["Roll"], float), np.asarray(att["Pitch"], float), np.asarray(att["Yaw"], float),
                        gt, gy, gs, lat, lon, params, _evidence(cols))


def _evidence(cols: dict[str, dict[str, np.ndarray]]) -> FlightEvidence:
    firmware = ""
    msg = cols.get("MSG")
    if msg is not None and "Message" in msg:
        for m in msg["Message"]:
            text = bytes(m).split(b"\0", 1)[0].decode("ascii", "replace").strip()
            if text.startswith(("Ardu", "APM:", "PX4", "Rover", "Blimp", "AntennaTracker")) and " V" in text:
                firmware = text
                break
    arm_t: list[float] = []
    armed: list[bool] = []
    arm = cols.get("ARM")
    if arm is not None and "ArmState" in arm and len(arm["TimeUS"]):
        arm_t += list(_t(arm))
        armed += [bool(v) for v in np.asarray(arm["ArmState"])]
    ev = cols.get("EV")
    not_landed = 0
    if ev is not None and "Id" in ev and len(ev["TimeUS"]):
        ids = np.asarray(ev["Id"]).astype(int)
        for t, i in zip(_t(ev), ids):
            if i in (EV_ARMED, EV_AUTO_ARMED, EV_DISARMED):
                arm_t.append(float(t))
                armed.append(i != EV_DISARMED)
        not_landed = int(np.count_nonzero(ids == EV_NOT_LANDED))
    order = np.argsort(np.asarray(arm_t, dtype=float), kind="stable")
    ctun = cols.get("CTUN")
    ct = _t(ctun) if ctun is not None and len(ctun.get("TimeUS", ())) else _empty()
    def cc(*names: str) -> np.ndarray:
        v = _col(ctun, *names)
        return v if v is not None and len(v) == len(ct) else np.full(len(ct), np.nan)
    gps = cols.get("GPS")
    gt = _t(gps) if gps is not None and len(gps.get("TimeUS", ())) else _empty()
    spd = _col(gps, "Spd")
    return FlightEvidence(firmware, np.asarray(arm_t, dtype=float)[order], np.asarray(armed, dtype=bool)[order],
                          not_landed, ct, cc("ThO"), cc("ThH"), cc("Alt"), gt,
                          spd if spd is not None and len(spd) == len(gt) else np.full(len(gt), np.nan))


def _yaw_unit_deg(cols: dict[str, dict[str, np.ndarray]], formats: dict, name: str, column: str) -> float | None:
    """Degrees per logged unit of ``name.column`` from the ``FMTU`` record of its type: the GSF
    yaw is logged in radians by ArduPilot 4.0/4.1 (unit ``r``) and in degrees later (``h``/``d``);
    None when the log does not say."""
    fmt = next((f for f in formats.values() if getattr(f, "name", None) == name), None)
    fmtu = cols.get("FMTU")
    if fmt is None or fmtu is None or not all(k in fmtu for k in ("FmtType", "UnitIds")) \
            or column not in fmt.columns:
        return None
    k = fmt.columns.index(column)
    for ty, units in zip(np.asarray(fmtu["FmtType"]), fmtu["UnitIds"]):
        if int(ty) != fmt.type:
            continue
        u = bytes(units).split(b"\0", 1)[0].decode("ascii", "replace")
        if k < len(u):
            return {"r": float(np.degrees(1.0)), "h": 1.0, "d": 1.0}.get(u[k])
    return None


def _looks_dataflash(p: Path) -> bool:
    try:
        with open(p, "rb") as fh:
            head = fh.read(3)
    except OSError:
        return False
    return head[:2] == b"\xa3\x95"
