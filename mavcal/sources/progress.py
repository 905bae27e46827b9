"""A tiny progress printer for long reads (no dependency).

It draws ``label  42%  120.3/286.0 MB`` on one stderr line, redrawn with ``\\r`` at most
every 0.2 s, and only when the stream is a terminal: piped or redirected output stays
silent. Use :func:`auto_progress` to get a callback or ``None``.
"""
from __future__ import annotations

import sys
import time
from typing import Callable, TextIO

ProgressFn = Callable[[int, int], None]


class ProgressPrinter:
    """Callable ``(done_bytes, total_bytes)`` that redraws one terminal line.

    Parameters
    ----------
    label : str
        Text before the percentage, e.g. the file name.
    stream : text stream, default ``sys.stderr``
    min_interval_s : float
        Minimum time between redraws.
    """

    def __init__(self, label: str, stream: TextIO | None = None, min_interval_s: float = 0.2) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.min_interval_s = min_interval_s
        self._last = 0.0
        self._drawn = False

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        final = total > 0 and done >= total
        if not final and now - self._last < self.min_interval_s:
            return
        self._last = now
        pct = 100.0 * done / total if total > 0 else 100.0
        self.stream.write(f"\r{self.label}  {pct:3.0f}%  {done / 1e6:.1f}/{total / 1e6:.1f} MB")
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


def auto_progress(label: str, stream: TextIO | None = None) -> ProgressPrinter | None:
    """A :class:`ProgressPrinter` if ``stream`` (default stderr) is a terminal, else ``None``."""
    stream = stream if stream is not None else sys.stderr
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    return ProgressPrinter(label, stream) if tty else None
