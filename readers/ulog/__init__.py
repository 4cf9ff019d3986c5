"""PX4 ULog files (``.ulg``).

May import: the readers' shared bottom only.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.readers.ulog.reader`: PX4 ULog files (``.ulg``) into the common table, with pyulog.
- :mod:`imupipe.readers.ulog.rotation`: PX4's board and sensor rotations (``SENS_BOARD_ROT``,
  ``CAL_MAGn_ROT``) and the rotation PX4 applies to a magnetometer after its calibration.
"""

__all__ = ["reader", "rotation"]
