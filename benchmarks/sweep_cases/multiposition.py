"""Multi-position sessions (``imupipe simulate poses``) through ``accel_calibration`` and then
``gyro_calibration`` with default options: 6 to 40 poses, holds of 1 to 30 s, moves of 1 to 5 s,
with and without a still start, clustered poses, misalignment 0 to 2 deg, scale errors to 15 %,
consumer to tactical noise, and truths the models do not have (a hand's tremor, a quadratic
scale error, drifting biases, a g-sensitive gyro).

Accelerometer: the error is the RMS over 200 orientations of the calibrated | |a| - g | against
the truth's (mg); the stated 95 % bound is the stage's ``error_95_mg``; within tolerance when the
error is at most twice that bound. Gyroscope: the error is the largest scale error (ppm); the
stated 95 % interval is Student's t quantile ``t(1 - 0.05 / 6, dof)`` (2.39 for many degrees of
freedom; three axes jointly 95 %) times the standard error per axis, with ``dof`` the residual's
degrees of freedom the standard errors come from (``metrics.degrees_of_freedom``); within
tolerance when every axis is within 5 standard errors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.stats import t as student_t

from imupipe.pipeline.simulate import simulate
from imupipe.stages.base import StageContext
from imupipe.stages.multiposition import accel_models as am
from imupipe.stages.multiposition.accel_calibration import AccelCalibrationStage
from imupipe.stages.multiposition.gyro_calibration import GyroCalibrationStage
from sweep_cases import judge

FAMILY = "multi-position"
DEG = np.pi / 180
TOLERANCE = 2.0
"""An answer is within tolerance when its error is at most this many times the stated 95 %
bound."""
FEW = (r"pose coverage", r"too few static poses")
"""The refusals a session with few or short poses may get (each says what to record)."""


def misalignment(deg: float) -> list[float]:
    """Three angles of about ``deg`` (rad), alternating in sign, as issue 25's sessions."""
    return (np.array([0.9, -1.0, 1.1]) * deg * DEG).tolist()


BASE: dict[str, Any] = {
    "init_static_s": 0.0,
    "pose_s": 6.0,
    "move_s": 3.0,
    "n_poses": 18,
    "accel_misalignment": misalignment(0.6),
    "accel_scale": [1.01, 0.99, 1.005],
    "accel_N": 1.0e-3,
}

CASES: list[tuple[str, dict[str, Any], tuple[str, ...], bool]] = [
    # (case, parameters over BASE, causes it may be refused for, in the quick subset)
    ("6 faces (PX4/ArduPilot)", {"n_poses": 6, "only_faces": True}, (), True),
    (
        "6 faces, 30 s holds, still start",
        {"n_poses": 6, "only_faces": True, "pose_s": 30.0, "init_static_s": 40.0},
        (),
        False,
    ),
    ("7 poses (six faces and one more)", {"n_poses": 7}, FEW, False),
    ("8 poses", {"n_poses": 8}, FEW, False),
    ("9 poses", {"n_poses": 9}, (r"pose coverage: .*misaligned",), True),
    ("10 poses", {"n_poses": 10}, FEW, False),
    ("12 poses", {"n_poses": 12}, (), True),
    ("15 poses", {"n_poses": 15}, (), False),
    ("24 poses", {"n_poses": 24}, (), False),
    ("40 poses, 2 s holds, 1 s moves", {"n_poses": 40, "pose_s": 2.0, "move_s": 1.0}, (), False),
    (
        "18 poses, 1 s holds",
        {"pose_s": 1.0},
        (*FEW, r"gravity-direction residual .*motion inside the static intervals"),
        False,
    ),
    ("18 poses, 2 s holds", {"pose_s": 2.0}, (), True),
    ("12 poses, 30 s holds", {"n_poses": 12, "pose_s": 30.0}, (), False),
    ("18 poses, 5 s moves", {"move_s": 5.0}, (), False),
    ("18 poses, 40 s still start", {"init_static_s": 40.0}, (), False),
    ("18 poses clustered within 30 deg", {"cluster_deg": 30.0}, FEW, True),
    ("18 poses, no misalignment", {"accel_misalignment": [0.0, 0.0, 0.0]}, (), False),
    ("18 poses, 2 deg misalignment", {"accel_misalignment": misalignment(2.0)}, (), False),
    ("18 poses, scale errors 15 %", {"accel_scale": [1.15, 0.9, 1.05]}, (), False),
    ("18 poses, consumer noise", {"accel_N": 3.0e-3, "gyro_N": 3.0e-4}, (), False),
    ("12 poses, tactical noise", {"n_poses": 12, "accel_N": 2.5e-4, "gyro_N": 1.5e-5}, (), True),
    (
        "18 poses, a hand's tremor and truths not in the model",
        {
            "tremor_deg": 0.05,
            "accel_nonlinearity": [1e-4, -5e-5, 8e-5],
            "accel_bias_rw": 1e-4,
            "gyro_bias_rw": 1e-5,
        },
        (),
        False,
    ),
]


def accel_error_mg(matrix: np.ndarray, offset: np.ndarray, truth: dict[str, Any]) -> float:
    """RMS over the sphere of the calibrated | |a| - g | of the truth's raw readings (mg)."""
    g = truth["gravity"]
    true_m = np.asarray(truth["accel"]["matrix"])
    raw = (g * am.SPHERE) @ np.linalg.inv(true_m).T + np.asarray(truth["accel"]["offset"])
    cal = (raw - offset) @ np.asarray(matrix).T
    return float(np.sqrt(np.mean(((np.linalg.norm(cal, axis=1) - g) / am.MG) ** 2)))


def run_case(params: dict[str, Any], seed: int) -> tuple[dict[str, Any], Any]:
    """Accel then gyro on one simulated session: (accel answer, gyro attempt)."""
    table, truth = simulate("poses", params, seed=seed)
    ctx = StageContext(name="accel_calibration", input_name="sweep", quiet=True)
    out = AccelCalibrationStage(AccelCalibrationStage.Options()).fit(table, ctx)
    m = out.results["metrics"]
    err = accel_error_mg(out.step.matrix, out.step.offset, truth)
    bound = m["error_95_mg"] if m["error_95_mg"] is not None else float("inf")
    accel = {
        "ok": err <= TOLERANCE * bound,
        "error": f"|a| {err:.3g} mg ({out.results['model']['chosen']})",
        "stated": f"<= {bound:.3g} mg",
        "covered": err <= bound,
    }

    def gyro() -> dict[str, Any]:
        corrected = out.step.apply(table)
        gctx = StageContext(name="gyro_calibration", input_name="sweep", quiet=True)
        res = GyroCalibrationStage(GyroCalibrationStage.Options()).fit(corrected, gctx).results
        scale = np.asarray(res["scale"])
        std = np.asarray(res["standard_errors"]["scale"])
        diff = scale - np.asarray(truth["gyro"]["scale"])
        z = np.abs(diff) / std
        dof = res["metrics"]["degrees_of_freedom"]
        k = float(student_t.ppf(1 - 0.05 / 6, dof)) if dof > 0 else np.inf
        return {
            "ok": bool(np.all(z <= 5.0)),
            "error": f"scale {1e6 * np.abs(diff).max():.3g} ppm ({res['model']['chosen']})",
            "stated": f"+-{1e6 * k * std.max():.3g} ppm",
            "covered": bool(np.all(z <= k)),
        }

    return accel, gyro


def run(quick: bool) -> list[dict[str, Any]]:
    rows = []
    seeds = (11,) if quick else (11, 12)
    for case, over, causes, in_quick in CASES:
        if quick and not in_quick:
            continue
        for seed in seeds:
            name = f"{case} (seed {seed})"
            params = {**BASE, **over}
            state: dict[str, Any] = {}

            def accel(params: dict[str, Any] = params, seed: int = seed, state=state):
                state["accel"], state["gyro"] = run_case(params, seed)
                return state["accel"]

            rows.append(judge(FAMILY, "accel: " + name, accel, causes))
            if "gyro" in state:
                rows.append(judge(FAMILY, "gyro: " + name, state["gyro"], causes))
    return rows
