"""``report.html``: one self-contained file with every stage's numbers and plots, that a real
browser renders."""

from __future__ import annotations

import base64
import io
import json
import re
import subprocess

import numpy as np
import pytest

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.pipeline.summary import fmt

from helpers import screenshot_tool


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


def _pngs(html: str) -> list[np.ndarray]:
    from matplotlib.image import imread

    return [
        imread(io.BytesIO(base64.b64decode(data)), format="png")
        for data in re.findall(r'src="data:image/png;base64,([^"]+)"', html)
    ]


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
    images = _pngs(html)
    assert len(images) >= 8
    assert all(_not_blank(im) for im in images)


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
    from matplotlib.image import imread

    assert _not_blank(imread(shot))


def test_log_axes_are_labelled_in_plain_text_at_any_span():
    """Log axes carry plain-text labels (no mathtext parse per label): powers of ten, and 2
    and 5 times them on an axis spanning less than two decades, which otherwise shows no
    label at all."""
    from matplotlib.figure import Figure

    from imupipe.pipeline.report import _log_axis, _pow10

    assert [_pow10(v) for v in (1e-3, 1.0, 100.0, 2e-5, 5e3, 0.0)] == [
        "10\u207b\u00b3",
        "10\u2070",
        "10\u00b2",
        "2\u00d710\u207b\u2075",
        "5\u00d710\u00b3",
        "",
    ]
    for lo, hi in ((1e-6, 1e-1), (2.2e-4, 7e-4)):
        ax = Figure().add_subplot()
        ax.plot([1.0, 10.0], [lo, hi])
        _log_axis(ax, "y")
        shown = [_pow10(v) for v in ax.get_yticks() if lo <= v <= hi]
        assert len([s for s in shown if s]) >= 1, (lo, hi, shown)
