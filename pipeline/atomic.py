"""Outputs that appear whole or not at all.

Every output file is written under a temporary name in its final folder and renamed into place
only when the whole command has succeeded; on any error the temporary files are removed, so a
failed run never leaves a half-written file behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class StagedOutputs:
    """Hands out temporary paths for final paths; commits (renames) or discards them together."""

    def __init__(self) -> None:
        self._pending: list[tuple[Path, Path]] = []
        self._created_dirs: list[Path] = []

    def path(self, final: str | os.PathLike[str]) -> Path:
        """A temporary path next to ``final``; it becomes ``final`` on commit."""
        final = Path(final)
        missing = [p for p in [final.parent, *final.parent.parents] if not p.exists()]
        final.parent.mkdir(parents=True, exist_ok=True)
        self._created_dirs.extend(missing)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent)
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())
        self._pending.append((Path(tmp), final))
        return Path(tmp)

    def write_text(self, final: str | os.PathLike[str], text: str) -> None:
        self.path(final).write_text(text, encoding="utf-8")

    def commit(self) -> None:
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
def staged_outputs() -> Iterator[StagedOutputs]:
    """Context manager: commit all staged files on success, remove them all on any exception."""
    staged = StagedOutputs()
    try:
        yield staged
    except BaseException:
        staged.discard()
        raise
    staged.commit()


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike[str]) -> Iterator[Path]:
    """One file: yields a temporary path that is renamed to ``final`` if the block succeeds."""
    with staged_outputs() as staged:
        yield staged.path(final)
