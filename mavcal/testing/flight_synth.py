"""A synthetic flight for the in-flight compass stage: a :class:`FlightSeries` made from
ArduPilot's compass model with known interference, offsets and calibration in force.

Each compass sees ``b = R^T B + s x - o_true`` (``s``: the interference per unit of the driver,
as SITL's ``SIM_MAG_MOT``; ``o_true``: the offsets that cancel its hard iron) plus white noise,
and logs what the firmware reports with the calibration in force (``OFS``, ``MOT``):
``mag = b + OFS + MOT x`` (DIA 1, ODI 0, SCALE 1). So the right ``COMPASS_MOT`` is ``-s`` and
the right ``COMPASS_OFS`` is ``o_true``.
"""
from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mavcal.sources.flight_series import CompassSeries, FlightSeries

__all__ = ["SynthCompass", "synth_flight", "write_flight_bin", "write_flight_tlog"]


@dataclass(frozen=True)
class SynthCompass:
    interference: tuple[float, float, float] = (0.0, 0.0, 0.0)  # s, mGauss per A
    ofs_true: tuple[float, float, float] = (5.0, 13.0, -18.0)
    ofs_in_force: tuple[float, float, float] = (5.0, 13.0, -18.0)
    mot_in_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_rotation_deg: float = 0.0  # mounted turned about z unlike its orientation in force


def _R(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    r, p, y = np.radians(roll), np.radians(pitch), np.radians(yaw)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.empty((len(roll), 3, 3))
    R[:, 0] = np.column_stack([cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy])
    R[:, 1] = np.column_stack([cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy])
    R[:, 2] = np.column_stack([-sp, sr * cp, cr * cp])
    return R


def synth_flight(compasses: Sequence[SynthCompass], *, seed: int = 0, duration_s: float = 150.0, rate_hz: float = 10.0,
                 current_max_a: float = 40.0, noise_mgauss: float = 2.0,
                 lat_lon: tuple[float, float] = (-35.363, 149.165), params: dict[str, float] | None = None,
                 field_ned: Sequence[float] | None = None) -> FlightSeries:
    """A flight of ``duration_s`` with turns through every heading, tilts up to ~20 deg, and a
    current between 0 and ``current_max_a`` (0 for a constant-current flight)."""
    from mavcal.sources.wmm import field_ned as wmm_ned

    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    yaw = (t * 360.0 / 40.0 + 20 * np.sin(t / 7.0)) % 360.0
    roll = 15 * np.sin(t / 3.1 + 1.0) * np.sin(t / 11.0)
    pitch = 12 * np.sin(t / 4.3) * np.cos(t / 13.0)
    cur = current_max_a * np.clip(0.5 + 0.45 * np.sin(t / 5.0) * np.sin(t / 17.0 + 0.5), 0.0, 1.0)
    R = _R(roll, pitch, yaw)
    B = np.asarray(field_ned, float) if field_ned is not None else wmm_ned(*lat_lon)
    body = np.einsum("nji,j->ni", R, B)
    p: dict[str, float] = {"COMPASS_MOTCT": 2.0}
    series = []
    for i, c in enumerate(compasses):
        s = "" if i == 0 else str(i + 1)
        p.update({f"COMPASS_OFS{s}_{a}": v for a, v in zip("XYZ", c.ofs_in_force)})
        p.update({f"COMPASS_MOT{s}_{a}": v for a, v in zip("XYZ", c.mot_in_force)})
        p.update({f"COMPASS_DIA{s}_{a}": 1.0 for a in "XYZ"})
        p.update({f"COMPASS_ODI{s}_{a}": 0.0 for a in "XYZ"})
        p.update({f"COMPASS_SCALE{s}": 1.0, f"COMPASS_ORIENT{s}": 0.0, f"COMPASS_USE{s}": 1.0})
        p["COMPASS_EXTERNAL" if i == 0 else f"COMPASS_EXTERN{i + 1}"] = 1.0
        a = np.radians(c.yaw_rotation_deg)
        Q = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        b = (Q @ body.T).T + cur[:, None] * np.asarray(c.interference) - np.asarray(c.ofs_true)
        b = b + rng.normal(0.0, noise_mgauss, b.shape)
        mo = cur[:, None] * np.asarray(c.mot_in_force)
        mag = np.round(b + np.asarray(c.ofs_in_force) + mo)
        series.append(CompassSeries(i, t.copy(), mag, np.tile(np.asarray(c.ofs_in_force, float), (len(t), 1)),
                                    np.round(mo), np.ones(len(t), bool)))
    p.update(params or {})
    return FlightSeries("synthetic", tuple(series), t.copy(), cur, t.copy(), cur / max(current_max_a, 1e-9) * 0.6,
                        t.copy(), roll, pitch, yaw, t.copy(), yaw.copy(), np.full(len(t), 1.0),
                        lat_lon[0], lat_lon[1], {k: v for k, v in p.items() if v is not None})


# --- the synthetic flight written as a DataFlash .bin (as ArduPilot 4.x logs these messages)

FORMATS = {  # name: (type, format, columns) as ArduPilot 4.x logs them
    "MAG": (30, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    "ATT": (31, "QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
    "BAT": (32, "QBfffffcfBBB", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct,H,SH"),
    "CTUN": (33, "Qfffffffccfhh", "TimeUS,ThI,ABst,ThO,ThH,DAlt,Alt,BAlt,DSAlt,SAlt,TAlt,DCRt,CRt"),
    "GPS": (34, "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    "XKY0": (35, "QBffffffffffff", "TimeUS,C,YC,YCS,Y0,Y1,Y2,Y3,Y4,W0,W1,W2,W3,W4"),
    "ARM": (36, "QBIBB", "TimeUS,ArmState,ArmChecks,Forced,Method"),
    "MSG": (37, "QZ", "TimeUS,Message"),
    "PARM": (38, "QNff", "TimeUS,Name,Value,Default"),
    "FMTU": (39, "QBNN", "TimeUS,FmtType,UnitIds,MultIds"),
}
PACK = {"Q": "Q", "B": "B", "h": "h", "H": "H", "I": "I", "f": "f", "c": "h", "C": "H", "L": "i", "e": "i",
        "Z": "64s", "N": "16s"}
SCALE = {"c": 100, "C": 100, "L": 1e7, "e": 100}


def write_flight_bin(path: str | Path, s: FlightSeries, *, gsf: bool = True, firmware: str = "ArduCopter V4.5.7",
                     armed: bool = True, hover: float = 0.35, gsf_unit: str | None = "h") -> Path:
    """Write the synthetic flight ``s`` as a DataFlash ``.bin`` with the messages the stage reads
    (``MAG``, ``ATT``, ``BAT``, ``CTUN``, ``GPS``, ``XKY0``, ``ARM``, ``MSG``, ``PARM``, ``FMTU``);
    ``gsf_unit``: the GSF yaw's unit as ``FMTU`` says ("h": deg as 4.2 on, "r": rad as 4.0/4.1,
    None: no FMTU for it)."""
    out = bytearray()
    for name, (ty, fmt, cols) in FORMATS.items():
        body = struct.pack("<BB4s16s64s", ty, 3 + struct.calcsize("<" + "".join(PACK[c] for c in fmt)),
                           name.encode(), fmt.encode(), cols.encode())
        out += b"\xa3\x95\x80" + body

    def rec(name: str, *values) -> None:
        ty, fmt, _ = FORMATS[name]
        vals = []
        for c, v in zip(fmt, values):
            if c in "ZN":
                vals.append(str(v).encode())
            elif c == "f":
                vals.append(float(v))
            else:
                vals.append(int(round(float(v) * SCALE.get(c, 1))))
        out.extend(b"\xa3\x95" + bytes([ty]) + struct.pack("<" + "".join(PACK[c] for c in fmt), *vals))

    rec("MSG", 1000, firmware)
    if gsf_unit is not None:
        rec("FMTU", 1000, FORMATS["XKY0"][0], f"s#{gsf_unit}d{gsf_unit * 5}-----", "F-000000000000")
    per = 1.0 if gsf_unit != "r" else np.radians(1.0)
    for k, v in s.params.items():
        rec("PARM", 2000, k, v, 0.0)
    t0 = 5.0
    if armed:
        rec("ARM", int((t0 - 1) * 1e6), 1, 0, 0, 0)
    cur_max = max(float(np.max(s.current_a)), 1e-9)
    for k, t in enumerate(s.att_time_s):
        us = int((t + t0) * 1e6)
        rec("ATT", us, 0, s.roll_deg[k], 0, s.pitch_deg[k], 0, s.yaw_deg[k] % 360.0, 0, 0, 3)
        for c in s.compasses:
            rec("MAG", us, c.instance, *c.field_mgauss[k], *c.ofs_mgauss[k], *c.motor_ofs_mgauss[k], 1, us // 1000)
        rec("BAT", us, 0, 16.0, 16.0, s.current_a[k], 1.0, 1.0, 25.0, 0.01, 90, 1, 0)
        alt = min(10.0, 2.0 * t)
        rec("CTUN", us, 0.5, 0, hover * (0.9 + 0.5 * s.current_a[k] / cur_max), hover, alt, alt, alt, 0, 0, 0, 0, 0, 0)
        if k % 2 == 0:
            rec("GPS", us, 0, 6, 0, 0, 12, 0.8, -35.363, 149.165, 600.0, 4.0, 0.0, 0.0, 0.0, 1)
        if gsf:
            rec("XKY0", us, 0, s.gsf_yaw_deg[k] * per, s.gsf_yaw_sigma_deg[k] * per, *([0.0] * 10))
    if armed:
        rec("ARM", int((s.att_time_s[-1] + t0 + 1) * 1e6), 0, 0, 0, 0)
    path = Path(path)
    path.write_bytes(bytes(out))
    return path


def write_flight_tlog(path: str | Path, s: FlightSeries, *, every: int = 1, current: bool = True,
                      autopilot: int = 3, params: bool = True) -> Path:
    """Write the synthetic flight ``s`` as a tlog, as an ArduPilot ground station records it: the
    corrected field of compasses 0-2 in ``RAW_IMU`` / ``SCALED_IMU2`` / ``SCALED_IMU3``, ``ATTITUDE``,
    ``SYS_STATUS`` (current in cA; -1 without ``current``), ``VFR_HUD`` (throttle %, altitude),
    ``GPS_RAW_INT``, an armed ``HEARTBEAT`` (``autopilot`` 3 ArduPilot, 12 PX4) and the parameters
    (``PARAM_VALUE``). ``every``: keep every n-th sample (a slower stream)."""
    from mavcal.testing.logwriters import TlogWriter

    t_unix = 1.7e9
    path = Path(path)
    with TlogWriter(path) as w:
        d = w.dialect
        w.heartbeat(t_unix, autopilot=autopilot, base_mode=81 | 128)
        if params:
            for k, (name, v) in enumerate(s.params.items()):
                w.param_value(t_unix + 0.001 * k, name, v, index=k, count=len(s.params))
        for k in range(0, len(s.att_time_s), every):
            t = t_unix + 5.0 + float(s.att_time_s[k])
            ms = int(float(s.att_time_s[k]) * 1000) + 5000
            for c in s.compasses:
                if c.instance == 0:
                    w.raw_imu(t, ms * 1000, (0, 0, -1000), (0, 0, 0), c.field_mgauss[k])
                else:
                    w.scaled_imu(c.instance + 1, t, ms, (0, 0, -1000), (0, 0, 0), c.field_mgauss[k])
            w.attitude(t, ms, *np.radians([s.roll_deg[k], s.pitch_deg[k], s.yaw_deg[k]]))
            cur = int(round(s.current_a[k] * 100)) if current else -1
            w.write(t, d.MAVLink_sys_status_message(0, 0, 0, 0, 16000, cur, 80, 0, 0, 0, 0, 0, 0))
            alt = 600.0 + min(10.0, 2.0 * float(s.att_time_s[k]))
            w.write(t, d.MAVLink_vfr_hud_message(0.0, 4.0, 0, int(round(100 * s.throttle[k])), alt, 0.0))
            if k % 5 == 0:
                w.heartbeat(t, autopilot=autopilot, base_mode=81 | 128)
                w.write(t, d.MAVLink_gps_raw_int_message(int(t * 1e6), 3, int(-35.363e7), int(149.165e7), 600000,
                                                         80, 120, 400, 0, 12))
    return path
