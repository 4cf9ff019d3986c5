"""Progress for long work: a rich bar on stderr when it is a terminal, silence otherwise
(rich is imported only when a bar is shown: a quiet run does not pay for it).

The convention of every command (``run``, ``convert``, ``survey``, ``simulate``): a bar on
stderr while stderr is a terminal, none with ``--quiet`` or when stderr is a file or a pipe;
the bar disappears when the work is done (what stays on the terminal is the command's output).

One bar goes through phases (:meth:`Bar.phase`), each counting its own units: bytes of a log
being read (the readers tell how far they are through :mod:`imupipe.readers.progress`, which
:meth:`Bar.listen` connects), messages written, steps; a phase without a known total shows the
time elapsed, so a long wait is never silent.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from imupipe.readers.progress import listening

if TYPE_CHECKING:
    from rich.progress import Progress

UNITS = ("", "bytes", "rows", "messages", "logs")
"""What a phase counts ("" : steps)."""


def size_of(path: Path) -> int:
    """Bytes of a file, or of the files in a folder (a ROS 2 bag); 0 when unreadable."""
    try:
        if path.is_dir():
            return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
        return path.stat().st_size
    except OSError:
        return 0


def count_text(done: float, total: float | None, unit: str) -> str:
    """``done/total unit`` as the bar shows it: bytes in MB (GB past 10 GB), counts whole."""
    if total is None:
        return ""
    if unit == "bytes":
        scale, name = (1e9, "GB") if total >= 10e9 else (1e6, "MB")
        digits = 0 if name == "MB" and total >= 10e6 else 1
        return f"{done / scale:.{digits}f}/{total / scale:.{digits}f} {name}"
    return f"{int(done)}/{int(total)}" + (f" {unit}" if unit else "")


class Bar:
    def __init__(self, progress: Progress | None, task: int | None) -> None:
        self._progress, self._task = progress, task
        self._unit = ""
        self._items: float | None = None  # items (logs) done, when a report moves within one
        self._hint: float | None = None  # the phase's total, shown once a report comes

    @property
    def shown(self) -> bool:
        return self._progress is not None and self._task is not None

    def _refresh(self, **fields: object) -> None:
        assert self._progress is not None and self._task is not None
        self._progress.update(self._task, **fields)  # type: ignore[arg-type]
        task = self._progress.tasks[self._task]
        self._progress.update(self._task, count=count_text(task.completed, task.total, self._unit))

    def advance(self, n: float = 1) -> None:
        if self.shown:
            if self._items is not None:  # whole items: what a report within one added goes
                self._items += n
                self._refresh(completed=self._items)
                return
            assert self._progress is not None and self._task is not None
            self._progress.advance(self._task, n)
            self._refresh()

    def describe(self, text: str) -> None:
        if self.shown:
            self._refresh(description=text)

    def phase(
        self, text: str, total: float | None, unit: str = "", *, when_reported: bool = False
    ) -> None:
        """Start counting afresh: ``total`` units of ``unit`` (None: unknown, the time shows).
        ``when_reported``: the count shows from the first report on (:meth:`fraction`); until
        then, as for a reader that does not report, the time elapsed (never a count stuck at
        0)."""
        if self.shown:
            self._unit, self._items = unit, None
            self._hint = total if when_reported else None
            self._refresh(description=text, total=None if when_reported else total, completed=0)

    def fraction(self, done: int, total: int) -> None:
        """``done`` of ``total`` of the phase (the listener of the readers' reports); when the
        bar counts items (:meth:`listen` ``within_items``), of the item under way."""
        if self.shown and total > 0:
            assert self._progress is not None and self._task is not None
            if self._items is not None:
                self._refresh(completed=self._items + min(done / total, 0.99))
                return
            whole = self._progress.tasks[self._task].total or self._hint
            if whole:
                self._refresh(total=whole, completed=min(done / total, 1.0) * whole)

    def listen(self, within_items: bool = False) -> contextlib.AbstractContextManager[None]:
        """Within the block, a reader's or writer's reports move this bar (:meth:`fraction`).
        ``within_items``: the bar counts items (logs, :meth:`advance` once each) and a report
        moves it within the one under way (logs read in this process: one log, ``--jobs 1``;
        worker processes report nothing here)."""
        self._items = 0.0 if within_items else None
        return listening(self.fraction if self.shown else None)


@contextlib.contextmanager
def progress_bar(
    description: str, total: float | None, *, quiet: bool = False, unit: str = ""
) -> Iterator[Bar]:
    """A progress bar counting ``total`` units; invisible when quiet or stderr is not a TTY."""
    if quiet or not sys.stderr.isatty():
        yield Bar(None, None)
        return
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.fields[count]}"),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=True,
    )
    with progress:
        bar = Bar(progress, progress.add_task(description, total=total, count=""))
        bar._unit = unit
        bar.describe(description)
        yield bar
