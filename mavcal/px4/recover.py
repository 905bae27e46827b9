"""The raw readings of a PX4 recording, in the frames the shared fit and quality stages take.

A ULog's ``sensor_accel`` / ``sensor_mag`` are raw already (before PX4's calibration, in the
sensor frame); a live link's SCALED_IMU accelerometer and HIGHRES_IMU magnetometer are PX4's
corrected values, undone here with the calibration in force (:mod:`mavcal.px4.firmware`).
SCALED_IMU's magnetometer is raw on PX4.

Frames of the results (those of :class:`mavcal.autopilot.raw.RawImu`):

* accelerometer: the sensor frame (the frame of ``CAL_ACCn_*OFF``/``SCALE``, before the rotation);
* magnetometer: the sensor frame turned by the rotation in force ``R_old`` (level adjustment x
  ``SENS_BOARD_ROT`` for an internal magnetometer, x ``CAL_MAGn_ROT`` for an external one), i.e.
  ``R_old s`` in mGauss: the offsets are not applied.

The calibration of each series is found by the series' device id (``extra["device_id"]``, a
ULog's); a series without one (a live link) is taken to be the device of slot ``instance``
(said in the warnings). A PX4 before 1.12 (no ``CAL_MAGn_PRIO``) calibrated its magnetometers in
the driver, so its logged ``sensor_mag`` is not raw (seen in sample_log_small.ulg: the primary's
``sensor_mag`` equals ``vehicle_magnetometer`` exactly): such magnetometers are left out, said.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from mavcal.autopilot.raw import RawImu, log_warnings_once
from mavcal.px4 import params as pn
from mavcal.px4.firmware import Px4AccelCal, Px4MagCal, accel_cal_from_params, mag_cal_from_params
from mavcal.sources.types import ImuLog, SensorSeries

__all__ = ["recover_raw", "device_id_of", "cal_of", "NO_RAW_ACCEL_LIVE", "CALIBRATED_ACCEL", "CALIBRATED_MAG",
           "ACCEL_FRAME", "MAG_FRAME"]

log = logging.getLogger(__name__)

ACCEL_FRAME = "sensor frame (before PX4's rotation)"
MAG_FRAME = "sensor frame turned by the rotation in force (before offsets and soft iron)"
#: the one line a live PX4 recording carries
NO_RAW_ACCEL_LIVE = ("PX4 sends no raw accelerometer over MAVLink (it refuses RAW_IMU): its calibrated SCALED_IMU "
                     "readings were undone with the CAL_ACC* in force (whole milli-g); for raw readings log "
                     "sensor_accel in a ULog (SDLOG_PROFILE high rate) and calibrate the .ulg")
#: messages whose accelerometer / magnetometer PX4 sends corrected (undone here)
CALIBRATED_ACCEL = frozenset({"SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU"})
CALIBRATED_MAG = frozenset({"HIGHRES_IMU"})


def device_id_of(s: SensorSeries, params: Mapping[str, float]) -> tuple[int, bool]:
    """(device id, whether it was assumed from slot ``s.instance``)."""
    dev = s.extra.get("device_id")
    if dev is not None and len(dev) and dev[-1]:
        return int(dev[-1]) & 0xFFFFFFFF, False
    ids = pn.device_ids(params, "accel" if s.sensor == "accel" else "mag")
    return ids.get(s.instance, 0), True


def cal_of(s: SensorSeries, params: Mapping[str, float]) -> Px4AccelCal | Px4MagCal:
    """The calibration PX4 applies to the sensor of series ``s``."""
    dev, _ = device_id_of(s, params)
    if s.sensor == "accel":
        return accel_cal_from_params(params, dev)
    ext = s.extra.get("is_external")
    return mag_cal_from_params(params, dev, bool(ext[-1]) if ext is not None and len(ext) else None)


def missing_calibration(s: SensorSeries, params: Mapping[str, float]) -> tuple[str, ...] | None:
    """The names of the calibration in force of series ``s``'s sensor that ``params`` lacks (the
    calibration in force is then not known), or None when it is known: its slot's ``_ID``,
    ``_ROT``, offsets and scales (and off-diagonals of a magnetometer) and ``SENS_BOARD_ROT``. A
    device no slot names, in a parameter set that has that kind's slots, is PX4's uncalibrated
    device (known); a parameter set without any slot of its kind says nothing."""
    kind = "accel" if s.sensor == "accel" else "mag"
    names_of = pn.accel_names if kind == "accel" else pn.mag_names
    board = pn.board_names()[0]
    slots = [names_of(k)["id"] for k in range(pn.MAX_SLOTS)]
    if not any(n in params for n in slots):
        return tuple(slots[:1] + ([board] if board not in params else []))
    cal = cal_of(s, params)
    need = [board]
    if cal.slot is not None:
        n = names_of(cal.slot)
        has_rot = any(names_of(k)["rot"] in params for k in range(pn.MAX_SLOTS))  # none before PX4 1.12: internal
        need += ([n["rot"]] if has_rot else []) + [*n["ofs"], *n["scale"]] \
            + (list(n["odiag"]) if kind == "mag" else [])  # type: ignore[typeddict-item]
    miss = tuple(x for x in need if x not in params)
    return miss or None


def _warnings(params: Mapping[str, float], log_: ImuLog) -> list[str]:
    out = []
    if params.get(pn.THERMAL_ACCEL):
        out.append("thermal compensation of the accelerometers is on (TC_A_ENABLE): PX4 subtracts its thermal "
                   "offsets before the calibration, so the offsets found include them at this temperature")
    if params.get(pn.MAG_COMP_TYPE):
        out.append("magnetometer power compensation is on (CAL_MAG_COMP_TYP): not modelled, readings taken at "
                   "rest (no motor current) are unaffected")
    return out


def recover_raw(log_: ImuLog) -> RawImu:
    """Raw accelerometer (sensor frame) and magnetometer (``R_old`` s) readings of a PX4 recording."""
    params = log_.params.snapshot()
    warnings = _warnings(params, log_)
    accel, mag = [], []
    missing: dict[str, tuple[str, ...]] = {}
    origin: dict[str, str] = {}
    old_mag_driver_cal = pn.mag_names(0)["id"] in params and pn.mag_names(0)["prio"] not in params
    for s in log_.series:
        if not len(s) or s.sensor == "gyro":
            continue
        dev, assumed = device_id_of(s, params)
        label = f"{'accel' if s.sensor == 'accel' else 'compass'}{s.instance}"
        miss = missing_calibration(s, params)
        if miss is not None:
            missing[label] = miss
            warnings.append(f"{s.sensor} {s.instance}: the recording lacks {', '.join(miss)}: the calibration in "
                            "force is not known, so its new values are not written")
        origin[label] = "" if miss is not None else log_.origin_of(
            [n for n in params if pn.is_calibration(n)])
        if assumed:
            warnings.append(f"{s.sensor} {s.instance}: device id not in the data, taken as slot {s.instance}'s ({dev})")
        cal = cal_of(s, params)
        if isinstance(cal, Px4AccelCal):
            raw = cal.undo(s.values) if s.message in CALIBRATED_ACCEL else s.values
            if s.message in CALIBRATED_ACCEL:
                warnings.append(NO_RAW_ACCEL_LIVE)
            accel.append(SensorSeries("accel", s.instance, s.message, s.time_s, raw, extra=dict(s.extra)))
            continue
        if old_mag_driver_cal and s.message == "sensor_mag":
            warnings.append(f"mag {s.instance}: this PX4 (before 1.12, no CAL_MAGn_PRIO) calibrated its "
                            "magnetometers in the driver, so the logged sensor_mag is not raw; compass left out")
            continue
        raw = cal.undo(s.values) if s.message in CALIBRATED_MAG else s.values
        mag.append(SensorSeries("mag", s.instance, s.message, s.time_s, np.asarray(raw) @ cal.rotation.T,
                                extra=dict(s.extra)))
    if not accel:
        warnings.append("no accelerometer readings")
    gyro = tuple(g for g in log_.series if g.sensor == "gyro" and len(g))
    log_warnings_once(log, warnings)
    a0 = next((s for s in log_.series if s.sensor == "accel" and len(s)), None)
    board = cal_of(a0, params).rotation if a0 is not None else None
    have = {f"accel{a.instance}" for a in accel} | {f"compass{m.instance}" for m in mag}
    return RawImu(source=log_.source, accel=tuple(accel), mag=tuple(mag), gyro=gyro,
                  params_used={n: ((0.0, float(v)),) for n, v in params.items() if pn.is_calibration(n)},
                  frames={"accel": ACCEL_FRAME, "mag": MAG_FRAME}, warnings=tuple(dict.fromkeys(warnings)),
                  board_rotation=None if board is None else np.array(board),
                  cal_origin={k: v for k, v in origin.items() if k in have},
                  cal_missing={k: v for k, v in missing.items() if k in have})
