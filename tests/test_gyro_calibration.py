"""gyro_calibration: static_poses on a simulated session with known truth, turntable and rotations
on synthetic runs, and the quaternion composition against scipy's Rotation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imupipe.pipeline.errors import FitError
from imupipe.pipeline.simulate import simulate
from imupipe.readers.table import make_table
from imupipe.stages import gyro_models as gm
from imupipe.stages.accel_calibration import AccelCalibrationStage
from imupipe.stages.base import StageContext
from imupipe.stages.gyro_calibration import GyroCalibrationStage
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
    np.testing.assert_allclose(out.step.matrix, truth["gyro"]["matrix"], atol=1e-3)
    np.testing.assert_allclose(out.step.offset, truth["gyro"]["offset"], atol=1e-4)


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
