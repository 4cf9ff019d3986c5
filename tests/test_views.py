"""Issue 28: the views a person reads at a glance (figures.py, recording.py, plot2d.py).

- a decimated signal is its min/max envelope: the noise keeps its height;
- lines of unlike magnitude go to plots of their own, in the recording and the report alike;
- a view's y range leaves the legend's corner free of data;
- 3D views carry axes of a round length;
- the report's time plots share one origin.
"""

from __future__ import annotations

import numpy as np

from imupipe.pipeline.report.figures import (
    Figures,
    Plot,
    Series,
    decimate,
    magnitude_groups,
    split_by_magnitude,
)
from imupipe.pipeline.report.recording import Recorder, legend_room, scale3d

T0 = 1_700_000_000 * 10**9


def _noise(n: int = 720_000, std: float = 0.0017, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(n, dtype=np.int64) * 10_000_000
    return t, rng.normal(0.01, std, (n, 1))


def test_decimated_noise_keeps_its_height():
    """720 000 samples of 0.0017 rad/s noise drawn with 20 000 points: the envelope spans what
    the samples span (block means spanned about a sixth of it)."""
    t, v = _noise()
    dt, dv = decimate(t, v, 20_000)
    assert len(dt) == 20_000 and np.all(np.diff(dt) >= 0)
    assert dv.min() == v.min() and dv.max() == v.max()
    blocks = v[: len(v) // 72 * 72].reshape(-1, 72).mean(axis=1)
    assert np.ptp(blocks) < np.ptp(dv) / 4  # what a mean showed


def _plot(series: list[tuple[str, list[str], np.ndarray]]) -> Plot:
    plot = Plot("s", "accel", "time", "accel", "m/s^2")
    t = T0 + np.arange(100, dtype=np.int64)
    for entity, names, values in series:
        plot.series.append(Series(entity, names, [(0, 0, 0)] * len(names), t, values))
    return plot


def test_lines_of_unlike_magnitude_go_apart_and_close_ones_stay():
    rng = np.random.default_rng(2)
    noise = rng.normal(0, 0.01, (100, 3))
    accel = noise + [0.15, -0.1, 9.8]
    plot = _plot([("/s/raw/accel", ["accel x raw", "accel y raw", "accel z raw"], accel)])
    groups = magnitude_groups(plot)
    assert [sorted(g["/s/raw/accel"]) for g in groups] == [
        ["accel x raw", "accel y raw"],
        ["accel z raw"],
    ]
    parts = split_by_magnitude(plot)
    assert [p.heading for p in parts] == ["accel: x, y (m/s^2)", "accel: z (m/s^2)"]
    assert parts[1].series[0].values.shape == (100, 1)
    # gyro before and after a 0.01 rad/s bias, with 0.005 rad/s of noise: one plot
    gyro = rng.normal(0, 0.005, (100, 2)) + [0.01, 0.0]
    assert len(split_by_magnitude(_plot([("/s/g", ["g raw", "g corrected"], gyro)]))) == 1


def test_the_legend_corner_is_left_free_of_data():
    values = np.linspace(0.0, 1.0, 100)[:, None]
    plot = _plot([("/s/a", ["a"], values)])
    lo, hi = legend_room(plot, rows=6)
    top = (hi - 1.0) / (hi - lo)  # the share of the view above the data
    assert lo < 0.0 and top >= (20.0 * 6 + 16.0) / 340.0


def test_3d_axes_have_a_round_length_outside_the_cloud():
    figures = Figures()
    plot = figures.plot("m", "cloud", "3d", title=None, unit="uT")
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(500, 3))
    pts = 48.0 * pts / np.linalg.norm(pts, axis=1, keepdims=True) + [12.0, -8.0, 21.0]
    plot.series.append(Series("/m/p", ["p"], [(0, 0, 0)], np.arange(500), pts, "cloud"))
    corner, length = scale3d(plot)
    assert length in (10.0, 20.0, 25.0, 30.0)  # a round share of the 48 uT radius
    assert np.allclose(corner, pts.min(axis=0))


def test_report_time_plots_share_one_origin(tmp_path):
    from imupipe.pipeline.report.svg_plot import time_axis

    rec = Recorder(None)
    t = T0 + np.arange(1000, dtype=np.int64) * 10**9
    rec.series("/s/raw/gyro", t, np.zeros((1000, 3)), unit="rad/s")
    rec.series("/s/means/gyro", t[250::500], np.zeros((2, 3)), unit="rad/s", plot="means")
    rec.series("/t/other", t + 3 * 86_400 * 10**9, np.zeros(1000), ("o",), unit="rad/s")
    origin = rec.figures.share_time_origin()
    titles = {p.key: time_axis(p)[2] for p in rec.figures.plots.values()}
    assert origin == T0 and titles["gyro"] == titles["means"]
    assert titles["other"] != titles["gyro"]  # another session, days later: its own origin
