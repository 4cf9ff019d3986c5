"""The conversion manifest: ``DIR/manifest.jsonl``, one JSON object per log and run.

Each line records what ``imupipe convert`` did with one log::

    {"input": "...", "output": "...", "parquet": null, "status": "converted",
     "counts": {"/imu/data": 12000, ...}, "calibration_sha256": "...", "seconds": 1.23,
     "cpu_seconds": 1.1, "messages": 12000, "mode": "streamed", "attempts": 1, "host": "...",
     "engine_log": null, "peak_rss_mb": 143.2, "provenance": "match", "warnings": [], "error": null,
     "finished_at": "2026-11-21T15:40:02Z"}

``status`` is ``converted``, ``skipped`` (an output for the same calibration already existed) or
``failed`` (``error`` says why). ``provenance`` says whether the log comes from the sensor the
calibration was fitted on: ``match``, ``mismatch: <what differs>``, ``unknown`` (the calibration
does not record it) or ``-`` (skipped, failed). Lines are only appended, each written whole and flushed to the
operating system as soon as its log is finished, so the manifest survives an interrupted or
killed run and shows every attempt in order; the latest line for an input is its current state.
(Lines are not fsynced: after a power cut the last ones may be missing, and the next run finds
their logs already done and records them as skipped.)
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from imupipe.pipeline.atomic import OutputGuard

MANIFEST_NAME = "manifest.jsonl"

FIELDS = (
    "input",
    "output",
    "parquet",
    "status",
    "counts",
    "calibration_sha256",
    "seconds",
    "cpu_seconds",
    "messages",
    "mode",
    "attempts",
    "host",
    "engine_log",
    "peak_rss_mb",
    "provenance",
    "warnings",
    "not_carried",
    "error",
    "finished_at",
)
"""The keys of every line, in this order (absent values are null)."""


def line_bytes(record: Mapping[str, Any]) -> bytes:
    """``record``'s manifest line: the keys of :data:`FIELDS` in order, ``finished_at`` now
    unless given, one JSON object and a newline."""
    line = {key: record.get(key) for key in FIELDS}
    line["finished_at"] = line["finished_at"] or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return (json.dumps(line, sort_keys=False) + "\n").encode("utf-8")


class Manifest:
    """Appends one line per finished log to ``DIR/manifest.jsonl`` (driver process only).

    With ``guard``, the path is checked by the path rule
    (:class:`~imupipe.pipeline.atomic.OutputGuard`: inside ``DIR``, not an input, not a
    symbolic link) when the manifest is made, before anything is written. The file is created by
    the first line, never followed through a symbolic link (``O_NOFOLLOW``); a line that cannot
    be written whole (a full disk) is taken back, and a manifest this run created is removed
    again, so a failed append leaves the file as it was."""

    def __init__(self, out_dir: str | os.PathLike[str], guard: OutputGuard | None = None) -> None:
        path = Path(out_dir).absolute() / MANIFEST_NAME
        self.path = path if guard is None else guard.check(path, in_place=True)

    def append(self, record: Mapping[str, Any]) -> None:
        """Append ``record``'s line; OSError (naming the manifest) when it cannot be written."""
        data = line_bytes(record)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
        existed = os.path.lexists(self.path)
        try:
            fd = os.open(self.path, flags, 0o666)
        except OSError as exc:
            exc.filename = exc.filename or str(self.path)
            raise
        try:
            size = os.fstat(fd).st_size
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view) :]
            except OSError as exc:
                with contextlib.suppress(OSError):
                    if existed:
                        os.ftruncate(fd, size)
                    else:
                        os.unlink(self.path)
                exc.filename = str(self.path)
                raise
        finally:
            os.close(fd)


def read_manifest(out_dir: str | os.PathLike[str]) -> Iterator[dict[str, Any]]:
    """Every line of ``DIR/manifest.jsonl`` in order (nothing when there is none yet).

    A last line cut short by a crash is ignored.
    """
    path = Path(out_dir) / MANIFEST_NAME
    if not path.exists():
        return
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            try:
                yield json.loads(line)
            except json.JSONDecodeError:
                continue


def latest(out_dir: str | os.PathLike[str]) -> dict[str, dict[str, Any]]:
    """Input -> its latest manifest line."""
    return {rec["input"]: rec for rec in read_manifest(out_dir) if "input" in rec}
