"""Two IMUs of one MCAP or ROS log are two devices, told apart by their topics.

A bag with ``/imu0/data`` and ``/imu1/data`` has no device id or instance: before, every step
of the chain applied to both, so ``run`` fitted the second IMU's bias on data already corrected
by the first one's (its entry held the difference of the two) and the first IMU's corrected log
got both biases. Checked on ``imupipe simulate fleet`` (one vehicle, two IMUs with known biases):
each fitted bias is its own IMU's, each corrected log has zero mean rate where it is still, and
``convert`` of a log whose IMU is neither of the calibration's says so in its manifest.
PX4 and ArduPilot topics are not devices (``sensor_combined`` fuses several IMUs): their devices
keep being told apart by instance and device id only.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.pipeline.calibration_file import UNNAMED, device_key, same_device
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers import dispatch
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import sensor

from conftest import run_cli

TOPICS = ("/imu0/data", "/imu1/data")


def test_device_identity_rules():
    """Message-log topics name devices; flight-log topics, CSV and imported steps do not."""
    a = {"stream": "imu", "topic": "/imu0/data", "format": "mcap"}
    b = {"stream": "imu", "topic": "/imu1/data", "format": "ros1"}
    assert device_key(a) == ("topic", "/imu0/data")
    assert not same_device(a, b) and same_device(a, dict(a))
    csv = {"stream": "imu", "format": "csv"}
    assert device_key(csv) == UNNAMED and same_device(a, csv) and same_device(csv, b)
    fused = {"stream": "imu", "topic": "sensor_combined", "format": "ulog"}
    raw = {"stream": "imu", "topic": "sensor_gyro_1", "format": "ulog", "instance": 1}
    assert device_key(fused) == UNNAMED and same_device(fused, raw)
    other = {"stream": "imu", "topic": "sensor_gyro", "format": "ulog", "instance": 0}
    assert not same_device(raw, other)  # by instance, as before


@pytest.fixture(scope="module")
def two_imus(tmp_path_factory):
    d = tmp_path_factory.mktemp("two_imus")
    params = {"vehicles": 1, "logs": 1, "imus": 2, "events": False}
    fleet, truth = simulate("fleet", params, seed=3)
    write_log(d / "fl", fleet)
    log = next((d / "fl").rglob("*.mcap"))
    devices = truth["devices"]
    first = devices[f"veh01:{TOPICS[0]}"]["logs"][0]["periods"][0]
    t0 = first["start_ns"]
    stop = min(
        (devices[f"veh01:{t}"]["logs"][0]["periods"][0]["stop_ns"] - t0) / 1e9 for t in TOPICS
    )
    interval = [0.5, stop - 0.5]
    body = ""
    for name, topic in zip("ab", TOPICS, strict=True):
        body += (
            f'[inputs.{name}]\npath = "{log}"\nimu_topic = "{topic}"\n'
            f'temperature_topic = "{topic.replace("data", "temperature")}"\n'
        )
    for name in "ab":
        body += f'[[stages]]\ntype = "gyro_bias"\nname = "bias_{name}"\ninput = "{name}"\n'
        body += f"interval = {interval}\n"
    body += '[output]\ndir = "out"\nrerun = false\nreport = false\n'
    (d / "run.toml").write_text(body)
    proc = run_cli("run", d / "run.toml", "--quiet", cwd=d)
    assert proc.returncode == 0, proc.stderr
    truth_bias = {
        t: np.asarray(devices[f"veh01:{t}"]["logs"][0]["periods"][0]["gyro_bias"]) for t in TOPICS
    }
    return d, log, interval, truth_bias


def test_each_imu_gets_its_own_bias(two_imus):
    """Each chain entry names its topic and holds its own IMU's bias (within 0.2 mrad/s: a
    25 s still period at the simulated noise), not the difference of the two."""
    d, _, _, truth = two_imus
    chain = json.loads((d / "out" / "calibration.json").read_text())["chain"]
    assert [e["device"]["topic"] for e in chain] == list(TOPICS)
    assert np.abs(truth[TOPICS[0]] - truth[TOPICS[1]]).max() > 5e-3  # two different biases
    for entry, topic in zip(chain, TOPICS, strict=True):
        assert np.allclose(entry["offset"], truth[topic], atol=2e-4), topic


def test_each_corrected_log_has_only_its_own_correction(two_imus):
    """``DIR/a.mcap`` (the first IMU) and ``DIR/b.mcap``: zero mean rate where still."""
    d, _, (lo, hi), _ = two_imus
    for name, topic in zip("ab", TOPICS, strict=True):
        spec = InputSpec(
            path=d / "out" / f"{name}.mcap",
            name=name,
            imu_topic=topic,
            temperature_topic=topic.replace("data", "temperature"),
        )
        table, _ = dispatch.read_input(spec)
        gyro = sensor(table, "gyro")
        s = (gyro.t_ns - gyro.t_ns[0]) * 1e-9
        still = (s > lo) & (s < hi)
        assert np.abs(gyro.values[still].mean(axis=0)).max() < 1e-5, name


def test_convert_names_a_log_of_neither_imu(two_imus, tmp_path):
    """A log whose IMU topic is neither of the calibration's: no step applied, and the manifest
    says why (``--on-mismatch refuse``: the log fails with that line)."""
    d, _, _, _ = two_imus
    log, _ = simulate("static", {"duration_s": 5.0}, seed=1)
    write_log(tmp_path / "other.mcap", log)
    cal = d / "out" / "calibration.json"
    proc = run_cli(
        "convert", "--calibration", cal, "--out", tmp_path / "conv", tmp_path / "other.mcap"
    )
    assert proc.returncode == 0, proc.stderr
    line = json.loads((tmp_path / "conv" / "manifest.jsonl").read_text().splitlines()[-1])
    assert "none of them" in line["provenance"] and "/imu/data" in line["provenance"]
    proc = run_cli(
        "convert",
        "--calibration",
        cal,
        "--out",
        tmp_path / "refused",
        "--on-mismatch",
        "refuse",
        tmp_path / "other.mcap",
    )
    assert proc.returncode == 1 and "none of them" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) <= 2
