"""What the calibration of one recording takes and gives: :class:`Options` (in),
:class:`Prepared` (a recording ready for the fit) and :class:`CalibrationRun` (out), and the
names of the stages a progress object is told of. :mod:`mavcal.pipeline` re-exports them."""
from __future__ import annotations

from dataclasses import dataclass

from mavcal.autopilot import gates as gates_mod
from mavcal.autopilot.mapping import ParamMapping
from mavcal.autopilot.raw import RawImu
from mavcal.core.accel_fit import AccelFit
from mavcal.core.types import Calibration
from mavcal.coverage import KeptParameter
from mavcal.errors import EXIT_PARTIAL, GateError
from mavcal.judging.quality import Quality
from mavcal.segment import Segmentation, StillConfig
from mavcal.sources.types import ImuLog

# the stages a progress object with a ``stage`` method is told of (mavcal.sources.progress)
STAGE_RECOVER = "recovering raw readings"
STAGE_SEGMENT = "finding still intervals"
STAGE_FIT = "fitting"

EXIT_ALL_ACCEPTED, EXIT_NONE_ACCEPTED = 0, GateError.exit_code
#: :attr:`CalibrationRun.verdict`
VERDICT_ACCEPTED, VERDICT_PARTLY, VERDICT_REJECTED = "accepted", "partly accepted", "rejected"

__all__ = ["Options", "Prepared", "CalibrationRun", "STAGE_RECOVER", "STAGE_SEGMENT", "STAGE_FIT",
           "EXIT_ALL_ACCEPTED", "EXIT_NONE_ACCEPTED", "VERDICT_ACCEPTED", "VERDICT_PARTLY", "VERDICT_REJECTED"]


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
        Limits of the quality gates (:class:`mavcal.autopilot.gates.GateConfig`).
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
        The readings with the autopilot's correction undone (:class:`mavcal.autopilot.raw.RawImu`).
    segmentation : Segmentation
        The still intervals found and their coverage (:class:`mavcal.segment.Segmentation`).
    intervals_used : tuple of int
        Indices into ``segmentation.intervals`` of the intervals the primary fit used.
    calibration : Calibration
        The fitted sensor models of the primary pair, in the paper's symbols
        (:class:`mavcal.core.types.Calibration`: ``accel.gain`` K_a, ``accel.bias`` b_a,
        ``mag.gain`` K_m, ``field`` h, ``orientations`` R_i, ``param_cov``, ``model``).
    mapping : ParamMapping
        The autopilot's parameters (:class:`mavcal.autopilot.mapping.ParamMapping`).
        ``mapping.new`` is a mapping **keyed by parameter name**, one entry per axis
        (``"COMPASS_OFS_X"``, ``"INS_ACCSCAL_Z"``, ``"COMPASS_ORIENT"`` ...) to the value to
        write, for every sensor calibrated; ``mapping.old`` holds the values in force in the
        log under the same names (None when unknown); ``mapping.changed()`` only the names
        whose value changes; ``mapping.notes`` what was decided and why, in words.
    quality : Quality
        The primary pair's quality numbers (:class:`mavcal.judging.quality.Quality`):
        ``heading_95_deg`` / ``tilt_95_deg`` (95 % bound of the worst heading/tilt error the
        written parameters leave over the flight envelope, degrees),
        ``holdout_accel_mps2`` / ``holdout_mag_mgauss`` (held-out error, NaN when not
        computed) and ``chi2_dof`` (J'/dof, about 1 when the noise model explains the data).
    gates : GateReport
        Every quality gate (:class:`mavcal.autopilot.gates.GateReport`): ``gates.passed``,
        ``gates.failures()`` (each with ``sensor``, ``name``, ``value``, ``limit``, ``reason``)
        and ``gates.by_sensor()`` (keyed ``"accel0"``, ``"compass1"``, ``"data"`` ...).
    params_before : dict of str to float
        Every parameter in force at the end of the log, keyed by name.
    warnings : tuple of str
        What was skipped or assumed, in words.
    kept : tuple of KeptParameter
        What the poses could not identify when they were all within reach of a vehicle that
        is not turned over (:func:`mavcal.coverage.reach_coverage`): each kept at its current
        value and not written, with why and which pose would identify it (empty otherwise).
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
    kept: tuple[KeptParameter, ...] = ()  # what poses within reach cannot identify: kept, not written

    @property
    def accepted(self) -> bool:
        """Every sensor accepted (False on a partly accepted run: see :attr:`verdict`)."""
        return self.gates.passed

    @property
    def verdict(self) -> str:
        """The run's verdict by name: ``"accepted"`` (every sensor), ``"partly accepted"`` (some
        sensors accepted, their parameters written, the others keep their values) or
        ``"rejected"`` (none); exit codes 0, 7 and 4 of ``mavcal calibrate``."""
        return {EXIT_ALL_ACCEPTED: VERDICT_ACCEPTED, EXIT_PARTIAL: VERDICT_PARTLY}.get(self.exit_code,
                                                                                      VERDICT_REJECTED)

    @property
    def partly_accepted(self) -> bool:
        """Some sensors accepted and some rejected (what the command line calls PARTLY ACCEPTED)."""
        return self.verdict == VERDICT_PARTLY

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
        """The accepted sensors' parameters (every sensor's with ``force``, except a sensor whose
        calibration in force is not known: never); a rejected sensor keeps its current values on
        the vehicle. This is what ``--param-out`` and ``--write`` write."""
        if not force:
            return self.mapping.restricted(self.gates.accepted_sensors())
        unknown = set(self.gates.not_known_sensors())
        drop = {n for s, p in self.mapping.by_sensor().items() if s in unknown for n in p}
        return {n: v for n, v in self.mapping.new.items() if n not in drop}

    def write_param_file(self, path, *, force: bool = False, title: str | None = None):
        """Write the .param file ``mavcal calibrate --param-out`` writes: the accepted sensors'
        parameters (:meth:`params_to_write`), kept parameters and rejected sensors left out.

        Parameters
        ----------
        path : str or path-like
            The file (written atomically: a file already there stays whole until the new one
            replaces it).
        force : bool
            As ``--force``: rejected sensors too, their lines marked with the failed gates
            (never a sensor whose calibration in force is not known).
        title : str, optional
            The first comment line (default ``"mavcal calibration of <source>"``).

        Returns
        -------
        dict of str to float
            The parameters written (empty: nothing accepted, and the file is still written, empty
            of parameters, so check :attr:`verdict` first).

        Raises
        ------
        OutputIsInputError
            ``path`` is the log the run was read from (nothing written).
        SourceError
            The file cannot be written.
        """
        from mavcal.autopilot.paramfile import write_param_file
        from mavcal.outputs import check_outputs

        check_outputs([("the .param file", str(path))], [self.source])  # never over the log it came from
        values = self.params_to_write(force)
        marks = self.rejected_params() if force else {}
        model = self.calibration.model if self.calibration is not None else "accelerometers alone"
        write_param_file(path, values, header=[title or f"mavcal calibration of {self.source}", f"model {model}"],
                         comments={n: f"REJECTED ({why}), written with --force" for n, why in marks.items()
                                   if n in values})
        return values

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
