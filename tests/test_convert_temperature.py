"""Issue 8: a temperature step (it needs the temperature stream and its rate, i.e. context beyond
one sample) applies through ``imupipe convert`` exactly as ``imupipe run`` applies it.

Convert streams every chain (a CSV is one batch), so the
corrected messages are byte for byte those of ``run``'s corrected MCAP.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow.csv as pacsv
from test_convert import raw_messages

from imupipe.pipeline.convert.manifest import read_manifest

from conftest import run_cli
from helpers import decode_mcap, vec


def test_temperature_step_converts_like_run(tmp_path):
    log = tmp_path / "therm.csv"
    proc = run_cli(
        "simulate", "thermal", "--out", log, "--rate", "1", "--set", "heating_rates=[2.0]",
        "--set", "hold_s=300",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    (tmp_path / "cfg.toml").write_text(
        '[inputs.therm]\npath = "therm.csv"\n\n[[stages]]\ntype = "temperature"\nsensor = "gyro"\n'
        '\n[output]\ndir = "run"\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    cal = tmp_path / "run" / "calibration.json"
    assert [s["kind"] for s in json.loads(cal.read_text())["chain"]] == ["temperature"]

    proc = run_cli("convert", "--calibration", cal, "--out", tmp_path / "conv", log)
    assert proc.returncode == 0, proc.stderr
    (line,) = read_manifest(tmp_path / "conv")
    assert line["mode"] == "streamed" and line["status"] == "converted"
    ours = raw_messages(tmp_path / "conv" / "therm.mcap")
    assert ours == raw_messages(tmp_path / "run" / "therm.mcap")
    # and the step did correct: the compensated gyro is much closer to the true rate (zero)
    raw = pacsv.read_csv(log)
    before = np.column_stack([raw.column(f"gyro_{a}").to_numpy() for a in "xyz"])
    after = vec(decode_mcap(tmp_path / "conv" / "therm.mcap")["/imu/data"], "angular_velocity")
    rms = [float(np.sqrt(np.mean(x**2))) for x in (before, after)]
    assert rms[1] < 0.2 * rms[0], rms


def test_temperature_step_streams_through_batches_like_the_whole_log(tmp_path):
    """Issue 17 item 1: a binary log many batches long (MCAP: IMU messages and a temperature
    topic), converted with a temperature step in batches of 997 rows, gives the messages that the
    whole log corrected at once gives (apply_chain on the whole table, written by write_mcap)."""
    from imupipe.pipeline.calibration_file import load_calibration
    from imupipe.pipeline.writers.mcap import write_mcap
    from imupipe.readers.dispatch import read_input
    from imupipe.readers.spec import InputSpec
    from imupipe.stages.steps import apply_chain

    fit, log = tmp_path / "fit.csv", tmp_path / "therm.mcap"
    for out, rates in ((fit, "[1.0, 0.5]"), (log, "[2.0]")):
        proc = run_cli(
            "simulate", "thermal", "--out", out, "--rate", "10", "--set", f"heating_rates={rates}",
            "--set", "hold_s=300",
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
    (tmp_path / "cfg.toml").write_text(
        '[inputs.fit]\npath = "fit.csv"\n\n[[stages]]\ntype = "temperature"\nsensor = "gyro"\n'
        'model = "lag"\n\n[output]\ndir = "run"\nrerun = false\nreport = false\napply_to = []\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    cal = tmp_path / "run" / "calibration.json"
    proc = run_cli(
        "convert", "--calibration", cal, "--out", tmp_path / "conv", "--batch-rows", "997", log
    )
    assert proc.returncode == 0, proc.stderr
    table, _ = read_input(InputSpec(path=log))
    assert table.num_rows > 20 * 997  # many batches
    _, steps = load_calibration(cal)
    write_mcap(tmp_path / "whole.mcap", apply_chain(table, steps))
    assert raw_messages(tmp_path / "conv" / "therm.mcap") == raw_messages(tmp_path / "whole.mcap")
