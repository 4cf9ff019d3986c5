"""Issue 2, done-when: `imupipe run` on a simulated static CSV with gyro_bias."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.csv as pacsv
import pytest

from imupipe.pipeline.simulate import simulate, write_log

from helpers import decode_mcap, mcap_attachments, rrd_rows, stamps_ns, vec


@pytest.fixture(scope="module")
def static_run(tmp_path_factory):
    from conftest import run_cli

    d = tmp_path_factory.mktemp("static")
    table, truth = simulate("static", {"duration_s": 30.0, "rate_hz": 200.0}, seed=3)
    write_log(d / "static.csv", table)
    (d / "cfg.toml").write_text(
        '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "average"\nwindow = 500\n\n'
        '[[stages]]\ntype = "gyro_bias"\n\n[output]\ndir = "out"\n'
    )
    proc = run_cli("run", d / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    return d, table, truth


def test_outputs_written(static_run):
    d, _, _ = static_run
    for name in ("calibration.json", "recording.rrd", "static.mcap"):
        assert (d / "out" / name).stat().st_size > 0
    leftovers = [p.name for p in (d / "out").iterdir() if p.name.endswith(".tmp")]
    assert leftovers == []


def test_gyro_bias_offset_is_static_mean(static_run):
    d, _, truth = static_run
    raw = pacsv.read_csv(d / "static.csv")
    mean = np.array([np.mean(raw.column(c).to_numpy()) for c in ("gyro_x", "gyro_y", "gyro_z")])
    cal = json.loads((d / "out" / "calibration.json").read_text())
    (step,) = cal["chain"]
    assert step["type"] == "gyro_bias" and step["sensor"] == "gyro"
    np.testing.assert_allclose(step["offset"], mean, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(step["matrix"], np.eye(3))
    # the simulated truth is recovered to within the noise of 30 s of data
    np.testing.assert_allclose(step["offset"], truth["gyro"]["bias"], atol=2e-4)


def test_mcap_holds_every_sample_corrected(static_run):
    d, table, _ = static_run
    topics = decode_mcap(d / "out" / "static.mcap")
    imu = topics["/imu/data"]
    assert len(imu) == table.num_rows
    assert len(topics["/imu/temperature"]) == table.num_rows
    np.testing.assert_array_equal(stamps_ns(imu), table.column("t_ns").to_numpy())
    gyro = vec(imu, "angular_velocity")
    assert np.abs(gyro.mean(axis=0)).max() < 1e-6
    accel = vec(imu, "linear_acceleration")
    np.testing.assert_allclose(accel[:, 2], table.column("accel_z").to_numpy(), rtol=1e-12)
    cal = json.loads(mcap_attachments(d / "out" / "static.mcap")["calibration.json"])
    assert cal["chain"][0]["type"] == "gyro_bias"


def test_recording_has_stage_entities(static_run):
    d, table, _ = static_run
    rows = rrd_rows(d / "out" / "recording.rrd")
    n = table.num_rows
    # one entity per line; sent once, shown by gyro_bias too
    assert rows["/average/raw/gyro/gyro_x_raw"] == n
    assert not any(e.startswith("/gyro_bias/raw/gyro") for e in rows)
    assert rows["/gyro_bias/corrected/gyro/gyro_z_corrected"] == n
    assert rows["/average/raw/accel/accel_y_raw"] == n
    means = [e for e in rows if e.startswith("/average/means/gyro/")]
    assert len(means) == 3 and all(rows[e] == int(np.ceil(n / 500)) for e in means)


def test_calibration_json_reapplies_the_same_chain(static_run):
    from imupipe.readers.csv.reader import read_csv
    from imupipe.readers.spec import InputSpec
    from imupipe.readers.table import sensor
    from imupipe.stages.steps import apply_chain, steps_from_json

    d, _, _ = static_run
    cal = json.loads((d / "out" / "calibration.json").read_text())
    steps = steps_from_json(cal["chain"])
    table, _ = read_csv(InputSpec(path=d / "static.csv"))
    corrected = sensor(apply_chain(table, steps), "gyro").values
    written = vec(decode_mcap(d / "out" / "static.mcap")["/imu/data"], "angular_velocity")
    np.testing.assert_array_equal(corrected, written)


def test_recording_has_a_blueprint(static_run):
    import rerun.chunk as rc

    d, _, _ = static_run
    reader = rc.RrdReader(str(d / "out" / "recording.rrd"))
    assert len(reader.recordings()) == 1
    assert len(reader.blueprints()) == 1
