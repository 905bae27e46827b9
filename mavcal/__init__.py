"""mavcal: joint accelerometer + magnetometer calibration for ArduPilot and PX4 over MAVLink.

Public API
----------
calibrate(accel_sets, mag_sets, *, method="ncar", tol=1e-4, seed=None) -> Calibration
estimate_orientations(calibration, accel_sets, mag_sets) -> (M, 3, 3) array
reconstruction_error(...) -> (delta_a, delta_m)
calibrate_multi(accel_sensors, mag_sensors, ...) -> MultiCalibration

The engine (numpy/scipy) is imported on first use, so that ``mavcal --help`` and the
commands that do not fit anything start at once. ``__version__`` is the installed
distribution's version (its metadata, set in ``pyproject.toml``), read on first use too.
"""
from __future__ import annotations

import importlib
from typing import Any

from mavcal.errors import CalibrationWarning, EstimationError, MavcalError

_LAZY = {
    "Calibration": "mavcal.core.types",
    "SensorModel": "mavcal.core.types",
    "calibrate": "mavcal.core.calibrate",
    "estimate_orientations": "mavcal.core.calibrate",
    "reconstruction_error": "mavcal.core.calibrate",
    "MultiCalibration": "mavcal.core.multi",
    "calibrate_multi": "mavcal.core.multi",
}


def _installed_version() -> str:
    """The version of the installed ``mavcal`` distribution (its metadata: one number, set in
    ``pyproject.toml``); ``0+unknown`` when the package runs from a tree that was never installed."""
    from importlib.metadata import PackageNotFoundError, version  # ~10 ms: not for `mavcal --help`

    try:
        return version("mavcal")
    except PackageNotFoundError:
        return "0+unknown"


def __getattr__(name: str) -> Any:
    if name == "__version__":
        globals()[name] = value = _installed_version()
        return value
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later look-ups skip this hook
        return value
    raise AttributeError(f"module 'mavcal' has no attribute {name!r}")


def __dir__() -> list:
    return sorted(set(globals()) | set(_LAZY) | {"__version__"})


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
