"""``report.html``: one self-contained file with every stage's numbers and plots (inline SVG),
that a real browser renders. The SVG is read back with ``xml.etree`` and checked the way a
person looks at a plot: every point of every line there in its colour, titles and units on the
axes, legible log labels, legends clear of the titles and of each other, nothing cut off."""

from __future__ import annotations

import json
import re
import subprocess
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from imupipe.pipeline.report.figures import Plot, Series
from imupipe.pipeline.report.plot_layout import SUPERSCRIPT, pow10_text
from imupipe.pipeline.report.summary import fmt
from imupipe.pipeline.report.svg_plot import text_width
from imupipe.pipeline.simulate import simulate, write_log

from helpers import screenshot_tool

NS = "{http://www.w3.org/2000/svg}"


@pytest.fixture(scope="module")
def report_run(tmp_path_factory):
    from conftest import run_cli

    d = tmp_path_factory.mktemp("report")
    for name, params, file in (
        ("poses", {}, "poses.csv"),
        ("mag", {"duration_s": 30.0}, "tumble.mcap"),
    ):
        table, _ = simulate(name, params, seed=2)
        write_log(d / file, table)
    (d / "cfg.toml").write_text(
        '[inputs.poses]\npath = "poses.csv"\n[inputs.tumble]\npath = "tumble.mcap"\n'
        '[[stages]]\ntype = "accel_calibration"\ninput = "poses"\n'
        '[[stages]]\ntype = "gyro_calibration"\ninput = "poses"\n'
        '[[stages]]\ntype = "mag_calibration"\ninput = "tumble"\n'
        '[output]\ndir = "out"\napply_to = []\nrerun = false\n'
    )
    done = run_cli("run", d / "cfg.toml", "--quiet")
    assert done.returncode == 0, done.stderr
    return d


def _svgs(html: str) -> list[ET.Element]:
    return [ET.fromstring(m) for m in re.findall(r"<svg .*?</svg>", html, flags=re.S)]


def _size(el: ET.Element) -> tuple[float, float]:
    _, _, w, h = (float(v) for v in el.get("viewBox").split())
    return w, h


def _points(text: str) -> np.ndarray:
    return np.array([[float(v) for v in p.split(",")] for p in text.split()]).reshape(-1, 2)


def _path_points(d: str) -> np.ndarray:
    """Every point a path goes through (M x y, then relative h and v steps)."""
    out, x, y = [], 0.0, 0.0
    for cmd, a, b in re.findall(r"([MhvV])\s*(-?[\d.]+)(?:[ ,](-?[\d.]+))?", d):
        if cmd == "M":
            x, y = float(a), float(b)
        elif cmd == "h":
            x += float(a)
        elif cmd == "v":
            y += float(a)
        out.append((x, y))
    return np.array(out).reshape(-1, 2)


def _text_box(el: ET.Element) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) px of a text as the layout reckons it (svg_plot.text_width)."""
    size = float(el.get("font-size").removesuffix("px"))
    w = text_width(el.text or "", size)
    if el.get("transform"):  # the rotated y title: translate(cx,cy) rotate(-90)
        cx, cy = (float(v) for v in re.findall(r"-?[\d.]+", el.get("transform"))[:2])
        return cx - size, cy - w / 2, cx + 0.3 * size, cy + w / 2
    x, y = float(el.get("x")), float(el.get("y"))
    x0 = {"start": x, "middle": x - w / 2, "end": x - w}[el.get("text-anchor")]
    return x0, y - size, x0 + w, y + 0.3 * size


def _extents(el: ET.Element):
    """(tag, (x0, y0, x1, y1)) of everything drawn in an SVG."""
    for e in el.iter():
        tag = e.tag.removeprefix(NS)
        if tag in ("polyline", "polygon"):
            pts = _points(e.get("points"))
        elif tag == "path":
            pts = _path_points(e.get("d"))
        elif tag == "rect":
            x, y, w, h = (float(e.get(k)) for k in ("x", "y", "width", "height"))
            pts = np.array([[x, y], [x + w, y + h]])
        elif tag == "text":
            yield tag, _text_box(e)
            continue
        else:
            continue
        yield tag, (*pts.min(axis=0), *pts.max(axis=0))


def _boxes_overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _legends(el: ET.Element) -> list[tuple[float, float, float, float]]:
    out = []
    for g in el.iter(f"{NS}g"):
        if g.get("class") == "legend":
            r = g.find(f"{NS}rect")
            x, y, w, h = (float(r.get(k)) for k in ("x", "y", "width", "height"))
            out.append((x, y, x + w, y + h))
    return out


def _texts(el: ET.Element, cls: str) -> list[ET.Element]:
    return [t for t in el.iter(f"{NS}text") if t.get("class") == cls]


def _not_blank(image: np.ndarray) -> bool:
    """Drawn: many shades, and data on the axes: coloured pixels (plot lines) or, for plots
    whose data are grey (a "before" bar chart beside tiny "after" bars), more ink than the
    frame, ticks and labels of an empty plot (about 3 % of the pixels)."""
    rgb = image[..., :3].reshape(-1, 3)
    coloured = (rgb.max(axis=1) - rgb.min(axis=1)) > 0.25
    ink = rgb.min(axis=1) < 0.85
    return rgb.std() > 0.05 and (coloured.mean() > 0.002 or ink.mean() > 0.045)


def test_report_is_one_self_contained_file(report_run):
    out = report_run / "out"
    assert not (out / "recording.rrd").exists()  # rerun = false; the report does not need it
    html = (out / "report.html").read_text()
    assert html.startswith("<!DOCTYPE html>")
    # nothing to fetch: no external scripts, styles or images
    assert not re.search(r'(src|href)="(https?:|//|file:)', html)
    assert "<script" not in html and "<link" not in html
    assert "<img" not in html and "data:image" not in html
    figures = _svgs(html)
    assert len(figures) >= 8
    for el in figures:
        assert el.get("width") == "100%" and el.get("viewBox")
        title = el.find(f"{NS}title").text
        assert title == el.get("aria-label") and f"<figcaption>{title}</figcaption>" in html
        drawn = [e for e in el.iter() if e.get("class") in ("dots", "bars", "band")]
        drawn += list(el.iter(f"{NS}polyline"))
        assert drawn, title


def test_report_holds_every_stage_with_its_numbers_and_plots(report_run):
    out = report_run / "out"
    html = (out / "report.html").read_text()
    cal = json.loads((out / "calibration.json").read_text())["results"]
    for stage in ("accel_calibration", "gyro_calibration", "mag_calibration"):
        assert f'id="stage-{stage.replace("_", "-")}"' in html
    residual = cal["accel_calibration"]["metrics"]["residual_mg"]["means_rms"]
    assert f"{fmt(residual, 3)} mg rms" in html
    field = fmt(cal["mag_calibration"]["field"] * 1e6)
    assert f'<td>field magnitude (uT)</td><td class="num">{field}</td>' in html
    for caption in (
        "|a| - g after calibration (mg) per pose",
        "gravity direction residual (deg) per transition",
        "raw samples and the fitted ellipsoid (uT): projections and directions",
        "corrected samples and the field sphere (uT): projections and directions",
        "accel (m/s^2) over time",
    ):
        assert f"<figcaption>{caption}</figcaption>" in html, caption
    assert html.count("What to look at.") == 3


def test_report_can_be_turned_off(report_run, cli):
    cfg = report_run / "cfg.toml"
    cfg.write_text(cfg.read_text().replace('dir = "out"', 'dir = "out2"\nreport = false'))
    done = cli("run", cfg, "--quiet")
    assert done.returncode == 0, done.stderr
    written = sorted(p.name for p in (report_run / "out2").iterdir())
    assert "calibration.json" in written and "report.html" not in written
    assert written == sorted(
        p.name for p in (report_run / "out").iterdir() if p.name != "report.html"
    )


def test_report_renders_in_a_headless_browser(report_run, tmp_path):
    tool = screenshot_tool()
    exe = tool.browser()
    if exe is None:
        pytest.skip("no chromium on PATH (Debian: apt-get install chromium)")
    shot = tmp_path / "report.png"
    subprocess.run(
        [
            exe,
            *tool.CHROMIUM_FLAGS,
            f"--user-data-dir={tmp_path / 'profile'}",
            "--window-size=1400,3000",
            f"--screenshot={shot}",
            (report_run / "out" / "report.html").as_uri(),
        ],
        capture_output=True,
        timeout=120,
        check=False,
    )
    assert shot.exists(), "chromium wrote no screenshot"
    cv2 = pytest.importorskip("cv2")
    image = cv2.imread(str(shot))[..., ::-1] / 255.0
    assert _not_blank(image)
    # the plots themselves: below the tables, the page holds lines in colour
    assert _not_blank(image[image.shape[0] // 3 :])


def test_report_figures_keep_inside_their_frames_and_legends_clear_of_titles(report_run):
    """Nothing drawn (lines, dots, bars, text as the layout reckons its width) leaves the
    viewBox; a legend overlaps neither a title nor another legend, and lies above its plot's
    frame, outside it (between the title and the data)."""
    html = (report_run / "out" / "report.html").read_text()
    for el in _svgs(html):
        w, h = _size(el)
        for tag, (x0, y0, x1, y1) in _extents(el):
            assert 0 <= x0 <= x1 <= w and 0 <= y0 <= y1 <= h, (el.get("aria-label"), tag)
        titles = [_text_box(t) for t in _texts(el, "title")]
        legends = _legends(el)
        frames = [
            tuple(float(r.get(k)) for k in ("x", "y", "width", "height"))
            for r in el.iter(f"{NS}rect")
            if r.get("class") == "frame"
        ]
        for i, box in enumerate(legends):
            assert not any(_boxes_overlap(box, t) for t in titles)
            assert not any(_boxes_overlap(box, other) for other in legends[i + 1 :])
            assert box[3] <= min(y for _, y, _, _ in frames)  # above every panel
            assert not any(_boxes_overlap(box, (x, y, x + fw, y + fh)) for x, y, fw, fh in frames)
        for i, a in enumerate(titles):
            assert not any(_boxes_overlap(a, b) for b in titles[i + 1 :])


def _plot(kind: str, series: list[Series], **kw) -> Plot:
    unit = kw.pop("unit", "rad/s")
    return Plot(stage="s", key="k", kind=kind, title="signal", unit=unit, series=series, **kw)


def _draw(plot: Plot) -> ET.Element:
    from imupipe.pipeline.report.svg_plot import svg

    return ET.fromstring(svg(plot))


def test_lines_keep_every_point_in_their_colour_and_break_at_gaps():
    t = 1_700_000_000_000_000_000 + np.arange(500, dtype=np.int64) * 10_000_000
    values = np.column_stack([np.sin(np.arange(500) / 20.0), np.cos(np.arange(500) / 30.0)])
    values[200:203, 1] = np.nan
    colors = [(228, 26, 28), (30, 160, 60)]
    plot = _plot("time", [])
    plot.series.append(Series("/s/a", ["a x", "a y"], colors, t, values))
    el = _draw(plot)
    lines = [(e.get("stroke"), len(_points(e.get("points")))) for e in el.iter(f"{NS}polyline")]
    data = [(c, n) for c, n in lines if c in ("#e41a1c", "#1ea03c") and n > 2]
    assert data == [("#e41a1c", 500), ("#1ea03c", 200), ("#1ea03c", 297)]
    # the legend names both lines; the axes carry the unit and the time since the first sample
    assert [t.text for t in el.iter(f"{NS}text") if t.text in ("a x", "a y")] == ["a x", "a y"]
    assert [t.text for t in _texts(el, "ytitle")] == ["rad/s"]
    assert [t.text for t in _texts(el, "xtitle")] == ["time since 2023-11-14 22:13:20 UTC (s)"]
    assert [t.text for t in _texts(el, "title")] == ["signal (rad/s)"]


def test_dots_bands_and_guides_of_an_allan_plot():
    """Measured values as one path of dots (one per finite value), the band as filled shapes
    beneath, the model terms dashed; the x title carries tau's unit."""
    tau = np.logspace(-2, 3, 30)
    dev = 1e-3 / np.sqrt(tau)
    dev[5] = np.nan
    plot = _plot("xy", [], x_label="tau", x_unit="s", log_x=True, log_y=True)
    plot.series += [
        Series("/s/band", ["68%"], [(150, 150, 150)], tau, np.column_stack([dev * 0.8, dev * 1.2]), "band"),
        Series("/s/m", ["measured"], [(40, 100, 230)], tau, dev[:, None], "points"),
        Series("/s/n", ["N"], [(30, 160, 60)], tau, (1e-3 / np.sqrt(tau))[:, None], "guide"),
    ]  # fmt: skip
    el = _draw(plot)
    dots = [e for e in el.iter(f"{NS}path") if e.get("class") == "dots"]
    counts = [e.get("d").count("M") for e in dots if e.get("stroke") == "#2864e6"]
    assert counts == [1, 29]  # the legend's swatch (above the plot), then the 29 finite values
    bands = [e for e in el.iter(f"{NS}polygon") if e.get("class") == "band"]
    assert [len(_points(b.get("points"))) for b in bands] == [2 * 5, 2 * 24]
    assert all(b.get("fill-opacity") == "0.3" for b in bands)
    data = next(e for e in dots if e.get("d").count("M") == 29)
    assert list(el).index(bands[0]) < list(el).index(data)  # beneath the data
    guides = [e for e in el.iter(f"{NS}polyline") if e.get("stroke-dasharray")]
    # the legend's swatch (2 points, above the plot), then the guide's 30
    assert [len(_points(g.get("points"))) for g in guides if g.get("stroke") == "#1ea03c"] == [
        2,
        30,
    ]
    assert [t.text for t in _texts(el, "xtitle")] == ["tau (s)"]


def _pow10_value(label: str) -> float:
    mantissa, _, power = label.rpartition("\u00d7")
    exponent = power.removeprefix("10").translate({v: k for k, v in SUPERSCRIPT.items()})
    return float(mantissa or 1.0) * 10.0 ** int(exponent)


def test_log_axes_are_labelled_in_plain_text_at_any_span():
    """Log axes carry plain-text labels: powers of ten, and 2 and 5 times them on an axis
    spanning less than two decades, so that a value inside the data's span is labelled."""
    assert [pow10_text(v) for v in (1e-3, 1.0, 100.0, 2e-5, 5e3, 0.0)] == [
        "10\u207b\u00b3",
        "10\u2070",
        "10\u00b2",
        "2\u00d710\u207b\u2075",
        "5\u00d710\u00b3",
        "",
    ]
    plain = re.compile("^([0-9.]+\u00d7)?10[\u207b\u2070\u00b9\u00b2\u00b3\u2074-\u2079]+$")
    for lo, hi in ((1e-6, 1e-1), (2.2e-4, 7e-4)):
        plot = _plot("xy", [], x_label="tau", x_unit="s", log_x=True, log_y=True)
        plot.series.append(
            Series("/s/a", ["a"], [(0, 0, 0)], np.array([1.0, 10.0]), np.array([[lo], [hi]]))
        )
        labels = [t.text for t in _texts(_draw(plot), "ytick")]
        assert labels and all(plain.match(s) for s in labels), labels
        assert any(lo <= _pow10_value(s) <= hi for s in labels), (lo, hi, labels)


def test_bars_are_grouped_per_item_on_integer_ticks():
    x = np.arange(17.0)
    plot = _plot("bars", [], x_label="transition", unit="deg")
    plot.series.append(
        Series("/s/r", ["start", "calibrated"], [(150, 150, 150), (40, 100, 230)], x, np.column_stack([x + 1, 0.1 * x]))
    )  # fmt: skip
    el = _draw(plot)
    groups = [g for g in el.iter(f"{NS}g") if g.get("class") == "bars"]
    assert [(g.get("fill"), len(g)) for g in groups] == [("#969696", 17), ("#2864e6", 17)]
    lefts = [float(groups[k][3].get("x")) for k in range(2)]
    assert lefts[0] < lefts[1]  # side by side within an item's slot
    ticks = [t.text for t in _texts(el, "xtick")]
    assert ticks == [str(i) for i in range(0, 17, 2)]
    assert [t.text for t in _texts(el, "xtitle")] == ["transition"]
    assert [t.text for t in _texts(el, "ytitle")] == ["deg"]


def test_3d_projections_are_at_equal_aspect_with_a_coverage_map():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(400, 3))
    pts = 50.0 * d / np.linalg.norm(d, axis=1)[:, None] * [1.0, 1.0, 0.5]
    plot = _plot("3d", [], unit="uT")
    plot.series += [
        Series("/s/p", ["samples"], [(60, 100, 230)], np.arange(400), pts, "cloud", {"colors": np.array([[60, 100, 230]] * 400)}),
        Series("/s/e", ["ellipsoid"], [(240, 180, 40)], np.zeros(1), np.zeros((1, 3)), "ellipsoid",
               {"half_sizes": np.array([50.0, 50.0, 25.0]), "rotation": np.eye(3)}),
    ]  # fmt: skip
    el = _draw(plot)
    assert _size(el) == (1280.0, 340.0)
    outlines = [
        _points(e.get("points")) for e in el.iter(f"{NS}polyline") if e.get("stroke") == "#f0b428"
    ]
    assert [len(o) for o in outlines] == [2, 200, 200, 200]  # the legend's swatch, 3 panels
    outlines = outlines[1:]
    spans = [np.ptp(o, axis=0) for o in outlines]
    assert spans[0][0] == pytest.approx(spans[0][1], abs=1.0)  # x-y: a circle stays round
    assert spans[1][0] == pytest.approx(2 * spans[1][1], abs=1.0)  # y-z: 50 across, 25 up
    dots = [e for e in el.iter(f"{NS}path") if e.get("class") == "dots"]
    # the legend's swatch, then three planes and the map
    assert [e.get("d").count("M") for e in dots] == [1] + [400] * 4
    assert "directions (coverage)" in [t.text for t in _texts(el, "title")]
    assert {t.text for t in _texts(el, "xtitle")} == {"x (uT)", "y (uT)", "z (uT)", "azimuth (deg)"}


def test_a_plot_with_nothing_to_draw_is_left_out():
    from imupipe.pipeline.report.svg_plot import svg

    assert svg(_plot("time", [])) is None
    assert (
        svg(_plot("xy", [Series("/s/a", ["a"], [(0, 0, 0)], np.zeros(0), np.zeros((0, 1)))]))
        is None
    )


def test_axes_of_values_near_the_float64_limit():
    """Cells of 1e308 are numbers: the axis of such a curve (span past float64's range) has
    finite ends and ticks, increasing, and every value maps into [0, 1]."""
    from imupipe.pipeline.report.plot_layout import Axis, nice_ticks, tick_labels

    for lo, hi in (
        (-1e308, 1e308),
        (0.0, 1.7e308),
        (-1.7e308, -1e307),
        (1e308, 1e308),
        (-1.0, 1.79e308),
    ):
        ticks = nice_ticks(lo, hi)
        assert np.isfinite(ticks).all() and (ticks[1:] > ticks[:-1]).all(), (lo, hi, ticks)
        assert len(tick_labels(ticks)) == len(ticks)
        axis = Axis([np.array([lo, hi, np.inf, np.nan])], log=False)
        axis.pad(0.05)
        assert np.isfinite([axis.lo, axis.hi]).all() and axis.hi > axis.lo
        assert len(axis.labels) == len(axis.ticks) >= 2
        fractions = axis(np.array([lo, hi, 0.0]))  # beyond the padded axis: inf, not drawn
        assert not np.isnan(fractions).any()


# -- the plot check: legends off the data, every entry and series visible -------------------------
def test_every_report_plot_passes_the_plot_check(report_run):
    """No legend covers data, no legend entry has nothing visible, no series is hidden by
    another, in every figure of a run's report (tests/plot_check.py)."""
    from plot_check import problems, svgs

    figures = svgs((report_run / "out" / "report.html").read_text())
    assert len(figures) >= 8
    assert [p for el in figures for p in problems(el)] == []


def _svg(body: str) -> ET.Element:
    return ET.fromstring(
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 200 100" aria-label="t">{body}</svg>'
    )


LINE = '<polyline points="10,50 190,50" fill="none" stroke="#e41a1c" stroke-width="2"/>'


def test_plot_check_fails_a_legend_over_data_and_an_entry_with_nothing_drawn():
    from plot_check import problems

    legend = (
        '<g class="legend"><rect x="20" y="40" width="60" height="20" fill="none"/>'
        '<polyline points="22,45 40,45" stroke="{c}" stroke-width="1.5" fill="none"/>'
        '<text x="44" y="48">{n}</text></g>'
    )
    over = problems(_svg(LINE + legend.format(c="#e41a1c", n="x")))
    assert len(over) == 1 and "covers data" in over[0]
    above = legend.replace('y="40"', 'y="0"').format(c="#1ea03c", n="ghost")
    missing = problems(_svg(LINE + above))
    assert missing == ["t: legend entry 'ghost' (#1ea03c) has nothing visible"]
    assert problems(_svg(LINE + legend.replace('y="40"', 'y="0"').format(c="#e41a1c", n="x"))) == []


def test_plot_check_fails_a_series_drawn_over_by_another():
    """Two curves with the same values: the second, opaque, hides the first entirely; drawn
    see-through (lines over time) both show."""
    from plot_check import problems

    x = np.linspace(0, 10, 50)
    y = np.sin(x)[:, None]
    same = [
        Series("/a", ["a"], [(228, 26, 28)], x, y, "line"),
        Series("/b", ["b"], [(30, 160, 60)], x, y, "line"),
    ]
    found = problems(_draw(_plot("xy", same)))
    assert any("#e41a1c is hidden" in p for p in found)
    assert any("'a'" in p and "nothing visible" in p for p in found)
    t = (x * 1e9).astype(np.int64)
    over_time = [Series(s.entity, s.names, s.colors, t, y, "line") for s in same]
    assert problems(_draw(_plot("time", over_time))) == []


def test_sparse_dots_are_drawn_over_a_dense_cloud_and_still_intervals_as_spans():
    """A few points amid many (the soak blocks among heating and cooling) come last, on white
    edges; a highlighted series (still intervals at g) is shaded spans beneath the data."""
    from plot_check import problems

    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, 400)
    dense = Series(
        "/h", ["heating"], [(228, 26, 28)], x, (x + 0.01 * rng.normal(size=400))[:, None], "points"
    )
    few = Series("/s", ["soak"], [(150, 150, 150)], x[:5], x[:5, None], "points")
    el = _draw(_plot("xy", [few, dense]))
    dots = [p for p in el.iter(f"{NS}path") if p.get("class") == "dots"]
    assert dots[-1].get("stroke") == "#969696"
    assert problems(el) == []
    t = np.arange(100, dtype=np.int64) * 10**8
    still = np.where((np.arange(100) // 25) % 2 == 0, 9.8, np.nan)
    spans = Series(
        "/still", ["still"], [(230, 120, 20)], t, still[:, None], "line", {"highlight": True}
    )
    line = Series("/a", ["|a|"], [(40, 100, 230)], t, np.full((100, 1), 9.8), "line")
    el = _draw(_plot("time", [spans, line], unit="m/s^2"))
    shaded = [g for g in el.iter(f"{NS}g") if g.get("class") == "spans"]
    assert len(shaded) == 1 and len(list(shaded[0])) == 2
    assert problems(el) == []
