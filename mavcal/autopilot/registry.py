"""The one registry: which autopilot's model a recording, a vehicle or a name gets.

The only module outside ``mavcal/ardupilot/`` and ``mavcal/px4/`` that names them. Which autopilot,
PX4 or ArduPilot, is decided here only: offline, a PX4 ULog (``kind`` "ulog") or a parameter set
that is PX4's (``CAL_ACC0_ID``, ``SENS_BOARD_ROT``...); live, the HEARTBEAT's ``autopilot`` field
(12 = MAV_AUTOPILOT_PX4) that :mod:`mavcal.link.live` records in ``ImuLog.vehicle["autopilot"]``.
Everything else is ArduPilot. A third autopilot is added here (its recognition, a branch in
:func:`model_for` and :func:`model_named`, its name in :data:`NAMES`) and in a folder of its own.
"""
from __future__ import annotations

from collections.abc import Container
from functools import lru_cache

from mavcal.autopilot.mavlink import MAV_AUTOPILOT_PX4
from mavcal.autopilot.model import AutopilotModel
from mavcal.sources.types import ImuLog

__all__ = ["NAMES", "is_px4", "is_px4_params", "model_for", "model_named", "models"]

#: the autopilots mavcal knows, by the name their model gives
NAMES = ("ArduPilot", "PX4")


def is_px4(log_: ImuLog) -> bool:
    """Whether ``log_`` comes from a PX4 autopilot (see the module docstring)."""
    if log_.kind == "ulog":
        return True
    ap = log_.vehicle.get("autopilot") if log_.vehicle else None
    if ap is not None:
        try:
            return int(ap) == MAV_AUTOPILOT_PX4  # type: ignore[call-overload]
        except (TypeError, ValueError):
            return False
    return bool(log_.params.changes) and is_px4_params(log_.params.changes)


def is_px4_params(names: Container[str]) -> bool:
    """Whether a set of parameter names is PX4's (it holds a calibration slot id or the board rotation)."""
    from mavcal.px4.params import is_px4_params as px4_says

    return px4_says(names)


def model_for(log_: ImuLog) -> AutopilotModel:
    """The model of ``log_``'s autopilot."""
    if is_px4(log_):
        from mavcal.px4.model import Px4Model

        return Px4Model(log_)
    from mavcal.ardupilot.model import ArduPilotModel

    return ArduPilotModel()


def model_named(name: str) -> AutopilotModel:
    """The model of the autopilot called ``name`` (one of :data:`NAMES`, any case) for a recording
    whose readings are not at hand (PX4's model then knows no device ids of its own)."""
    key = name.strip().lower()
    if key == "px4":
        from mavcal.px4.model import Px4Model

        return Px4Model(ImuLog(source="", kind="ulog", series=()))
    if key == "ardupilot":
        from mavcal.ardupilot.model import ArduPilotModel

        return ArduPilotModel()
    raise ValueError(f"unknown autopilot {name!r} (known: {', '.join(NAMES)})")


@lru_cache(maxsize=1)
def models() -> tuple[AutopilotModel, ...]:
    """One model of every autopilot, in the order of :data:`NAMES`: the write rules ask each of them
    about the parameter names it knows (:mod:`mavcal.autopilot.protocol`)."""
    return tuple(model_named(n) for n in NAMES)
