"""The conversion manifest: ``DIR/manifest.jsonl``, one JSON object per log and run.

Each line records what ``imupipe convert`` did with one log::

    {"input": "...", "output": "...", "parquet": null, "status": "converted",
     "counts": {"/imu/data": 12000, ...}, "calibration_sha256": "...", "seconds": 1.23,
     "cpu_seconds": 1.1, "messages": 12000, "mode": "streamed", "attempts": 1, "host": "...",
     "peak_rss_mb": 143.2, "provenance": "match", "warnings": [], "error": null,
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

import json
import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

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
    "peak_rss_mb",
    "provenance",
    "warnings",
    "error",
    "finished_at",
)
"""The keys of every line, in this order (absent values are null)."""


class Manifest:
    """Appends one line per finished log to ``DIR/manifest.jsonl`` (driver process only)."""

    def __init__(self, out_dir: str | os.PathLike[str]) -> None:
        self.path = Path(out_dir) / MANIFEST_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)

    def append(self, record: Mapping[str, Any]) -> None:
        line = {key: record.get(key) for key in FIELDS}
        line["finished_at"] = line["finished_at"] or time.strftime(
            "%Y-%m-%dT%H:%M:%SZ", time.gmtime()
        )
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(line, sort_keys=False) + "\n")


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
