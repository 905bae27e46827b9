"""PX4's calibration model: a sibling of ArduPilot's, implementing
:class:`mavcal.autopilot.model.AutopilotModel` for PX4 autopilots.

:mod:`~mavcal.px4.params` spells PX4's parameter names (the only place that does),
:mod:`~mavcal.px4.firmware` applies and undoes PX4's correction, :mod:`~mavcal.px4.recover` gives
the raw readings the fit takes, :mod:`~mavcal.px4.mapping` maps a joint calibration onto
``CAL_ACC<n>_*`` / ``CAL_MAG<n>_*`` and :mod:`~mavcal.px4.model` is what the pipeline calls
(:func:`mavcal.autopilot.model_for` picks it for a ULog or a vehicle whose HEARTBEAT says PX4).
"""
