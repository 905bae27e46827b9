"""The safe parameter writer: write, verify by echo, and undo everything on failure.

Protocol facts it relies on (ArduPilot ``GCS_Param.cpp``, ``AP_Param.cpp``; research note section 8):

* PARAM_SET of an unknown name (or NaN/Inf) is silently ignored up to ArduPilot 4.6: only a timeout shows it. So
  names are checked against the vehicle's own table *before* anything is written. ArduPilot master (PR #31062,
  2025-10) answers them with PARAM_ERROR; a write-denied parameter gets STATUSTEXT "Param write denied (NAME)"
  (since 4.0.4, PR #13823), an echo of the unchanged value, and on master a PARAM_ERROR
  ``MAV_PARAM_ERROR_PERMISSION_DENIED``. Either ends the attempts at once and the failure is reported in the
  vehicle's words.
* Values outside ArduPilot's limits (:mod:`mavcal.autopilot.protocol`) are refused before any write unless
  ``allow_out_of_range``; a sensor kind whose values fail is never force-saved.
* Retries are bounded by time (``budget_s`` per parameter / force-save, after at least ``retries`` attempts), not by
  a fixed count: a lossy link gets as many attempts as fit.
* The vehicle converts the float to the stored type (integers: +/-0.01 in float32, clamp, truncate) and echoes
  PARAM_VALUE (``param_index`` 65535) after storing it; setting the X element of a Vector3 echoes all three (Y or Z
  only themselves). An echo with the right name and the expected value (float32-equal after the conversion) confirms
  a write; anything else is ignored until the attempt times out, then the PARAM_SET is sent again.
* Values go out as float32 (REAL32) to ArduPilot; to PX4 an integer goes byte-wise with its type, and each changed
  CAL_* vector by a detour (:func:`mavcal.autopilot.protocol.detoured_order`).

Sequence of :func:`write_params`:

1. the vehicle's table (fetched, or given) and fresh values of the parameters to change (PARAM_REQUEST_READ);
   unknown names, non-finite values and values an integer parameter would not store exactly are refused before any
   write;
2. a backup ``.param`` of every value about to change, written and fsync'ed before the first PARAM_SET (never
   overwriting an existing file);
3. one parameter at a time (PX4's detours first, its parameter saves waited out: :mod:`mavcal.link.after_write`):
   PARAM_SET, wait for the matching echo, retry. For steps 3-6 the vehicle is kept talking (ATTITUDE at 5 Hz, put
   back to its default rate at the end) and a silence is measured against a limit derived from the link's observed
   loss (:mod:`mavcal.link.silence`); while the vehicle is silent nothing is sent and the budget does not run, and
   the write resumes when it is heard again (within the write budget);
4. force-save (``MAV_CMD_PREFLIGHT_CALIBRATION`` param2=76 compass, param5=76 accel) so the device ids are stored
   with the calibration; a missing ACK is reported, not fatal, and a refusal in the COMMAND_ACK's result words;
5. read every written parameter back once more (PARAM_REQUEST_READ) and compare; then the vehicle must still stream
   (LinkError if it fell silent, :class:`~mavcal.link.after_write.StreamCheck`);
6. on any failure in 3-5: restore every parameter a PARAM_SET was sent for (including the one in flight) from the
   backup values - first waiting for a silent vehicle, up to the restore's own allowance ``restore_wait_s`` - verify
   the restore by echo and read-back, then raise :class:`~mavcal.errors.ParamWriteError` (exit 5) - or
   :class:`~mavcal.errors.RestoreFailedError` (exit 6) naming the parameters in doubt (and how long the vehicle was
   unheard when that is why).

The library logs and never prints; the :class:`WriteReport` is data.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NoReturn

from pymavlink import mavutil

from mavcal.autopilot.protocol import (
    check_limits,
    detour_dwell_s,
    detoured_order,
    failing_kinds,
    needs_reboot,
    vector_group,
)
from mavcal.errors import (
    LinkError,
    OutOfRangeError,
    ParamWriteError,
    RestoreFailedError,
    UnknownParameterError,
    UsageError,
)
from mavcal.link.after_write import Px4Pacing, StreamCheck
from mavcal.link.backup import write_backup
from mavcal.link.connection import Link, as_link, param_to_wire
from mavcal.link.params import (
    ParamTable,
    fetch_all_params,
    fetch_for_write,
    read_params,
    vehicle_param_error,
)
from mavcal.link.silence import SETTLE_S, Patience, VehicleSilence
from mavcal.link.write_plan import ParamResult, WriteReport, expected_stored_value, plan_changes, same_stored

__all__ = ["ParamResult", "WriteReport", "write_params", "plan_changes", "UnknownParameterError",
           "OutOfRangeError", "expected_stored_value", "FORCE_SAVE_KINDS", "DEFAULT_BUDGET_FACTOR", "result_words",
           "RESTORE_WAIT_FACTOR", "fetch_for_write"]

log = logging.getLogger(__name__)

_A = mavutil.mavlink
#: kind -> (param2, param5) of MAV_CMD_PREFLIGHT_CALIBRATION that force-saves it
FORCE_SAVE_KINDS = {"compass": (76.0, 0.0), "accel": (0.0, 76.0)}
#: default time budget per PARAM_SET / force-save, in units of the per-attempt timeout
DEFAULT_BUDGET_FACTOR = 15.0
#: default time the restore waits for a silent vehicle, in units of the write budget
RESTORE_WAIT_FACTOR = 4.0
#: read-back rounds at most (a round is repeated when the vehicle fell silent during it)
_READ_ROUNDS = 10
_DENIED_PREFIX = "Param write denied ("


def result_words(result: int) -> str:
    """A MAV_RESULT in MAVLink's words, e.g. ``"MAV_RESULT_DENIED"``."""
    entry = _A.enums.get("MAV_RESULT", {}).get(int(result))
    return entry.name if entry is not None else f"MAV_RESULT {int(result)}"


# ----------------------------------------------------------------------------------------------
# the write loop
# ----------------------------------------------------------------------------------------------
class _EchoWatch:
    """Remembers, while registered, the PARAM_VALUEs per name from the vehicle and its refusals
    (PARAM_ERROR, STATUSTEXT "Param write denied (NAME)") per name."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.last: dict[str, float] = {}
        self.seen: dict[str, list[float]] = {}
        self.refused: dict[str, list[str]] = {}
        self._tokens = [link.add_handler("PARAM_VALUE", self._on), link.add_handler("PARAM_ERROR", self._on_error),
                        link.add_handler("STATUSTEXT", self._on_text)]

    def _on(self, m: Any) -> None:
        if not self.link.is_from_vehicle(m):
            return
        name = m.param_id.decode("ascii", "replace") if isinstance(m.param_id, bytes) else m.param_id
        name = name.rstrip("\x00")
        value = self.link.param_value(m)
        self.last[name] = value
        self.seen.setdefault(name, []).append(value)

    def _on_error(self, m: Any) -> None:
        hit = vehicle_param_error(self.link, m)
        if hit is not None:
            self.refused.setdefault(hit[0], []).append(f"PARAM_ERROR {hit[1]}")

    def _on_text(self, m: Any) -> None:
        text = m.text.decode("ascii", "replace") if isinstance(m.text, bytes) else str(m.text)
        text = text.rstrip("\x00")
        if self.link.is_from_vehicle(m) and text.startswith(_DENIED_PREFIX) and text.endswith(")"):
            self.refused.setdefault(text[len(_DENIED_PREFIX):-1], []).append(f'"{text}"')

    def close(self) -> None:
        for t in self._tokens:
            self.link.remove_handler(t)


@dataclass(frozen=True)
class _SetOutcome:
    ok: bool
    echoed: float | None
    attempts: int
    refusal: str | None = None  # the vehicle's own words when it refused the value
    unheard: str | None = None  # why the attempts stopped: the vehicle stayed silent


def _set_and_confirm(link: Link, watch: _EchoWatch, name: str, value: float, expected: float,
                     retries: int, timeout_s: float, budget_s: float, wait: Patience,
                     param_type: int = _A.MAV_PARAM_TYPE_REAL32,
                     before_send: Callable[[], None] = lambda: None) -> _SetOutcome:
    """PARAM_SET ``name`` until an echo equal to ``expected`` arrives, the vehicle refuses it, or
    at least ``retries`` attempts were sent and ``budget_s`` has passed while the vehicle was heard.
    ArduPilot takes every value as a REAL32; a bytewise vehicle (PX4) gets an integer's bytes with its
    ``param_type``.

    While the vehicle is silent (``wait``) no PARAM_SET is sent and the budget does not run: the
    attempts resume when it is heard again, and stop when it stays unheard past the allowance
    of ``wait`` (the outcome's ``unheard`` says so); ``before_send()`` before every PARAM_SET (a
    PX4's save pacing). Raises LinkError when the connection fails.
    """
    attempts = 0
    wire_type = param_type if link.bytewise_params else _A.MAV_PARAM_TYPE_REAL32
    wire_value = param_to_wire(value, wire_type, link.bytewise_params)
    mark = len(watch.seen.get(name, []))
    rmark = len(watch.refused.get(name, []))
    start, unheard0 = time.monotonic(), wait.silence.unheard_s()

    def confirmed() -> bool:
        return any(same_stored(v, expected) for v in watch.seen.get(name, [])[mark:])

    def refused() -> bool:
        return len(watch.refused.get(name, [])) > rmark

    def heard_s() -> float:  # time spent trying while the vehicle was not silent
        return time.monotonic() - start - (wait.silence.unheard_s() - unheard0)

    while attempts < max(1, retries) or heard_s() < budget_s:
        try:
            wait.until_heard()
        except LinkError as exc:
            seen = watch.seen.get(name, [])[mark:]
            return _SetOutcome(False, seen[-1] if seen else None, attempts, unheard=str(exc))
        attempts += 1
        before_send()
        link.mav.param_set_send(link.target_system, link.target_component, name.encode("ascii"),
                                wire_value, wire_type)
        if link.wait(lambda: confirmed() or refused(), timeout_s) and confirmed():
            return _SetOutcome(True, expected, attempts)
        seen = watch.seen.get(name, [])[mark:]
        if refused():  # the echo of the value it kept follows the refusal: it may be what we want
            if link.wait(confirmed, timeout_s):
                return _SetOutcome(True, expected, attempts)
            seen = watch.seen.get(name, [])[mark:]
            return _SetOutcome(False, seen[-1] if seen else None, attempts, watch.refused[name][-1])
        log.debug("%s: no matching echo (attempt %d, last %r)", name, attempts, watch.last.get(name))
    seen = watch.seen.get(name, [])[mark:]
    return _SetOutcome(False, seen[-1] if seen else None, attempts)


def _force_save(link: Link, kind: str, retries: int, timeout_s: float, budget_s: float,
                wait: Patience) -> str | None:
    """Send the force-save until the vehicle acknowledges it (or the budget runs out; paused,
    as a PARAM_SET's, while the vehicle is silent).

    Returns None when accepted, else the reason (the COMMAND_ACK result in MAVLink's words, or
    "no COMMAND_ACK ...").
    """
    p2, p5 = FORCE_SAVE_KINDS[kind]
    acks: list[int] = []

    def on_ack(m: Any) -> None:
        if link.is_from_vehicle(m) and m.command == _A.MAV_CMD_PREFLIGHT_CALIBRATION:
            acks.append(int(m.result))

    token = link.add_handler("COMMAND_ACK", on_ack)
    sent = 0
    start, unheard0 = time.monotonic(), wait.silence.unheard_s()
    try:
        while not acks and (sent < max(1, retries)
                            or time.monotonic() - start - (wait.silence.unheard_s() - unheard0) < budget_s):
            wait.until_heard()
            link.mav.command_long_send(link.target_system, link.target_component,
                                       _A.MAV_CMD_PREFLIGHT_CALIBRATION, min(sent, 255),
                                       0, p2, 0, 0, p5, 0, 0)
            sent += 1
            link.wait(lambda: bool(acks), timeout_s)
    finally:
        link.remove_handler(token)
    if acks and acks[0] == _A.MAV_RESULT_ACCEPTED:
        return None
    reason = (f"the vehicle answered {result_words(acks[0])}" if acks
              else f"no COMMAND_ACK after {sent} attempts in {time.monotonic() - start:.1f} s")
    log.warning("force-save of the %s calibration not acknowledged (%s)", kind, reason)
    return reason


def _set_failure(r: ParamResult, out: _SetOutcome) -> str:
    """Why a PARAM_SET failed, in the vehicle's words when it said something."""
    if out.refusal is not None:
        return f"{r.name}: the vehicle refused {r.requested:g}: {out.refusal}"
    if out.echoed is None:
        return f"{r.name}: no echo after {out.attempts} attempts"
    return f"{r.name}: no echo of {r.expected!r} after {out.attempts} attempts (last heard {out.echoed!r})"


def _read_back(link: Link, names: Sequence[str], retries: int, timeout_s: float, wait: Patience) -> ParamTable:
    """Read ``names`` back; the round is repeated for the names that did not answer while the
    vehicle fell silent during it (they were not refused: the link was down)."""
    got: ParamTable = {}
    for _ in range(_READ_ROUNDS):
        missing = [n for n in names if n not in got]
        if not missing:
            break
        wait.until_heard()
        silences = wait.silence.silences
        got.update(read_params(link, missing, timeout_s=timeout_s, attempts=max(1, retries)))
        if wait.silence.silences == silences and not wait.silence.silent():
            break
    return got




class _WriteRun:
    """One write after the plan and the backup: steps 3-6 and their bookkeeping."""

    def __init__(self, link: Link, *, retries: int, timeout_s: float, restore_retries: int, restore_wait_s: float,
                 budget_s: float) -> None:
        self.link = link
        self.retries, self.timeout_s, self.budget_s = retries, timeout_s, budget_s
        self.restore_retries, self.restore_wait_s = restore_retries, restore_wait_s
        self.restore_problem: str | None = None
        self.table: ParamTable = {}
        self.plan: list[ParamResult] = []
        self.backup = Path()
        self.results: dict[str, ParamResult] = {}
        self.attempted: list[str] = []
        self.force_saved: list[str] = []
        self.force_failed: list[str] = []
        self.force_reasons: list[str] = []
        self.force_skipped: tuple[str, ...] = ()
        self.out_of_range: tuple[str, ...] = ()
        self.px4: Px4Pacing | None = None  # a PX4's parameter saves, waited out (self._before_send)

    def start(self, changes: Mapping[str, float], params: ParamTable | None, force_save: Sequence[str], *,
              dry_run: bool, fetch_timeout_s: float, allow_out_of_range: bool, backup_path: str | None,
              backup_header: Sequence[str] | None, keepalive: bool) -> WriteReport:
        """Steps 1-2 (the table, the plan, the backup), then :meth:`execute` with the vehicle kept
        talking (asked before the backup is written: that gives the stream time to start)."""
        self.px4 = Px4Pacing(self.link) if self.link.bytewise_params else None  # a PX4: PARAM_SETs out of its saves
        self.table = _vehicle_table(self.link, changes, params, fetch_timeout_s, self.timeout_s,
                                    self.restore_retries, self.budget_s)
        self.plan = plan_changes(changes, self.table)
        self.results = {r.name: r for r in self.plan}
        self.out_of_range, self.force_skipped = _limit_check(changes, self.table, force_save, allow_out_of_range)
        to_write = [r for r in self.plan if not r.ok]
        if dry_run or not to_write:
            return _no_write_report(self.plan, to_write, dry_run)
        with VehicleSilence(self.link, keepalive=keepalive, answer_s=self.timeout_s) as self.silence:
            self.backup = write_backup(self.link, str(backup_path), {r.name: r.old for r in to_write}, backup_header)
            return self.execute(to_write, [k for k in force_save if k not in self.force_skipped])

    def _patience(self) -> Patience:
        """The write's wait for a silent vehicle: the write budget, per PARAM_SET / force-save / read."""
        return Patience(self.silence, self.budget_s, "the write")

    def execute(self, to_write: Sequence[ParamResult], force_save: Sequence[str]) -> WriteReport:
        """Steps 3-6: the report of a complete write, or ParamWriteError / RestoreFailedError."""
        self.watch = _EchoWatch(self.link)
        streams = StreamCheck(self.link)
        try:
            self.silence.settle(min(self.budget_s, SETTLE_S))
            failure = self.write_each(to_write)
            if failure is None:
                failure = self.save_and_verify(force_save)
            if failure is None:
                streams.check(len(self.attempted), str(self.backup), self.px4)  # the vehicle still streams
                return self.success()
            self.restore(failure)
        finally:
            streams.close()
            self.watch.close()

    def _before_send(self) -> None:
        return None if self.px4 is None else self.px4.before_send()

    def _final(self) -> tuple[ParamResult, ...]:
        return tuple(self.results[r.name] for r in self.plan)

    # 3. one at a time, confirmed by echo
    def _set(self, r: ParamResult, value: float, wait: Patience | None = None) -> tuple[_SetOutcome, str | None]:
        """One confirmed PARAM_SET of the write (or, with the restore's ``wait``, of the restore)."""
        if r.name not in self.attempted:
            self.attempted.append(r.name)
        try:
            return _set_and_confirm(self.link, self.watch, r.name, value, expected_stored_value(
                value, self.table[r.name][1]), self.retries if wait is None else self.restore_retries, self.timeout_s,
                self.budget_s, wait or self._patience(), self.table[r.name][1], self._before_send), None
        except LinkError as exc:
            return _SetOutcome(False, self.watch.last.get(r.name), max(1, self.retries)), str(exc)

    def write_each(self, to_write: Sequence[ParamResult]) -> str | None:
        """PARAM_SET every change until its echo confirms it (PX4's detours first, then the changes in
        their order, see :func:`~mavcal.autopilot.protocol.detoured_order`); the failure, or None."""
        order, detours = detoured_order({r.name: r.requested for r in to_write})
        for name, value in detours.items():
            out, failure = self._set(self.results[name], value)
            if not out.ok:
                return failure or out.unheard or f"{name}: the detour to {value:g} was not confirmed"
        try:
            self.link.pump(detour_dwell_s() if detours else 0.0)
        except LinkError as exc:
            return str(exc)
        for name in order:
            r = self.results[name]
            out, failure = self._set(r, r.requested)
            ok, echoed, attempts = out.ok, out.echoed, out.attempts
            self.results[r.name] = replace(r, ok=ok, echoed=echoed, attempts=attempts)
            if not ok:
                return failure or out.unheard or _set_failure(r, out)
            if vector_group(r.name):
                log.debug("%s confirmed (vector echo of %s)", r.name, "/".join(vector_group(r.name) or ()))
        return None

    # 4. force-save, 5. read back
    def save_and_verify(self, force_save: Sequence[str]) -> str | None:
        """Force-save (a missing ACK is reported, not fatal), then read every written value back."""
        for kind in force_save:
            try:
                reason = _force_save(self.link, kind, self.retries, self.timeout_s, self.budget_s, self._patience())
            except LinkError as exc:
                reason = str(exc)
            (self.force_saved if reason is None else self.force_failed).append(kind)
            if reason is not None:
                self.force_reasons.append(f"force-save of {kind} failed: {reason}")
        failure = None
        try:
            back = _read_back(self.link, self.attempted, self.restore_retries, self.timeout_s, self._patience())
        except LinkError as exc:
            back, failure = {}, str(exc)
        for name in self.attempted:
            r = self.results[name]
            if name in back:
                self.results[name] = replace(r, echoed=back[name][0], ok=same_stored(back[name][0], r.expected))
            else:
                self.results[name] = replace(r, ok=False)
        bad = [n for n in self.attempted if not self.results[n].ok]
        if bad and failure is None:
            failure = "read-back does not confirm " + ", ".join(
                f"{n} (got {self.results[n].echoed!r}, expected {self.results[n].expected!r})" if n in back
                else f"{n} (no answer)" for n in bad)
        return failure

    def success(self) -> WriteReport:
        reboot = tuple(n for n in self.attempted if needs_reboot(n, self.results[n].requested))
        msg = f"{len(self.attempted)} parameters written and verified"
        if self.force_reasons:
            msg += "; " + "; ".join(self.force_reasons)
        if self.force_skipped:
            msg += f"; {'/'.join(self.force_skipped)} not marked calibrated (values outside ArduPilot's limits)"
        return WriteReport(results=self._final(), backup_path=str(self.backup), complete=True,
                           reboot_required=reboot, force_saved=tuple(self.force_saved),
                           force_save_failed=tuple(self.force_failed), message=msg,
                           force_save_skipped=self.force_skipped, out_of_range=self.out_of_range)

    # 6. restore everything attempted (including the one in flight), newest first
    def _restore_each(self, wait: Patience) -> bool:
        """PARAM_SET every attempted parameter back to its old value, first waiting for a silent
        vehicle (``wait``: the restore's own allowance); False if it stayed unheard past it."""
        link_ok = True
        try:
            self.link.pump(min(self.timeout_s, 0.5))  # let late echoes of the failed attempts arrive first
        except LinkError:
            link_ok = False
        _, detours = detoured_order({n: self.results[n].old for n in self.attempted})  # pivots: restored last
        for name, value in detours.items():
            if link_ok:
                out, problem = self._set(self.results[name], value, wait)
                if out.unheard is not None or problem is not None:
                    link_ok, self.restore_problem = False, out.unheard or problem
        try:
            if detours and link_ok:
                self.link.pump(detour_dwell_s())
        except LinkError as exc:
            link_ok, self.restore_problem = False, str(exc)
        for name in reversed(self.attempted):
            r = self.results[name]
            if not link_ok:
                self.results[name] = replace(r, restored=False)
                continue
            out, problem = self._set(r, r.old, wait)
            if problem is not None:  # the connection failed: one attempt, nothing heard
                out = _SetOutcome(False, None, 1)
            if out.unheard is not None or problem is not None:
                link_ok, self.restore_problem = False, out.unheard or problem
            self.results[name] = replace(r, restored=out.ok, restore_attempts=out.attempts,
                                         echoed=out.echoed if out.echoed is not None else r.echoed)
        return link_ok

    def _verify_restore(self, wait: Patience) -> None:
        """Read the restored parameters back; one that does not read back its old value is in doubt."""
        confirmed = [n for n in self.attempted if self.results[n].restored]
        if not confirmed:
            return
        try:
            back = _read_back(self.link, confirmed, self.restore_retries, self.timeout_s, wait)
        except LinkError as exc:
            back, self.restore_problem = {}, str(exc)
        for n in confirmed:
            r = self.results[n]
            good = n in back and same_stored(back[n][0], expected_stored_value(r.old, self.table[n][1]))
            self.results[n] = replace(r, restored=good, echoed=back[n][0] if n in back else r.echoed)

    def restore(self, failure: str) -> NoReturn:
        """Undo the write, then raise ParamWriteError (restored) or RestoreFailedError (in doubt)."""
        log.warning("write failed (%s); restoring %d parameters from %s", failure, len(self.attempted), self.backup)
        wait = Patience(self.silence, self.restore_wait_s, "the restore")
        if self._restore_each(wait):
            self._verify_restore(wait)
        in_doubt = tuple(n for n in self.attempted if not self.results[n].restored)
        saved, failed = tuple(self.force_saved), tuple(self.force_failed)
        if in_doubt:
            report = WriteReport(results=self._final(), backup_path=str(self.backup), complete=False,
                                 restored=False, in_doubt=in_doubt, force_saved=saved, force_save_failed=failed,
                                 message=f"write failed ({failure}) and the restore failed")
            why = f" ({self.restore_problem})" if self.restore_problem else ""
            raise RestoreFailedError(
                f"write failed ({failure}); restore not verified for {', '.join(in_doubt)}{why}; "
                f"backup in {self.backup}", in_doubt=in_doubt, report=report)
        report = WriteReport(results=self._final(), backup_path=str(self.backup), complete=False, restored=True,
                             force_saved=saved, force_save_failed=failed,
                             message=f"write failed ({failure}); {len(self.attempted)} parameters restored")
        raise ParamWriteError(f"write failed ({failure}); restored {len(self.attempted)} parameters "
                              f"from {self.backup}", report=report)


def _vehicle_table(link: Link, changes: Mapping[str, float], params: ParamTable | None, fetch_timeout_s: float,
                   timeout_s: float, read_retries: int, budget_s: float) -> ParamTable:
    """1. The vehicle's table: fetched whole, or ``params`` with fresh values of the names to change."""
    if params is None:
        return fetch_all_params(link, fetch_timeout_s, retry_s=max(timeout_s, 0.2))
    table = dict(params)
    plan_changes(changes, table)  # refuse unknown names before talking to the vehicle
    fresh = read_params(link, list(changes), timeout_s=timeout_s, attempts=max(1, read_retries), budget_s=budget_s)
    missing = [n for n in changes if n not in fresh]
    if missing:
        raise LinkError(f"{link.device}: no answer reading {', '.join(missing)} (nothing was written)")
    table.update(fresh)
    return table


def _limit_check(changes: Mapping[str, float], table: ParamTable, force_save: Sequence[str],
                 allow: bool) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Refuse values outside ArduPilot's limits (OutOfRangeError) unless ``allow``.

    Returns the violations written anyway (one line each) and the force-save kinds to skip.
    """
    values = {n: v for n, (v, _) in table.items()}
    violations = check_limits(changes, values)
    if violations and not allow:
        raise OutOfRangeError(violations)
    for v in violations:
        log.warning("writing a value outside ArduPilot's limits (forced): %s", v.message)
    skipped = tuple(k for k in force_save if k in failing_kinds(changes, values))
    return tuple(v.message for v in violations), skipped


def _checked_request(changes: Mapping[str, float], force_save: Sequence[str], backup_path: str | None,
                     dry_run: bool) -> dict[str, float]:
    """``changes`` as str -> float; refuses unknown force-save kinds and a missing backup path."""
    bad_kinds = [k for k in force_save if k not in FORCE_SAVE_KINDS]
    if bad_kinds:
        raise UsageError(f"unknown force_save kind(s) {bad_kinds}; use 'compass' and/or 'accel'")
    if not dry_run and backup_path is None:
        raise UsageError("a backup path is required to write parameters")
    return {str(k): float(v) for k, v in changes.items()}


def _no_write_report(plan: Sequence[ParamResult], to_write: Sequence[ParamResult], dry_run: bool) -> WriteReport:
    msg = ("dry run: " if dry_run else "") + (
        f"{len(to_write)} of {len(plan)} parameters would change" if dry_run
        else "nothing to change: the vehicle already holds every value")
    return WriteReport(results=tuple(plan), backup_path=None, complete=not dry_run, dry_run=dry_run,
                       reboot_required=tuple(r.name for r in to_write if needs_reboot(r.name, r.requested)),
                       message=msg)


def write_params(conn: Any, changes: Mapping[str, float], *, backup_path: str | None,
                 params: ParamTable | None = None, force_save: Sequence[str] = ("compass", "accel"),
                 retries: int = 3, timeout_s: float = 1.0, restore_retries: int | None = None,
                 dry_run: bool = False, fetch_timeout_s: float = 30.0, restore_wait_s: float | None = None,
                 budget_s: float | None = None, allow_out_of_range: bool = False,
                 backup_header: Sequence[str] | None = None, keepalive: bool = True) -> WriteReport:
    """Write ``changes`` to the vehicle safely (see the module docstring for the sequence).

    Parameters
    ----------
    conn : Link or pymavlink connection
        Link to the vehicle (a bare connection must have seen its HEARTBEAT).
    changes : mapping of str to float
        New values by parameter name.
    backup_path : str or path-like or None
        Where the backup of the old values goes (must not exist yet). Required unless
        ``dry_run``.
    params : dict of str to (float, int), optional
        The vehicle's table as returned by :func:`~mavcal.link.params.fetch_all_params`. If
        given, it is used for the name check and the types, and only the parameters to change
        are re-read for fresh old values; if None, the whole table is fetched first.
    force_save : sequence of {"compass", "accel"}
        Force-saves to send after the writes (empty: none).
    retries : int
        PARAM_SETs (and force-saves) sent at least, per parameter, before giving up.
    timeout_s : float
        Wait for each echo / answer before sending again.
    restore_retries : int, optional
        PARAM_SETs per parameter when restoring, and read requests per parameter when
        reading values (reads change nothing, so they may insist); default ``5 * retries``,
        at least 20. A silent vehicle is waited for instead (``budget_s``, ``restore_wait_s``).
    dry_run : bool
        Only compute the diff; write nothing (no backup either).
    fetch_timeout_s : float
        Bound on the initial parameter download.
    restore_wait_s : float, optional
        How long the restore waits in all for a silent vehicle (:mod:`mavcal.link.silence`) before
        its parameters are in doubt. Default ``RESTORE_WAIT_FACTOR * budget_s`` (60 s in the CLI).
    backup_header : sequence of str, optional
        Comment lines for the backup file.
    budget_s : float, optional
        Time budget per PARAM_SET / force-save / read: keep retrying (after ``retries``
        attempts) until it runs out. It does not run while the vehicle is silent (see
        :mod:`mavcal.link.silence`): the write waits up to ``budget_s`` more for it to be heard
        again, then fails (and restores). Default ``DEFAULT_BUDGET_FACTOR * timeout_s``.
    allow_out_of_range : bool
        Write values outside ArduPilot's limits anyway (reported in ``out_of_range``); the
        sensor kinds whose values fail are still not force-saved.
    keepalive : bool
        Ask for ATTITUDE at a few Hz during the write, its default rate put back after (False:
        a link that is not handed ATTITUDE; silences then measured on the heartbeat alone).

    Returns
    -------
    WriteReport
        ``complete`` True (or a dry run / nothing to change).

    Raises
    ------
    UnknownParameterError, OutOfRangeError, UsageError
        Refused before any write.
    LinkError
        The vehicle does not answer before any write (nothing was written).
    ParamWriteError
        A write failed; every attempted parameter was restored and verified (exit 5).
        ``.report`` holds the :class:`WriteReport`.
    RestoreFailedError
        A write failed and the restore could not be verified (exit 6); ``.in_doubt`` lists
        the parameters whose value is unknown and ``.report`` the report.
    """
    restore_retries = max(20, 5 * retries) if restore_retries is None else restore_retries
    budget_s = DEFAULT_BUDGET_FACTOR * timeout_s if budget_s is None else budget_s
    run = _WriteRun(as_link(conn), retries=retries, timeout_s=timeout_s, restore_retries=restore_retries,
                    budget_s=budget_s, restore_wait_s=RESTORE_WAIT_FACTOR * budget_s if restore_wait_s is None
                    else restore_wait_s)
    changes = _checked_request(changes, force_save, backup_path, dry_run)
    return run.start(changes, params, force_save, dry_run=dry_run, fetch_timeout_s=fetch_timeout_s,
                     allow_out_of_range=allow_out_of_range, backup_path=backup_path, backup_header=backup_header,
                     keepalive=keepalive)
