"""Issue 3: ``imupipe inspect LOG`` lists topics, types, counts, rates and time span, and the
table columns the reader would fill (checked against the log that was written)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_readers import multi_stream_table

from imupipe.pipeline.simulate import write_log

from conftest import run_cli, shared_path


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("inspect")
    table = multi_stream_table(seed=6)
    for name in ("log.mcap", "log.bag", "log.db3", "log.csv"):
        write_log(d / name, table)
    return d


@pytest.mark.parametrize("name", ["log.mcap", "log.bag", "log.db3"])
def test_inspect_binary_json(logs, name):
    proc = run_cli("inspect", logs / name, "--json")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    topics = info["topics"]
    assert {t: (v["type"], v["count"]) for t, v in topics.items()} == {
        "/imu/data": ("sensor_msgs/msg/Imu", 600),
        "/imu/mag": ("sensor_msgs/msg/MagneticField", 150),
        "/imu/temp": ("sensor_msgs/msg/Temperature", 3),
    }
    # 600 messages 5 ms apart (log times jitter by up to 3 ms): about 200 Hz over 3 s
    assert topics["/imu/data"]["rate_hz"] == pytest.approx(200, rel=0.01)
    assert topics["/imu/data"]["duration_s"] == pytest.approx(2.995, abs=0.004)
    assert info["streams"]["mag"]["topic"] == "/imu/mag"
    for col in ("gyro_x", "accel_cov", "mag_z", "mag_cov", "temperature", "frame_id"):
        assert col in info["columns"]


def test_inspect_text_and_csv(logs):
    proc = run_cli("inspect", logs / "log.bag")
    assert proc.returncode == 0, proc.stderr
    assert "/imu/mag" in proc.stdout and "sensor_msgs/msg/MagneticField" in proc.stdout
    assert "columns filled:" in proc.stdout
    proc = run_cli("inspect", logs / "log.csv", "--json")
    info = json.loads(proc.stdout)
    assert info["streams"]["imu"]["count"] == 600 and info["streams"]["mag"]["count"] == 150
    assert "mag_x" in info["columns"]


def test_inspect_real_bag_and_bad_topic():
    path = shared_path("logs", "rl_test1.bag")
    info = json.loads(run_cli("inspect", path, "--json").stdout)
    assert info["topics"]["/fix"]["count"] == 989
    assert info["topics"]["/fix"]["rate_hz"] == pytest.approx(2.5, rel=0.01)
    assert info["streams"] == {
        "imu": {"topic": "/imu/data", "type": "sensor_msgs/msg/Imu", "count": 11865}
    }
    info = json.loads(run_cli("inspect", path, "--json", "--imu-topic", "/fix").stdout)
    assert (
        "has type sensor_msgs/msg/NavSatFix, expected sensor_msgs/msg/Imu"
        in info["selection_error"]
    )


def test_inspect_missing_file_is_one_line(tmp_path):
    proc = run_cli("inspect", tmp_path / "nope.mcap")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"imupipe: error: {tmp_path / 'nope.mcap'}: no such file or folder"
    ]


@pytest.mark.parametrize("size", [4, 10, 22, 45])
def test_inspect_of_an_mcap_cut_shorter_than_its_footer_is_one_line(logs, tmp_path, size):
    """A file cut before its footer's length (the summary reader seeks back past its start)."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((logs / "log.mcap").read_bytes()[:size])
    proc = run_cli("inspect", cut)
    assert proc.returncode == 2
    [line] = proc.stderr.strip().splitlines()
    assert line.startswith(f"imupipe: error: {cut}")


def test_csv_of_another_layout_shows_its_columns_and_reads_with_a_mapping(tmp_path, cli):
    """A CSV not in imupipe's own layout (the MPU-6050's metadata lines, ax..gz in counts):
    inspect shows its layout instead of failing, and reads it with --config's [csv] mapping."""
    log = Path(__file__).parent / "data" / "mpu6050_tomisuarez" / "imu_static_test.csv"
    done = cli("inspect", log)
    assert done.returncode == 0, done.stderr
    assert "file columns: ax, ay, az, gx, gy, gz" in done.stdout
    assert "data from line 6, rate 100 Hz" in done.stdout and "--config" in done.stdout
    (tmp_path / "read.toml").write_text(
        '[csv]\naccel = ["ax", "ay", "az"]\naccel_unit = "raw"\n'
        'gyro = ["gx", "gy", "gz"]\ngyro_unit = "raw"\n'
    )
    done = cli("inspect", "--config", tmp_path / "read.toml", log)
    assert done.returncode == 0, done.stderr
    assert "stream imu: csv columns (9986 samples, 100.00 Hz)" in done.stdout
