"""The Rerun sink: bulk signals, and a blueprint whose plots open on each stage's own data."""

from __future__ import annotations

import numpy as np

from imupipe.pipeline.recording import Recorder

from helpers import rrd_rows


def _span(view) -> tuple[int, int]:
    rng = view.properties["TimeAxis"].view_range.as_arrow_array()[0].as_py()
    return rng["start"], rng["end"]


def test_views_open_on_their_stage_span_and_split_by_signal_kind(tmp_path):
    rec = Recorder(tmp_path / "r.rrd", max_points=1000)
    t_a = 1_000_000_000_000 + np.arange(5000, dtype=np.int64) * 10_000_000  # 50 s
    t_b = t_a + 36_000_000_000_000  # ten hours later
    rec.series("/a/input/gyro", t_a, np.zeros((5000, 3)))
    rec.series("/a/input/temperature", t_a, np.full(5000, 25.0), ("t",))
    rec.ensure_stage("a")
    rec.series("/b/input/gyro", t_b, np.zeros((5000, 3)))
    rec.ensure_stage("b")
    rec.blueprint()
    views_a, views_b = rec._views["a"], rec._views["b"]
    assert [v.name for v in views_a] == ["a: gyro", "a: temperature"]
    # what was recorded: means of 5-sample blocks, stamped at the block centres
    centre = 20_000_000
    for view in views_a:
        assert _span(view) == (int(t_a[0]) + centre, int(t_a[-1]) - centre)
    assert _span(views_b[0]) == (int(t_b[0]) + centre, int(t_b[-1]) - centre)
    rec.close()
    rows = rrd_rows(tmp_path / "r.rrd")
    assert rows["/a/input/gyro"] == 1000  # block-averaged to max_points
    assert rows["/b/input/gyro"] == 1000


def test_curve_views_open_on_their_sequence_span(tmp_path):
    import rerun.blueprint as rrb

    rec = Recorder(tmp_path / "r.rrd")
    x = np.arange(-2000, 3500, 100)
    rec.curve("/allan/gyro/x", x, np.zeros((len(x), 2)), ("adev", "fit"), timeline="log10_tau")
    rec.add_view("allan", rrb.TimeSeriesView(origin="/allan/gyro", name="gyro"))
    rec.blueprint()
    assert _span(rec._views["allan"][0]) == (-2000, 3400)
    rec.close()
