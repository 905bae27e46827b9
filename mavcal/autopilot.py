"""Which autopilot's model a recording needs: PX4 or ArduPilot.

Offline, a PX4 ULog (``kind`` "ulog") or a parameter set that is PX4's (``CAL_ACC0_ID``,
``SENS_BOARD_ROT``...); live, the HEARTBEAT's ``autopilot`` field (12 = MAV_AUTOPILOT_PX4) that
:mod:`mavcal.link.live` records in ``ImuLog.vehicle["autopilot"]``. Everything else is ArduPilot.
The model undoes the readings (``recover_raw``) and maps a fit onto parameters
(``map_calibration``, ``map_accel``); the pipeline around it is one.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import numpy as np

from mavcal.ardupilot.gates import GateConfig
from mavcal.ardupilot.mapping import AccelMapping, ParamMapping
from mavcal.ardupilot.recover import RawImu
from mavcal.sources.types import ImuLog

__all__ = ["AutopilotModel", "model_for", "is_px4", "MAV_AUTOPILOT_PX4"]

MAV_AUTOPILOT_PX4 = 12


class AutopilotModel(Protocol):
    name: str

    def recover_raw(self, log_: ImuLog) -> RawImu: ...

    def map_calibration(self, cal, params: Mapping[str, float], raw_mag_means, **kw) -> ParamMapping: ...

    def map_accel(self, K_a: np.ndarray, b_a: np.ndarray, params: Mapping[str, float],
                  instance: int) -> AccelMapping: ...

    def gate_config(self, base: GateConfig) -> GateConfig: ...

    def device_ids(self, log_: ImuLog, params: Mapping[str, float], accel_instance: int,
                   mag_instance: int) -> tuple[float | None, float | None]: ...


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
    from mavcal.px4.params import is_px4_params

    return bool(log_.params.changes) and is_px4_params(log_.params.changes)


def model_for(log_: ImuLog) -> AutopilotModel:
    """The model of ``log_``'s autopilot."""
    if is_px4(log_):
        from mavcal.px4.model import Px4Model

        return Px4Model(log_)
    from mavcal.ardupilot.model import ArduPilotModel

    return ArduPilotModel()
