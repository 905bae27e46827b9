"""What a person looks at after a calibration: a self-contained HTML report and a short
terminal summary.

:func:`write_html` writes one HTML file per :class:`mavcal.pipeline.CalibrationRun` with
every figure embedded as a base64 PNG (no external CSS, JavaScript, fonts or images, so
the file can be mailed or archived alone), and optionally the same figures as PNG files:

* ``timeline``: accelerometer and compass readings as logged (components and norm) and
  the norm after the new calibration, against time, with the still intervals shaded
  (used ones green, unused ones orange) and numbered in a strip on top;
* ``magnitudes``: |a| and |B| per interval before (the corrected readings as logged) and
  after (the raw interval samples through the new ArduPilot parameters, the firmware's
  own equations of :mod:`mavcal.ardupilot.firmware`);
* ``residuals``: per-interval mean minus the model prediction ``K R_i g + b`` in
  standard deviations of the interval mean (``sqrt(diag(Sigma) / n_i)``);
* ``coverage``: the gravity direction of every interval on two equal-area hemispheres.

The numbers behind the per-interval figures come from :func:`interval_stats` (pure
numpy, no matplotlib). :func:`summary_text` is the terminal summary the CLI prints.

matplotlib is an optional dependency (``pip install 'mavcal[plots]'``); it is imported
only inside :func:`write_html`, through its object-oriented API with the Agg canvas, so
the caller's pyplot state and backend are left alone.
"""
from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

import mavcal
from mavcal.ardupilot import firmware as fw
from mavcal.errors import UsageError

log = logging.getLogger(__name__)

__all__ = ["write_html", "summary_text", "interval_stats", "IntervalStats", "FIGURE_NAMES"]

#: Figures of the report, in page order; also the PNG file names (``NAME.png``) in ``png_dir``.
FIGURE_NAMES = ("timeline", "magnitudes", "residuals", "coverage")

G0 = fw.GRAVITY_MSS
_USED = "#2e7d32"  # opaque span colours of the interval strip (tests look for them)
_UNUSED = "#ef6c00"
_BEFORE = "#c62828"
_AFTER = "#1565c0"
_MAX_POINTS = 20000  # per plotted series in the timeline (plain decimation beyond)


# --------------------------------------------------------------------------- numbers

@dataclass(frozen=True, eq=False)
class IntervalStats:
    """Per-interval numbers of the report (one entry per interval of the segmentation).

    Attributes
    ----------
    used : (N,) bool array
        Whether the interval went into the fit.
    accel_before, accel_before_std : (N,) arrays
        Mean and standard deviation of |a| (m/s^2) over the interval, readings as logged.
    accel_after, accel_after_std : (N,) arrays
        The same for the raw samples through the new INS_ACC* parameters.
    mag_before, mag_before_std, mag_after, mag_after_std : (N,) arrays
        |B| in mGauss, as logged and through the new COMPASS_* parameters.
    accel_resid_sigma, mag_resid_sigma : (N, 3) arrays
        Interval mean minus the model prediction ``gain @ R_i @ (gravity|field) + bias``
        per axis, in standard deviations of the mean, ``sqrt(noise_cov_jj / n_i)``
        (NaN for unused intervals).
    accel_resid_norm, mag_resid_norm : (N,) arrays
        The whitened length ``sqrt(r^T (noise_cov / n_i)^-1 r)`` (chi with 3 degrees of
        freedom if the model and noise level are right).
    g_target_mps2, field_target_mgauss : float
        What the corrected magnitudes should be: g0 and the field magnitude the compass
        was scaled to.

    Notes
    -----
    NaN wherever an interval holds no sample of the sensor instance.
    """

    used: np.ndarray
    accel_before: np.ndarray
    accel_before_std: np.ndarray
    accel_after: np.ndarray
    accel_after_std: np.ndarray
    mag_before: np.ndarray
    mag_before_std: np.ndarray
    mag_after: np.ndarray
    mag_after_std: np.ndarray
    accel_resid_sigma: np.ndarray
    mag_resid_sigma: np.ndarray
    accel_resid_norm: np.ndarray
    mag_resid_norm: np.ndarray
    g_target_mps2: float
    field_target_mgauss: float

    def __len__(self) -> int:
        return int(self.used.shape[0])


def _instances(run) -> Tuple[int, int]:
    return run.mapping.accel[0].instance, run.mapping.compass[0].instance


def _raw_mag_to_sensor(run, b_body: np.ndarray) -> np.ndarray:
    """Raw compass readings (body frame after the *old* orientation) -> sensor frame."""
    return np.asarray(b_body, float) @ run.mapping.compass[0].old.mount_matrix


def corrected_after(run, sensor: str, raw_values: np.ndarray) -> np.ndarray:
    """Raw readings of the run's instance through the new parameters (the firmware's equations).

    Parameters
    ----------
    run : CalibrationRun
    sensor : "accel" or "mag"
    raw_values : (n, 3) array
        Recovered raw readings: accel in the board frame (m/s^2), compass in the body
        frame after the old orientation (mGauss), as in ``run.raw``.

    Returns
    -------
    (n, 3) array, body frame, what ArduPilot would report with the new parameters.
    """
    if sensor == "accel":
        return fw.apply_accel(run.mapping.accel[0].new, raw_values)
    # the new COMPASS_ORIENT replaces the old rotation, so go back to the sensor's axes first
    return fw.apply_compass(run.mapping.compass[0].new, _raw_mag_to_sensor(run, raw_values), sensor_frame=True)


def _window(series, t0: float, t1: float, pad: float) -> np.ndarray:
    if series is None or len(series) == 0:
        return np.empty((0, 3))
    t = series.time_s
    i0, i1 = np.searchsorted(t, t0 - pad, "left"), np.searchsorted(t, t1 + pad, "right")
    return np.asarray(series.values[i0:i1], float)


def _norm_stats(v: np.ndarray) -> Tuple[float, float]:
    if v.shape[0] == 0:
        return float("nan"), float("nan")
    n = np.linalg.norm(v, axis=1)
    return float(np.mean(n)), float(np.std(n))


def interval_stats(run) -> IntervalStats:
    """Magnitudes before/after and whitened model residuals of every still interval.

    Parameters
    ----------
    run : mavcal.pipeline.CalibrationRun

    Returns
    -------
    IntervalStats
    """
    seg = run.segmentation
    cal = run.calibration
    ai, mi = _instances(run)
    N = len(seg.intervals)
    used_idx = list(run.intervals_used)
    used = np.zeros(N, bool)
    used[used_idx] = True
    la, lm = run.log.get("accel", ai), run.log.get("mag", mi)
    arr = {k: np.full(N, np.nan) for k in ("ab", "abs", "aa", "aas", "mb", "mbs", "ma", "mas")}
    for k, iv in enumerate(seg.intervals):
        pad = 0.5 * iv.sample_period_s + 1e-6
        arr["ab"][k], arr["abs"][k] = _norm_stats(_window(la, iv.start_s, iv.end_s, pad))
        arr["mb"][k], arr["mbs"][k] = _norm_stats(_window(lm, iv.start_s, iv.end_s, pad))
        ra = iv.accel_mps2.get(ai)
        if ra is not None and ra.shape[0]:
            arr["aa"][k], arr["aas"][k] = _norm_stats(corrected_after(run, "accel", ra))
        rm = iv.mag_mgauss.get(mi)
        if rm is not None and rm.shape[0]:
            arr["ma"][k], arr["mas"][k] = _norm_stats(corrected_after(run, "mag", rm))

    res = {"a": np.full((N, 3), np.nan), "m": np.full((N, 3), np.nan)}
    rn = {"a": np.full(N, np.nan), "m": np.full(N, np.nan)}
    R = np.asarray(cal.orientations)
    for j, k in enumerate(used_idx[: R.shape[0]]):
        iv = seg.intervals[k]
        for key, samples, model, ref in (("a", iv.accel_mps2[ai], cal.accel, cal.gravity),
                                         ("m", iv.mag_mgauss[mi], cal.mag, cal.field)):
            n = samples.shape[0]
            r = samples.mean(0) - (model.gain @ R[j] @ ref + model.bias)
            C = np.asarray(model.noise_cov, float) / n
            res[key][k] = r / np.sqrt(np.diag(C))
            try:
                rn[key][k] = float(np.sqrt(max(r @ np.linalg.solve(C, r), 0.0)))
            except np.linalg.LinAlgError:
                rn[key][k] = float("nan")
    return IntervalStats(used=used, accel_before=arr["ab"], accel_before_std=arr["abs"], accel_after=arr["aa"],
                         accel_after_std=arr["aas"], mag_before=arr["mb"], mag_before_std=arr["mbs"],
                         mag_after=arr["ma"], mag_after_std=arr["mas"], accel_resid_sigma=res["a"],
                         mag_resid_sigma=res["m"], accel_resid_norm=rn["a"], mag_resid_norm=rn["m"],
                         g_target_mps2=G0, field_target_mgauss=float(run.mapping.compass[0].field_mgauss))


def _rms_dev(x: np.ndarray, target: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean((x - target) ** 2))) if x.size else float("nan")


# --------------------------------------------------------------------------- text

def _fmt(v: Optional[float]) -> str:
    from mavcal.ardupilot.paramfile import format_param_value

    if v is None:
        return "-"
    try:
        return format_param_value(v)
    except Exception:  # non-finite
        return str(v)


def _changed(old: Optional[float], new: float) -> bool:
    return old is None or np.float32(old) != np.float32(new)


def _param_rows(run) -> List[Tuple[str, Optional[float], float, bool]]:
    return [(n, run.mapping.old.get(n), float(v), _changed(run.mapping.old.get(n), v))
            for n, v in sorted(run.mapping.new.items())]


def _group_vectors(rows):
    """Merge NAME_X/_Y/_Z rows into one (NAME_{X,Y,Z}) row: (label, olds, news, any changed)."""
    out, i = [], 0
    while i < len(rows):
        n = rows[i][0]
        if n.endswith("_X") and i + 2 < len(rows) and rows[i + 1][0] == n[:-1] + "Y" and rows[i + 2][0] == n[:-1] + "Z":
            trio = rows[i:i + 3]
            out.append((n[:-2] + "_XYZ", [r[1] for r in trio], [r[2] for r in trio], any(r[3] for r in trio)))
            i += 3
        else:
            out.append((n, [rows[i][1]], [rows[i][2]], rows[i][3]))
            i += 1
    return out


def _gate_failures_by_sensor(run) -> Dict[str, List[str]]:
    out: Dict[str, List[str]] = {}
    for g in run.gates.failures():
        out.setdefault(g.sensor, []).append(f"{g.name}: {g.reason or 'failed (limit ' + g.limit + ')'}")
    return out


def summary_text(run) -> str:
    """Short human summary of a run for a terminal.

    Parameters
    ----------
    run : mavcal.pipeline.CalibrationRun

    Returns
    -------
    str
        A few lines: intervals, model, the 95 % heading and tilt error bounds, the
        parameter table old -> new (changed values marked ``*``), the verdict of the
        quality gates with the reasons per sensor, and the warnings.
    """
    q = run.quality
    cal = run.calibration
    seg = run.segmentation
    cm = run.mapping.compass[0]
    am = run.mapping.accel[0]
    L = [f"{run.source}: {len(run.intervals_used)} of {len(seg.intervals)} still intervals used, "
         f"{seg.coverage.n_orientations} distinct orientations (coverage {seg.coverage.status})",
         f"model: {cal.model} - {cal.model_reason}" if cal.model_reason else f"model: {cal.model}",
         f"heading error <= {q.heading_95_deg:.3f} deg, tilt error <= {q.tilt_95_deg:.3f} deg "
         f"(95 % confidence, over the flight envelope)",
         f"held-out error: accel {q.holdout_accel_mps2:.4f} m/s^2, compass {q.holdout_mag_mgauss:.2f} mGauss; "
         f"fit chi2/dof {q.chi2_dof:.2f}",
         f"accel {am.instance}: cross-axis terms ArduPilot cannot hold cause up to {am.dropped_tilt_deg:.3f} deg tilt",
         f"compass {cm.instance}: {cm.orientation_note}; field {cm.field_mgauss:.0f} mGauss ({cm.field_source})"]
    rows = _param_rows(run)
    if rows:
        grouped = _group_vectors(rows)
        w = max(len(g[0]) for g in grouped)
        L.append(f"  {'PARAMETER':<{w}}  OLD -> NEW   (* changed)")
        for name, olds, news, ch in grouped:
            if len(news) == 1:
                L.append(f"  {name:<{w}}  {_fmt(olds[0])} -> {_fmt(news[0])}{'  *' if ch else ''}")
            else:
                L.append(f"  {name:<{w}}  ({', '.join(_fmt(o) for o in olds)}) -> "
                         f"({', '.join(_fmt(v) for v in news)}){'  *' if ch else ''}")
        n_ch = sum(r[3] for r in rows)
        L.append(f"  ({n_ch} of {len(rows)} parameters change; _X/_Y/_Z shown together)")
    fails = _gate_failures_by_sensor(run)
    if fails:
        L.append("REJECTED by the quality gates:")
        for sensor, why in fails.items():
            L += [f"  {sensor} {w_}" for w_ in why]
    else:
        L.append("ACCEPTED: all quality gates passed")
    if run.mapping.reboot_required:
        L.append("reboot needed after writing (custom orientation)")
    L += [f"warning: {m}" for m in run.warnings]
    return "\n".join(L)


# --------------------------------------------------------------------------- figures

def _decimate(t: np.ndarray, v: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    step = max(1, int(np.ceil(t.shape[0] / _MAX_POINTS)))
    return t[::step], v[::step]


def _fig_timeline(Figure, run) -> Tuple[object, int]:
    """Timeline figure and the number of interval spans drawn in its strip."""
    ai, mi = _instances(run)
    seg = run.segmentation
    used = set(run.intervals_used)
    fig = Figure(figsize=(14, 7.2), dpi=100, layout="constrained")
    gs = fig.add_gridspec(3, 1, height_ratios=[0.5, 3, 3])
    strip = fig.add_subplot(gs[0])
    ax_a = fig.add_subplot(gs[1], sharex=strip)
    ax_m = fig.add_subplot(gs[2], sharex=strip)
    n_spans = 0
    for k, iv in enumerate(seg.intervals):
        c = _USED if k in used else _UNUSED
        strip.axvspan(iv.start_s, iv.end_s, ymin=0.0, ymax=0.55, color=c, lw=0, gid=f"interval-{k}")
        n_spans += 1
        strip.text(0.5 * (iv.start_s + iv.end_s), 0.78, str(k), ha="center", va="center", fontsize=7)
        for ax in (ax_a, ax_m):
            ax.axvspan(iv.start_s, iv.end_s, color=c, alpha=0.15, lw=0)
    strip.set_ylim(0, 1)
    strip.set_yticks([])
    strip.tick_params(labelbottom=False)
    strip.set_title(f"{run.source}: {len(seg.intervals)} still intervals "
                    f"({len(used)} used = green, {len(seg.intervals) - len(used)} unused = orange)", fontsize=10)
    for ax, sensor, inst, unit, target, name in (
            (ax_a, "accel", ai, "m/s$^2$", G0, "accelerometer"),
            (ax_m, "mag", mi, "mGauss", float(run.mapping.compass[0].field_mgauss), "compass")):
        s = run.log.get(sensor, inst)
        r = run.raw.get(sensor, inst)
        if s is None or len(s) == 0:
            ax.text(0.5, 0.5, f"no {name} {inst} data", transform=ax.transAxes, ha="center")
            continue
        t, v = _decimate(s.time_s, np.asarray(s.values, float))
        for j, (lab, col) in enumerate(zip("xyz", ("#ef9a9a", "#a5d6a7", "#90caf9"))):
            ax.plot(t, v[:, j], lw=0.6, color=col, label=f"{lab} as logged")
        ax.plot(t, np.linalg.norm(v, axis=1), lw=1.0, color=_BEFORE, label="|v| as logged")
        if r is not None and len(r):
            tr, vr = _decimate(r.time_s, np.asarray(r.values, float))
            after = np.linalg.norm(corrected_after(run, sensor, vr), axis=1)
            ax.plot(tr, after, lw=1.0, color=_AFTER, ls="--", label="|v| new calibration")
        ax.axhline(target, color="k", lw=0.5, ls=":")
        ax.set_ylabel(f"{name} {inst} ({unit})")
        ax.legend(loc="lower right", fontsize=7, ncol=5, framealpha=0.8)
        ax.grid(alpha=0.3)
    ax_a.tick_params(labelbottom=False)
    ax_m.set_xlabel("time (s, log time base)")
    return fig, n_spans


def _fig_magnitudes(Figure, st: IntervalStats):
    fig = Figure(figsize=(14, 6), dpi=100, layout="constrained")
    axs = fig.subplots(2, 1, sharex=True)
    x = np.arange(len(st))
    for ax, b, bs, a, as_, target, lab, unit in (
            (axs[0], st.accel_before, st.accel_before_std, st.accel_after, st.accel_after_std, st.g_target_mps2,
             "|a|", "m/s$^2$"),
            (axs[1], st.mag_before, st.mag_before_std, st.mag_after, st.mag_after_std, st.field_target_mgauss,
             "|B|", "mGauss")):
        ax.axhline(target, color="k", lw=0.8, ls=":", label=f"target {target:.2f}")
        for vals, err, col, off, name in ((b, bs, _BEFORE, -0.12, "before (as logged)"),
                                          (a, as_, _AFTER, 0.12, "after (new parameters)")):
            rms = _rms_dev(vals[st.used], target)
            ax.errorbar(x[st.used] + off, vals[st.used], yerr=err[st.used], fmt="o", ms=5, color=col, capsize=2,
                        label=f"{name}: RMS deviation {rms:.3g}")
            if (~st.used).any():
                ax.errorbar(x[~st.used] + off, vals[~st.used], yerr=err[~st.used], fmt="o", ms=5, mfc="none",
                            color=col, capsize=2)
        ax.set_ylabel(f"{lab} ({unit})")
        ax.legend(fontsize=8, loc="best")
        ax.grid(alpha=0.3)
    axs[0].set_title("Gravity and field magnitude per still interval (hollow = interval not used in the fit)",
                     fontsize=10)
    axs[1].set_xlabel("interval")
    axs[1].set_xticks(x)
    return fig


def _fig_residuals(Figure, st: IntervalStats):
    fig = Figure(figsize=(14, 6), dpi=100, layout="constrained")
    axs = fig.subplots(2, 1, sharex=True)
    x = np.arange(len(st))
    w = 0.26
    for ax, r, rn, name in ((axs[0], st.accel_resid_sigma, st.accel_resid_norm, "accelerometer"),
                            (axs[1], st.mag_resid_sigma, st.mag_resid_norm, "compass")):
        for j, (lab, col) in enumerate(zip("xyz", ("#e53935", "#43a047", "#1e88e5"))):
            ax.bar(x + (j - 1) * w, np.nan_to_num(r[:, j]), width=w, color=col, label=lab)
        ax.plot(x, rn, "kD", ms=4, label="whitened norm")
        ax.axhline(0, color="k", lw=0.6)
        for s in (-2, 2):
            ax.axhline(s, color="k", lw=0.6, ls="--")
        ax.set_ylabel(f"{name}\n(std of the mean)")
        ax.legend(fontsize=8, ncol=4, loc="best")
        ax.grid(alpha=0.3, axis="y")
    axs[0].set_title("Interval mean minus model prediction K R_i g + b, in standard deviations of the mean "
                     "(dashed: +-2)", fontsize=10)
    axs[1].set_xlabel("interval")
    axs[1].set_xticks(x)
    return fig


def _lambert(d: np.ndarray, up: bool) -> np.ndarray:
    """Lambert azimuthal equal-area projection of unit vectors about +z (up) or -z."""
    z = d[:, 2] if up else -d[:, 2]
    k = np.sqrt(2.0 / np.maximum(1.0 + z, 1e-9))
    return np.column_stack([d[:, 1] * k, -d[:, 0] * k])  # screen: right = +y, up = -x


def _fig_coverage(Figure, run):
    seg = run.segmentation
    used = set(run.intervals_used)
    dirs = np.array([iv.gravity_dir for iv in seg.intervals]).reshape(-1, 3)
    fig = Figure(figsize=(11, 5.6), dpi=100, layout="constrained")
    axs = fig.subplots(1, 2)
    rim = np.sqrt(2.0)
    th = np.linspace(0, 2 * np.pi, 200)
    for ax, up, title in ((axs[0], True, "gravity towards +z: right side up"),
                          (axs[1], False, "gravity towards -z: upside down")):
        for deg in (30, 60, 90):
            r = 2 * np.sin(np.radians(deg) / 2)
            ax.plot(r * np.cos(th), r * np.sin(th), color="k" if deg == 90 else "#bdbdbd", lw=0.8 if deg == 90 else 0.5)
        ax.plot([-rim, rim], [0, 0], color="#bdbdbd", lw=0.5)
        ax.plot([0, 0], [-rim, rim], color="#bdbdbd", lw=0.5)
        for (xx, yy, txt) in ((0, rim * 1.06, "nose up (-x)"), (0, -rim * 1.1, "nose down (+x)"),
                              (rim * 1.04, 0, "right\nside\ndown\n(+y)"), (-rim * 1.04, 0, "left\nside\ndown\n(-y)")):
            ax.text(xx, yy, txt, ha="center" if xx == 0 else ("left" if xx > 0 else "right"), va="center", fontsize=8)
        sel = [k for k in range(len(dirs)) if (dirs[k, 2] >= 0) == up]
        if sel:
            p = _lambert(dirs[sel], up)
            for (px, py), k in zip(p, sel):
                u = k in used
                ax.plot(px, py, "o", ms=9, color=_USED if u else _UNUSED, mfc=_USED if u else "none")
                ax.annotate(str(k), (px, py), xytext=(6, 4), textcoords="offset points", fontsize=8)
        ax.set_title(f"{title} ({len(sel)})", fontsize=10)
        ax.set_xlim(-rim * 1.45, rim * 1.45)
        ax.set_ylim(-rim * 1.25, rim * 1.2)
        ax.set_aspect("equal")
        ax.axis("off")
    cov = seg.coverage
    fig.suptitle(f"Coverage: {cov.n_intervals} intervals, {cov.n_orientations} distinct orientations, largest empty "
                 f"cap {cov.largest_empty_cap_deg:.0f} deg ({cov.status}); rings at 30/60/90 deg from the pole, "
                 "equal-area", fontsize=10)
    return fig


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


# --------------------------------------------------------------------------- html

_CSS = """
body{font-family:-apple-system,'Segoe UI',Roboto,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1450px;
color:#212121;padding:0 1em}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.15em;border-bottom:1px solid #ddd;padding-bottom:.2em;
margin-top:1.6em}
.meta{color:#616161;font-size:.9em}
.verdict{display:inline-block;padding:.25em .8em;border-radius:4px;font-weight:bold;color:#fff}
.ok{background:#2e7d32}.bad{background:#c62828}
table{border-collapse:collapse;font-size:.88em;margin:.5em 0}
th,td{border:1px solid #ddd;padding:.25em .6em;text-align:right}th{background:#f5f5f5}
td.l,th.l{text-align:left}
tr.changed td{background:#fff8e1}tr.changed td.name{font-weight:bold}
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


def _html(run, st: IntervalStats, images: Dict[str, bytes], n_spans: int) -> str:
    cal, q, seg = run.calibration, run.quality, run.segmentation
    am, cm = run.mapping.accel[0], run.mapping.compass[0]
    accepted = run.accepted
    n_int = len(seg.intervals)
    n_used = len(run.intervals_used)
    P: List[str] = []
    P.append("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
             f"<title>mavcal report: {_e(run.source)}</title><style>{_CSS}</style></head>")
    P.append(f"<body data-intervals='{n_int}' data-intervals-used='{n_used}' "
             f"data-accepted='{str(accepted).lower()}'>")
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    P.append(f"<h1>mavcal calibration report</h1><p class='meta'>{_e(run.source)} &middot; mavcal "
             f"{_e(mavcal.__version__)} &middot; generated {now}</p>")
    P.append(f"<p><span class='verdict {'ok' if accepted else 'bad'}'>"
             f"{'ACCEPTED' if accepted else 'REJECTED'}</span> "
             f"<span id='interval-count'>{n_int} still intervals found, {n_used} used</span>, "
             f"{seg.coverage.n_orientations} distinct orientations; heading error &le; "
             f"<b>{_num(q.heading_95_deg, '.3f')}&deg;</b>, tilt error &le; <b>{_num(q.tilt_95_deg, '.3f')}&deg;</b> "
             "(95 % confidence).</p>")

    # quality and model
    P.append("<h2>Quality and model</h2>")
    kv = [("heading error, 95 % bound (deg)", _num(q.heading_95_deg, ".4f")),
          ("tilt error, 95 % bound (deg)", _num(q.tilt_95_deg, ".4f")),
          ("heading / tilt error of the written parameters at the estimate (deg)",
           f"{_num(q.heading_nominal_deg, '.4f')} / {_num(q.tilt_nominal_deg, '.4f')}"),
          ("held-out error, accel (m/s^2) / compass (mGauss)",
           f"{_num(q.holdout_accel_mps2, '.4f')} / {_num(q.holdout_mag_mgauss, '.3f')}"),
          ("fit chi2 / dof", _num(q.chi2_dof, ".3f")),
          ("model", _e(cal.model)), ("why this model", _e(cal.model_reason or "-")),
          ("estimator", f"{_e(cal.method)}, {'converged' if cal.converged else 'NOT converged'}: {_e(cal.message)}"),
          ("field magnitude (mGauss)", f"{_num(cm.field_mgauss, '.1f')} ({_e(cm.field_source)})"),
          ("field dip (deg)", _num(cm.inclination_deg, ".2f") + (
              "" if cm.inclination_model_deg is None else f" (World Magnetic Model {_num(cm.inclination_model_deg, '.2f')})")),
          ("compass orientation", _e(cm.orientation_note))]
    P.append("<table class='kv'>" + "".join(f"<tr><td>{_e(k)}</td><td class='l'>{v}</td></tr>" for k, v in kv)
             + "</table>")

    # parameters
    rows, cls = [], []
    for n, o, v, ch in _param_rows(run):
        d = "-" if o is None else _num(v - float(o), "+.4g")
        rows.append([_e(n), _e(_fmt(o)), _e(_fmt(v)), d if ch else ""])
        cls.append("changed" if ch else "")
    n_ch = sum(1 for c in cls if c)
    P.append(f"<h2>Parameters: old &rarr; new</h2><p>{n_ch} of {len(rows)} parameters change (highlighted)."
             + (" <b>A reboot is needed after writing.</b>" if run.mapping.reboot_required else "") + "</p>")
    P.append(_table(["parameter", "old", "new", "change"], rows, cls))

    # dropped terms
    ca = np.asarray(am.cross_axis)
    P.append("<h2>What ArduPilot cannot hold (dropped terms)</h2><ul>"
             f"<li>accelerometer {am.instance} cross-axis terms (no off-diagonal INS_ACC parameters): largest "
             f"{_num(np.max(np.abs(ca - np.diag(np.diag(ca)))) if ca.size else float('nan'), '.2e')}, causing up to "
             f"{_num(am.dropped_tilt_deg, '.4f')} deg tilt and {_num(am.dropped_magnitude_mps2, '.4f')} m/s^2</li>"
             f"<li>compass {cm.instance} rotation left uncorrected: {_num(cm.residual_rotation_deg, '.3f')} deg "
             f"(estimated misalignment to the accelerometer {_num(cm.rotation_deg, '.3f')} deg)</li>"
             "<li>compass motor compensation: unchanged (still poses cannot observe it)</li></ul>")

    # figures
    captions = {
        "timeline": "Readings as logged (components and norm) and the norm with the new parameters, with the "
                    "still intervals shaded and numbered (green: used in the fit, orange: not used).",
        "magnitudes": "Gravity and field magnitude per interval: as logged (before) and the raw interval samples "
                      "through the new ArduPilot parameters (after); the dotted line is what they should read.",
        "residuals": "Model residual of every used interval per axis in standard deviations of the interval mean; "
                     "bars far beyond +-2 mean the vehicle moved or the model does not fit that pose.",
        "coverage": "Gravity direction of every interval in the body frame (equal-area projection of the two "
                    "hemispheres); a good calibration has poses spread over both.",
    }
    P.append("<h2>Figures</h2>")
    for name in FIGURE_NAMES:
        if name not in images:
            continue
        extra = f" data-shaded-spans='{n_spans}'" if name == "timeline" else ""
        b64 = base64.b64encode(images[name]).decode("ascii")
        P.append(f"<figure class='fig' id='fig-{name}'{extra}><img alt='{name}' "
                 f"src='data:image/png;base64,{b64}'><figcaption>{_e(captions[name])}</figcaption></figure>")

    # gates
    P.append("<h2>Quality gates</h2>")
    fails = _gate_failures_by_sensor(run)
    if fails:
        P.append("<p><b>Failed:</b></p><ul>" + "".join(
            f"<li><b>{_e(s)}</b>: " + "; ".join(_e(w) for w in why) + "</li>" for s, why in fails.items()) + "</ul>")
    else:
        P.append("<p>All gates passed.</p>")
    grows, gcls = [], []
    for g in run.gates.gates:
        grows.append([_e(g.sensor), _e(g.name), "pass" if g.ok else "<b>FAIL</b>", _num(g.value, ".4g"), _e(g.limit),
                      _e(g.reason)])
        gcls.append("" if g.ok else "fail")
    P.append(_table(["sensor", "gate", "result", "value", "limit", "reason"], grows, gcls, left=(0, 1, 4, 5)))

    # intervals
    P.append(f"<h2>Still intervals ({n_int})</h2>")
    irows, icls = [], []
    for k, iv in enumerate(seg.intervals):
        g = iv.gravity_dir
        irows.append([str(k), "yes" if st.used[k] else "no", _num(iv.start_s, ".2f"), _num(iv.end_s, ".2f"),
                      _num(iv.duration_s, ".2f"), str(iv.n_accel.get(am.instance, 0)), str(iv.n_mag.get(cm.instance, 0)),
                      f"({g[0]:+.2f}, {g[1]:+.2f}, {g[2]:+.2f})",
                      _num(st.accel_before[k], ".4f"), _num(st.accel_after[k], ".4f"),
                      _num(st.mag_before[k], ".1f"), _num(st.mag_after[k], ".1f"),
                      _num(st.accel_resid_norm[k], ".2f"), _num(st.mag_resid_norm[k], ".2f")])
        icls.append("" if st.used[k] else "fail")
    P.append(_table(["#", "used", "start (s)", "end (s)", "duration (s)", "accel samples", "mag samples",
                     "gravity dir (FRD)", "|a| before", "|a| after", "|B| before", "|B| after",
                     "accel resid (sigma)", "mag resid (sigma)"], irows, icls, left=()))

    # coverage, notes, warnings
    msgs = list(seg.coverage.messages)
    P.append("<h2>Coverage, notes and warnings</h2>")
    P.append(f"<p>Coverage: {_e(seg.coverage.status)}, largest empty cap "
             f"{_num(seg.coverage.largest_empty_cap_deg, '.0f')} deg.</p>")
    if msgs:
        P.append("<ul>" + "".join(f"<li>{_e(m)}</li>" for m in msgs) + "</ul>")
    if run.mapping.notes:
        P.append("<p>Notes:</p><ul>" + "".join(f"<li>{_e(m)}</li>" for m in run.mapping.notes) + "</ul>")
    if run.warnings:
        P.append("<p>Warnings:</p><ul class='warnings'>" + "".join(f"<li>{_e(m)}</li>" for m in run.warnings)
                 + "</ul>")
    else:
        P.append("<p>No warnings.</p>")
    P.append("</body></html>\n")
    return "\n".join(P)


def write_html(run, path, *, png_dir=None) -> Path:
    """Write the self-contained HTML report of a calibration run.

    Parameters
    ----------
    run : mavcal.pipeline.CalibrationRun
    path : str or path-like
        The HTML file to write (its directory must exist).
    png_dir : str or path-like, optional
        Also write every figure there as ``NAME.png`` (see :data:`FIGURE_NAMES`); the
        directory is created if needed.

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
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure as _Figure
    except ImportError:
        raise UsageError("the HTML report needs matplotlib: pip install 'mavcal[plots]'") from None

    def Figure(**kw):
        fig = _Figure(**kw)
        FigureCanvasAgg(fig)
        return fig

    path = Path(path)
    st = interval_stats(run)
    fig_t, n_spans = _fig_timeline(Figure, run)
    figs = {"timeline": fig_t, "magnitudes": _fig_magnitudes(Figure, st), "residuals": _fig_residuals(Figure, st),
            "coverage": _fig_coverage(Figure, run)}
    images = {name: _png(fig) for name, fig in figs.items()}
    try:
        if png_dir is not None:
            d = Path(png_dir)
            d.mkdir(parents=True, exist_ok=True)
            for name, data in images.items():
                (d / f"{name}.png").write_bytes(data)
            log.info("figures written to %s", d)
        path.write_text(_html(run, st, images, n_spans), encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"cannot write the report: {exc.filename or path}: {exc.strerror or exc}") from None
    log.info("HTML report written to %s", path)
    return path
