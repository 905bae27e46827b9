"""A synthetic PX4 flight written as a ULog, made from PX4's own equations with a known truth.

PX4 corrects each raw reading ``s`` (gauss, sensor frame) as ``R S ((s + power COMP) - OFF)``
(:mod:`mavcal.px4.flight`). The truth of compass k is the calibration that makes that the Earth
field in the body frame exactly: ``OFF_true``, ``S``, ``R`` and ``COMP_true``, so its raw reading is::

    s = S^-1 R^T B_body + OFF_true - power COMP_true  (+ white noise)

with ``power`` the battery current in kA (``CAL_MAG_COMP_TYP`` 2) or the throttle (1, the length
of ``vehicle_thrust_setpoint``). The log carries the calibration *in force* (``COMP`` 0 unless
said, offsets as the truth unless made wrong), the attitude (``vehicle_attitude``), the current
(``battery_status``), the thrust, the GPS, the EKF-GSF yaw (``yaw_estimator_status``), the arming
state and the altitude. The flight's motion is :mod:`mavcal.testing.flight_synth`'s.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mavcal.px4 import params as pn
from mavcal.px4.rotations import sensor_rotation
from mavcal.testing.ulog_writer import UlogWriter

__all__ = ["Px4SynthCompass", "write_px4_flight", "MAG_IDS"]

#: device ids of the simulated compasses (bus type 4, simulation; then two external UAVCAN-like ids)
MAG_IDS = (197388, 0x0A1E03, 0x0A1F03)


@dataclass(frozen=True)
class Px4SynthCompass:
    comp_true: tuple[float, float, float] = (0.0, 0.0, 0.0)  # CAL_MAGn_xCOMP that cancels it (G/kA or G)
    ofs_true_gauss: tuple[float, float, float] = (0.05, -0.03, 0.08)
    ofs_in_force_gauss: tuple[float, float, float] | None = None  # None: as the truth
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    odiag: tuple[float, float, float] = (0.0, 0.0, 0.0)
    comp_in_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rot: int = -1  # CAL_MAGn_ROT: -1 internal (SENS_BOARD_ROT), else an external compass's rotation
    slot: int | None = None  # its CAL_MAGn slot (None: its instance)


def _motion(duration_s: float, rate_hz: float, current_max_a: float):
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    yaw = (t * 360.0 / 40.0 + 20 * np.sin(t / 7.0)) % 360.0
    roll = 15 * np.sin(t / 3.1 + 1.0) * np.sin(t / 11.0)
    pitch = 12 * np.sin(t / 4.3) * np.cos(t / 13.0)
    cur = current_max_a * np.clip(0.5 + 0.45 * np.sin(t / 5.0) * np.sin(t / 17.0 + 0.5), 0.0, 1.0)
    return t, roll, pitch, yaw, cur


def write_px4_flight(path: str | Path, compasses: Sequence[Px4SynthCompass], *, seed: int = 0,
                     comp_type: int = 2, duration_s: float = 150.0, rate_hz: float = 20.0,
                     current_max_a: float = 40.0, noise_mgauss: float = 2.0,
                     lat_lon: tuple[float, float] = (47.397, 8.546), battery: bool = True,
                     gsf: bool = True) -> Path:
    """Write the flight to ``path`` (see the module's notes); the throttle is ``0.2 + 0.5 I / I_max``
    (the hover thrust 0.35); ``battery`` False: no battery_status (no current sensor)."""
    from mavcal.sources.wmm import field_ned

    rng = np.random.default_rng(seed)
    t, roll, pitch, yaw, cur = _motion(duration_s, rate_hz, current_max_a)
    thr = 0.2 + 0.5 * cur / max(current_max_a, 1e-9)
    rot = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    R = rot.as_matrix()  # body -> NED
    B = field_ned(*lat_lon)
    body = np.einsum("nji,j->ni", R, B) / 1000.0  # gauss
    power = cur / 1000.0 if comp_type in (2, 3) else thr
    t_us = (5_000_000 + t * 1e6).astype(np.int64)
    path = Path(path)
    with UlogWriter(path) as w:
        w.info("sys_name", "PX4")
        w.info("ver_sw", "synthetic")
        w.param(pn.MAG_COMP_TYPE, comp_type, int32=True)
        w.param(pn.board_names()[0], 0, int32=True)
        w.param("MAV_SYS_ID", 1, int32=True)
        raws = []
        for k, c in enumerate(compasses):
            slot = k if c.slot is None else c.slot
            n = pn.mag_names(slot)
            w.param(n["id"], MAG_IDS[k], int32=True)
            w.param(n["prio"], 50 if c.rot < 0 else 75, int32=True)
            w.param(n["rot"], c.rot, int32=True)
            ofs_force = c.ofs_true_gauss if c.ofs_in_force_gauss is None else c.ofs_in_force_gauss
            for names, vals in ((n["ofs"], ofs_force), (n["scale"], c.scale), (n["odiag"], c.odiag),
                                (n["comp"], c.comp_in_force)):
                for nm, v in zip(names, vals):
                    w.param(nm, v)
            d, o = c.scale, c.odiag
            S = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
            Rs = sensor_rotation(0 if c.rot < 0 else c.rot, (0.0, 0.0, 0.0))
            s = (np.linalg.solve(S, (body @ Rs).T).T + np.asarray(c.ofs_true_gauss)
                 - power[:, None] * np.asarray(c.comp_true))
            raws.append(s + rng.normal(0.0, noise_mgauss / 1000.0, s.shape))
        w.topic("sensor_mag", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
                               ("float", "x"), ("float", "y"), ("float", "z"), ("float", "temperature"),
                               ("uint32_t", "error_count"), ("bool", "is_external")])
        w.topic("vehicle_attitude", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[4]", "q")])
        w.topic("battery_status", [("uint64_t", "timestamp"), ("bool", "connected"), ("float", "voltage_v"),
                                   ("float", "current_a")])
        w.topic("vehicle_thrust_setpoint", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                                            ("float[3]", "xyz")])
        w.topic("hover_thrust_estimate", [("uint64_t", "timestamp"), ("float", "hover_thrust")])
        w.topic("vehicle_gps_position", [("uint64_t", "timestamp"), ("double", "latitude_deg"),
                                         ("double", "longitude_deg"), ("double", "altitude_msl_m"),
                                         ("float", "vel_m_s"), ("uint8_t", "fix_type")])
        w.topic("yaw_estimator_status", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                                         ("float", "yaw_composite"), ("float", "yaw_variance"),
                                         ("bool", "yaw_composite_valid")])
        w.topic("vehicle_status", [("uint64_t", "timestamp"), ("uint8_t", "arming_state"), ("uint8_t", "nav_state")])
        w.topic("vehicle_local_position", [("uint64_t", "timestamp"), ("float", "z"), ("float", "vx"),
                                           ("float", "vy")])
        for k, s in enumerate(raws):
            w.data("sensor_mag", k, {"timestamp": t_us, "timestamp_sample": t_us, "device_id": MAG_IDS[k],
                                     "x": s[:, 0], "y": s[:, 1], "z": s[:, 2], "temperature": 30.0,
                                     "is_external": compasses[k].rot >= 0})
        q = rot.as_quat()  # x, y, z, w
        w.data("vehicle_attitude", 0, {"timestamp": t_us, "timestamp_sample": t_us,
                                       "q": np.column_stack([q[:, 3], q[:, 0], q[:, 1], q[:, 2]])})
        if battery:
            w.data("battery_status", 0, {"timestamp": t_us, "connected": True, "voltage_v": 16.0, "current_a": cur})
        w.data("vehicle_thrust_setpoint", 0, {"timestamp": t_us, "timestamp_sample": t_us,
                                              "xyz": np.column_stack([0 * thr, 0 * thr, -thr])})
        w.data("hover_thrust_estimate", 0, {"timestamp": t_us[::20], "hover_thrust": 0.35})
        w.data("vehicle_gps_position", 0, {"timestamp": t_us[::4], "latitude_deg": lat_lon[0],
                                           "longitude_deg": lat_lon[1], "altitude_msl_m": 500.0, "vel_m_s": 4.0,
                                           "fix_type": 3})
        if gsf:
            w.data("yaw_estimator_status", 0, {
                "timestamp": t_us, "timestamp_sample": t_us,
                "yaw_composite": np.radians((yaw + 180.0) % 360.0 - 180.0 + rng.normal(0.0, 1.0, len(t))),
                "yaw_variance": np.radians(1.0) ** 2, "yaw_composite_valid": True})
        w.data("vehicle_status", 0, {"timestamp": np.array([t_us[0] - 1_000_000, t_us[-1] + 1]),
                                     "arming_state": np.array([2, 1]), "nav_state": 2})
        w.data("vehicle_local_position", 0, {"timestamp": t_us[::4], "z": -10.0 - 5 * np.sin(t[::4] / 9.0),
                                             "vx": 4.0, "vy": 0.0})
    return path
