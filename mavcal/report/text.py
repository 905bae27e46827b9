"""Text for people: the calibration summary, the parameter table and the outcome of a
write to the vehicle (the same words from ``mavcal apply/restore/calibrate/capture`` and
the MAVProxy module).

Every function returns a string (no printing); an empty string means nothing to show.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from mavcal.autopilot.paramfile import format_param_value
from mavcal.determined import bound_phrase, joint_unidentified

__all__ = ["summary_text", "holdout_text", "verdict_lines", "kept_lines", "next_step", "param_rows", "format_value",
           "gate_failures_by_sensor", "param_table", "written_rows",
           "rejection_notes", "plan_text", "gate_refusal_text", "write_done_text",
           "write_failed_text", "in_doubt_text", "writing_text", "forced_limits_text", "CLI_HINTS", "MAVPROXY_HINTS",
           "in_force_lines"]

#: how the ``mavcal`` command names the next steps (:func:`next_step`)
CLI_HINTS: dict[str, str] = {"force_hint": "--force", "write_hint": "--write, or load the .param file",
                             "write_hint_log": "--write --connect DEVICE, or load the .param file",
                             "only_hint": "--accel-only / --compass-only"}
#: how the MAVProxy module names them
MAVPROXY_HINTS: dict[str, str] = {"force_hint": "'mavcal set force 1'", "write_hint": "'mavcal write'",
                                  "only_hint": ""}


def format_value(v: float | None) -> str:
    if v is None:
        return "-"
    try:
        return format_param_value(v)
    except Exception:  # non-finite
        return str(v)


def _changed(old: float | None, new: float) -> bool:
    return old is None or np.float32(old) != np.float32(new)


def param_rows(run) -> list[tuple[str, float | None, float, bool]]:
    return [(n, run.mapping.old.get(n), float(v), _changed(run.mapping.old.get(n), v))
            for n, v in sorted(run.mapping.new.items())]


def rejection_notes(run) -> dict[str, str]:
    """Sensor -> why it is rejected, by the gates its verdict names (the data's, when the data
    cannot identify it), e.g. ``{"compass0": "field directions"}``; accepted sensors are absent."""
    out = {}
    for sensor, gs in run.gates.by_sensor().items():
        failed = [g for g in gs if not g.ok]
        shown = [g for g in failed if g.cause == "data"] or failed
        if shown:
            out[sensor] = ", ".join(dict.fromkeys(g.name for g in shown))
    return out


def written_rows(run, force: bool = False) -> list[tuple[str, float | None, float | None, bool, str]]:
    """Every parameter of the calibration as (name, old, new, changed, note): ``new`` and
    ``changed`` only for what will be written (:meth:`CalibrationRun.params_to_write`, the
    .param file and the write plan); a parameter left out has ``new`` None and the note
    ``not written (rejected: <sensor>: <gates>)``; a rejected sensor's value written with
    ``force`` has the note ``REJECTED (...), written with --force``."""
    write = run.params_to_write(force)
    notes = rejection_notes(run)
    sensor_of = {n: s for s, p in run.mapping.by_sensor().items() for n in p}
    out = []
    for n, v in sorted(run.mapping.new.items(), key=lambda nv: (nv[0] not in write, nv[0])):  # written first
        old = run.mapping.old.get(n)
        why = f"{sensor_of[n]}: {notes[sensor_of[n]]}" if sensor_of.get(n) in notes else ""
        if n in write:
            out.append((n, old, float(v), _changed(old, v), f"REJECTED ({why}), written anyway" if why else ""))
        else:
            out.append((n, old, None, False, f"not written (rejected: {why})" if why else "not written"))
    return out


def _group_vectors(rows):
    """Merge NAME_X/_Y/_Z rows into one (NAME_{X,Y,Z}) row: (label, olds, news, any changed, note)."""
    out, i = [], 0
    while i < len(rows):
        n = rows[i][0]
        if n.endswith("_X") and i + 2 < len(rows) and rows[i + 1][0] == n[:-1] + "Y" and rows[i + 2][0] == n[:-1] + "Z":
            trio = rows[i:i + 3]
            out.append((n[:-2] + "_XYZ", [r[1] for r in trio], [r[2] for r in trio], any(r[3] for r in trio),
                        trio[0][4] if len(rows[i]) > 4 else ""))
            i += 3
        else:
            out.append((n, [rows[i][1]], [rows[i][2]], rows[i][3], rows[i][4] if len(rows[i]) > 4 else ""))
            i += 1
    return out


def _table_lines(rows) -> list[str]:
    """The summary's parameter table: what will be written, old -> new (changed marked ``*``),
    a rejected sensor's parameters as "not written (rejected: ...)" without its values, and
    the count of what will be written."""
    grouped = _group_vectors(rows)
    w = max(len(g[0]) for g in grouped)
    L = [f"  {'PARAMETER':<{w}}  OLD -> NEW   (* changed)"]
    for name, olds, news, ch, note in grouped:
        if news[0] is None:
            L.append(f"  {name:<{w}}  {note}")
            continue
        old_t, new_t = (f"{format_value(olds[0])}", f"{format_value(news[0])}") if len(news) == 1 else (
            f"({', '.join(format_value(o) for o in olds)})", f"({', '.join(format_value(v) for v in news)})")
        L.append(f"  {name:<{w}}  {old_t} -> {new_t}{'  *' if ch else ''}{f'  {note}' if note else ''}")
    n_w = sum(r[2] is not None for r in rows)
    n_ch = sum(r[3] for r in rows)
    L.append(f"  ({n_w} parameter{'s' if n_w != 1 else ''} will be written, {n_ch} of them change"
             + (f"; {len(rows) - n_w} not written" if n_w < len(rows) else "") + "; _X/_Y/_Z shown together)")
    return L


def gate_failures_by_sensor(run) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for g in run.gates.failures():
        out.setdefault(g.sensor, []).append(f"{g.name}: {g.reason or 'failed (limit ' + g.limit + ')'}")
    return out


def verdict_lines(run) -> list[str]:
    """One line per sensor, accepted or REJECTED with its reasons (the first thing a user reads)."""
    out = []
    for v in run.verdicts:
        out.append(f"{v.sensor}: {'accepted' if v.accepted else 'REJECTED'}")
        out += [f"    {r}" for r in v.reasons]
    return out


def kept_lines(run) -> list[str]:
    """Per sensor, what poses within reach left: the parameters written, and every parameter kept
    at its current value (not written) with why and which pose would identify it; empty when
    nothing was kept (:attr:`mavcal.run.CalibrationRun.kept`)."""
    kept = getattr(run, "kept", ())
    if not kept:
        return []
    write = run.params_to_write()
    out = []
    for sensor, names in run.mapping.by_sensor().items():
        written = sorted(n for n in names if n in write)
        if written:
            out.append(f"{sensor}: written: {', '.join(written)}")
    by: dict[str, list] = {}
    for k in kept:
        by.setdefault(k.sensor, []).append(k)
    for sensor, ks in by.items():
        whole = not run.mapping.by_sensor().get(sensor)
        out.append(f"{sensor}: kept at its current calibration, nothing written" if whole else f"{sensor}: kept:")
        out += [f"    {k.what} kept: {k.why}; would need {k.pose}" for k in ks]
    return out


def next_step(run, *, force_hint: str = CLI_HINTS["force_hint"], write_hint: str = CLI_HINTS["write_hint"],
              only_hint: str = CLI_HINTS["only_hint"], write_hint_log: str | None = None) -> str:
    """What to do now, from the verdicts (the hints name the commands: :data:`CLI_HINTS`,
    :data:`MAVPROXY_HINTS`; an empty ``only_hint`` is left out). ``write_hint_log`` is how to
    write after a log rather than a live recording (the command line's ``--write`` then needs
    ``--connect``); None: ``write_hint`` (and, with the default ``write_hint``, the command
    line's)."""
    code = run.exit_code
    unknown = run.gates.not_known_sensors()  # never written, not even with --force: say how to get it in
    if unknown and code != 0:
        head = "write the accepted sensors' parameters; " if code == 7 else "nothing is written; "
        others = [x for x in run.gates.rejected_sensors() if x not in unknown]
        live = getattr(getattr(run, "log", None), "kind", None) == "live"
        how = ("connect again and let the parameter download finish" if live else
               "give the parameters in force with --params FILE, or record again with them (how: above)")
        return (f"next: {head}{', '.join(unknown)}: {how}"
                + (f"; {', '.join(others)}: fix the cause named above and record again" if others else ""))
    if code == 0:
        if write_hint_log is None and write_hint == CLI_HINTS["write_hint"]:
            write_hint_log = CLI_HINTS["write_hint_log"]
        live = getattr(getattr(run, "log", None), "kind", None) == "live"
        hint = write_hint if live or write_hint_log is None else write_hint_log
        return f"next: write the parameters ({hint}), then reboot the vehicle"
    if code == 7:
        bad = ", ".join(run.gates.rejected_sensors())
        only = f"{only_hint}, or " if only_hint else ""
        return (f"next: write the accepted sensors' parameters; {bad} keep their current values: fix the cause "
                f"named above and record again (or {only}{force_hint} to write them anyway)")
    return f"next: nothing is written; fix the causes named above and record again ({force_hint} writes anyway)"


def _field_flag(cm) -> str:
    """" -- IMPLAUSIBLE: ..." when a compass not scaled to a known field measures one Earth never has."""
    from mavcal.autopilot.gates import EARTH_FIELD_MGAUSS

    lo, hi = EARTH_FIELD_MGAUSS
    if cm.field_checked or lo <= cm.field_mgauss <= hi:
        return ""
    return f" -- IMPLAUSIBLE: Earth's field is {lo:.0f}-{hi:.0f} mGauss everywhere"


def _not_certified(run) -> str:
    """The joint fit is not certified as the optimum: what that means for what is written (its
    compass fails its "converged" gate; the accelerometer is judged, and written, on its own fit)."""
    a, m = run.mapping.accel[0].instance, run.mapping.compass[0].instance
    return (f"the joint fit of accel{a} + compass{m} is not certified as the global optimum: compass{m} is "
            f"rejected for it (gate converged), accel{a} is judged and written from its own fit")


def holdout_text(run) -> str:
    """The held-out error, or why it was not run (NaN from :func:`mavcal.judging.quality.holdout_errors`)."""
    q = run.quality
    if np.isfinite(q.holdout_accel_mps2) and np.isfinite(q.holdout_mag_mgauss):
        return f"held-out error: accel {q.holdout_accel_mps2:.4f} m/s^2, compass {q.holdout_mag_mgauss:.2f} mGauss"
    from mavcal.core.models import MODELS

    if run.calibration is None:
        return "held-out error: not run (no joint fit: accelerometers calibrated alone)"
    n, need = len(run.intervals_used), MODELS[run.calibration.model].min_intervals
    if n - 1 < need:
        why = f"leaving one of {n} intervals out leaves fewer than the {need} the {run.calibration.model} model needs"
    else:
        g = np.array([run.segmentation.intervals[k].gravity_dir for k in run.intervals_used])
        twice = ((g @ g.T) > np.cos(np.radians(30.0))).sum(axis=1) >= 2
        why = "disabled or no refit succeeded" if twice.any() else (
            "no pose was held twice: each interval is alone within 30 deg of its gravity direction, so leaving it "
            "out would measure extrapolation, not the fit")
    return f"held-out error: not run ({why})"


def in_force_lines(run) -> list[str]:
    """Where the calibration in force came from, when not (only) from the source itself (a
    parameter file given with ``--params``): ``calibration in force: --params v.param (accel0)``."""
    by: dict[str, list[str]] = {}
    for sensor, origin in run.raw.cal_origin.items():
        if origin and origin not in ("the recording's parameters", "the vehicle") and not origin.startswith("raw"):
            by.setdefault(origin, []).append(sensor)
    return [f"calibration in force: {o} ({', '.join(ss)})" for o, ss in by.items()]


def summary_text(run, *, hints: dict[str, str] | None = None, param_table: bool = True, force: bool = False) -> str:
    """Short human summary of a run for a terminal.

    Parameters
    ----------
    run : mavcal.pipeline.CalibrationRun
    hints : dict, optional
        How :func:`next_step` names the commands (default :data:`CLI_HINTS`).
    param_table : bool
        Include the parameter table (False when a write to the vehicle follows: its plan shows
        the same parameters against the vehicle's current values, so the table is not printed twice).
    force : bool
        The rejected sensors' parameters are written too (``--force``): the table shows them as such.

    Returns
    -------
    str
        A few lines: the verdict per sensor with its reasons and the next step first, then
        intervals, model, the 95 % heading and tilt error bounds, the parameter table of
        exactly what will be written (:func:`written_rows`), old -> new, changed values marked
        ``*``, a rejected sensor's parameters as "not written (rejected: ...)", and the warnings.
    """
    q = run.quality
    cal = run.calibration
    seg = run.segmentation
    n_ok = sum(v.accepted for v in run.verdicts)
    overall = {0: "ACCEPTED", 7: "PARTLY ACCEPTED"}.get(run.exit_code, "REJECTED")
    L = [f"{overall}: {run.source}: {n_ok} of {len(run.verdicts)} sensors accepted", *verdict_lines(run),
         *kept_lines(run), next_step(run, **(hints or {}))]
    within = ("poses within reach: enough for what is written, not for a full calibration"
              if cal is not None and cal.held else f"coverage {seg.coverage.status}")
    L += [f"{len(run.intervals_used)} of {len(seg.intervals)} still intervals used, "
          f"{seg.coverage.n_orientations} distinct orientations ({within})"]
    L += in_force_lines(run)
    why_a, why_m = joint_unidentified(run)  # numbers of a sensor the poses do not identify: not printed
    why = why_a or why_m
    if cal is None:
        L.append("model: accelerometers calibrated alone (no compass)")
    else:
        if why:  # the Wald statistics of a model the poses do not identify hold no digits
            L.append(f"model: {cal.model} (the choice of model is not determined: {why})")
        else:
            L.append(f"model: {cal.model} - {cal.model_reason}" if cal.model_reason else f"model: {cal.model}")
        if not cal.converged and not why and run.mapping.accel and run.mapping.compass:
            L.append(_not_certified(run))
    if cal is not None and run.mapping.accel and run.mapping.compass:
        L.append(f"joint fit of accel{run.mapping.accel[0].instance} + compass{run.mapping.compass[0].instance} "
                 "(each sensor's own numbers are in its verdict):")
    if why_a:
        L.append(f"heading and tilt errors not determined ({why_a})")
    else:
        envelope = "over the flight envelope"
        if run.kept:
            from mavcal.coverage import REACH_FLOWN_TILT_DEG

            envelope = (f"over the attitudes flown, tilts up to {REACH_FLOWN_TILT_DEG:g} deg; the kept values' "
                        "uncertainty counted")
        L.append(f"{bound_phrase('heading', q.heading_95_deg, why=why_m)}, {bound_phrase('tilt', q.tilt_95_deg)} "
                 f"(95 % confidence, {envelope})")
    if why:
        L.append("not determined either, for the same reason: the held-out error, fit chi2/dof"
                 + "".join(f", accel {am.instance}'s cross-axis terms" for am in run.mapping.accel[:1] if why_a)
                 + "".join(f", compass {cm.instance}'s misalignment and field" for cm in run.mapping.compass[:1]))
    else:
        L.append(f"{holdout_text(run)}; fit chi2/dof {q.chi2_dof:.2f}")
    L += [f"accel {am.instance}: cross-axis terms ArduPilot cannot hold cause up to {am.dropped_tilt_deg:.3f} deg tilt"
          for am in run.mapping.accel[:1] if not why_a]
    L += [f"compass {cm.instance}: {cm.orientation_note}; field {cm.field_mgauss:.0f} mGauss ({cm.field_source})"
          + _field_flag(cm) for cm in run.mapping.compass[:1] if not why]
    rows = written_rows(run, force) if param_table else []
    if rows:
        L += _table_lines(rows)
    if run.exit_code == 0:  # (the reasons of a rejection are said once, at the top)
        L.append("ACCEPTED: all quality gates passed")
    if run.mapping.reboot_required:
        why = "; ".join(dict.fromkeys(c.reboot_reason for c in run.mapping.compass if c.reboot_required))
        L.append("reboot needed after writing" + (f" ({why})" if why else ""))
    L += [f"warning: {m}" for m in run.warnings]
    return "\n".join(L)


# --------------------------------------------------------------------------- figures


# --------------------------------------------------------------------------- writes

def _status(r) -> str:
    if not r.changed:
        return "unchanged"
    if r.restored is True:
        return "restored"
    if r.restored is False:
        return "IN DOUBT"
    if r.ok:
        return "ok" if r.attempts else "to write"
    return "FAILED" if r.attempts else "not written"


def param_table(results: Iterable, *, show_status: bool = True) -> str:
    """An old -> new table of :class:`~mavcal.link.writer.ParamResult` (one line each, with
    a header; "" when there is none)."""
    rows = [(r.name, format_param_value(r.old), format_param_value(r.expected), _status(r)) for r in results]
    if not rows:
        return ""
    w = max(16, max(len(x[0]) for x in rows))
    wo = max(10, max(len(x[1]) for x in rows))
    wn = max(10, max(len(x[2]) for x in rows))
    out = [f"{'PARAMETER':<{w}}  {'OLD':>{wo}}     {'NEW':<{wn}}" + ("  STATUS" if show_status else "")]
    for name, old, new, status in rows:
        out.append(f"{name:<{w}}  {old:>{wo}}  -> {new:<{wn}}" + (f"  {status}" if show_status else ""))
    return "\n".join(out) + "\n"


def _lines(lines: Sequence[str], prefix: str) -> str:
    return "".join(f"{prefix}{x}\n" for x in lines)


def gate_refusal_text(run, override_hint: str, *, prefix: str = "") -> str:
    """Why nothing is written: the quality gates that failed, and how to override."""
    fails = "; ".join(f"{s} {why}" for s, why in rejection_notes(run).items())  # the verdicts' gates
    return _lines([f"nothing written: the calibration failed a quality gate ({fails}); {override_hint} to override"],
                  prefix)


def forced_limits_text(violations: Sequence[str], unsaved_kinds: Sequence[str], *, override: str = "--force",
                       prefix: str = "mavcal: ") -> str:
    """The loud warning of a write forced past ArduPilot's limits: one line per value
    (:attr:`mavcal.autopilot.limits.LimitViolation.message`) and the sensor kinds that will not
    be marked calibrated; "" when there is none."""
    lines = [f"WARNING: {override}: writing {v}" for v in violations]
    if unsaved_kinds:
        lines.append(f"WARNING: {'/'.join(unsaved_kinds)} will NOT be marked calibrated (no force-save)")
    return _lines(lines, prefix)


def plan_text(plan, *, dry_run: bool = False, confirm_hint: str | None = None, prefix: str = "") -> str:
    """The dry-run plan of a write (a :class:`~mavcal.link.writer.WriteReport`): the table,
    then "nothing to change", the dry-run count, or how to confirm (``confirm_hint``)."""
    n = len(plan.changed)
    text = param_table(plan.results)
    if n == 0:
        return text + _lines(["nothing to change: the vehicle already holds every value"], prefix)
    if dry_run:
        return text + _lines([f"dry run: {n} of {len(plan.results)} parameters would change; nothing written"],
                             prefix)
    if confirm_hint:
        return text + _lines([f"{n} parameter(s) would change; {confirm_hint}"], prefix)
    return text


def writing_text(n_changed: int, backup_path: str, *, prefix: str = "") -> str:
    """Said just before the writes start."""
    return _lines([f"writing {n_changed} parameter(s) (backup {backup_path})..."], prefix)


def write_done_text(report, *, prefix: str = "") -> str:
    """The outcome of a successful write (:class:`~mavcal.link.writer.WriteReport`)."""
    lines = [f"{report.message}; backup of the old values in {report.backup_path}"]
    if report.force_saved:
        lines.append(f"calibration marked saved ({', '.join(report.force_saved)}), device ids stored")
    if report.force_save_failed:
        failed = ", ".join(report.force_save_failed)
        lines.append(f"warning: the vehicle did not acknowledge the force-save of {failed}")
    if report.reboot_required:
        lines.append(f"reboot the vehicle for {', '.join(report.reboot_required)} to take effect")
    return param_table(report.changed) + _lines(lines, prefix)


def in_doubt_text(names: Sequence[str], backup_path: str, connect: str | None = None, *,
                  prefix: str = "") -> str:
    """The parameters whose value is unknown after a failed restore, and how to restore them."""
    cmd = f"mavcal restore {backup_path}" + (f" --connect {connect}" if connect else "")
    return (_lines(["parameters in doubt (value on the vehicle unknown):"], prefix)
            + "".join(f"  {n}\n" for n in names)
            + _lines([f"restore them when the vehicle answers again: {cmd}"], prefix))


def write_failed_text(exc, what: str, backup_path: str, connect: str | None = None, *,
                      prefix: str = "") -> str:
    """The outcome of a failed write: a :class:`~mavcal.errors.ParamWriteError` (everything
    restored) or a :class:`~mavcal.errors.RestoreFailedError` (parameters in doubt)."""
    from mavcal.errors import RestoreFailedError

    text = param_table(exc.report.results) if getattr(exc, "report", None) is not None else ""
    if isinstance(exc, RestoreFailedError):
        return text + in_doubt_text(exc.in_doubt, backup_path, connect, prefix=prefix)
    return text + _lines([f"{what} failed; every value written was restored (backup kept in {backup_path})"], prefix)
