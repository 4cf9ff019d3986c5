"""Block averaging (``ImuDataSum`` of the MATLAB example in the Chinese article "【IMU】温度零偏标定"
on IMU temperature bias calibration).

The samples are cut into consecutive blocks of ``window`` samples (or of ``window_s`` seconds of
timestamps); each block is replaced by its mean. The trailing partial block is averaged too (as
``ImuDataSum`` does), so no sample is dropped. Block times are the mean of the block's sample
times, i.e. the block centre for evenly spaced samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Blocks:
    """Block means: ``t_ns`` (m,) block centres, ``means`` (m, k), ``counts`` (m,) samples per
    block, ``starts`` (m,) index of each block's first sample."""

    t_ns: np.ndarray
    means: np.ndarray
    counts: np.ndarray
    starts: np.ndarray


def block_starts(
    t_ns: np.ndarray,
    window: int | None = None,
    window_s: float | None = None,
    *,
    increasing: bool = False,
) -> np.ndarray:
    """Start index of each block: every ``window`` samples, or every ``window_s`` seconds
    (each block's first sample; blocks without samples skipped). ``increasing``: the caller
    has checked that ``t_ns`` does not decrease; the blocks are then found by bisection at each
    block edge instead of a division per sample (the same indices)."""
    n = len(t_ns)
    if (window is None) == (window_s is None):
        raise ValueError("give exactly one of window and window_s")
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if window is not None:
        if window < 1:
            raise ValueError("window must be >= 1 sample")
        return np.arange(0, n, int(window), dtype=np.int64)
    if not window_s or window_s <= 0:
        raise ValueError("window_s must be > 0")
    width = int(round(window_s * 1e9))
    if increasing:
        t0 = int(t_ns[0])
        edges = t0 + width * np.arange(1, (int(t_ns[-1]) - t0) // width + 1, dtype=np.int64)
        return np.unique(np.r_[0, np.searchsorted(t_ns, edges)]).astype(np.int64)
    index = (t_ns - t_ns[0]) // width
    return np.flatnonzero(np.r_[True, index[1:] != index[:-1]]).astype(np.int64)


def block_means(
    t_ns: np.ndarray,
    values: np.ndarray,
    window: int | None = None,
    window_s: float | None = None,
    starts: np.ndarray | None = None,
) -> Blocks:
    """Means of consecutive blocks of ``values`` (n,) or (n, k); see the module docstring.
    ``starts``: the blocks as :func:`block_starts` gave them (instead of a window)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    squeeze = values.ndim == 1
    values2 = values.reshape(len(t_ns), -1)
    if starts is None:
        starts = block_starts(t_ns, window, window_s)
    if len(starts) == 0:
        return Blocks(t_ns, values2[:0], np.zeros(0, np.int64), starts)
    counts = np.diff(np.r_[starts, len(t_ns)])
    means = np.add.reduceat(values2, starts, axis=0) / counts[:, None]
    return Blocks(
        block_centres(t_ns, starts, counts), means[:, 0] if squeeze else means, counts, starts
    )


def block_centres(t_ns: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The mean time of each block (int64 ns, rounded to the nearest ns), relative to the first
    sample. The sums of ``t - t[0]`` are taken in int64 without making ``t - t[0]``: numpy's
    integer sums wrap modulo 2^64, so ``sum(t) - count * t[0]`` is the exact relative sum whenever
    that fits in an int64 (checked: span x longest block < 2^62); else in float64. (The float
    copy of a 2.88 M-sample time column cost 0.02-0.05 s of first-touch page faults per call.)"""
    t0 = t_ns[0]
    span = int(t_ns.max()) - int(t_ns.min())
    if span * int(counts.max()) < 1 << 62:
        rel = np.add.reduceat(t_ns, starts) - counts * t0  # exact modulo 2^64: the true sum
        return t0 + np.round(rel / counts).astype(np.int64)
    rel_f = (t_ns - t0).astype(np.float64)
    return t0 + np.round(np.add.reduceat(rel_f, starts) / counts).astype(np.int64)
