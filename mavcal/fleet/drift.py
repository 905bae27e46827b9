"""Drift over time per vehicle, from a results table's rows.

A vehicle here is what the rows tell of it: system id, firmware, and the compass and IMU device
ids (with their instances) of the row. Its rows are put in time order (the log's start time
where the log has one, a tlog; else the log's name, which a fleet's downloads usually carry
the date in), and a vehicle is flagged when its accepted calibrations moved between flights
beyond the drift thresholds of :mod:`mavcal.batch`: the compass offsets (mGauss), the
accelerometer offsets (m/s^2) or a scale, from one accepted log's new values to the next's.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from mavcal.batch import DRIFT_ACCEL_OFS_MPS2, DRIFT_ACCEL_SCALE, DRIFT_COMPASS_MGAUSS

__all__ = ["VehicleDrift", "drift_over_time", "drift_text"]


@dataclass(frozen=True)
class VehicleDrift:
    """One vehicle's accepted calibrations in time order and the largest move between two in a row.

    ``steps``: per pair of consecutive accepted logs ``(from, to, compass mGauss, accel m/s^2,
    scale)`` (None where a value is missing); ``flagged``: a step beyond a threshold."""

    vehicle: str
    logs: tuple[str, ...]
    steps: tuple[tuple[str, str, float | None, float | None, float | None], ...]
    flagged: bool


def _key(r: dict) -> tuple:
    return (r.get("sysid"), r.get("firmware"), r.get("compass_instance"), r.get("compass_dev_id"),
            r.get("accel_instance"), r.get("accel_id"))


def _name(k: tuple) -> str:
    sysid, fw, ci, cid, ai, aid = k
    who = f"sys {sysid if sysid is not None else '?'}" + (f", {fw}" if fw else "")
    return f"{who}, compass{ci}({cid if cid is not None else '?'}), accel{ai}({aid if aid is not None else '?'})"


def _vec(r: dict, name: str, unit: str) -> tuple[float, float, float] | None:
    v = [r.get(f"{name}_new_{a}{unit}") for a in "xyz"]
    return None if any(x is None or (isinstance(x, float) and math.isnan(x)) for x in v) else (
        float(v[0]), float(v[1]), float(v[2]))


def _dist(a, b) -> float | None:
    return None if a is None or b is None else math.dist(a, b)


def _maxabs(a, b) -> float | None:
    return None if a is None or b is None else max(abs(x - y) for x, y in zip(a, b))


def drift_over_time(rows: Sequence[dict]) -> list[VehicleDrift]:
    """Per vehicle (module docstring) with two accepted logs or more: the moves between them."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r.get("ok") and r.get("accepted"):
            groups.setdefault(_key(r), []).append(r)
    out = []
    for k, rs in sorted(groups.items(), key=lambda kv: _name(kv[0])):
        rs = sorted(rs, key=lambda r: (r.get("log_start_utc") or "", r["source"]))
        steps = []
        flagged = False
        for a, b in zip(rs, rs[1:]):
            c = _dist(_vec(a, "compass_ofs", "_mgauss"), _vec(b, "compass_ofs", "_mgauss"))
            o = _dist(_vec(a, "accel_ofs", "_mps2"), _vec(b, "accel_ofs", "_mps2"))
            s = _maxabs(_vec(a, "accel_scale", ""), _vec(b, "accel_scale", ""))
            steps.append((a["source"], b["source"], c, o, s))
            flagged |= any(v is not None and v > t for v, t in ((c, DRIFT_COMPASS_MGAUSS), (o, DRIFT_ACCEL_OFS_MPS2),
                                                                (s, DRIFT_ACCEL_SCALE)))
        if steps:
            out.append(VehicleDrift(_name(k), tuple(r["source"] for r in rs), tuple(steps), flagged))
    return out


def _f(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def drift_text(rows: Sequence[dict]) -> str:
    """The drift-over-time summary: per vehicle with two accepted logs or more, whether its
    calibration moved between flights beyond the thresholds, and the largest move; "" if none."""
    vs = drift_over_time(rows)
    if not vs:
        return ""
    out = ["", f"drift over time (accepted logs of one vehicle in time order; moved: compass offsets > "
               f"{DRIFT_COMPASS_MGAUSS:g} mGauss, accel offsets > {DRIFT_ACCEL_OFS_MPS2:g} m/s^2 or scale > "
               f"{DRIFT_ACCEL_SCALE:g} between two flights):"]
    for v in vs:
        worst = max(v.steps, key=lambda s: max((x or 0.0) / t for x, t in zip(s[2:], (
            DRIFT_COMPASS_MGAUSS, DRIFT_ACCEL_OFS_MPS2, DRIFT_ACCEL_SCALE))))
        out.append(f"  {v.vehicle}: {len(v.logs)} logs, {'MOVED' if v.flagged else 'steady'}; largest step "
                   f"{worst[0].rsplit('/', 1)[-1]} -> {worst[1].rsplit('/', 1)[-1]}: compass {_f(worst[2], '.1f')} mG, "
                   f"accel {_f(worst[3], '.3f')} m/s^2, scale {_f(worst[4], '.4f')}")
    return "\n".join(out)
