"""The CSV plumbing of the calibration sessions: gyro in a second file (imu_tk), a label column
(imucal), the simulator's poses scenario on the command line, and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.pipeline.config import load_config
from imupipe.pipeline.errors import ConfigError, ReadError
from imupipe.readers.csv.reader import read_csv
from imupipe.readers.table import sensor

from conftest import TEST_DATA
from helpers import rrd_rows, rrd_static


def write_cfg(tmp_path, body: str):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(body)
    return cfg


def test_gyro_file_is_read_row_for_row(tmp_path):
    (tmp_path / "acc.mat").write_text("0.00 1 2 3\n0.01 4 5 6\n")
    (tmp_path / "gyr.mat").write_text("0.00 7 8 9\n0.01 10 11 12\n")
    cfg = write_cfg(
        tmp_path,
        '[inputs.a]\npath = "acc.mat"\n[inputs.a.csv]\ntime = 0\ntime_unit = "s"\n'
        'accel = [1, 2, 3]\naccel_unit = "raw"\ngyro_file = "gyr.mat"\ngyro = [1, 2, 3]\n',
    )
    table, _ = read_csv(load_config(cfg).inputs["a"])
    np.testing.assert_array_equal(sensor(table, "accel").values, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(sensor(table, "gyro").values, [[7, 8, 9], [10, 11, 12]])
    (tmp_path / "gyr.mat").write_text("0.00 7 8 9\n")
    with pytest.raises(ReadError, match="gyr.mat: csv.gyro_file has 1 rows, the main file 2"):
        read_csv(load_config(cfg).inputs["a"])
    cfg.write_text(cfg.read_text().replace("gyr.mat", "missing.mat"))
    with pytest.raises(ConfigError, match=r"csv.gyro_file: no such file"):
        load_config(cfg)


def test_label_column_reaches_the_table(tmp_path):
    cfg = write_cfg(
        tmp_path,
        f'[inputs.s]\npath = "{TEST_DATA / "imucal" / "annotated_session.csv"}"\n'
        '[inputs.s.csv]\nrate_hz = 204.8\naccel = ["acc_x", "acc_y", "acc_z"]\naccel_unit = "raw"\n'
        'gyro = ["gyr_x", "gyr_y", "gyr_z"]\ngyro_unit = "raw"\nlabel = "part"\n',
    )
    table, _ = read_csv(load_config(cfg).inputs["s"])
    labels = table.column("label").to_pylist()
    assert labels[0] == "x_a" and set(labels) == {
        f"{a}_{s}" for a in "xyz" for s in ("p", "a", "rot")
    }
    cfg.write_text(cfg.read_text().replace('label = "part"', 'label = "nope"'))
    with pytest.raises(ReadError, match="column 'nope' \\(csv.label\\) not found"):
        read_csv(load_config(cfg).inputs["s"])


def test_simulate_poses_cli_and_ferraris_without_labels_fails_in_one_line(tmp_path, cli):
    log = tmp_path / "poses.csv"
    done = cli("simulate", "poses", "--out", log, "--set", "n_poses=10", "--set", "pose_s=3")
    assert done.returncode == 0, done.stderr
    truth = json.loads((tmp_path / "poses.csv.truth.json").read_text())
    assert len(truth["static_intervals_s"]) == 10 and truth["accel"]["matrix"]
    cfg = write_cfg(
        tmp_path,
        '[inputs.p]\npath = "poses.csv"\n[[stages]]\ntype = "accel_calibration"\n'
        'method = "ferraris"\n[output]\ndir = "out"\n',
    )
    done = cli("run", cfg)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "imupipe: error: stage 'accel_calibration' on input 'p': method 'ferraris' needs "
        "labelled segments: set csv.label (or give every part as [start_s, end_s] in "
        "ferraris_parts)"
    ]
    assert not (tmp_path / "out").exists()

    cfg.write_text(
        '[inputs.p]\npath = "poses.csv"\n[[stages]]\ntype = "accel_calibration"\n'
        '[[stages]]\ntype = "gyro_calibration"\n[output]\ndir = "out"\n'
    )
    done = cli("run", cfg)
    assert done.returncode == 0, done.stderr
    rows = rrd_rows(tmp_path / "out" / "recording.rrd")
    for entity in ("/accel_calibration/norm/raw", "/accel_calibration/norm/calibrated"):
        assert any(e.startswith(entity + "/") and n > 0 for e, n in rows.items()), sorted(rows)
    bars = rrd_static(tmp_path / "out" / "recording.rrd")  # bar charts: static, no time axis
    assert bars["/accel_calibration/residual_per_pose/a_g"]["BarChart:values"][0]["shape"] == [10]
    assert "BarChart:values" in bars["/gyro_calibration/gravity_direction_residual_deg/calibrated"]
