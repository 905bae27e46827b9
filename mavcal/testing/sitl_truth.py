"""The truth of the SITL logs in ``sitl_logs/`` (``*.truth.json``, format "sitl_dance truth v1").

ArduPilot's SITL simulates (``model_equations`` of the truth file)::

    mag raw  = SIM_MAG1_SCALING * rot(SIM_MAG1_ORIENT)^T (M_sim^-1 B_body - SIM_MAG1_OFS)
    acc raw  = f_body / SIM_ACC1_SCAL + SIM_ACC1_BIAS      (element-wise)

with M_sim the symmetric matrix of SIM_MAG1_DIA/ODI (DIA all zero = identity). The
functions below give those raw readings for any true body vectors, so written parameters
can be checked with :func:`mavcal.autopilot.evaluate.attitude_errors`.

:class:`InjectedErrors` are the same errors for a live SITL (:mod:`mavcal.testing.sitl`):
drawn from a seed, as SIM_* parameters, with the ideal ArduPilot calibration they imply;
:func:`score` scores a calibration written to that vehicle against them.
"""
from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.evaluate import AttitudeErrors, attitude_errors
from mavcal.autopilot.rotations import rotation_matrix


@dataclass(frozen=True, eq=False)
class SitlTruth:
    raw_accel: Callable[[np.ndarray], np.ndarray]
    raw_mag_sensor: Callable[[np.ndarray], np.ndarray]
    field_ned_mgauss: np.ndarray
    expected: dict[str, float]
    injected: dict[str, float]


def load_truth(path) -> SitlTruth:
    t = json.loads(Path(path).read_text())
    if t.get("format") != "sitl_dance truth v1":
        raise ValueError(f"{path}: not a sitl_dance truth v1 file")
    p = t["injected_sim_params"]

    def v3(prefix):
        return np.array([p[f"{prefix}_X"], p[f"{prefix}_Y"], p[f"{prefix}_Z"]], dtype=float)

    M_sim = fw.soft_iron_matrix(v3("SIM_MAG1_DIA"), v3("SIM_MAG1_ODI"))
    R_orient = rotation_matrix(int(p.get("SIM_MAG1_ORIENT", 0)))
    scaling = float(p.get("SIM_MAG1_SCALING", 1.0)) or 1.0
    ofs = v3("SIM_MAG1_OFS")
    acc_scal = v3("SIM_ACC1_SCAL")
    acc_bias = v3("SIM_ACC1_BIAS")
    M_inv = np.linalg.inv(M_sim)

    def raw_accel(f_body):
        return np.asarray(f_body) / acc_scal + acc_bias

    def raw_mag_sensor(B_body):
        return scaling * ((np.asarray(B_body) @ M_inv.T - ofs) @ R_orient)

    return SitlTruth(raw_accel, raw_mag_sensor, np.array(t["reference"]["earth_field_ned_mgauss"], dtype=float),
                     dict(t["expected_vehicle_params_for_perfect_calibration"]), dict(p))


# ------------------------------------------------------------------------------------------
# the errors a live SITL is started with (mavcal.testing.sitl), their truth and a scorer
# ------------------------------------------------------------------------------------------
Vec3 = tuple[float, float, float]


def _f32(x: float) -> float:
    return float(np.float32(x))


def _v3(a: Iterable[float]) -> Vec3:
    x, y, z = (_f32(v) for v in a)
    return (x, y, z)


@dataclass(frozen=True)
class InjectedErrors:
    """The simulator's errors of compass 1 and IMU 1 (values as float32, as stored)."""

    mag_ofs_mgauss: Vec3 = (5.0, 13.0, -18.0)  # SIM_MAG1_OFS (copter.parm's COMPASS_OFS)
    mag_dia: Vec3 = (1.0, 1.0, 1.0)  # SIM_MAG1_DIA
    mag_odi: Vec3 = (0.0, 0.0, 0.0)  # SIM_MAG1_ODI
    mag_orient: int = 0  # SIM_MAG1_ORIENT: the compass's mounting (the right COMPASS_ORIENT)
    mag_noise_mgauss: float = 3.0  # SIM_MAG_RND (uniform, per axis)
    acc_bias_mps2: Vec3 = (0.0, 0.0, 0.0)  # SIM_ACC1_BIAS
    acc_scale: Vec3 = (1.0, 1.0, 1.0)  # SIM_ACC1_SCAL

    def __post_init__(self) -> None:
        for name in ("mag_ofs_mgauss", "mag_dia", "mag_odi", "acc_bias_mps2", "acc_scale"):
            object.__setattr__(self, name, _v3(getattr(self, name)))

    @classmethod
    def random(cls, seed: int, *, mag_orient: int = 0) -> InjectedErrors:
        """Realistic errors: compass offsets up to 250 mGauss, soft iron 0.9-1.1 / +-0.05,
        accelerometer biases up to 0.4 m/s^2, scales 0.97-1.03 (rounded as a person types them)."""
        rng = np.random.default_rng(seed)
        return cls(mag_ofs_mgauss=tuple(np.round(rng.uniform(-250, 250, 3), 1)),
                   mag_dia=tuple(np.round(rng.uniform(0.9, 1.1, 3), 4)),
                   mag_odi=tuple(np.round(rng.uniform(-0.05, 0.05, 3), 4)),
                   mag_orient=int(mag_orient),
                   acc_bias_mps2=tuple(np.round(rng.uniform(-0.4, 0.4, 3), 3)),
                   acc_scale=tuple(np.round(rng.uniform(0.97, 1.03, 3), 4)))

    def sim_params(self) -> dict[str, float]:
        """The SIM_* parameters that inject these errors."""
        out: dict[str, float] = {"SIM_MAG1_ORIENT": float(self.mag_orient), "SIM_MAG1_SCALING": 1.0,
                                 "SIM_MAG_RND": _f32(self.mag_noise_mgauss)}
        for prefix, v in (("SIM_MAG1_OFS", self.mag_ofs_mgauss), ("SIM_MAG1_DIA", self.mag_dia),
                          ("SIM_MAG1_ODI", self.mag_odi), ("SIM_ACC1_BIAS", self.acc_bias_mps2),
                          ("SIM_ACC1_SCAL", self.acc_scale)):
            out.update({f"{prefix}_{a}": x for a, x in zip("XYZ", v)})
        return out

    def ideal_params(self) -> dict[str, float]:
        """The perfect ArduPilot calibration of compass 1 and IMU 1 (COMPASS_SCALE 1)."""
        c, a = fw.compass_param_names(0), fw.accel_param_names(0)
        out: dict[str, float] = {}
        for names, v in ((c["ofs"], self.mag_ofs_mgauss), (c["dia"], self.mag_dia), (c["odi"], self.mag_odi),
                         (a["ofs"], self.acc_bias_mps2), (a["scale"], self.acc_scale)):
            out.update(dict(zip(names, v)))
        out[c["orient"]] = float(self.mag_orient)
        out[c["scale"]] = 1.0
        return out

    def raw_accel(self, f_body_mps2) -> np.ndarray:
        """SITL's raw accelerometer reading for the true specific force (no noise)."""
        return np.asarray(f_body_mps2, dtype=float) / np.array(self.acc_scale) + np.array(self.acc_bias_mps2)

    def raw_mag_sensor(self, B_body_mgauss) -> np.ndarray:
        """SITL's raw compass reading (sensor frame) for the true field in the body frame."""
        M = fw.soft_iron_matrix(self.mag_dia, self.mag_odi)
        R = rotation_matrix(self.mag_orient)
        return (np.asarray(B_body_mgauss, dtype=float) @ np.linalg.inv(M).T - np.array(self.mag_ofs_mgauss)) @ R

    def body_field(self, raw_mag_sensor) -> np.ndarray:
        """The true body-frame field from a raw reading (inverse of :meth:`raw_mag_sensor`)."""
        M = fw.soft_iron_matrix(self.mag_dia, self.mag_odi)
        R = rotation_matrix(self.mag_orient)
        return (np.asarray(raw_mag_sensor, dtype=float) @ R.T + np.array(self.mag_ofs_mgauss)) @ M.T

    def sitl_truth(self, field_ned_mgauss) -> SitlTruth:
        """As :func:`mavcal.testing.sitl_truth.load_truth` gives for a recorded SITL log."""
        return SitlTruth(self.raw_accel, self.raw_mag_sensor, np.asarray(field_ned_mgauss, dtype=float),
                         self.ideal_params(), self.sim_params())


@dataclass(frozen=True)
class Score:
    """A written calibration of compass 1 / IMU 1 against the injected truth."""

    errors: AttitudeErrors  # heading / tilt over the flight envelope (roll, pitch +-45 deg, every yaw)
    max_heading_deg: float
    max_tilt_deg: float
    compass_ofs_error_mgauss: float  # largest |COMPASS_OFS - truth| per axis
    accel_ofs_error_mps2: float
    accel_scale_error: float
    orient: int
    orient_right: bool

    def line(self) -> str:
        return (f"heading {self.max_heading_deg:.3f} deg, tilt {self.max_tilt_deg:.4f} deg, "
                f"compass offsets {self.compass_ofs_error_mgauss:.2f} mGauss, accel offsets "
                f"{self.accel_ofs_error_mps2:.4f} m/s^2, scales {self.accel_scale_error:.5f}, "
                f"COMPASS_ORIENT {self.orient} ({'right' if self.orient_right else 'WRONG'})")


def score(params: Mapping[str, float], errors: InjectedErrors, field_ned_mgauss) -> Score:
    """Score the calibration ``params`` (the vehicle's parameters after a write) of compass 1
    and IMU 1 against ``errors``: what ArduPilot will see with them, over the flight envelope."""
    cal_c = fw.compass_cal_from_params(params, 0)
    cal_a = fw.accel_cal_from_params(params, 0)
    e = attitude_errors(errors.raw_accel, errors.raw_mag_sensor, cal_a, cal_c, np.asarray(field_ned_mgauss, float))
    return Score(errors=e, max_heading_deg=e.max_heading_deg, max_tilt_deg=e.max_tilt_deg,
                 compass_ofs_error_mgauss=float(np.max(np.abs(np.array(cal_c.ofs_mgauss) - errors.mag_ofs_mgauss))),
                 accel_ofs_error_mps2=float(np.max(np.abs(np.array(cal_a.ofs_mps2) - errors.acc_bias_mps2))),
                 accel_scale_error=float(np.max(np.abs(np.array(cal_a.scale) - errors.acc_scale))),
                 orient=cal_c.orient, orient_right=cal_c.orient == errors.mag_orient)
