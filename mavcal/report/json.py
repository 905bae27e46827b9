"""The JSON report of a calibration run, both ways.

:func:`to_json` turns a :class:`mavcal.pipeline.CalibrationRun` into a JSON-ready dict
(``"format": "mavcal report v1"``, ``"format_version": 2``); :func:`from_json` loads such a
dict back into the same objects: the :class:`~mavcal.core.types.Calibration`, a
:class:`~mavcal.autopilot.mapping.ParamMapping` with the parameters (old and new values,
notes; no per-sensor mapping details), the :class:`~mavcal.judging.quality.Quality`, the
:class:`~mavcal.autopilot.gates.GateReport` and the still intervals (bounds and counts,
not the samples). Non-finite numbers are written as ``null`` and read back as NaN.

Format versions: 1 (mavcal 0.1 before the loader) lacks the full noise covariances,
orientations, parameter covariance and sample counts; it loads with the noise
covariances rebuilt from their diagonals and those other fields empty. 2 adds them.
"""
from __future__ import annotations

import json as _json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

import mavcal
from mavcal.autopilot.gates import Gate, GateReport
from mavcal.autopilot.mapping import ParamMapping
from mavcal.core.types import Calibration, SensorModel
from mavcal.determined import determined, joint_unidentified
from mavcal.errors import SourceError, UsageError
from mavcal.judging.quality import Quality

__all__ = ["FORMAT", "FORMAT_VERSION", "SavedInterval", "SavedCalibration", "to_json", "refusal_json", "from_json",
           "write_json", "read_json"]

FORMAT = "mavcal report v1"  # the document kind (kept from the first version)
FORMAT_VERSION = 2


@dataclass(frozen=True, eq=False)
class SavedInterval:
    """A still interval as saved: bounds and sample counts per sensor instance (no samples)."""

    index: int
    start_s: float
    end_s: float
    duration_s: float
    samples_accel: Mapping[int, int]
    samples_mag: Mapping[int, int]
    gravity_dir: np.ndarray
    used: bool


@dataclass(frozen=True, eq=False)
class SavedCalibration:
    """A calibration run loaded from its JSON report.

    ``mapping`` holds the parameters (``new``, ``old``, ``notes``, ``reboot_required``);
    its ``accel``/``compass`` tuples are empty. ``document`` is the whole JSON dict (for
    the sections that have no object: dropped terms, compass decision, coverage, ...).
    """

    format_version: int
    source: str
    mavcal_version: str
    accepted: bool
    calibration: Calibration | None  # None: accelerometers calibrated alone
    mapping: ParamMapping
    quality: Quality
    gates: GateReport
    intervals: tuple[SavedInterval, ...]
    warnings: tuple[str, ...]
    document: Mapping[str, Any]


# --------------------------------------------------------------------------- writing

def _f(x):
    if isinstance(x, (np.floating, float)):
        return None if not np.isfinite(x) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return [_f(v) for v in x.tolist()] if x.ndim else _f(x.item())
    if isinstance(x, (list, tuple)):
        return [_f(v) for v in x]
    return x


def _calibration(cal: Calibration) -> dict[str, Any]:
    return {"model": cal.model, "model_reason": cal.model_reason, "method": cal.method,
            "cost": cal.cost, "dof": cal.dof, "converged": cal.converged, "message": cal.message,
            "K_a": _f(cal.accel.gain), "b_a": _f(cal.accel.bias), "K_m": _f(cal.mag.gain),
            "b_m": _f(cal.mag.bias), "field": _f(cal.field),
            "accel_noise_std": _f(np.sqrt(np.diag(cal.accel.noise_cov))),
            "mag_noise_std": _f(np.sqrt(np.diag(cal.mag.noise_cov))),
            # format 2: what the loader needs to rebuild the Calibration
            "accel_noise_cov": _f(cal.accel.noise_cov), "mag_noise_cov": _f(cal.mag.noise_cov),
            "gravity": _f(cal.gravity), "orientations": _f(cal.orientations), "iterations": cal.iterations,
            "block_iterations": cal.block_iterations, "refine_iterations": cal.refine_iterations,
            "param_names": list(cal.param_names), "param_cov": None if cal.param_cov is None else _f(cal.param_cov),
            "n_accel": None if cal.n_accel is None else _f(cal.n_accel),
            "n_mag": None if cal.n_mag is None else _f(cal.n_mag)}


def _compass(cm) -> dict[str, Any]:
    return {"instance": cm.instance, "external": cm.external, "orientation": cm.orientation_note,
            "rotation_deg": cm.rotation_deg, "field_mgauss": cm.field_mgauss, "field_source": cm.field_source,
            "inclination_deg": cm.inclination_deg, "inclination_model_deg": _f(cm.inclination_model_deg),
            "inclination_difference_deg": (None if cm.inclination_model_deg is None
                                           else cm.inclination_deg - cm.inclination_model_deg)}


def _instances(run) -> dict[str, Any]:
    return {"accel": run.mapping.accel[0].instance if run.mapping.accel else None,
            "compass": run.mapping.compass[0].instance if run.mapping.compass else None,
            "accel_present": list(run.raw.accel_instances()), "compass_present": list(run.raw.mag_instances()),
            "accel_calibrated": [{"instance": a.instance, "offsets_mps2": _f(np.array(a.new.ofs_mps2)),
                                  "scales": _f(np.array(a.new.scale)), "dropped_tilt_deg": a.dropped_tilt_deg}
                                 for a in run.mapping.accel],
            "compass_calibrated": [{"instance": c.instance, "external": c.external,
                                    "offsets_mgauss": _f(np.array(c.new.ofs_mgauss)),
                                    "orientation": c.orientation_note, "rotation_deg": c.rotation_deg,
                                    "residual_rotation_deg": c.residual_rotation_deg,
                                    "field_mgauss": c.field_mgauss, "field_checked": c.field_checked,
                                    "field_source": c.field_source}
                                   for c in run.mapping.compass],
            "pairs": [{"accel": r.mapping.accel[0].instance, "compass": r.mapping.compass[0].instance,
                       "model": r.calibration.model, "heading_95_deg": r.quality.heading_95_deg,
                       "tilt_95_deg": r.quality.tilt_95_deg, **_determined(r)} for r in (run,) + tuple(run.others)
                      if r.mapping.accel and r.mapping.compass and r.calibration is not None]}


def _determined(run) -> dict[str, Any]:
    """The flags beside the bounds (:mod:`mavcal.determined`): ``heading_determined`` /
    ``tilt_determined`` False when the bound is above 90 / 45 deg or the poses do not identify
    the pair's sensors (``not_determined_why`` then says which; "" otherwise)."""
    why_a, why_m = joint_unidentified(run)
    q = run.quality
    return {"heading_determined": not (why_a or why_m) and determined("heading", q.heading_95_deg),
            "tilt_determined": not why_a and determined("tilt", q.tilt_95_deg),
            "not_determined_why": why_a or why_m}


def _changed(old: float | None, new: float) -> bool:
    return bool(old is None or np.float32(new) != np.float32(old))


def sensors_json(gates: GateReport) -> list[dict[str, Any]]:
    """``[{"sensor": "accel0", "accepted": true, "reasons": []}, ...]``: exactly these keys."""
    return [{"sensor": v.sensor, "accepted": v.accepted, "reasons": list(v.reasons)} for v in gates.verdicts()]


def _dropped(run) -> dict[str, Any]:
    out: dict[str, Any] = {"compass_motor_compensation": "unchanged (still poses cannot observe it)"}
    if run.mapping.accel:
        am = run.mapping.accel[0]
        out.update({"accel_cross_axis": _f(am.cross_axis), "accel_tilt_deg": am.dropped_tilt_deg,
                    "accel_magnitude_mps2": am.dropped_magnitude_mps2})
    if run.mapping.compass:
        out["compass_residual_rotation_deg"] = run.mapping.compass[0].residual_rotation_deg
    return out


def _parameters(run) -> dict[str, Any]:
    """Every parameter of the calibration, old and new; ``"written"`` whether it goes into the
    .param / write plan (without --force), ``"rejected"`` its sensor's rejection (the new value
    of a rejected sensor is kept here, marked, and nowhere else)."""
    from mavcal.report.text import rejection_notes

    old, write, notes = run.mapping.old, run.params_to_write(), rejection_notes(run)
    sensor_of = {n: s for s, p in run.mapping.by_sensor().items() for n in p}
    return {n: {"old": _f(old.get(n)), "new": _f(v), "changed": _changed(old.get(n), v), "written": n in write,
                "rejected": f"{sensor_of[n]}: {notes[sensor_of[n]]}" if sensor_of.get(n) in notes else None}
            for n, v in sorted(run.mapping.new.items())}


def to_json(run) -> dict[str, Any]:
    """The JSON report of a :class:`mavcal.pipeline.CalibrationRun` (a dict for :func:`json.dump`).

    ``"sensors"`` holds the per-sensor verdicts, ``"verdict"`` the run's ("accepted", "partly accepted",
    "rejected") and ``"exit_code"`` the CLI's (0, 7 or 4); ``"raw_recovery"`` says per sensor where the
    calibration in force came from (``"calibration_in_force"``, null: not known, never written);
    ``"calibration"`` and ``"compass"`` are null when the accelerometers were calibrated alone."""
    seg = run.segmentation
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "mavcal_version": mavcal.__version__,
        "source": run.source,
        "accepted": run.accepted,
        "verdict": run.verdict,
        "sensors": sensors_json(run.gates),
        "kept": [{"sensor": k.sensor, "parameter": k.what, "why": k.why, "pose": k.pose} for k in run.kept],
        "exit_code": run.exit_code,
        "parameters": _parameters(run),
        "reboot_required": run.mapping.reboot_required,
        "quality": {**{k: _f(v) for k, v in run.quality.__dict__.items()}, **_determined(run)},
        "gates": [{"sensor": g.sensor, "name": g.name, "ok": g.ok, "value": _f(g.value), "limit": g.limit,
                   "reason": g.reason, "ran": g.ran, "cause": g.cause} for g in run.gates.gates],
        "dropped": _dropped(run),
        "compass": _compass(run.mapping.compass[0]) if run.mapping.compass else None,
        "calibration": None if run.calibration is None else _calibration(run.calibration),
        "intervals": [{"index": k, "start_s": iv.start_s, "end_s": iv.end_s, "duration_s": iv.duration_s,
                       "samples_accel": iv.n_accel, "samples_mag": iv.n_mag, "gravity_dir": _f(iv.gravity_dir),
                       "used": k in run.intervals_used} for k, iv in enumerate(seg.intervals)],
        "coverage": {"n_intervals": seg.coverage.n_intervals, "n_orientations": seg.coverage.n_orientations,
                     "largest_empty_cap_deg": seg.coverage.largest_empty_cap_deg, "status": seg.coverage.status,
                     "messages": list(seg.coverage.messages)},
        "instances": _instances(run),
        "raw_recovery": {"frames": dict(run.raw.frames), "accel_cal_periods": _f(run.raw.accel_cal_periods),
                         "params_used": {k: _f(v) for k, v in run.raw.params_used.items()},
                         "calibration_in_force": {k: v or None for k, v in run.raw.cal_origin.items()}},
        "notes": list(run.mapping.notes),
        "warnings": list(run.warnings),
    }


def refusal_json(source: str, error: Exception, verdicts: Sequence[Any] = (), prep: Any = None) -> dict[str, Any]:
    """The JSON report of a recording that could not be calibrated at all (too little data,
    unreadable): ``"sensors"`` (each sensor with data rejected with the reasons, see
    :func:`mavcal.pipeline.refusal_verdicts`; empty when the log could not be read),
    ``"exit_code"`` (the CLI's), ``"error"`` (the one-line refusal) and, when the log was
    read, the still intervals, coverage and warnings. It has no ``"calibration"`` or
    ``"parameters"``: :func:`from_json` refuses it."""
    out: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "mavcal_version": mavcal.__version__,
        "source": str(source),
        "accepted": False,
        "sensors": [{"sensor": v.sensor, "accepted": bool(v.accepted), "reasons": list(v.reasons)}
                    for v in verdicts],
        "exit_code": int(getattr(error, "exit_code", 1)),
        "error": str(error),
    }
    if prep is not None:
        seg = prep.segmentation
        out["intervals"] = [{"index": k, "start_s": iv.start_s, "end_s": iv.end_s, "duration_s": iv.duration_s,
                             "samples_accel": iv.n_accel, "samples_mag": iv.n_mag,
                             "gravity_dir": _f(iv.gravity_dir), "used": False}
                            for k, iv in enumerate(seg.intervals)]
        out["coverage"] = {"n_intervals": seg.coverage.n_intervals, "n_orientations": seg.coverage.n_orientations,
                           "largest_empty_cap_deg": _f(seg.coverage.largest_empty_cap_deg),
                           "status": seg.coverage.status, "messages": list(seg.coverage.messages)}
        out["raw_recovery"] = {"frames": dict(prep.raw.frames), "accel_cal_periods": _f(prep.raw.accel_cal_periods)}
        out["warnings"] = list(prep.warnings)
    return out


def write_json(run, path) -> Path:
    """Write :func:`to_json` of ``run`` to ``path`` ('-' is not a path here); UsageError when it cannot."""
    from mavcal.errors import SourceError
    from mavcal.outputs import write_atomic

    path = Path(path)
    try:
        write_atomic(path, _json.dumps(to_json(run), indent=1))  # an interrupted run leaves the old file whole
    except SourceError as exc:
        raise UsageError(f"cannot write the JSON report: {exc}") from None
    return path


# --------------------------------------------------------------------------- reading

def _num(x) -> float:
    return float("nan") if x is None else float(x)


def _nested(x) -> np.ndarray:
    """A nested list with nulls -> float array (NaN for null)."""
    def conv(v):
        return [conv(e) for e in v] if isinstance(v, list) else (np.nan if v is None else v)
    return np.array(conv(x), dtype=float)


def _calibration_from(c: Mapping[str, Any]) -> Calibration:
    if "accel_noise_cov" in c:  # format 2
        Sa, Sm = _nested(c["accel_noise_cov"]), _nested(c["mag_noise_cov"])
        R = _nested(c["orientations"]).reshape(-1, 3, 3)
        gravity = _nested(c["gravity"])
    else:  # format 1: the diagonals only, no orientations
        Sa, Sm = np.diag(_nested(c["accel_noise_std"]) ** 2), np.diag(_nested(c["mag_noise_std"]) ** 2)
        R, gravity = np.empty((0, 3, 3)), np.array([0.0, 0.0, -1.0])

    def opt(key):
        v = c.get(key)
        return None if v is None else _nested(v)

    return Calibration(
        accel=SensorModel(_nested(c["K_a"]), _nested(c["b_a"]), Sa, "accel"),
        mag=SensorModel(_nested(c["K_m"]), _nested(c["b_m"]), Sm, "mag"),
        gravity=gravity, field=_nested(c["field"]), orientations=R, cost=_num(c["cost"]),
        iterations=int(c.get("iterations", 0)), converged=bool(c["converged"]), message=str(c["message"]),
        method=str(c["method"]), model=str(c["model"]), model_reason=str(c.get("model_reason") or ""),
        param_names=tuple(c.get("param_names", ())), param_cov=opt("param_cov"), n_accel=opt("n_accel"),
        n_mag=opt("n_mag"), block_iterations=int(c.get("block_iterations", 0)),
        refine_iterations=int(c.get("refine_iterations", 0)), dof=int(c.get("dof", 0)))


def _interval_from(d: Mapping[str, Any]) -> SavedInterval:
    return SavedInterval(index=int(d["index"]), start_s=_num(d["start_s"]), end_s=_num(d["end_s"]),
                         duration_s=_num(d["duration_s"]),
                         samples_accel={int(k): int(v) for k, v in d["samples_accel"].items()},
                         samples_mag={int(k): int(v) for k, v in d["samples_mag"].items()},
                         gravity_dir=_nested(d["gravity_dir"]), used=bool(d["used"]))


def from_json(doc: Mapping[str, Any]) -> SavedCalibration:
    """Load a JSON report (the dict of :func:`to_json`, format version 1 or 2).

    Raises
    ------
    mavcal.errors.SourceError
        Not a mavcal report, a newer format version, or a required section missing.
    """
    if not isinstance(doc, Mapping) or doc.get("format") != FORMAT:
        raise SourceError("not a mavcal JSON report (no \"format\": \"mavcal report v1\")")
    if "error" in doc and "calibration" not in doc:
        raise SourceError(f"this JSON report holds no calibration: the recording was refused ({doc['error']})")
    version = int(doc.get("format_version", 1))
    if version > FORMAT_VERSION:
        raise SourceError(f"JSON report format version {version} is newer than this mavcal reads "
                          f"({FORMAT_VERSION}); update mavcal")
    try:
        params = doc["parameters"]
        mapping = ParamMapping(accel=(), compass=(), new={n: float(p["new"]) for n, p in params.items()},
                               old={n: None if p["old"] is None else float(p["old"]) for n, p in params.items()},
                               notes=tuple(doc.get("notes", ())), reboot_required=bool(doc["reboot_required"]))
        q = doc["quality"]
        quality = Quality(**{f.name: _num(q[f.name]) for f in fields(Quality) if f.name in q})
        gates = GateReport(tuple(Gate(g["sensor"], g["name"], bool(g["ok"]), _num(g["value"]), g["limit"],
                                      g.get("reason", ""), bool(g.get("ran", True)), g.get("cause", ""))
                                 for g in doc["gates"]))
        intervals = tuple(_interval_from(d) for d in doc["intervals"])
        cal = None if doc["calibration"] is None else _calibration_from(doc["calibration"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SourceError(f"JSON report incomplete or damaged: {type(exc).__name__}: {exc}") from None
    return SavedCalibration(format_version=version, source=str(doc.get("source", "")),
                            mavcal_version=str(doc.get("mavcal_version", "")), accepted=bool(doc["accepted"]),
                            calibration=cal, mapping=mapping, quality=quality, gates=gates, intervals=intervals,
                            warnings=tuple(doc.get("warnings", ())), document=doc)


def read_json(path) -> SavedCalibration:
    """:func:`from_json` of a report file; SourceError when it cannot be read or parsed."""
    try:
        doc = _json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise SourceError(f"{path}: cannot read the JSON report: {exc}") from None
    return from_json(doc)
