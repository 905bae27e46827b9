"""Progress of long runs, on a terminal line or through a callback (no dependency).

Two kinds of report reach a progress object:

* ``progress(done_bytes, total_bytes)``: the reading of a file (what
  :func:`mavcal.sources.reader.read_log` calls, a :data:`ProgressFn`);
* ``progress.stage(name, done, total)``: a stage of the pipeline (``"recovering raw
  readings"``, ``"finding still intervals"``, ``"fitting"`` ...) with its own count, sent by
  :func:`report` only to objects that have a ``stage`` method (a plain two-argument function
  gets the reading alone, as before).

:class:`ProgressPrinter` draws ``label  42% [########            ] 120.3/286.0 MB`` on one
stderr line, redrawn with ``\\r`` at most every 0.2 s, once the run has lasted
``show_after_s`` (:data:`SHOW_AFTER_S` from :func:`auto_progress`: a short run prints
nothing). :func:`auto_progress` gives one only when
the stream is a terminal and the command is not ``--quiet``: piped or redirected output
stays silent. :class:`CallbackProgress` turns the reports into calls
``fn(stage, fraction)`` at most every ``min_interval_s``, for a host with its own display
(the MAVProxy module's console).
"""
from __future__ import annotations

import logging
import sys
import time
from typing import Callable, TextIO

ProgressFn = Callable[[int, int], None]
StageFn = Callable[[str, float], None]  # (stage, fraction 0..1)

READING = "reading"
SHOW_AFTER_S = 1.0  # auto_progress: a run shorter than this prints no progress at all

__all__ = ["ProgressFn", "StageFn", "ProgressPrinter", "CallbackProgress", "auto_progress", "report", "READING"]


def report(progress: object, stage: str, done: float, total: float) -> None:
    """Send a stage report to ``progress`` if it takes stages (has a ``stage`` method)."""
    fn = getattr(progress, "stage", None)
    if fn is not None:
        fn(stage, done, total)


class ProgressPrinter:
    """Callable ``(done_bytes, total_bytes)`` and ``stage(name, done, total)`` that redraws one
    terminal line per stage.

    Parameters
    ----------
    label : str
        Text before the percentage of the reading, e.g. ``"reading big.tlog"``.
    stream : text stream, default ``sys.stderr``
    min_interval_s : float
        Minimum time between redraws.
    show_after_s : float
        Nothing is drawn before the run (or the stage) has lasted this long.
    """

    BAR = 20

    def __init__(self, label: str, stream: TextIO | None = None, min_interval_s: float = 0.2,
                 show_after_s: float = 0.0) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.min_interval_s = min_interval_s
        self.show_after_s = show_after_s
        self._t0 = time.monotonic()
        self._stage: str | None = None
        self._stage_t0 = self._t0
        self._last = 0.0
        self._drawn = False
        self._width = 0

    def __call__(self, done: int, total: int) -> None:
        self.stage(self.label, done, total, unit="MB", scale=1e-6)

    def stage(self, name: str, done: float, total: float, unit: str = "", scale: float = 1.0) -> None:
        """Report ``done`` of ``total`` of stage ``name`` (a new name ends the previous line)."""
        now = time.monotonic()
        if name != self._stage:
            self.close()
            self._stage, self._stage_t0, self._last = name, now, 0.0
        final = total > 0 and done >= total
        if now - self._t0 < self.show_after_s and now - self._stage_t0 < self.show_after_s and not self._drawn:
            return
        if not final and now - self._last < self.min_interval_s:
            return
        self._last = now
        frac = min(1.0, done / total) if total > 0 else 0.0
        bar = "#" * int(round(frac * self.BAR))
        count = f"{done * scale:.1f}/{total * scale:.1f} {unit}" if unit else f"{done:g}/{total:g}"
        text = f"{name}  {100 * frac:3.0f}% [{bar:<{self.BAR}}] {count}"
        if final:
            text += f"  {now - self._stage_t0:.1f} s"
        self.stream.write("\r" + text + " " * max(0, self._width - len(text)))
        self._width = len(text)
        self._drawn = True
        if final:
            self.close()
        else:
            self.stream.flush()

    def close(self) -> None:
        """End the line (if anything was drawn)."""
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
        self._width = 0


class CallbackProgress:
    """Reports as calls ``fn(stage, fraction)``, at most every ``min_interval_s`` per stage
    (and always at a stage's start and end): the hook for a display of one's own, e.g.
    ``CallbackProgress(lambda s, f: console.set_status("mavcal", f"mavcal: {s} {f:.0%}"))``.
    Pass it as ``progress=`` to :func:`mavcal.pipeline.calibrate_source` or
    :func:`mavcal.pipeline.prepare`."""

    def __init__(self, fn: StageFn, min_interval_s: float = 0.5) -> None:
        self.fn = fn
        self.min_interval_s = min_interval_s
        self._stage: str | None = None
        self._last = 0.0

    def __call__(self, done: int, total: int) -> None:
        self.stage(READING, done, total)

    def stage(self, name: str, done: float, total: float) -> None:
        now = time.monotonic()
        frac = min(1.0, done / total) if total > 0 else 0.0
        new = name != self._stage
        if not new and frac < 1.0 and now - self._last < self.min_interval_s:
            return
        self._stage, self._last = name, now
        self.fn(name, frac)


def _quiet() -> bool:
    """The command line's ``--quiet`` (it sets mavcal's logging to errors only)."""
    return logging.getLogger("mavcal").getEffectiveLevel() >= logging.ERROR


def auto_progress(label: str, stream: TextIO | None = None, quiet: bool | None = None) -> ProgressPrinter | None:
    """A :class:`ProgressPrinter` if ``stream`` (default stderr) is a terminal and not ``quiet``
    (None: quiet when mavcal's log level is errors only, i.e. ``mavcal -q``), else ``None``."""
    stream = stream if stream is not None else sys.stderr
    if quiet if quiet is not None else _quiet():
        return None
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    return ProgressPrinter(label, stream, show_after_s=SHOW_AFTER_S) if tty else None
