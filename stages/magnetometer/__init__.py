"""Magnetometer calibration (``mag_calibration``): ellipsoid fits, hard and soft iron.

May import: the stages' shared bottom; no other family.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.stages.magnetometer.calibration`: ``mag_calibration`` stage: hard and soft iron...
- :mod:`imupipe.stages.magnetometer.ellipsoid`: Ellipsoid fitting for magnetometer calibration...
- :mod:`imupipe.stages.magnetometer.inflight`: ``mag_inflight`` stage: the compass calibrated...
- :mod:`imupipe.stages.magnetometer.wmm`: The earth's magnetic field from the World Magnetic...
"""

__all__ = ["calibration", "ellipsoid", "inflight", "wmm"]
