"""From a log or a live link to ArduPilot parameters; this module only chains the stages:

    open_source (:mod:`mavcal.sources.reader` / :mod:`mavcal.link.live`)
    -> prepare (untruncate, :mod:`mavcal.ardupilot.recover`, :mod:`mavcal.segment`)
    -> calibrate (:mod:`mavcal.core`) -> map (:mod:`mavcal.ardupilot.mapping`)
    -> quality (:mod:`mavcal.quality`) -> gates (:mod:`mavcal.ardupilot.gates`).

:func:`calibrate_source` is what ``mavcal calibrate``, the capture command and the
MAVProxy module call. It never writes to a vehicle (that is :mod:`mavcal.link.writer`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot import gates as gates_mod
from mavcal.ardupilot.mapping import AccelMapping, ParamMapping, combine, map_accel, map_calibration
from mavcal.ardupilot.recover import RawImu, recover_raw
from mavcal.core.accel_fit import AccelFit, fit_accel, holdout_accel_mps2
from mavcal.core.calibrate import calibrate
from mavcal.core.models import MODEL_CHAIN, MODELS
from mavcal.core.stats import IntervalStats, interval_stats
from mavcal.core.types import Calibration
from mavcal.errors import EXIT_PARTIAL, EstimationError, GateError, InsufficientDataError, MavcalError, SourceError
from mavcal.quality import Quality, accel_tilt_bounds, holdout_errors, quality_of
from mavcal.segment import Segmentation, StillConfig, find_still_intervals
from mavcal.sources.progress import ProgressFn, report
from mavcal.sources.types import ImuLog
from mavcal.workers import ForkPool

log = logging.getLogger(__name__)

# the stages a progress object with a ``stage`` method is told of (mavcal.sources.progress)
STAGE_RECOVER = "recovering raw readings"
STAGE_SEGMENT = "finding still intervals"
STAGE_FIT = "fitting"

EXIT_ALL_ACCEPTED, EXIT_NONE_ACCEPTED = 0, GateError.exit_code

__all__ = ["Options", "Prepared", "CalibrationRun", "Quality", "open_source", "prepare", "calibrate_source",
           "calibrate_prepared", "STAGE_RECOVER", "STAGE_SEGMENT", "STAGE_FIT", "refusal_verdicts"]


@dataclass(frozen=True)
class Options:
    """Everything :func:`calibrate_source` can be told; every field is optional.

    ``Options()`` is what ``mavcal calibrate`` uses by default; change fields with
    ``Options(model="ardupilot")`` or :func:`dataclasses.replace`.

    Attributes
    ----------
    still : StillConfig
        Thresholds of the still-interval detector (:class:`mavcal.segment.StillConfig`).
    method : str
        The paper's block-step variant: ``"ncdr"``, ``"ncar"``, ``"fcar"`` or ``"dcar"``.
    tol : float
        Stop rule of the block steps, J'_{k-1} - J'_k < tol.
    model : str
        ``"auto"`` (model selection by Wald tests), or one of ``"full"``, ``"diag-accel"``,
        ``"ardupilot"``, ``"offsets-scales"`` (:mod:`mavcal.core.models`).
    seed : int
        Seed of the random restarts and of the uncertainty draws (results are repeatable).
    accel_instance, mag_instance : int
        The primary pair: its accelerometer defines the board frame, its quality numbers are
        :attr:`CalibrationRun.quality`.
    all_instances : bool
        Also calibrate every other IMU (jointly with compass ``mag_instance``) and every other
        compass (with IMU ``accel_instance``); False: the primary pair only.
    field_mgauss : float or None
        Earth's field magnitude in mGauss; None: the World Magnetic Model at ``location``
        (or the log's position), else the current calibration's.
    location : (lat_deg, lon_deg, alt_m) or None
        Where the log was recorded, when the log has no position.
    orient_tol_deg : float
        Largest misalignment for a standard COMPASS_ORIENT value.
    allow_custom : bool
        Allow a custom rotation (CUST_ROT, orientation 101/102) beyond ``orient_tol_deg``.
    force_external : bool
        Treat every compass as external (write its orientation).
    untruncate : bool
        Undo the integer truncation of RAW_IMU / SCALED_IMU readings.
    uncertainty_draws : int
        Parameter draws for the 95 % heading/tilt bounds (fewer: faster, coarser).
    holdout : bool
        Compute the leave-one-interval-out (held-out) errors; costs one refit per interval.
    gates : GateConfig
        Limits of the quality gates (:class:`mavcal.ardupilot.gates.GateConfig`).
    workers : int
        Processes for the fits (:class:`mavcal.workers.ForkPool`): with more than 1, the
        accelerometer/compass pairs, then the accelerometers, are fitted in that many forked
        worker processes; the results are the same to the bit. 1 (default): in this process,
        as a host application with its own threads (MAVProxy) needs.
    """

    still: StillConfig = StillConfig()
    method: str = "ncar"
    tol: float = 1e-4
    model: str = "auto"
    seed: int = 0
    accel_instance: int = 0  # the primary pair: the board frame and the quality numbers
    mag_instance: int = 0
    all_instances: bool = True  # also every other IMU (with compass 0) and compass (with IMU 0)
    field_mgauss: float | None = None
    location: tuple[float, float, float] | None = None
    orient_tol_deg: float = 1.0
    allow_custom: bool = True
    force_external: bool = False
    untruncate: bool = True
    uncertainty_draws: int = 200
    holdout: bool = True
    gates: gates_mod.GateConfig = gates_mod.GateConfig()
    workers: int = 1  # fit the pairs, then the accelerometers, in this many forked processes (mavcal.workers)
    sensors: str = "both"  # "accel": accelerometers alone (no compass needed); "compass": compasses only
    only_instances: tuple[int, ...] | None = None  # with sensors "accel"/"compass": just these instances


@dataclass(frozen=True, eq=False)
class CalibrationRun:
    """Everything one run of :func:`calibrate_source` produced (read-only).

    Attributes
    ----------
    source : str
        The log path or device string.
    log : ImuLog
        The readings as read (:class:`mavcal.sources.types.ImuLog`).
    raw : RawImu
        The readings with ArduPilot's correction undone (:class:`mavcal.ardupilot.recover.RawImu`).
    segmentation : Segmentation
        The still intervals found and their coverage (:class:`mavcal.segment.Segmentation`).
    intervals_used : tuple of int
        Indices into ``segmentation.intervals`` of the intervals the primary fit used.
    calibration : Calibration
        The fitted sensor models of the primary pair, in the paper's symbols
        (:class:`mavcal.core.types.Calibration`: ``accel.gain`` K_a, ``accel.bias`` b_a,
        ``mag.gain`` K_m, ``field`` h, ``orientations`` R_i, ``param_cov``, ``model``).
    mapping : ParamMapping
        The ArduPilot parameters (:class:`mavcal.ardupilot.mapping.ParamMapping`).
        ``mapping.new`` is a mapping **keyed by parameter name**, one entry per axis
        (``"COMPASS_OFS_X"``, ``"INS_ACCSCAL_Z"``, ``"COMPASS_ORIENT"`` ...) to the value to
        write, for every sensor calibrated; ``mapping.old`` holds the values in force in the
        log under the same names (None when unknown); ``mapping.changed()`` only the names
        whose value changes; ``mapping.notes`` what was decided and why, in words.
    quality : Quality
        The primary pair's quality numbers (:class:`mavcal.quality.Quality`):
        ``heading_95_deg`` / ``tilt_95_deg`` (95 % bound of the worst heading/tilt error the
        written parameters leave over the flight envelope, degrees),
        ``holdout_accel_mps2`` / ``holdout_mag_mgauss`` (held-out error, NaN when not
        computed) and ``chi2_dof`` (J'/dof, about 1 when the noise model explains the data).
    gates : GateReport
        Every quality gate (:class:`mavcal.ardupilot.gates.GateReport`): ``gates.passed``,
        ``gates.failures()`` (each with ``sensor``, ``name``, ``value``, ``limit``, ``reason``)
        and ``gates.by_sensor()`` (keyed ``"accel0"``, ``"compass1"``, ``"data"`` ...).
    params_before : dict of str to float
        Every parameter in force at the end of the log, keyed by name.
    warnings : tuple of str
        What was skipped or assumed, in words.
    others : tuple of CalibrationRun
        The fits of the other accelerometer/compass pairs (``Options.all_instances``);
        their parameters and gates are already merged into ``mapping`` and ``gates``.
    """

    source: str
    log: ImuLog
    raw: RawImu
    segmentation: Segmentation
    intervals_used: tuple[int, ...]
    calibration: Calibration | None  # None when the accelerometers were calibrated alone
    mapping: ParamMapping
    quality: Quality
    gates: gates_mod.GateReport
    params_before: dict[str, float]
    warnings: tuple[str, ...] = ()
    others: tuple[CalibrationRun, ...] = ()  # the fits of the other instances (all_instances)
    accel_fits: tuple[tuple[int, AccelFit], ...] = ()  # each accelerometer's own fit (its verdict)

    @property
    def accepted(self) -> bool:
        """Every sensor accepted."""
        return self.gates.passed

    @property
    def verdicts(self) -> tuple[gates_mod.SensorVerdict, ...]:
        """One verdict per sensor with data (accepted, or rejected with reasons)."""
        return self.gates.verdicts()

    @property
    def exit_code(self) -> int:
        """0 every sensor accepted, 7 some accepted and some rejected, 4 none accepted."""
        v = self.verdicts
        n_ok = sum(x.accepted for x in v)
        return EXIT_ALL_ACCEPTED if n_ok == len(v) else EXIT_PARTIAL if n_ok else EXIT_NONE_ACCEPTED

    def params_to_write(self, force: bool = False) -> dict[str, float]:
        """The accepted sensors' parameters (every sensor's with ``force``); a rejected sensor
        keeps its current values on the vehicle."""
        return dict(self.mapping.new) if force else self.mapping.restricted(self.gates.accepted_sensors())

    def rejected_params(self) -> dict[str, str]:
        """Parameter name -> the failed gates of its (rejected) sensor, e.g. ``"compass1 diagonal"``."""
        by = self.mapping.by_sensor()
        out: dict[str, str] = {}
        for s, gs in self.gates.by_sensor().items():
            failed = ", ".join(f"{s} {g.name}" for g in gs if not g.ok)
            if failed:
                out.update({n: failed for n in by.get(s, {})})
        return out

    def to_json(self) -> dict:
        """The JSON report (:func:`mavcal.report.json.to_json`)."""
        from mavcal.report.json import to_json

        return to_json(self)


@dataclass(frozen=True, eq=False)
class Prepared:
    """A log read, de-truncated, raw-recovered and segmented (the input of the fit)."""

    log: ImuLog
    raw: RawImu
    segmentation: Segmentation
    quantization: dict[tuple[str, int], float]
    warnings: tuple[str, ...]


# --------------------------------------------------------------------------- read

def open_source(source, *, baud: int = 115200, duration_s: float = 10.0, heartbeat_timeout_s: float = 5.0,
                param_timeout_s: float = 30.0, rate_hz: float = 50.0,
                progress: ProgressFn | None = None) -> ImuLog:
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
                             param_timeout_s=param_timeout_s, rate_hz=rate_hz, progress=progress)
    return read_log(src, progress=progress)


def prepare(source, options: Options = Options(), *, progress=None, owned: bool = False) -> Prepared:
    """Read a source and make it ready for the fit (everything before the estimation).

    Undoes the integer truncation of the telemetry, undoes ArduPilot's correction with the
    parameters in force at each sample (raw readings) and finds the still intervals.

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
        instead of in a copy of every series (on a 100 MB tlog, 80 MB less). The values are
        bit-identical either way; a log read here from a path is always owned.

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
    warnings: list[str] = list(log_.warnings)
    steps = {(s.sensor, s.instance): quantization_step(s) for s in log_.series}
    report(progress, STAGE_RECOVER, 0, 1)
    if opts.untruncate:
        log_, _ = untruncate_log(log_, in_place=own)
    raw = recover_raw(log_)
    report(progress, STAGE_RECOVER, 1, 1)
    warnings += list(raw.warnings)
    report(progress, STAGE_SEGMENT, 0, 1)
    seg = find_still_intervals(raw, opts.still)
    report(progress, STAGE_SEGMENT, 1, 1)
    warnings += list(seg.warnings)
    return Prepared(log_, raw, seg, steps, tuple(warnings))


# --------------------------------------------------------------------------- chain

def calibrate_source(source, options: Options = Options(), *, progress=None) -> CalibrationRun:
    """Calibrate from a log or a live vehicle: the whole chain, without writing anything.

    read -> undo truncation -> raw recovery -> still intervals -> joint fit (paper's
    algorithm, refinement, model selection, uncertainty) -> ArduPilot parameters ->
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

    Returns
    -------
    CalibrationRun
        ``run.mapping.new`` maps each ArduPilot parameter name (``"COMPASS_OFS_X"``,
        ``"INS_ACCSCAL_Y"`` ...) to its new value, for every accelerometer and compass with
        enough data; ``run.quality`` the heading/tilt 95 % bounds and held-out errors;
        ``run.gates`` the quality gates (``run.accepted`` is ``run.gates.passed``);
        ``run.to_json()`` the JSON report as a dict. Write a ``.param`` file with
        :func:`mavcal.ardupilot.paramfile.write_param_file` (``run.mapping.new``) and a
        vehicle with :mod:`mavcal.link.writer`; this function never writes.

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
    >>> run.accepted, round(run.mapping.new["COMPASS_OFS_X"])  # doctest: +SKIP
    (True, -141)
    """
    return calibrate_prepared(prepare(source, options, progress=progress), options, progress=progress)


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
    opts, warnings = _resolve(prep, options)
    if opts.sensors == "accel":
        return _accel_only(prep, opts, warnings, progress)
    ai = opts.accel_instance
    pairs = _other_pairs(prep, opts)
    n_fits = 1 + len(pairs) + (len(prep.raw.accel_instances()) if opts.sensors == "both" else 0)
    report(progress, STAGE_FIT, 0, n_fits)
    stats: _StatsCache = {}
    jobs = [opts] + [replace(options, accel_instance=a, mag_instance=m, holdout=opts.holdout and a == ai)
                     for a, m in pairs]
    with ForkPool((prep, stats), opts.workers) as pool:
        if pool.workers > 1:
            _prefill_stats(prep, jobs, stats, opts.sensors == "both")
        runs = pool.map(_pair_job, jobs[:1] if pool.workers == 1 else jobs,  # in turn: the primary first
                        done=lambda k: report(progress, STAGE_FIT, k, n_fits))
        if not runs[0][0]:
            raise runs[0][1]
        if pool.workers == 1:
            runs += pool.map(_pair_job, jobs[1:], done=lambda k: report(progress, STAGE_FIT, 1 + k, n_fits))
        primary = _attach(runs[0][1], prep)
        warnings += list(primary.warnings)
        others = []
        for (a, m), (ok, r) in zip(pairs, runs[1:]):
            if ok:
                others.append(_attach(r, prep))
            else:
                warnings.append(f"accelerometer {a} / compass {m} not calibrated: {r}")
        compass_runs = [primary] + [r for r in others if r.mapping.accel[0].instance == ai]
        gates = [g for r in compass_runs for g in r.gates.gates]
        compasses = [r.mapping.compass[0] for r in compass_runs]
        accels, fits, accel_gates = (_judge_accels(pool, prep, opts, [primary] + others, warnings,
                                                   lambda k: report(progress, STAGE_FIT, 1 + len(pairs) + k, n_fits))
                                     if opts.sensors == "both" else ([], [], []))
    report(progress, STAGE_FIT, n_fits, n_fits)
    notes = list(primary.mapping.notes) + [f"compass {c.instance}: {c.orientation_note}" for c in compasses[1:]]
    mapping = combine(accels, compasses, primary.params_before, notes)
    return replace(primary, mapping=mapping, gates=gates_mod.GateReport(tuple(accel_gates + gates)),
                   others=tuple(others), warnings=tuple(dict.fromkeys(warnings)), accel_fits=tuple(fits))


def _judge_accels(pool: ForkPool, prep: Prepared, opts: Options, runs: list[CalibrationRun], warnings: list[str],
                  done) -> tuple[list[AccelMapping], list[tuple[int, AccelFit]], list[gates_mod.Gate]]:
    """Every accelerometer judged on its own fit, written from its joint fit with compass
    ``opts.mag_instance`` (in ``runs``, the primary first) when that compass is accepted."""
    mi = opts.mag_instance
    mi_ok = all(g.ok for g in runs[0].gates.gates)
    joint = {r.mapping.accel[0].instance: r for r in runs if r.mapping.compass[0].instance == mi}
    insts = prep.raw.accel_instances()
    judged = pool.map(_accel_job, [(opts, a, joint[a].mapping.accel[0] if a in joint and mi_ok else None)
                                   for a in insts], done=done)
    accels: list[AccelMapping] = []
    fits: list[tuple[int, AccelFit]] = []
    gates: list[gates_mod.Gate] = []
    for a, (ok, out) in zip(insts, judged):
        if not ok:
            warnings.append(f"accelerometer {a} not calibrated: {out}")
            continue
        am, ag, fit, _, _ = out
        accels.append(am)
        fits.append((a, fit))
        gates += ag
        if a in joint and not mi_ok:
            warnings.append(f"accelerometer {a} written from its own fit: compass {mi}, its joint partner, "
                            "was rejected")
    return accels, fits, gates


def _prefill_stats(prep: Prepared, jobs: list[Options], stats: _StatsCache, accels: bool) -> None:
    """Every interval statistic the fit jobs will ask for, computed here before the workers
    fork: each is computed once (not once per worker) and its full-length working arrays
    are this process's, not one more copy per worker. A job whose data are refused raises
    that itself, later."""
    wanted = []
    for o in jobs:
        try:
            used = _intervals_of_pair(prep, o.accel_instance, o.mag_instance)
        except MavcalError:
            continue
        wanted += [("accel", o.accel_instance, used), ("mag", o.mag_instance, used)]
    if accels:
        for a in prep.raw.accel_instances():
            try:
                wanted.append(("accel", a, _accel_sets(prep, a)[0]))
            except MavcalError:
                continue
    for kind, inst, used in wanted:
        try:
            _stats_of(prep, stats, kind, inst, used)
        except MavcalError:
            continue


_Shared = tuple[Prepared, "_StatsCache"]  # what the fit jobs share (inherited by forked workers)


def _pair_job(shared: _Shared, opts: Options) -> CalibrationRun:
    """One accelerometer/compass pair (:func:`_calibrate_pair`) without the readings (a worker
    sends back only the fit: :func:`_attach` puts the recording back)."""
    prep, stats = shared
    return replace(_calibrate_pair(prep, opts, stats), log=None, raw=None, segmentation=None)


def _attach(run: CalibrationRun, prep: Prepared) -> CalibrationRun:
    return replace(run, log=prep.log, raw=prep.raw, segmentation=prep.segmentation)


def _accel_job(shared: _Shared, item: tuple[Options, int, AccelMapping | None]):
    """One accelerometer judged on its own fit (:func:`_judge_accel`)."""
    prep, stats = shared
    opts, a, joint = item
    return _judge_accel(prep, opts, a, joint, stats)


def _other_pairs(prep: Prepared, opts: Options) -> list[tuple[int, int]]:
    """The accelerometer/compass pairs fitted besides the primary one (``opts.all_instances``)."""
    ai, mi = opts.accel_instance, opts.mag_instance
    pairs: list[tuple[int, int]] = []
    if opts.all_instances:
        if opts.sensors == "both":
            pairs += [(a, mi) for a in prep.raw.accel_instances() if a != ai]
        pairs += [(ai, m) for m in _wanted(prep.raw.mag_instances(), opts, "compass") if m != mi]
    return pairs


def _wanted(instances, opts: Options, kind: str) -> list[int]:
    inst = list(instances)
    if opts.sensors == kind and opts.only_instances is not None:
        inst = [i for i in inst if i in opts.only_instances]
    return inst


def _resolve(prep: Prepared, options: Options) -> tuple[Options, list[str]]:
    """The options as they apply to this log (a log without compass: accelerometers alone)."""
    opts, warnings = options, []
    if opts.sensors not in ("both", "accel", "compass"):
        raise MavcalError(f"sensors must be both, accel or compass; got {opts.sensors!r}")
    if opts.sensors == "both" and not prep.raw.mag_instances():
        warnings.append("the log has no compass data: the accelerometers were calibrated alone")
        opts = replace(opts, sensors="accel", only_instances=None)
    if opts.sensors in ("accel", "compass") and opts.only_instances is not None:
        have = prep.raw.accel_instances() if opts.sensors == "accel" else prep.raw.mag_instances()
        missing = [i for i in opts.only_instances if i not in have]
        if missing:
            raise SourceError(f"{prep.log.source}: no {opts.sensors} {', '.join(map(str, missing))} data "
                              f"(the log has {opts.sensors} {', '.join(map(str, have)) or 'none'})")
        first = opts.only_instances[0]
        opts = replace(opts, **({"accel_instance": first} if opts.sensors == "accel" else {"mag_instance": first}))
    return opts, warnings


def refusal_verdicts(prep: Prepared, error: Exception, options: Options = Options()
                     ) -> tuple[gates_mod.SensorVerdict, ...]:
    """A verdict for every sensor with data of a recording that could not be calibrated at all
    (``error``: the refusal): each rejected, with how many still intervals it has and ``error``."""
    seg, raw, none = prep.segmentation, prep.raw, np.empty((0, 3))
    ai = options.accel_instance
    out = []
    for kind, label, insts in (("accel", "accel", raw.accel_instances()), ("compass", "compass",
                                                                           raw.mag_instances())):
        if options.sensors not in ("both", kind):
            continue
        for i in _wanted(insts, options, kind):
            if kind == "accel":
                used = [iv for iv in seg.intervals if iv.accel_mps2.get(i, none).shape[0] >= 2]
                what = f"accelerometer {i} data"
            else:
                used = [iv for iv in seg.intervals if iv.mag_mgauss.get(i, none).shape[0] >= 2
                        and iv.accel_mps2.get(ai, none).shape[0] >= 2]
                what = f"compass {i} and accelerometer {ai} data"
            dirs = np.array([iv.gravity_dir for iv in used]).reshape(-1, 3)
            first = (f"not calibrated: {len(used)} still interval(s) with {what}, in "
                     f"{_n_orientations(dirs, seg) if len(used) else 0} distinct orientation(s)")
            out.append(gates_mod.SensorVerdict(f"{label}{i}", False, tuple(dict.fromkeys([first, str(error)]))))
    return tuple(out)


def _blind_cal(prep: Prepared) -> list[str]:
    """The refusal's reason when the log holds calibration prompts but no IMU data during them."""
    return [f"the log holds ArduPilot's accelerometer calibration ({a:.1f}..{b:.1f} s: 'Place vehicle' prompts) "
            "but no IMU data during it (the ground station stopped streaming RAW_IMU?), so its poses are lost; "
            "record the IMU stream while calibrating" for a, b in prep.raw.accel_cal_without_imu]


def _with_blind_cal(prep: Prepared, exc: MavcalError) -> MavcalError:
    """``exc``, or (when the log holds calibration prompts without IMU data) an
    InsufficientDataError that gives that reason as well."""
    return InsufficientDataError("; ".join([str(exc)] + _blind_cal(prep))) if _blind_cal(prep) else exc


def _accel_sets(prep: Prepared, a: int) -> tuple[list[int], list[np.ndarray]]:
    none = np.empty((0, 3))
    used = [k for k, iv in enumerate(prep.segmentation.intervals) if iv.accel_mps2.get(a, none).shape[0] >= 2]
    if prep.raw.get("accel", a) is None:
        raise SourceError(f"{prep.log.source}: no accelerometer {a} data")
    if not used:
        raise InsufficientDataError(f"{prep.log.source}: no still interval with accelerometer {a} data; "
                                    + "; ".join(list(prep.segmentation.coverage.messages) + _blind_cal(prep)))
    return used, [prep.segmentation.intervals[k].accel_mps2[a] for k in used]


_StatsCache = dict[tuple[str, int, tuple[int, ...]], IntervalStats]


def _stats_of(prep: Prepared, cache: _StatsCache, kind: str, inst: int, used: list[int]) -> IntervalStats:
    """The interval statistics (:func:`mavcal.core.stats.interval_stats`, per interval too) of
    sensor ``kind`` ``inst`` over the intervals ``used``, computed once per run: the pairs of
    one accelerometer or compass, its own fit and the held-out checks share them (the same
    numbers, to the bit, as each computing them from the readings)."""
    key = (kind, inst, tuple(used))
    if key not in cache:
        q = prep.quantization.get((kind, inst), 0.0)
        ivs = prep.segmentation.intervals
        sets = [ivs[k].accel_mps2[inst] if kind == "accel" else ivs[k].mag_mgauss[inst] for k in used]
        cache[key] = interval_stats(sets, f"{kind}_sets", noise_floor=q / np.sqrt(12) if q else None,
                                    per_interval=True)
    return cache[key]


def _judge_accel(prep: Prepared, opts: Options, a: int, joint: AccelMapping | None, stats: _StatsCache):
    """Accelerometer ``a`` on its own: its fit, written values (``joint``'s when given, else
    its own), gates, (tilt 95 %, nominal) and held-out error."""
    used, acc = _accel_sets(prep, a)
    q = prep.quantization.get(("accel", a), 0.0)
    floor = q / np.sqrt(12) if q else None
    try:
        st = _stats_of(prep, stats, "accel", a, used)
        fit = fit_accel(st)
    except (InsufficientDataError, EstimationError) as exc:
        raise _with_blind_cal(prep, exc) from None
    am = joint if joint is not None else map_accel(fit.gain, fit.bias,
                                                   fw.accel_cal_from_params(prep.log.params.snapshot(), a), a)
    tilt = accel_tilt_bounds(fit, am, opts.uncertainty_draws, opts.seed)
    ho = holdout_accel_mps2(acc, noise_floor=floor, start=fit, stats=st) if opts.holdout else float("nan")
    dirs = np.array([prep.segmentation.intervals[k].gravity_dir for k in used])
    n_orient = _n_orientations(dirs, prep.segmentation)
    gates = gates_mod.accel_gates(am, n_intervals=len(used), n_orientations=n_orient, tilt_95_deg=tilt[0],
                                  holdout_mps2=ho, config=opts.gates)
    return am, gates, fit, tilt, ho


def _n_orientations(dirs: np.ndarray, seg: Segmentation) -> int:
    """Distinct gravity directions among ``dirs`` (greedy clusters of the segmentation's size)."""
    if len(dirs) == len(seg.intervals):
        return seg.coverage.n_orientations
    cos_c = np.cos(np.radians(30.0))
    centres: list[np.ndarray] = []
    for d in dirs:
        if not any(float(d @ c) > cos_c for c in centres):
            centres.append(d)
    return len(centres)


def _accel_only(prep: Prepared, opts: Options, warnings: list[str], progress=None) -> CalibrationRun:
    """Every wanted accelerometer calibrated from its own intervals alone."""
    params_now = prep.log.params.snapshot()
    accels, gates, fits = [], [], []
    quality = None
    first_used: tuple[int, ...] = ()
    wanted = _wanted(prep.raw.accel_instances(), opts, "accel")
    if not wanted:
        raise SourceError(f"{prep.log.source}: no accelerometer data")
    errors = []
    for k, a in enumerate(wanted):
        report(progress, STAGE_FIT, k, len(wanted))
        try:
            am, ag, fit, tilt, ho = _judge_accel(prep, opts, a, None, {})
        except MavcalError as exc:
            errors.append(exc)
            warnings.append(f"accelerometer {a} not calibrated: {exc}")
            continue
        accels.append(am)
        gates += ag
        fits.append((a, fit))
        if quality is None:
            quality = Quality(float("nan"), tilt[0], float("nan"), tilt[1], ho, float("nan"),
                              fit.cost / fit.dof if fit.dof > 0 else float("nan"))
            first_used = tuple(_accel_sets(prep, a)[0])
    report(progress, STAGE_FIT, len(wanted), len(wanted))
    if quality is None:
        raise errors[0]
    if not params_now:
        warnings.append("the log has no parameters: readings were taken as raw and the old values are unknown")
    mapping = combine(accels, [], params_now, [f"accelerometer {am.instance} calibrated alone (no compass)"
                                               for am in accels])
    return CalibrationRun(source=prep.log.source, log=prep.log, raw=prep.raw, segmentation=prep.segmentation,
                          intervals_used=first_used, calibration=None, mapping=mapping, quality=quality,
                          gates=gates_mod.GateReport(tuple(gates)), params_before=params_now,
                          warnings=tuple(dict.fromkeys(list(prep.warnings) + warnings)), accel_fits=tuple(fits))


def _intervals_of_pair(prep: Prepared, ai: int, mi: int) -> list[int]:
    """The still intervals holding samples of both accelerometer ``ai`` and compass ``mi``;
    InsufficientDataError/SourceError when too few for any model."""
    log_, raw, seg = prep.log, prep.raw, prep.segmentation
    none = np.empty((0, 3))
    used = [k for k, iv in enumerate(seg.intervals)
            if iv.accel_mps2.get(ai, none).shape[0] >= 2 and iv.mag_mgauss.get(mi, none).shape[0] >= 2]
    if not used:
        if raw.get("accel", ai) is None:
            raise SourceError(f"{log_.source}: no accelerometer {ai} data")
        if raw.get("mag", mi) is None:
            raise SourceError(f"{log_.source}: no compass {mi} data")
        raise InsufficientDataError(f"{log_.source}: no still intervals found ({len(seg.intervals)} detected, none "
                                    "with both sensors); " + "; ".join(list(seg.coverage.messages) + _blind_cal(prep)))
    n_min = MODELS[MODEL_CHAIN[-1]].min_intervals
    if len(used) < n_min:
        why = "; ".join(_blind_cal(prep) + list(seg.coverage.messages)) \
            or f"{seg.coverage.n_orientations} distinct orientation(s)"
        raise InsufficientDataError(
            f"{log_.source}: {len(used)} still interval(s) with accelerometer {ai} and compass {mi} data; at least "
            f"{n_min} in different orientations are needed ({MODELS['full'].min_intervals} for the full model): {why}")
    return used


def _calibrate_pair(prep: Prepared, options: Options, stats: _StatsCache) -> CalibrationRun:
    """calibrate -> map -> quality -> gates for one accelerometer/compass pair (``stats``:
    the run's interval statistics, :func:`_stats_of`)."""
    opts = options
    log_, seg = prep.log, prep.segmentation
    warnings: list[str] = list(prep.warnings)
    ai, mi = opts.accel_instance, opts.mag_instance
    used = _intervals_of_pair(prep, ai, mi)
    acc = [seg.intervals[k].accel_mps2[ai] for k in used]
    mag = [seg.intervals[k].mag_mgauss[mi] for k in used]
    qa, qm = prep.quantization.get(("accel", ai), 0.0), prep.quantization.get(("mag", mi), 0.0)
    noise_floor = (qa / np.sqrt(12) if qa else None, qm / np.sqrt(12) if qm else None)
    try:
        sa, sm = _stats_of(prep, stats, "accel", ai, used), _stats_of(prep, stats, "mag", mi, used)
        cal = calibrate(sa, sm, method=opts.method, tol=opts.tol, seed=opts.seed, model=opts.model)
    except (InsufficientDataError, EstimationError) as exc:
        raise _with_blind_cal(prep, exc) from None
    params_now = log_.params.snapshot()
    if not params_now:
        warnings.append("the log has no parameters: readings were taken as raw and the old values are unknown")
    mapping = map_calibration(cal, params_now, np.array([m.mean(0) for m in mag]), accel_instance=ai,
                              mag_instance=mi, location=opts.location or log_.position,
                              field_mgauss=opts.field_mgauss, orient_tol_deg=opts.orient_tol_deg,
                              allow_custom=opts.allow_custom, force_external=opts.force_external)
    am, cm = mapping.accel[0], mapping.compass[0]
    ho = (holdout_errors(acc, mag, cal, method=opts.method, tol=opts.tol, seed=opts.seed, noise_floor=noise_floor,
                         stats=(sa, sm)) if opts.holdout else (float("nan"), float("nan")))
    quality = quality_of(cal, am, cm, am.old.board_matrix, opts.uncertainty_draws, opts.seed, ho)
    dirs = np.array([seg.intervals[k].gravity_dir for k in used])
    report = gates_mod.GateReport(tuple(gates_mod.compass_gates(
        cm, params_now, n_intervals=len(used), n_orientations=_n_orientations(dirs, seg),
        heading_95_deg=quality.heading_95_deg, holdout_mgauss=ho[1], config=opts.gates,
        fit_converged=cal.converged,
        fit_message=cal.certificate.reason if cal.certificate is not None and cal.certificate.reason else cal.message)))
    return CalibrationRun(source=log_.source, log=log_, raw=prep.raw, segmentation=seg, intervals_used=tuple(used),
                          calibration=cal, mapping=mapping, quality=quality, gates=report, params_before=params_now,
                          warnings=tuple(dict.fromkeys(warnings)))
