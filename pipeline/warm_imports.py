"""Import on a second thread, while the inputs are read, the modules a run imports next.

A run reads its inputs first (pyarrow's parse and the log readers spend most of that time in
compiled code, without the GIL), then imports what it had no need of until then: Rerun for the
recording (about 0.25 s), scipy for the stages' solvers (about 0.22 s, loaded by the ``allan``
stage on first use), the report's and the exporters' modules. :class:`WarmImports` imports
those on a daemon thread during the read, so that the main thread finds them loaded; on a
machine with a core to spare the run ends that much sooner, on a busy one it costs nothing but
the same import done elsewhere.

Safety: two threads importing at once can deadlock only on a cycle of modules each holds and
the other needs. The modules warmed here (the stages', the recorder's, the report's and the
exporters', with Rerun, scipy and PyYAML: the standard library, numpy's submodules) are none of
what the read imports (the readers' modules, imported before the thread starts, pyarrow and the
format libraries), and the main thread :meth:`~WarmImports.wait` s for the thread before it
imports any of them itself. A module that fails to import on the thread is left to fail again,
with its own message, where the main thread imports it.
"""

from __future__ import annotations

import gc
import importlib
import threading
from collections.abc import Sequence
from types import TracebackType


class WarmImports:
    """``with WarmImports(modules):`` imports ``modules`` in order on a daemon thread and waits
    for it when the block ends (also when it ends on an exception).

    ``freeze`` (for a process that runs once, the command line): the cyclic garbage collector is
    paused while the modules load and every object it tracks is then frozen (:func:`gc.freeze`):
    the hundreds of thousands of objects Rerun and scipy define live as long as the process, and
    the collector no longer scans them. Measured on a 2 h Allan run: the collections during the
    run 0.08-0.12 s (238 of them) -> 0.01 s (77), a full collection at the end 0.02-0.03 s -> 0."""

    def __init__(self, modules: Sequence[str], *, freeze: bool = False) -> None:
        self.modules = list(modules)
        self.freeze = freeze
        self.failed: list[str] = []
        """The modules whose import raised on the thread (the main thread's import re-raises)."""
        self._thread: threading.Thread | None = None
        self._started = False

    def _run(self) -> None:
        paused = self.freeze and gc.isenabled()
        if paused:
            gc.disable()
        try:
            for name in self.modules:
                try:
                    importlib.import_module(name)
                except Exception:  # noqa: BLE001  (the main thread's own import reports it)
                    self.failed.append(name)
        finally:
            if self.freeze:
                gc.freeze()
            if paused:
                gc.enable()

    def start(self) -> None:
        """Start the thread (once: later calls, and calls after :meth:`wait`, do nothing)."""
        if self.modules and not self._started:
            self._thread = threading.Thread(
                target=self._run, name="imupipe-warm-imports", daemon=True
            )
            self._thread.start()
        self._started = True

    def __enter__(self) -> WarmImports:
        self.start()
        return self

    def wait(self) -> None:
        """Return once every module has been imported (or has failed to)."""
        self._started = True
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.wait()
