"""The one table of value limits for calibration parameters, shared by the quality gates and
by every write (``apply``, ``restore``, ``calibrate --write``).

Each limit is ArduPilot's own, checked in its source where one exists:

* compass offsets: vector length <= ``COMPASS_OFFS_MAX`` (int16, default 1800, @Range 500-3000;
  ``AP_Arming::compass_checks``; ``CompassCalibrator::fit_acceptable`` bounds each axis by it);
* soft iron: 0.2 < DIA < 5 and |ODI| < 1 (``CompassCalibrator::fit_acceptable``); an all-zero
  DIA vector is legal (the matrix is switched off, ``AP_Compass_Backend::correct_field``);
* ``COMPASS_SCALEn``: 0 (off) or within [1/1.5, 1.5] (``COMPASS_MIN/MAX_SCALE_FACTOR``);
* ``COMPASS_MOTn``: @Range -1000..1000 (mGauss per A or at full throttle);
* earth field magnitude 185-875 mGauss (arming check; gates only, not a parameter);
* accelerometer offsets |ofs| <= 3.5 m/s^2 (@Range of INS_ACCOFFS; ``AccelCalibrator`` itself
  accepts |p| <= g) and scales 0.8-1.2 (``AccelCalibrator::accept_result`` and @Range);
* ``AHRS_TRIM_*``: |trim| <= 10 deg (``HAL_INS_TRIM_LIMIT_DEG``);
* orientations: a Rotation enum value (0..43, 101, 102); ``COMPASS_EXTERNn`` 0/1/2.

``CUST_ROTn_*`` angles have no ArduPilot bound; mavcal refuses beyond +/-360 deg as absurd.

:func:`check_limits` checks values about to be written (overlaid on the vehicle's table, so a
vector is judged whole); :func:`failing_kinds` says which sensor kinds (``"compass"``,
``"accel"``) must not be force-saved ("marked calibrated") because their values fail.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.limits import LimitViolation
from mavcal.autopilot.rotations import is_valid_rotation

__all__ = ["ACCEL_OFFSET_MAX_MPS2", "ACCEL_SCALE_RANGE", "COMPASS_OFFSET_MAX_DEFAULT_MGAUSS", "COMPASS_OFFS_MAX",
           "COMPASS_OFFS_MAX_RANGE", "DIA_RANGE", "ODI_MAX", "FIELD_RANGE_MGAUSS", "COMPASS_SCALE_RANGE",
           "COMPASS_MOT_MAX", "AHRS_TRIM_MAX_RAD", "CUSTOM_ANGLE_MAX_DEG", "LimitViolation", "check_limits",
           "failing_kinds", "compass_offset_max", "sensor_of", "related_names"]

ACCEL_OFFSET_MAX_MPS2 = 3.5
ACCEL_SCALE_RANGE = (0.8, 1.2)
COMPASS_OFFS_MAX = "COMPASS_OFFS_MAX"
COMPASS_OFFSET_MAX_DEFAULT_MGAUSS = 1800.0
COMPASS_OFFS_MAX_RANGE = (500.0, 3000.0)
DIA_RANGE = (0.2, 5.0)  # exclusive
ODI_MAX = 1.0  # exclusive
FIELD_RANGE_MGAUSS = (185.0, 875.0)
COMPASS_SCALE_RANGE = (fw.COMPASS_MIN_SCALE, fw.COMPASS_MAX_SCALE)
COMPASS_MOT_MAX = 1000.0
AHRS_TRIM_MAX_RAD = math.radians(10.0)
CUSTOM_ANGLE_MAX_DEG = 360.0
_EXTERNAL_VALUES = (0, 1, 2)


def _index() -> dict[str, tuple[str, int, str]]:
    """name -> (kind, instance, field) for every per-sensor and board name mavcal bounds."""
    out: dict[str, tuple[str, int, str]] = {}
    for k in range(fw.MAX_COMPASSES):
        cn = fw.compass_param_names(k)
        for f, three in (("ofs", cn["ofs"]), ("dia", cn["dia"]), ("odi", cn["odi"]), ("mot", cn["mot"])):
            for n in three:
                out[n] = ("compass", k, f)
        for f, one in (("scale", cn["scale"]), ("orient", cn["orient"]), ("external", cn["external"])):
            out[one] = ("compass", k, f)
    for i in range(fw.MAX_IMUS):
        an = fw.accel_param_names(i)
        for f, three in (("ofs", an["ofs"]), ("scale", an["scale"])):
            for n in three:
                out[n] = ("accel", i, f)
    b = fw.board_param_names()
    out[b["orientation"]] = ("board", 0, "orientation")
    for n in b["trim"]:
        out[n] = ("board", 0, "trim")
    for n in b["custom1"] + b["custom2"]:
        out[n] = ("board", 0, "custom")
    out[COMPASS_OFFS_MAX] = ("board", 0, "offs_max")
    return out


_INDEX = _index()


def sensor_of(name: str) -> tuple[str, int] | None:
    """``("compass", k)`` / ``("accel", i)`` for a per-sensor calibration name, else None."""
    hit = _INDEX.get(name)
    return (hit[0], hit[1]) if hit and hit[0] != "board" else None


def compass_offset_max(params: Mapping[str, float]) -> float:
    """``COMPASS_OFFS_MAX`` of ``params`` (1800, ArduPilot's default, when absent)."""
    return float(params.get(COMPASS_OFFS_MAX, COMPASS_OFFSET_MAX_DEFAULT_MGAUSS))


def _vector(params: Mapping[str, float], names) -> tuple[float, float, float]:
    a, b, c = (float(params.get(n, 0.0)) for n in names)
    return (a, b, c)


def _compass_limit(name: str, v: float, k: int, field: str, merged: Mapping[str, float]) -> str | None:
    cn = fw.compass_param_names(k)
    if field == "ofs":
        omax = compass_offset_max(merged)
        length = math.sqrt(sum(x * x for x in _vector(merged, cn["ofs"])))
        if not length <= omax:
            return f"COMPASS_OFFS_MAX {omax:g} (offset length {length:g} mGauss)"
    elif field == "dia":
        lo, hi = DIA_RANGE
        if not (lo < v < hi) and any(_vector(merged, cn["dia"])):
            return f"{lo:g} < DIA < {hi:g} (0 only with all three 0)"
    elif field == "odi":
        if not abs(v) < ODI_MAX:
            return f"|ODI| < {ODI_MAX:g}"
    elif field == "mot":
        if not abs(v) <= COMPASS_MOT_MAX:
            return f"|MOT| <= {COMPASS_MOT_MAX:g}"
    elif field == "scale":
        lo, hi = COMPASS_SCALE_RANGE
        if not (v == 0.0 or lo <= v <= hi):
            return f"0 or {lo:.3f}..{hi:g}"
    elif field == "orient":
        if not (v == int(v) and is_valid_rotation(int(v))):
            return "a rotation 0..43, 101 or 102"
    elif field == "external" and v not in _EXTERNAL_VALUES:
        return "0, 1 or 2"
    return None


def _limit_of(name: str, v: float, merged: Mapping[str, float]) -> str | None:
    """The limit ``v`` violates (text), or None."""
    hit = _INDEX.get(name)
    if hit is None:
        return None
    kind, k, field = hit
    if not math.isfinite(v):
        return "finite values"
    if kind == "compass":
        return _compass_limit(name, v, k, field, merged)
    if kind == "accel" and field == "ofs" and not abs(v) <= ACCEL_OFFSET_MAX_MPS2:
        return f"|offset| <= {ACCEL_OFFSET_MAX_MPS2:g} m/s^2"
    if kind == "accel" and field == "scale" and not ACCEL_SCALE_RANGE[0] <= v <= ACCEL_SCALE_RANGE[1]:
        return f"{ACCEL_SCALE_RANGE[0]:g}..{ACCEL_SCALE_RANGE[1]:g}"
    if field == "orientation" and not (v == int(v) and is_valid_rotation(int(v))):
        return "a rotation 0..43, 101 or 102"
    if field == "trim" and not abs(v) <= AHRS_TRIM_MAX_RAD:
        return f"|trim| <= {AHRS_TRIM_MAX_RAD:.4f} rad (10 deg)"
    if field == "custom" and not abs(v) <= CUSTOM_ANGLE_MAX_DEG:
        return f"|angle| <= {CUSTOM_ANGLE_MAX_DEG:g} deg"
    if field == "offs_max" and not COMPASS_OFFS_MAX_RANGE[0] <= v <= COMPASS_OFFS_MAX_RANGE[1]:
        return f"{COMPASS_OFFS_MAX_RANGE[0]:g}..{COMPASS_OFFS_MAX_RANGE[1]:g}"
    return None


def check_limits(values: Mapping[str, float], vehicle: Mapping[str, float] | None = None) -> list[LimitViolation]:
    """The values in ``values`` that break an ArduPilot limit.

    Parameters
    ----------
    values : mapping of str to float
        Values about to be written. Names without a limit are not checked.
    vehicle : mapping of str to float, optional
        The vehicle's current values: the rest of a vector (offset length) and
        ``COMPASS_OFFS_MAX`` come from here when ``values`` does not hold them.

    Returns
    -------
    list of LimitViolation
        In the order of ``values``; empty when everything is within its limit.
    """
    merged = dict(vehicle or {})
    merged.update({k: float(v) for k, v in values.items()})
    out = []
    for name, value in values.items():
        limit = _limit_of(name, float(value), merged)
        if limit is not None:
            hit = sensor_of(name)
            out.append(LimitViolation(name, float(value), limit, hit[0] if hit else None))
    return out


def failing_kinds(values: Mapping[str, float], vehicle: Mapping[str, float] | None = None) -> set[str]:
    """Sensor kinds (``"compass"``, ``"accel"``) touched by ``values`` whose resulting calibration
    (``values`` over ``vehicle``) breaks a limit: these must not be force-saved."""
    merged = dict(vehicle or {})
    merged.update({k: float(v) for k, v in values.items()})
    touched = {s for s in map(sensor_of, values) if s is not None}
    bad: set[str] = set()
    for kind, k in touched:
        names = _sensor_names(kind, k)
        if check_limits({n: merged[n] for n in names if n in merged}, merged):
            bad.add(kind)
    return bad


def _sensor_names(kind: str, k: int) -> list[str]:
    return [n for n, (knd, inst, _) in _INDEX.items() if knd == kind and inst == k]


def related_names(names: Iterable[str]) -> list[str]:
    """What judging ``names`` needs from the vehicle besides themselves: every limit-checked name
    of each sensor they touch, ``COMPASS_OFFS_MAX``, and the sensors' device ids (and compass
    priorities)."""
    out: dict[str, None] = {COMPASS_OFFS_MAX: None}
    for hit in {s for s in map(sensor_of, names) if s is not None}:
        kind, k = hit
        out.update(dict.fromkeys(_sensor_names(kind, k)))
        if kind == "compass":
            cn = fw.compass_param_names(k)
            out.update(dict.fromkeys((cn["dev_id"], cn["prio_id"])))
        else:
            out[fw.accel_param_names(k)["id"]] = None
    return list(out)
