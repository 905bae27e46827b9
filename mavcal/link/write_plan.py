"""What a parameter write will do and did, as data: the plan checked against the vehicle's table
before anything is sent (:func:`plan_changes`: names, finite values, what an integer parameter
stores, :func:`expected_stored_value`) and the outcome (:class:`ParamResult` per parameter,
:class:`WriteReport` for the write). The protocol run itself is :mod:`mavcal.link.writer`.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from pymavlink import mavutil

from mavcal.autopilot.mavlink import valid_param_name
from mavcal.errors import UnknownParameterError, UsageError
from mavcal.link.params import ParamTable

__all__ = ["ParamResult", "WriteReport", "plan_changes", "expected_stored_value", "same_stored"]

_A = mavutil.mavlink
_INT_RANGE = {_A.MAV_PARAM_TYPE_INT8: (-128, 127), _A.MAV_PARAM_TYPE_INT16: (-32768, 32767),
              _A.MAV_PARAM_TYPE_INT32: (-2147483648, 2147483647)}
_TYPE_NAMES = {_A.MAV_PARAM_TYPE_INT8: "INT8", _A.MAV_PARAM_TYPE_INT16: "INT16",
               _A.MAV_PARAM_TYPE_INT32: "INT32", _A.MAV_PARAM_TYPE_REAL32: "REAL32"}


# ----------------------------------------------------------------------------------------------
# value semantics
# ----------------------------------------------------------------------------------------------
def expected_stored_value(value: float, param_type: int) -> float:
    """The value ArduPilot stores for a PARAM_SET of ``value`` (``AP_Param::set_float``).

    Integer types: add 0.01 (-0.01 for negatives) in float32, clamp to the type's range, and
    truncate toward zero. Everything else: float32 rounding.
    """
    if param_type in _INT_RANGE:
        v = np.float32(value)
        v = np.float32(v + (np.float32(-0.01) if v < 0 else np.float32(0.01)))
        lo, hi = _INT_RANGE[param_type]
        return float(int(min(max(float(v), lo), hi)))
    return float(np.float32(value))


def same_stored(a: float | None, b: float | None) -> bool:
    """Equal as float32 values (the wire format), within one float32 ulp."""
    if a is None or b is None:
        return False
    fa, fb = np.float32(a), np.float32(b)
    if fa == fb:
        return True
    return bool(abs(float(fa) - float(fb)) <= float(np.spacing(np.abs(fb))))


def _check_values(changes: Mapping[str, float], table: ParamTable) -> None:
    bad = []
    for name, value in changes.items():
        v = float(value)
        if not math.isfinite(v):
            bad.append(f"{name}={value!r} is not finite")
            continue
        ptype = table[name][1]
        if ptype in _INT_RANGE:
            lo, hi = _INT_RANGE[ptype]
            stored = expected_stored_value(v, ptype)
            if not (lo <= v <= hi) or abs(stored - v) > 1e-3 * max(1.0, abs(v)):
                bad.append(f"{name} is {_TYPE_NAMES[ptype]}: {v!r} would be stored as {stored:g}")
        elif abs(v) > float(np.finfo(np.float32).max):
            bad.append(f"{name}={v!r} does not fit a float32")
    if bad:
        raise UsageError("refusing to write (nothing was written): " + "; ".join(bad))


def plan_changes(changes: Mapping[str, float], table: ParamTable) -> list[ParamResult]:
    """Check ``changes`` against the vehicle's ``table`` and describe each change.

    Returns
    -------
    list of ParamResult
        Not yet written (``attempts`` 0; ``ok`` True only where nothing changes).

    Raises
    ------
    UnknownParameterError
        A name is not in ``table``.
    UsageError
        A bad name, a non-finite value, or a value an integer parameter cannot hold.
    """
    badnames = [n for n in changes if not valid_param_name(n)]
    if badnames:
        raise UsageError("bad parameter name " + ", ".join(repr(n) for n in badnames))
    unknown = [n for n in changes if n not in table]
    if unknown:
        raise UnknownParameterError(unknown)
    _check_values(changes, table)
    plan = []
    for name, value in changes.items():
        old, ptype = table[name]
        exp = expected_stored_value(float(value), ptype)
        unchanged = same_stored(old, exp)
        plan.append(ParamResult(name=name, old=float(old), requested=float(value), expected=exp,
                                echoed=float(old) if unchanged else None, ok=unchanged, attempts=0))
    return plan


@dataclass(frozen=True)
class ParamResult:
    """The fate of one parameter.

    Attributes
    ----------
    name : str
    old : float
        Value on the vehicle before the write (the backup value).
    requested : float
        Value asked for.
    expected : float
        What the vehicle stores for ``requested`` (float32 rounding, integer conversion).
    echoed : float or None
        Last value the vehicle reported for it (echo or read-back); None if never heard.
    ok : bool
        True if the vehicle holds ``expected`` (confirmed), or nothing had to change.
    attempts : int
        PARAM_SETs sent for the new value (0: unchanged, not written).
    restored : bool or None
        None if no restore touched it; True if restored to ``old`` and verified; False if the
        restore could not be verified (value in doubt).
    restore_attempts : int
        PARAM_SETs sent to restore it.
    """

    name: str
    old: float
    requested: float
    expected: float
    echoed: float | None
    ok: bool
    attempts: int
    restored: bool | None = None
    restore_attempts: int = 0

    @property
    def changed(self) -> bool:
        """True if the value differs from the old one (something had to be written)."""
        return not same_stored(self.old, self.expected)


@dataclass(frozen=True)
class WriteReport:
    """What :func:`write_params` did. Frozen; built once at the end.

    Attributes
    ----------
    results : tuple of ParamResult
        One per requested parameter, in request order.
    backup_path : str or None
        The backup written before the first PARAM_SET (None for a dry run or no change).
    complete : bool
        Every change written and verified by read-back.
    restored : bool
        A failure happened and every attempted parameter was restored and verified.
    in_doubt : tuple of str
        Parameters whose value on the vehicle is unknown (restore not verified).
    reboot_required : tuple of str
        Changed parameters that only take effect after a reboot.
    force_saved : tuple of str
        Force-saves acknowledged by the vehicle (``"compass"``, ``"accel"``).
    force_save_failed : tuple of str
        Force-saves not acknowledged (or refused: the words are in ``message``).
    force_save_skipped : tuple of str
        Force-saves not sent because that sensor kind's values break a limit.
    out_of_range : tuple of str
        One line per value outside its limit that was written anyway (``allow_out_of_range``).
    dry_run : bool
        Nothing was written.
    message : str
        One-line summary.
    """

    results: tuple[ParamResult, ...]
    backup_path: str | None
    complete: bool
    restored: bool = False
    in_doubt: tuple[str, ...] = ()
    reboot_required: tuple[str, ...] = ()
    force_saved: tuple[str, ...] = ()
    force_save_failed: tuple[str, ...] = ()
    dry_run: bool = False
    message: str = ""
    force_save_skipped: tuple[str, ...] = ()
    out_of_range: tuple[str, ...] = ()

    @property
    def needs_reboot(self) -> bool:
        """True if some changed parameter needs a reboot to take effect."""
        return bool(self.reboot_required)

    @property
    def changed(self) -> tuple[ParamResult, ...]:
        """Results of the parameters whose value had to change."""
        return tuple(r for r in self.results if r.changed)

    @property
    def total_attempts(self) -> int:
        """PARAM_SETs sent in total (writes and restores)."""
        return sum(r.attempts + r.restore_attempts for r in self.results)
