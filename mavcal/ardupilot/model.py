"""ArduPilot as the pipeline sees it: raw recovery and parameter mapping (:mod:`mavcal.autopilot`),
the functions of :mod:`mavcal.ardupilot.recover` and :mod:`mavcal.ardupilot.mapping` unchanged."""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.flight import ArduPilotFlight
from mavcal.ardupilot.gates import GateConfig
from mavcal.ardupilot.mapping import AccelMapping, ParamMapping, map_accel, map_calibration
from mavcal.ardupilot.recover import RawImu, recover_raw
from mavcal.sources.types import ImuLog

__all__ = ["ArduPilotModel", "NAME"]

NAME = "ArduPilot"


class ArduPilotModel:
    """The ArduPilot model (the same for every recording)."""

    name = NAME

    def recover_raw(self, log_: ImuLog) -> RawImu:
        return recover_raw(log_)

    def map_calibration(self, cal, params: Mapping[str, float], raw_mag_means, **kw) -> ParamMapping:
        return map_calibration(cal, params, raw_mag_means, **kw)

    def gate_config(self, base: GateConfig) -> GateConfig:
        """``base`` unchanged: its limits are ArduPilot's (:mod:`mavcal.ardupilot.limits`)."""
        return base

    def device_ids(self, log_: ImuLog, params: Mapping[str, float], accel_instance: int,
                   mag_instance: int) -> tuple[float | None, float | None]:
        """(INS_ACC<n>_ID, COMPASS_DEV_ID<n>) of the instances as ``params`` hold them; None when absent."""
        try:
            accel = params.get(fw.accel_param_names(accel_instance)["id"])
        except ValueError:  # no such instance
            accel = None
        try:
            compass = params.get(fw.compass_param_names(mag_instance)["dev_id"])
        except ValueError:
            compass = None
        return accel, compass

    def flight(self) -> ArduPilotFlight:
        """ArduPilot's in-flight compass model (:mod:`mavcal.ardupilot.flight`)."""
        return ArduPilotFlight()

    def map_accel(self, K_a: np.ndarray, b_a: np.ndarray, params: Mapping[str, float], instance: int) -> AccelMapping:
        return map_accel(K_a, b_a, fw.accel_cal_from_params(params, instance), instance)
