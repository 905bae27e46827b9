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
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from mavcal.batch import DRIFT_ACCEL_OFS_MPS2, DRIFT_ACCEL_SCALE, DRIFT_COMPASS_MGAUSS

__all__ = ["VehicleDrift", "DriftLog", "drift_over_time", "drift_text", "drift_html", "line_plot"]


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


class DriftLog:
    """A fleet's rows reduced, one at a time, to what drift over time needs: per vehicle, each
    accepted log's name, start time and new offsets and scales (a tuple of about 200 bytes; a
    rejected or failed log is counted, not kept). The parent of a fleet run adds each row as it
    is written, so it never holds the rows themselves."""

    def __init__(self, rows: Iterable[dict] = ()) -> None:
        self.n_rows = 0
        self.vehicles: dict[tuple, list[tuple]] = {}
        for r in rows:
            self.add(r)

    def add(self, r: dict) -> None:
        self.n_rows += 1
        if r.get("ok") and r.get("accepted"):
            self.vehicles.setdefault(_key(r), []).append(
                (r.get("log_start_utc") or "", str(r["source"]), _vec(r, "compass_ofs", "_mgauss"),
                 _vec(r, "accel_ofs", "_mps2"), _vec(r, "accel_scale", "")))


def _log(rows: Iterable[dict] | DriftLog) -> DriftLog:
    return rows if isinstance(rows, DriftLog) else DriftLog(rows)


def _ordered(log: DriftLog) -> list[tuple[tuple, list[tuple]]]:
    return [(k, sorted(recs, key=lambda t: (t[0], t[1])))
            for k, recs in sorted(log.vehicles.items(), key=lambda kv: _name(kv[0]))]


def drift_over_time(rows: Iterable[dict] | DriftLog) -> list[VehicleDrift]:
    """Per vehicle (module docstring) with two accepted logs or more: the moves between them.
    ``rows``: a table's rows, or a :class:`DriftLog` of them."""
    out = []
    for k, rs in _ordered(_log(rows)):
        steps = []
        flagged = False
        for a, b in zip(rs, rs[1:]):
            c, o, s = _dist(a[2], b[2]), _dist(a[3], b[3]), _maxabs(a[4], b[4])
            steps.append((a[1], b[1], c, o, s))
            flagged |= any(v is not None and v > t for v, t in ((c, DRIFT_COMPASS_MGAUSS), (o, DRIFT_ACCEL_OFS_MPS2),
                                                                (s, DRIFT_ACCEL_SCALE)))
        if steps:
            out.append(VehicleDrift(_name(k), tuple(r[1] for r in rs), tuple(steps), flagged))
    return out


def _f(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def drift_text(rows: Iterable[dict] | DriftLog) -> str:
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


# --------------------------------------------------------------------------- HTML page

_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")  # x, y, z


def line_plot(title: str, unit: str, series: Sequence[Sequence[float | None] | None], labels: Sequence[str],
              names: Sequence[str] = ("x", "y", "z")) -> str:
    """An inline SVG line plot (no external asset) of up to three quantities (``names``) over the
    logs in time order: ``series[i]`` the values at log ``i`` (None: not known there)."""
    from html import escape

    w, h, left, right, top, bottom = 640, 220, 60, 20, 24, 40
    pts = [(i, v) for i, v in enumerate(series) if v is not None]
    vals = [x for _, v in pts for x in v if x is not None]
    if not vals:
        return ""
    lo, hi = min(vals), max(vals)
    if hi - lo < 1e-12:
        lo, hi = lo - 1.0, hi + 1.0
    n = max(len(series) - 1, 1)

    def px(i: float) -> float:
        return left + (w - left - right) * i / n

    def py(v: float) -> float:
        return top + (h - top - bottom) * (hi - v) / (hi - lo)

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" role="img" '
           f'aria-label="{escape(title)}">', f'<text x="{left}" y="16" font-size="13">{escape(title)} ({unit})</text>',
           f'<line x1="{left}" y1="{h - bottom}" x2="{w - right}" y2="{h - bottom}" stroke="#888"/>',
           f'<line x1="{left}" y1="{top}" x2="{left}" y2="{h - bottom}" stroke="#888"/>',
           f'<text x="4" y="{py(hi) + 4:.1f}" font-size="11">{hi:.3g}</text>',
           f'<text x="4" y="{py(lo) + 4:.1f}" font-size="11">{lo:.3g}</text>']
    for k, (colour, name) in enumerate(zip(_COLOURS, names)):
        mine = [(i, v[k]) for i, v in pts if k < len(v) and v[k] is not None]
        if not mine:
            continue
        line = " ".join(f"{px(i):.1f},{py(y):.1f}" for i, y in mine)
        out.append(f'<polyline fill="none" stroke="{colour}" stroke-width="2" points="{line}"/>')
        out += [f'<circle cx="{px(i):.1f}" cy="{py(y):.1f}" r="3" fill="{colour}"/>' for i, y in mine]
        out.append(f'<text x="{w - right - 60 * (len(names) - k)}" y="16" font-size="12" fill="{colour}">'
                   f'{escape(name)}</text>')
    for i, lab in enumerate(labels):
        out.append(f'<text x="{px(i):.1f}" y="{h - bottom + 14}" font-size="10" text-anchor="middle">'
                   f'<title>{escape(lab)}</title>{i + 1}</text>')  # the log's name on hovering its number
    out.append("</svg>")
    return "\n".join(out)


def drift_html(rows: Iterable[dict] | DriftLog) -> str:
    """A self-contained HTML page (no script, style or image from elsewhere): the drift summary,
    and per vehicle that moved, its compass and accelerometer offsets over its logs in time
    order (one inline SVG plot each) with the logs listed."""
    from html import escape

    log = _log(rows)
    vs = drift_over_time(log)
    recs = {k: {r[1]: r for r in rs} for k, rs in log.vehicles.items()}
    flagged = [v for v in vs if v.flagged]
    body = ["<h1>mavcal: drift over time</h1>",
            f"<p>{log.n_rows} logs, {len(vs)} vehicle(s) with two accepted logs or more, {len(flagged)} moved beyond "
            f"the thresholds (compass offsets {DRIFT_COMPASS_MGAUSS:g} mGauss, accel offsets "
            f"{DRIFT_ACCEL_OFS_MPS2:g} m/s², a scale {DRIFT_ACCEL_SCALE:g}, from one flight to the next).</p>"]
    if not vs:
        body.append("<p>No vehicle has two accepted logs yet: nothing to compare.</p>")
    body.append("<ul>" + "".join(f"<li>{escape(v.vehicle)}: {len(v.logs)} logs, "
                                  f"<b>{'MOVED' if v.flagged else 'steady'}</b></li>" for v in vs) + "</ul>")
    by_name = {_name(k): by for k, by in recs.items()}
    for v in flagged:
        logs = [by_name[v.vehicle][s] for s in v.logs]
        body.append(f"<h2>{escape(v.vehicle)}</h2>")
        body.append(line_plot("compass offsets", "mGauss", [r[2] for r in logs], v.logs))
        body.append(line_plot("accelerometer offsets", "m/s²", [r[3] for r in logs], v.logs))
        items = "".join(f"<li>{escape(r[0] or 'time not in the log')}: {escape(r[1])}</li>" for r in logs)
        steps = "".join(f"<tr><td>{escape(a.rsplit('/', 1)[-1])} → {escape(b.rsplit('/', 1)[-1])}</td>"
                        f"<td>{_f(c, '.1f')}</td><td>{_f(o, '.3f')}</td><td>{_f(s, '.4f')}</td></tr>"
                        for a, b, c, o, s in v.steps)
        body.append(f"<ol>{items}</ol><table><tr><th>step</th><th>compass mGauss</th><th>accel m/s²</th>"
                    f"<th>scale</th></tr>{steps}</table>")
    style = ("body{font-family:sans-serif;max-width:60em;margin:1em auto}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px}")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>mavcal: drift over time"
            f"</title><style>{style}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
