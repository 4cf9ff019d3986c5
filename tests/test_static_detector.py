"""Static-interval detection: windowed variance against numpy, runs, and the simulated truth."""

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
    make_detector,
    moving_variance_norm,
    runs,
    segment_mask,
)


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


def test_detects_every_simulated_pose():
    table, truth = simulate("poses", seed=4)
    acc = sensor(table, "accel")
    iv = make_detector(acc.t_ns, acc.values).detect(3.0)
    true = np.array(truth["static_intervals_s"])
    assert len(iv) == len(true) == 18
    t = acc.t_s
    # every detected interval lies inside its true rest, and covers most of it
    assert np.all(t[iv.start] >= true[:, 0] - 1e-9) and np.all(t[iv.stop - 1] <= true[:, 1] + 1e-9)
    assert np.all((t[iv.stop - 1] - t[iv.start]) > 0.7 * (true[:, 1] - true[:, 0]))


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
