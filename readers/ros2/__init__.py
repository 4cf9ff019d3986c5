"""ROS 2 bags: a bag folder (sqlite3 or mcap storage) or a bare ``.db3``.

May import: the readers' shared bottom and ``mcap`` (mcap storage).

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.readers.ros2.reader`: ROS 2 bags into the common table: a bag folder (sqlite3 or...
"""

__all__ = ["reader"]
