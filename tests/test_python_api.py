"""Issue 29: ``import imupipe``, the public Python API (``pipeline/python-api/``).

- ``import imupipe`` stays light (no numpy, pyarrow, Rerun...) and every public name resolves;
- one function per stage type, whose keywords are its ``Options`` fields with their types and
  defaults (``imupipe/_stages.py`` is what ``imupipe._codegen`` writes, so they cannot drift);
- the functions give what the pipeline gives: the same fitted values as ``imupipe run``, the
  truth of a simulated log within its uncertainty, the same errors (one line naming the key);
- ``Calibration`` round trip (save, load, apply), ``run`` from a dict, ``convert``;
- the notebook example runs (the how-to page "Use imupipe from Python" runs as written with
  every how-to and tutorial page: ``tests/test_docs_examples.py``).
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import subprocess
import sys
import typing
import warnings
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

import imupipe
from imupipe import _codegen, _stages
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.table import sensor
from imupipe.stages.registry import STAGE_TYPES, stage_class

from conftest import REPO, run_cli

HEAVY = ("numpy", "pyarrow", "rerun", "ray", "scipy", "rosbags", "mcap", "rich")
OWN = {"table", "name", "accept_failed_checks"}


def test_import_is_light_and_every_name_resolves() -> None:
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", "import imupipe"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    loaded = {line.split("|")[-1].strip().split(".")[0] for line in proc.stderr.splitlines()}
    assert not loaded & set(HEAVY)
    for name in imupipe.__all__:
        assert getattr(imupipe, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = imupipe.nope
    # the root package's folder (pipeline/python-api/) is reachable from imupipe.pipeline's
    # folder in a source tree, but never imported under a second name
    with pytest.raises(ImportError, match="is the package 'imupipe'"):
        importlib.import_module("imupipe.pipeline.python-api._api")
    assert "imupipe.pipeline.python-api._api" not in sys.modules


def test_one_function_per_stage_type_with_its_options_as_keywords() -> None:
    assert set(imupipe.STAGES) == set(STAGE_TYPES)
    assert set(_stages.__all__) == set(STAGE_TYPES)
    for type_name in STAGE_TYPES:
        options = stage_class(type_name).Options
        fields = {f.name: f for f in dataclasses.fields(options)}
        function = getattr(imupipe, type_name)
        params = inspect.signature(function).parameters
        assert list(params) == ["table", *fields, "name", "accept_failed_checks"], type_name
        hints = typing.get_type_hints(function)
        option_hints = typing.get_type_hints(options)
        for key, f in fields.items():
            assert params[key].kind is inspect.Parameter.KEYWORD_ONLY
            if f.default is not dataclasses.MISSING:
                assert params[key].default == f.default, (type_name, key)
                assert hints[key] == option_hints[key], (type_name, key)
            else:  # a list or table default: None keeps it
                assert params[key].default is None
                assert hints[key] == option_hints[key] | None, (type_name, key)
        assert hints["return"] is imupipe.StageResult
    # the file is exactly what the generator writes from the stages of today
    assert Path(_stages.__file__).read_text(encoding="utf-8") == _codegen.module_source()


@pytest.fixture(scope="module")
def static(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """A simulated static log (60 s at 200 Hz) and its truth."""
    table, truth = simulate("static", seed=3)
    path = tmp_path_factory.mktemp("static") / "static.csv"
    write_log(path, table)
    return path, truth


def test_stage_function_recovers_the_truth_and_shows_tables(static) -> None:
    path, truth = static
    table = imupipe.read(path)
    with pytest.warns(imupipe.ImupipeWarning, match=r"\[gyro_bias\] only 58 s of data"):
        result = imupipe.gyro_bias(table, interval=[1, 59])
    bias = np.array(result.values["bias"])
    sigma = np.array(result.uncertainties["metrics.bias_std_error"])
    assert np.all(np.abs(bias - truth["params"]["gyro_bias"]) < 5 * sigma)
    assert result.step is not None and result.step.sensor == "gyro"
    (short,) = result.warnings  # 58 s: under the minute a bias wants (issue 38)
    assert short.startswith("only 58 s of data (11600 samples; the at-rest check had 58 one-")
    corrected = sensor(result.apply(table), "gyro").values.mean(axis=0)
    np.testing.assert_allclose(corrected, 0.0, atol=5 * sigma.max())
    text, page = repr(result), result._repr_html_()
    assert "gyro_bias (gyro_bias on table): ok" in text and "bias (rad/s)" in text
    assert f"{bias[0]:.4g}"[:5] in text
    assert "<table>" in page and "bias (rad/s)" in page
    assert result.metrics["samples"] == 58 * 200  # the interval, at the simulated 200 Hz


def test_stage_options_checked_as_the_config_checks_them(static) -> None:
    table = imupipe.read(static[0])
    with pytest.raises(imupipe.ImupipeError, match=r"imupipe.allan\(\).kind: 'bogus' is not"):
        imupipe.allan(table, kind="bogus")  # type: ignore[arg-type]
    with pytest.raises(imupipe.ImupipeError, match=r"motion_threshold: nan is not a finite"):
        imupipe.gyro_bias(table, motion_threshold=float("nan"))
    with pytest.raises(TypeError, match="pyarrow.Table"):
        imupipe.gyro_bias(str(static[0]))  # type: ignore[arg-type]


def test_same_values_as_imupipe_run(static, tmp_path: Path) -> None:
    """The Allan function and ``imupipe run`` fit the same coefficients; its warnings are in
    the result and issued as ImupipeWarning (the log lasts 1 min, not 2 h)."""
    path, _ = static
    cfg = tmp_path / "allan.toml"
    cfg.write_text(f'[inputs.s]\npath = "{path}"\n[[stages]]\ntype = "allan"\nterms = ["N", "K"]\n'
                   f'[output]\ndir = "{tmp_path / "out"}"\nrerun = false\nreport = false\n')  # fmt: skip
    proc = run_cli("run", cfg, "--quiet")
    assert proc.returncode == 0, proc.stderr
    ran = json.loads((tmp_path / "out" / "calibration.json").read_text())["results"]["allan"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = imupipe.allan(imupipe.read(path), terms=("N", "K"))  # type: ignore[arg-type]
    assert result.values["gyro"] == ran["gyro"] and result.values["accel"] == ran["accel"]
    assert result.warnings == ran["warnings"] and result.warnings
    assert [str(w.message) for w in caught] == [f"[allan] {w}" for w in result.warnings]
    assert all(w.category is imupipe.ImupipeWarning for w in caught)
    assert caught[0].filename == __file__  # points at the user's line
    assert any(k.endswith("K_range_68") for k in result.uncertainties)


def test_inspect_says_what_the_command_says(static) -> None:
    path, _ = static
    shown = imupipe.inspect(path)
    proc = run_cli("inspect", path, "--json")
    assert proc.returncode == 0, proc.stderr
    assert shown.info == json.loads(proc.stdout)
    assert shown["streams"]["imu"]["count"] == 12000  # 60 s at 200 Hz
    assert repr(shown) == run_cli("inspect", path).stdout.rstrip("\n")
    assert repr(shown).splitlines()[0] in shown._repr_html_()


def test_read_errors_and_warnings(tmp_path: Path) -> None:
    with pytest.raises(imupipe.ImupipeError, match=r"imupipe.read\('none.csv'\).path: no such"):
        imupipe.read("none.csv")
    with pytest.raises(imupipe.ImupipeError, match=r"csv: unknown key 'colour'"):
        imupipe.read(REPO / "tests/data/imucal/annotated_session.csv", csv={"colour": 1})
    log = tmp_path / "back.csv"
    log.write_text("t_ns,gyro_x,gyro_y,gyro_z\n2000,0,0,0\n1000,0,0,0\n3000,0,0,0\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        table = imupipe.read(log)
    assert table.column("t_ns").to_pylist() == [1000, 2000, 3000]
    assert caught and all(w.category is imupipe.ImupipeWarning for w in caught)
    assert str(caught[0].message).startswith(f"[imupipe.read({str(log)!r})]")


def test_read_gives_aligned_samples_by_default(tmp_path: Path) -> None:
    """Issue 38: a log whose temperature has messages of its own reads as one row per IMU
    sample, the temperature carried onto them by linear interpolation; ``rows="messages"``
    keeps one row per message, as ``imupipe run`` reads it."""
    table, _ = simulate("static", {"duration_s": 10.0, "temperature": None}, seed=4)
    n = table.num_rows
    t_ns = table.column("t_ns").to_numpy()
    slow = t_ns[::100] + 3_000_000  # 2 Hz, between the IMU stamps
    temp = 25.0 + 0.1 * np.arange(len(slow))  # a ramp: interpolation is exact on it
    from imupipe.readers.table import make_table

    temps = make_table(slow, temperature=temp)
    both = pa.concat_tables([table.select(temps.column_names), temps]).sort_by("t_ns")
    path = tmp_path / "two_streams.mcap"
    write_log(path, both)
    messages = imupipe.read(path, rows="messages")
    assert messages.num_rows == n + len(slow)
    assert np.isnan(np.mean(messages["gyro_x"].to_numpy(zero_copy_only=False)))
    aligned = imupipe.read(path)
    assert aligned.num_rows == n and aligned["gyro_x"].null_count == 0
    assert aligned["temperature"].null_count == 0
    got = aligned["temperature"].to_numpy()
    inside = (t_ns >= slow[0]) & (t_ns <= slow[-1])
    expected = 25.0 + 0.1 * (t_ns - slow[0]) / (slow[1] - slow[0])
    np.testing.assert_allclose(got[inside], expected[inside], rtol=0, atol=1e-9)
    assert np.all(got[t_ns < slow[0]] == temp[0]) and np.all(got[t_ns > slow[-1]] == temp[-1])
    np.testing.assert_array_equal(aligned["gyro_x"].to_numpy(), table["gyro_x"].to_numpy())
    with pytest.raises(imupipe.ImupipeError, match=r"rows='message': must be 'samples' or"):
        imupipe.read(path, rows="message")  # type: ignore[arg-type]


def test_mag_stage_on_aligned_rows_warns(tmp_path: Path) -> None:
    table, _ = simulate("mag", seed=1)
    path = tmp_path / "mag.mcap"
    write_log(path, table)
    with pytest.warns(imupipe.ImupipeWarning, match="rows='messages' to fit on the magnet"):
        imupipe.mag_calibration(imupipe.read(path))
    with warnings.catch_warnings():
        warnings.simplefilter("error", imupipe.ImupipeWarning)
        messages = imupipe.read(path, rows="messages")
    result = imupipe.mag_calibration(messages)
    assert not any("rows='messages'" in w for w in result.warnings)


def test_flight_stage_on_aligned_rows_says_to_read_messages() -> None:
    log = REPO / "tests/data/px4_ulog/sample_log_small.ulg"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        aligned = imupipe.read(log)
    assert any("rows='samples' keeps the IMU samples" in str(w.message) for w in caught)
    assert aligned["gyro_x"].null_count == 0
    with pytest.raises(imupipe.ImupipeError, match=r"mag_inflight\(\): the table was read with "
                       r"rows='samples' .*\(attitude, current, position, throttle\)"):  # fmt: skip
        imupipe.mag_inflight(aligned)


def test_dir_lists_the_public_names_only() -> None:
    assert dir(imupipe) == sorted(imupipe.__all__)
    assert not {"Any", "TYPE_CHECKING", "importlib", "annotations"} & set(dir(imupipe))


def test_a_misspelt_keyword_names_the_allowed_ones(static) -> None:
    """As the config's unknown key: an ImupipeError with the allowed list (still a TypeError,
    what Python raises for a bad call); the signature stays the function's."""
    with pytest.raises(
        imupipe.ImupipeError,
        match=r"imupipe.read\(\): unknown keyword 'imu_topc'; did you mean 'imu_topic'\? "
        r"\(allowed: imu_topic, mag_topic, temperature_topic, time, csv, gyro_topic, accel_topic, fields, rows\)",
    ) as caught:
        imupipe.read(static[0], imu_topc="/imu")  # type: ignore[call-arg]
    assert isinstance(caught.value, TypeError)
    table = imupipe.read(static[0])
    with pytest.raises(imupipe.ImupipeError, match=r"'term'; did you mean 'terms'\? \(allowed"):
        imupipe.allan(table, term=["N"])  # type: ignore[call-arg]
    with pytest.raises(imupipe.ImupipeError, match=r"imupipe.gyro_bias\(\): takes table as"):
        imupipe.gyro_bias()  # type: ignore[call-arg]
    assert list(inspect.signature(imupipe.read).parameters)[-1] == "rows"


def test_calibration_round_trip_and_run_from_a_dict(
    static, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, _ = static
    table = imupipe.read(path)
    bias = imupipe.gyro_bias(table)
    cal = imupipe.Calibration.from_results(bias)
    saved = cal.save(tmp_path / "cal.json")
    loaded = imupipe.Calibration.load(saved)
    assert loaded.document["chain"] == json.loads(json.dumps(cal.document["chain"]))
    assert loaded.apply(table).equals(bias.apply(table))
    assert "1. gyro: gyro_bias (linear)" in repr(loaded) and "<ol>" in loaded._repr_html_()
    # imupipe run from a dict: the same chain, the files written, each stage's result
    monkeypatch.chdir(tmp_path)
    config = {
        "inputs": {"s": {"path": str(path)}},
        "stages": [{"type": "gyro_bias"}],
        "output": {"dir": "out", "rerun": False, "report": False, "apply_to": []},
    }
    run = imupipe.run(config)
    assert run.out_dir == tmp_path / "out" and (tmp_path / "out" / "calibration.json") in run.files
    assert run.calibration.apply(table).equals(loaded.apply(table))
    assert run.stages["gyro_bias"].values["bias"] == bias.values["bias"]
    assert run.stages["gyro_bias"].step is not None
    assert "gyro_bias (gyro_bias on s): ok" in repr(run) and "<table>" in run._repr_html_()
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.s]\npath = "{path}"\n[[stages]]\ntype = "gyro_bias"\n'
        '[output]\ndir = "out_toml"\nrerun = false\nreport = false\n'
    )
    from_file = imupipe.run(tmp_path / "cfg.toml")
    assert from_file.calibration.document["chain"] == run.calibration.document["chain"]
    with pytest.raises(imupipe.ImupipeError, match=r"<dict>: stages\[0\].type: unknown stage"):
        imupipe.run({"inputs": config["inputs"], "stages": [{"type": "allen"}]})
    with pytest.raises(imupipe.ImupipeError, match="not valid JSON"):
        (tmp_path / "bad.json").write_text("{")
        imupipe.Calibration.load(tmp_path / "bad.json")


def test_convert_applies_a_saved_calibration(static, tmp_path: Path) -> None:
    path, _ = static
    table = imupipe.read(path)
    cal = imupipe.gyro_bias(table).calibration().save(tmp_path / "cal.json")
    summary = imupipe.convert([path], cal, tmp_path / "out", jobs=1, quiet=True)
    assert isinstance(summary, imupipe.ConvertSummary) and not summary.failed
    (written,) = [Path(s.output) for s in summary.converted]
    got = sensor(imupipe.read(written), "gyro").values
    np.testing.assert_allclose(
        got, sensor(imupipe.Calibration.load(cal).apply(table), "gyro").values, atol=1e-12
    )


# -- the notebook, run as written ----------------------------------------------------------------


def test_notebook_example_runs() -> None:
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    notebook = nbformat.read(REPO / "examples" / "python_api.ipynb", as_version=4)
    client = nbclient.NotebookClient(
        notebook, timeout=120, kernel_name="python3",
        resources={"metadata": {"path": str(REPO / "examples")}},
    )  # fmt: skip
    client.execute()
    html = [
        out["data"]["text/html"]
        for cell in notebook.cells
        if cell.cell_type == "code"
        for out in cell.outputs
        if "text/html" in out.get("data", {})
    ]
    assert any("<table>" in page for page in html)  # results shown as tables


@pytest.mark.slow
def test_wheel_holds_each_module_once(tmp_path: Path) -> None:
    """The built wheel has the root package's files under ``imupipe/`` and nowhere else (not
    under ``imupipe/pipeline/python-api/``), with ``py.typed``."""
    import zipfile

    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(REPO), "-w", str(tmp_path), "--no-deps", "-q"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    (wheel,) = tmp_path.glob("imupipe-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    root = sorted(n for n in names if n.count("/") == 1 and n.startswith("imupipe/"))
    assert root == [
        f"imupipe/{f}" for f in ("__init__.py", "_api.py", "_codegen.py", "_stages.py", "py.typed")
    ]
    assert not [n for n in names if "python-api" in n]
    stems = [n.rsplit("/", 1)[-1] for n in names if n.endswith(".py") and "/" in n]
    assert stems.count("_api.py") == 1
