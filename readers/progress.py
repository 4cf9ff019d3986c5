"""How far a long read (or write) has got, told to whoever listens: the command line's progress
bar (:mod:`imupipe.pipeline.progress`). Nobody listens by default; a report then costs one
context-variable lookup.

A reader calls :func:`report` with how much of its file it has passed (``done`` of ``total``,
in its own units: bytes of the file for the chunked formats, MCAP and ROS 1 bags), as often as
once per chunk; a writer the same, in messages. The listener, set with :func:`listening` around
the read, turns it into the bar's position.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator

Listener = Callable[[int, int], None]
"""``listener(done, total)``: ``done`` of ``total`` units passed."""

_listener: contextvars.ContextVar[Listener | None] = contextvars.ContextVar(
    "imupipe_progress", default=None
)


@contextlib.contextmanager
def listening(listener: Listener | None) -> Iterator[None]:
    """Within the block, :func:`report` calls ``listener`` (None: nobody listens)."""
    token = _listener.set(listener)
    try:
        yield
    finally:
        _listener.reset(token)


def report(done: int, total: int) -> None:
    """``done`` of ``total`` units of the current read or write have been passed."""
    listener = _listener.get()
    if listener is not None:
        listener(done, total)
