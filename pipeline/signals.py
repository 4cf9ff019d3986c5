"""SIGTERM as an exception, so that a terminated command cleans up like an interrupted one.

Python turns SIGINT into :class:`KeyboardInterrupt`; SIGTERM (what ``kill``, systemd, Docker and
batch schedulers send) ends the process at once by default, leaving temporary files behind.
:func:`terminate_on_sigterm` makes it raise :class:`Terminated` instead: ``finally`` blocks run,
staged outputs are discarded, worker pools are stopped.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator
from types import FrameType


class Terminated(BaseException):
    """The process received SIGTERM (a BaseException, like KeyboardInterrupt: nothing catches it
    by accident)."""

    exit_code = 128 + signal.SIGTERM


_RECEIVED: list[int] = []
"""SIGTERMs received since :func:`terminate_on_sigterm`: Python drops an exception raised in a
finaliser or a weak-reference callback (it prints "Exception ignored in ..."), so a
:class:`Terminated` raised there never reaches the command; :func:`was_terminated` still knows."""


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    _RECEIVED.append(signum)
    raise Terminated()


def was_terminated() -> bool:
    """Whether SIGTERM arrived since :func:`terminate_on_sigterm`, even when its
    :class:`Terminated` was swallowed where Python ignores exceptions."""
    return bool(_RECEIVED)


def _exit_terminated(signum: int, frame: FrameType | None) -> None:
    try:
        os.write(2, b"imupipe: terminated\n")
    finally:
        os._exit(Terminated.exit_code)


def exit_on_sigterm() -> None:
    """From now on SIGTERM ends the process at once with status 143 and one line, running no
    ``finally`` block nor ``atexit`` callback: for the moments when the command has nothing to
    clean up (before it starts, after its outputs are in place), where an exception would be
    printed as "Exception ignored in atexit callback" or the default action would end the
    process by the signal. Main thread only (a no-op elsewhere)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _exit_terminated)


def terminate_on_sigterm() -> None:
    """From now on SIGTERM raises :class:`Terminated` in the main thread."""
    _RECEIVED.clear()
    signal.signal(signal.SIGTERM, _raise_terminated)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM held back until the block ends, then delivered to their own handlers:
    for work that must not be cut in two (committing a set of outputs, constructing a Rerun
    ``RecordingStream``, whose half-made object prints a traceback when collected).

    Python runs signal handlers in the main thread only, so the main thread's handlers are swapped
    for ones that note the signal; a block in another thread is never interrupted anyway. (A
    thread signal mask would not do: the kernel hands a process signal to any thread that does not
    block it, pyarrow's and Rerun's included, and Python then raises it in the main thread.)
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = (signal.SIGINT, signal.SIGTERM)
    noted: list[int] = []
    old = {sig: signal.signal(sig, lambda signum, frame: noted.append(signum)) for sig in held}
    try:
        yield
    finally:
        for sig, handler in old.items():  # None: a handler set outside Python
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        for sig in dict.fromkeys(noted):  # once each, in order of arrival
            signal.raise_signal(sig)
