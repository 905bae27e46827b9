"""The report's figures (matplotlib's object-oriented API; ``Figure`` is handed in by
:func:`mavcal.report.html.write_html`, made by :func:`figure_factory`, the one place matplotlib is
imported, when a page is written; never pyplot).

* ``timeline``: readings as logged and the norm after the new calibration against time,
  the still intervals shaded (used green, unused orange) and numbered in a strip on top;
* ``magnitudes``: |a| and |B| per interval before and after;
* ``residuals``: per-interval model residuals in standard deviations of the mean;
* ``coverage``: the gravity direction of every interval on two equal-area hemispheres.
"""
from __future__ import annotations

import io

import numpy as np

from mavcal.report.numbers import G0, IntervalNumbers, corrected_after, instances, rms_deviation

#: Figures of the report, in page order; also the PNG file names (``NAME.png``) in ``png_dir``.
FIGURE_NAMES = ("timeline", "magnitudes", "residuals", "coverage")

USED_COLOUR = "#2e7d32"  # opaque span colours of the interval strip (tests look for them)
UNUSED_COLOUR = "#ef6c00"
_BEFORE = "#c62828"
_AFTER = "#1565c0"
_MAX_POINTS = 20000  # per plotted series in the timeline (plain decimation beyond)

def _decimate(series) -> tuple[np.ndarray, np.ndarray]:
    """Every ``step``-th time and value of a series (only those values computed when packed)."""
    t = series.time_s
    step = max(1, int(np.ceil(t.shape[0] / _MAX_POINTS)))
    return t[::step], np.asarray(series.values_at(slice(None, None, step)), float)


def fig_timeline(Figure, run) -> tuple[object, int]:
    """Timeline figure and the number of interval spans drawn in its strip."""
    ai, mi = instances(run)
    seg = run.segmentation
    used = set(run.intervals_used)
    fig = Figure(figsize=(14, 7.2), dpi=100, layout="constrained")
    gs = fig.add_gridspec(3, 1, height_ratios=[0.5, 3, 3])
    strip = fig.add_subplot(gs[0])
    ax_a = fig.add_subplot(gs[1], sharex=strip)
    ax_m = fig.add_subplot(gs[2], sharex=strip)
    n_spans = 0
    for k, iv in enumerate(seg.intervals):
        c = USED_COLOUR if k in used else UNUSED_COLOUR
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
        t, v = _decimate(s)
        for j, (lab, col) in enumerate(zip("xyz", ("#ef9a9a", "#a5d6a7", "#90caf9"))):
            ax.plot(t, v[:, j], lw=0.6, color=col, label=f"{lab} as logged")
        ax.plot(t, np.linalg.norm(v, axis=1), lw=1.0, color=_BEFORE, label="|v| as logged")
        if r is not None and len(r):
            tr, vr = _decimate(r)
            after = np.linalg.norm(corrected_after(run, sensor, vr), axis=1)
            ax.plot(tr, after, lw=1.0, color=_AFTER, ls="--", label="|v| new calibration")
        ax.axhline(target, color="k", lw=0.5, ls=":")
        ax.set_ylabel(f"{name} {inst} ({unit})")
        ax.legend(loc="lower right", fontsize=7, ncol=5, framealpha=0.8)
        ax.grid(alpha=0.3)
    ax_a.tick_params(labelbottom=False)
    ax_m.set_xlabel("time (s, log time base)")
    return fig, n_spans


def fig_magnitudes(Figure, st: IntervalNumbers):
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
            rms = rms_deviation(vals[st.used], target)
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


def fig_residuals(Figure, st: IntervalNumbers):
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


def fig_coverage(Figure, run):
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
                ax.plot(px, py, "o", ms=9, color=USED_COLOUR if u else UNUSED_COLOUR, mfc=USED_COLOUR if u else "none")
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


def png_bytes(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def figure_factory():
    """``Figure(**kw)``: a matplotlib figure on the Agg canvas (no pyplot, no display), for the
    report pages; :class:`mavcal.errors.UsageError` when matplotlib is not installed."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure as _Figure
    except ImportError:
        from mavcal.errors import UsageError

        raise UsageError("the HTML report needs matplotlib: pip install 'mavcal[plots]'") from None

    def Figure(**kw):
        fig = _Figure(**kw)
        FigureCanvasAgg(fig)
        return fig

    return Figure
