"""The autopilot-neutral layer: what any autopilot is to mavcal, and the one registry.

This package says what any autopilot is to mavcal (:class:`~mavcal.autopilot.model.AutopilotModel`)
and holds the vocabulary every autopilot speaks: the raw readings (:mod:`~mavcal.autopilot.raw`),
the calibration form (:mod:`~mavcal.autopilot.calform`), the mapping's results
(:mod:`~mavcal.autopilot.mapping`), the gates (:mod:`~mavcal.autopilot.gates`,
:mod:`~mavcal.autopilot.verdicts`), the attitude judging (:mod:`~mavcal.autopilot.evaluate`),
rotations, MAVLink commands, parameter files, and the write rules each autopilot answers for
(:mod:`~mavcal.autopilot.protocol`, :mod:`~mavcal.autopilot.limits`), the in-flight compass model
(:mod:`~mavcal.autopilot.flight`).
ArduPilot's and PX4's models are sibling implementations; the registry
(:mod:`~mavcal.autopilot.registry`) is the one place that names them and decides which autopilot a
recording or a vehicle is.
"""
from __future__ import annotations

from mavcal.autopilot.mavlink import MAV_AUTOPILOT_PX4
from mavcal.autopilot.model import AutopilotModel
from mavcal.autopilot.registry import NAMES, is_px4, is_px4_params, model_for, model_named, models

__all__ = ["AutopilotModel", "model_for", "model_named", "models", "is_px4", "is_px4_params", "MAV_AUTOPILOT_PX4",
           "NAMES"]
