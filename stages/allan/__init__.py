"""The ``allan`` stage: Allan-variance estimators, the five-term noise model and its
non-negative fit.

May import: the stages' shared bottom (base, steps, errors, stillness, sample_clock, cores,
gyro_bias) and the readers' table; no other stage family.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.stages.allan.estimators`: Exact frequency-stability estimators (NIST SP1065,...
- :mod:`imupipe.stages.allan.fit`: The five-term Allan-variance noise model (IEEE Std 952-1997...
- :mod:`imupipe.stages.allan.nnls`: Non-negative least squares for a handful of unknowns, by...
- :mod:`imupipe.stages.allan.stage`: ``allan`` stage: IMU noise identification from a long...
"""

__all__ = ["estimators", "fit", "nnls", "stage"]
