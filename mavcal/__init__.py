"""mavcal: joint accelerometer + magnetometer calibration for ArduPilot over MAVLink.

Public API
----------
calibrate(accel_sets, mag_sets, *, method="ncar", tol=1e-4, seed=None) -> Calibration
estimate_orientations(calibration, accel_sets, mag_sets) -> (M, 3, 3) array
reconstruction_error(...) -> (delta_a, delta_m)
calibrate_multi(accel_sensors, mag_sensors, ...) -> MultiCalibration
"""
from __future__ import annotations

__version__ = "0.1.0"

from mavcal.core.types import Calibration, SensorModel  # noqa: E402
from mavcal.errors import (  # noqa: E402
    CalibrationWarning,
    EstimationError,
    MavcalError,
)

from mavcal.core.calibrate import (  # noqa: E402
    calibrate,
    estimate_orientations,
    reconstruction_error,
)
from mavcal.core.multi import MultiCalibration, calibrate_multi  # noqa: E402

__all__ = [
    "Calibration",
    "SensorModel",
    "MultiCalibration",
    "calibrate",
    "calibrate_multi",
    "estimate_orientations",
    "reconstruction_error",
    "MavcalError",
    "EstimationError",
    "CalibrationWarning",
]
