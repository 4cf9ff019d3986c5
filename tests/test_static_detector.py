"""Static-interval detection: windowed variance against numpy, runs, the noise floor measured on
the log (no still start needed), poses, the regularised clock, and the simulated truth."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from imupipe.pipeline.errors import FitError
from imupipe.pipeline.simulate import simulate
from imupipe.readers.table import sensor
from imupipe.stages.static_detector import (
    Intervals,
    Poses,
    make_detector,
    moving_variance_norm,
    runs,
    sample_clock,
    segment_mask,
)

USUAL = {"init_static_s": 0.0, "accel_N": 0.4e-3 * 9.80665 / 10}
"""A session recorded the usual way: 18 poses of 6 s, moves of 3 s, no long rest at the start,
100 Hz, accelerometer noise 0.4 mg per sample."""


def test_moving_variance_matches_numpy_sliding_windows():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(200, 3)) * [1.0, 2.0, 0.5] + 1000.0
    got = moving_variance_norm(x, 11)
    ref = np.linalg.norm(sliding_window_view(x, 11, axis=0).var(axis=2, ddof=1), axis=1)
    np.testing.assert_allclose(got[5:-5], ref, rtol=1e-8)
    assert np.isinf(got[:5]).all() and np.isinf(got[-5:]).all()


def test_runs_means_and_labels():
    mask = np.array([0, 1, 1, 1, 0, 1, 0, 1, 1, 0], dtype=bool)
    iv = runs(mask, min_length=2)
    assert iv.start.tolist() == [1, 7] and iv.stop.tolist() == [4, 9]
    values = np.arange(30, dtype=float).reshape(10, 3)
    np.testing.assert_allclose(iv.means(values), [values[1:4].mean(0), values[7:9].mean(0)])
    assert iv.labels(10).tolist() == [-1, 0, 0, 0, -1, -1, -1, 1, 1, -1]
    assert iv.mask(10).tolist() == [bool(v >= 0) for v in iv.labels(10)]


@pytest.mark.parametrize("params", [{}, USUAL], ids=["still start", "usual way"])
def test_detects_every_simulated_pose(params):
    table, truth = simulate("poses", params, seed=4)
    acc = sensor(table, "accel")
    detector = make_detector(acc.t_ns, acc.values)
    assert "noise floor" in detector.source
    iv = detector.detect(3.0)
    true = np.array(truth["static_intervals_s"])
    assert len(iv) == len(true) == 18
    t = acc.t_s
    # every detected interval lies inside its true rest, and covers most of it
    assert np.all(t[iv.start] >= true[:, 0] - 1e-9) and np.all(t[iv.stop - 1] <= true[:, 1] + 1e-9)
    assert np.all((t[iv.stop - 1] - t[iv.start]) > 0.7 * (true[:, 1] - true[:, 0]))


def test_initial_rest_rule_needs_a_still_start():
    """imu_tk's rule (threshold x the variance of the first init_static_s) on a log that moves
    from the start sees everything as static; the noise floor does not."""
    table, _ = simulate("poses", USUAL, seed=4)
    acc = sensor(table, "accel")
    imu_tk = make_detector(acc.t_ns, acc.values, init_static_s=30.0)
    floor = make_detector(acc.t_ns, acc.values)
    assert imu_tk.reference > 1e5 * floor.reference
    assert [len(imu_tk.detect(k)) for k in (2, 5, 10)] == [1, 1, 1]
    assert [len(floor.detect(k)) for k in (2, 5, 10)] == [18, 18, 18]


def test_poses_merge_intervals_and_keep_their_samples():
    iv = Intervals(np.array([0, 10, 30]), np.array([5, 20, 40]))
    poses = Poses(iv, np.array([0, 0, 1]))
    values = np.arange(40, dtype=float)[:, None] * [1.0, 2.0, 3.0]
    assert len(poses) == 2
    assert poses.start.tolist() == [0, 30] and poses.stop.tolist() == [20, 40]
    assert poses.lengths.tolist() == [15, 10]
    expected = np.vstack([values[np.r_[0:5, 10:20]].mean(0), values[30:40].mean(0)])
    np.testing.assert_allclose(poses.means(values), expected)


def test_sample_clock_regularises_repeated_stamps():
    """Stamps printed to 10 ms at 200 Hz (as the T265 session's) repeat; integration needs the
    even clock they came from."""
    true_s = np.arange(2000) / 199.8
    t_ns = (np.floor(true_s * 100) * 1e7).astype(np.int64)
    assert np.count_nonzero(np.diff(t_ns) == 0) > 900
    t_s, note = sample_clock(t_ns)
    assert "quantised to 10 ms" in note
    np.testing.assert_allclose(np.diff(t_s), 1 / 199.8, rtol=1e-3)
    np.testing.assert_allclose(t_s, true_s - true_s[0], atol=0.006)
    even = np.arange(100, dtype=np.int64) * 10_000_000
    assert sample_clock(even)[1] is None
    gap = np.r_[np.arange(50), np.arange(50) + 80].astype(np.int64) * 10_000_000
    gap[10] = gap[9]  # a repeat, but a 0.3 s gap: no even clock explains it
    assert sample_clock(gap)[1] is None


def test_detector_rejects_a_short_initial_period():
    t_ns = np.arange(50, dtype=np.int64) * 10_000_000
    with pytest.raises(FitError, match="initial static period"):
        make_detector(t_ns, np.zeros((50, 3)) + 1.0, init_static_s=0.05)


def test_segment_mask_by_label_and_time():
    t = np.arange(6, dtype=float)
    labels = pa.chunked_array([pa.array(["a", "a", "b", "b", None, "a"])])
    assert segment_mask(t, labels, "w", "b").tolist() == [0, 0, 1, 1, 0, 0]
    assert segment_mask(t, None, "w", [1.0, 2.5]).tolist() == [0, 1, 1, 0, 0, 0]
    with pytest.raises(FitError, match="no samples"):
        segment_mask(t, labels, "w", "zz")
    with pytest.raises(FitError, match="no label column"):
        segment_mask(t, None, "w", "a")
    assert isinstance(Intervals(np.array([0]), np.array([1])).lengths, np.ndarray)
