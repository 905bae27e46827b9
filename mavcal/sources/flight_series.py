"""The series of a flight that the in-flight compass stage needs, read from a DataFlash .bin.

One pass of the vectorised decoder (:mod:`mavcal.sources.fast_dataflash`) over ``MAG``,
``BAT``, ``ATT``, ``XKQ``, ``XKY0``, ``GPS``, ``CTUN``, ``RCOU`` and ``PARM``; the result is
plain numpy columns with units in their names (:class:`FlightSeries`). Nothing here knows what
a parameter means: the parameters are the first logged value of each name.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mavcal.errors import SourceError
from mavcal.sources.fast_dataflash import decode_dataflash

__all__ = ["CompassSeries", "FlightSeries", "read_flight_series"]

MESSAGES = ("MAG", "BAT", "ATT", "XKQ", "XKY0", "GPS", "CTUN", "PARM")


@dataclass(frozen=True)
class CompassSeries:
    """One compass as logged (``MAG`` with instance ``I``): the corrected field the firmware used
    (body frame, mGauss), the offsets it applied and the motor offset it added."""

    instance: int
    time_s: np.ndarray
    field_mgauss: np.ndarray  # (n, 3)
    ofs_mgauss: np.ndarray  # (n, 3)
    motor_ofs_mgauss: np.ndarray  # (n, 3)
    healthy: np.ndarray  # (n,) bool


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


def _t(cols: dict[str, np.ndarray]) -> np.ndarray:
    return np.asarray(cols["TimeUS"], dtype=np.float64) * 1e-6


def _empty() -> np.ndarray:
    return np.zeros(0)


def read_flight_series(path: str | Path) -> FlightSeries:
    """Read the flight series of a DataFlash ``.bin``; :class:`SourceError` when it has no MAG or attitude."""
    p = Path(path)
    if not p.is_file():
        raise SourceError(f"{path}: no such file")
    if p.suffix.lower() not in (".bin", ".log") and not _looks_dataflash(p):
        raise SourceError(f"{path}: not a DataFlash .bin (the in-flight stage reads .bin logs)")
    try:
        cols, _, _ = decode_dataflash(str(p), MESSAGES)
    except (OSError, ValueError) as exc:
        raise SourceError(f"{path}: cannot read: {exc}") from None
    mag = cols.get("MAG")
    att = cols.get("ATT")
    if mag is None or len(mag["TimeUS"]) == 0:
        raise SourceError(f"{path}: no MAG messages (no compass logged)")
    if att is None or len(att["TimeUS"]) < 10:
        raise SourceError(f"{path}: no ATT messages (no attitude logged)")
    inst = np.asarray(mag.get("I", np.zeros(len(mag["TimeUS"]), dtype=np.uint8)))
    compasses = []
    for i in np.unique(inst):
        m = inst == i
        def v3(a: str, b: str, c: str, m: np.ndarray = m) -> np.ndarray:
            return np.column_stack([np.asarray(mag[k], dtype=np.float64)[m] for k in (a, b, c)])
        health = np.asarray(mag["Health"])[m].astype(bool) if "Health" in mag else np.ones(int(m.sum()), bool)
        mot = v3("MOX", "MOY", "MOZ") if "MOX" in mag else np.zeros((int(m.sum()), 3))
        compasses.append(CompassSeries(int(i), _t(mag)[m], v3("MagX", "MagY", "MagZ"), v3("OfsX", "OfsY", "OfsZ"),
                                       mot, health))
    bat = cols.get("BAT")
    if bat is not None and len(bat["TimeUS"]):
        b0 = np.asarray(bat.get("Inst", np.zeros(len(bat["TimeUS"]))) == 0)
        cur_t, cur = _t(bat)[b0], np.asarray(bat["Curr"], dtype=np.float64)[b0]
    else:
        cur_t, cur = _empty(), _empty()
    ctun = cols.get("CTUN")
    if ctun is not None and "ThO" in ctun:
        thr_t, thr = _t(ctun), np.asarray(ctun["ThO"], dtype=np.float64)
    else:
        thr_t, thr = _empty(), _empty()
    xky = cols.get("XKY0")
    if xky is not None and len(xky["TimeUS"]):
        c0 = np.asarray(xky.get("C", np.zeros(len(xky["TimeUS"])))) == 0
        gt, gy, gs = _t(xky)[c0], np.asarray(xky["YC"], float)[c0], np.asarray(xky["YCS"], float)[c0]
    else:
        gt, gy, gs = _empty(), _empty(), _empty()
    lat = lon = None
    gps = cols.get("GPS")
    if gps is not None and len(gps["TimeUS"]):
        ok = np.asarray(gps["Status"]) >= 3
        if ok.any():
            lat = float(np.median(np.asarray(gps["Lat"], float)[ok]))
            lon = float(np.median(np.asarray(gps["Lng"], float)[ok]))
    params: dict[str, float] = {}
    parm = cols.get("PARM")
    if parm is not None:
        for n, v in zip(parm["Name"], parm["Value"]):
            name = n.split(b"\0", 1)[0].decode("ascii", "replace")
            params.setdefault(name, float(v))
    return FlightSeries(str(path), tuple(compasses), cur_t, cur, thr_t, thr, _t(att),
                        np.asarray(att["Roll"], float), np.asarray(att["Pitch"], float), np.asarray(att["Yaw"], float),
                        gt, gy, gs, lat, lon, params)


def _looks_dataflash(p: Path) -> bool:
    try:
        with open(p, "rb") as fh:
            head = fh.read(3)
    except OSError:
        return False
    return head[:2] == b"\xa3\x95"
