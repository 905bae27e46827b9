"""A guided capture's result against the test vehicle's truth (issue 35: the offline capture tests
check "reached the target" with the truth at hand, not only with the code's own bound).

:func:`heading_error_vs_truth` -- the largest heading error over level (or tilted) attitudes of the
calibration a run would write, computed with the :class:`~mavcal.testing.vehicle.TestVehicle`'s true
sensor errors (board-mounted compasses, board orientation 0).
"""
from __future__ import annotations

import numpy as np

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.evaluate import attitude_errors, attitude_grid

__all__ = ["heading_error_vs_truth"]


def heading_error_vs_truth(vehicle, written: dict[str, float], *, instance: int = 0,
                           max_tilt_deg: float = 0.0) -> float:
    """Largest heading error (deg) of compass ``instance`` and accelerometer 0 as the vehicle's parameters
    with ``written`` on top calibrate them, against the vehicle's true errors, over attitudes tilted up to
    ``max_tilt_deg`` (every heading)."""
    ct, at = vehicle.truth.compasses[instance], vehicle.truth.accels[0]
    if ct.orientation or getattr(vehicle.truth, "board_orientation", 0):
        raise ValueError("heading_error_vs_truth: board-mounted compasses and board orientation 0 only")
    M = fw.soft_iron_matrix(ct.dia, ct.odi)
    params = {**vehicle.params, **written}
    e = attitude_errors(lambda f: f / np.array(at.scale) + np.array(at.offsets),
                        lambda b: b @ np.linalg.inv(M).T / ct.scale - np.array(ct.offsets),
                        fw.accel_cal_from_params(params, 0), fw.compass_cal_from_params(params, instance),
                        np.array(vehicle.truth.earth_field_ned_mgauss), attitude_grid(max_tilt_deg=max_tilt_deg))
    return e.max_heading_deg
