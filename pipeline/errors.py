"""The pipeline's errors, and every error type users see, in one place for the command line.

Each package defines its own errors on the common base :class:`ImupipeError`
(``imupipe.readers.errors``): readers raise :class:`ReadError`, stages :class:`FitError` and
:class:`CalibrationError`, the pipeline :class:`ConfigError`. The command line prints the one-line
message of any of them on stderr and exits with status 2.
"""

from __future__ import annotations

from imupipe.readers.errors import ImupipeError, ReadError
from imupipe.stages.errors import CalibrationError, FitError

__all__ = ["CalibrationError", "ConfigError", "FitError", "ImupipeError", "ReadError", "one_line"]


def one_line(text: str) -> str:
    """``text`` on one line: a line break or carriage return (in a file name, say) written as
    ``\\n`` / ``\\r``, so that an error stays one line on stderr."""
    return text.replace("\r", "\\r").replace("\n", "\\n")


class ConfigError(ImupipeError):
    """The config file is malformed, or a key or value in it is wrong."""
