"""The truth of the SITL logs in ``sitl_logs/`` (``*.truth.json``, format "sitl_dance truth v1").

ArduPilot's SITL simulates (``model_equations`` of the truth file)::

    mag raw  = SIM_MAG1_SCALING * rot(SIM_MAG1_ORIENT)^T (M_sim^-1 B_body - SIM_MAG1_OFS)
    acc raw  = f_body / SIM_ACC1_SCAL + SIM_ACC1_BIAS      (element-wise)

with M_sim the symmetric matrix of SIM_MAG1_DIA/ODI (DIA all zero = identity). The
functions below give those raw readings for any true body vectors, so written parameters
can be checked with :func:`mavcal.ardupilot.evaluate.attitude_errors`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.rotations import rotation_matrix


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
