"""ROS 1 bags (v2.0).

May import: the readers' shared bottom only.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.readers.ros1.reader`: ROS 1 bags (v2.0; uncompressed, bz2 or lz4 chunks) into...
"""

__all__ = ["reader"]
