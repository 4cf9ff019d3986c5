"""gyro_calibration: static_poses on simulated sessions with known truth (with and without a still
start), the direction-residual check, turntable and rotations on synthetic runs, the quaternion
composition against scipy's Rotation; gyro_bias's motion check. The real sessions run end to end in
tests/test_real_sessions.py."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imupipe.pipeline.errors import FitError
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import make_table, replace_sensor, sensor
from imupipe.stages.base import StageContext
from imupipe.stages.gyro_bias import GyroBiasStage
from imupipe.stages.multiposition import gyro_models as gm
from imupipe.stages.multiposition.accel_calibration import AccelCalibrationStage
from imupipe.stages.multiposition.gyro_calibration import GyroCalibrationStage
from imupipe.stages.steps import apply_chain

DEG = np.pi / 180
M_TRUE = np.array([[1.02, 0.004, -0.003], [-0.002, 0.98, 0.006], [0.005, -0.001, 1.01]])
B_TRUE = np.array([0.02, -0.01, 0.03])


def fit(table, **options):
    stage = GyroCalibrationStage(GyroCalibrationStage.Options(**options))
    return stage.fit(table, StageContext(name="gyro", input_name="sim", quiet=True))


def test_compose_matches_scipy_rotation_product():
    rng = np.random.default_rng(0)
    phi = rng.normal(scale=0.3, size=(2, 37, 3))
    got = gm.compose(gm.rotvec_to_quat(phi))
    for k in range(2):
        ref = Rotation.identity()
        for v in phi[k]:  # 37 rotations in the test's reference, not a hot path
            ref = ref * Rotation.from_rotvec(v)
        w, x, y, z = got[k]
        assert (Rotation.from_quat([x, y, z, w]).inv() * ref).magnitude() < 1e-12
        u = rng.normal(size=3)
        np.testing.assert_allclose(
            gm.rotate_inverse(got[k : k + 1], u[None])[0], ref.inv().apply(u)
        )


def test_static_poses_recovers_simulated_truth():
    table, truth = simulate("poses", seed=11)
    accel = AccelCalibrationStage(AccelCalibrationStage.Options(method="lm")).fit(
        table, StageContext(name="a", input_name="sim", quiet=True)
    )
    out = fit(apply_chain(table, [accel.step]), method="static_poses")
    metrics = out.results["metrics"]
    assert metrics["transitions"] == 17
    assert metrics["gravity_direction_residual_deg"]["rms"] < 0.05
    assert metrics["gravity_direction_residual_deg"]["start_rms"] > 0.5
    # the simulated gyro is in rad/s: 'before calibration' is the raw gyro's residual (its bias
    # uncorrected, so larger than the start's)
    raw = metrics["gravity_direction_residual_deg"]["raw_rms"]
    assert raw is not None and raw > metrics["gravity_direction_residual_deg"]["rms"]
    np.testing.assert_allclose(out.step.matrix, truth["gyro"]["matrix"], atol=1e-3)
    np.testing.assert_allclose(out.step.offset, truth["gyro"]["offset"], atol=1e-4)


def test_motions_that_do_not_turn_the_imu_are_refused():
    """A thermal ramp at rest (`imupipe simulate thermal`): the detector's 'poses' are drifts
    of one orientation, the motions turn nothing and the scales came out 0.0047, 1.8e-4 and 17.9
    with a residual of 0.26 deg, 'ok'. Their standard errors (30 to 860 times the scale) refuse
    it; real sessions' are under 1 %."""
    table, _ = simulate("thermal", {"rate_hz": 2.0}, seed=0)
    with pytest.raises(FitError, match=r"do not determine the gyro scale: .* % of it > 10 %"):
        fit(table, method="static_poses")


def test_two_motions_say_they_are_too_few_for_nine_parameters():
    """Two motions hold too few observations for the 9-parameter gyro model: the reason says so,
    never that the scale-only model was asked for (the default allows both)."""
    from imupipe.stages.static_detector import Intervals

    fs, g = 100.0, 9.80665
    turn = np.pi / 2  # rad/s for one second: 90 deg about x, then about y
    segments = [([0, 0, 0], 5.0), ([turn, 0, 0], 1.0), ([0, 0, 0], 5.0), ([0, turn, 0], 1.0)]
    segments.append(([0, 0, 0], 5.0))
    gyro = np.vstack([np.tile(w, (int(sec * fs), 1)) for w, sec in segments])
    up = [Rotation.identity(), Rotation.from_rotvec([turn, 0, 0])]
    up.append(up[1] * Rotation.from_rotvec([0, turn, 0]))
    accel = np.vstack(
        [np.tile(r.inv().apply([0, 0, g]), (600 if i < 2 else 500, 1)) for i, r in enumerate(up)]
    )
    accel = accel[: len(gyro)]
    t_s = np.arange(len(gyro)) / fs
    intervals = Intervals(np.array([0, 600, 1200]), np.array([500, 1100, 1700]))
    moves = gm.PoseTransitions.build(t_s, gyro, accel, intervals)
    out = gm.fit_static_poses(moves, np.zeros(3))
    assert out["fit"].name == "scale-only"
    assert out["reason"] == "2 motions: the 9-parameter model needs at least 3", out["reason"]


def synthetic(segments: list[tuple[np.ndarray, float]], fs: float = 100.0):
    """Raw gyro for piecewise-constant true rates: [(w (3,) rad/s, seconds)], raw = M w + b."""
    w = np.vstack([np.tile(rate, (int(round(sec * fs)), 1)) for rate, sec in segments])
    t_ns = np.round(np.arange(len(w)) * 1e9 / fs).astype(np.int64)
    raw = w @ M_TRUE.T + B_TRUE
    accel = np.tile([0.0, 0.0, 9.80665], (len(w), 1))
    return make_table(t_ns, gyro=raw, accel=accel), w


def test_turntable_scale_from_plus_minus_runs():
    r1, r2 = 50 * DEG, 100 * DEG
    plan = [(np.zeros(3), 2.0)]
    runs = []
    t = 2.0
    for axis, name in enumerate("xyz"):
        for rate, rate_dps in ((r1, 50.0), (r2, 100.0)):
            e = np.eye(3)[axis]
            plan += [(rate * e, 2.0), (-rate * e, 2.0)]
            runs.append(
                {
                    "axis": name,
                    "rate_dps": rate_dps,
                    "plus": [t + 0.1, t + 1.9],
                    "minus": [t + 2.1, t + 3.9],
                }
            )
            t += 4.0
    table, _ = synthetic(plan)
    out = fit(table, method="turntable", runs=runs)
    np.testing.assert_allclose(out.results["sensitivity"], M_TRUE, atol=1e-12)
    np.testing.assert_allclose(out.step.offset, B_TRUE, atol=1e-12)
    np.testing.assert_allclose(out.step.matrix, np.linalg.inv(M_TRUE), atol=1e-12)
    assert [r["scale"] for r in out.results["runs"][:2]] == pytest.approx([1.02, 1.02])
    with pytest.raises(FitError, match="needs runs"):
        fit(table, method="turntable")


def test_rotations_recover_sensitivity_from_full_turns():
    rate = 90 * DEG  # 4 s per 360 deg turn
    plan = [(np.zeros(3), 3.0)]
    for axis in range(3):
        plan += [(rate * np.eye(3)[axis], 4.0), (np.zeros(3), 1.0)]
    table, _ = synthetic(plan)
    segments = {"x": [2.995, 6.995], "y": [7.995, 11.995], "z": [12.995, 16.995]}
    out = fit(table, method="rotations", segments=segments, init_static_s=2.9)
    np.testing.assert_allclose(out.results["sensitivity"], M_TRUE, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.step.offset, B_TRUE, atol=1e-12)
    with pytest.raises(FitError, match="segments"):
        fit(table, method="rotations", segments={"x": [0.0, 1.0]})


def test_static_poses_without_a_still_start():
    """A session recorded the usual way (no long rest at the start): the bias comes from the
    static intervals, and the calibration still recovers the truth."""
    table, truth = simulate("poses", {"init_static_s": 0.0}, seed=12)
    accel = AccelCalibrationStage(AccelCalibrationStage.Options()).fit(
        table, StageContext(name="a", input_name="sim", quiet=True)
    )
    out = fit(apply_chain(table, [accel.step]))
    assert out.results["bias_from"] == "mean over the 18 static intervals"
    assert out.results["model"]["chosen"] == "9-parameter"
    np.testing.assert_allclose(out.step.matrix, truth["gyro"]["matrix"], atol=1e-3)
    np.testing.assert_allclose(out.step.offset, truth["gyro"]["offset"], atol=1e-4)
    se = out.results["standard_errors"]
    assert len(se["scale"]) == 3 and set(se["misalignment_rad"]) == {
        "yz",
        "zy",
        "zx",
        "xz",
        "xy",
        "yx",
    }


def test_gyro_fit_that_does_not_chain_the_poses_is_not_applied():
    """A gyro whose z axis is dead (reads 0) cannot carry one pose onto the next: the dead-axis
    check names it and stops the stage, and so does the direction-residual check with the
    figure, unless accepted (issue 37)."""
    table, _ = simulate("poses", seed=13)
    accel = AccelCalibrationStage(AccelCalibrationStage.Options()).fit(
        table, StageContext(name="a", input_name="sim", quiet=True)
    )
    corrected = apply_chain(table, [accel.step])
    gyro = sensor(corrected, "gyro").values
    dead = replace_sensor(corrected, "gyro", np.arange(len(gyro)), gyro * [1.0, 1.0, 0.0])
    with pytest.raises(FitError, match=r"input 'sim': gyro z \(always 0.0\): a dead axis"):
        fit(dead)
    ctx = StageContext(name="gyro", input_name="sim", quiet=True, accept_failed_checks=True)
    GyroCalibrationStage(GyroCalibrationStage.Options()).fit(dead, ctx)
    assert "gyro z (always 0.0): a dead axis" in ctx.failed_checks[0]
    assert ctx.failed_checks[1].startswith("gravity-direction residual")


def test_gyro_bias_on_a_recording_that_moves(tmp_path, cli):
    """gyro_bias on data that moves: one line naming the motion against its threshold, exit 2,
    nothing written; with accept_failed_checks = true the bias is used, the warning and the
    failed check are in calibration.json and the corrected MCAP is written."""
    table, _ = simulate("poses", {"n_poses": 4}, seed=14)
    log = tmp_path / "moving.csv"
    write_log(log, table)
    cfg = tmp_path / "cfg.toml"
    body = '[inputs.m]\npath = "moving.csv"\n[[stages]]\ntype = "gyro_bias"\n{extra}\n[output]\ndir = "out"\nrerun = false\n'
    cfg.write_text(body.format(extra=""))
    done = cli("run", cfg)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "imupipe: error: stage 'gyro_bias' on input 'm': motion in the bias recording: 1 s gyro "
        "means depart"
    )
    assert "(motion_threshold 0.02 rad/s)" in lines[0] and "accept_failed_checks = true" in lines[0]
    assert not (tmp_path / "out").exists()
    cfg.write_text(body.format(extra="accept_failed_checks = true"))
    done = cli("run", cfg, "--quiet")
    assert done.returncode == 0, done.stderr
    doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert doc["results"]["gyro_bias"]["failed_checks"][0].startswith("motion in the bias")
    assert doc["results"]["gyro_bias"]["metrics"]["static"] is False
    assert (tmp_path / "out" / "m.mcap").exists()


def test_gyro_bias_refuses_a_real_robot_that_moves():
    """The Phidgets bag (an IMU turned by hand, upside down): main warned '1 s gyro means depart
    0.595 rad/s' and applied the bias; now the stage stops."""
    from imupipe.readers.dispatch import read_input

    from conftest import shared_path

    bag = shared_path("logs", "madgwick_phidgets_imu_upside_down.bag")
    spec = InputSpec(path=bag, name="phidgets")
    table, _ = read_input(spec)
    stage = GyroBiasStage(GyroBiasStage.Options())
    with pytest.raises(FitError, match=r"1 s gyro means depart 0.595 rad/s"):
        stage.fit(table, StageContext(name="gyro_bias", input_name="phidgets", quiet=True))


def test_turns_sampled_as_a_gyro_outputs_them_give_unbiased_scales():
    """Issue 25: a nearly noise-free session with 1 s turns at 100 Hz. The simulator's gyro
    sample is the mean rate over its sample period (what an anti-alias filter or a delta-angle
    output gives); sampled at instants, the turns' steps of angular acceleration made every scale
    82 ppm high. The fit now recovers the scales to a few ppm, and states the degrees of freedom
    of its standard errors."""
    params = {"init_static_s": 0.0, "move_s": 1.0, "gyro_N": 1e-6, "accel_N": 1e-5}
    table, truth = simulate("poses", params, seed=11)
    accel = AccelCalibrationStage(AccelCalibrationStage.Options()).fit(
        table, StageContext(name="a", input_name="sim", quiet=True)
    )
    out = fit(apply_chain(table, [accel.step]))
    error = np.asarray(out.results["scale"]) - np.asarray(truth["gyro"]["scale"])
    assert np.abs(error).max() < 5e-6, error
    metrics = out.results["metrics"]
    assert metrics["degrees_of_freedom"] == 2 * metrics["transitions"] - 9
