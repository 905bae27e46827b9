"""A value outside its limit (:class:`LimitViolation`): what every autopilot's limit check returns.

Each autopilot's model checks the names it knows (``check_limits``); :mod:`mavcal.autopilot.protocol`
asks every model.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["LimitViolation"]


@dataclass(frozen=True)
class LimitViolation:
    """One value outside its limit: ``message`` is the one-line refusal."""

    name: str
    value: float
    limit: str
    kind: str | None  # "compass", "accel" or None (board-wide)

    @property
    def message(self) -> str:
        return f"{self.name} = {self.value:g}: limit {self.limit}"
