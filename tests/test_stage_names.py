"""Issue 12 item 5: stages written without ``name`` get distinct default names from what tells
them apart (input, then options); only identical stages on one input need a ``name``."""

from __future__ import annotations

import json

import pytest

from imupipe.pipeline.config import load_config
from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.simulate import simulate, write_log

from conftest import run_cli


def names(tmp_path, stages: str, inputs: str = '[inputs.a]\npath = "a.csv"\n') -> list[str]:
    (tmp_path / "a.csv").write_text("t_ns,gyro_x,gyro_y,gyro_z\n0,0,0,0\n")
    (tmp_path / "b.csv").write_text("t_ns,gyro_x,gyro_y,gyro_z\n0,0,0,0\n")
    (tmp_path / "cfg.toml").write_text(inputs + stages)
    return [st.name for st in load_config(tmp_path / "cfg.toml").stages]


def test_one_stage_of_a_type_is_named_by_its_type(tmp_path):
    assert names(tmp_path, '[[stages]]\ntype = "temperature"\n') == ["temperature"]


def test_two_stages_of_a_type_are_named_by_their_options(tmp_path):
    stages = (
        '[[stages]]\ntype = "temperature"\nsensor = "gyro"\n'
        '[[stages]]\ntype = "temperature"\nsensor = "accel"\n'
        '[[stages]]\ntype = "temperature"\nname = "mine"\nsensor = "accel"\n'
    )
    assert names(tmp_path, stages) == ["temperature_gyro", "temperature_accel", "mine"]
    stages = (
        '[[stages]]\ntype = "temperature"\nsensor = "gyro"\norder = 2\n'
        '[[stages]]\ntype = "temperature"\nsensor = "accel"\n'
    )
    assert names(tmp_path, stages) == ["temperature_gyro_order2", "temperature_accel"]


def test_same_options_on_two_inputs_are_named_by_input(tmp_path):
    inputs = '[inputs.a]\npath = "a.csv"\n[inputs.b]\npath = "b.csv"\n'
    stages = '[[stages]]\ntype = "allan"\ninput = "a"\n[[stages]]\ntype = "allan"\ninput = "b"\n'
    assert names(tmp_path, stages, inputs) == ["allan_a", "allan_b"]


def test_identical_stages_on_one_input_need_a_name(tmp_path):
    stages = '[[stages]]\ntype = "temperature"\n[[stages]]\ntype = "temperature"\n'
    with pytest.raises(ConfigError, match=r"stages\[0\] \(temperature on input 'a'\).*'name'"):
        names(tmp_path, stages)
    stages = (
        '[[stages]]\ntype = "temperature"\nname = "temperature_gyro"\n'
        '[[stages]]\ntype = "temperature"\nsensor = "gyro"\n'
        '[[stages]]\ntype = "temperature"\nsensor = "accel"\n'
    )
    with pytest.raises(ConfigError, match="like another stage's name"):
        names(tmp_path, stages)


def test_gyro_and_accel_temperature_stages_run_without_names(tmp_path):
    """The issue's case: two temperature stages on one input, written without names."""
    table, _ = simulate("thermal", {"heating_rates": [2.0], "rate_hz": 0.5, "hold_s": 300.0})
    write_log(tmp_path / "chamber.csv", table)
    (tmp_path / "cfg.toml").write_text(
        '[inputs.chamber]\npath = "chamber.csv"\n'
        '[[stages]]\ntype = "temperature"\nsensor = "gyro"\n'
        '[[stages]]\ntype = "temperature"\nsensor = "accel"\n'
        '[output]\ndir = "out"\napply_to = []\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert list(doc["results"]) == ["temperature_gyro", "temperature_accel"]
