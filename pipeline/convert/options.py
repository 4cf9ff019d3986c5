"""The choices and defaults of ``imupipe convert`` shared by its command line and its Python API
(a module that imports nothing the interpreter has not loaded already, so that ``imupipe convert
--help`` starts at once); and which arguments name objects on a store (``s3://...``), so that a
local conversion never imports :mod:`imupipe.pipeline.convert.remote` (issue 39)."""

from __future__ import annotations

import os
import re
from pathlib import Path

DEFAULT_BATCH_ROWS = 25_000
"""Rows per streamed batch: a worker's memory is bounded by this, not by the log. The written
file does not depend on it (the writer encodes fixed slices counted from the first row). Issue
39, 500,000 messages, one worker: peak RSS 275-282 MB at 100,000 rows, 215 MB at 25,000 (a
thermal chain: 335-351 MB against 261-262 MB), the same CPU time within the noise."""

ON_MISMATCH = ("warn", "refuse")
"""What a log that is not from the calibration's sensor does (``--on-mismatch``)."""

ENGINES = ("local", "ray")
"""Where the logs are converted (``--engine``): a process pool on this machine, or Ray."""

URL = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://(?P<rest>.*)$")
"""A URL: ``scheme://...`` (``file://`` is a local path)."""


def is_url(value: str | os.PathLike[str]) -> bool:
    """Whether ``value`` names an object (``s3://...``), not a local path."""
    m = URL.match(os.fspath(value))
    return m is not None and m["scheme"].lower() != "file"


def local_path(value: str | os.PathLike[str]) -> Path:
    """A local path from an argument (``file:///x`` -> ``/x``)."""
    text = os.fspath(value)
    return Path(text[len("file://") :] if text.lower().startswith("file://") else text)
