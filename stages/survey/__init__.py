"""The math of ``imupipe survey``: each still period's statistics and the fleet rules (the
IMUs' and the compasses').

May import: the stages' shared bottom (static_detector, steps); the thermal models.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.stages.survey.compass`: The compass's fleet view in ``imupipe survey``: each...
- :mod:`imupipe.stages.survey.fleet`: The fleet view of ``imupipe survey``: each device's...
- :mod:`imupipe.stages.survey.stats`: The still moments of a log and what each one says about an...
- :mod:`imupipe.stages.survey.streaming`: Still periods and their statistics from a log read in...
"""

__all__ = ["compass", "fleet", "stats", "streaming"]
