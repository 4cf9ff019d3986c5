"""How the Rerun viewer draws lines that share a time-series view: a probe recording to render.

    python docs/screenshots/probe_draw_order.py --out /tmp/probe
    python docs/screenshots/make_screenshots.py /tmp/probe/draw_order.rrd --out /tmp/probe

writes ``draw_order.rrd``: four views of one 11 h signal, its noisy samples (a min/max envelope
at full opacity or see-through) and their running mean, under entity paths that sort the raw
line after the mean (``/a/raw`` > ``/a/means``) or before it (``/d/araw``). What it showed with
rerun-sdk 0.41 (kept for the record, see docs/explanation/recording.md): the viewer draws a
view's lines in the order of their entity paths, not in the order the view lists them, so the
opaque raw envelope hides the mean (A); at 35 % opacity the mean shows through it (B, C); a
path that sorts first puts the raw line beneath (D). Its time axes (a duration timeline, views
~690 px wide) label every hour; at ~280 px they labelled none (Rerun's marks go from 1 h to 12 h
apart and are labelled only 60 px or more apart).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("probe"), help="folder for draw_order.rrd")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    n = 20_000
    t = np.arange(n, dtype=np.int64) * 2_000_000_000  # 2 s apart: 11 h
    raw = 0.01 * np.sin(np.arange(n) / 3000) + rng.normal(0, 0.01, n)
    means = np.convolve(raw, np.ones(50) / 50, mode="same")
    rec = rr.RecordingStream("probe_draw_order")
    rec.save(str(args.out / "draw_order.rrd"))
    index = [rr.TimeColumn("time", duration=t.astype("timedelta64[ns]"))]
    span = rrb.TimeAxis(
        view_range=rrb.TimeRange(
            start=rrb.TimeRangeBoundary.absolute(nanos=0),
            end=rrb.TimeRangeBoundary.absolute(nanos=int(t[-1])),
        )
    )
    views = []
    for name, alpha, raw_path, mean_path, width in [
        ("A opaque, raw path after the mean's", 255, "/a/raw/x", "/a/means/x", 1.0),
        ("B raw at 35 %", 90, "/b/raw/x", "/b/means/x", 1.0),
        ("C raw at 35 %, mean 2.5 px", 90, "/c/raw/x", "/c/means/x", 2.5),
        ("D raw path before the mean's", 255, "/d/araw/x", "/d/means/x", 1.5),
    ]:
        policy = rr.components.AggregationPolicy.MinMax
        style = rr.SeriesLines(names=["raw"], colors=[(226, 160, 160, alpha)], aggregation_policy=policy)  # fmt: skip
        rr.log(raw_path, style, static=True, recording=rec)
        line = rr.SeriesLines(names=["mean"], colors=[(228, 26, 28)], widths=[width])
        rr.log(mean_path, line, static=True, recording=rec)
        for path, values in ((raw_path, raw), (mean_path, means)):
            rr.send_columns(
                path, indexes=index, columns=rr.Scalars.columns(scalars=values), recording=rec
            )
        views.append(
            rrb.TimeSeriesView(origin="/", contents=[mean_path, raw_path], name=name, axis_x=span)
        )
    blueprint = rrb.Blueprint(
        rrb.Tabs(rrb.Grid(*views, name="draw order")),
        rrb.TimePanel(timeline="time", state="collapsed"),
    )
    rec.send_blueprint(blueprint, make_active=True, make_default=True)
    rec.flush()
    print(args.out / "draw_order.rrd")


if __name__ == "__main__":
    main()
