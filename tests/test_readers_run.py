"""Issue 3, done-when: the same simulated log as CSV, MCAP, ROS 1 bag and ROS 2 bag goes through
``imupipe run`` and comes back as MCAP with every Imu, MagneticField and Temperature message,
its original timestamps and the magnetic field in tesla; bad logs end in one line naming the
file (and topic), exit 2, and leave no output behind."""

from __future__ import annotations

import numpy as np
import pyarrow.compute as pc
import pytest
from test_readers import multi_stream_table

from imupipe.pipeline.simulate import write_log
from imupipe.readers.table import sensor

from conftest import run_cli
from helpers import decode_mcap, stamps_ns, vec

FORMATS = ["log.csv", "log.mcap", "log.bag", "log.db3", "log_folder"]
CFG = '[inputs.a]\npath = "{path}"\n{extra}\n[[stages]]\ntype = "gyro_bias"\n\n[output]\ndir = "{out}"\nrerun = false\n'


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    table = multi_stream_table(seed=2)
    for name in FORMATS:
        write_log(d / name, table)
    results = {}
    for name in FORMATS:
        cfg = d / f"{name}.toml"
        cfg.write_text(CFG.format(path=name, extra="", out=f"out_{name}"))
        proc = run_cli("run", cfg, "--quiet")
        assert proc.returncode == 0, (name, proc.stderr)
        results[name] = decode_mcap(d / f"out_{name}" / "a.mcap")
    return table, results


@pytest.mark.parametrize("name", FORMATS)
def test_run_writes_every_message_with_original_times(runs, name):
    table, results = runs
    out = results[name]
    # CSV has no topic names: SPEC's defaults; binary logs keep theirs
    topics = (
        {"imu": "/imu/data", "mag": "/imu/mag", "temperature": "/imu/temperature"}
        if name.endswith(".csv")
        else {"imu": "/imu/data", "mag": "/imu/mag", "temperature": "/imu/temp"}
    )
    assert set(out) == set(topics.values())
    for stream, first in (("imu", "gyro"), ("mag", "mag"), ("temperature", "temperature")):
        msgs = sorted(out[topics[stream]], key=lambda m: m[0])
        data = sensor(table, first)
        assert len(msgs) == len(data)
        np.testing.assert_array_equal(stamps_ns(msgs), data.t_ns)
        if not name.endswith(".csv"):  # binary logs keep the log (receive) times
            key = {"imu": "gyro_x", "mag": "mag_x", "temperature": "temperature"}[stream]
            log = table.filter(pc.is_valid(table.column(key))).column("log_time_ns").to_numpy()
            np.testing.assert_array_equal([t for t, _ in msgs], log)
    mag = vec(sorted(out[topics["mag"]], key=lambda m: m[0]), "magnetic_field")
    np.testing.assert_array_equal(mag, sensor(table, "mag").values)  # tesla, untouched
    accel = vec(sorted(out[topics["imu"]], key=lambda m: m[0]), "linear_acceleration")
    np.testing.assert_array_equal(accel, sensor(table, "accel").values)


def _one_line_error(proc, *needles: str) -> str:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def good_logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    table = multi_stream_table(seed=3)
    for name in ("good.mcap", "good.bag", "good.db3"):
        write_log(d / name, table)
    return d


@pytest.mark.parametrize("name", ["good.mcap", "good.bag", "good.db3"])
def test_truncated_log_is_one_line_and_no_output(good_logs, tmp_path, name):
    data = (good_logs / name).read_bytes()
    bad = tmp_path / name.replace("good", "cut")
    bad.write_bytes(data[: len(data) * 2 // 3])
    (tmp_path / "cfg.toml").write_text(CFG.format(path=bad.name, extra="", out="out"))
    line = _one_line_error(run_cli("run", tmp_path / "cfg.toml", "--quiet"), bad.name)
    assert "imupipe: error:" in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "extra, needles",
    [
        ('imu_topic = "/nope"', ["good.mcap", "'/nope'", "/imu/data"]),
        (
            'imu_topic = "/imu/mag"',
            ["good.mcap", "'/imu/mag'", "MagneticField", "expected sensor_msgs/msg/Imu"],
        ),
        (
            'mag_topic = "/imu/data"',
            ["good.mcap", "'/imu/data'", "expected sensor_msgs/msg/MagneticField"],
        ),
    ],
)
def test_topic_errors_name_file_and_topic(good_logs, tmp_path, extra, needles):
    (tmp_path / "cfg.toml").write_text(
        CFG.format(path=good_logs / "good.mcap", extra=extra, out="out")
    )
    _one_line_error(run_cli("run", tmp_path / "cfg.toml", "--quiet"), *needles)
    assert not (tmp_path / "out").exists()
