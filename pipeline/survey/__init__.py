"""The fleet survey (``imupipe survey``): still moments of a fleet's logs, per IMU, each flight
log's compass fit, and their fleet view.

May import: the pipeline's top, ``report`` (figures, plots), ``convert`` (finding logs),
``exports`` (the autopilots' compass parameters, composed with a fit), the stages and the
readers; nothing imports it but the command line.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.pipeline.survey.compass`: The compass in ``imupipe survey``: every flight log's...
- :mod:`imupipe.pipeline.survey.report`: The fleet view of ``imupipe survey``:...
- :mod:`imupipe.pipeline.survey.scan`: ``imupipe survey LOG|FOLDER ...
- :mod:`imupipe.pipeline.survey.stream`: One IMU topic of one log surveyed in batches: a worker's...
"""

__all__ = ["compass", "report", "scan", "stream"]
