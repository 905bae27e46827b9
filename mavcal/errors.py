"""Exception hierarchy of mavcal.

Every error a user can provoke with bad input is a :class:`MavcalError`. Each class
carries the process exit code the CLI uses for it, so the CLI maps exceptions to exit
codes in one place and the library never prints.

Exit codes (CLI contract):

==  =========================================================
0   success
2   usage error (bad command line, bad option value)
3   unreadable source, no IMU data, device that does not answer
4   no sensor accepted by the gates, or too little/unusable data
5   parameter write failed and the vehicle was restored
6   parameter write failed and the restore failed too
7   some sensors accepted (written / in the .param), some rejected
8   the vehicle requires MAVLink 2 signing and no key, or a wrong key, was given
9   an output file is an input (or another output): refused before any work
10  ``--connect auto`` found several serial ports that could be the vehicle: choose one
11  the connected vehicle is not the one the log comes from (system id or device ids differ)
==  =========================================================
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

EXIT_PARTIAL = 7  # calibrate: some sensors accepted, some rejected (not an error: outputs are written)


class MavcalError(Exception):
    """Base class of every mavcal error. ``exit_code`` is what the CLI returns."""

    exit_code: int = 1


class UsageError(MavcalError, ValueError):
    """The caller asked for something that does not make sense (bad option, bad value)."""

    exit_code = 2


class UnknownParameterError(UsageError):
    """Some requested names do not exist on the vehicle (nothing was written)."""

    def __init__(self, names: Sequence[str]) -> None:
        self.names = list(names)
        super().__init__("the vehicle has no parameter " + ", ".join(self.names) + " (nothing was written)")


class OutOfRangeError(UsageError):
    """Some values break ArduPilot's limits (nothing was written); ``violations`` lists them
    (each with a one-line ``message``, see :class:`mavcal.autopilot.limits.LimitViolation`)."""

    def __init__(self, violations: Sequence[Any]) -> None:
        self.violations = list(violations)
        super().__init__("refusing to write (nothing was written): "
                         + "; ".join(v.message for v in self.violations) + " (--force writes anyway)")


class OutputIsInputError(UsageError):
    """An output path is an input file (the same file, also through a link) or another output:
    refused before any work, so no input is ever overwritten (:mod:`mavcal.outputs`)."""

    exit_code = 9


class SourceError(MavcalError):
    """A log or device cannot be read: missing, empty, corrupt, no IMU data, no answer."""

    exit_code = 3


class LinkError(SourceError):
    """A live MAVLink device could not be reached or stopped answering."""


class SigningError(LinkError):
    """The vehicle and mavcal disagree on MAVLink 2 signing: the vehicle signs its messages and
    drops our unsigned ones (no key given), or its signatures do not match the key given, or
    a key was given and the vehicle does not sign. Nothing was written."""

    exit_code = 8


class AmbiguousPortError(LinkError):
    """``--connect auto`` found several serial ports that could be the vehicle; ``ports`` lists them
    (nothing was opened). The user chooses one with ``--connect PORT``."""

    exit_code = 10

    def __init__(self, ports: Sequence[str]) -> None:
        self.ports = list(ports)
        super().__init__(f"{len(self.ports)} serial ports could be the vehicle: {'; '.join(self.ports)}: "
                         "choose one with --connect PORT")


class WrongVehicleError(MavcalError):
    """The connected vehicle is not the one the log comes from: its system id or a compass's device
    id differs from the log's. Nothing is written."""

    exit_code = 11


class InsufficientDataError(MavcalError):
    """The data cannot identify the calibration (too few intervals, poor coverage)."""

    exit_code = 4


class SegmentationError(InsufficientDataError):
    """Still-interval detection found too few usable intervals."""


class EstimationError(MavcalError, ValueError):
    """The inputs to the estimator are unusable (NaN, wrong shape, degenerate geometry)."""

    exit_code = 4


class ParameterMappingError(MavcalError):
    """A calibration cannot be expressed as ArduPilot parameters (e.g. mirrored compass)."""

    exit_code = 4


class GateError(MavcalError):
    """The calibration failed a quality gate and was not written (use --force to override)."""

    exit_code = 4


class ParamWriteError(MavcalError):
    """Writing parameters failed; every value already written was restored and verified."""

    exit_code = 5

    def __init__(self, message: str, report: object | None = None) -> None:
        super().__init__(message)
        self.report = report


class RestoreFailedError(ParamWriteError):
    """Writing failed and restoring the previous values failed as well.

    ``in_doubt`` lists the parameter names whose value on the vehicle is unknown.
    """

    exit_code = 6

    def __init__(self, message: str, in_doubt: Sequence[str] = (), report: object | None = None) -> None:
        super().__init__(message, report)
        self.in_doubt = list(in_doubt)


class CalibrationWarning(UserWarning):
    """A result that is usable but suspicious (poor coverage, large uncertainty...)."""
