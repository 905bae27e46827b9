"""Did the vehicle fly? The in-flight stage has nothing to say about a log without a flight.

A flight is **armed and airborne**. From the log (:class:`mavcal.sources.flight_series.FlightEvidence`):

* the vehicle: a log whose firmware (``MSG``) is ArduSub or Rover never flies;
* armed: the ``ARM`` records (``ArmState``) or the ``EV`` arm/disarm events (before the first
  record, the state it leaves: a log that starts logging at arming records only the disarm); a
  log with neither is taken as armed throughout (and says so);
* airborne, while armed: the throttle out at or above :data:`HOVER_FRACTION` of the hover
  throttle (``CTUN`` ``ThO`` against ``ThH``: a multicopter lifts off there), or the GPS ground
  speed above :data:`MIN_GPS_SPEED_MS` (a plane or a copter moving); at least
  :data:`MIN_AIRBORNE_S` of it;
* and a move to show for it: the altitude (``CTUN`` ``Alt``) spanning at least
  :data:`MIN_CLIMB_M` while armed, or that ground speed.

A bench log (rotated by hand, never armed), a hop below the hover throttle, or a sub fails it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavcal.sources.flight_series import FlightEvidence

__all__ = ["Airborne", "judge_flight", "HOVER_FRACTION", "MIN_AIRBORNE_S", "MIN_CLIMB_M", "MIN_GPS_SPEED_MS",
           "NOT_FLYING"]

HOVER_FRACTION = 0.8
MIN_AIRBORNE_S = 10.0
MIN_CLIMB_M = 1.0
MIN_GPS_SPEED_MS = 3.0
NOT_FLYING = ("ArduSub", "ArduRover", "Rover", "AntennaTracker")


@dataclass(frozen=True)
class Airborne:
    flew: bool
    why: str  # what was (not) seen, in words
    armed_s: float
    airborne_s: float


def _armed_mask(ev: FlightEvidence, t: np.ndarray) -> np.ndarray:
    if not len(ev.arm_time_s):
        return np.ones(len(t), dtype=bool)
    idx = np.searchsorted(ev.arm_time_s, t, side="right") - 1
    # before the first record: the state it left (a log that starts at arming records only the disarm)
    out = np.full(len(t), not bool(ev.armed[0]), dtype=bool)
    ok = idx >= 0
    out[ok] = ev.armed[idx[ok]]
    return out


def _seconds(t: np.ndarray, mask: np.ndarray) -> float:
    """Time covered by the samples in ``mask`` (each counts up to the next sample, at most 1 s)."""
    if len(t) < 2:
        return 0.0
    dt = np.clip(np.diff(t), 0.0, 1.0)
    return float(np.sum(dt[mask[:-1]]))


def judge_flight(ev: FlightEvidence) -> Airborne:
    fw = ev.firmware
    if fw.startswith(NOT_FLYING):
        return Airborne(False, f"the vehicle is {fw.split(' ')[0]} ({fw}): it does not fly", 0.0, 0.0)
    known_arm = bool(len(ev.arm_time_s))
    if known_arm and not ev.armed.any() and not _armed_mask(ev, ev.ctun_time_s).any() \
            and not _armed_mask(ev, ev.gps_time_s).any():
        return Airborne(False, "the vehicle was never armed", 0.0, 0.0)
    ct_armed = _armed_mask(ev, ev.ctun_time_s)
    gps_armed = _armed_mask(ev, ev.gps_time_s)
    armed_s = max(_seconds(ev.ctun_time_s, ct_armed), _seconds(ev.gps_time_s, gps_armed))
    with np.errstate(invalid="ignore"):
        hover = np.nan_to_num(ev.hover_throttle, nan=0.0)
        lift = ct_armed & (hover > 0) & (ev.throttle_out >= HOVER_FRACTION * hover)
        moving = gps_armed & (ev.gps_speed_ms > MIN_GPS_SPEED_MS)
    airborne_s = max(_seconds(ev.ctun_time_s, lift), _seconds(ev.gps_time_s, moving))
    alt = ev.alt_m[ct_armed & np.isfinite(ev.alt_m)]
    climb = float(np.ptp(alt)) if len(alt) else 0.0
    moved = climb >= MIN_CLIMB_M or _seconds(ev.gps_time_s, moving) >= MIN_AIRBORNE_S
    armed_txt = f"armed for {armed_s:.0f} s" if known_arm else "no arming record (taken as armed throughout)"
    hov = hover[ct_armed & (hover > 0)]
    thr = ev.throttle_out[ct_armed & np.isfinite(ev.throttle_out)]
    thr_txt = (f"the throttle reached {float(thr.max()):.2f} against a hover throttle of {float(np.median(hov)):.2f}"
               if len(thr) and len(hov) else "no throttle against the hover throttle logged")
    spd = ev.gps_speed_ms[gps_armed & np.isfinite(ev.gps_speed_ms)]
    spd_txt = f"ground speed up to {float(spd.max()):.1f} m/s" if len(spd) else "no GPS speed"
    why = (f"{armed_txt}; airborne {airborne_s:.0f} s ({thr_txt}); "
           f"the altitude spanned {climb:.1f} m; {spd_txt}")
    flew = airborne_s >= MIN_AIRBORNE_S and moved
    return Airborne(flew, why, armed_s, airborne_s)
