"""The ``allan`` stage on the five real ROS 1 bags of ../shared/data/logs (imu_tools,
robot_localization; GPL/BSD, read from shared): jittered stamps and lost samples are told apart,
every bag runs with default options to an answer or to a one-line refusal naming the motion
figure, and with ``accept_failed_checks = true`` to an answer with warnings."""

from __future__ import annotations

import functools

import pytest

from imupipe.pipeline.exports.kalibr import noise_yaml
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.stages.allan.stage import AllanStage
from imupipe.stages.base import StageContext
from imupipe.stages.errors import FitError

from conftest import run_cli, shared_path

BAGS = {  # bag: (missing samples counted, gaps filled, longest stretch's IMU samples)
    "madgwick_ardrone_imu": (101, 74, 2766),  # a 1 s gap at 34 s: the last 57 s are used
    "madgwick_phidgets_imu_upside_down": (97, 96, 13964),
    "madgwick_sparkfun_razor": (0, 0, 2144),
    "rl_test1": (0, 0, 11865),
    "rl_test2": (0, 0, 3061),
}


@functools.cache
def bag_table(bag: str):
    return read_input(InputSpec(path=shared_path("logs", f"{bag}.bag")))[0]


def allan(bag: str, accept: bool):
    table = bag_table(bag)
    ctx = StageContext(name="allan", input_name=bag, quiet=True, accept_failed_checks=accept)
    return AllanStage(AllanStage.Options()).fit(table, ctx), ctx


@pytest.mark.parametrize("bag", list(BAGS))
def test_every_bag_runs_or_is_refused_for_motion(bag):
    """All five bags move (a drone, a hand-held Razor, two driving robots, a Phidgets IMU
    turning at up to 0.6 rad/s): the default refuses each with the motion figure, never with
    a gap or a jittered stamp; accepted, each gives every term of every axis."""
    with pytest.raises(FitError, match=r"1 s gyro means depart \d.* rad/s from the mean"):
        allan(bag, accept=False)
    out, ctx = allan(bag, accept=True)
    m = out.results["metrics"]
    assert (m["missing_samples"], m["gaps_filled"], m["samples"]) == BAGS[bag]
    assert m["static"] is False and any("two hours" in w for w in ctx.warnings)
    assert not any("2.0 > 2.0" in w or "time jump" in w for w in ctx.warnings)
    for sensor in ("gyro", "accel"):
        for axis in "xyz":
            terms = out.results[sensor][axis]
            assert set(terms) == {"Q", "N", "B", "K", "R"} and max(terms.values()) > 0
    assert "accelerometer_noise_density" in noise_yaml("allan", out.results)


def test_phidgets_jitter_is_not_a_gap():
    """The Phidgets bag's stamps jitter (steps of 1.66 + 0.34 periods, 0.18 to 2.7 periods in
    all) and 97 samples are lost (steps of two periods between steps of one): 97 slots filled,
    the mean rate over the slots of the nominal clock 250.0 Hz (over the stamps: 248.3 Hz)."""
    out, ctx = allan("madgwick_phidgets_imu_upside_down", accept=True)
    m = out.results["metrics"]
    assert m["rate_hz"] == pytest.approx(250.0, abs=0.01)
    assert 0.05 < m["timestamp_jitter"] < 0.08
    (warning,) = [w for w in ctx.warnings if "missing" in w]
    assert warning.startswith("97 IMU samples missing in 96 gap(s) (0.69 % of the 250 Hz clock")


def test_cli_refusal_is_one_line(tmp_path):
    bag = shared_path("logs", "madgwick_phidgets_imu_upside_down.bag")
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.log]\npath = "{bag}"\n\n[[stages]]\ntype = "allan"\n\n'
        '[output]\ndir = "out"\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 2
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("imupipe: error: stage 'allan' on input 'log': the data does not look")
    assert "0.595 rad/s" in line and "accept_failed_checks = true" in line
    assert not (tmp_path / "out").exists()
