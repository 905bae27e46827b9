"""mavcal's PARAM_SETs to a PX4 stay out of its parameter saves (issue 35, item 8).

PX4's autosave is modelled here from its source (``autosave.cpp``: a change schedules a save 300 ms
later, or 2 s after the last save; ``param_save_default``: export, then verify against the values in
force), independently of :mod:`mavcal.px4.autosave`; the writer's sequence of changes, paced by
:class:`~mavcal.px4.autosave.SaveSchedule`, never lands during a save, whatever each PARAM_SET takes.
"""
from __future__ import annotations

import random

import pytest

from mavcal.px4.autosave import QUIET_S, SAVE_DELAY_S, SAVE_SPAN_S, SaveSchedule

#: what an export + verify takes in the model (the schedule allows SAVE_SPAN_S)
EXPORT_S = 0.4


class Px4Autosave:
    """``ParamAutosave::request`` / ``Run`` (PX4 main): times in seconds."""

    def __init__(self, last_save_s: float | None = None) -> None:
        self.scheduled: float | None = None
        self.last_save = last_save_s
        self.saves: list[tuple[float, float]] = []  # (export start, verify end)

    def run_until(self, t: float) -> None:
        if self.scheduled is not None and self.scheduled <= t:
            start = self.scheduled
            self.scheduled = None
            self.last_save = start
            self.saves.append((start, start + EXPORT_S))

    def param_set(self, t: float) -> None:
        self.run_until(t)
        if self.scheduled is not None:
            return
        delay = 0.3
        if self.last_save is not None:
            elapsed = t - self.last_save
            if elapsed < 2.0 and 2.0 > elapsed + delay:
                delay = 2.0 - elapsed
        self.scheduled = t + delay


def _write(rng: random.Random, n_sets: int, px4: Px4Autosave, start: float, quiet_since: float,
           dwell_after: int = 0) -> list[float]:
    """The writer's sets: each waits as the schedule says, then lands; returns the landing times."""
    clock = SaveSchedule(quiet_since)
    t = start
    landed = []
    for k in range(n_sets):
        t += clock.wait_s(t)
        clock.changed(t)
        px4.param_set(t)
        landed.append(t)
        t += rng.choice((0.002, 0.01, 0.05, 0.2, 0.9))  # the echo's round trip, a retry, a loaded machine
        if k == dwell_after:
            t += 0.3  # the detours' dwell
    px4.run_until(t + 10)
    by = clock.saved_by_s()
    assert by is None or all(end <= by for _, end in px4.saves)  # the check after the write waits for the last
    return landed


@pytest.mark.parametrize("seed", range(40))
def test_no_set_lands_during_a_save(seed):
    rng = random.Random(seed)
    earlier = rng.choice((None, 0.0, 1.0, 2.5))  # a change of mavcal's earlier write, or none known
    px4 = Px4Autosave()
    if earlier is not None:
        px4.param_set(earlier)
    start = 3.0
    landed = _write(rng, rng.randint(1, 30), px4, start, earlier if earlier is not None else start,
                    dwell_after=rng.randint(0, 3))
    assert px4.saves
    for a, b in px4.saves:
        inside = [t for t in landed if a <= t <= b]
        assert not inside, (seed, (a, b), inside)


def test_the_first_change_waits_for_quiet_and_its_save_is_300_ms_later():
    s = SaveSchedule(quiet_since_s=10.0)
    assert s.wait_s(10.5) == pytest.approx(QUIET_S - 0.5)
    t0 = 10.0 + QUIET_S
    assert s.wait_s(t0) == 0
    s.changed(t0)
    assert s.pending_s == pytest.approx(t0 + SAVE_DELAY_S)
    assert s.wait_s(t0 + 0.1) == 0  # before the save: free
    assert s.wait_s(t0 + 0.25) == pytest.approx(SAVE_DELAY_S + SAVE_SPAN_S - 0.25)  # too close to it
    s.changed(t0 + SAVE_DELAY_S + SAVE_SPAN_S)
    assert s.pending_s == pytest.approx(t0 + SAVE_DELAY_S + 2.0)  # the rate limit: 2 s after the save
    assert s.saved_by_s() == pytest.approx(t0 + SAVE_DELAY_S + 2.0 + SAVE_SPAN_S)


def test_without_the_schedule_the_detour_straddles_a_save():
    """The write as it was (detours, 0.3 s, the rest at once): the export runs between a detour and
    its target (what PX4's verify tripped on)."""
    px4 = Px4Autosave()
    t = 0.0
    landed = []
    for k in range(18):
        px4.param_set(t)
        landed.append(t)
        t += 0.02 + (0.3 if k == 1 else 0.0)
    px4.run_until(t + 10)
    a, b = px4.saves[0]
    assert any(a <= x <= b for x in landed)
