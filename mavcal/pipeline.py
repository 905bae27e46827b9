"""From a log or a live link to an autopilot's parameters; this module only chains the stages:

    open_source (:mod:`mavcal.sources.reader` / :mod:`mavcal.link.live`)
    -> prepare (untruncate, the autopilot model's ``recover_raw``, :mod:`mavcal.segment`)
    -> coverage (:mod:`mavcal.coverage`) -> fit (:mod:`mavcal.fits`, :mod:`mavcal.core`)
    -> map (the model's ``map_calibration``) -> judge (:mod:`mavcal.judging`: the numbers of
    :mod:`mavcal.judging.quality`, the gates of :mod:`mavcal.autopilot.gates`) -> verdict (:class:`CalibrationRun`).

:func:`calibrate_source` is what ``mavcal calibrate``, the capture command and the
MAVProxy module call. It never writes to a vehicle (that is :mod:`mavcal.link.writer`).
"""
from __future__ import annotations

import logging
from dataclasses import replace

from mavcal.autopilot import model_for
from mavcal.autopilot.raw import RawImu
from mavcal.errors import UsageError
from mavcal.fit_inputs import coverage_rule
from mavcal.fits import fit_recording, refusal_verdicts
from mavcal.judging.quality import Quality
from mavcal.memory import release_free_memory
from mavcal.run import STAGE_FIT, STAGE_RECOVER, STAGE_SEGMENT, CalibrationRun, Options, Prepared
from mavcal.segment import find_still_intervals
from mavcal.sources.progress import ProgressFn, report
from mavcal.sources.types import ImuLog, SensorSeries

log = logging.getLogger(__name__)

__all__ = ["Options", "Prepared", "CalibrationRun", "Quality", "open_source", "prepare", "calibrate_source",
           "calibrate_prepared", "STAGE_RECOVER", "STAGE_SEGMENT", "STAGE_FIT", "refusal_verdicts", "coverage_rule"]


# --------------------------------------------------------------------------- read

def open_source(source, *, baud: int = 115200, duration_s: float = 10.0, heartbeat_timeout_s: float = 5.0,
                param_timeout_s: float = 30.0, rate_hz: float = 50.0,
                progress: ProgressFn | None = None, tlog=None) -> ImuLog:
    """Read a log file, or record from a live vehicle.

    Parameters
    ----------
    source : str or path-like
        A ``.tlog``, DataFlash ``.bin``/``.log`` or ``.csv`` path (read by
        :func:`mavcal.sources.reader.read_log`), or a MAVLink device string
        (``udpin:0.0.0.0:14550``, ``tcp:HOST:PORT``, ``/dev/ttyACM0``), from which
        ``duration_s`` seconds are recorded (:func:`mavcal.link.live.record_device`).
    baud, duration_s, heartbeat_timeout_s, param_timeout_s, rate_hz
        Only for a device: serial baud rate, recording length, how long to wait for a
        heartbeat and for the parameters, and the IMU stream rate requested.
    progress : callable(done, total), optional
        Called as the file is read.
    tlog : path, optional
        Only for a device: also save everything received in this telemetry log, which this
        function reads back to the same readings (a recording to keep, share or calibrate again).

    Returns
    -------
    ImuLog
        Every sensor series (readings as sent, i.e. corrected by the calibration in force),
        the parameter timeline, events, position and warnings
        (:class:`mavcal.sources.types.ImuLog`).

    Raises
    ------
    SourceError
        Unreadable file, no IMU data, or a device that does not answer.
    """
    from mavcal.sources.reader import is_device, read_log

    src = str(source)
    if is_device(src):
        from mavcal.link.live import record_device  # type: ignore[import-not-found,unused-ignore]

        return record_device(src, baud=baud, duration_s=duration_s, heartbeat_timeout_s=heartbeat_timeout_s,
                             param_timeout_s=param_timeout_s, rate_hz=rate_hz, progress=progress, tlog=tlog)
    if tlog is not None:
        raise UsageError("tlog saves a live recording: the source is a log file already")
    return read_log(src, progress=progress)


def prepare(source, options: Options = Options(), *, progress=None, owned: bool = False, params=None) -> Prepared:
    """Read a source and make it ready for the fit (everything before the estimation).

    Undoes the integer truncation of the telemetry, undoes the autopilot's correction with the
    parameters in force at each sample (raw readings; ArduPilot's or PX4's model,
    :func:`mavcal.autopilot.model_for`) and finds the still intervals.

    Parameters
    ----------
    source : str, path-like or ImuLog
        What :func:`open_source` accepts, or an already read :class:`ImuLog`.
    options : Options
        Only ``options.untruncate`` and ``options.still`` are used here.
    progress : callable(done, total), optional
        Passed to :func:`open_source`; an object that also has ``stage(name, done, total)``
        (:class:`mavcal.sources.progress.ProgressPrinter`, :class:`~mavcal.sources.progress.CallbackProgress`)
        is told the later stages too (:data:`STAGE_RECOVER`, :data:`STAGE_SEGMENT`).
    owned : bool
        ``source`` is an :class:`ImuLog` the caller hands over (it has just read it and keeps
        no other use for the readings as read): the truncation is undone in its own arrays
        instead of in a copy of every series (on a 100 MB tlog, 80 MB less), and the series'
        receive times (``log_time_s``, which no later stage reads) are dropped. The values
        are bit-identical either way; a log read here from a path is always owned.
    params : path or mapping of str to float, optional
        The parameters the vehicle held when the log was recorded (a Mission Planner / MAVProxy
        .param file, what ``--params FILE`` gives): the calibration in force of the sensors whose
        parameters the recording lacks (:func:`mavcal.in_force.with_param_file`). Without it, a
        sensor whose calibration in force is not in the recording is judged but never written.

    Returns
    -------
    Prepared
        ``log``, ``raw``, ``segmentation``, ``quantization`` (the telemetry step per
        ``(sensor, instance)``, e.g. ``("accel", 0)``; 0 when not quantised) and
        ``warnings``. Pass it to :func:`calibrate_prepared`, as many times as needed.

    Raises
    ------
    SourceError
        As :func:`open_source`.
    """
    from mavcal.sources.quantization import quantization_step, untruncate_log

    opts = options
    given = isinstance(source, ImuLog)
    own = owned or not given  # nobody else reads it as read: changed in place
    log_ = source if given else open_source(source, progress=progress)
    if params is not None:
        from mavcal.in_force import with_param_file

        log_ = with_param_file(log_, params)
    warnings: list[str] = list(log_.warnings)
    steps = {(s.sensor, s.instance): quantization_step(s) for s in log_.series}
    report(progress, STAGE_RECOVER, 0, 1)
    if opts.untruncate:
        log_, _ = untruncate_log(log_, in_place=own)
    release_free_memory()  # what reading freed (decoding buffers): before the raw readings are made
    raw = model_for(log_).recover_raw(log_)  # ArduPilot's or PX4's correction undone
    if own:
        log_, raw = _without_receive_times(log_, raw)
    report(progress, STAGE_RECOVER, 1, 1)
    warnings += list(raw.warnings)
    report(progress, STAGE_SEGMENT, 0, 1)
    seg = find_still_intervals(raw, opts.still)
    report(progress, STAGE_SEGMENT, 1, 1)
    warnings += list(seg.warnings)
    return Prepared(log_, raw, seg, steps, tuple(warnings))


def _without_receive_times(log_: ImuLog, raw: RawImu) -> tuple[ImuLog, RawImu]:
    """``log_`` and ``raw`` with every series' ``log_time_s`` set to None.

    The receive times serve only the reader (the time base, parameter times); no stage after
    the raw recovery reads them, and on a long tlog they are 8 bytes per message (12 MB of a
    100 MB file, held through the fits). Only for an owned log: whoever hands it over keeps
    no other reference to the series (the values are shared, not copied)."""
    new = {id(s): replace(s, log_time_s=None) for s in log_.series + raw.accel + raw.mag + raw.gyro
           if s.log_time_s is not None}

    def strip(series: tuple[SensorSeries, ...]) -> tuple[SensorSeries, ...]:
        return tuple(new.get(id(s), s) for s in series)

    return (replace(log_, series=strip(log_.series)),
            replace(raw, accel=strip(raw.accel), mag=strip(raw.mag), gyro=strip(raw.gyro)))


# --------------------------------------------------------------------------- chain

def calibrate_source(source, options: Options = Options(), *, progress=None, params=None) -> CalibrationRun:
    """Calibrate from a log or a live vehicle: the whole chain, without writing anything.

    read -> undo truncation -> raw recovery -> still intervals -> joint fit (paper's
    algorithm, refinement, model selection, uncertainty) -> the autopilot's parameters ->
    quality numbers -> quality gates. This is what ``mavcal calibrate`` runs.

    Parameters
    ----------
    source : str, path-like or ImuLog
        A log path (``.tlog``, ``.bin``/``.log``, ``.csv``), a MAVLink device string or an
        already read :class:`ImuLog` (see :func:`open_source`).
    options : Options, optional
        Fit, mapping and gate settings; the defaults are the command line's.
    progress : callable(done, total), optional
        Called as the file is read; an object with a ``stage(name, done, total)`` method
        is told every stage (reading, recovery, segmentation, :data:`STAGE_FIT` counted in
        fits): :func:`mavcal.sources.progress.auto_progress` for a terminal line,
        :class:`mavcal.sources.progress.CallbackProgress` for ``fn(stage, fraction)`` calls.
    params : path or mapping of str to float, optional
        As :func:`prepare`'s (``--params FILE``).

    Returns
    -------
    CalibrationRun
        ``run.verdict`` ("accepted", "partly accepted", "rejected") and ``run.verdicts`` (one
        per sensor); ``run.write_param_file(path)`` writes what ``--param-out`` writes (the
        accepted sensors' parameters) and ``run.params_to_write()`` returns them;
        ``run.quality`` the heading/tilt 95 % bounds and held-out errors; ``run.gates`` the
        quality gates; ``run.to_json()`` the JSON report as a dict. ``run.mapping.new`` holds
        every fitted sensor's values, rejected ones included: not what to write. A vehicle is
        written with :mod:`mavcal.link.writer`; this function never writes.

    Raises
    ------
    SourceError
        Unreadable source, no IMU data, no data of the requested instance.
    InsufficientDataError
        Too few still intervals for any model (the message says which poses are missing).
    MavcalError
        The base of both, and of estimation failures (:mod:`mavcal.errors`).

    Examples
    --------
    >>> from mavcal.pipeline import calibrate_source
    >>> run = calibrate_source("sitl_logs/sitl02.tlog")        # doctest: +SKIP
    >>> run.verdict, round(run.params_to_write()["COMPASS_OFS_X"])  # doctest: +SKIP
    ('accepted', -141)
    """
    return calibrate_prepared(prepare(source, options, progress=progress, params=params), options, progress=progress)


def calibrate_prepared(prep: Prepared, options: Options = Options(), *, progress=None) -> CalibrationRun:
    """The fits, mapping, quality and per-sensor gates for a :class:`Prepared` recording.

    Every accelerometer is judged on its own fit (:mod:`mavcal.core.accel_fit`); it is written
    from its joint fit with compass ``mag_instance`` when that compass is accepted, else
    from its own fit. Every compass is fitted jointly with accelerometer ``accel_instance``
    (so all compasses are in the primary IMU's board frame) and judged on that fit.
    ``options.sensors`` "accel" calibrates the accelerometers alone (also what a log
    without compass gets), "compass" only the compasses. An instance without enough data
    is skipped with a warning.

    Parameters
    ----------
    prep : Prepared
        From :func:`prepare`; it is not changed, so one recording can be fitted with several
        ``options`` (a different model, other gate limits) without reading it again.
    options : Options, optional
        Everything except ``still`` and ``untruncate`` (those act in :func:`prepare`).
    progress : optional
        As :func:`calibrate_source`'s: told :data:`STAGE_FIT` (fits done of fits to do).

    Returns
    -------
    CalibrationRun
        As :func:`calibrate_source`: ``mapping.new`` keyed by ArduPilot parameter name,
        ``quality``, ``gates``.

    Raises
    ------
    SourceError, InsufficientDataError
        As :func:`calibrate_source`, for the primary pair.
    """
    return with_in_force_gates(fit_recording(prep, options, progress=progress))


def with_in_force_gates(run: CalibrationRun) -> CalibrationRun:
    """``run`` with a failed gate for every fitted sensor whose calibration in force is not known
    (:func:`mavcal.in_force.in_force_gates`): judged, never accepted, never written."""
    from mavcal.autopilot.gates import GateReport
    from mavcal.in_force import in_force_gates

    fitted = set(run.gates.by_sensor())
    extra = [g for g in in_force_gates(run.raw, live=run.log.kind == "live") if g.sensor in fitted]
    if not extra:
        return run
    return replace(run, gates=GateReport(tuple(extra) + tuple(run.gates.gates)))
