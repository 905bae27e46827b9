"""The compass's in-flight compensation in force (the motor interference model), autopilot-neutral.

The in-flight stage (:mod:`mavcal.flight`) fits one form for every autopilot (its equation (1))::

    mag_i = A (b_i + o) + m x_i

``b_i`` the raw field of the sample, ``A`` what multiplies ``b + o`` into the body frame, ``o``
the offsets, ``m`` the motor term in the body frame per unit of the driver ``x`` (the battery
current in A, or the throttle 0..1). Each autopilot says how its own model maps onto that form
(:class:`FlightModel`): ArduPilot's and PX4's, each in its own folder; the stage gets the one it needs from the registry
(``mavcal.autopilot.model_named(name).flight()``), never by the folder's name.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from mavcal.sources.flight_series import CompassSeries

__all__ = ["COMPENSATION_CURRENT", "COMPENSATION_OFF", "COMPENSATION_THROTTLE", "AsApplied", "FlightModel",
           "InForce", "kind_code", "KIND_NAMES"]

#: the kinds of motor compensation, the same codes in ArduPilot (``COMPASS_MOTCT``) and PX4
#: (``CAL_MAG_COMP_TYP``; PX4's 3, the current of battery 1, is reported as the current)
COMPENSATION_OFF, COMPENSATION_THROTTLE, COMPENSATION_CURRENT = 0, 1, 2
KIND_NAMES = {COMPENSATION_THROTTLE: "throttle", COMPENSATION_CURRENT: "current"}


def kind_code(kind: str) -> int:
    """The compensation code of a driver's name ("current" or "throttle")."""
    return COMPENSATION_CURRENT if kind == "current" else COMPENSATION_THROTTLE


@dataclass(frozen=True)
class InForce:
    """One compass's calibration in force, in the stage's form (1).

    ``A`` (3, 3) what multiplies ``b + o``; ``ofs_mgauss`` the offsets ``o`` in force (None: the
    log carries them per sample, :class:`AsApplied`); ``mot_per_unit`` the motor term ``m`` in
    force (body frame, mGauss per A or per full throttle, for the kind in force); ``missing`` the
    parameters the log does not carry (their defaults assumed: not written); ``slot`` where its
    parameters live (ArduPilot's compass instance, PX4's ``CAL_MAGn`` slot)."""

    instance: int
    A: np.ndarray
    ofs_mgauss: np.ndarray | None
    mot_per_unit: np.ndarray
    missing: tuple[str, ...]
    slot: int

    @property
    def matrix_times_scale(self) -> np.ndarray:
        """``A`` (its name in ArduPilot's terms: ``M(DIA, ODI) · SCALE``)."""
        return self.A


@dataclass(frozen=True)
class AsApplied:
    """A compass's samples as the firmware used them, in the stage's form: the corrected field
    ``A (b + o) + m x`` (mGauss, body frame), the offsets ``o`` and the motor offset ``m x``
    applied, and the raw field ``b``; all (n, 3)."""

    field_mgauss: np.ndarray
    ofs_mgauss: np.ndarray
    motor_ofs_mgauss: np.ndarray
    raw_mgauss: np.ndarray


class FlightModel(Protocol):
    """An autopilot's in-flight compass model (see the module's notes)."""

    name: str
    #: the parameter that says what drives the compensation (``COMPASS_MOTCT``, ``CAL_MAG_COMP_TYP``)
    type_param: str
    #: the names the vehicle's MAVLink system id parameter has had (``MAV_SYSID`` / ``SYSID_THISMAV``, ``MAV_SYS_ID``)
    sysid_params: tuple[str, ...]

    def id_name(self, slot: int) -> str:
        """The parameter holding the device id of the compass whose parameters are in ``slot`` ("" : none)."""

    def motor_type(self, params: Mapping[str, float]) -> int | None:
        """The compensation kind in force (:data:`COMPENSATION_OFF`, ``_THROTTLE``, ``_CURRENT``); None: unknown."""

    def battery_instance(self, params: Mapping[str, float]) -> int:
        """The battery whose current the firmware compensates with."""

    def in_force(self, params: Mapping[str, float], c: CompassSeries) -> InForce:
        """Compass ``c``'s calibration in force; ValueError when the firmware has no such compass."""

    def as_applied(self, f: InForce, c: CompassSeries, params: Mapping[str, float],
                   driver_time_s: np.ndarray, driver: np.ndarray) -> AsApplied:
        """``c``'s samples as applied; ``driver``: the series of the kind in force (empty: none)."""

    def compass_in_use(self, params: Mapping[str, float], f: InForce) -> bool | None:
        """Whether the firmware uses the compass (None: the log does not say)."""

    def param_values(self, f: InForce, kind: int, mot_per_unit: np.ndarray) -> dict[str, float]:
        """The compensation parameters of the compass for a motor term ``m`` (body frame, per unit of ``kind``)."""

    def type_values(self, kind: int, params: Mapping[str, float]) -> dict[str, float]:
        """The parameter that selects the compensation ``kind`` (``params``: those in force)."""

