"""Magnetometer tumbles (``imupipe simulate mag``) through ``mag_calibration`` with default
options: full and partial coverage (a part of a tumble, a turn on a table), noise from a good
sensor's 0.1 uT to a phone's 2 uT per sample, raw counts, and a second field (the recording
carried on near steel: half the samples see another field).

The error is the RMS over 200 directions of the calibrated field's norm about its mean, in % of
it, for the truth's field in every orientation (the shape a heading depends on: 1 % is at most
0.6 deg of heading); within tolerance at most :data:`TOLERANCE_PCT`. The stage states the
standard errors of its offsets and soft-iron scales (``metrics.standard_errors``: the fit's
Jacobian and residual); covered when all six are within :data:`Z95` standard errors of the
truth. Refusals of partial coverage must name the
orientations; of a second field, the field that changed.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from imupipe.pipeline.simulate import simulate
from imupipe.readers.table import make_table, sensor
from imupipe.stages.base import StageContext
from imupipe.stages.magnetometer.calibration import MagCalibrationStage
from imupipe.stages.multiposition import accel_models as am
from sweep_cases import judge

FAMILY = "magnetometer"
TOLERANCE_PCT = 1.0
COVERAGE = (r"covers too few orientations", r"did not turn")
SECOND_FIELD = (r"not one ellipsoid", r"field that changed")

CASES: list[tuple[str, dict[str, Any], dict[str, Any], tuple[str, ...], bool]] = [
    # (case, simulation parameters, post-processing, causes it may be refused for, quick)
    ("full tumble, 0.1 uT noise", {}, {}, (), True),
    ("full tumble, 2 uT noise (a phone)", {"mag_noise": 2.0e-6}, {}, (), True),
    (
        "full tumble, 0.5 uT noise, 20 s at 50 Hz",
        {"mag_noise": 5.0e-7, "duration_s": 20.0, "rate_hz": 50.0},
        {},
        COVERAGE,
        False,
    ),
    ("turned on a table only (planar)", {"motion": "planar"}, {}, COVERAGE, True),
    ("the first 8 s of a tumble (partial)", {}, {"keep_s": 8.0}, COVERAGE, True),
    ("the first 20 s of a tumble (partial)", {}, {"keep_s": 20.0}, COVERAGE, False),
    ("a hemisphere of orientations only", {}, {"cap_deg": 90.0}, COVERAGE, True),
    ("a 45 deg cap of orientations only", {}, {"cap_deg": 45.0}, COVERAGE, False),
    ("a second field for the second half", {}, {"second_field": True}, SECOND_FIELD, True),
    ("raw counts (0.15 uT/LSB)", {}, {"counts": 0.15e-6}, (), False),
]


def recording(params: dict[str, Any], post: dict[str, Any], seed: int):
    table, truth = simulate("mag", params, seed=seed)
    mag = sensor(table, "mag")
    t_ns, values = mag.t_ns, mag.values.copy()
    if "keep_s" in post:
        keep = (t_ns - t_ns[0]) * 1e-9 <= post["keep_s"]
        t_ns, values = t_ns[keep], values[keep]
    if "cap_deg" in post:  # only the orientations whose body field is within a cap
        t = truth["mag"]
        body = (values - np.asarray(t["hard_iron"])) @ np.linalg.inv(np.asarray(t["soft_iron"])).T
        unit = body / np.linalg.norm(body, axis=1, keepdims=True)
        keep = unit @ unit.mean(axis=0) / np.linalg.norm(unit.mean(axis=0)) >= np.cos(
            np.radians(post["cap_deg"])
        )
        t_ns, values = t_ns[keep], values[keep]
    if post.get("second_field"):  # another field (40 % weaker, turned 40 deg) from half time
        half = len(values) // 2
        t = truth["mag"]
        a = np.asarray(t["soft_iron"])
        body = (values[half:] - np.asarray(t["hard_iron"])) @ np.linalg.inv(a).T
        turn = Rotation.from_rotvec([0.0, np.radians(40.0), 0.0]).as_matrix()
        values[half:] = (0.6 * body @ turn.T) @ a.T + np.asarray(t["hard_iron"])
    if "counts" in post:
        values = np.round(values / post["counts"])
    return make_table(t_ns, mag=values, metadata={}), truth


def shape_error_pct(matrix: np.ndarray, offset: np.ndarray, truth: dict[str, Any], scale: float):
    """RMS over the sphere of the calibrated norm about its mean (%), for the truth's field."""
    t = truth["mag"]
    body = t["field_norm"] * am.SPHERE
    raw = (body @ np.asarray(t["soft_iron"]).T + np.asarray(t["hard_iron"])) / scale
    norm = np.linalg.norm((raw - offset) @ np.asarray(matrix).T, axis=1)
    return float(100 * np.sqrt(np.mean((norm / norm.mean() - 1) ** 2)))


Z95 = 2.64
"""The six offsets and scales jointly at 95 %: each within 2.64 standard errors (Sidak,
1 - 0.05 / 12 two-sided per parameter)."""


def coverage(results: dict[str, Any], truth: dict[str, Any], scale: float) -> tuple[Any, float]:
    """Per-parameter errors in standard errors (offset x, y, z, soft-iron diagonal x, y, z) of
    the stage's fit against the truth, and the largest. The truth's correction shape is the
    symmetric ``(A A')^-1/2`` of the soft iron ``A``, to unit determinant."""
    t = truth["mag"]
    a = np.asarray(t["soft_iron"])
    values, vectors = np.linalg.eigh(a @ a.T)
    w = vectors @ np.diag(values**-0.5) @ vectors.T
    true = np.concatenate(
        [np.asarray(t["hard_iron"]) / scale, np.diag(w) / np.linalg.det(w) ** (1 / 3)]
    )
    got = np.concatenate([results["centre"], results["metrics"]["soft_iron_diagonal"]])
    se = results["metrics"]["standard_errors"]
    z = np.abs(got - true) / np.concatenate([se["offset"], se["soft_iron_diagonal"]])
    return z, float(z.max())


def run(quick: bool) -> list[dict[str, Any]]:
    rows = []
    seeds = (31,) if quick else (31, 32)
    for case, params, post, causes, in_quick in CASES:
        if quick and not in_quick:
            continue
        for seed in seeds:

            def attempt(params=params, post=post, seed=seed) -> dict[str, Any]:
                table, truth = recording(params, post, seed)
                ctx = StageContext(name="mag_calibration", input_name="sweep", quiet=True)
                out = MagCalibrationStage(MagCalibrationStage.Options()).fit(table, ctx)
                err = shape_error_pct(
                    out.step.matrix, out.step.offset, truth, post.get("counts", 1.0)
                )
                scale = post.get("counts", 1.0)
                m = out.results["metrics"]
                z, worst = coverage(out.results, truth, scale)
                se = m["standard_errors"]
                return {
                    "ok": err <= TOLERANCE_PCT,
                    "error": f"|h| {err:.3g} %; offset, scales at {worst:.2g} SE",
                    "stated": (
                        f"+-{Z95 * max(se['offset']) * scale * 1e6:.2g} uT, "
                        f"+-{Z95 * 100 * max(se['soft_iron_diagonal']):.2g} %"
                    ),
                    "covered": bool(worst <= Z95),
                }

            rows.append(judge(FAMILY, f"{case} (seed {seed})", attempt, causes))
    return rows
