"""Fault injection: hostile configs through ``imupipe run`` (issue 18).

Hypothesis writes configs with every key given values of every type (strings where tables are
due, tables where strings are, NaN, infinities, integers past int64, hostile input names and
output folders); each run must keep the contract of :mod:`faults`: exit 0 or one line and exit
2, inputs untouched, nothing written outside the output folder, no temporary file left. Then the
cases the campaign found, one by one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from faults import check, cli, snapshot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imupipe.stages.registry import STAGE_TYPES, stage_class


def good_csv(n: int = 300, seed: int = 0) -> str:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 10_000_000
    gyro = 0.01 + 1e-3 * rng.standard_normal((n, 3))
    accel = np.array([0.0, 0.0, 9.81]) + 1e-2 * rng.standard_normal((n, 3))
    rows = "".join(
        f"{t[i]},{','.join(f'{v:.9g}' for v in gyro[i])},{','.join(f'{v:.9g}' for v in accel[i])}\n"
        for i in range(n)
    )
    return "t_ns,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + rows


GOOD_CSV = good_csv()


def toml_value(value) -> str:
    """A TOML literal (written here by hand so that hostile values reach the parser as is)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(value)


scalars = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, -1, 3, 1e-9, 1e9, 0.5, 2**63, -(2**63) - 1]),
    st.text(max_size=8),
    st.sampled_from(["gyro", "accel", "mag", "temperature", "header", "log", "lm", "a"]),
)
values = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(st.text("abcxyz", min_size=1, max_size=3), inner, max_size=2)
    ),
    max_leaves=6,
)
names = st.one_of(
    st.just("a"),
    st.sampled_from(["../x", "/tmp/abs", "a/b", "..", ".", ".hidden", "a b", "a\nb", "é", "-a"]),
    st.text(min_size=1, max_size=6),
)
out_dirs = st.sampled_from(["out", "out", ".", "sub/out", "a.csv", "", "out/../out2"])


@st.composite
def configs(draw) -> dict:
    name = draw(names)
    entry = {"path": draw(st.sampled_from(["a.csv"] * 4 + ["missing.csv", "."]) | values)}
    if draw(st.booleans()):
        entry[draw(st.sampled_from(["time", "imu_topic", "csv", "bogus"]))] = draw(values)
    stages = []
    for _ in range(draw(st.integers(0, 2))):
        stype = draw(st.sampled_from(sorted(STAGE_TYPES)) | values)
        stage = {"type": stype}
        if isinstance(stype, str) and stype in STAGE_TYPES:
            fields = [f.name for f in dataclasses.fields(stage_class(stype).Options)]
            for key in draw(st.lists(st.sampled_from(fields), max_size=3, unique=True)):
                stage[key] = draw(values)
        if draw(st.booleans()):
            stage[draw(st.sampled_from(["input", "name", "accept_failed_checks"]))] = draw(
                values | names
            )
        stages.append(stage)
    output = {"dir": draw(out_dirs | values), "rerun": draw(st.sampled_from([False] * 5 + [True]))}
    if draw(st.booleans()):
        output["apply_to"] = draw(st.sampled_from([[], [name], ["zz"]]) | values)
    return {"name": name, "input": entry, "stages": stages, "output": output}


def render(cfg: dict) -> str:
    lines = [f"[inputs.{json.dumps(cfg['name'])}]"]
    lines += [f"{json.dumps(k)} = {toml_value(v)}" for k, v in cfg["input"].items()]
    for stage in cfg["stages"]:
        lines += ["", "[[stages]]"] + [
            f"{json.dumps(k)} = {toml_value(v)}" for k, v in stage.items()
        ]
    lines += ["", "[output]"] + [f"{k} = {toml_value(v)}" for k, v in cfg["output"].items()]
    return "\n".join(lines) + "\n"


def run_case(root: Path, config_text: str | bytes, case: str, csv: str = GOOD_CSV) -> tuple:
    (root / "a.csv").write_text(csv)
    cfg = root / "cfg.toml"
    cfg.write_bytes(config_text if isinstance(config_text, bytes) else config_text.encode())
    before = snapshot(root)
    code, err = cli("run", cfg, "--quiet")
    outs = [p for p in (root / "out", root / "out2", root / "sub") if p.exists()]
    # with dir = "." the config's folder is the output folder: everything new is an output
    if 'dir = "."' in str(config_text) or 'dir = ""' in str(config_text):
        outs.append(root)
    check(case, code, err, root, before, outs)
    return code, err


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(configs())
def test_generated_configs_keep_the_contract(cfg):
    with tempfile.TemporaryDirectory() as d:
        run_case(Path(d), render(cfg), render(cfg))


BASE = '[inputs.a]\npath = "a.csv"\n\n[[stages]]\ntype = "gyro_bias"\n{extra}\n[output]\ndir = "out"\nrerun = false\n'


@pytest.mark.parametrize(
    "extra,needles",
    [
        ('input = ["a"]', ("stages[0].input", "must be a string")),
        ("input = {x = 1}", ("stages[0].input", "must be a string")),
        ("motion_threshold = nan", ("motion_threshold", "not a finite number")),
        ("motion_threshold = inf", ("motion_threshold", "not a finite number")),
        ("interval = [0.0, nan]", ("interval[1]", "not a finite number")),
        ("name = 3", ("stages[0].name",)),
    ],
)
def test_found_config_faults(tmp_path, extra, needles):
    code, err = run_case(tmp_path, BASE.format(extra=extra), extra)
    assert code == 2 and all(n in err for n in needles), err


def test_average_window_nan_and_type_table(tmp_path):
    cfg = BASE.replace('type = "gyro_bias"', 'type = "average"\nwindow_s = nan').format(extra="")
    code, err = run_case(tmp_path, cfg, "window_s = nan")
    assert code == 2 and "window_s" in err and "not a finite number" in err
    cfg = BASE.format(extra="").replace('type = "gyro_bias"', "type = {a = 1}")
    code, err = run_case(tmp_path, cfg, "type table")
    assert code == 2 and "stages[0].type: must be a string" in err


def test_config_not_utf8(tmp_path):
    code, err = run_case(tmp_path, b'[inputs.a]\npath = "a.csv\xff"\n', "latin-1 config")
    assert code == 2 and "not UTF-8" in err and "cfg.toml" in err


@pytest.mark.parametrize("name", ["../x", "/tmp/imupipe-abs", "a\nb", "..", "a/b"])
def test_input_names_never_become_paths(tmp_path, name):
    cfg = BASE.format(extra="").replace("[inputs.a]", f"[inputs.{json.dumps(name)}]")
    code, err = run_case(tmp_path, cfg, f"input name {name!r}")
    assert code == 2 and "becomes a file name" in err, err
    assert not Path("/tmp/imupipe-abs.mcap").exists()


def test_output_dir_of_the_input_never_overwrites_it(tmp_path):
    """[output] dir = the input's folder and an input whose stem gives its output's name: the
    campaign saw the input overwritten by its corrected copy."""
    from imupipe.pipeline.simulate import simulate
    from imupipe.pipeline.writers.mcap import write_mcap

    table, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 100.0}, seed=1)
    write_mcap(tmp_path / "a.mcap", table)
    cfg = BASE.format(extra="").replace('"a.csv"', '"a.mcap"').replace('dir = "out"', 'dir = "."')
    code, err = run_case(tmp_path, cfg, "dir = input folder")
    assert code == 2 and "would overwrite the input" in err and "a.mcap" in err, err
    # and a symbolic link in the output folder pointing at the input is seen through
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "a.mcap").symlink_to(tmp_path / "a.mcap")
    code, err = run_case(tmp_path, BASE.format(extra="").replace('"a.csv"', '"a.mcap"'), "link")
    assert code == 2 and "would overwrite the input" in err, err


def test_output_dir_is_a_file_or_holds_a_folder_of_an_output_name(tmp_path):
    code, err = run_case(
        tmp_path, BASE.format(extra="").replace('dir = "out"', 'dir = "a.csv"'), "file"
    )
    assert code == 2 and "not a folder" in err
    (tmp_path / "out" / "calibration.json").mkdir(parents=True)  # "busy": a folder in the way
    code, err = run_case(tmp_path, BASE.format(extra=""), "folder in the way")
    assert code == 2 and "calibration.json" in err, err


def test_output_dir_inside_an_input_folder_is_refused(tmp_path):
    """A ROS 2 bag is a folder: writing into it would change the bag (its reader takes every
    .mcap/.db3 file there)."""
    from test_convert import write_bag_with_rosbags

    from imupipe.pipeline.simulate import simulate

    table, _ = simulate("static", {"duration_s": 0.5, "rate_hz": 100.0, "temperature": None}, 2)
    write_bag_with_rosbags(tmp_path / "bag", table, 2, status=0)
    cfg = (
        BASE.format(extra="").replace('"a.csv"', '"bag"').replace('dir = "out"', 'dir = "bag/out"')
    )
    code, err = run_case(tmp_path, cfg, "dir inside the input bag")
    assert code == 2 and "inside the input" in err and "bag" in err, err
