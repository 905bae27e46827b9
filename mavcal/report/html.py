"""The self-contained HTML report of a calibration run.

:func:`write_html` writes one HTML file per :class:`mavcal.pipeline.CalibrationRun` with
every figure (:mod:`mavcal.report.figures`) embedded as a base64 PNG (no external CSS,
JavaScript, fonts or images, so the file can be mailed or archived alone), and optionally
the same figures as PNG files.

matplotlib is an optional dependency (``pip install 'mavcal[plots]'``); it is imported
only inside :func:`write_html`, through its object-oriented API with the Agg canvas, so
the caller's pyplot state and backend are left alone.
"""
from __future__ import annotations

import base64
import datetime as _dt
import html
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import mavcal
from mavcal.determined import bound_value_words, determined, joint_unidentified
from mavcal.errors import UsageError
from mavcal.report.figures import (
    FIGURE_NAMES,
    fig_coverage,
    fig_magnitudes,
    fig_residuals,
    fig_timeline,
    figure_factory,
    png_bytes,
)
from mavcal.report.numbers import IntervalNumbers, interval_numbers
from mavcal.report.text import format_value, gate_failures_by_sensor, holdout_text, written_rows

log = logging.getLogger(__name__)

__all__ = ["write_html", "html_page", "FIGURE_NAMES"]

_CAPTIONS = {
    "timeline": "Readings as logged (components and norm) and the norm with the new parameters, with the "
                "still intervals shaded and numbered (green: used in the fit, orange: not used).",
    "magnitudes": "Gravity and field magnitude per interval: as logged (before) and the raw interval samples "
                  "through the new ArduPilot parameters (after); the dotted line is what they should read.",
    "residuals": "Model residual of every used interval per axis in standard deviations of the interval mean; "
                 "bars far beyond +-2 mean the vehicle moved or the model does not fit that pose.",
    "coverage": "Gravity direction of every interval in the body frame (equal-area projection of the two "
                "hemispheres); a good calibration has poses spread over both.",
}

_CSS = """
body{font-family:-apple-system,'Segoe UI',Roboto,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1450px;
color:#212121;padding:0 1em}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.15em;border-bottom:1px solid #ddd;padding-bottom:.2em;
margin-top:1.6em}
.meta{color:#616161;font-size:.9em}
.verdict{display:inline-block;padding:.25em .8em;border-radius:4px;font-weight:bold;color:#fff}
.ok{background:#2e7d32}.bad{background:#c62828}.partial{background:#ef6c00}
table{border-collapse:collapse;font-size:.88em;margin:.5em 0}
th,td{border:1px solid #ddd;padding:.25em .6em;text-align:right}th{background:#f5f5f5}
td.l,th.l{text-align:left}
tr.changed td{background:#fff8e1}tr.changed td.name{font-weight:bold}tr.rejected td{color:#777}
tr.fail td{background:#ffebee}
.kv td:first-child{text-align:left;color:#616161}
figure{margin:1em 0}figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.88em;color:#424242}
ul{margin:.3em 0}
"""


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _num(v, fmt: str = ".4g") -> str:
    if v is None:
        return "-"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return _e(v)
    return "-" if not np.isfinite(f) else format(f, fmt)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], row_classes: Sequence[str] = (),
           left: Sequence[int] = (0,)) -> str:
    th = "".join(f"<th class='l'>{_e(h)}</th>" if i in left else f"<th>{_e(h)}</th>" for i, h in enumerate(header))
    out = [f"<table><tr>{th}</tr>"]
    for i, r in enumerate(rows):
        cls = row_classes[i] if i < len(row_classes) and row_classes[i] else ""
        tds = "".join(f"<td class='l{' name' if j == 0 else ''}'>{c}</td>" if j in left else f"<td>{c}</td>"
                      for j, c in enumerate(r))
        out.append(f"<tr class='{cls}'>{tds}</tr>" if cls else f"<tr>{tds}</tr>")
    out.append("</table>")
    return "".join(out)


#: exit code -> (the overall verdict, its CSS class): 7 = some sensors accepted, some rejected
_OVERALL = {0: ("ACCEPTED", "ok"), 7: ("PARTLY ACCEPTED", "partial"), 4: ("REJECTED", "bad")}


def _top(run) -> list[str]:
    seg = run.segmentation
    n_int, n_used, accepted = len(seg.intervals), len(run.intervals_used), run.accepted
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return ["<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            f"<title>mavcal report: {_e(run.source)}</title><style>{_CSS}</style></head>",
            f"<body data-intervals='{n_int}' data-intervals-used='{n_used}' "
            f"data-accepted='{str(accepted).lower()}'>",
            f"<h1>mavcal calibration report</h1><p class='meta'>{_e(run.source)} &middot; mavcal "
            f"{_e(mavcal.__version__)} &middot; generated {now}</p>",
            f"<p><span class='verdict {_OVERALL[run.exit_code][1]}'>{_OVERALL[run.exit_code][0]}</span> "
            f"<span id='interval-count'>{n_int} still intervals found, {n_used} used</span>, "
            f"{seg.coverage.n_orientations} distinct orientations; {_bounds(run, '.3f')} "
            "(95 % confidence).</p>"] + _verdicts(run)


def _bounds(run, fmt: str) -> str:
    """'heading error &le; <b>0.123&deg;</b>, tilt error ...', or 'not determined (why)'
    for a bound the data do not determine (:mod:`mavcal.determined`)."""
    q = run.quality
    why_a, why_m = joint_unidentified(run)
    out = []
    for kind, v, why in (("heading", q.heading_95_deg, why_a or why_m), ("tilt", q.tilt_95_deg, why_a)):
        if why or not determined(kind, v):
            out.append(f"{kind} error <b>{_e(bound_value_words(kind, v, fmt, why))}</b>")
        else:
            out.append(f"{kind} error &le; <b>{_num(v, fmt)}&deg;</b>")
    return ", ".join(out)


def _verdicts(run) -> list[str]:
    """The per-sensor verdicts with their reasons, then the next step: the report's first screen."""
    from mavcal.report.text import next_step

    items = []
    for v in run.verdicts:
        why = "".join(f"<li>{_e(r)}</li>" for r in v.reasons)
        items.append(f"<li data-sensor='{_e(v.sensor)}' data-sensor-accepted='{str(v.accepted).lower()}'>"
                     f"<span class='verdict {'ok' if v.accepted else 'bad'}'>"
                     f"{'accepted' if v.accepted else 'REJECTED'}</span> <b>{_e(v.sensor)}</b>"
                     + (f"<ul>{why}</ul>" if why else "") + "</li>")
    return ["<h2>Verdict per sensor</h2><ul id='verdicts'>" + "".join(items) + "</ul>"] + _kept(run) + [
            f"<p id='next-step'><b>{_e(next_step(run))}</b></p>"]


def _kept(run) -> list[str]:
    """What poses within reach left: the parameters written and those kept (not written), each
    with why and which pose would identify it."""
    if not run.kept:
        return []
    write = run.params_to_write()
    rows = [[_e(s), "written", _e(", ".join(sorted(n for n in p if n in write))), ""]
            for s, p in run.mapping.by_sensor().items() if any(n in write for n in p)]
    rows += [[_e(k.sensor), f"{_e(k.what)} kept (not written)", _e(k.why), _e(k.pose)] for k in run.kept]
    return ["<h2>Written and kept</h2><p>The poses were all within reach of a vehicle that is not turned over: "
            "what they cannot identify keeps its current value and is not written.</p>",
            "<div id='kept'>" + _table(["sensor", "parameter", "why", "what pose would identify it"], rows,
                                    left=(0, 1, 2, 3)) + "</div>"]


def _quality(run) -> list[str]:
    cal, q = run.calibration, run.quality
    cm = run.mapping.compass[0] if run.mapping.compass else None
    why_a, why_m = joint_unidentified(run)
    why = why_a or why_m
    kv = [("heading error, 95 % bound (deg)", _bound_cell("heading", q.heading_95_deg, why)),
          ("tilt error, 95 % bound (deg)", _bound_cell("tilt", q.tilt_95_deg, why_a)),
          ("heading / tilt error of the written parameters at the estimate (deg)",
           f"{_num(q.heading_nominal_deg, '.4f')} / {_num(q.tilt_nominal_deg, '.4f')}"),
          ("held-out error, accel (m/s^2) / compass (mGauss)",
           f"{_num(q.holdout_accel_mps2, '.4f')} / {_num(q.holdout_mag_mgauss, '.3f')}"
           if np.isfinite(q.holdout_accel_mps2) and np.isfinite(q.holdout_mag_mgauss)
           else _e(holdout_text(run).removeprefix("held-out error: "))),
          ("fit chi2 / dof", _num(q.chi2_dof, ".3f"))]
    if why:  # the numbers of a fit the poses do not identify are not shown as if they were estimates
        kv[2:] = [("errors at the estimate, held-out error, fit chi2 / dof", _e(f"not determined ({why})"))]
    if cal is not None:
        kv += [("model", _e(cal.model)),
               ("why this model", _e(f"not determined ({why})" if why else cal.model_reason or "-")),
               ("estimator",
                f"{_e(cal.method)}, {'converged' if cal.converged else 'NOT converged'}: {_e(cal.message)}")]
    if cm is not None and why:
        kv += [("field magnitude, dip, compass orientation", _e(f"not determined ({why})"))]
    elif cm is not None:
        dip = _num(cm.inclination_deg, ".2f") + ("" if cm.inclination_model_deg is None else
                                                 f" (World Magnetic Model {_num(cm.inclination_model_deg, '.2f')})")
        kv += [("field magnitude (mGauss)", f"{_num(cm.field_mgauss, '.1f')} ({_e(cm.field_source)})"),
               ("field dip (deg)", dip), ("compass orientation", _e(cm.orientation_note))]
    return ["<h2>Quality and model</h2>",
            "<table class='kv'>" + "".join(f"<tr><td>{_e(k)}</td><td class='l'>{v}</td></tr>" for k, v in kv)
            + "</table>"]


def _bound_cell(kind: str, v: float, why: str) -> str:
    return _e(bound_value_words(kind, v, ".4f", why)) if why or not determined(kind, v) else _num(v, ".4f")


def _parameters(run, force: bool = False) -> list[str]:
    """Exactly what will be written (:func:`mavcal.report.text.written_rows`); a rejected
    sensor's parameters say "not written (rejected: ...)" without its values (they are in the JSON)."""
    rows, cls = [], []
    written = written_rows(run, force)
    for n, o, v, ch, note in written:
        if v is None:
            rows.append([_e(n), _e(format_value(o)), _e(note), ""])
            cls.append("rejected")
            continue
        d = "-" if o is None else _num(v - float(o), "+.4g")
        rows.append([_e(n), _e(format_value(o)), _e(format_value(v) + (f" ({note})" if note else "")),
                     d if ch else ""])
        cls.append("changed" if ch else "")
    n_w = sum(1 for r in written if r[2] is not None)
    n_ch = sum(1 for c in cls if c == "changed")
    left = len(written) - n_w
    return [f"<h2>Parameters: old &rarr; new</h2><p id='param-count'>{n_w} parameter{'s' if n_w != 1 else ''} "
            f"will be written, {n_ch} of them change (highlighted)"
            + (f"; {left} of rejected sensors not written: they keep their current values" if left else "") + "."
            + (" <b>A reboot is needed after writing.</b>" if run.mapping.reboot_required else "") + "</p>",
            _table(["parameter", "old", "new", "change"], rows, cls)]


def _dropped(run) -> list[str]:
    items = []
    for am in run.mapping.accel[:1]:
        ca = np.asarray(am.cross_axis)
        largest = np.max(np.abs(ca - np.diag(np.diag(ca)))) if ca.size else float("nan")
        items.append(f"<li>accelerometer {am.instance} cross-axis terms (no off-diagonal INS_ACC parameters): "
                     f"largest {_num(largest, '.2e')}, causing up to {_num(am.dropped_tilt_deg, '.4f')} deg tilt "
                     f"and {_num(am.dropped_magnitude_mps2, '.4f')} m/s^2</li>")
    for cm in run.mapping.compass[:1]:
        items.append(f"<li>compass {cm.instance} rotation left uncorrected: {_num(cm.residual_rotation_deg, '.3f')} "
                     f"deg (estimated misalignment to the accelerometer {_num(cm.rotation_deg, '.3f')} deg)</li>")
    return (["<h2>What ArduPilot cannot hold (dropped terms)</h2><ul>"] + items
            + ["<li>compass motor compensation: unchanged (still poses cannot observe it)</li></ul>"])


def _figures(images: dict[str, bytes], n_spans: int) -> list[str]:
    P = ["<h2>Figures</h2>"]
    for name in FIGURE_NAMES:
        if name not in images:
            continue
        extra = f" data-shaded-spans='{n_spans}'" if name == "timeline" else ""
        b64 = base64.b64encode(images[name]).decode("ascii")
        P.append(f"<figure class='fig' id='fig-{name}'{extra}><img alt='{name}' "
                 f"src='data:image/png;base64,{b64}'><figcaption>{_e(_CAPTIONS[name])}</figcaption></figure>")
    return P


def _gates(run) -> list[str]:
    P = ["<h2>Quality gates</h2>"]
    fails = gate_failures_by_sensor(run)
    if fails:
        P.append("<p><b>Failed:</b></p><ul>" + "".join(
            f"<li><b>{_e(s)}</b>: " + "; ".join(_e(w) for w in why) + "</li>" for s, why in fails.items()) + "</ul>")
    else:
        P.append("<p>All gates passed.</p>")
    grows, gcls = [], []
    for g in run.gates.gates:
        result = "not run" if not g.ran else "pass" if g.ok else "<b>FAIL</b>"
        grows.append([_e(g.sensor), _e(g.name), result, _num(g.value, ".4g") if g.ran else "-", _e(g.limit),
                      _e(g.reason)])
        gcls.append("" if g.ok else "fail")
    P.append(_table(["sensor", "gate", "result", "value", "limit", "reason"], grows, gcls, left=(0, 1, 4, 5)))
    return P


def _intervals(run, st: IntervalNumbers) -> list[str]:
    seg = run.segmentation
    ai, mi = run.mapping.accel[0].instance, run.mapping.compass[0].instance
    irows, icls = [], []
    for k, iv in enumerate(seg.intervals):
        g = iv.gravity_dir
        irows.append([str(k), "yes" if st.used[k] else "no", _num(iv.start_s, ".2f"), _num(iv.end_s, ".2f"),
                      _num(iv.duration_s, ".2f"), str(iv.n_accel.get(ai, 0)), str(iv.n_mag.get(mi, 0)),
                      f"({g[0]:+.2f}, {g[1]:+.2f}, {g[2]:+.2f})",
                      _num(st.accel_before[k], ".4f"), _num(st.accel_after[k], ".4f"),
                      _num(st.mag_before[k], ".1f"), _num(st.mag_after[k], ".1f"),
                      _num(st.accel_resid_norm[k], ".2f"), _num(st.mag_resid_norm[k], ".2f")])
        icls.append("" if st.used[k] else "fail")
    return [f"<h2>Still intervals ({len(seg.intervals)})</h2>",
            _table(["#", "used", "start (s)", "end (s)", "duration (s)", "accel samples", "mag samples",
                    "gravity dir (FRD)", "|a| before", "|a| after", "|B| before", "|B| after",
                    "accel resid (sigma)", "mag resid (sigma)"], irows, icls, left=())]


def _notes(run) -> list[str]:
    seg = run.segmentation
    msgs = list(seg.coverage.messages)
    P = ["<h2>Coverage, notes and warnings</h2>",
         f"<p>Coverage: {_e(seg.coverage.status)}, largest empty cap "
         f"{_num(seg.coverage.largest_empty_cap_deg, '.0f')} deg.</p>"]
    if msgs:
        P.append("<ul>" + "".join(f"<li>{_e(m)}</li>" for m in msgs) + "</ul>")
    if run.mapping.notes:
        P.append("<p>Notes:</p><ul>" + "".join(f"<li>{_e(m)}</li>" for m in run.mapping.notes) + "</ul>")
    if run.warnings:
        P.append("<p>Warnings:</p><ul class='warnings'>" + "".join(f"<li>{_e(m)}</li>" for m in run.warnings)
                 + "</ul>")
    else:
        P.append("<p>No warnings.</p>")
    return P


def html_page(run, st: IntervalNumbers | None, images: dict[str, bytes], n_spans: int,
              force: bool = False) -> str:
    """The whole HTML page: verdict, quality, parameters (what will be written; ``force``: the
    rejected sensors' too), dropped terms, figures, gates, intervals, coverage/notes/warnings."""
    full = st is not None
    P = (_top(run) + _quality(run) + _parameters(run, force) + _dropped(run) + _figures(images, n_spans) + _gates(run)
         + (_intervals(run, st) if full else []) + _notes(run))
    P.append("</body></html>\n")
    return "\n".join(P)


def missing_dependencies() -> list[str]:
    """The optional packages the HTML report needs that are not installed (``[]`` when it can
    be written): checked before any work, so a run never fails at its end for want of them."""
    import importlib.util

    return [] if importlib.util.find_spec("matplotlib") is not None else ["matplotlib"]


def write_html(run, path, *, png_dir=None, force: bool = False) -> Path:
    """Write the self-contained HTML report of a calibration run.

    Parameters
    ----------
    run : mavcal.pipeline.CalibrationRun
    path : str or path-like
        The HTML file to write (its directory must exist).
    png_dir : str or path-like, optional
        Also write every figure there as ``NAME.png`` (see :data:`FIGURE_NAMES`); the
        directory is created if needed.
    force : bool
        The rejected sensors' parameters are written too (``--force``); else the table shows
        them as not written.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    mavcal.errors.UsageError
        matplotlib is not installed, or the file or directory cannot be written.

    Notes
    -----
    The body carries ``data-intervals`` (still intervals found) and
    ``data-intervals-used``; the timeline figure carries ``data-shaded-spans``, the number
    of interval spans actually drawn in it.
    """
    Figure = figure_factory()

    path = Path(path)
    if not (run.mapping.accel and run.mapping.compass and run.calibration is not None):
        # one kind of sensor only (--accel-only / --compass-only): verdicts, quality, parameters, gates
        _write(path, html_page(run, None, {}, 0, force))
        return path
    st = interval_numbers(run)
    fig_t, n_spans = fig_timeline(Figure, run)
    figs = {"timeline": fig_t, "magnitudes": fig_magnitudes(Figure, st), "residuals": fig_residuals(Figure, st),
            "coverage": fig_coverage(Figure, run)}
    images = {name: png_bytes(fig) for name, fig in figs.items()}
    try:
        if png_dir is not None:
            d = Path(png_dir)
            d.mkdir(parents=True, exist_ok=True)
            for name, data in images.items():
                (d / f"{name}.png").write_bytes(data)
            log.info("figures written to %s", d)
    except OSError as exc:
        raise UsageError(f"cannot write the report: {exc.filename or path}: {exc.strerror or exc}") from None
    _write(path, html_page(run, st, images, n_spans, force))
    log.info("HTML report written to %s", path)
    return path


def _write(path: Path, text: str) -> None:
    """The page, atomically (:func:`mavcal.outputs.write_atomic`); UsageError when it cannot be written."""
    from mavcal.errors import SourceError
    from mavcal.outputs import write_atomic

    try:
        write_atomic(path, text)
    except SourceError as exc:
        raise UsageError(f"cannot write the report: {exc}") from None
