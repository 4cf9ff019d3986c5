"""The choices and defaults of ``imupipe convert`` shared by its command line and its Python API
(a module that imports nothing, so that ``imupipe convert --help`` starts at once)."""

from __future__ import annotations

DEFAULT_BATCH_ROWS = 100_000
"""Rows per streamed batch: a worker's memory is bounded by this, not by the log."""

ON_MISMATCH = ("warn", "refuse")
"""What a log that is not from the calibration's sensor does (``--on-mismatch``)."""

ENGINES = ("local", "ray")
"""Where the logs are converted (``--engine``): a process pool on this machine, or Ray."""
