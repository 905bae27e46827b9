"""The self-contained HTML report of ``mavcal flight`` (issue 39, item 4): the verdict per compass
in words, the parameters to write, and per compass one figure of three panels:

* **field magnitude along the flight**: ``|B|`` as logged (the calibration and compensation in
  force) and as fitted (the fitted offsets and motor term), against the field's length;
* **field error against the driver** (the current, or the throttle): the field with the fitted
  offsets but no motor term, minus the Earth field seen in the body frame (``R^T B``, the
  attitude with the compass-independent yaw where the log has it), per axis, with the fitted
  interference ``-COMPASS_MOT · x`` as lines;
* **heading against the GSF yaw**: the compass's tilt-compensated heading minus the field's
  direction, by the EKF-GSF yaw estimator's attitude (``XKY0``, the yaw no compass enters), as
  logged and as fitted; without a converged GSF yaw the panel says so.

Figures are embedded as base64 PNGs (no external CSS, JavaScript, fonts or images). matplotlib
is optional (``pip install 'mavcal[plots]'``), imported only by :func:`write_flight_html`
through its object-oriented API with the Agg canvas.
"""
from __future__ import annotations

import base64
import html
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mavcal.autopilot import model_named
from mavcal.errors import UsageError
from mavcal.flight.reference import reference_at
from mavcal.flight.stage import CompassResult, FlightResult, in_force_driver, param_values
from mavcal.report.figures import figure_factory, png_bytes
from mavcal.sources.flight_series import FlightSeries

__all__ = ["CompassCurves", "compass_curves", "flight_page", "write_flight_html", "missing_dependencies"]

log = logging.getLogger(__name__)

_BEFORE, _AFTER, _FIELD = "#c62828", "#1565c0", "#424242"
_AXES = (("x", "#c62828"), ("y", "#2e7d32"), ("z", "#1565c0"))
_MAX_POINTS = 5000  # per plotted series (plain decimation beyond)
_CSS = """
body{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em;color:#212121}
h1{font-size:1.4em}h2{font-size:1.15em;border-bottom:1px solid #ccc;padding-bottom:.2em}
.wrong{color:#b71c1c;font-weight:bold}.fine{color:#1b5e20}
table{border-collapse:collapse;font-size:.88em;margin:.5em 0}
th,td{border:1px solid #ddd;padding:.25em .6em;text-align:right}th{background:#f5f5f5}
td.l,th.l{text-align:left}
figure{margin:1em 0}figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.88em;color:#424242}
"""


@dataclass(frozen=True)
class CompassCurves:
    """What the figure of one compass draws (time in s, fields in mGauss, headings in deg)."""

    time_s: np.ndarray
    norm_before_mgauss: np.ndarray
    norm_after_mgauss: np.ndarray
    field_norm_mgauss: float  # the World Magnetic Model's at the flight's place, else the fitted field's
    driver: np.ndarray  # at the compass's samples with the fitted delay, where the attitude is known
    error_mgauss: np.ndarray  # (n, 3) field without the motor term minus R^T B, those samples
    slope_per_unit: np.ndarray  # the fitted interference: -mot (mGauss per unit of the driver)
    heading_time_s: np.ndarray
    heading_before_deg: np.ndarray
    heading_after_deg: np.ndarray
    yaw_source: str  # the yaw of the error and heading panels: "gsf" or "ekf"


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def _heading_deg(R: np.ndarray, mag: np.ndarray, B: np.ndarray) -> np.ndarray:
    h = np.einsum("nij,nj->ni", R, mag)
    return _wrap_deg(np.degrees(np.arctan2(h[:, 1], h[:, 0]) - np.arctan2(B[1], B[0])))


def compass_curves(s: FlightSeries, r: FlightResult, c: CompassResult) -> CompassCurves:
    """The series of one compass's figure, from the flight and the stage's result."""
    cs = next(x for x in s.compasses if x.instance == c.instance)
    fit = c.fit
    assert fit is not None
    model = model_named(s.autopilot).flight()
    f = model.in_force(s.params, cs)
    a = model.as_applied(f, cs, s.params, *in_force_driver(s, model.motor_type(s.params)))
    dt, dx = (s.current_time_s, s.current_a) if r.driver_kind == "current" else (s.throttle_time_s, s.throttle)
    x = np.interp(cs.time_s - fit.delay_s, dt, dx) if len(dt) else np.zeros(len(cs.time_s))
    # the field with the fitted offsets and no motor term; with the fitted motor term
    bare = a.field_mgauss + (f.A @ (fit.ofs_mgauss - a.ofs_mgauss).T).T - a.motor_ofs_mgauss
    after = bare + x[:, None] * fit.mot_per_unit
    gsf = len(s.gsf_time_s) > 10
    ref = reference_at(s, cs.time_s, "gsf" if gsf else "ekf")
    k = ref.valid & cs.healthy
    B = fit.B_ned_mgauss
    err = bare[k] - np.einsum("nji,j->ni", ref.R[k], B)
    independent = ref.yaw_source == "gsf"
    hk = k if independent else np.zeros(len(k), dtype=bool)
    # the Earth field's length: the field model's where the flight's place is known, else the fitted one
    field = r.B0_ned_mgauss if r.field_source == "wmm" else B
    return CompassCurves(cs.time_s, np.linalg.norm(a.field_mgauss, axis=1), np.linalg.norm(after, axis=1),
                         float(np.linalg.norm(field)), x[k], err, -np.asarray(fit.mot_per_unit, float),
                         cs.time_s[hk], _heading_deg(ref.R[hk], a.field_mgauss[hk], ref.B0_ned_mgauss),
                         _heading_deg(ref.R[hk], after[hk], ref.B0_ned_mgauss), ref.yaw_source)


def _every(n: int) -> slice:
    return slice(None, None, max(1, int(np.ceil(n / _MAX_POINTS))))


def fig_compass(Figure, r: FlightResult, c: CompassResult, cv: CompassCurves):
    """One compass's three panels (see the module's notes)."""
    unit = "A" if r.driver_kind == "current" else "throttle (0..1)"
    fig = Figure(figsize=(15, 4.4), dpi=100, layout="constrained")
    ax_m, ax_e, ax_h = fig.subplots(1, 3)
    d = _every(len(cv.time_s))
    ax_m.plot(cv.time_s[d], cv.norm_before_mgauss[d], color=_BEFORE, lw=0.8, label="as logged")
    ax_m.plot(cv.time_s[d], cv.norm_after_mgauss[d], color=_AFTER, lw=0.8, label="as fitted")
    ax_m.axhline(cv.field_norm_mgauss, color=_FIELD, ls="--", lw=1.0,
                 label="Earth field (WMM)" if r.field_source == "wmm" else "Earth field (fitted)")
    ax_m.set_xlabel("time since boot (s)")
    ax_m.set_ylabel("|B| (mGauss)")
    ax_m.set_title("field magnitude along the flight", fontsize=10)
    ax_m.legend(fontsize=8, loc="best")
    e = _every(len(cv.driver))
    xs = np.linspace(float(cv.driver.min()), float(cv.driver.max()), 2) if len(cv.driver) else np.zeros(2)
    for j, (name, col) in enumerate(_AXES):
        ax_e.plot(cv.driver[e], cv.error_mgauss[e, j], ".", ms=2, color=col, alpha=0.35)
        ax_e.plot(xs, xs * cv.slope_per_unit[j], "-", color=col, lw=1.6,
                  label=f"{name}: {cv.slope_per_unit[j]:+.2f} mGauss/{'A' if r.driver_kind == 'current' else 'unit'}")
    ax_e.set_xlabel(f"{r.driver_kind} ({unit})")
    ax_e.set_ylabel("field error without the motor term (mGauss)")
    ax_e.set_title(f"field error against the {r.driver_kind}, the fitted interference as lines "
                   f"(yaw: {cv.yaw_source})", fontsize=10)
    ax_e.legend(fontsize=8, loc="best")
    if len(cv.heading_time_s):
        h = _every(len(cv.heading_time_s))
        ax_h.plot(cv.heading_time_s[h], cv.heading_before_deg[h], ".", ms=2, color=_BEFORE,
                  label=f"as logged ({_rms(cv.heading_before_deg):.1f} deg RMS)")
        ax_h.plot(cv.heading_time_s[h], cv.heading_after_deg[h], ".", ms=2, color=_AFTER,
                  label=f"as fitted ({_rms(cv.heading_after_deg):.1f} deg RMS)")
        ax_h.axhline(0.0, color=_FIELD, lw=0.8)
        ax_h.set_ylim(-180, 180)
        ax_h.legend(fontsize=8, loc="best")
    else:
        ax_h.text(0.5, 0.5, "no converged EKF-GSF yaw (XKY0) in this log:\nno compass-independent heading",
                  ha="center", va="center", transform=ax_h.transAxes, fontsize=9)
    ax_h.set_xlabel("time since boot (s)")
    ax_h.set_ylabel("heading minus the GSF yaw's (deg)")
    ax_h.set_title("heading against the compass-independent (GSF) yaw", fontsize=10)
    fig.suptitle(f"compass{c.instance}" + (" (WRONG in flight)" if c.verdict.wrong else ""), fontsize=11)
    return fig


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a * a))) if len(a) else float("nan")


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _v(a, fmt: str = "+.2f") -> str:
    return "(" + ", ".join(format(float(v), fmt) for v in a) + ")"


def _compass_rows(r: FlightResult) -> str:
    head = ("compass", "verdict", "interference % (left)", "COMPASS_MOT fit +- 95 %", "delay s",
            "heading vs GSF deg RMS (logged -> fitted)", "written")
    rows = ["<table><tr>" + "".join(f"<th class='l'>{_e(h)}</th>" for h in head) + "</tr>"]
    for c in r.compasses:
        v, f = c.verdict, c.fit
        assert f is not None
        what = (f"<span class='wrong'>WRONG in flight: {_e('; '.join(v.causes))}</span>" if v.wrong
                else f"<span class='fine'>{_e(v.level)}</span>")
        g = c.gsf_heading_err_deg
        hd = "-" if not np.isfinite(g[0]) else f"{g[0]:.1f} -> {g[1]:.1f}"
        rows.append(f"<tr><td class='l'>compass{c.instance}</td><td class='l'>{what}</td>"
                    f"<td>{v.interference_pct:.0f} ({v.interference_left_pct:.0f})</td>"
                    f"<td>{_v(f.mot_per_unit)} +- {_v(f.mot_bound95_per_unit, '.2f')}</td><td>{f.delay_s:+.2f}</td>"
                    f"<td>{hd}</td><td class='l'>{'yes' if v.accepted else _e('no: ' + v.not_written_because)}"
                    "</td></tr>")
    rows.append("</table>")
    return "".join(rows)


def flight_page(r: FlightResult, images: dict[int, bytes]) -> str:
    """The whole page: the header, the verdicts, the parameters, one figure per compass, warnings."""
    P = ["<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
         f"<title>mavcal flight: {_e(r.source)}</title><style>{_CSS}</style></head>",
         f"<body data-compasses='{len(r.compasses)}' data-figures='{len(images)}'>",
         f"<h1>mavcal flight: {_e(r.source)}</h1>",
         f"<p>Interference driver: {_e(r.driver_kind)}; rotation judged against: "
         + ("the EKF-GSF yaw (compass-independent)" if r.rotation_reference == "gsf"
            else "nothing (no compass-independent yaw in the log)")
         + f"; field: {_e(r.field_source)} ({', '.join(f'{v:.0f}' for v in r.B0_ned_mgauss)} mGauss NED).</p>",
         "<h2>Compasses</h2>", _compass_rows(r), "<ul>"]
    for c in r.compasses:
        P.append(f"<li>compass{c.instance}: {_e(c.verdict.summary)}"
                 + (f"; advice: {_e('; '.join(c.verdict.advice))}" if c.verdict.advice else "") + "</li>")
    P.append("</ul><h2>Parameters to write</h2>")
    params = param_values(r)
    P.append("<table><tr><th class='l'>name</th><th>value</th></tr>"
             + "".join(f"<tr><td class='l'>{_e(k)}</td><td>{v:.4g}</td></tr>" for k, v in params.items())
             + "</table>" if params else "<p>None: no compass accepted.</p>")
    P.append("<h2>Figures</h2>")
    for k, png in images.items():
        b64 = base64.b64encode(png).decode("ascii")
        P.append(f"<figure data-compass='{k}'><img alt='compass{k}: field magnitude, field error against the "
                 f"{_e(r.driver_kind)}, heading against the GSF yaw' src='data:image/png;base64,{b64}'>"
                 f"<figcaption>compass{k}: the field's magnitude along the flight as logged and as fitted; the field "
                 f"error (the fitted offsets, no motor term) against the {_e(r.driver_kind)} with the fitted "
                 "interference as lines; the heading against the compass-independent (EKF-GSF) yaw as logged and "
                 "as fitted.</figcaption></figure>")
    if r.warnings:
        P.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{_e(w)}</li>" for w in r.warnings) + "</ul>")
    P.append("</body></html>\n")
    return "\n".join(P)


def missing_dependencies() -> list[str]:
    """The optional packages the page needs that are not installed (checked before any work)."""
    import importlib.util

    return [] if importlib.util.find_spec("matplotlib") is not None else ["matplotlib"]


def write_flight_html(s: FlightSeries, r: FlightResult, path: str | Path) -> Path:
    """Write the page of ``r`` (the stage's result on the flight ``s``) to ``path``, atomically;
    :class:`UsageError` when matplotlib is missing or the file cannot be written."""
    Figure = figure_factory()

    images = {c.instance: png_bytes(fig_compass(Figure, r, c, compass_curves(s, r, c)))
              for c in r.compasses if c.fit is not None}
    from mavcal.errors import SourceError
    from mavcal.outputs import write_atomic

    path = Path(path)
    try:
        write_atomic(path, flight_page(r, images))
    except SourceError as exc:
        raise UsageError(f"cannot write the report: {exc}") from None
    log.info("HTML report written to %s", path)
    return path
