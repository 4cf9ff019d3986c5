"""Issue 28: one record of what happened, and views without empty legend entries.

- Every warning and note a run prints on stderr is in ``calibration.json`` (its stage's
  ``warnings`` and the top-level ``warnings`` list, with what it means), in ``report.html`` and
  in the recording's Summary tab, and the terminal ends with all of them; a stage that warned
  never reads a bare ``ok``.
- No view of the recording's blueprint has a legend entry without data: every line a time
  series view lists has samples in the view's time range, and every legend label of a 2D plot
  names a line or markers drawn in it.

A small run (a 10 min still recording: the allan stage warns) runs in CI; the demo itself
(``examples/demo.sh``: its simulated sessions and ``imupipe run examples/demo.toml``) is
``slow``.
"""

from __future__ import annotations

import collections
import html
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from imupipe.pipeline.simulate import simulate, write_log

from helpers import rrd_static

ROOT = Path(__file__).resolve().parents[1]
PRINTED = re.compile(r"^imupipe: (warning|note): \[([^\]]+)\] (.*)$")

SMALL = """
[inputs.static]
path = "static.mcap"
[[stages]]
type = "allan"
input = "static"
[[stages]]
type = "gyro_bias"
input = "static"
[output]
dir = "out"
apply_to = []
"""


def run(cfg: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "imupipe.pipeline.cli", "run", str(cfg)],
        capture_output=True,
        text=True,
        cwd=cfg.parent,
        timeout=900,
    )


@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    d = tmp_path_factory.mktemp("small_run")
    table, _ = simulate("static", {"duration_s": 600.0, "rate_hz": 100.0}, seed=1)
    write_log(d / "static.mcap", table)
    (d / "cfg.toml").write_text(SMALL)
    done = run(d / "cfg.toml")
    assert done.returncode == 0, done.stderr
    return d / "out", done


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """The demo's calibration as ``examples/demo.sh`` runs it: its ``imupipe simulate`` lines
    before ``imupipe run``, then the run, in a fresh folder."""
    d = tmp_path_factory.mktemp("demo")
    (d / "data").mkdir()
    (d / "demo.toml").write_text((ROOT / "examples" / "demo.toml").read_text())
    script = (ROOT / "examples" / "demo.sh").read_text().split("imupipe run demo.toml")[0]
    for line in script.splitlines():
        if line.strip().startswith("imupipe simulate"):
            args = shlex.split(line.split("#")[0])[1:]
            subprocess.run([sys.executable, "-m", "imupipe.pipeline.cli", *args], cwd=d, check=True)
    done = run(d / "demo.toml")
    assert done.returncode == 0, done.stderr
    return d / "out", done


# -- one record ------------------------------------------------------------------------------------
def printed(stderr: str) -> list[tuple[str, str, str]]:
    """(level, where, message) of every warning and note printed while the run went."""
    return [m.groups() for line in stderr.splitlines() if (m := PRINTED.match(line))]


def check_one_record(out: Path, done: subprocess.CompletedProcess) -> int:
    """Every printed warning and note is in calibration.json, report.html, the recording's
    Summary tab and the end of the terminal summary; returns how many there were."""
    said = printed(done.stderr)
    doc = json.loads((out / "calibration.json").read_text())
    listed = doc["warnings"]
    assert all(set(n) >= {"level", "stage", "source", "message", "meaning"} for n in listed)
    report = html.unescape((out / "report.html").read_text())
    summary = rrd_static(out / "recording.rrd")["/summary"]["TextDocument:text"]
    summary = summary[0] if isinstance(summary, list) else summary
    tail = done.stdout.rsplit("(also in calibration.json and report.html):", 1)[-1]
    for level, _where, message in said:
        # the step's own prefix ([temperature gyro]) names the step; the record its stage
        found = [n for n in listed if message in n["message"] and n["level"] == level]
        assert found, (message, listed)
        for n in found:
            if n["stage"] is not None:
                assert n["message"] in doc["results"][n["stage"]]["warnings"]
            assert n["meaning"] and n["meaning"] in report
        assert message in report, message
        assert message.replace("|", "\\|") in summary, message
        assert " ".join(message.split()[:6]) in " ".join(tail.split()), message
    # a stage that warned never reads a bare "ok"
    for name, result in doc["results"].items():
        if result["warnings"]:
            count = len(result["warnings"])
            status = f"ok, {count} warning" + ("s" if count > 1 else "")
            assert f"{name} ({result['type']} on {result['input']}): {status}" in done.stdout
            assert status in report and status in summary
    return len(said)


def test_small_run_keeps_one_record_of_its_warnings(small_run):
    out, done = small_run
    assert check_one_record(out, done) >= 1  # 10 min at rest: allan wants two hours
    doc = json.loads((out / "calibration.json").read_text())
    (short,) = [n for n in doc["warnings"] if "two hours" in n["message"]]
    assert short["stage"] == "allan" and "Record two hours" in short["meaning"]
    assert "at rest: yes" in done.stdout  # 10 min still: judged (a 5 s one is not, below)
    assert doc["results"]["gyro_bias"]["metrics"]["static_judged"] is True


@pytest.mark.slow
def test_demo_keeps_one_record_of_its_warnings(demo_run):
    out, done = demo_run
    assert check_one_record(out, done) >= 3  # two extrapolated rates, one exports note
    doc = json.loads((out / "calibration.json").read_text())
    rates = [n for n in doc["warnings"] if "temperature rate" in n["message"]]
    assert {n["stage"] for n in rates} == {"temp_gyro", "temp_accel"}
    assert all("degC/min" in n["message"] and "degC/s" not in n["message"] for n in rates)


# -- legends -------------------------------------------------------------------------------------
def blueprint_views(rrd: Path) -> list[dict]:
    """Every view of a recording's blueprint: class, name, contents, time range."""
    import rerun.chunk as rc

    reader = rc.RrdReader(str(rrd))
    fields: dict[str, dict] = collections.defaultdict(dict)
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        for column in batch.schema.names:
            if ":" in column:
                fields[chunk.entity_path][column] = pa.array(batch.column(column)).to_pylist()[-1]
    views = []
    for path, f in fields.items():
        if path.startswith("/view/") and path.count("/") == 2:
            query = fields[f"{path}/ViewContents"]["ViewContents:query"]
            rng = (fields.get(f"{path}/TimeAxis") or {}).get("TimeAxis:view_range")
            views.append(
                {
                    "class": f["ViewBlueprint:class_identifier"][0],
                    "name": f["ViewBlueprint:display_name"][0],
                    "query": [q.lstrip("+ ").strip() for q in query],
                    "range": (rng[0]["start"], rng[0]["end"]) if rng else None,
                }
            )
    return views


def timed_values(rrd: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Entity -> (times on the ``time`` timeline, scalar values) of every signal."""
    import rerun.chunk as rc

    parts: dict[str, list] = collections.defaultdict(list)
    for chunk in rc.RrdReader(str(rrd)).stream().to_chunks():
        batch = chunk.to_record_batch()
        if chunk.is_static or "Scalars:scalars" not in batch.schema.names:
            continue
        t = pa.array(batch.column("time")).cast(pa.int64()).to_numpy()
        v = [np.ravel(x) for x in pa.array(batch.column("Scalars:scalars")).to_pylist()]
        parts[chunk.entity_path].append((t, np.array([x[0] if len(x) else np.nan for x in v])))
    return {e: (np.concatenate([a for a, _ in p]), np.concatenate([b for _, b in p])) for e, p in parts.items()}  # fmt: skip


def legend_entries_without_data(rrd: Path) -> list[str]:
    """The legend entries of the recording's views that name nothing drawn in the view."""
    static = rrd_static(rrd)
    signals = timed_values(rrd)
    missing = []
    for view in blueprint_views(rrd):
        if view["class"] == "TimeSeries":
            for q in view["query"]:
                entities = [e for e in signals if e == q or (q.endswith("/**") and e.startswith(q[:-3]))]  # fmt: skip
                shown = False
                for e in entities:
                    t, v = signals[e]
                    inside = np.ones(len(t), bool)
                    if view["range"]:
                        inside = (t >= view["range"][0]) & (t <= view["range"][1])
                    shown |= bool(np.isfinite(v[inside]).any())
                if not shown:
                    missing.append(f"{view['name']}: {q}")
        elif view["class"] == "2D":
            legend = [q[:-3] + "/legend" for q in view["query"] if q.endswith("/axes/**")]
            drawn = set()
            for q in view["query"]:
                comps = static.get(q, {})
                for key in ("LineStrips2D:labels", "Points2D:labels"):
                    if comps.get(key) and (comps.get("LineStrips2D:strips") or comps.get("Points2D:positions")):  # fmt: skip
                        drawn |= set(comps[key])
            for entity in legend:
                for label in static.get(entity, {}).get("Points2D:labels", []):
                    if label not in drawn:
                        missing.append(f"{view['name']}: {label}")
    return missing


def test_small_run_legends_name_only_what_is_drawn(small_run):
    out, _ = small_run
    assert legend_entries_without_data(out / "recording.rrd") == []


def test_the_recording_counts_time_from_the_runs_first_sample(small_run):
    """The recording's time line starts at 0 at the first sample the run read (issue 38: the
    viewer labels it +10m, not the hour of the day)."""
    import pyarrow.compute as pc

    from imupipe.pipeline.config import load_config
    from imupipe.readers.dispatch import read_input

    out, _ = small_run
    signals = timed_values(out / "recording.rrd")
    assert min(int(t.min()) for t, _ in signals.values()) == 0
    assert max(int(t.max()) for t, _ in signals.values()) == pytest.approx(600e9, rel=0.01)
    table, _ = read_input(load_config(out.parent / "cfg.toml").inputs["static"])
    assert pc.min(table.column("t_ns")).as_py() > 10**18  # a date on the log's clock


@pytest.mark.slow
def test_demo_legends_name_only_what_is_drawn(demo_run):
    out, _ = demo_run
    assert legend_entries_without_data(out / "recording.rrd") == []


def test_a_line_without_data_gets_no_legend_entry(tmp_path):
    """The check above can fail: a line all NaN is left out of the plot and its legend."""
    from imupipe.pipeline.report.recording import Recorder

    rec = Recorder(tmp_path / "r.rrd")
    t = 10**18 + np.arange(100, dtype=np.int64) * 10**7
    values = np.column_stack([np.sin(np.arange(100)), np.full(100, np.nan)])
    rec.series("/s/sig", t, values, ["kept", "empty"], unit="rad/s")
    rec.curve("/s/curve", np.arange(10.0), np.column_stack([np.ones(10), np.full(10, np.nan)]),
              ["kept curve", "empty curve"], unit="rad/s")  # fmt: skip
    names = [n for p in rec.figures.plots.values() for s in p.series for n in s.names]
    assert names == ["kept", "kept curve"]
    rec.close()
    assert legend_entries_without_data(tmp_path / "r.rrd") == []


def test_the_legend_check_finds_an_empty_line(tmp_path):
    """A view listing a line that has only NaN in its range is reported."""
    import rerun as rr
    import rerun.blueprint as rrb

    rec = rr.RecordingStream("t")
    rec.save(str(tmp_path / "r.rrd"))
    t = rr.TimeColumn("time", timestamp=(10**18 + np.arange(5) * 10**9).astype("datetime64[ns]"))
    for name, v in (("full", np.arange(5.0)), ("empty", np.full(5, np.nan))):
        rr.send_columns(f"/s/{name}", indexes=[t], columns=rr.Scalars.columns(scalars=v), recording=rec)  # fmt: skip
    view = rrb.TimeSeriesView(origin="/", contents=["/s/full", "/s/empty"], name="v")
    rec.send_blueprint(rrb.Blueprint(view), make_active=True, make_default=True)
    rec.flush()
    rec.disconnect()
    assert legend_entries_without_data(tmp_path / "r.rrd") == ["v: /s/empty"]


# -- the README's image ----------------------------------------------------------------------------
@pytest.mark.slow
def test_readme_image_shows_what_the_demo_shows(demo_run):
    """docs/images/recording_allan.png was made from the demo by make_screenshots.py --hero,
    which wrote beside it what the tab showed; the demo of this code must show the same (else
    run the commands in make_screenshots.py's docstring again)."""
    import importlib.util

    out, _ = demo_run
    images = ROOT / "docs" / "images"
    spec = importlib.util.spec_from_file_location(
        "make_screenshots", ROOT / "docs" / "screenshots" / "make_screenshots.py"
    )
    shots = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(shots)
    for image in images.glob("recording_*.png"):
        record = json.loads(image.with_suffix(".json").read_text())
        now = shots.hero_record(out / "recording.rrd", record["stage"])
        assert now == record, f"{image.name} has drifted from the demo: make it again"
    assert (ROOT / "README.md").read_text().count("docs/images/recording_allan.png") == 1


# -- the walk-through ----------------------------------------------------------------------------
def test_a_log_passed_as_the_config_says_a_config_was_expected(tmp_path):
    table, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 50.0}, seed=1)
    write_log(tmp_path / "tumble.bag", table)
    (tmp_path / "tumble_no_suffix").write_bytes((tmp_path / "tumble.bag").read_bytes())
    (tmp_path / "latin1.toml").write_bytes(b'[inputs.a]\npath = "a.csv\xff"\n')
    for log in ("tumble.bag", "tumble_no_suffix", "."):
        done = subprocess.run(
            [sys.executable, "-m", "imupipe.pipeline.cli", "run", log],
            capture_output=True, text=True, cwd=tmp_path, timeout=120,
        )  # fmt: skip
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
        assert "expected a TOML config file, got a log or a folder" in done.stderr
        assert "UTF-8" not in done.stderr
    done = subprocess.run(
        [sys.executable, "-m", "imupipe.pipeline.cli", "run", "latin1.toml"],
        capture_output=True, text=True, cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2 and "not UTF-8" in done.stderr  # a text config, mis-encoded


def test_help_and_commands_page_list_every_scenario():
    from imupipe.pipeline.simulate import SCENARIOS

    done = subprocess.run(
        [sys.executable, "-m", "imupipe.pipeline.cli", "--help"], capture_output=True, text=True
    )
    helptext = " ".join(done.stdout.split())
    page = (ROOT / "docs" / "reference" / "commands.md").read_text()
    for name in SCENARIOS:
        assert re.search(rf"\b{name}\b", helptext), name
        assert f"`{name}`" in page, name


# -- issue 38: a reader's warning names its input and says what it means -----------------------
ULOG = Path(__file__).resolve().parent / "data" / "px4_ulog" / "sample_log_small.ulg"


def test_reader_warnings_name_their_input_and_their_meaning(tmp_path: Path) -> None:
    from imupipe.pipeline.notices import FALLBACK

    (tmp_path / "px4.toml").write_text(
        f'[inputs.gyro1]\npath = "{ULOG}"\nimu_topic = "sensor_gyro_1"\n'
        '[[stages]]\ntype = "gyro_bias"\n[output]\ndir = "out"\nrerun = false\n'
    )
    done = subprocess.run(
        [sys.executable, "-m", "imupipe.pipeline.cli", "run", "px4.toml"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
    read = [n for n in doc["warnings"] if n["source"] == "inputs.gyro1"]
    assert len(read) == 3 and all(n["stage"] == "gyro_bias" for n in read)
    tail = done.stdout.rsplit("(also in calibration.json and report.html):", 1)[-1]
    for n in read:  # listed under the input they came from, not the stage that read it
        assert f"warning [inputs.gyro1]: {n['message'][:40]}" in " ".join(tail.split())
    assert "warning [gyro_bias]: magnetometer" not in tail
    for n in doc["warnings"]:  # a meaning, never a pointer to a page
        assert n["meaning"] not in FALLBACK.values(), n
        assert "docs/reference/outputs.md" not in n["meaning"]
    (short,) = [n for n in doc["warnings"] if n["source"] == "stage"]
    assert short["message"].startswith("only 5 s of data (6 samples;")
    assert "too few to judge whether the IMU was at rest" in short["message"]
    assert "minute or more" in short["meaning"]
    # too short to judge stillness: the summary line says so, as the warning does
    not_judged = "at rest: not judged (5 s, need a minute or more)"
    assert doc["results"]["gyro_bias"]["metrics"]["static_judged"] is False
    status = "ok, at rest not judged (5 s), 4 warnings"
    assert f"gyro_bias (gyro_bias on gyro1): {status}" in done.stdout
    assert not_judged in done.stdout and "at rest: yes" not in done.stdout
    # report.html: the reader's warnings in the input's section with their meanings; the
    # stage's section has its own warning and points to the input's
    report = html.unescape((tmp_path / "out" / "report.html").read_text())
    head, rest = report.split('<h2 id="input-gyro1">inputs.gyro1', 1)
    section, stage = rest.split('<h2 id="stage-gyro-bias">', 1)
    for n in read:
        assert n["message"] in section and n["meaning"] in section
        assert f"[inputs.gyro1]: {n['message']}" in head  # the list under the summary table
        assert n["message"] not in stage
    assert short["message"] in stage and short["message"] not in section
    pointer = "The reader of its input gyro1 warned (3): listed under inputs.gyro1"
    assert pointer in re.sub(r"<[^>]+>", "", stage)
    assert status in stage  # counting them all, as calibration.json does
    assert report.count(status) == 2  # the summary table and the stage's heading
    assert not_judged in stage and "at rest: yes" not in report


def test_convert_says_where_its_read_keys_go(tmp_path: Path) -> None:
    """A reader's "set mag_topic in ..." names the --config file convert was given (or says to
    give one), not an [inputs.NAME] table convert has none of."""
    (tmp_path / "cal.json").write_text(
        json.dumps({"chain": [{"type": "gyro_bias", "sensor": "gyro", "kind": "linear",
                               "matrix": np.eye(3).tolist(), "offset": [0.0, 0.0, 0.0]}]})
    )  # fmt: skip
    (tmp_path / "read.toml").write_text('imu_topic = "sensor_gyro_1"\n')
    from imupipe.pipeline.convert.settings import load_read_settings

    # without --config: the keys go in one
    assert load_read_settings(None).settings_place == "a --config TOML file (e.g. read.toml)"
    for extra, place in ((["--config", "read.toml"], "set mag_topic in read.toml (--config)"),):
        done = subprocess.run(
            [sys.executable, "-m", "imupipe.pipeline.cli", "convert", "--calibration",
             "cal.json", *extra, "--out", f"out{len(extra)}", str(ULOG)],
            cwd=tmp_path, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        assert place in done.stderr and "[inputs." not in done.stderr, done.stderr


@pytest.mark.slow
def test_every_figure_of_the_demo_report_passes_the_plot_check(demo_run):
    """The demo's report (every stage): no legend on data, no legend entry with nothing
    visible, no series hidden by another (tests/plot_check.py)."""
    from plot_check import problems, svgs

    out, _ = demo_run
    figures = svgs((out / "report.html").read_text())
    assert len(figures) >= 40
    assert [p for el in figures for p in problems(el)] == []
