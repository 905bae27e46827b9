"""The autopilot-neutral layer and its one registry: which autopilot's model a recording needs.

This package says what any autopilot is to mavcal (:class:`AutopilotModel`) and holds the
vocabulary every autopilot speaks (:mod:`~mavcal.autopilot.raw`, :mod:`~mavcal.autopilot.verdicts`,
:mod:`~mavcal.autopilot.rotations`, :mod:`~mavcal.autopilot.mavlink`, :mod:`~mavcal.autopilot.paramfile`,
and the names the rest of mavcal uses for the calibration form, mapping, gates and write rules).
``mavcal/ardupilot/`` and ``mavcal/px4/`` are sibling implementations; nothing else names them.

Which autopilot, PX4 or ArduPilot, is decided here only.

Offline, a PX4 ULog (``kind`` "ulog") or a parameter set that is PX4's (``CAL_ACC0_ID``,
``SENS_BOARD_ROT``...); live, the HEARTBEAT's ``autopilot`` field (12 = MAV_AUTOPILOT_PX4) that
:mod:`mavcal.link.live` records in ``ImuLog.vehicle["autopilot"]``. Everything else is ArduPilot.
The model undoes the readings (``recover_raw``) and maps a fit onto parameters
(``map_calibration``, ``map_accel``); the pipeline around it is one.
"""
from __future__ import annotations

from collections.abc import Container, Mapping
from typing import TYPE_CHECKING, Protocol

import numpy as np

from mavcal.autopilot.mavlink import MAV_AUTOPILOT_PX4
from mavcal.px4.autosave import SaveSchedule  # PX4's parameter autosave, which a write to a PX4 keeps out of
from mavcal.px4.params import DETOUR_DWELL_S  # how long the vehicle is let see a write's detours
from mavcal.sources.types import ImuLog

if TYPE_CHECKING:
    from mavcal.autopilot.flight import FlightModel
    from mavcal.autopilot.gates import GateConfig
    from mavcal.autopilot.mapping import AccelMapping, ParamMapping
    from mavcal.autopilot.raw import RawImu

__all__ = ["AutopilotModel", "model_for", "model_named", "is_px4", "is_px4_params", "detoured_order", "DETOUR_DWELL_S",
           "SaveSchedule", "MAV_AUTOPILOT_PX4", "NAMES"]


#: the autopilots mavcal knows, by the name their model gives
NAMES = ("ArduPilot", "PX4")


class AutopilotModel(Protocol):
    """What an autopilot provides: its readings undone (``recover_raw``), a fit mapped onto its
    parameters (``map_calibration``, ``map_accel``), its own gate limits (``gate_config``) and the
    device ids of a sensor's slot (``device_ids``)."""

    name: str

    def recover_raw(self, log_: ImuLog) -> RawImu: ...

    def map_calibration(self, cal, params: Mapping[str, float], raw_mag_means, **kw) -> ParamMapping: ...

    def map_accel(self, K_a: np.ndarray, b_a: np.ndarray, params: Mapping[str, float],
                  instance: int) -> AccelMapping: ...

    def gate_config(self, base: GateConfig) -> GateConfig: ...

    def device_ids(self, log_: ImuLog, params: Mapping[str, float], accel_instance: int,
                   mag_instance: int) -> tuple[float | None, float | None]: ...

    def flight(self) -> FlightModel: ...


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


def detoured_order(changes: Mapping[str, float]) -> tuple[dict[str, float], dict[str, float]]:
    """The order in which to send ``changes`` and the detours to send before them: PX4's ``CAL_*``
    vectors go by a detour (:func:`mavcal.px4.params.detoured_order`); every other name (ArduPilot's)
    is sent as given, without detour."""
    from mavcal.px4.params import detoured_order as px4_order

    return px4_order(changes)
