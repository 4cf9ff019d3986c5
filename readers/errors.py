"""The base of every error users see, and the readers' own error.

Every problem with the user's input (files, config, data that cannot support a fit) is raised as
an :class:`ImupipeError` whose message is one line saying what is wrong and where (file, key,
topic, row). The command line prints that line on stderr and exits with status 2; nothing else
is printed unless ``--debug`` is given.

This module is the bottom layer: it imports nothing of imupipe. Each package adds its own
subclasses (``imupipe.stages.errors``, ``imupipe.pipeline.errors``).
"""

from __future__ import annotations


class ImupipeError(Exception):
    """A user-facing error: the message is the whole story, on one line."""

    exit_code = 2

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class ReadError(ImupipeError):
    """A log cannot be read: missing, truncated, corrupt, wrong type, unknown topic."""


READ_TO_CUT = "read up to the cut"
"""The words of every warning about a cut-off log read up to the cut (``--read-truncated``), by
which a command picks them out of a log's warnings to say them on the terminal."""
