"""Multi-position calibration (``accel_calibration``, ``gyro_calibration``): the pose
models, Ferraris' method.

May import: the stages' shared bottom (base, steps, errors, static_detector); no other family.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.stages.multiposition.accel_calibration`: ``accel_calibration`` stage:...
- :mod:`imupipe.stages.multiposition.accel_models`: Accelerometer models fitted on static poses:...
- :mod:`imupipe.stages.multiposition.ferraris`: Ferraris calibration (Ferraris et al.
- :mod:`imupipe.stages.multiposition.gyro_calibration`: ``gyro_calibration`` stage: gyroscope...
- :mod:`imupipe.stages.multiposition.gyro_models`: Gyroscope scale and misalignment models:...
"""

__all__ = ["accel_calibration", "accel_models", "ferraris", "gyro_calibration", "gyro_models"]
