"""The choices and defaults of ``imupipe convert`` shared by its command line and its Python API
(a module that imports nothing, so that ``imupipe convert --help`` starts at once)."""

from __future__ import annotations

DEFAULT_BATCH_ROWS = 25_000
"""Rows per streamed batch: a worker's memory is bounded by this, not by the log. The written
file does not depend on it (the writer encodes fixed slices counted from the first row). Issue
39, 500,000 messages, one worker: peak RSS 275-282 MB at 100,000 rows, 215 MB at 25,000 (a
thermal chain: 335-351 MB against 261-262 MB), the same CPU time within the noise."""

ON_MISMATCH = ("warn", "refuse")
"""What a log that is not from the calibration's sensor does (``--on-mismatch``)."""

ENGINES = ("local", "ray")
"""Where the logs are converted (``--engine``): a process pool on this machine, or Ray."""
