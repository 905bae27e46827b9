"""Many logs at once: calibrate a fleet's logs in parallel and show which vehicles drifted.

:func:`calibrate_many` runs :func:`mavcal.pipeline.calibrate_source` on every log, in
forked worker **processes** when ``jobs > 1`` (:class:`mavcal.workers.ForkPool`: never more
than the logs nor :func:`mavcal.workers.worker_limit`, and gone when this process is). A
worker handles one log at a time and sends back only a small :class:`BatchRow` (numbers and
strings, never the sample arrays), and is replaced after :data:`MAX_TASKS_PER_CHILD` logs, so
the memory of each worker stays that of one log. A log that cannot be calibrated gives a row
with the error message and the exit code the CLI would return for it alone (70 when its
worker process died, e.g. out of memory); it never stops the batch.

:func:`format_fleet_table` prints one line per log, grouped per vehicle (system id,
firmware and sensor device ids, as far as the log tells) and ordered by how much the
calibration changes (biggest first), with the lines above the drift thresholds flagged.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from mavcal.autopilot import model_for
from mavcal.determined import determined, joint_unidentified, unidentified
from mavcal.errors import EXIT_PARTIAL, GateError, MavcalError, UsageError
from mavcal.workers import ForkPool, Outcome

if TYPE_CHECKING:
    from mavcal.autopilot.gates import SensorVerdict

log = logging.getLogger(__name__)

__all__ = ["BatchRow", "calibrate_many", "calibrate_one", "format_fleet_table", "fleet_exit_code",
           "MAX_TASKS_PER_CHILD", "DRIFT_COMPASS_MGAUSS", "DRIFT_ACCEL_OFS_MPS2", "DRIFT_ACCEL_SCALE"]

#: Logs a worker process handles before it is replaced (bounds fragmentation growth).
MAX_TASKS_PER_CHILD = 8
#: A change of the compass offsets longer than this (mGauss) flags the log as drifted.
DRIFT_COMPASS_MGAUSS = 25.0
#: A change of the accelerometer offsets longer than this (m/s^2) flags it.
DRIFT_ACCEL_OFS_MPS2 = 0.1
#: A change of any accelerometer scale larger than this flags it.
DRIFT_ACCEL_SCALE = 0.01

Vec3 = tuple[float, float, float]
ProgressFn = Callable[[int, int, "BatchRow"], None]


@dataclass(frozen=True)
class BatchRow:
    """The summary of one log of a batch (small and picklable).

    Attributes
    ----------
    source : str
        The log as given.
    ok : bool
        The calibration ran (its result may still be rejected by the gates).
    error : str or None
        Why it did not run (``ok`` False).
    exit_code : int
        What ``mavcal calibrate`` would return for this log alone: 0 every sensor accepted,
        7 some rejected, 4 none accepted, else the :attr:`MavcalError.exit_code` of the error (1 for an
        unexpected one).
    sysid, firmware : vehicle identity from the log (None when unknown).
    compass_dev_id, accel_id : COMPASS_DEV_ID(n) / INS_ACC(n)_ID of the calibrated instances.
    accel_instance, compass_instance : int
    accepted : bool or None
        Every sensor accepted (all quality gates passed).
    sensors : tuple of SensorVerdict
        One verdict per sensor with data, exactly those of ``mavcal calibrate`` of this log
        alone (its JSON's ``"sensors"``): accepted, or rejected with the reasons shown; for a
        log that could not be calibrated, every sensor with data rejected with why.
    failed_gates : tuple of str
        ``"sensor reason"`` per reason of a rejected sensor's verdict (the reasons the summary
        of this log alone shows: the data's cause alone when the poses cannot identify it).
    heading_95_deg, tilt_95_deg : float or None
        95 % bounds of the heading and tilt error with the new parameters.
    heading_determined, tilt_determined : bool or None
        Whether those bounds are estimates (the JSON's ``quality`` flags): False when the poses
        do not identify the pair's sensors or the bound is above 90 / 45 deg; the table then
        says "not determined", as the summary does.
    not_determined_why : str
        Why not ("" when determined).
    compass_determined, accel_determined : bool or None
        Whether the poses identify the compass / accelerometer of the row (the offsets'
        changes of one they do not identify are "not determined" in the table and no drift).
    compass_ofs_old, compass_ofs_new : (3,) tuples (mGauss) or None
    compass_ofs_change_mgauss : float or None
        |new - old| of the compass offsets (None when the log has no old values).
    accel_ofs_old, accel_ofs_new : (3,) tuples (m/s^2) or None
    accel_ofs_change_mps2 : float or None
        |new - old| of the accelerometer offsets.
    accel_scale_old, accel_scale_new : (3,) tuples or None
    accel_scale_change : float or None
        Largest |new - old| of the accelerometer scales.
    model : str or None
        The calibration model used.
    n_intervals : int or None
        Still intervals used in the fit.
    warnings : tuple of str
    elapsed_s : float
        Wall time of this log in its worker.
    log_start_unix_s : float or None
        When the log starts (Unix seconds, UTC): a tlog's first timestamp; None when the log
        does not tell (DataFlash and ULog carry the vehicle's time since boot).
    """

    source: str
    ok: bool
    error: str | None = None
    exit_code: int = 0
    sysid: int | None = None
    firmware: str | None = None
    compass_dev_id: int | None = None
    accel_id: int | None = None
    accel_instance: int = 0
    compass_instance: int = 0
    accepted: bool | None = None
    sensors: tuple[SensorVerdict, ...] = ()
    failed_gates: tuple[str, ...] = ()
    heading_95_deg: float | None = None
    tilt_95_deg: float | None = None
    heading_determined: bool | None = None
    tilt_determined: bool | None = None
    not_determined_why: str = ""
    compass_determined: bool | None = None
    accel_determined: bool | None = None
    compass_ofs_old: Vec3 | None = None
    compass_ofs_new: Vec3 | None = None
    compass_ofs_change_mgauss: float | None = None
    accel_ofs_old: Vec3 | None = None
    accel_ofs_new: Vec3 | None = None
    accel_ofs_change_mps2: float | None = None
    accel_scale_old: Vec3 | None = None
    accel_scale_new: Vec3 | None = None
    accel_scale_change: float | None = None
    model: str | None = None
    n_intervals: int | None = None
    warnings: tuple[str, ...] = ()
    elapsed_s: float = 0.0
    log_start_unix_s: float | None = None

    @property
    def vehicle(self) -> str:
        """Words for the vehicle identity, e.g. ``"sys 1, ArduCopter V4.5.7"`` or ``"unknown"``."""
        parts = []
        if self.sysid is not None:
            parts.append(f"sys {self.sysid}")
        if self.firmware:
            parts.append(str(self.firmware))
        return ", ".join(parts) if parts else "unknown"

    @property
    def drift(self) -> float | None:
        """Largest change relative to its flag threshold (>= 1: drifted); None if unknown (a
        change of a sensor the poses do not identify is not known)."""
        mag, acc = self.compass_determined is not False, self.accel_determined is not False
        terms = [c / t for c, t, known in ((self.compass_ofs_change_mgauss, DRIFT_COMPASS_MGAUSS, mag),
                                           (self.accel_ofs_change_mps2, DRIFT_ACCEL_OFS_MPS2, acc),
                                           (self.accel_scale_change, DRIFT_ACCEL_SCALE, acc))
                 if c is not None and known]
        return max(terms) if terms else None

    @property
    def result(self) -> str:
        """The verdict in the words of the single log's summary: ``ACCEPTED``, ``PARTLY
        ACCEPTED (1 of 3)``, ``REJECTED``, or ``ERROR <exit code>``."""
        if not self.ok:
            return f"ERROR {self.exit_code}"
        if self.exit_code == EXIT_PARTIAL:
            return f"PARTLY ACCEPTED ({sum(v.accepted for v in self.sensors)} of {len(self.sensors)})"
        return "ACCEPTED" if self.exit_code == 0 else "REJECTED"


# --------------------------------------------------------------------------- worker

def _vec(v) -> Vec3:
    a = np.asarray(v, dtype=float)
    return (float(a[0]), float(a[1]), float(a[2]))


def _old_vec(old: dict[str, float | None], names: Sequence[str]) -> Vec3 | None:
    vals = [old.get(n) for n in names]
    return None if any(v is None for v in vals) else _vec(vals)


def _int_or_none(v) -> int | None:
    try:
        return None if v is None else int(v)
    except (TypeError, ValueError):
        return None


def _identity(log_, params: dict[str, float], ai: int, mi: int) -> dict:
    veh = dict(getattr(log_, "vehicle", {}) or {})
    out = {"sysid": _int_or_none(veh.get("sysid")), "firmware": veh.get("firmware")}
    out["firmware"] = None if out["firmware"] is None else str(out["firmware"])
    accel_id, compass_id = model_for(log_).device_ids(log_, params, ai, mi)
    out["compass_dev_id"], out["accel_id"] = _int_or_none(compass_id), _int_or_none(accel_id)
    return out


def _row_from_run(source: str, run, ai: int, mi: int, elapsed: float) -> BatchRow:
    am = run.mapping.accel[0] if run.mapping.accel else None
    cm = run.mapping.compass[0] if run.mapping.compass else None
    old = dict(run.mapping.old)
    # the calibration in force: the parameters as logged by instance (None when the log lacks them); where
    # a slot follows the device id (PX4) the mapping's old values in the common form
    model = model_for(run.log)
    c_old = c_new = a_old = a_new = s_old = s_new = None
    if cm is not None:
        cn = model.vector_names("compass", cm.instance)
        c_old, c_new = _vec(cm.old.ofs_mgauss) if cn is None else _old_vec(old, cn["ofs"]), _vec(cm.new.ofs_mgauss)
    if am is not None:
        an = model.vector_names("accel", am.instance)
        a_old, a_new = _vec(am.old.ofs_mps2) if an is None else _old_vec(old, an["ofs"]), _vec(am.new.ofs_mps2)
        s_old, s_new = _vec(am.old.scale) if an is None else _old_vec(old, an["scale"]), _vec(am.new.scale)
    verdicts = tuple(run.verdicts)  # the single log's own (the data's cause alone when it applies)
    why_a, why_m = joint_unidentified(run)
    q = run.quality
    return BatchRow(
        source=source, ok=True, exit_code=int(run.exit_code),
        **_identity(run.log, dict(run.params_before), ai, mi),
        accel_instance=am.instance if am else ai, compass_instance=cm.instance if cm else mi,
        accepted=bool(run.accepted), sensors=verdicts,
        failed_gates=tuple(f"{v.sensor} {r}" for v in verdicts for r in v.reasons),
        heading_95_deg=float(q.heading_95_deg), tilt_95_deg=float(q.tilt_95_deg),
        heading_determined=not (why_a or why_m) and determined("heading", q.heading_95_deg),
        tilt_determined=not why_a and determined("tilt", q.tilt_95_deg), not_determined_why=why_a or why_m,
        compass_determined=None if cm is None else not unidentified(run, f"compass{cm.instance}"),
        accel_determined=None if am is None else not unidentified(run, f"accel{am.instance}"),
        compass_ofs_old=c_old, compass_ofs_new=c_new,
        compass_ofs_change_mgauss=None if c_old is None or c_new is None else
         float(np.linalg.norm(np.subtract(c_new, c_old))),
        accel_ofs_old=a_old, accel_ofs_new=a_new,
        accel_ofs_change_mps2=None if a_old is None or a_new is None else
         float(np.linalg.norm(np.subtract(a_new, a_old))),
        accel_scale_old=s_old, accel_scale_new=s_new,
        accel_scale_change=None if s_old is None or s_new is None else
         float(np.max(np.abs(np.subtract(s_new, s_old)))),
        model=run.calibration.model if run.calibration is not None else "accel alone",
        n_intervals=len(run.intervals_used), warnings=tuple(run.warnings),
        elapsed_s=float(elapsed))


@dataclass(frozen=True)
class _Job:
    """What every log of a batch is calibrated with (inherited by the workers)."""

    options: object  # mavcal.pipeline.Options
    csv_rate_hz: float | None = None


def _log_start(log_) -> float | None:
    """A log's first wall-clock time (Unix seconds), when it has one (a tlog's timestamps)."""
    for s in getattr(log_, "series", ()):
        t = getattr(s, "log_time_s", None)
        if t is not None and len(t) and np.isfinite(t[0]) and t[0] > 0:
            return float(t[0])
    return None


def calibrate_one(source: str, options, csv_rate_hz: float | None = None) -> BatchRow:
    """The row of one log of a batch: what ``mavcal calibrate SOURCE`` of it alone says, as a
    small :class:`BatchRow` (a log that cannot be calibrated: a row with the error)."""
    return _calibrate_one(source, options, csv_rate_hz)


def _calibrate_one(source: str, options, csv_rate_hz: float | None = None) -> BatchRow:
    """Calibrate one log and keep only its summary (runs in a worker process).

    The same steps as ``mavcal calibrate LOG`` of this log alone (read with ``--csv-rate``,
    prepare the log read, fit; a refusal's message with its hint and every sensor's verdict),
    so that its row is that log's verdict, whatever the path."""
    from mavcal.commands.segments import csv_rate_hint
    from mavcal.errors import InsufficientDataError
    from mavcal.pipeline import calibrate_prepared, prepare, refusal_verdicts
    from mavcal.sources.reader import DEFAULT_CSV_RATE_HZ, read_log

    ai, mi = options.accel_instance, options.mag_instance
    t0 = time.perf_counter()
    ident: dict = {}
    prep = None
    start: float | None = None
    try:
        log_ = read_log(source, csv_rate_hz=DEFAULT_CSV_RATE_HZ if csv_rate_hz is None else csv_rate_hz)
        start = ident["log_start_unix_s"] = _log_start(log_)
        prep = prepare(log_, options, owned=True)
        del log_
        ident = {**_identity(prep.log, prep.log.params.snapshot(), ai, mi), "log_start_unix_s": start}
        run = calibrate_prepared(prep, options)
        prep = None  # what the run does not hold is freed now
        return replace(_row_from_run(source, run, ai, mi, time.perf_counter() - t0), log_start_unix_s=start)
    except MavcalError as exc:
        log.info("%s: %s", source, exc)
        hint = csv_rate_hint(prep.log if prep is not None else None)
        error = f"{exc}{hint}" if hint and isinstance(exc, InsufficientDataError) else str(exc)
        told = exc if error == str(exc) else type(exc)(error)
        verdicts = refusal_verdicts(prep, told, options) if prep is not None else ()
        return BatchRow(source=source, ok=False, error=error, exit_code=int(exc.exit_code), accel_instance=ai,
                        compass_instance=mi, sensors=tuple(verdicts),
                        failed_gates=tuple(f"{v.sensor} {r}" for v in verdicts for r in v.reasons),
                        elapsed_s=time.perf_counter() - t0, **ident)
    except Exception as exc:  # a bug or a resource limit: report it, keep the batch going
        log.exception("%s: unexpected error", source)
        return BatchRow(source=source, ok=False, error=f"unexpected {type(exc).__name__}: {exc}", exit_code=1,
                        accel_instance=ai, compass_instance=mi, elapsed_s=time.perf_counter() - t0, **ident)


def _calibrate_indexed(job: _Job, item: tuple[int, str]) -> BatchRow:
    """:func:`_calibrate_one` as a :class:`~mavcal.workers.ForkPool` job (``item``: index, source)."""
    return _calibrate_one(item[1], job.options, job.csv_rate_hz)


# --------------------------------------------------------------------------- batch

def calibrate_many(sources: list[str], options, jobs: int = 1, *,
                   progress: ProgressFn | None = None, csv_rate_hz: float | None = None) -> list[BatchRow]:
    """Calibrate many logs, in parallel worker processes when ``jobs > 1``.

    Parameters
    ----------
    sources : list of str
        Log files (device strings work too, but record one after the other).
    options : mavcal.pipeline.Options
        The same options for every log.
    jobs : int
        Worker processes (1: in this process, one log after the other); never more than the
        logs nor :func:`mavcal.workers.worker_limit`.
    progress : callable ``(done, total, row)``, optional
        Called in this process after each log, in completion order.
    csv_rate_hz : float, optional
        Sample rate of a CSV log without a time column (``--csv-rate``; default the reader's).

    Returns
    -------
    list of BatchRow
        One per source, in the order of ``sources``.

    Raises
    ------
    mavcal.errors.UsageError
        ``jobs < 1``.
    """
    if int(jobs) < 1:
        raise UsageError(f"jobs must be at least 1, got {jobs}")
    sources = [str(s) for s in sources]
    total = len(sources)
    rows: list[BatchRow | None] = [None] * total
    done = 0

    def finish(i: int, row: BatchRow) -> None:
        nonlocal done
        rows[i] = row
        done += 1
        log.info("[%d/%d] %s: %s", done, total, row.source, "ok" if row.ok else row.error)
        if progress is not None:
            progress(done, total, row)

    def then(item: tuple[int, str], outcome: Outcome) -> list:
        i, source = item
        ok, row = outcome
        if not ok:  # its worker process died (out of memory?): this log alone fails
            row = BatchRow(source=source, ok=False, error=str(row), exit_code=int(row.exit_code),
                           accel_instance=options.accel_instance, compass_instance=options.mag_instance)
        finish(i, row)
        return []

    with ForkPool(_Job(options, csv_rate_hz), min(int(jobs), total), max_tasks=MAX_TASKS_PER_CHILD) as pool:
        pool.run(_calibrate_indexed, list(enumerate(sources)), then)
    return [r for r in rows if r is not None]


# --------------------------------------------------------------------------- table

def _f(v: float | None, fmt: str) -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, fmt)


def _names(rows: Sequence[BatchRow]) -> dict[str, str]:
    """Short names for the sources: the file name unless two share it."""
    base = [Path(r.source).name for r in rows]
    return {r.source: (b if base.count(b) == 1 else r.source) for r, b in zip(rows, base)}


_HEADER = ["VEHICLE", "COMPASS(DEV_ID)", "ACCEL(ID)", "LOG", "RESULT", "|dOFS| mG", "COMPASS OFS old -> new",
           "|dACC| m/s2", "max dSCAL", "HDG95", "TILT95", "MODEL", "N", "FLAG"]
_RIGHT = {5, 7, 8, 9, 10, 12}


def _group_key(r: BatchRow) -> tuple:
    return (r.sysid, r.firmware, r.compass_dev_id, r.accel_id, r.compass_instance, r.accel_instance)


def _score(r: BatchRow) -> float:
    d = r.drift
    return -1.0 if d is None else d


def _ids(r: BatchRow) -> list[str]:
    return [r.vehicle, f"{r.compass_instance}({r.compass_dev_id if r.compass_dev_id is not None else '?'})",
            f"{r.accel_instance}({r.accel_id if r.accel_id is not None else '?'})"]


#: the table's words for a number the data do not determine (the summary's)
NOT_DETERMINED = "not determined"


def _ok_cells(r: BatchRow, name: str) -> list[str]:
    nd_mag, nd_acc = r.compass_determined is False, r.accel_determined is False
    ofs = ("-" if r.compass_ofs_new is None else NOT_DETERMINED if nd_mag else
           ("?" if r.compass_ofs_old is None else "(" + ",".join(f"{v:.0f}" for v in r.compass_ofs_old) + ")")
           + " -> (" + ",".join(f"{v:.0f}" for v in r.compass_ofs_new) + ")")

    def known(v: float | None, fmt: str, ok: bool | None) -> str:
        return NOT_DETERMINED if ok is False and v is not None else _f(v, fmt)

    return _ids(r) + [name, r.result, known(r.compass_ofs_change_mgauss, ".1f", not nd_mag), ofs,
                      known(r.accel_ofs_change_mps2, ".3f", not nd_acc), known(r.accel_scale_change, ".4f", not nd_acc),
                      known(r.heading_95_deg, ".2f", r.heading_determined),
                      known(r.tilt_95_deg, ".3f", r.tilt_determined), r.model or "-",
                      "-" if r.n_intervals is None else str(r.n_intervals),
                      ("DRIFT" if r.accepted else "drift?") if _score(r) >= 1.0 else ""]


def _footer(rows: Sequence[BatchRow], names: dict[str, str], n_failed: int, n_groups: int) -> list[str]:
    drifted = [names[r.source] for r in rows if r.ok and r.accepted and _score(r) >= 1.0]
    unsure = [names[r.source] for r in rows if r.ok and not r.accepted and _score(r) >= 1.0]
    n_acc = sum(1 for r in rows if r.ok and r.exit_code == 0)
    n_part = sum(1 for r in rows if r.ok and r.exit_code == EXIT_PARTIAL)
    n_rej = len(rows) - n_failed - n_acc - n_part
    out = ["", f"{len(rows)} logs: {n_acc} accepted, {n_part} partly accepted, {n_rej} rejected by the gates, "
               f"{n_failed} failed; {n_groups} vehicle/instance group(s); exit code {fleet_exit_code(rows)} "
               "(the worst log's)",
           (f"drifted (compass offsets > {DRIFT_COMPASS_MGAUSS:g} mGauss, accel offsets > {DRIFT_ACCEL_OFS_MPS2:g} "
            f"m/s^2 or scale > {DRIFT_ACCEL_SCALE:g}): " + ", ".join(drifted))
           if drifted else "no accepted calibration drifted beyond the thresholds"]
    if unsure:
        out.append("large changes in rejected calibrations (not trustworthy, see the gates): " + ", ".join(unsure))
    return out


def _rank(r: BatchRow) -> tuple[int, int]:
    """How bad a row's outcome is (larger: worse), :func:`fleet_exit_code`'s order."""
    if not r.ok:
        return (4, r.exit_code) if r.exit_code != GateError.exit_code else (3, 0)
    return ({0: 0, EXIT_PARTIAL: 1}.get(r.exit_code, 2), r.exit_code)


def fleet_exit_code(rows: Sequence[BatchRow]) -> int:
    """The exit code of a many-log run: the worst row's, in this order (worst first): a log that
    failed with an error (the largest such code: 70 an internal error, 8 signing, 3 unreadable
    ...), a log too short to calibrate (4), a log whose every sensor was rejected (4), a
    partial acceptance (7), full acceptance (0). No rows: 0."""
    return max(rows, key=_rank).exit_code if rows else 0


def _verdict_lines(r: BatchRow) -> list[str]:
    """What the summary of the log alone says of its sensors: each rejected sensor and its reasons."""
    if not r.ok:
        return [f"    {r.error}"]
    if not r.sensors:  # a row made without verdicts (older callers): its failed gates
        return [f"    gate {fg}" for fg in r.failed_gates]
    out = []
    for v in r.sensors:
        if not v.accepted:
            out.append(f"    {v.sensor}: REJECTED")
            out += [f"        {reason}" for reason in v.reasons]
    return out


def format_fleet_table(rows: Sequence[BatchRow]) -> str:
    """A table of a batch per vehicle and instance, the biggest changes first.

    Parameters
    ----------
    rows : sequence of BatchRow

    Returns
    -------
    str
        One line per log grouped per vehicle identity (system id, firmware, compass and
        accelerometer device ids); the groups and the lines in them ordered by the
        largest calibration change relative to the drift thresholds
        (:data:`DRIFT_COMPASS_MGAUSS`, :data:`DRIFT_ACCEL_OFS_MPS2`,
        :data:`DRIFT_ACCEL_SCALE`), ``DRIFT`` marking accepted calibrations beyond them
        (``drift?`` for rejected ones, whose values are not trustworthy); under each line
        its rejected sensors with the reasons of its own summary; "not determined" where the
        summary says so; failed logs last with their error; then a count line with the exit
        code (:func:`fleet_exit_code`) and the drifted logs by name.
    """
    rows = list(rows)
    if not rows:
        return "no logs"
    names = _names(rows)
    groups: dict[tuple, list[BatchRow]] = {}
    for r in rows:
        if r.ok:
            groups.setdefault(_group_key(r), []).append(r)
    ordered = [r for g in sorted(groups.values(), key=lambda g: -max(_score(r) for r in g))
               for r in sorted(g, key=lambda r: -_score(r))]
    failed = [r for r in rows if not r.ok]
    table = [_ok_cells(r, names[r.source]) for r in ordered]
    table += [_ids(r) + [names[r.source], f"ERROR {r.exit_code}"] + [""] * (len(_HEADER) - 5) for r in failed]
    widths = [max(len(_HEADER[j]), *(len(t[j]) for t in table)) for j in range(len(_HEADER))]

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.rjust(w) if j in _RIGHT else c.ljust(w)
                         for j, (c, w) in enumerate(zip(cells, widths))).rstrip()

    out = [line(_HEADER), line(["-" * w for w in widths])]
    for t, r in zip(table, ordered + failed):
        out.append(line(t))
        out += _verdict_lines(r)
    return "\n".join(out + _footer(rows, names, len(failed), len(groups)))
