"""The one error type users see.

Every problem with the user's input (files, config, data that cannot support a fit) is raised as an
:class:`ImupipeError` whose message is one line saying what is wrong and where (file, key, topic,
row). The command line prints that line on stderr and exits non-zero; nothing else is printed
unless ``--debug`` is given.
"""

from __future__ import annotations


class ImupipeError(Exception):
    """A user-facing error: the message is the whole story, on one line."""

    exit_code = 2

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class ConfigError(ImupipeError):
    """The config file is malformed, or a key or value in it is wrong."""


class ReadError(ImupipeError):
    """A log cannot be read: missing, truncated, corrupt, wrong type, unknown topic."""


class FitError(ImupipeError):
    """The data cannot support the requested fit (too short, too few poses, planar, ...)."""
