"""Simulators: the paper's Monte Carlo experiment (:mod:`mavcal.sim.paper`) and realistic
ArduPilot logs (:mod:`mavcal.sim.logs`)."""
from mavcal.sim.paper import SimData, Sensors, Truth, draw_intervals, draw_sensors, simulate

__all__ = ["SimData", "Sensors", "Truth", "draw_intervals", "draw_sensors", "simulate"]
