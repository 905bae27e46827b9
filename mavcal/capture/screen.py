"""The text of a capture status: one line (a log, a piped terminal) or one terminal screen.

Shared by the ``capture`` command and the MAVProxy module.
"""
from __future__ import annotations

from mavcal.capture.session import CaptureStatus, coverage_map
from mavcal.determined import determined

__all__ = ["status_line", "status_screen", "sensors_line"]


def _fmt(x: float | None, nd: int = 2) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def _deg(x: float | None, nd: int, kind: str) -> str:
    """A 95 % ``kind`` bound: "0.12 deg", "- deg" before a fit, "not determined" above its limit."""
    return f"{_fmt(x, nd)} deg" if x is None or determined(kind, x) else "not determined"


def status_line(st: CaptureStatus) -> str:
    """One line for a log or a piped terminal: intervals, bound, and the next pose in words.

    The next pose also comes as angles, ``(roll R pitch P yaw Y deg magnetic)``, so a
    program can follow it.
    """
    head = (f"{st.n_intervals} intervals, {'still' if st.still_now else 'moving'}, "
            f"heading {_deg(st.heading_95_deg, 2, 'heading')}")
    if st.done:
        return f"{head}: {'ABORTED: ' if st.aborted else 'done: '}{st.reason}"
    if st.next_pose is None:
        return f"{head}: {st.reason}"
    a = st.next_pose
    line = (f"{head}; next: {a.words} (roll {a.roll_deg:.4g} pitch {a.pitch_deg:.4g} yaw {a.yaw_deg:.4g} "
            f"deg magnetic)")
    if st.advice_for:
        line += f" for {st.advice_for}"
    if st.offer_finish_without:
        line += f"; {', '.join(st.offer_finish_without)} cannot reach the target: stop to finish without"
    return line


def sensors_line(st: CaptureStatus) -> str:
    """Every sensor's 95 % bound against its target, e.g. ``accel0 tilt 0.06/0.3 ok, compass1
    heading 0.81/0.5`` (``cannot`` when it cannot get there, ``dropped`` when finished without)."""
    def one(p) -> str:
        b = "-" if p.bound_deg is None else f"{p.bound_deg:.2f}" if determined(p.kind, p.bound_deg) else "undetermined"
        tag = (" dropped" if p.dropped else " ok" if p.met else " cannot" if p.blocked
               else " needs poses" if p.needs else "")
        return f"{p.sensor} {p.kind} {b}/{p.target_deg:g}{tag}"
    return ", ".join(one(p) for p in st.sensors)


def status_screen(st: CaptureStatus, target_deg: float | None = None) -> str:
    """A terminal screen of the capture state: still now?, intervals, coverage, bound, next pose."""
    lines = ["mavcal guided capture (Ctrl-C stops and keeps what was captured)", ""]
    lines.append(f"still now: {'yes' if st.still_now else 'no'}        intervals kept: {st.n_intervals}")
    tgt = f" (target {target_deg:g})" if target_deg is not None else ""
    lines.append(f"heading error bound 95 %: {_deg(st.heading_95_deg, 2, 'heading')}{tgt}    "
                 f"tilt: {_deg(st.tilt_95_deg, 3, 'tilt')}    model: {st.model or '-'}")
    if st.sensors:
        lines.append(f"every sensor's bound/target (deg): {sensors_line(st)}")
    if st.field_calibrated_mgauss is not None:
        raw = f" (raw reading {st.field_mgauss:.0f} mGauss)" if st.field_mgauss is not None else ""
        lines.append(f"field: {st.field_calibrated_mgauss:.0f} mGauss calibrated{raw}")
    elif st.field_mgauss is not None:
        lines.append(f"field: {st.field_mgauss:.0f} mGauss raw (not calibrated yet)")
    lines += ["", "gravity directions covered (body frame; columns: azimuth, rows: elevation):",
              coverage_map(st.gravity_dirs), ""]
    if st.done:
        lines.append(("ABORTED: " if st.aborted else "DONE: ") + st.reason)
    elif st.next_pose is not None:
        a = st.next_pose
        lines.append(f"NEXT POSE: {a.words}" + (f"   (for {st.advice_for})" if st.advice_for else ""))
        lines.append(f"           (roll {a.roll_deg:.0f}, pitch {a.pitch_deg:.0f}, yaw {a.yaw_deg:.0f} deg "
                     f"from magnetic north)")
        lines.append(st.reason)
    lines += [f"note: {m}" for m in st.messages]
    return "\n".join(lines)
