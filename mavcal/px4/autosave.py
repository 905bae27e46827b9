"""When PX4 saves its parameters, predicted from the changes mavcal sends (issue 35, item 8).

Read in PX4's source (``src/lib/parameters/autosave.cpp`` ``ParamAutosave::request`` / ``Run``,
``parameters.cpp`` ``param_set_internal`` and ``param_save_default``; PX4 main, 2023-2026):

* every ``param_set`` that changes a value (a PARAM_SET of the value already held changes nothing)
  calls ``request()``: unless a save is already scheduled it schedules one **300 ms** later, or,
  when the last save ran less than **2 s** ago, at 2 s after that save (the rate limit);
* ``Run()`` clears "scheduled" and then saves: it exports every non-default parameter to the
  parameter file and **verifies** the file against the values in force (``param_verify``: each
  value read back must equal ``param_get``); a parameter changed between export and verify fails
  the verify ("verify: 'CAL_MAG0_XOFF' invalid BSON value 0.020 (expected 0.120)", "parameter
  export to parameters.bson failed (1) attempt 1"), and the save is tried again.

Seen on the PX4 SITL under load (issue 35): the writer's detour of a CAL_* vector and its target
0.3 s later straddled such a save, the verify failed, and PX4 stopped streaming. So mavcal keeps
its PARAM_SETs out of every predicted save: :class:`SaveSchedule` says how long to wait before the
next change may be sent, and when the save of the last change has run.

The prediction needs a known start: before the first change of a write, no change of mavcal's for
:data:`QUIET_S` (the last save of earlier changes then ran more than 1.7 s before, and the first
change's save comes exactly :data:`SAVE_DELAY_S` after it). Changes made by another ground station
at the same time are beyond it.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SAVE_DELAY_S", "SAVE_RATE_S", "SAVE_SPAN_S", "SAVE_MARGIN_S", "QUIET_S", "SaveSchedule"]

#: a change schedules a save this long after it (``ParamAutosave::request``: ``delay = 300_ms``)
SAVE_DELAY_S = 0.3
#: saves are at least this far apart (``rate_limit = 2_s``)
SAVE_RATE_S = 2.0
#: how long mavcal lets a save take (export, verify, and the low-priority work queue's lateness on a
#: loaded machine: an export of ~100 changed parameters takes milliseconds)
SAVE_SPAN_S = 0.6
#: no change is sent this close before a predicted save (the link's latency, a scheduler's jitter)
SAVE_MARGIN_S = 0.1
#: quiet before the first change of a write: the save of any earlier change (at most 2 s after it) has
#: run more than ``SAVE_RATE_S - SAVE_DELAY_S`` before the first change, so its save is 300 ms after it
QUIET_S = SAVE_RATE_S + (SAVE_RATE_S - SAVE_DELAY_S)


@dataclass
class SaveSchedule:
    """PX4's autosave as the changes mavcal sends schedule it (times: ``time.monotonic()`` seconds).

    ``quiet_since_s`` is the time of mavcal's last change to this vehicle, or, when none is known,
    the time the write began (nothing of it changed a parameter yet).
    """

    quiet_since_s: float
    last_save_s: float | None = None
    pending_s: float | None = None

    def _roll(self, now: float) -> None:
        if self.pending_s is not None and now >= self.pending_s + SAVE_SPAN_S:
            self.last_save_s, self.pending_s = self.pending_s, None

    def wait_s(self, now: float) -> float:
        """Seconds to wait before a change may be sent at ``now`` (0: send now)."""
        self._roll(now)
        if self.pending_s is None and self.last_save_s is None:
            return max(0.0, self.quiet_since_s + QUIET_S - now)
        if self.pending_s is not None and now >= self.pending_s - SAVE_MARGIN_S:
            return self.pending_s + SAVE_SPAN_S - now
        return 0.0

    def changed(self, now: float) -> None:
        """A change was sent at ``now``: the save it schedules (if none is scheduled yet)."""
        self._roll(now)
        if self.pending_s is None:
            after_last = self.last_save_s + SAVE_RATE_S if self.last_save_s is not None else float("-inf")
            self.pending_s = max(now + SAVE_DELAY_S, after_last)
        self.quiet_since_s = now

    def saved_by_s(self) -> float | None:
        """When the save of the last change will have run (None: none is pending)."""
        return None if self.pending_s is None else self.pending_s + SAVE_SPAN_S
