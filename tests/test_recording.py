"""The Rerun recording: what a person sees when it opens.

A run over every stage type is read back from ``recording.rrd`` (data and blueprint, with
``rerun.chunk.RrdReader``) and every view is checked the way a person would look at it: it has
data on the timeline the time panel opens on (or static data, for the views that have no time
axis), its title carries its unit, and the lines it shows have distinct names.
"""

from __future__ import annotations

import collections
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from imupipe.pipeline.report.figures import Figures, display_unit
from imupipe.pipeline.report.plot_layout import Axis, nice_ticks, tick_labels
from imupipe.pipeline.report.recording import Recorder
from imupipe.pipeline.simulate import simulate, write_log

from helpers import rrd_rows, rrd_static

CONFIG = """
[inputs.static]
path = "static.mcap"
[inputs.poses]
path = "poses.csv"
[inputs.tumble]
path = "tumble.mcap"
[inputs.chamber]
path = "chamber.csv"
[[stages]]
type = "average"
input = "static"
window = 500
[[stages]]
type = "allan"
input = "static"
[[stages]]
type = "gyro_bias"
input = "static"
[[stages]]
type = "accel_calibration"
input = "poses"
[[stages]]
type = "gyro_calibration"
input = "poses"
[[stages]]
type = "mag_calibration"
input = "tumble"
[[stages]]
type = "temperature"
input = "chamber"
sensor = "gyro"
[output]
dir = "out"
apply_to = []
rerun_max_points = 2000
report = false
"""


@pytest.fixture(scope="module")
def every_stage(tmp_path_factory) -> Path:
    """A run of every stage type on short simulated sessions; returns its output folder."""
    from conftest import run_cli

    d = tmp_path_factory.mktemp("every_stage")
    sessions = [
        ("static", {"duration_s": 600.0, "rate_hz": 100.0}, "static.mcap"),
        ("poses", {}, "poses.csv"),
        ("mag", {"duration_s": 30.0}, "tumble.mcap"),
        ("thermal", {"heating_rates": [2.0], "hold_s": 300.0, "rate_hz": 1.0}, "chamber.csv"),
    ]
    for name, params, file in sessions:
        table, _ = simulate(name, params, seed=1)
        write_log(d / file, table)
    (d / "cfg.toml").write_text(CONFIG)
    done = run_cli("run", d / "cfg.toml", "--quiet")
    assert done.returncode == 0, done.stderr
    return d / "out"


# -- reading a recording back -------------------------------------------------------------------
def _last(batch: pa.RecordBatch, column: str):
    return pa.array(batch.column(column)).to_pylist()[-1]


def read_blueprint(path: Path) -> tuple[dict[str, dict], str, list[str]]:
    """(views by path, the time panel's timeline, the root tabs' names) of a recording."""
    import rerun.chunk as rc

    reader = rc.RrdReader(str(path))
    fields: dict[str, dict[str, object]] = collections.defaultdict(dict)
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        for column in batch.schema.names:
            if ":" in column:
                fields[chunk.entity_path][column] = _last(batch, column)
    views = {}
    for path_, f in fields.items():
        if path_.startswith("/view/") and path_.count("/") == 2:
            views[path_] = {
                "class": f["ViewBlueprint:class_identifier"][0],
                "name": f["ViewBlueprint:display_name"][0],
                "query": [
                    q.replace("$origin", f["ViewBlueprint:space_origin"][0].rstrip("/"))
                    for q in fields[f"{path_}/ViewContents"]["ViewContents:query"]
                ],
                "range": (fields.get(f"{path_}/TimeAxis") or {}).get("TimeAxis:view_range"),
            }
    timeline = fields["/time_panel"]["TimePanelBlueprint:timeline"][0]
    root = bytes(fields["/viewport"]["ViewportBlueprint:root_container"][0])
    import uuid

    tabs = fields[f"/container/{uuid.UUID(bytes=root)}"]["ContainerBlueprint:contents"]
    names = []
    for tab in tabs:
        f = fields["/" + tab]
        names.append(
            (f.get("ContainerBlueprint:display_name") or f["ViewBlueprint:display_name"])[0]
        )
    return views, timeline, names


def read_data(path: Path) -> tuple[dict, dict, dict]:
    """(static entity -> components, (entity, timeline) -> (first, last), entity -> line names)."""
    import rerun.chunk as rc

    static = rrd_static(path)
    names = {e: c["SeriesLines:names"] for e, c in static.items() if "SeriesLines:names" in c}
    spans: dict[tuple[str, str], tuple[int, int]] = {}
    for chunk in rc.RrdReader(str(path)).stream().to_chunks():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        for timeline in chunk.timeline_names:
            col = pa.array(batch.column(timeline)).cast(pa.int64()).to_numpy()
            key = (chunk.entity_path, timeline)
            first, last = spans.get(key, (int(col.min()), int(col.max())))
            spans[key] = (min(first, int(col.min())), max(last, int(col.max())))
    return static, spans, names


def _entities(query: list[str], known: set[str]) -> list[str]:
    out = []
    for q in query:
        q = q.lstrip("+ ").strip()
        out += [e for e in known if e.startswith(q[:-3])] if q.endswith("/**") else [q]
    return out


# -- the run of every stage -----------------------------------------------------------------------
def test_every_view_shows_data_on_the_timeline_the_time_panel_opens_on(every_stage):
    views, timeline, _ = read_blueprint(every_stage / "recording.rrd")
    static, spans, _ = read_data(every_stage / "recording.rrd")
    assert timeline == "time"
    known = set(static) | {e for e, _ in spans}
    assert len(views) > 20
    for view in views.values():
        entities = _entities(view["query"], known)
        assert entities, view
        if view["class"] == "TimeSeries":
            start, end = view["range"][0]["start"], view["range"][0]["end"]
            for e in entities:
                first, last = spans[(e, timeline)]  # data on the time panel's timeline
                assert first <= end and last >= start, (view["name"], e)  # inside the view
        else:  # no time axis: static data, shown whatever the time cursor
            assert all(e in static for e in entities), view


def test_views_say_their_units_and_lines_have_distinct_names(every_stage):
    views, _, _ = read_blueprint(every_stage / "recording.rrd")
    static, spans, names = read_data(every_stage / "recording.rrd")
    known = set(static) | {e for e, _ in spans}
    titles = {v["name"] for v in views.values()}
    for expected in (
        "gyro (rad/s)",
        "accel (m/s^2)",
        "mag (uT)",
        "|h| (uT)",
        "gyro x Allan deviation (rad/s) vs tau (s)",
        "accel z Allan deviation (m/s^2) vs tau (s)",
        "gyro y bias (rad/s) vs temperature (degC)",
        "|a| - g after calibration (mg) per pose",
        "raw samples and the fitted ellipsoid (uT); axes 40 uT",
    ):
        assert expected in titles, sorted(titles)
    assert not any("(T)" in t or "log10" in t or "timeline" in t for t in titles)
    for view in views.values():
        if view["class"] in ("TimeSeries", "2D", "BarChart", "3D"):
            assert view["name"].count("(") >= 1 or "scale factor" in view["name"], view["name"]
        if view["class"] == "TimeSeries":
            lines = [n for e in _entities(view["query"], known) for n in names[e]]
            assert len(lines) == len(set(lines)), (view["name"], lines)
    # the pipeline's before/after signals say which is which (one entity per line)
    gyro = _lines(names, "/gyro_bias/corrected/gyro")
    assert gyro == ["gyro x corrected", "gyro y corrected", "gyro z corrected"]
    assert _lines(names, "/average/raw/gyro") == ["gyro x raw", "gyro y raw", "gyro z raw"]


def _lines(names: dict, signal: str) -> list[str]:
    """The line names of a signal: its lines are the entities under it."""
    return [n for e in sorted(names) if e.rsplit("/", 1)[0] == signal for n in names[e]]


def test_summary_tab_first_then_one_tab_per_stage(every_stage):
    _, _, tabs = read_blueprint(every_stage / "recording.rrd")
    assert tabs == [
        "Summary",
        "average",
        "allan",
        "gyro_bias",
        "accel_calibration",
        "gyro_calibration",
        "mag_calibration",
        "temperature",
    ]
    static, _, _ = read_data(every_stage / "recording.rrd")
    assert "TextDocument:text" in static["/summary"]
    assert all("TextDocument:text" in static[f"/{t}/summary"] for t in tabs[1:])


def test_magnetometer_in_microtesla_and_signals_capped(every_stage):
    import rerun.chunk as rc

    rows = rrd_rows(every_stage / "recording.rrd")
    assert max(rows.values()) <= 2000  # rerun_max_points
    # 60000 samples: the min and max of 1000 blocks of 60; 3000: of 1000 blocks of 3
    assert rows["/average/raw/gyro/gyro_x_raw"] == 2000
    assert rows["/mag_calibration/raw/mag/mag_x_raw"] == 2000
    values = collections.defaultdict(list)
    for chunk in rc.RrdReader(str(every_stage / "recording.rrd")).stream().to_chunks():
        parent, line = chunk.entity_path.rsplit("/", 1)
        if parent == "/mag_calibration/corrected/mag" and not chunk.is_static:
            col = pa.array(chunk.to_record_batch().column("Scalars:scalars"))
            values[line].append(np.array(col.to_pylist(), dtype=float).ravel())
    xyz = np.column_stack([np.concatenate(values[f"mag_{a}_corrected"]) for a in "xyz"])
    norm = np.linalg.norm(xyz, axis=1)
    assert 40 < np.median(norm) < 60  # the simulated field is 48.2 uT


def test_the_field_magnitude_is_drawn_over_the_noisy_magnitude(every_stage):
    """The viewer draws a view's lines in entity-path order: the field's magnitude, a constant,
    must come after |h| corrected, whose noise hid it (its legend entry named nothing seen)."""
    views, _, _ = read_blueprint(every_stage / "recording.rrd")
    (view,) = [v for v in views.values() if v["name"] == "|h| (uT)"]
    paths = [q.lstrip("+ ").strip() for q in view["query"]]
    (field,) = [p for p in paths if p.endswith("field_magnitude")]
    (corrected,) = [p for p in paths if p.endswith("h_corrected")]
    assert sorted([corrected, field]) == [corrected, field]


def test_static_input_is_sent_once_for_the_stages_that_share_it(every_stage):
    rows = rrd_rows(every_stage / "recording.rrd")
    assert "/average/raw/gyro/gyro_x_raw" in rows
    assert not any(e.startswith(("/allan/raw/gyro", "/gyro_bias/raw/gyro")) for e in rows)
    views, _, _ = read_blueprint(every_stage / "recording.rrd")
    shown = [v for v in views.values() if "/average/raw/gyro/gyro_x_raw" in v["query"]]
    assert len(shown) == 3  # average, allan and gyro_bias each plot it


# -- the recorder ----------------------------------------------------------------------------------
def _span(view) -> tuple[int, int]:
    rng = view.properties["TimeAxis"].view_range.as_arrow_array()[0].as_py()
    return rng["start"], rng["end"]


def test_plots_split_by_unit_and_open_on_their_own_span(tmp_path):
    rec = Recorder(tmp_path / "r.rrd", max_points=1000)
    t_a = 1_000_000_000_000 + np.arange(5000, dtype=np.int64) * 10_000_000  # 50 s
    t_b = t_a + 36_000_000_000_000  # ten hours later
    rec.series("/a/gyro", t_a, np.zeros((5000, 3)), unit="rad/s")
    rec.series("/a/temperature", t_a, np.full(5000, 25.0), ("T",), unit="degC")
    rec.series("/b/gyro", t_b, np.zeros((5000, 3)), unit="rad/s")
    plots = {(p.stage, p.key): p for p in rec.figures.plots.values()}
    assert plots[("a", "gyro")].heading == "gyro (rad/s)"
    assert plots[("a", "temperature")].heading == "temperature (degC)"
    # the envelope of 500 blocks of 10: each block's min at its first sample, max at its 6th
    (view_a,) = rec._time_views(plots[("a", "gyro")])
    (view_b,) = rec._time_views(plots[("b", "gyro")])
    # on the time line: elapsed since the first sample
    assert _span(view_a) == (0, int(t_a[4995] - t_a[0]))
    assert _span(view_b) == (int(t_b[0] - t_a[0]), int(t_b[4995] - t_a[0]))
    rec.close()
    assert rrd_rows(tmp_path / "r.rrd")["/a/gyro/x"] == 1000  # max_points rows per line


def test_one_physical_unit_per_plot():
    figures = Figures()
    gyro = figures.plot("s", "gyro", "time", title=None, unit="rad/s")
    counts = figures.plot("s", "gyro", "time", title=None, unit="raw counts")
    assert counts is not gyro and counts.heading == "gyro (raw counts)"
    assert figures.plot("s", "gyro", "time", title=None, unit="rad/s") is gyro
    assert display_unit("T") == ("uT", 1e6)
    assert display_unit("rad/s") == ("rad/s", 1.0)


def test_curves_without_time_become_static_2d_plots(tmp_path):
    rec = Recorder(tmp_path / "r.rrd")
    tau = np.logspace(-2, 3, 40)
    rec.curve("/allan/gyro/x/measured", tau, 1e-3 / np.sqrt(tau), ("measured",), plot="x",
              unit="rad/s", x_label="tau", x_unit="s", log_x=True, log_y=True, points=True)  # fmt: skip
    # the older form (a timeline name for x) still works
    rec.curve("/old/c", np.arange(10), np.arange(10.0), ("c",), timeline="pose")
    rec.close()
    views, _, _ = read_blueprint(tmp_path / "r.rrd")
    assert {v["class"] for v in views.values()} == {"2D"}
    static, spans, _ = read_data(tmp_path / "r.rrd")
    assert "Points2D:positions" in static["/allan/gyro/x/measured"]
    assert "Points2D:labels" in static["/allan/x/axes/x_ticks"]
    assert not spans  # nothing on any timeline


def test_markers_under_a_fitted_line_show_beside_it(tmp_path):
    """The Allan deviation's measured markers lie under the fitted line that follows them: they
    must be wide enough to show on both sides of it (1 px at least), or a reader sees the fit
    only (the measured points were hidden for tau < 100 s in the viewer)."""
    from imupipe.pipeline.report import plot2d

    rec = Recorder(None)
    tau = np.logspace(-2, 3, 40)
    rec.curve("/allan/gyro/x/measured", tau, 1e-3 / np.sqrt(tau), ("measured",), plot="x",
              unit="rad/s", x_label="tau", x_unit="s", log_x=True, log_y=True, points=True)  # fmt: skip
    rec.curve("/allan/gyro/x/fit", tau, 1e-3 / np.sqrt(tau), ("fit",), plot="x",
              unit="rad/s", x_label="tau", x_unit="s", log_x=True, log_y=True)  # fmt: skip
    (plot,) = rec.figures.plots.values()
    drawn = dict(plot2d.draw(plot))
    marker, line = drawn["/allan/gyro/x/measured"], drawn["/allan/gyro/x/fit"]
    radius = -marker.radii.as_arrow_array().to_pylist()[0]  # UI points (negative radii)
    half_width = -line.radii.as_arrow_array().to_pylist()[0]
    order = (marker.draw_order.as_arrow_array().to_pylist()[0], line.draw_order.as_arrow_array().to_pylist()[0])  # fmt: skip
    assert order[0] < order[1]  # the fit over the markers
    assert radius - half_width >= 1.0, (radius, half_width)


def test_a_few_points_amid_many_are_drawn_over_everything():
    """The soak blocks (a few points) among heating and cooling (thousands): drawn under the
    others their legend entry named nothing visible; on top they show, as in report.html."""
    from imupipe.pipeline.report import plot2d

    rec = Recorder(None)
    temp = np.linspace(-40, 80, 2000)
    for name, n in (("heating", 2000), ("soak", 12)):
        x = temp[:: 2000 // n][:n]
        rec.curve(f"/t/bias/{name}", x, 1e-4 * x, (f"bias {name}",), plot="b", unit="rad/s",
                  x_label="temperature", x_unit="degC", points=True)  # fmt: skip
    rec.curve("/t/bias/fit", temp, 1e-4 * temp, ("fit",), plot="b", unit="rad/s",
              x_label="temperature", x_unit="degC")  # fmt: skip
    (plot,) = rec.figures.plots.values()
    drawn = dict(plot2d.draw(plot))
    order = {k: drawn[f"/t/bias/{k}"].draw_order.as_arrow_array().to_pylist()[0]
             for k in ("heating", "soak", "fit")}  # fmt: skip
    assert order["heating"] < order["fit"] < order["soak"]


def test_axes_ticks():
    # round steps (1, 2, 2.5, 5 x 10^k) that cover the data
    np.testing.assert_allclose(nice_ticks(-0.0183, 0.0327), [-0.02, 0.0, 0.02, 0.04], atol=1e-15)
    np.testing.assert_allclose(nice_ticks(-40.0, 80.0), [-40, -20, 0, 20, 40, 60, 80])
    assert tick_labels(np.array([-0.02, 0.0, 0.02])) == ["-0.02", "0.00", "0.02"]
    log = Axis([np.array([2e-5, 3e-2])], log=True)
    assert log.labels == ["1e-5", "1e-4", "0.001", "0.01", "0.1"]
    np.testing.assert_allclose(log(np.array([1e-5, 1e-1])), [0.0, 1.0])
    assert np.isnan(log(np.array([0.0]))[0])  # no log of zero: a gap in the curve


def test_raw_counts_are_plotted_apart_from_si(tmp_path, cli):
    """imu_tk's Xsens log (raw counts, tests/data/imu_tk_xsens): the input is shown in counts,
    the corrected signal in m/s^2, never on one axis; the summary's offsets are in counts."""
    from conftest import TEST_DATA

    data = TEST_DATA / "imu_tk_xsens"
    cfg = tmp_path / "xsens.toml"
    cfg.write_text(
        f'[inputs.xsens]\npath = "{data / "xsens_acc.mat"}"\n[inputs.xsens.csv]\ntime = 0\n'
        'time_unit = "s"\naccel = [1, 2, 3]\naccel_unit = "raw"\n'
        f'gyro_file = "{data / "xsens_gyro.mat"}"\ngyro = [1, 2, 3]\ngyro_unit = "raw"\n'
        '[[stages]]\ntype = "accel_calibration"\ngravity = 9.81744\ninit_static_s = 50.0\n'
        '[output]\ndir = "out"\napply_to = []\nreport = false\n'
    )
    done = cli("run", cfg)
    assert done.returncode == 0, done.stderr
    views, _, _ = read_blueprint(tmp_path / "out" / "recording.rrd")
    titles = {v["name"] for v in views.values()}
    assert {"accel (raw counts)", "accel (m/s^2)", "|a| (raw counts)", "|a| (m/s^2)"} <= titles
    assert "bias (counts)" in done.stdout and "bias (m/s^2)" not in done.stdout


@pytest.mark.parametrize("field_ut,corrected", [(None, "mag (raw counts)"), (50.0, "mag (uT)")])
def test_a_magnetometer_fitted_in_counts_stays_in_counts(tmp_path, cli, field_ut, corrected):
    """The QMC5883L tumble in raw counts (tests/data, MIT): without field_ut the corrected field
    keeps the counts' scale and is plotted in counts (it was drawn as tesla: +-1e9 uT); with
    field_ut it is tesla, shown in uT."""
    from conftest import TEST_DATA

    path = TEST_DATA / "qmc5883l_tomisuarez" / "filtered_raw_data.csv"
    cfg = tmp_path / "qmc.toml"
    cfg.write_text(
        f'[inputs.qmc]\npath = "{path}"\n[inputs.qmc.csv]\nmag = ["mx", "my", "mz"]\n'
        'mag_unit = "raw"\n[[stages]]\ntype = "mag_calibration"\n'
        + (f"field_ut = {field_ut}\n" if field_ut else "")
        + '[output]\ndir = "out"\napply_to = []\nreport = false\n'
    )
    done = cli("run", cfg)
    assert done.returncode == 0, done.stderr
    views, _, _ = read_blueprint(tmp_path / "out" / "recording.rrd")
    titles = {v["name"] for v in views.values()}
    assert {"mag (raw counts)", corrected} <= titles
    assert ("mag (uT)" in titles) == (field_ut is not None)


@pytest.mark.parametrize(
    "t0,kind,label",
    [(0, "duration[ns]", "time since 5 s on the log's clock (s)"),
     (1_700_000_000_000_000_000, "timestamp[ns]", "time since 2023-11-14 22:13:25 UTC (s)")],
)  # fmt: skip
def test_the_time_line_is_time_since_the_start_and_the_log_time_a_second(tmp_path, t0, kind, label):
    """The recording opens on time elapsed since the start of the recording (a duration from
    0: the viewer labels ``+10m``, not the hour of the day), as the report counts time since
    its start; the samples' own time is a second timeline: a date for a ROS or MCAP stamp, a
    duration for a CSV counting from 0 or a ULog's time since boot, never a day in 1970."""
    import xml.etree.ElementTree as ET

    import rerun.chunk as rc

    from imupipe.pipeline.report.recording import LOG_TIMELINE, TIMELINE
    from imupipe.pipeline.report.svg_plot import svg

    rec = Recorder(tmp_path / "r.rrd", max_points=1000)
    rec.start_at(t0 + 4_000_000_000)  # the run's first sample: a second before this signal's
    t = t0 + 5_000_000_000 + np.arange(100, dtype=np.int64) * 10_000_000
    rec.series("/a/gyro", t, np.zeros((100, 3)), unit="rad/s")
    rec.start_at(t0)  # once a signal is sent, the origin stays
    rec.series("/a/temperature", t, np.full(100, 25.0), ("T",), unit="degC")
    (view,) = rec._time_views(next(iter(rec.figures.plots.values())))
    rec.close()
    kinds, times = set(), collections.defaultdict(list)
    for chunk in rc.RrdReader(str(tmp_path / "r.rrd")).stream().to_chunks():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        kinds.add((str(batch.schema.field(TIMELINE).type), str(batch.schema.field(LOG_TIMELINE).type)))  # fmt: skip
        for name in (TIMELINE, LOG_TIMELINE):
            times[name] += pa.array(batch.column(name)).cast(pa.int64()).to_pylist()
    assert kinds == {("duration[ns]", kind)}
    assert min(times[TIMELINE]) == 1_000_000_000 and max(times[TIMELINE]) == 1_990_000_000
    assert sorted(set(times[LOG_TIMELINE])) == t.tolist()
    assert _span(view) == (1_000_000_000, 1_990_000_000)  # the view opens on its data
    drawn = ET.fromstring(svg(next(iter(rec.figures.plots.values()))))
    titles = [e.text for e in drawn.iter("{http://www.w3.org/2000/svg}text")]
    assert [t for t in titles if t.startswith("time since")] == [label]


def test_the_survey_stays_on_the_calendar(tmp_path):
    """The fleet survey's points over months of flights are on the calendar, one timeline."""
    import rerun.chunk as rc

    rec = Recorder(tmp_path / "s.rrd", elapsed=False)
    t = 1_700_000_000_000_000_000 + np.arange(3, dtype=np.int64) * 86_400_000_000_000
    rec.series("/survey/a/bias", t, np.zeros((3, 3)), unit="rad/s", points=True)
    rec.close()
    for chunk in rc.RrdReader(str(tmp_path / "s.rrd")).stream().to_chunks():
        if not chunk.is_static:
            batch = chunk.to_record_batch()
            assert "log time" not in batch.schema.names
            assert str(batch.schema.field("time").type) == "timestamp[ns]"
            assert pa.array(batch.column("time")).cast(pa.int64()).to_pylist() == t.tolist()


def test_a_cloud_far_from_the_origin_gets_the_points_of_the_same_cloud_at_it():
    """A raw magnetometer tumble (centre ~6000 counts, radius ~1000) is drawn with points sized
    by its own spread, not by its distance from the origin (points 6x too large before)."""
    from imupipe.pipeline.report.recording import cloud_radius

    rng = np.random.default_rng(3)
    d = rng.standard_normal((5000, 3))
    sphere = 1000.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    at_origin = cloud_radius(sphere)
    assert at_origin == pytest.approx(8.0, rel=0.05)  # the median of a sampled sphere: ~0
    assert cloud_radius(sphere + [6159.0, 252.0, 3447.0]) == pytest.approx(at_origin, rel=0.01)
    with_nan = np.vstack([sphere, [[np.nan, 0.0, 0.0]]])
    assert cloud_radius(with_nan) == pytest.approx(at_origin, rel=0.01)


def test_the_blueprint_is_the_first_thing_in_the_file(tmp_path):
    """A viewer that streams the recording (``rerun --web-viewer``, a URL) gets imupipe's tabs
    with the first bytes: the blueprint store comes before any data chunk, the data is all
    there, and the time panel is paused."""
    import subprocess

    from helpers import screenshot_tool

    tool = screenshot_tool()
    rec = Recorder(tmp_path / "r.rrd", max_points=1000)
    t = 1_000_000_000_000 + np.arange(3000, dtype=np.int64) * 10_000_000
    rec.series("/a/gyro", t, np.zeros((3000, 3)), unit="rad/s")
    rec.document(None, "# run")
    rec.close()
    assert rrd_rows(tmp_path / "r.rrd")["/a/gyro/x"] == 1000
    assert not list(tmp_path.glob("*.blueprint-first"))  # the rewrite leaves nothing beside
    printed = subprocess.run(
        [tool.rerun_binary(), "rrd", "print", str(tmp_path / "r.rrd")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    blueprint = printed.index("Blueprint,")
    data = printed.index("/a/gyro/")
    assert blueprint < data
    bp = tool.Blueprint(tmp_path / "r.rrd")
    from rerun.blueprint.components import PlayState

    assert bp.field("/time_panel", "TimePanelBlueprint:play_state") == PlayState.Paused.value
