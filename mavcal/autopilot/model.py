"""What an autopilot is to mavcal: the methods every autopilot's model provides (:class:`AutopilotModel`).

The registry (:mod:`mavcal.autopilot.registry`) hands out one model per recording or vehicle;
ArduPilot's and PX4's models are sibling implementations of this protocol. Nothing here knows a
parameter name.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from mavcal.autopilot.calform import AccelCal, CompassCal
    from mavcal.autopilot.flight import FlightModel
    from mavcal.autopilot.gates import GateConfig
    from mavcal.autopilot.limits import LimitViolation
    from mavcal.autopilot.mapping import AccelMapping, ParamMapping
    from mavcal.autopilot.raw import RawImu
    from mavcal.sources.types import ImuLog

__all__ = ["AutopilotModel"]


class AutopilotModel(Protocol):
    """What an autopilot provides.

    Readings and calibration: its readings undone (``recover_raw``), the calibration in force in
    the common form (``accel_cal``, ``compass_cal``), a fit mapped onto its parameters
    (``map_calibration``, ``map_accel``), its own gate limits (``gate_config``, ``compass_offset_max``,
    ``compass_slot_gate``), the device ids of a sensor's slot (``device_ids``), its slots
    (``max_instances``, ``slot_limit``, ``vector_names``), the plausibility of a logged value
    (``param_value_plausible``), its in-flight compass model (``flight``: :mod:`mavcal.autopilot.flight`).

    Writes, each autopilot answering for the parameter names it knows (:mod:`mavcal.autopilot.protocol`
    asks every model): value limits
    (``check_limits``, ``failing_kinds``, ``related_names``), device ids (``id_names``,
    ``device_id_problems``, ``remap_changes``), the write rules (``vector_group``, ``needs_reboot``,
    ``force_save_kinds``, ``detoured_order`` and ``detour_dwell_s``) and its parameter autosave
    (``autosave``).
    """

    name: str
    #: the most instances of a sensor kind ("accel", "mag") the autopilot logs
    max_instances: Mapping[str, int]
    #: how long the vehicle is let see a write's detours (s; 0: it takes none)
    detour_dwell_s: float
    #: poses within reach may hold its accelerometer at the calibration in force (``accel_cal``,
    #: :func:`mavcal.fits.reach_of`); False: its recordings take the full fit
    holds_accel_within_reach: bool

    def recover_raw(self, log_: ImuLog) -> RawImu: ...

    def accel_cal(self, params: Mapping[str, float], instance: int) -> AccelCal: ...

    def compass_cal(self, params: Mapping[str, float], instance: int) -> CompassCal: ...

    def map_calibration(self, cal, params: Mapping[str, float], raw_mag_means, **kw) -> ParamMapping: ...

    def map_accel(self, K_a: np.ndarray, b_a: np.ndarray, params: Mapping[str, float],
                  instance: int) -> AccelMapping: ...

    def gate_config(self, base: GateConfig) -> GateConfig: ...

    def compass_offset_max(self, params: Mapping[str, float]) -> float: ...

    def compass_slot_gate(self, params: Mapping[str, float], instance: int) -> tuple[float, str, str] | None: ...

    def device_ids(self, log_: ImuLog, params: Mapping[str, float], accel_instance: int,
                   mag_instance: int) -> tuple[float | None, float | None]: ...

    def flight(self) -> FlightModel: ...

    def vector_names(self, sensor: str, instance: int) -> Mapping[str, tuple[str, str, str]] | None: ...

    def slot_limit(self, kind: str) -> int | None: ...

    def param_value_plausible(self, name: str, value: float) -> bool: ...

    def check_limits(self, values: Mapping[str, float],
                     vehicle: Mapping[str, float] | None = None) -> list[LimitViolation]: ...

    def failing_kinds(self, values: Mapping[str, float], vehicle: Mapping[str, float] | None = None) -> set[str]: ...

    def related_names(self, names: Iterable[str]) -> list[str]: ...

    def id_names(self) -> list[str]: ...

    def device_id_problems(self, changes: Iterable[str], log_params: Mapping[str, float],
                           vehicle: Mapping[str, float], **maps: Any) -> list[str]: ...

    def remap_changes(self, changes: Mapping[str, float], **maps: Any) -> dict[str, float]: ...

    def vector_group(self, name: str) -> tuple[str, str, str] | None: ...

    def needs_reboot(self, name: str, value: float | None = None) -> bool: ...

    def force_save_kinds(self, names: Iterable[str]) -> tuple[str, ...]: ...

    def detoured_order(self, changes: Mapping[str, float]) -> tuple[dict[str, float], dict[str, float]]: ...

    def autosave(self, quiet_since_s: float) -> Any | None: ...
