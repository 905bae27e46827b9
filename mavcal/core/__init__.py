"""Core estimation math (no I/O, no MAVLink, no ArduPilot parameter names).

Implements the joint accelerometer + magnetometer maximum-likelihood calibration of
Miranda & Ferreira, "Efficient Simultaneous Calibration of a Magnetometer and an
Accelerometer" (the paper in ``shared/paper``), plus a joint Gauss-Newton refinement,
parameter uncertainty, model selection and multi-sensor fits.
"""
