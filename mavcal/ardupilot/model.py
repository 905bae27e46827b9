"""ArduPilot's model (:class:`mavcal.autopilot.model.AutopilotModel`): what the rest of mavcal asks of
ArduPilot, answered by this folder's modules (raw recovery, mapping, firmware, limits, device slots,
write rules), the same for every recording."""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import replace

import numpy as np

from mavcal.ardupilot import devices, protocol
from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot import limits as L
from mavcal.ardupilot.flight import ArduPilotFlight
from mavcal.ardupilot.mapping import map_accel, map_calibration
from mavcal.ardupilot.recover import recover_raw
from mavcal.autopilot.calform import AccelCal, CompassCal
from mavcal.autopilot.gates import GateConfig
from mavcal.autopilot.limits import LimitViolation
from mavcal.autopilot.mapping import AccelMapping, ParamMapping
from mavcal.autopilot.raw import RawImu
from mavcal.sources.types import ImuLog

__all__ = ["ArduPilotModel", "NAME"]

NAME = "ArduPilot"


class ArduPilotModel:
    """The ArduPilot model (the same for every recording)."""

    name = NAME
    max_instances: Mapping[str, int] = {"accel": fw.MAX_IMUS, "mag": fw.MAX_COMPASSES}
    detour_dwell_s = 0.0  # no detours
    holds_accel_within_reach = True

    # ------------------------------------------------------------------ readings and calibration

    def recover_raw(self, log_: ImuLog) -> RawImu:
        return recover_raw(log_)

    def accel_cal(self, params: Mapping[str, float], instance: int) -> AccelCal:
        """INS_ACC<n>* and the board orientation as the common form."""
        return fw.accel_cal_from_params(params, instance)

    def compass_cal(self, params: Mapping[str, float], instance: int) -> CompassCal:
        """COMPASS_*<n> as the common form."""
        return fw.compass_cal_from_params(params, instance)

    def map_calibration(self, cal, params: Mapping[str, float], raw_mag_means, **kw) -> ParamMapping:
        return map_calibration(cal, params, raw_mag_means, **kw)

    def map_accel(self, K_a: np.ndarray, b_a: np.ndarray, params: Mapping[str, float], instance: int) -> AccelMapping:
        return map_accel(K_a, b_a, fw.accel_cal_from_params(params, instance), instance)

    def gate_config(self, base: GateConfig) -> GateConfig:
        """``base`` in ArduPilot's words (its limit values are ``base``'s defaults, :mod:`.limits`'s table)."""
        return replace(base, limits_of="ArduPilot's", autopilot=NAME, offset_limit_name=L.COMPASS_OFFS_MAX)

    def compass_offset_max(self, params: Mapping[str, float]) -> float:
        """COMPASS_OFFS_MAX of ``params``, else its default."""
        return L.compass_offset_max(params)

    def compass_slot_gate(self, params: Mapping[str, float], instance: int) -> tuple[float, str, str] | None:
        """(value, limit, reason) of the failed "device id" gate when the compass slot holds another device
        than its priority names (the slots swapped after a priority change); None when they agree."""
        names = fw.compass_param_names(instance)
        dev = params.get(names["dev_id"])
        prio = params.get(names["prio_id"])
        if dev is not None and prio is not None and int(dev) != int(prio) and int(prio) != 0:
            return (dev, f"= COMPASS_PRIO{instance + 1}_ID",
                    f"compass slot {instance + 1} holds device {int(dev)} but priority {instance + 1} is device "
                    f"{int(prio)}: the slots swapped after a priority change; reboot the vehicle and recalibrate")
        return None

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
        """ArduPilot's in-flight compass model (:mod:`.flight`)."""
        return ArduPilotFlight()

    def vector_names(self, sensor: str, instance: int) -> Mapping[str, tuple[str, str, str]] | None:
        """The names of a sensor's calibration vectors by instance: a compass's ``ofs``, an
        accelerometer's ``ofs`` and ``scale``."""
        if sensor == "compass":
            return {"ofs": fw.compass_param_names(instance)["ofs"]}
        an = fw.accel_param_names(instance)
        return {"ofs": an["ofs"], "scale": an["scale"]}

    def slot_limit(self, kind: str) -> int | None:
        """The slots of a kind ("compass", else the IMUs) a log slot may be mapped to."""
        return fw.MAX_COMPASSES if kind == "compass" else fw.MAX_IMUS

    def param_value_plausible(self, name: str, value: float) -> bool:
        return fw.param_value_plausible(name, value)

    # ------------------------------------------------------------------ writes: the names ArduPilot knows

    def check_limits(self, values: Mapping[str, float],
                     vehicle: Mapping[str, float] | None = None) -> list[LimitViolation]:
        return L.check_limits(values, vehicle)

    def failing_kinds(self, values: Mapping[str, float], vehicle: Mapping[str, float] | None = None) -> set[str]:
        return L.failing_kinds(values, vehicle)

    def related_names(self, names: Iterable[str]) -> list[str]:
        return L.related_names(names)

    def id_names(self) -> list[str]:
        return devices.id_names()

    def device_id_problems(self, changes: Iterable[str], log_params: Mapping[str, float],
                           vehicle: Mapping[str, float], **maps) -> list[str]:
        return devices.device_id_problems(changes, log_params, vehicle, **maps)

    def remap_changes(self, changes: Mapping[str, float], **maps) -> dict[str, float]:
        return devices.remap_changes(changes, **maps)

    def vector_group(self, name: str) -> tuple[str, str, str] | None:
        return protocol.vector_group(name)

    def needs_reboot(self, name: str, value: float | None = None) -> bool:
        return protocol.needs_reboot(name, value)

    def force_save_kinds(self, names: Iterable[str]) -> tuple[str, ...]:
        return protocol.force_save_kinds(names)

    def detoured_order(self, changes: Mapping[str, float]) -> tuple[dict[str, float], dict[str, float]]:
        """``changes`` as given, without detour."""
        return dict(changes), {}

    def autosave(self, quiet_since_s: float) -> None:
        """None: ArduPilot saves each PARAM_SET at once."""
        return None
