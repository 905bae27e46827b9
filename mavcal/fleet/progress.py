"""The progress line of a fleet run on a terminal: logs done of the total, rate, ETA, failures.

Written to stderr only when it is a terminal and ``-q`` was not given (:func:`progress_line`);
redrawn in place (``\\r``) at most every ``every_s`` seconds and once at the end. The table,
the JSON and the Parquet file are not affected.
"""
from __future__ import annotations

import time
from typing import TextIO

__all__ = ["ProgressLine", "progress_line", "format_eta"]


def format_eta(seconds: float) -> str:
    """``"42 s"``, ``"3 min 05 s"``, ``"2 h 07 min"``."""
    s = max(0, int(round(seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"


class ProgressLine:
    """Call with each finished log's :class:`mavcal.fleet.run.FleetResult`; :meth:`close` at the end."""

    def __init__(self, out: TextIO, total: int, *, every_s: float = 0.5, clock=time.monotonic) -> None:
        self.out, self.total, self.every_s, self.clock = out, total, every_s, clock
        self.t0 = clock()
        self.done = self.failed = self.skipped = 0
        self._shown = -1.0

    def text(self) -> str:
        """The line as it stands: ``"fleet: 12/100 logs (1 failed, 3 skipped), 0.80 logs/s, ETA 1 min 50 s"``."""
        elapsed = max(self.clock() - self.t0, 1e-9)
        worked = self.done - self.skipped  # the rate of the logs calibrated (a skipped one is only hashed)
        rate = worked / elapsed
        left = self.total - self.done
        eta = "ETA " + format_eta(left / rate) if rate > 0 and left else ("done" if not left else "ETA ?")
        extra = [f"{self.failed} failed"] + ([f"{self.skipped} already in the table"] if self.skipped else [])
        return f"fleet: {self.done}/{self.total} logs ({', '.join(extra)}), {rate:.2f} logs/s, {eta}"

    def __call__(self, res) -> None:
        self.done += 1
        if res.row is None:
            self.skipped += 1
        elif not res.row.ok:
            self.failed += 1
        now = self.clock()
        if now - self._shown >= self.every_s or self.done == self.total:
            self._shown = now
            self.out.write(f"\r{self.text()}\x1b[K")
            self.out.flush()

    def close(self) -> None:
        if self._shown >= 0:
            self.out.write("\n")
            self.out.flush()


def progress_line(out: TextIO, total: int, *, quiet: bool = False) -> ProgressLine | None:
    """A :class:`ProgressLine` on ``out`` when it is a terminal and not ``quiet``; else None."""
    try:
        tty = out.isatty()
    except (AttributeError, ValueError):
        tty = False
    return ProgressLine(out, total) if tty and not quiet else None
