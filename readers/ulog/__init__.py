"""PX4 ULog files (``.ulg``).

May import: the readers' shared bottom only.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.readers.ulog.reader`: PX4 ULog files (``.ulg``) into the common table, with pyulog.
"""

__all__ = ["reader"]
