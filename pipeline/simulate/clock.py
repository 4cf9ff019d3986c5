"""The sample clock every scenario shares: ``n`` samples at ``fs`` Hz from ``t0_s`` (epoch s)."""

from __future__ import annotations

import numpy as np


def sample_times(t0_s: float, n: int, fs: float) -> np.ndarray:
    """int64 ns timestamps of ``n`` evenly spaced samples at ``fs`` Hz starting at ``t0_s``."""
    return int(round(t0_s * 1e9)) + np.round(np.arange(n) * (1e9 / fs)).astype(np.int64)
