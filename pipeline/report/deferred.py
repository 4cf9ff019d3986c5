"""The run's recorder while Rerun is still importing: the stages run, their drawing is kept.

``imupipe run`` imports Rerun (0.5-0.75 s of CPU) on a second thread while it reads its inputs
(:mod:`imupipe.pipeline.warm_imports`). A short log is read before that import ends; the run
used to wait for it there, before its first stage. :class:`DeferredRecorder` stands for the
:class:`~imupipe.pipeline.report.recording.Recorder` in that time: each drawing call
(:data:`QUEUED`: they return nothing) is kept, in order, with a copy of every numpy array it
was given, and made on the real recorder once it exists, in the same order, so the recording
and the report hold what they held (the same calls, the same values, in the same order). The
real recorder is made when the Rerun import is done (the next call after it), or when the run
needs it: anything that is not a drawing call (``figures``, ``input_unit``, ``close``).

This module imports no Rerun (nor anything heavy): the run imports it before the read.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

QUEUED = frozenset(
    {
        "start_at",
        "sensors",
        "series",
        "curve",
        "bars",
        "points3d",
        "ellipsoid",
        "log",
        "add_view",
        "document",
        "ensure_stage",
    }
)
"""The recorder's methods that only draw (they return None): kept while Rerun imports."""


def recording_files(cfg: Any) -> list[Path]:
    """The files the recorder of a run writes: ``recording.rrd`` with ``[output] rerun``."""
    return [cfg.output.dir / "recording.rrd"] if cfg.output.rerun else []


def _kept(value: Any) -> Any:
    """``value`` as it is now: a numpy array copied (the caller may reuse its buffer), lists and
    tuples of them too; anything else (tables, strings, numbers, Rerun archetypes) as given."""
    if isinstance(value, np.ndarray):
        return value.copy()
    if isinstance(value, list):
        return [_kept(v) for v in value]
    if isinstance(value, tuple):
        return tuple(_kept(v) for v in value)
    return value


class DeferredRecorder:
    """Stands for the run's recorder until ``make()`` can build it without waiting
    (``ready()``), or until it is needed (see the module's text)."""

    enabled = True

    def __init__(self, make: Callable[[], Any], ready: Callable[[], bool]) -> None:
        self._make = make
        self._ready = ready
        self._calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = []
        self._real: Any = None

    @property
    def made(self) -> bool:
        """Whether the real recorder exists (every call kept so far made on it)."""
        return self._real is not None

    def real(self) -> Any:
        """The real recorder: built (waiting for Rerun's import if need be) and given the calls
        kept so far, in order, the first time."""
        if self._real is None:
            self._real = self._make()
            calls, self._calls = self._calls, []
            for name, args, kwargs in calls:
                getattr(self._real, name)(*args, **kwargs)
        return self._real

    def _keep(self, name: str) -> Callable[..., None]:
        def call(*args: Any, **kwargs: Any) -> None:
            if self._real is None and not self._ready():
                self._calls.append((name, _kept(args), {k: _kept(v) for k, v in kwargs.items()}))
            else:
                getattr(self.real(), name)(*args, **kwargs)

        return call

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        if name in QUEUED and self._real is None:
            return self._keep(name)
        return getattr(self.real(), name)
