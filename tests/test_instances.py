"""Every raw instance of a log in one run (issue 26): ``[inputs.X] instances = "all"``.

On ``imupipe simulate board`` (two IMUs and a barometer, PX4 v1.11 warm-up ULog, the log's slots
opposite to the instances): three stages written once give the complete TC file (TC_G0/1,
TC_A0/1, TC_B0), each device in its own slot, with the same numbers as the explicit
one-stage-per-instance config; a list restricts the instances; mistakes are one line.
"""

from __future__ import annotations

import json

import pytest
from test_exports import qgc_params

from imupipe.pipeline.config import load_config
from imupipe.pipeline.errors import ConfigError, ReadError
from imupipe.pipeline.instances import expand_instances
from imupipe.pipeline.simulate import simulate, write_log

from conftest import run_cli

STAGES = (
    '[[stages]]\ntype = "temperature"\nsensor = "gyro"\norder = 3\nrate_terms = []\n'
    '[[stages]]\ntype = "temperature"\nsensor = "accel"\norder = 3\nrate_terms = []\n'
    '[[stages]]\ntype = "baro_temperature"\n'
)
OUTPUT = 'dir = "{out}"\napply_to = []\nrerun = false\nreport = false\nexports = ["px4"]\n'


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    d = tmp_path_factory.mktemp("instances")
    log, truth = simulate("board", {"rate_hz": 2.0, "cal_order": [1, 0]}, seed=11)
    write_log(d / "board.ulg", log)
    return d, truth


def _run(d, name: str, body: str):
    (d / f"{name}.toml").write_text(body + "[output]\n" + OUTPUT.format(out=name))
    return run_cli("run", d / f"{name}.toml", "--quiet", cwd=d)


@pytest.fixture(scope="module")
def all_instances(board):
    d, truth = board
    proc = _run(d, "all", '[inputs.board]\npath = "board.ulg"\ninstances = "all"\n' + STAGES)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((d / "all" / "calibration.json").read_text())
    return d, truth, doc, qgc_params((d / "all" / "px4_calibration.params").read_text())


def test_one_run_gives_the_complete_tc_file(all_instances):
    """TC_G, TC_A of both IMUs in the slots of the log's CAL_*_ID, TC_B0 for the barometer."""
    _, truth, doc, px4 = all_instances
    ids = [imu["device_id"] for imu in truth["imus"]]
    for prefix in ("TC_G", "TC_A"):
        assert px4[f"{prefix}_ENABLE"] == 1
        assert [px4[f"{prefix}{k}_ID"] for k in (0, 1)] == [ids[1], ids[0]]
    assert px4["TC_B_ENABLE"] == 1 and px4["TC_B0_ID"] == truth["baro"]["device_id"]
    assert sorted(doc["results"]) == sorted(
        [f"temperature_{s}_sensor_gyro{i}" for s in ("gyro", "accel") for i in ("", "_1")]
        + ["baro_temperature_sensor_baro"]
    )
    assert {e["device"]["device_id"] for e in doc["chain"]} == {*ids, truth["baro"]["device_id"]}
    baro = doc["results"]["baro_temperature_sensor_baro"]["fitted_on"]["topics"]
    assert baro == {"temperature": "sensor_baro/temperature"}  # imu_topic = "": no IMU read
    gyro = doc["results"]["temperature_gyro_sensor_gyro_1"]["fitted_on"]["topics"]
    assert gyro == {"imu": "sensor_gyro_1", "temperature": "sensor_gyro_1/temperature"}


def test_same_numbers_as_one_stage_per_instance(all_instances):
    """The explicit config (one input and one stage per instance) writes the same file."""
    d, _, _, px4 = all_instances
    body = ""
    for key, topics in (
        ("g0", 'imu_topic = "sensor_gyro"\n'),
        ("g1", 'imu_topic = "sensor_gyro_1"\n'),
        ("b0", 'imu_topic = "sensor_gyro"\ntemperature_topic = "sensor_baro"\n'),
    ):
        body += f'[inputs.{key}]\npath = "board.ulg"\n{topics}'
    for key in ("g0", "g1"):
        for s in ("gyro", "accel"):
            body += f'[[stages]]\ntype = "temperature"\nsensor = "{s}"\ninput = "{key}"\n'
            body += "order = 3\nrate_terms = []\n"
    body += '[[stages]]\ntype = "baro_temperature"\ninput = "b0"\n'
    proc = _run(d, "explicit", body)
    assert proc.returncode == 0, proc.stderr
    theirs = qgc_params((d / "explicit" / "px4_calibration.params").read_text())
    assert theirs == px4


def _expanded(d, name: str, body: str):
    (d / f"{name}.toml").write_text(body + "[output]\n" + OUTPUT.format(out=name))
    return expand_instances(load_config(d / f"{name}.toml"))


def test_a_list_keeps_only_its_instances(board):
    """instances = ["sensor_gyro_1"]: the IMU stages run on instance 1 only, an input of its own
    named after it, which apply_to names in the expanded input's place."""
    d, _ = board
    body = '[inputs.board]\npath = "board.ulg"\ninstances = ["sensor_gyro_1"]\n'
    body += STAGES.split('[[stages]]\ntype = "baro')[0]
    cfg = _expanded(d, "one", body.replace("apply_to = []", ""))
    assert list(cfg.inputs) == ["board-sensor_gyro_1"]
    spec = cfg.inputs["board-sensor_gyro_1"]
    assert (spec.imu_topic, spec.temperature_topic) == ("sensor_gyro_1", None)
    assert [(st.name, st.input) for st in cfg.stages] == [
        ("temperature_gyro_sensor_gyro_1", "board-sensor_gyro_1"),
        ("temperature_accel_sensor_gyro_1", "board-sensor_gyro_1"),
    ]


def test_a_barometer_input_reads_its_pressure(board):
    d, _ = board
    body = '[inputs.board]\npath = "board.ulg"\ninstances = "all"\n'
    cfg = _expanded(d, "b", body + '[[stages]]\ntype = "baro_temperature"\n')
    (spec,) = [cfg.inputs[st.input] for st in cfg.stages]
    assert (spec.imu_topic, spec.mag_topic, spec.temperature_topic) == ("", "", "sensor_baro")


def test_an_unknown_instance_is_one_line(board):
    d, _ = board
    body = '[inputs.board]\npath = "board.ulg"\ninstances = ["sensor_gyro_7"]\n' + STAGES
    with pytest.raises(ConfigError, match="sensor_gyro_7 not among the log's raw sensor"):
        _expanded(d, "bad", body)


def test_a_bad_value_is_one_line(board):
    d, _ = board
    proc = _run(d, "bad2", '[inputs.board]\npath = "board.ulg"\ninstances = "some"\n' + STAGES)
    assert proc.returncode == 2
    assert 'instances: "all" or a list' in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_csv_input_has_no_instances(tmp_path):
    (tmp_path / "x.csv").write_text("t_ns,temperature\n0,20\n1000000,21\n")
    body = '[inputs.x]\npath = "x.csv"\ninstances = "all"\n[[stages]]\ntype = "baro_temperature"\n'
    with pytest.raises(ReadError, match="has no sensor instances"):
        _expanded(tmp_path, "csv", body)
