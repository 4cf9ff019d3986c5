"""SIGTERM as an exception, so that a terminated command cleans up like an interrupted one.

Python turns SIGINT into :class:`KeyboardInterrupt`; SIGTERM (what ``kill``, systemd, Docker and
batch schedulers send) ends the process at once by default, leaving temporary files behind.
:func:`terminate_on_sigterm` makes it raise :class:`Terminated` instead: ``finally`` blocks run,
staged outputs are discarded, worker pools are stopped.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from types import FrameType


class Terminated(BaseException):
    """The process received SIGTERM (a BaseException, like KeyboardInterrupt: nothing catches it
    by accident)."""

    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


def terminate_on_sigterm() -> None:
    """From now on SIGTERM raises :class:`Terminated` in the main thread."""
    signal.signal(signal.SIGTERM, _raise_terminated)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM held back (delivered when the block ends): for a third-party object
    whose construction must not be cut in two (an interrupted Rerun ``RecordingStream.__init__``
    prints a traceback when the half-made object is collected)."""
    held = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
