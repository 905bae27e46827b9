"""The judge stage: each sensor judged on its own fit, the accelerometers (:mod:`~mavcal.judging.accel`)
and the compasses (:mod:`~mavcal.judging.compass`) side by side, from the numbers of
:mod:`mavcal.judging.quality` (95 % bounds, held-out errors) through the autopilot model's gates.
"""
