"""mavcal: joint accelerometer + magnetometer calibration for ArduPilot over MAVLink.

Public API
----------
calibrate(accel_sets, mag_sets, *, method="ncar", tol=1e-4, seed=None) -> Calibration
estimate_orientations(calibration, accel_sets, mag_sets) -> (M, 3, 3) array
reconstruction_error(...) -> (delta_a, delta_m)
calibrate_multi(accel_sensors, mag_sensors, ...) -> MultiCalibration

The engine (numpy/scipy) is imported on first use, so that ``mavcal --help`` and the
commands that do not fit anything start at once.
"""
from __future__ import annotations

import importlib
from typing import Any

from mavcal.errors import CalibrationWarning, EstimationError, MavcalError

__version__ = "0.1.0"

_LAZY = {
    "Calibration": "mavcal.core.types",
    "SensorModel": "mavcal.core.types",
    "calibrate": "mavcal.core.calibrate",
    "estimate_orientations": "mavcal.core.calibrate",
    "reconstruction_error": "mavcal.core.calibrate",
    "MultiCalibration": "mavcal.core.multi",
    "calibrate_multi": "mavcal.core.multi",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later look-ups skip this hook
        return value
    raise AttributeError(f"module 'mavcal' has no attribute {name!r}")


def __dir__() -> list:
    return sorted(set(globals()) | set(_LAZY))


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
