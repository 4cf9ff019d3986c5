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


# -- what a person sees in the recording's tabs (round 2) ------------------------------------------
H = 3_600 * 10**9  # an hour in ns


def _override_alpha(view) -> dict[str, int]:
    """entity -> the opacity (0..255) a view's colour override gives it."""
    out = {}
    for path, vis in (view.visualizer_overrides or {}).items():
        for batch in vis.overrides:
            if str(batch.component_descriptor()).endswith("colors"):
                out[str(path)] = int(batch.as_arrow_array().to_pylist()[0]) & 0xFF
    return out


def test_lines_under_others_are_see_through_in_the_views_they_share(tmp_path):
    """Rerun draws a view's lines in entity-path order (raw after means): the raw envelope is
    made see-through where it lies over block means, and keeps its colour alone in a view."""
    rec = Recorder(tmp_path / "r.rrd", max_points=1000)
    t = T0 + np.arange(2000, dtype=np.int64) * 10**9
    rng = np.random.default_rng(4)
    rec.series("/s/raw/gyro", t, rng.normal(0, 1e-3, (2000, 3)), ("gx raw", "gy raw", "gz raw"),
               unit="rad/s", plot="gyro", under=True)  # fmt: skip
    rec.series("/s/means/gyro", t[::100], np.zeros((20, 3)), ("gx m", "gy m", "gz m"),
               unit="rad/s", plot="gyro")  # fmt: skip
    rec.series("/u/raw/gyro", t, rng.normal(0, 1e-3, (2000, 3)), ("ux", "uy", "uz"),
               unit="rad/s", under=True)  # fmt: skip
    plots = {(p.stage, p.key): p for p in rec.figures.plots.values()}
    (shared,) = rec._time_views(plots[("s", "gyro")])
    alpha = _override_alpha(shared)
    raw = ["/s/raw/gyro/gx_raw", "/s/raw/gyro/gy_raw", "/s/raw/gyro/gz_raw"]
    assert all(0 < alpha[p] < 255 for p in raw)
    # the means, all at 0, lie over each other: lighter than opaque, never as light as the raw
    means = ["/s/means/gyro/gx_m", "/s/means/gyro/gy_m", "/s/means/gyro/gz_m"]
    assert sorted(alpha) == sorted(raw + means)
    assert all(alpha[r] < alpha[m] < 255 for r in raw for m in means)
    widths = {
        str(path): batch.as_arrow_array().to_pylist()[0]
        for path, vis in shared.visualizer_overrides.items()
        for batch in vis.overrides
        if str(batch.component_descriptor()).endswith("widths")
    }
    assert sorted(widths) == raw and min(widths.values()) >= 2.0  # a halo round the means
    (alone,) = rec._time_views(plots[("u", "gyro")])
    assert _override_alpha(alone) == {}
    rec.close()


def test_lines_over_each_other_are_see_through_lines_apart_are_not():
    """x, y and z corrected, all about 0, drawn in one view: the one Rerun draws last hid the
    others; made see-through (the report's opacity) they all show. Lines apart keep theirs."""
    rec = Recorder(None)
    t = T0 + np.arange(500, dtype=np.int64) * 10**8
    rng = np.random.default_rng(5)
    noise = rng.normal(0, 1e-3, (500, 3))
    rec.series("/c/corrected/gyro", t, noise, ("x corrected", "y corrected", "z corrected"),
               unit="rad/s")  # fmt: skip
    rec.series("/d/means/gyro", t, noise * 0.1 + [0.01, -0.02, 0.005], ("x", "y", "z"),
               unit="rad/s")  # fmt: skip
    plots = {p.stage: p for p in rec.figures.plots.values()}
    (over,) = rec._time_views(plots["c"])
    assert sorted(_override_alpha(over).values()) == [153, 153, 153]  # 0.6 of 255
    assert all(_override_alpha(v) == {} for v in rec._time_views(plots["d"]))


def test_a_long_session_gets_wide_views_that_label_its_hours():
    """Rerun labels a time axis's hour marks only 60-80 px apart (then 12 h marks): a 13.7 h
    session beside the results document in a grid of 7 had one label. Its signals now stack at
    full width, four to an inner tab, with room for every hour; a 2 h session keeps the grid."""
    from imupipe.pipeline.report.recording import HOUR_PX, plan_tab

    long = plan_tab(True, 6, 7, 13.7)
    assert long.long and long.columns == 1
    assert long.width_px / 13.7 >= HOUR_PX  # px per hour: every hour labelled
    assert long.plot_px > 150  # four views to a tab keep a readable height
    assert not plan_tab(True, 6, 7, 30.0).long  # 12 h marks, labelled in the grid as well
    short = plan_tab(True, 0, 4, 2.0)
    assert not short.long and short.columns == 2
    before = 1600 * 3 / 5 / 3 - 70  # a view of the grid of 7 beside the document (the old layout)
    assert before / 13.7 < 60  # Rerun wrote no hour label there


def test_long_session_tab_stacks_its_signals_in_inner_tabs(tmp_path):
    rec = Recorder(tmp_path / "r.rrd", max_points=500)
    t = T0 + np.linspace(0, 13.7 * H, 5000).astype(np.int64)
    for k in range(7):
        rec.series(f"/th/s{k}", t, np.sin(np.arange(5000) / (300 + k))[:, None], (f"line {k}",),
                   unit="degC")  # fmt: skip
    rec.curve("/th/fit", np.arange(10.0), np.arange(10.0), ("c",), unit="degC", x_label="T")
    rec.document("th", "# th")
    tab = rec.blueprint().root_container.contents[0]
    assert type(tab).__name__ == "Tabs"
    names = [str(c.name) for c in tab.contents]
    assert names == ["th: fit", "th: signals 1/2", "th: signals 2/2"]
    assert [len(c.contents) for c in tab.contents[1:]] == [4, 3]
    assert {type(c).__name__ for c in tab.contents[1:]} == {"Vertical"}
    rec.close()


def test_a_wide_views_legend_sits_beside_the_data():
    """In a wide view the legend's corner is kept free by a time range that runs on past the
    last sample (a tenth of the width), not by squeezing the data under it."""
    rec = Recorder(None)
    t = T0 + np.linspace(0, 13.7 * H, 1000).astype(np.int64)
    rec.series("/w/accel", t, np.column_stack([np.sin(np.arange(1000) / 50.0)] * 4),
               ("accel x corrected", "accel y corrected", "accel x input", "accel y input"),
               unit="m/s^2")  # fmt: skip
    (plot,) = rec.figures.plots.values()
    (view,) = rec._time_views(plot, plot_px=150.0, width_px=1530.0)
    rng = view.properties["TimeAxis"].view_range.as_arrow_array()[0].as_py()
    free = 1 - (int(t[-1] - t[0]) - rng["start"]) / (rng["end"] - rng["start"])  # elapsed
    assert 0.08 < free < 0.2  # the legend's width, ~150 px of 1530
    y = view.properties["ScalarAxis"].range.as_arrow_array().to_pylist()[0]
    assert y[1] < 1.2  # the data fills the height: no room kept above it
    (tall,) = rec._time_views(plot, plot_px=150.0, width_px=200.0)  # narrow: room above
    assert tall.properties["ScalarAxis"].range.as_arrow_array().to_pylist()[0][1] > 2.0
