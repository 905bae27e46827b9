"""The calibration in force: where it came from, and what happens when it is not known.

A log holds the readings *as corrected* by the calibration the vehicle had then (ArduPilot's
RAW_IMU, DataFlash IMU/MAG; a live PX4's SCALED_IMU). To fit a new calibration, mavcal undoes
that correction (the autopilot model's ``recover_raw``: ArduPilot's, PX4's), which takes the
values that were in force. They come from

* the recording's parameters (a tlog's PARAM_VALUE messages, a DataFlash log's PARM records, a
  ULog's parameters), or the vehicle itself on a live link;
* a parameter file saved from the vehicle when the log was recorded, given with
  ``--params FILE`` (:func:`with_param_file`): Mission Planner's ``NAME,VALUE`` and MAVProxy's
  ``NAME VALUE`` .param files (:mod:`mavcal.autopilot.paramfile`).

Each sensor's origin is in :attr:`mavcal.autopilot.raw.RawImu.cal_origin`. A sensor whose
calibration in force is not known (no parameters at all, or only some of its names) is still
fitted and judged, but its verdict is "not written" (:func:`in_force_gates`): its new values
would be off by exactly the calibration in force, and writing them would erase it. No default
is ever guessed for it, and neither ``--force`` nor the API writes it
(:meth:`mavcal.run.CalibrationRun.params_to_write`).
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import replace
from typing import Union

import numpy as np

from mavcal.autopilot.gates import CAUSE_IN_FORCE, Gate
from mavcal.autopilot.raw import RawImu
from mavcal.sources.types import ImuLog, ParamTimeline

__all__ = ["with_param_file", "in_force_gates", "not_known_reason", "HOW_TO_RECORD", "GATE_NAME"]

PathLike = Union[str, "os.PathLike[str]"]

#: the name of the gate a sensor without a known calibration in force fails
GATE_NAME = "calibration in force"

#: what to do, in the ground stations' words (the same line in the verdict and in docs/recording.md)
HOW_TO_RECORD = (
    "record with the parameters (Mission Planner: Full Parameter List > Refresh Params while the log records; "
    "QGroundControl: Parameters > Tools > Refresh; MAVProxy: param fetch) or give the ones saved when it was "
    "recorded with --params FILE (Mission Planner: Save to file; QGroundControl: Tools > Save to file; "
    "MAVProxy: param save FILE)")


def _names_text(names: tuple[str, ...]) -> str:
    """``INS_ACCOFFS_X/Y/Z, AHRS_ORIENTATION`` (X/Y/Z triples shortened), at most 6 groups."""
    out: list[str] = []
    for n in names:
        short = n[:-2] + "_X/Y/Z" if n[-2:] in ("_X", "_Y", "_Z") else n
        if short not in out:
            out.append(short)
    return ", ".join(out[:6]) + (f" and {len(out) - 6} more" if len(out) > 6 else "")


def not_known_reason(sensor: str, missing: tuple[str, ...], live: bool = False) -> str:
    """The verdict's reason of ``sensor``, whose calibration in force lacks ``missing``."""
    what = f" ({_names_text(missing)} missing)" if missing else " (it has no parameter slot)"
    if live:
        return (f"not written: the vehicle did not send the calibration in force of {sensor}{what}; connect "
                "again and let the parameter download finish")
    return f"not written: the calibration in force is not in the recording{what}: {HOW_TO_RECORD}"


def in_force_gates(raw: RawImu, *, live: bool = False) -> list[Gate]:
    """A failed gate per sensor of ``raw`` whose calibration in force is not known
    (:attr:`~mavcal.autopilot.raw.RawImu.cal_missing`): it rejects the sensor, and its
    reason comes first in the sensor's verdict."""
    return [Gate(sensor, GATE_NAME, False, 0.0, "known (the recording's parameters, --params FILE or the vehicle)",
                 not_known_reason(sensor, tuple(missing), live), True, CAUSE_IN_FORCE)
            for sensor, missing in raw.cal_missing.items()]


def with_param_file(log_: ImuLog, params: PathLike | Mapping[str, float], origin: str | None = None) -> ImuLog:
    """``log_`` with the parameters of a .param file (or a name -> value mapping) as the
    calibration in force from its start, where the recording lacks them.

    The file is what the vehicle held when the log was recorded (saved from Mission Planner,
    QGroundControl or MAVProxy then). A name the recording holds keeps the recording's values
    (they carry their times: a change during the log counts from its time); a different value in
    the file is said in the log's warnings. A name the recording lacks takes the file's value
    from the first reading on, as if the recording had held it from its start (the parameter
    history then bounds it by the log's own events, ArduPilot's parameter history).

    Parameters
    ----------
    log_ : ImuLog
        The recording as read.
    params : path or mapping of str to float
        A .param file (:func:`mavcal.autopilot.paramfile.read_param_file`) or the values.
    origin : str, optional
        How the file is named in the report (default ``"--params <file name>"``).

    Returns
    -------
    ImuLog
        The same recording; ``params`` and ``param_origins`` extended, ``warnings`` with the
        conflicts.

    Raises
    ------
    ParamFileError
        The file cannot be read or has a malformed line (exit code 3).
    """
    from mavcal.autopilot.paramfile import read_param_file

    # (values as the vehicle holds them, float32: a .param file's "0.001" stands for float32(0.001), the
    # value a PARAM_VALUE / PARM record carries)
    if isinstance(params, Mapping):
        values = {str(k): float(v) for k, v in params.items()}
        origin = origin or "--params"
    else:
        values = read_param_file(params)
        origin = origin or f"--params {os.path.basename(os.fspath(params))}"
    starts = [float(s.time_s[0]) for s in log_.series if len(s) and np.isfinite(s.time_s[0])]
    t0 = min(starts + [float(ts[0]) for ts, _ in log_.params.changes.values() if len(ts)], default=0.0)
    changes = dict(log_.params.changes)
    origins = dict(log_.param_origins)
    differ = []
    for name, v in values.items():
        if name in changes:
            if np.float32(changes[name][1][0]) != np.float32(v):
                differ.append(name)
            continue
        changes[name] = (np.array([t0]), np.array([float(np.float32(v))]))  # the vehicle holds float32
        origins[name] = origin
    warnings = list(log_.warnings)
    if differ:
        warnings.append(f"{origin}: {len(differ)} value(s) differ from the recording's ({', '.join(sorted(differ)[:5])}"
                        f"{' ...' if len(differ) > 5 else ''}): the recording's are used (they are the ones in force "
                        "when it was recorded)")
    return replace(log_, params=ParamTimeline(changes), param_origins=origins, warnings=tuple(warnings))
