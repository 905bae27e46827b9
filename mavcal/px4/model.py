"""PX4's model (:class:`mavcal.autopilot.model.AutopilotModel`): raw recovery, parameter mapping, its
gate limits and write rules.

The pipeline is the same for every autopilot; what differs is how the readings are undone
(:mod:`mavcal.px4.recover`) and what the calibration is written as (:mod:`mavcal.px4.mapping`).
The calibration of each sensor is found by its device id (``CAL_ACC<n>_ID``, ``CAL_MAG<n>_ID``).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import replace

import numpy as np

from mavcal.autopilot.calform import AccelCal, CompassCal
from mavcal.autopilot.gates import GateConfig
from mavcal.autopilot.limits import LimitViolation
from mavcal.autopilot.mapping import AccelMapping, ParamMapping
from mavcal.autopilot.raw import RawImu
from mavcal.px4 import params as pn
from mavcal.px4.autosave import SaveSchedule
from mavcal.px4.firmware import Px4AccelCal, Px4MagCal
from mavcal.px4.flight import Px4Flight
from mavcal.px4.mapping import map_accel_px4, map_calibration_px4
from mavcal.px4.recover import cal_of, device_id_of, recover_raw
from mavcal.sources.types import ImuLog, SensorSeries

__all__ = ["Px4Model", "NAME"]

NAME = "PX4"

#: PX4's own compass limits (src/modules/commander/mag_calibration.cpp, check_calibration_result):
#: it refuses a sphere radius (the field) outside 0.2-0.7 gauss and a non-positive scale, and warns of
#: offsets beyond 1.3 gauss (the compass saturates in some directions). Its accelerometer
#: calibration checks no range: the accelerometer and soft-iron gates keep mavcal's plausible ones.
PX4_FIELD_RANGE_MGAUSS = (200.0, 700.0)
PX4_OFFSET_MAX_MGAUSS = 1300.0


class Px4Model:
    """The PX4 model of one recording (it knows the recording's device ids)."""

    name = NAME
    max_instances: Mapping[str, int] = {"accel": pn.MAX_SLOTS, "mag": pn.MAX_SLOTS}
    detour_dwell_s = pn.DETOUR_DWELL_S
    holds_accel_within_reach = False  # the held accelerometer is read in ArduPilot's terms: PX4 takes the full fit

    def __init__(self, log_: ImuLog) -> None:
        self._series: dict[tuple[str, int], SensorSeries] = {(s.sensor, s.instance): s for s in log_.series
                                                            if s.sensor != "gyro"}

    def recover_raw(self, log_: ImuLog) -> RawImu:
        return recover_raw(log_)

    def _cal(self, sensor: str, instance: int, params: Mapping[str, float]) -> Px4AccelCal | Px4MagCal:
        s = self._series.get((sensor, instance))
        if s is None:
            s = SensorSeries(sensor, instance, "", np.zeros(0), np.zeros((0, 3)))
        return cal_of(s, params)

    def accel_cal(self, params: Mapping[str, float], instance: int) -> AccelCal:
        """The accelerometer's ``CAL_ACC*`` (its slot by device id) in the common form."""
        cal = self._cal("accel", instance, params)
        assert isinstance(cal, Px4AccelCal)
        return cal.ardupilot_form()

    def compass_cal(self, params: Mapping[str, float], instance: int) -> CompassCal:
        """The magnetometer's ``CAL_MAG*`` (its slot by device id) in the common form."""
        cal = self._cal("mag", instance, params)
        assert isinstance(cal, Px4MagCal)
        return cal.ardupilot_form()

    def map_calibration(self, cal, params: Mapping[str, float], raw_mag_means, *, accel_instance: int = 0,
                        mag_instance: int = 0, **kw) -> ParamMapping:
        old_a, old_m = self._cal("accel", accel_instance, params), self._cal("mag", mag_instance, params)
        assert isinstance(old_a, Px4AccelCal) and isinstance(old_m, Px4MagCal)
        return map_calibration_px4(cal, params, old_a, old_m, accel_instance=accel_instance,
                                   mag_instance=mag_instance, **kw)

    def gate_config(self, base: GateConfig) -> GateConfig:
        """``base`` with PX4's own limits where it has them (module constants), in PX4's words;
        a limit the user set (``compass_offset_max_mgauss``) is kept."""
        return replace(base, limits_of="the plausible", autopilot=NAME, field_range_mgauss=PX4_FIELD_RANGE_MGAUSS,
                       compass_offset_max_mgauss=base.compass_offset_max_mgauss or PX4_OFFSET_MAX_MGAUSS,
                       offset_limit_name="PX4's saturation warning at 1.3 gauss")

    def device_ids(self, log_: ImuLog, params: Mapping[str, float], accel_instance: int,
                   mag_instance: int) -> tuple[float | None, float | None]:
        """The device ids of the instances (the recording's, else the slot's ``CAL_*_ID``); None when
        the recording has no such sensor."""
        out: list[float | None] = []
        for sensor, i in (("accel", accel_instance), ("mag", mag_instance)):
            s = self._series.get((sensor, i))
            out.append(None if s is None else (device_id_of(s, params)[0] or None))
        return out[0], out[1]

    def flight(self) -> Px4Flight:
        """PX4's in-flight compass model (:mod:`mavcal.px4.flight`)."""
        return Px4Flight()

    def map_accel(self, K_a: np.ndarray, b_a: np.ndarray, params: Mapping[str, float], instance: int) -> AccelMapping:
        old = self._cal("accel", instance, params)
        assert isinstance(old, Px4AccelCal)
        return map_accel_px4(K_a, b_a, old, params, instance)

    def compass_offset_max(self, params: Mapping[str, float]) -> float:
        """PX4's saturation warning (1.3 gauss): it has no offset limit parameter."""
        return PX4_OFFSET_MAX_MGAUSS

    def compass_slot_gate(self, params: Mapping[str, float], instance: int) -> tuple[float, str, str] | None:
        """None: PX4 finds a magnetometer's slot by its device id, no slot can hold another device."""
        return None

    def vector_names(self, sensor: str, instance: int) -> Mapping[str, tuple[str, str, str]] | None:
        """None: a PX4 slot follows the device id, not the instance (the mapping's old values stand)."""
        return None

    def slot_limit(self, kind: str) -> int | None:
        """None: PX4 finds a sensor's slot by device id, there are no slots to map."""
        return None

    def param_value_plausible(self, name: str, value: float) -> bool:
        return True

    # ------------------------------------------------------------------ writes: the names PX4 knows
    # PX4 checks no values before a write (its parameters' own ranges hold), has no slots to match by
    # position, takes its CAL_* vectors whole by the detours of detoured_order and needs no force-save.

    def check_limits(self, values: Mapping[str, float],
                     vehicle: Mapping[str, float] | None = None) -> list[LimitViolation]:
        return []

    def failing_kinds(self, values: Mapping[str, float], vehicle: Mapping[str, float] | None = None) -> set[str]:
        return set()

    def related_names(self, names: Iterable[str]) -> list[str]:
        return []

    def id_names(self) -> list[str]:
        return []

    def device_id_problems(self, changes: Iterable[str], log_params: Mapping[str, float],
                           vehicle: Mapping[str, float], **maps) -> list[str]:
        return []

    def remap_changes(self, changes: Mapping[str, float], **maps) -> dict[str, float]:
        return dict(changes)

    def vector_group(self, name: str) -> tuple[str, str, str] | None:
        return None

    def needs_reboot(self, name: str, value: float | None = None) -> bool:
        return False

    def force_save_kinds(self, names: Iterable[str]) -> tuple[str, ...]:
        return ()

    def detoured_order(self, changes: Mapping[str, float]) -> tuple[dict[str, float], dict[str, float]]:
        """PX4's ``CAL_*`` vectors by a detour (:func:`.params.detoured_order`); other names as given."""
        return pn.detoured_order(changes)

    def autosave(self, quiet_since_s: float) -> SaveSchedule:
        """PX4's parameter autosave as a write's changes schedule it (:mod:`.autosave`)."""
        return SaveSchedule(quiet_since_s)
