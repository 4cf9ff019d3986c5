"""``gyro_calibration`` stage: gyroscope scale and misalignment (and bias) by ``method``:

- ``static_poses`` (Tedaldi, Pretto and Menegatti, ICRA 2014; imu_tk): the static intervals are
  detected on the accelerometer as corrected so far (same detector and threshold choice as
  ``accel_calibration``); bias = mean gyro over those intervals (or, with ``init_static_s``, over
  that initial rest as imu_tk); then the gyro model that carries the gravity direction of each
  static interval onto the next's (:mod:`imupipe.stages.multiposition.gyro_models`: nine parameters or the three
  scales, chosen by AICc unless ``misalignment`` forces one). Put it *after*
  ``accel_calibration``: the gravity directions come from the accelerometer as corrected so far.
- ``turntable``: ``runs = [{axis = "z", rate_dps = 100.0, plus = SEG, minus = SEG}]``
  where SEG is a label (``csv.label``) or ``[start_s, end_s]``; each run gives the column
  ``(out(+r) - out(-r)) / 2r`` of the sensitivity matrix M (the scale-factor formula of the
  gyroscope temperature-calibration patent; least squares over an axis's rates); bias = mean of
  the runs' midpoints; ``matrix = M^-1``. Axes without runs keep unit sensitivity.
- ``rotations`` (imucal / Ferraris): ``segments = {x = SEG, y = SEG, z = SEG}`` are turns of
  ``expected_angle_deg`` about each axis; bias from ``bias_segment`` (default: the first
  ``init_static_s`` seconds, 30 s when unset); the bias-free gyro summed over each turn and
  divided by the rate gives the columns of ``W``; ``M = W / angle``, ``matrix = M^-1``.

Correction: ``w [rad/s] = matrix @ (raw - offset)`` (``offset`` = bias, raw units).

Quality checks of ``static_poses`` (``ctx.check``): the calibrated gravity-direction residual
RMS over the motions at most :data:`MAX_DIRECTION_RESIDUAL_DEG` degrees, and each scale's
standard error at most :data:`MAX_SCALE_ERROR` of it (motions that do not turn the IMU, or not
about every axis, leave a scale undetermined however small the residual).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import SensorData, has_stream, imu_pairs, sensor
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.errors import FitError
from imupipe.stages.multiposition import gyro_models as gm
from imupipe.stages.multiposition.accel_calibration import StaticSetup, detect_intervals, rms
from imupipe.stages.static_detector import sample_clock, sample_rate, segment_mask
from imupipe.stages.steps import LinearStep

DEG = np.pi / 180
MAX_DIRECTION_RESIDUAL_DEG = 2.0
"""deg: the largest gravity-direction residual RMS of a gyro calibration that is applied."""
MAX_SCALE_ERROR = 0.1
"""The largest standard error of a fitted gyro scale, as a fraction of it (real sessions: 0.02 to
0.9 %; a log at rest: 30 to 800 times the scale)."""
ACCEL_MODELS = ["9-parameter", "6-parameter"]
"""The accelerometer models the interval detection weighs (the accelerometer is corrected
already; the models only score the thresholds)."""
GYRO_MISALIGNMENT_MODELS: dict[str, list[str]] = {
    "auto": ["9-parameter", "scale-only"],
    "true": ["9-parameter"],
    "false": ["scale-only"],
}


def imu_samples(table: pa.Table, ctx: StageContext | None = None) -> SensorData:
    """Accelerometer and gyroscope of each IMU sample side by side: values (n, 6); sampled
    apart, on the gyro's stamps (:func:`~imupipe.readers.table.imu_pairs`, its note warned)."""
    gyro, acc, note = imu_pairs(table)
    if note and ctx is not None:
        ctx.warn(note)
    return SensorData(gyro.t_ns, np.hstack([acc.values, gyro.values]), gyro.rows)


class GyroCalibrationStage(Stage):
    type = "gyro_calibration"
    sensors = ("gyro",)
    corrects = True

    @dataclass
    class Options(StaticSetup):
        method: Literal["static_poses", "turntable", "rotations"] = "static_poses"
        """``static_poses`` (the rotations between the still poses of a multi-position session
        carry one pose's gravity direction onto the next: Tedaldi et al., ICRA 2014),
        ``turntable`` (runs at +rate and -rate about each axis, ``runs``) or ``rotations`` (one
        full turn about each axis, ``segments``, as imucal's Ferraris method)."""
        gravity: float = 9.80665
        """static_poses: local g, m/s^2 (only used to choose the static threshold)."""
        misalignment: Literal["auto"] | bool = "auto"
        """static_poses: fit the six gyro misalignment angles (true), only the three scales
        (false), or let the motions decide by AICc ("auto")."""
        runs: list[dict] = field(default_factory=list)
        """turntable: [{axis, rate_dps, plus, minus}]; plus/minus a label or [start_s, end_s]."""
        segments: dict[str, Any] = field(default_factory=dict)
        """rotations: axis (x, y, z) -> a label or [start_s, end_s] of one turn about it."""
        expected_angle_deg: float = 360.0
        """rotations: the signed angle of each turn (imucal's clockwise convention: -360)."""
        bias_segment: str | list[float] | None = None
        """rotations: the static segment giving the bias (default the first init_static_s s, 30
        s when unset)."""

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        if not has_stream(table, "imu"):
            raise ctx.fail("the input has no gyroscope samples")
        if self.options.method == "static_poses":
            # accelerometer and gyroscope side by side: values (n, 6)
            gyro = ctx.finite(
                imu_samples(table, ctx),
                "IMU (accelerometer and gyroscope)",
                minimum=2,
                axes=[f"{s} {a}" for s in ("accel", "gyro") for a in "xyz"],
            )
        else:
            gyro = ctx.finite(sensor(table, "gyro"), "gyroscope", minimum=2)
        for k, name in enumerate(("accel", "gyro") if gyro.values.shape[1] == 6 else ("gyro",)):
            part = gyro.values[:, 3 * k : 3 * k + 3]
            ctx.dead_axes(SensorData(gyro.t_ns, part, gyro.rows), name)  # coupled axes
        labels = (
            table.column("label").take(pa.array(gyro.rows))
            if "label" in table.column_names
            else None
        )
        method = {
            "static_poses": self._static_poses,
            "turntable": self._turntable,
            "rotations": self._rotations,
        }[self.options.method]
        try:
            matrix, bias, results = method(table, gyro, labels, ctx)
        except FitError as exc:
            raise ctx.fail(str(exc)) from None
        if not np.isfinite(matrix).all() or abs(np.linalg.det(matrix)) < 1e-300:
            raise ctx.fail("the fitted gyro matrix is singular or not finite")
        if self.options.method == "static_poses":
            residual = results["metrics"]["gravity_direction_residual_deg"]["rms"]
            ctx.check(
                residual <= MAX_DIRECTION_RESIDUAL_DEG,
                f"gravity-direction residual {residual:.3g} deg RMS over "
                f"{results['metrics']['transitions']} motions > {MAX_DIRECTION_RESIDUAL_DEG:g} "
                "deg: the calibrated gyro does not carry one pose onto the next (motion inside "
                "the static intervals, a wrong clock, or an uncalibrated accelerometer; hold each "
                "pose still for 2 s or more)",
            )
            scale, std = results["scale"], results["standard_errors"]["scale"]
            worst = int(np.argmax(np.abs(std) / np.abs(scale)))
            relative = abs(std[worst] / scale[worst])
            ctx.check(
                relative <= MAX_SCALE_ERROR,
                f"the motions do not determine the gyro scale: {'xyz'[worst]}'s standard error is "
                f"{100 * relative:.3g} % of it > {100 * MAX_SCALE_ERROR:g} % (turn the IMU about "
                "every axis between the poses, by tens of degrees)",
            )
        step = LinearStep(
            type=self.type,
            sensor="gyro",
            matrix=matrix,
            offset=bias,
            params={"method": self.options.method},
        )
        return StageOutput(results={"method": self.options.method, **results}, step=step)

    # -- methods -----------------------------------------------------------------------------
    def _static_poses(
        self, table: pa.Table, both: SensorData, labels: Any, ctx: StageContext
    ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """``both``: the finite IMU samples, accelerometer and gyroscope side by side."""
        o = self.options
        acc_values, gyro_values = both.values[:, :3], both.values[:, 3:]
        norm = float(np.median(np.linalg.norm(acc_values, axis=1)))
        if abs(norm - o.gravity) > 0.05 * o.gravity:
            ctx.warn(
                f"the accelerometer norm is {norm:.4g}, not about g = {o.gravity}: is it "
                "calibrated? (put accel_calibration before gyro_calibration)"
            )
        found = detect_intervals(both.t_ns, acc_values, o, o.gravity, ACCEL_MODELS)
        intervals, poses = found.intervals, found.poses
        if o.init_static_s is None:
            bias = gyro_values[intervals.mask(len(both))].mean(axis=0)
            bias_from = f"mean over the {len(intervals)} static intervals"
        else:
            bias = gyro_values[both.t_s <= o.init_static_s].mean(axis=0)
            bias_from = f"mean over the first init_static_s = {o.init_static_s:g} s"
        t_s, clock_note = sample_clock(both.t_ns)
        if clock_note:
            ctx.warn(clock_note)
        moves = gm.PoseTransitions.build(t_s, gyro_values, acc_values, poses)
        models = GYRO_MISALIGNMENT_MODELS[str(o.misalignment).lower()]
        fit = gm.fit_static_poses(moves, bias, models)
        chosen: gm.GyroFit = fit["fit"]
        after, before = fit["residual_deg"], fit["residual_deg_start"]
        self._record_transitions(ctx, before, after)
        std = chosen.standard_errors()
        angle_names = ("yz", "zy", "zx", "xz", "xy", "yx")
        if o.misalignment == "auto" and chosen.name == "scale-only":
            ctx.warn(
                "gyro misalignment not fitted: the motions do not support the 9-parameter model, "
                f"so the three scales alone are fitted ({fit['reason']})"
            )
        results = {
            "scale": chosen.scale.tolist(),
            "misalignment_rad": dict(zip(angle_names, chosen.x[3:].tolist(), strict=True)),
            "bias": bias.tolist(),
            "bias_from": bias_from,
            "model": {
                "chosen": chosen.name,
                "reason": fit["reason"],
                "candidates": fit["candidates"],
            },
            "standard_errors": {
                "scale": (std[:3] * chosen.start_scale).tolist(),
                "misalignment_rad": dict(zip(angle_names, std[3:].tolist(), strict=True)),
            },
            "metrics": {
                "intervals": len(intervals),
                "poses": len(poses),
                "transitions": len(after),
                "threshold": found.report,
                "gravity_direction_residual_deg": {
                    "rms": rms(after),
                    "max": float(after.max()),
                    "start_rms": rms(before),
                    # the raw gyro (no bias removed, unit scale) where it is in rad/s already
                    "raw_rms": rms(moves.angles_deg(np.eye(3), np.zeros(3)))
                    if 0.8 <= fit["start_scale"] <= 1.25
                    else None,
                },
                "start_scale": fit["start_scale"],
                "condition_number": chosen.condition_number(),
                # of the residual behind the standard errors: their intervals are Student's t
                "degrees_of_freedom": chosen.n_obs - chosen.n_params,
                "function_evaluations": chosen.function_evaluations,
                "time_s": fit["time_s"],
                **({"clock": clock_note} if clock_note else {}),
            },
        }
        return chosen.matrix, bias, results

    def _turntable(
        self, table: pa.Table, gyro: SensorData, labels: Any, ctx: StageContext
    ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        if not self.options.runs:
            raise FitError("method 'turntable' needs runs = [{axis, rate_dps, plus, minus}, ...]")
        runs = []
        for i, run in enumerate(self.options.runs):
            where = f"runs[{i}]"
            if set(run) != {"axis", "rate_dps", "plus", "minus"}:
                raise FitError(f"{where}: needs exactly the keys axis, rate_dps, plus, minus")
            if run["axis"] not in ("x", "y", "z"):
                raise FitError(f"{where}.axis: '{run['axis']}' is not x, y or z")
            rate = run["rate_dps"]
            if isinstance(rate, bool) or not isinstance(rate, int | float) or rate <= 0:
                raise FitError(f"{where}.rate_dps: must be a number > 0")
            plus = gyro.values[segment_mask(gyro.t_s, labels, f"{where}.plus", run["plus"])]
            minus = gyro.values[segment_mask(gyro.t_s, labels, f"{where}.minus", run["minus"])]
            runs.append(("xyz".index(run["axis"]), rate * DEG, plus.mean(0), minus.mean(0)))
        sensitivity, bias, per_run = gm.turntable_columns(runs)
        results = {
            "sensitivity": sensitivity.tolist(),
            "bias": bias.tolist(),
            "runs": per_run,
            "metrics": {"condition_number": float(np.linalg.cond(sensitivity))},
        }
        return np.linalg.inv(sensitivity), bias, results

    def _rotations(
        self, table: pa.Table, gyro: SensorData, labels: Any, ctx: StageContext
    ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        o = self.options
        if set(o.segments) != {"x", "y", "z"}:
            raise FitError("method 'rotations' needs segments = {x = SEG, y = SEG, z = SEG}")
        if o.expected_angle_deg == 0:
            raise FitError("expected_angle_deg must not be 0")
        if o.bias_segment is None:
            bias_mask = gyro.t_s <= (30.0 if o.init_static_s is None else o.init_static_s)
        else:
            bias_mask = segment_mask(gyro.t_s, labels, "bias_segment", o.bias_segment)
        bias = gyro.values[bias_mask].mean(axis=0)
        fs = sample_rate(gyro.t_ns)
        w = np.column_stack(
            [
                (
                    gyro.values[segment_mask(gyro.t_s, labels, f"segments.{a}", o.segments[a])]
                    - bias
                ).sum(axis=0)
                / fs
                for a in "xyz"
            ]
        )
        sensitivity = w / (o.expected_angle_deg * DEG)
        scale = np.linalg.norm(sensitivity, axis=1)
        results = {
            "sensitivity": sensitivity.tolist(),
            "scale": scale.tolist(),
            "rotation": (sensitivity / scale[:, None]).tolist(),
            "bias": bias.tolist(),
            "metrics": {
                "sample_rate_hz": fs,
                "bias_samples": int(bias_mask.sum()),
                "condition_number": float(np.linalg.cond(sensitivity)),
            },
        }
        return np.linalg.inv(sensitivity), bias, results

    def _record_transitions(self, ctx: StageContext, before: np.ndarray, after: np.ndarray) -> None:
        if ctx.recorder.enabled:
            ctx.recorder.bars(
                f"/{ctx.name}/gravity_direction_residual_deg",
                np.column_stack([before, after]),
                ("start", "calibrated"),
                x_label="transition",
                unit="deg",
                title="gravity direction residual",
            )
