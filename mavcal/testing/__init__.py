"""Test fixtures shipped with mavcal, for tests, benchmarks and plug-in authors (like ``numpy.testing``).

* :mod:`mavcal.testing.vehicle` -- :class:`~mavcal.testing.vehicle.TestVehicle`, a loopback
  ArduPilot emulator that speaks MAVLink 2 on 127.0.0.1 (parameter protocol, commands, IMU
  streams from simulated sensors with known errors, fault injection);
  :mod:`mavcal.testing.vehicle_params` (its parameter table and ArduPilot's PARAM_SET
  semantics) and :mod:`mavcal.testing.vehicle_sensors` (true sensor errors, motion, readings).
* :mod:`mavcal.testing.simlog` -- simulated hand-held calibration sessions written as
  .tlog / DataFlash .bin logs, with their truth.
* :mod:`mavcal.testing.logwriters` -- .tlog and DataFlash writers.
* :mod:`mavcal.testing.sitl_truth` -- the truth files of the SITL logs in ``sitl_logs/``, and
  the errors a live SITL is started with (:class:`~mavcal.testing.sitl_truth.InjectedErrors`)
  with a scorer of a written calibration.
* :mod:`mavcal.testing.sitl` -- :class:`~mavcal.testing.sitl.SitlVehicle`, the real ArduPilot
  SITL (``../shared/sitl``) in a private network namespace: known injected errors, poses,
  the truth, processes in its namespace; :mod:`mavcal.testing.sitl_hand` -- a scripted hand
  that holds the poses a guided capture advises; :mod:`mavcal.testing.sitl_sessions` -- whole
  ``mavcal apply`` sessions against it through lossy relays, checked over its own channel.
* :mod:`mavcal.testing.relay` -- :class:`~mavcal.testing.relay.LossRelay`, a lossy UDP relay
  (drops, duplicates, blackouts) between a vehicle and a tool.
* :mod:`mavcal.testing.numbers` -- comparing computed numbers at a stated tolerance: golden
  text, JSON and arrays (never bit for bit: the last bits differ between BLAS kernels and CPUs).
* :mod:`mavcal.testing.installed` -- CI's check of an installed wheel (``.ci/wheel``): mavcal
  imported from site-packages, and ``mavcal capture --ui`` against the loopback vehicle serving
  the installed package's page, script and style.
* :mod:`mavcal.testing.damaged` -- damaged inputs: the ULog pyulog 1.3 loops on, and the check that
  an error line names no Python exception; :mod:`mavcal.testing.capture_truth` -- a capture's result
  against the test vehicle's truth; :mod:`mavcal.testing.ci` -- under ``CI=true`` a skipped real-log
  or browser test fails.

Two conventions for a sensor's truth exist, and the class names say which:
:class:`~mavcal.testing.vehicle_sensors.AccelCalTruth` states the truth as the ideal
ArduPilot calibration (``raw = u / scale + offsets``), :class:`~mavcal.testing.simlog.AccelErrorTruth`
as the sensor's own errors (``raw = K u + bias``).

Only this package (besides :mod:`mavcal.sources` and :mod:`mavcal.link`) imports pymavlink,
and it may spell ArduPilot parameter names; no product module imports it. Nothing is
imported here: import the submodule you need.
"""
