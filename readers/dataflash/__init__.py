"""ArduPilot DataFlash logs (``.bin``).

May import: the readers' shared bottom only.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.readers.dataflash.reader`: ArduPilot DataFlash logs (``.bin``) into the common...
"""

__all__ = ["reader"]
