"""The paper's Monte Carlo experiment (:mod:`mavcal.sim.paper`), behind ``mavcal simulate``.

Simulated ArduPilot sessions and logs are test fixtures: :mod:`mavcal.testing.simlog`.
"""
from mavcal.sim.paper import Sensors, SimData, Truth, draw_intervals, draw_sensors, simulate

__all__ = ["SimData", "Sensors", "Truth", "draw_intervals", "draw_sensors", "simulate"]
