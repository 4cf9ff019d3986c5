"""The `average` stage (seed 000's ImuDataSum) against a direct per-block reference."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.stages.blocks import block_centres, block_means


def imudatasum(values: np.ndarray, window: int) -> np.ndarray:
    """Seed 000's MATLAB ImuDataSum, transcribed: mean of each block, the last partial one too."""
    out = []
    for start in range(0, len(values), window):
        out.append(values[start : start + window].mean(axis=0))
    return np.array(out)


@pytest.mark.parametrize("n,window", [(1000, 500), (1234, 500), (7, 3), (5, 10)])
def test_block_means_match_imudatasum(n, window):
    rng = np.random.default_rng(n)
    values = rng.standard_normal((n, 3))
    t = np.arange(n, dtype=np.int64) * 10_000_000
    blocks = block_means(t, values, window=window)
    np.testing.assert_allclose(blocks.means, imudatasum(values, window), rtol=1e-13, atol=1e-15)
    assert blocks.counts.sum() == n
    # block times are the centres of the blocks
    np.testing.assert_allclose(
        blocks.t_ns, imudatasum(t.astype(float)[:, None], window)[:, 0], atol=1
    )


def test_window_seconds_uses_timestamps():
    t = np.array([0, 1, 2, 10, 11, 25], dtype=np.int64) * 100_000_000  # 0.1 s units
    v = np.arange(6, dtype=float)
    blocks = block_means(t, v, window_s=1.0)
    np.testing.assert_array_equal(blocks.counts, [3, 2, 1])
    np.testing.assert_allclose(blocks.means, [1.0, 3.5, 5.0])


@pytest.mark.parametrize(
    ("step_max", "window"),
    [(5_000_000, 1440), (10, 3), (1 << 44, 5000)],  # the last: span x block >= 2^62, float path
)
def test_block_centres_are_exact_means_of_the_times(step_max, window):
    """The int64 path (wrapping sums of the absolute times) and the float fallback both give the
    mean time of each block, rounded to the ns, as exact integer arithmetic does."""
    rng = np.random.default_rng(7)
    n = 20_000
    t = 1_700_000_000_000_000_000 + np.cumsum(rng.integers(1, step_max, n)).astype(np.int64)
    starts = np.arange(0, n, window)
    counts = np.diff(np.r_[starts, n])
    got = block_centres(t, starts, counts)
    want = [
        int(t[0]) + round(sum(int(x) - int(t[0]) for x in t[s : s + k]) / k)
        for s, k in zip(starts, counts, strict=True)
    ]
    tol = 0 if step_max < 1 << 40 else 1e-12 * (int(t[-1]) - int(t[0]))  # float64 rounding
    assert np.abs(got - np.array(want)).max() <= tol
