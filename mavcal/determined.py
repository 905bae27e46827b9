"""What the data determine, and how a number they do not determine is said (issue 30).

A 95 % heading bound above :data:`~mavcal.coverage.UNIDENTIFIED_HEADING_DEG` (90 deg) or a tilt
bound above :data:`~mavcal.coverage.UNIDENTIFIED_TILT_DEG` (45 deg) says that the poses did not
identify the sensor: such a bound is a Monte Carlo percentile of errors that may lie anywhere in
a quarter or half turn, and its digits change with the CPU's floating-point paths. The same
holds for every number of a fit whose sensor fails the coverage rule (a gate with cause
``"data"``, :mod:`mavcal.coverage`): its misalignment, field, cross-axis terms, held-out error
and the Wald statistics of its model choice. What a person reads then says "not determined"
with the reason instead of digits; the JSON keeps the numbers and adds the flags.
"""
from __future__ import annotations

import math
from typing import Any

from mavcal.coverage import UNIDENTIFIED_HEADING_DEG, UNIDENTIFIED_TILT_DEG

__all__ = ["LIMIT_DEG", "determined", "bound_phrase", "bound_value_words", "unidentified", "joint_unidentified"]

#: a 95 % bound above this (deg) is no estimate: "heading" of a compass, "tilt" of an accelerometer
LIMIT_DEG = {"heading": UNIDENTIFIED_HEADING_DEG, "tilt": UNIDENTIFIED_TILT_DEG}


def determined(kind: str, bound_deg: float | None) -> bool:
    """Whether a 95 % ``kind`` ("heading" or "tilt") bound is an estimate: finite and at most
    :data:`LIMIT_DEG`."""
    return bound_deg is not None and math.isfinite(bound_deg) and bound_deg <= LIMIT_DEG[kind]


def bound_value_words(kind: str, bound_deg: float | None, fmt: str = ".3f", why: str = "") -> str:
    """``"<= 0.123 deg"``, or ``"not determined (95 % bound above 90 deg)"`` (``why`` in the
    brackets instead when given: the sensor's coverage failure)."""
    if why:
        return f"not determined ({why})"
    if not determined(kind, bound_deg):
        return f"not determined (95 % bound above {LIMIT_DEG[kind]:g} deg)"
    assert bound_deg is not None
    return f"<= {bound_deg:{fmt}} deg"


def bound_phrase(kind: str, bound_deg: float | None, fmt: str = ".3f", why: str = "") -> str:
    """``"heading error <= 0.123 deg"`` or ``"heading error not determined (95 % bound above 90 deg)"``."""
    return f"{kind} error {bound_value_words(kind, bound_deg, fmt, why)}"


def unidentified(run: Any, sensor: str) -> str:
    """Why the poses of ``run`` do not identify ``sensor`` ("the poses do not identify compass0:
    only 6 distinct field directions"), from its first failed gate with cause ``"data"``; "" when
    they do."""
    for g in run.gates.failures():
        if g.sensor == sensor and g.cause == "data":
            first = g.reason.split(":")[0]
            return first if first.startswith("the poses do not identify") else \
                f"the poses do not identify {sensor}: {first}"
    return ""


def joint_unidentified(run: Any) -> tuple[str, str]:
    """(accelerometer's, compass's) :func:`unidentified` reasons for the joint fit's pair of
    ``run`` ("" for a sensor it does not have or that is identified)."""
    acc = unidentified(run, f"accel{run.mapping.accel[0].instance}") if run.mapping.accel else ""
    mag = unidentified(run, f"compass{run.mapping.compass[0].instance}") if run.mapping.compass else ""
    return acc, mag
