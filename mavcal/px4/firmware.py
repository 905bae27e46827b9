"""How PX4 applies its sensor calibration, forward and inverse (pure numpy).

Read in PX4's ``src/lib/sensor_calibration/`` (``Accelerometer.hpp`` / ``Magnetometer.hpp``,
``Correct``), per sample, ``R`` = level adjustment x rotation (:mod:`mavcal.px4.rotations`)::

    accel:  a = R @ ((u - thermal - OFF) * SCALE)          # u raw m/s^2, OFF m/s^2, SCALE per axis
    mag:    m = R @ (S @ ((s + power * COMP) - OFF))       # s raw gauss, OFF gauss, S symmetric

``S`` has ``_{X,Y,Z}SCALE`` on its diagonal and ``_{X,Y,Z}ODIAG`` at (0,1), (0,2), (1,2). ``R`` is
``SENS_BOARD_ROT`` for an internal sensor (``_ROT`` = -1) and ``CAL_MAGn_ROT`` for an external
magnetometer; an external accelerometer's ``CAL_ACCn_ROT`` likewise. A sensor without a slot
(no ``_ID`` equal to its device id) is used uncalibrated: OFF 0, scales 1, its default rotation.
mavcal reads the magnetometer in mGauss (x 1000); thermal and power compensation are not
modelled (warned when enabled, :mod:`mavcal.px4.recover`).

Each calibration also has an :meth:`~Px4MagCal.ardupilot_form`: the same function of the raw
reading written in the common form of :mod:`mavcal.autopilot.calform` (``M (R s + OFS)`` with
``M = R S R^T``, ``OFS = -R OFF``; a custom rotation holding ``R``), so that the shared quality
and gate stages judge a PX4 calibration with the equations they already have.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from mavcal.autopilot import calform as apfw
from mavcal.autopilot.rotations import CUSTOM_1
from mavcal.px4 import params as pn
from mavcal.px4.rotations import euler_deg, sensor_rotation

__all__ = ["Px4AccelCal", "Px4MagCal", "accel_cal_from_params", "mag_cal_from_params", "board_level_deg",
           "board_rotation_value", "device_external", "BUS_SIMULATION"]

BUS_SIMULATION = 4
_EXTERNAL_BUSES = (3, 5, 6)  # UAVCAN, SERIAL, MAVLINK (device::Device::DeviceBusType)


def _v3(x) -> tuple[float, float, float]:
    a = np.asarray(x, dtype=float).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


def _frozen(R) -> np.ndarray:
    m = np.array(R, dtype=float).reshape(3, 3)
    m.setflags(write=False)
    return m


def _get(params: Mapping[str, float], name: str, default: float) -> float:
    v = params.get(name)
    return float(v) if v is not None and np.isfinite(v) else float(default)


def board_level_deg(params: Mapping[str, float]) -> tuple[float, float, float]:
    """``SENS_BOARD_{X,Y,Z}_OFF`` (degrees; 0 when missing)."""
    return _v3([_get(params, n, 0.0) for n in pn.board_names()[1]])


def board_rotation_value(params: Mapping[str, float]) -> int:
    """``SENS_BOARD_ROT`` (0 when missing or invalid, as PX4's ``GetBoardRotation``)."""
    v = int(_get(params, pn.board_names()[0], 0.0))
    return v if v >= 0 else 0


def device_external(device_id: int) -> bool | None:
    """External by the device id's bus type (UAVCAN, serial, MAVLink: yes; simulation: no); None for
    I2C/SPI, whose answer depends on the board (PX4 asks the board's bus table)."""
    bus = int(device_id) & 0x7
    if bus == BUS_SIMULATION:
        return False
    if bus in _EXTERNAL_BUSES:
        return True
    return None


def _ap_rotation(R: np.ndarray) -> tuple[int, tuple[float, float, float]]:
    return CUSTOM_1, euler_deg(R)


@dataclass(frozen=True)
class Px4AccelCal:
    """One accelerometer's calibration as PX4 applies it (slot None: no slot, defaults)."""

    device_id: int
    slot: int | None
    ofs_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    rotation: np.ndarray = field(default_factory=lambda: _frozen(np.eye(3)))
    rot_value: int = -1
    external: bool = False

    def correct(self, raw_mps2) -> np.ndarray:
        """PX4's corrected, rotated acceleration (..., 3) for raw readings (sensor frame)."""
        u = np.asarray(raw_mps2, dtype=float)
        return ((u - np.asarray(self.ofs_mps2)) * np.asarray(self.scale)) @ self.rotation.T

    def undo(self, corrected_mps2) -> np.ndarray:
        """The raw readings (sensor frame) behind PX4's corrected ones."""
        a = np.asarray(corrected_mps2, dtype=float)
        return (a @ self.rotation) / np.asarray(self.scale) + np.asarray(self.ofs_mps2)

    def ardupilot_form(self) -> apfw.AccelCal:
        """The same correction as :class:`mavcal.autopilot.calform.AccelCal` (identical form)."""
        orient, custom = _ap_rotation(self.rotation)
        return apfw.AccelCal(ofs_mps2=self.ofs_mps2, scale=self.scale, board_orient=orient, custom_deg=custom)


@dataclass(frozen=True)
class Px4MagCal:
    """One magnetometer's calibration as PX4 applies it (offsets in gauss, sensor frame)."""

    device_id: int
    slot: int | None
    ofs_gauss: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    odiag: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: np.ndarray = field(default_factory=lambda: _frozen(np.eye(3)))
    rot_value: int = -1
    external: bool = False
    custom_deg: tuple[float, float, float] | None = None

    @property
    def matrix(self) -> np.ndarray:
        """S: diagonal SCALE, off-diagonal ODIAG at (0,1), (0,2), (1,2), symmetric."""
        d, o = self.scale, self.odiag
        return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])

    def correct(self, raw_mgauss) -> np.ndarray:
        """PX4's corrected, rotated field (..., 3) in mGauss for raw readings in mGauss (sensor frame)."""
        s = np.asarray(raw_mgauss, dtype=float) - 1000.0 * np.asarray(self.ofs_gauss)
        return s @ (self.rotation @ self.matrix).T

    def undo(self, corrected_mgauss) -> np.ndarray:
        """The raw readings (sensor frame, mGauss) behind PX4's corrected ones."""
        c = np.asarray(corrected_mgauss, dtype=float)
        return np.linalg.solve(self.rotation @ self.matrix, c.reshape(-1, 3).T).T.reshape(c.shape) \
            + 1000.0 * np.asarray(self.ofs_gauss)

    def ardupilot_form(self) -> apfw.CompassCal:
        """The same function of the raw reading in ArduPilot's form: ``M (R s + OFS)`` with
        ``M = R S R^T``, ``OFS = -R OFF`` (mGauss), ``R`` as a custom rotation, scale 1."""
        R = self.rotation
        M = R @ self.matrix @ R.T
        M = 0.5 * (M + M.T)
        orient, custom = _ap_rotation(R)
        return apfw.CompassCal(ofs_mgauss=_v3(-1000.0 * (R @ np.asarray(self.ofs_gauss))),
                               dia=(M[0, 0], M[1, 1], M[2, 2]), odi=(M[0, 1], M[0, 2], M[1, 2]), scale=1.0,
                               orient=orient, external=self.external, custom_deg=custom)


def _vector(params: Mapping[str, float], names, default: float) -> tuple[float, float, float]:
    return _v3([_get(params, n, default) for n in names])


def accel_cal_from_params(params: Mapping[str, float], device_id: int, external: bool | None = None) -> Px4AccelCal:
    """The calibration PX4 applies to accelerometer ``device_id`` with parameters ``params``."""
    level = board_level_deg(params)
    slot = pn.find_slot(params, "accel", device_id)
    ext = bool(external) if external is not None else bool(device_external(device_id))
    if slot is None:
        return Px4AccelCal(int(device_id), None, rotation=_frozen(sensor_rotation(
            0 if ext else board_rotation_value(params), level)), external=ext)
    n = pn.accel_names(slot)
    rot = int(_get(params, n["rot"], pn.ROT_INTERNAL))
    if external is None:
        ext = rot >= 0
    value = (rot if 0 <= rot < pn.ROT_CUSTOM else 0) if ext else board_rotation_value(params)
    return Px4AccelCal(int(device_id), slot, _vector(params, n["ofs"], 0.0), _vector(params, n["scale"], 1.0),
                       _frozen(sensor_rotation(value, level)), rot, ext)


def mag_cal_from_params(params: Mapping[str, float], device_id: int, external: bool | None = None) -> Px4MagCal:
    """The calibration PX4 applies to magnetometer ``device_id``: its slot by device id; external
    when ``external`` says so, else when its ``_ROT`` is set (PX4 forces -1 on an internal one),
    else by the device id's bus."""
    level = board_level_deg(params)
    slot = pn.find_slot(params, "mag", device_id)
    dev_ext = device_external(device_id)
    if slot is None:
        ext = bool(external) if external is not None else bool(dev_ext)
        return Px4MagCal(int(device_id), None, rotation=_frozen(sensor_rotation(
            0 if ext else board_rotation_value(params), level)), external=ext)
    n = pn.mag_names(slot)
    rot = int(_get(params, n["rot"], pn.ROT_INTERNAL))
    ext = bool(external) if external is not None else rot >= 0
    custom = None
    if ext:
        if rot == pn.ROT_CUSTOM:
            custom = _vector(params, n["custom"], 0.0)
            value = pn.ROT_CUSTOM
        else:
            value = rot if 0 <= rot <= max(rotation_value_range()) else 0
    else:
        value = board_rotation_value(params)
    return Px4MagCal(int(device_id), slot, _vector(params, n["ofs"], 0.0), _vector(params, n["scale"], 1.0),
                     _vector(params, n["odiag"], 0.0), _frozen(sensor_rotation(value, level, custom)), rot, ext,
                     custom)


def rotation_value_range() -> range:
    """The rotation values PX4 knows (0..47 in ``rot_lookup``)."""
    from mavcal.px4.rotations import ROT_LOOKUP_DEG

    return range(0, max(ROT_LOOKUP_DEG) + 1)


