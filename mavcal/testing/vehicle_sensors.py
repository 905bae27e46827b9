"""The test vehicle's physical side: true sensor errors, motion, and what the sensors read.

:class:`VehicleTruth` states each sensor's true errors **as the ideal ArduPilot
calibration** (the parameter values that would correct it exactly), so a test can compare
written parameters with the truth directly. :class:`SensorModel` produces the raw readings
of that truth for an attitude, and applies the calibration in force the way ArduPilot
does: :func:`mavcal.ardupilot.firmware.apply_accel` / :func:`~mavcal.ardupilot.firmware.apply_compass`
with the calibrations ``accel_cal_from_params`` / ``compass_cal_from_params`` build from
the current parameters. Two boot-time behaviours are kept on top of that: custom rotations
(101/102) use the ``CUST_ROTn_*`` angles read at the last boot, and a rotation value the
firmware does not know acts as NONE.

:class:`Motion` is the hand holding the vehicle: still, tumbling, or visiting a script of
poses. Attitudes are body-to-NED DCMs (:func:`mavcal.autopilot.rotations.euler_to_matrix`).
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot import rotations
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.testing.vehicle_params import COMPASS_DEV_IDS, N_COMPASS_SLOTS, N_IMUS, calibration_param_names

__all__ = ["AccelCalTruth", "CompassTruth", "VehicleTruth", "Motion", "SensorModel"]

_CAL_PARAM_NAMES = calibration_param_names()


# ------------------------------------------------------------------------------------------
# truth (the physical sensors)
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AccelCalTruth:
    """One accelerometer's true errors, stated **as its ideal ArduPilot calibration**.

    Convention: the sensor reads ``raw = u / scale + offsets`` in the board frame
    (u = true specific force, m/s^2, element-wise division), so the perfect parameters are
    ``INS_ACCnOFFS = offsets`` and ``INS_ACCnSCAL = scale``. (Not to be confused with
    :class:`mavcal.testing.simlog.AccelErrorTruth`, which states the sensor's own gain and
    bias: ``raw = K u + bias``.)
    """

    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    noise_mps2: float = 0.02


@dataclass(frozen=True)
class CompassTruth:
    """One compass's true errors, stated **as its ideal ArduPilot calibration**.

    The sensor reads ``s = R_mount^T ((1/scale) M^-1 B - offsets)`` (mGauss) for a body field
    B, with M from ``dia``/``odi``; the perfect parameters are ``COMPASS_OFS = offsets``,
    ``DIA/ODI = dia/odi``, ``SCALE = scale`` and (external compass) ``COMPASS_ORIENT =
    orientation``. ``dev_id`` identifies the physical device (slots follow it at boot).
    """

    dev_id: int
    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dia: tuple[float, float, float] = (1.0, 1.0, 1.0)
    odi: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    orientation: int = 0
    external: bool = False
    noise_mgauss: float = 2.0


@dataclass(frozen=True)
class VehicleTruth:
    """The simulated airframe: sensors' true errors, board mounting, Earth's field.

    ``board_orientation`` and the compasses' ``orientation`` are standard ArduPilot
    rotations (0..43).
    """

    accels: tuple[AccelCalTruth, ...]
    compasses: tuple[CompassTruth, ...]
    earth_field_ned_mgauss: tuple[float, float, float] = (205.0, 15.0, 420.0)
    board_orientation: int = 0
    gyro_noise_rads: float = 0.002
    temperature_c: float = 35.0

    @classmethod
    def random(cls, seed: int = 0) -> VehicleTruth:
        """Realistic random sensor errors (reproducible with ``seed``)."""
        rng = np.random.default_rng(seed)
        accels = tuple(AccelCalTruth(offsets=_t3(rng.uniform(-0.4, 0.4, 3)),
                                     scale=_t3(rng.uniform(0.97, 1.03, 3))) for _ in range(N_IMUS))
        comps = []
        for i, dev in enumerate(COMPASS_DEV_IDS):
            comps.append(CompassTruth(dev_id=dev, offsets=_t3(rng.uniform(-250, 250, 3)),
                                      dia=_t3(rng.uniform(0.92, 1.08, 3)),
                                      odi=_t3(rng.uniform(-0.04, 0.04, 3)),
                                      orientation=0, external=(i == 0)))
        return cls(accels=accels, compasses=tuple(comps))

    @classmethod
    def perfect(cls) -> VehicleTruth:
        """Sensors without errors (the default parameter table is then the ideal calibration)."""
        return cls(accels=(AccelCalTruth(),) * N_IMUS,
                   compasses=tuple(CompassTruth(dev_id=d, external=(i == 0)) for i, d in enumerate(COMPASS_DEV_IDS)))


def _t3(a: np.ndarray) -> tuple[float, float, float]:
    return (float(a[0]), float(a[1]), float(a[2]))


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    C = 1 - c
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


# ------------------------------------------------------------------------------------------
# motion
# ------------------------------------------------------------------------------------------
class Motion:
    """Attitude ``R`` (body to NED) and body rate ``omega`` of the hand-held vehicle.

    Not thread-safe: the vehicle holds its lock around every call.
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self.R = np.eye(3)
        self.omega = np.zeros(3)
        self.moving = False
        self._script: list[tuple[np.ndarray, np.ndarray, float]] = []
        self._script_t0 = 0.0
        self._last: float | None = None
        self.script_done = threading.Event()
        self.script_done.set()

    def hold(self, R: np.ndarray) -> None:
        """Hold still in attitude ``R`` (ends a tumble or a script)."""
        self.R = np.array(R, dtype=float)
        self.moving = False
        self.omega = np.zeros(3)
        self._script = []
        self.script_done.set()

    def tumble(self, moving: bool, rate_dps: float) -> None:
        """Start (or stop) a slow tumble about a random axis."""
        self.moving = bool(moving)
        if moving:
            axis = self._rng.normal(size=3)
            self.omega = math.radians(rate_dps) * axis / np.linalg.norm(axis)
        else:
            self.omega = np.zeros(3)

    def script(self, mats: Sequence[np.ndarray], hold_s: float, move_s: float) -> None:
        """Turn for ``move_s`` to each attitude, then hold it ``hold_s``."""
        prev = self.R.copy()
        self._script = []
        for M in mats:
            self._script.append((prev, M, move_s))
            self._script.append((M, M, hold_s))
            prev = M
        self._script_t0 = time.monotonic()
        self.script_done.clear()

    def advance(self, now: float) -> None:
        """Move on to monotonic time ``now``."""
        dt = now - (self._last if self._last is not None else now)
        self._last = now
        if self._script:
            self._follow_script(now - self._script_t0)
        elif self.moving and dt > 0:
            rate = float(np.linalg.norm(self.omega))
            self.R = self.R @ _axis_angle(self.omega / max(rate, 1e-12), rate * dt)
            u, _, vt = np.linalg.svd(self.R)  # re-orthonormalise
            self.R = u @ vt

    def _follow_script(self, t: float) -> None:
        for A, B, dur in self._script:
            if t <= dur:
                s = t / dur if dur > 0 else 1.0
                rel = A.T @ B
                ang = math.acos(max(-1.0, min(1.0, (np.trace(rel) - 1) / 2)))
                if ang < 1e-9:
                    self.R, self.omega = B.copy(), np.zeros(3)
                else:
                    axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
                    n = np.linalg.norm(axis)
                    axis = axis / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])
                    self.R = A @ _axis_angle(axis, ang * s)
                    self.omega = axis * ang / dur
                self.moving = ang >= 1e-9
                return
            t -= dur
        self.R = self._script[-1][1].copy()
        self.omega = np.zeros(3)
        self.moving = False
        self._script = []
        self.script_done.set()


# ------------------------------------------------------------------------------------------
# sensors
# ------------------------------------------------------------------------------------------
class SensorModel:
    """Raw and corrected readings of :class:`VehicleTruth` (not thread-safe, see :class:`Motion`).

    :meth:`boot` must be called after every (simulated) boot: it maps the physical compasses
    to slots by ``COMPASS_DEV_IDn`` and takes the custom rotation angles.
    """

    def __init__(self, truth: VehicleTruth, rng: np.random.Generator) -> None:
        self.truth = truth
        self._rng = rng
        self._slot_truth: list[CompassTruth | None] = [None] * N_COMPASS_SLOTS
        self._custom_deg: dict[int, tuple[float, float, float]] = {}
        self._cal_key: tuple[Any, ...] | None = None
        self._cal_cache: tuple[list[fw.AccelCal], list[fw.CompassCal]] = ([], [])

    def boot(self, dev_ids: Sequence[int], custom_deg: Mapping[int, tuple[float, float, float]]) -> None:
        """The compass in each slot (by device id) and the custom rotations built at boot."""
        by_id = {c.dev_id: c for c in self.truth.compasses}
        self._slot_truth = [by_id.get(int(d)) for d in dev_ids]
        self._custom_deg = dict(custom_deg)

    def _firmware_rotation(self, orient: int) -> tuple[int, tuple[float, float, float] | None]:
        """A rotation value as the firmware applies it: (value, custom angles or None)."""
        if orient in (rotations.CUSTOM_1, rotations.CUSTOM_2):
            return orient, self._custom_deg[orient]  # the angles read at boot
        if orient in rotations.ROTATIONS:
            return orient, None
        return 0, None  # Vector3::rotate of an unknown value: internal error, no rotation

    def calibrations(self, params: Mapping[str, float]) -> tuple[list[fw.AccelCal], list[fw.CompassCal]]:
        """The calibrations in force: accel per IMU, compass per priority slot.

        Rebuilt only when a parameter they depend on (or the boot-time custom angles) changed.
        """
        key = tuple(params.get(n) for n in _CAL_PARAM_NAMES) + tuple(self._custom_deg.values())
        if key == self._cal_key:
            return self._cal_cache
        accels = []
        for i in range(N_IMUS):
            acal = fw.accel_cal_from_params(params, i)
            o, c = self._firmware_rotation(acal.board_orient)
            accels.append(dataclasses.replace(acal, board_orient=o, custom_deg=c))
        compasses = []
        for slot in range(N_COMPASS_SLOTS):
            ccal = fw.compass_cal_from_params(params, slot)
            o, c = self._firmware_rotation(ccal.orient)
            compasses.append(dataclasses.replace(ccal, orient=o, custom_deg=c))
        self._cal_key, self._cal_cache = key, (accels, compasses)
        return accels, compasses

    def raw(self, R: np.ndarray, omega: np.ndarray, noise: bool) -> dict[str, Any]:
        """What the sensors measure in attitude ``R`` turning at ``omega``, before any calibration.

        ``accel_mps2`` (3, 3) board frame per IMU, ``mag_mgauss`` (3, 3) sensor frame per
        compass slot (None for a slot without a compass), ``gyro_rads`` (3, 3).
        """
        tr = self.truth
        f_body = R.T @ np.array([0.0, 0.0, -GRAVITY_MPS2])  # specific force at rest
        R_board = rotations.rotation_matrix(tr.board_orientation)
        accels = []
        for i in range(N_IMUS):
            at = tr.accels[i]
            raw = (R_board.T @ f_body) / np.array(at.scale) + np.array(at.offsets)
            if noise:
                raw = raw + self._rng.normal(0, at.noise_mps2, 3)
            accels.append(raw)
        B_body = R.T @ np.array(tr.earth_field_ned_mgauss)
        mags: list[np.ndarray | None] = []
        for ct in self._slot_truth:
            if ct is None:
                mags.append(None)
                continue
            M = fw.soft_iron_matrix(ct.dia, ct.odi)
            ideal = np.linalg.solve(M, B_body) / ct.scale - np.array(ct.offsets)
            mount = rotations.rotation_matrix(ct.orientation) if ct.external else R_board
            s = mount.T @ ideal
            if noise:
                s = s + self._rng.normal(0, ct.noise_mgauss, 3)
            mags.append(s)
        gyro = np.tile(omega, (3, 1))
        if noise:
            gyro = gyro + self._rng.normal(0, tr.gyro_noise_rads, (3, 3))
        return {"accel_mps2": np.array(accels), "mag_mgauss": mags, "gyro_rads": gyro}

    def corrected(self, R: np.ndarray, omega: np.ndarray, params: Mapping[str, float],
                  noise: bool) -> dict[str, Any]:
        """:meth:`raw` with the calibration in force applied (see the module docstring)."""
        raw = self.raw(R, omega, noise)
        accel_cals, compass_cals = self.calibrations(params)
        accels = [fw.apply_accel(cal, u) for cal, u in zip(accel_cals, raw["accel_mps2"])]
        mags = [np.zeros(3) if m is None else fw.apply_compass(cal, m)
                for cal, m in zip(compass_cals, raw["mag_mgauss"])]
        return {"accel_mps2": np.array(accels), "mag_mgauss": np.array(mags), "gyro_rads": raw["gyro_rads"]}
