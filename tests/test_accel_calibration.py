"""accel_calibration: simulated truth (held-out session), imu_tk's Xsens raw counts, imucal's
Ferraris snapshot, the T265 session, and the errors that say why a fit cannot be trusted."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from imupipe.pipeline.errors import FitError
from imupipe.pipeline.run import run
from imupipe.pipeline.simulate import simulate
from imupipe.readers.table import sensor
from imupipe.stages import accel_models as am
from imupipe.stages.accel_calibration import AccelCalibrationStage
from imupipe.stages.base import StageContext

from conftest import TEST_DATA, shared_path

G = 9.80665


@pytest.fixture(scope="module")
def sessions():
    train = simulate("poses", seed=1)
    held_out = simulate("poses", {"faces": False}, seed=2)
    return train, held_out


def fit(table, **options):
    stage = AccelCalibrationStage(AccelCalibrationStage.Options(**options))
    return stage.fit(table, StageContext(name="accel", input_name="sim", quiet=True))


def held_out_rms_mg(apply, session) -> float:
    """| |a| - g | RMS (mg) on the means of the held-out session's true rests (1 s trimmed)."""
    table, truth = session
    acc = sensor(table, "accel")
    cal = apply(acc.values)
    means = [
        cal[(acc.t_s >= a + 0.5) & (acc.t_s <= b - 0.5)].mean(axis=0)
        for a, b in truth["static_intervals_s"]
    ]
    return float(np.sqrt(np.mean(((np.linalg.norm(means, axis=1) - G) / am.MG) ** 2)))


def test_lm_and_frank_wolfe_on_held_out_session(sessions):
    train, held_out = sessions
    raw = held_out_rms_mg(lambda v: v, held_out)
    assert raw > 5.0
    matrices = {}
    for method in ("lm", "frank_wolfe"):
        out = fit(train[0], method=method)
        assert out.results["metrics"]["intervals"] == 18
        rms = held_out_rms_mg(out.step.apply_values, held_out)
        assert rms < 0.1, (method, rms)
        np.testing.assert_allclose(out.step.matrix, train[1]["accel"]["matrix"], atol=3e-4)
        np.testing.assert_allclose(out.step.offset, train[1]["accel"]["offset"], atol=2e-3)
        matrices[method] = out.step.matrix
    np.testing.assert_allclose(matrices["lm"], matrices["frank_wolfe"], atol=1e-5)
    ctx = StageContext(name="accel", input_name="sim", quiet=True)
    stage = AccelCalibrationStage(AccelCalibrationStage.Options(method="six_position"))
    six = stage.fit(train[0], ctx)
    assert held_out_rms_mg(six.step.apply_values, held_out) < raw / 3
    assert any("misalignment is not estimated" in w for w in ctx.warnings)


def test_frank_wolfe_reports_iterations_and_stopping_rule(sessions):
    out = fit(sessions[0][0], method="frank_wolfe")
    solver = out.results["metrics"]["solver"]
    assert solver["stop"].startswith("duality gap")
    assert 1 < solver["iterations"] < 20000
    assert solver["at_box_bound"] is False


def test_jacobian_matches_finite_differences(sessions):
    table = sessions[0][0]
    acc = sensor(table, "accel").values[::500] * 1000 + 30000  # raw-count-like numbers
    problem = am.NormProblem(acc, G, am.initial_guess(acc, G))
    x = np.linspace(-0.01, 0.02, 9)
    numeric = np.array(
        [approx_fprime(x, lambda z, i=i: problem.residual(z)[i], 1e-7) for i in range(5)]
    )
    np.testing.assert_allclose(problem.jacobian(x)[:5], numeric, atol=1e-6)


def test_six_faces_only_needs_misalignment_off():
    table, truth = simulate("poses", {"n_poses": 12, "only_faces": True}, seed=5)
    with pytest.raises(FitError, match="misalignment = false"):
        fit(table, method="lm")
    out = fit(table, method="lm", misalignment=False)
    assert out.results["misalignment_rad"] == {"yz": 0.0, "zy": 0.0, "zx": 0.0}
    np.testing.assert_allclose(np.diag(out.step.matrix), truth["accel"]["scale"], rtol=2e-3)


def test_six_position_names_the_missing_face():
    table, _ = simulate("poses", {"n_poses": 9, "faces": False}, seed=6)
    with pytest.raises(FitError, match=r"six_position: no static pose with [+-][xyz]"):
        fit(table, method="six_position")


def test_too_few_intervals_is_an_error():
    table, _ = simulate("poses", {"n_poses": 5}, seed=7)
    with pytest.raises(FitError, match="too few static intervals: need at least 9"):
        fit(table, method="lm")


XSENS_CSV = """
[inputs.xsens.csv]
time = 0
time_unit = "s"
accel = [1, 2, 3]
accel_unit = "raw"
gyro_file = "{gyro}"
gyro = [1, 2, 3]
gyro_unit = "raw"
"""


def test_xsens_raw_counts_without_initial_guess(tmp_path):
    data = TEST_DATA / "imu_tk_xsens"
    cfg = tmp_path / "xsens.toml"
    cfg.write_text(
        f'[inputs.xsens]\npath = "{data / "xsens_acc.mat"}"\n'
        + XSENS_CSV.format(gyro=data / "xsens_gyro.mat")
        + """
[[stages]]
type = "accel_calibration"
method = "lm"
gravity = 9.81744
init_static_s = 50.0

[[stages]]
type = "gyro_calibration"
method = "static_poses"
gravity = 9.81744
init_static_s = 50.0

[output]
dir = "out"
rerun = false
apply_to = []
"""
    )
    doc = run(cfg, quiet=True).calibration
    accel = doc["results"]["accel_calibration"]["metrics"]
    assert accel["intervals"] >= 30
    assert accel["residual_mg"]["means_rms"] <= 0.2
    assert accel["residual_mg"]["samples_rms"] <= 1.0
    assert accel["residual_mg"]["start_means_rms"] > 1.0  # the start alone is not the answer
    gyro = doc["results"]["gyro_calibration"]["metrics"]
    assert gyro["gravity_direction_residual_deg"]["rms"] <= 0.75
    # imu_tk's nominal 1/6258 (rad/s)/count is 25 % off; the data says ~2.09e-4
    np.testing.assert_allclose(doc["results"]["gyro_calibration"]["scale"], 2.09e-4, rtol=0.02)


def test_ferraris_reproduces_imucal_snapshot(tmp_path):
    data = TEST_DATA / "imucal"
    cfg = tmp_path / "ferraris.toml"
    cfg.write_text(
        f'[inputs.session]\npath = "{data / "annotated_session.csv"}"\n'
        """
[inputs.session.csv]
rate_hz = 204.8
accel = ["acc_x", "acc_y", "acc_z"]
accel_unit = "raw"
gyro = ["gyr_x", "gyr_y", "gyr_z"]
gyro_unit = "raw"
label = "part"

[[stages]]
type = "accel_calibration"
method = "ferraris"
gravity = 9.81

[output]
dir = "out"
rerun = false
"""
    )
    summary = run(cfg, quiet=True)
    got = summary.calibration["results"]["accel_calibration"]["imucal"]
    expected = json.loads((data / "annotated_session_expected_cal.json").read_text())
    for key in ("K_a", "R_a", "b_a", "K_g", "R_g", "K_ga", "b_g"):
        e = np.asarray(expected[key])
        np.testing.assert_allclose(got[key], e, rtol=1e-6, atol=1e-6 * np.abs(e).max())
    chain = summary.calibration["chain"]
    assert [s["sensor"] for s in chain] == ["accel", "gyro"]
    acc = np.asarray(chain[0]["matrix"])
    np.testing.assert_allclose(
        acc, np.linalg.inv(np.asarray(expected["R_a"])) @ np.linalg.inv(np.asarray(expected["K_a"]))
    )


def test_t265_end_to_end_with_data_derived_start(tmp_path):
    acc_file = shared_path("calib", "imu_tk_t265_cggos", "t265_acc.mat")
    gyro_file = acc_file.with_name("t265_gyr.mat")
    shutil.copy(acc_file, tmp_path / "t265_acc.mat")
    shutil.copy(gyro_file, tmp_path / "t265_gyr.mat")
    cfg = tmp_path / "t265.toml"
    stages = """
[inputs.t265]
path = "t265_acc.mat"
[inputs.t265.csv]
time = 0
time_unit = "s"
accel = [1, 2, 3]
gyro_file = "t265_gyr.mat"
gyro = [1, 2, 3]

[[stages]]
type = "accel_calibration"
method = "lm"
gravity = 9.8016
{extra}

[[stages]]
type = "gyro_calibration"
gravity = 9.8016

[output]
dir = "out"
rerun = false
"""
    cfg.write_text(stages.format(extra=""))
    with pytest.raises(FitError, match="6 distinct poses.*misalignment = false"):
        run(cfg, quiet=True)
    cfg.write_text(stages.format(extra="misalignment = false"))
    summary = run(cfg, quiet=True)
    accel = summary.calibration["results"]["accel_calibration"]["metrics"]
    assert accel["intervals"] >= 30
    assert accel["residual_mg"]["means_rms"] < 1.0 < accel["residual_mg"]["start_means_rms"]
    gyro = summary.calibration["results"]["gyro_calibration"]["metrics"]
    assert gyro["gravity_direction_residual_deg"]["rms"] < 1.5
    assert Path(summary.out_dir / "t265.mcap").exists()
