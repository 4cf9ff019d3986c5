"""Outputs that appear whole or not at all, only inside the output folder, never over an input.

Every output file is written under a temporary name in its final folder and renamed into place
only when the whole command has succeeded; on any error (an exception, SIGINT, SIGTERM) the
temporary files are removed, so a failed run never leaves a half-written file behind.

**Temporary names** say who wrote them: ``.<name>.<pid>@<host>.<random>.tmp`` (``host`` is a
short hash of the machine's name). A process killed outright (SIGKILL, out of memory) cannot
remove its own; :func:`remove_stale_temps` removes those whose process is gone, and every
command calls it on its output folder before it writes.

**The path rule** (every file a command writes: outputs, temporaries, the manifest, the
Parquet files). With an :class:`OutputGuard`, every path is resolved (symbolic links followed)
before anything is written, and refused with one line when it

- lies outside the output folder ``DIR`` (or is ``DIR`` itself),
- is an input, or lies inside an input that is a folder (a ROS 2 bag),
- lies inside a folder searched for inputs (``convert fleet/``), unless ``DIR`` itself lies
  strictly inside that folder (the search skips ``DIR``); ``DIR`` equal to a searched folder is
  refused at once: its outputs would sit among its inputs.

A file that is appended to in place (the manifest) must also not be a symbolic link.
The start-up sweep of stale temporaries (:func:`remove_stale_temps`) looks only in the folders
the command writes into, never below them, and only at names this module makes.
"""

from __future__ import annotations

import contextlib
import os
import re
import socket
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from imupipe.pipeline.digests import sha1_hex
from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.signals import signals_deferred

HOST_KEY = sha1_hex(socket.gethostname().encode())[:8]
"""A short, file-name-safe key of this machine (temporary names carry it)."""

TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)@(?P<host>[0-9a-f]{8})\.[a-z0-9_]{8}\.tmp$")
"""A temporary output's name: ``.<final name>.<pid>@<host key>.<random>.tmp`` (``random``: the
8 characters ``tempfile.mkstemp`` draws from ``a-z0-9_``); nothing else is ever swept."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_stale_temps(
    folder: str | os.PathLike[str],
    *,
    name: str | None = None,
    other_hosts: bool = False,
) -> list[Path]:
    """Remove the temporary outputs in ``folder`` (not below it) left by processes that no
    longer run; only names of :data:`TEMP_NAME` are ever touched.

    A temporary file of this machine is stale when its process is gone; one of another machine
    (a Ray node) only with ``other_hosts`` (the caller then owns every output of that name).
    ``name``: only the temporary files of that final name. Returns the files removed."""
    root = Path(folder)
    if not root.is_dir():
        return []
    removed = []
    for f in sorted(os.listdir(root)):
        m = TEMP_NAME.match(f)
        if m is None or (name is not None and m["name"] != name):
            continue
        if m["host"] == HOST_KEY:
            pid = int(m["pid"])
            if pid == os.getpid() or _alive(pid):
                continue
        elif not other_hosts:
            continue
        path = root / f
        if not path.is_file() or path.is_symlink():
            continue
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
            removed.append(path)
    return removed


class OutputGuard:
    """Refuses paths that break the path rule (see the module docstring).

    ``inputs``: the input files and folders (a ROS 2 bag); ``searched``: the folders searched
    for inputs. ``where`` names the setting that chose the folder in messages (``[output] dir``,
    ``--out``).
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        inputs: Iterable[str | os.PathLike[str]],
        where: str,
        *,
        searched: Iterable[str | os.PathLike[str]] = (),
    ) -> None:
        self.root = Path(root).absolute()
        self.where = where
        self._root = self.root.resolve()
        self._inputs = {Path(p).absolute().resolve() for p in inputs}
        # the folders among them (a ROS 2 bag), found once: a check per output asking each
        # input made a fleet's plan O(logs^2) in stat calls (1,000 logs: 10^6, issue 39)
        self._input_dirs = {inp for inp in self._inputs if inp.is_dir()}
        if self.root.exists() and not self.root.is_dir():
            raise ConfigError(f"{where} {self.root}: exists and is not a folder")
        for inp in self._inputs:
            if self._root == inp or (inp in self._input_dirs and self._root.is_relative_to(inp)):
                raise ConfigError(
                    f"{where} {self.root}: is inside the input {inp}; choose another folder"
                )
        self._searched = []
        for folder in {Path(p).absolute().resolve() for p in searched}:
            if folder == self._root:
                raise ConfigError(
                    f"{where} {self.root}: is the folder searched for logs, so its outputs would "
                    "sit among the inputs; choose another folder (one inside it is not searched)"
                )
            if not self._root.is_relative_to(folder):  # DIR strictly inside: DIR is skipped
                self._searched.append(folder)

    def probe(self) -> None:
        """ConfigError unless a file can be created in the output folder (or, when it does not
        exist yet, in its nearest existing parent): read-only, permission, full inode table."""
        folder = next(p for p in [self.root, *self.root.parents] if p.exists())
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".probe.{os.getpid()}@{HOST_KEY}.", dir=folder)
        except OSError as exc:
            raise ConfigError(
                f"{self.where} {self.root}: cannot write in {folder}: {exc.strerror or exc}"
            ) from None
        os.close(fd)
        os.unlink(tmp)

    def check(self, final: str | os.PathLike[str], *, in_place: bool = False) -> Path:
        """``final`` made absolute; ConfigError when it must not be written. ``in_place``: the
        file is opened and written where it is (appended to), so it must not be a symbolic
        link either."""
        return self.check_resolved(final, in_place=in_place)[0]

    def check_resolved(
        self, final: str | os.PathLike[str], *, in_place: bool = False
    ) -> tuple[Path, Path]:
        """:meth:`check`, and ``final``'s real path (resolved: a fleet's plan needs it for
        every output, and resolving again cost 47 us an output)."""
        final = Path(final)
        final = final if final.is_absolute() else self.root / final
        real = final.resolve()
        inside = real if real in self._inputs else None
        if inside is None:
            inside = next((inp for inp in self._input_dirs if real.is_relative_to(inp)), None)
        if inside is not None:
            raise ConfigError(
                f"{final}: would overwrite the input {inside}; choose another {self.where}"
            )
        for folder in self._searched:
            if real.is_relative_to(folder):
                raise ConfigError(
                    f"{final}: would be written into {folder}, a folder searched for logs; "
                    f"choose another {self.where}"
                )
        if not real.is_relative_to(self._root) or real == self._root:
            raise ConfigError(
                f"{final}: would be written outside the output folder {self.root} ({self.where})"
            )
        if in_place and final.is_symlink():
            raise ConfigError(
                f"{final}: is a symbolic link; imupipe writes it in place and follows no link "
                "there: remove it"
            )
        return final, real


class StagedOutputs:
    """Hands out temporary paths for final paths; commits (renames) or discards them together."""

    def __init__(self, guard: OutputGuard | None = None) -> None:
        self.guard = guard
        self._pending: list[tuple[Path, Path]] = []
        self._created_dirs: list[Path] = []

    def path(self, final: str | os.PathLike[str]) -> Path:
        """A temporary path next to ``final``; it becomes ``final`` on commit."""
        final = Path(final) if self.guard is None else self.guard.check(final)
        if not final.parent.is_dir():  # the folders this makes, deepest first (one stat else)
            missing = [p for p in [final.parent, *final.parent.parents] if not p.exists()]
            final.parent.mkdir(parents=True, exist_ok=True)
            self._created_dirs.extend(missing)
        with signals_deferred():  # a SIGTERM or SIGINT right after the file is made: listed first
            fd, tmp = tempfile.mkstemp(
                prefix=f".{final.name}.{os.getpid()}@{HOST_KEY}.", suffix=".tmp", dir=final.parent
            )
            self._pending.append((Path(tmp), final))
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())
        return Path(tmp)

    def folder(self) -> str | None:
        """The output folder (for messages): the guard's, else the first output's."""
        if self.guard is not None:
            return str(self.guard.root)
        return str(self._pending[0][1].parent) if self._pending else None

    def write_text(self, final: str | os.PathLike[str], text: str) -> None:
        self.path(final).write_text(text, encoding="utf-8")

    def commit(self) -> None:
        """Rename every staged file to its final name, with SIGINT and SIGTERM held back until
        the last rename: an interrupted run leaves all of its outputs or none."""
        with signals_deferred():
            for tmp, final in self._pending:
                os.replace(tmp, final)
            self._pending.clear()

    def discard(self) -> None:
        for tmp, _ in self._pending:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        self._pending.clear()
        for folder in self._created_dirs:  # deepest first: folders this run made, if left empty
            with contextlib.suppress(OSError):
                folder.rmdir()
        self._created_dirs.clear()


@contextlib.contextmanager
def staged_outputs(guard: OutputGuard | None = None) -> Iterator[StagedOutputs]:
    """Context manager: commit all staged files on success, remove them all on any exception
    (SIGINT and SIGTERM included: the command line turns both into exceptions)."""
    staged = StagedOutputs(guard)
    try:
        yield staged
    except BaseException as exc:
        if isinstance(exc, OSError) and exc.filename is None:  # e.g. a write on a full disk
            exc.filename = staged.folder()
        staged.discard()
        raise
    try:
        staged.commit()
    except BaseException:
        staged.discard()
        raise


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike[str]) -> Iterator[Path]:
    """One file: yields a temporary path that is renamed to ``final`` if the block succeeds."""
    with staged_outputs() as staged:
        yield staged.path(final)
