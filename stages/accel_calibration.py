"""``accel_calibration`` stage: accelerometer scale, non-orthogonality and bias from a
multi-position session (seeds 002 and 003; imu_tk; imucal's Ferraris).

Static intervals are detected automatically (:mod:`imupipe.stages.static_detector`; the threshold
``k`` with the lowest residual per degree of freedom of a 9-parameter fit wins). Then ``method``:

- ``six_position`` (seed 002): per axis ``b = (max + min) / 2``, ``k = 2 g / (max - min)`` over the
  static-interval means; ``matrix = diag(k)``, ``offset = b``. Needs all six faces.
- ``lm``: the 9-parameter model ``a = S K (a_t - b)`` (:mod:`imupipe.stages.accel_models`) with
  scipy's Levenberg-Marquardt.
- ``frank_wolfe``: the same model by Frank-Wolfe over a box around the data-derived start (seed 003).
- ``ferraris``: imucal's Ferraris calibration from *labelled* segments (``csv.label``; six static
  poses and three turns); adds an accelerometer and a gyroscope step (:mod:`imupipe.stages.ferraris`).

The start of lm and frank_wolfe comes from the data (bias = sphere centre of the static means,
scale = g / their median radius), so raw counts (``accel_unit = "raw"``) need no hand-made guess.
Output ``matrix``/``offset`` are SI: ``a [m/s^2] = matrix @ (raw - offset)``. Metrics in mg
(1 mg = 9.80665e-3 m/s^2) are | |a| - g | over the static intervals.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import has_stream, sensor
from imupipe.stages import accel_models as am
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.errors import FitError
from imupipe.stages.ferraris import ROTATION_PARTS, STATIC_PARTS, ferraris
from imupipe.stages.static_detector import (
    Intervals,
    choose_threshold,
    make_detector,
    sample_rate,
    segment_mask,
)
from imupipe.stages.steps import LinearStep

DEG = np.pi / 180


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def norm_residual_mg(values: np.ndarray, g: float) -> np.ndarray:
    """| |a| - g | per row of ``values`` (n, 3) m/s^2, in mg (signed)."""
    return (np.linalg.norm(values, axis=1) - g) / am.MG


@dataclass
class StaticSetup:
    """The detection options shared by the accelerometer and gyroscope stages."""

    window_s: float = 1.0
    """Variance window, s."""
    init_static_s: float = 30.0
    """Length of the initial static period (threshold reference; gyro bias), s."""
    min_interval_s: float = 1.0
    """Shortest static interval kept, s."""
    thresholds: list[float] = field(default_factory=lambda: [2, 3, 4, 5, 6, 7, 8, 9, 10])
    """Candidate k (threshold = k x variance of the initial period); the best is chosen."""


def detect_intervals(
    t_ns: np.ndarray, accel: np.ndarray, setup: Any, g: float, n_params: int
) -> tuple[Intervals, dict[str, Any]]:
    """Static intervals with the threshold chosen by the lowest residual per degree of freedom
    of an LM fit of the model (``n_params`` 9, or 6 without misalignment) on the interval means;
    at least ``n_params`` intervals."""
    detector = make_detector(
        t_ns,
        accel,
        window_s=setup.window_s,
        init_static_s=setup.init_static_s,
        min_interval_s=setup.min_interval_s,
    )

    def score(intervals: Intervals) -> float | None:
        means = intervals.means(accel)
        free = np.ones(9, dtype=bool)
        free[3:6] = n_params == 9
        try:
            problem = am.NormProblem(means, g, am.initial_guess(means, g), free)
            sol = am.solve_lm(problem, xtol=1e-8)
        except (FitError, np.linalg.LinAlgError, ValueError):
            return None
        r = problem.residual(sol.x) * g / am.MG
        dof = len(r) - n_params
        return float(r @ r) / dof if dof > 0 else 1e300

    choice = choose_threshold(detector, setup.thresholds, score, n_params)
    info = {
        "threshold_k": choice.k,
        "threshold_scores": {f"{k:g}": v for k, v in choice.scores.items()},
        "reference_variance": detector.reference,
    }
    return choice.intervals, info


class AccelCalibrationStage(Stage):
    type = "accel_calibration"
    sensors = ("accel",)
    corrects = True

    @dataclass
    class Options(StaticSetup):
        method: Literal["six_position", "lm", "frank_wolfe", "ferraris"] = "lm"
        gravity: float = 9.80665
        """Local gravity g, m/s^2."""
        misalignment: bool = True
        """lm / frank_wolfe: fit the three non-orthogonality angles (false: 6 parameters, for
        sessions whose poses are only the six faces, where misalignment is unobservable)."""
        fit_on: Literal["means", "samples"] = "means"
        """Fit on the static-interval means, or on up to ``samples_per_interval`` samples from the
        middle of each interval (imu_tk's acc_use_means = false)."""
        samples_per_interval: int = 100
        fw_box: list[float] = field(default_factory=lambda: [0.05, 0.05, 0.05])
        """Frank-Wolfe box half-widths around the start: relative scale, angles (rad), bias
        (relative to g)."""
        fw_max_iter: int = 20000
        fw_gap_rtol: float = 1e-2
        """Frank-Wolfe stops when its duality gap is below this fraction of the cost."""
        ferraris_parts: dict[str, str] | None = None
        """ferraris: imucal part name (x_p ... z_rot) -> label in the data (default: the same)."""
        ferraris_expected_angle_deg: float = -360.0
        """ferraris: the angle of each turn (imucal's default -360: clockwise)."""

    @classmethod
    def sensors_for(cls, options: Any) -> tuple[str, ...]:
        return ("accel", "gyro") if options.method == "ferraris" else cls.sensors

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        o = self.options
        if not has_stream(table, "imu"):
            raise ctx.fail("the input has no accelerometer samples")
        if not o.gravity > 0:
            raise ctx.fail(f"gravity must be > 0, got {o.gravity}")
        if o.method == "ferraris":
            return self._ferraris(table, ctx)
        acc = sensor(table, "accel")
        if not np.isfinite(acc.values).all():
            bad = int(np.flatnonzero(~np.isfinite(acc.values).all(axis=1))[0])
            raise ctx.fail(f"non-finite accelerometer sample at sample {bad}")
        g = o.gravity
        try:
            n_params = 9 if o.misalignment and o.method != "six_position" else 6
            intervals, detection = detect_intervals(acc.t_ns, acc.values, o, g, n_params)
        except FitError as exc:
            raise ctx.fail(str(exc)) from None
        means = intervals.means(acc.values)
        distinct = am.distinct_poses(means)
        start = am.initial_guess(means, g)
        results: dict[str, Any] = {"method": o.method}
        metrics: dict[str, Any] = {
            "intervals": len(intervals),
            "distinct_poses": distinct,
            **detection,
        }
        try:
            params, solver = self._solve(means, acc.values, intervals, start, ctx, metrics)
        except FitError as exc:
            raise ctx.fail(str(exc)) from None
        if solver:
            metrics["solver"] = solver

        inside = intervals.mask(len(acc))
        per_pose = norm_residual_mg(params.apply(means), g)
        per_sample = norm_residual_mg(params.apply(acc.values[inside]), g)
        metrics["residual_mg"] = {
            "means_rms": rms(per_pose),
            "means_max": float(np.abs(per_pose).max()),
            "samples_rms": rms(per_sample),
            "start_means_rms": rms(norm_residual_mg(start.apply(means), g)),
        }
        results.update(
            {
                "scale": params.scale.tolist(),
                "misalignment_rad": dict(
                    zip(("yz", "zy", "zx"), params.angles.tolist(), strict=True)
                ),
                "bias": params.bias.tolist(),
                "gravity": g,
                "intervals_s": np.column_stack(
                    [acc.t_s[intervals.start], acc.t_s[intervals.stop - 1]]
                ).tolist(),
                "metrics": metrics,
            }
        )
        self._record(ctx, acc.t_ns, acc.values, params, intervals, per_pose, g)
        step = LinearStep(
            type=self.type,
            sensor="accel",
            matrix=params.matrix,
            offset=params.bias,
            params={
                "method": o.method,
                "scale": params.scale.tolist(),
                "misalignment_rad": params.angles.tolist(),
                "bias": params.bias.tolist(),
            },
        )
        return StageOutput(results=results, step=step)

    # -- methods -----------------------------------------------------------------------------
    def _solve(
        self,
        means: np.ndarray,
        samples: np.ndarray,
        intervals: Intervals,
        start: am.NineParams,
        ctx: StageContext,
        metrics: dict[str, Any],
    ) -> tuple[am.NineParams, dict[str, Any] | None]:
        o = self.options
        if o.method == "six_position":
            params = am.six_position(means, o.gravity)
            ctx.warn(
                "six_position fits scale and bias only: axis misalignment is not estimated "
                "(use lm or frank_wolfe on nine or more distinct poses)"
            )
            return params, None
        free = np.ones(9, dtype=bool)
        free[3:6] = o.misalignment
        if metrics["distinct_poses"] < free.sum():
            raise FitError(
                f"{metrics['distinct_poses']} distinct poses (>= 10 deg apart) in "
                f"{len(intervals)} static intervals: the {free.sum()}-parameter model needs at "
                f"least {free.sum()}"
                + (
                    " (with only the six faces the misalignment is unobservable: set "
                    "misalignment = false, or record more poses)"
                    if o.misalignment
                    else ""
                )
            )
        data = means if o.fit_on == "means" else _middle_samples(samples, intervals, o)
        problem = am.NormProblem(data, o.gravity, start, free)
        if o.method == "lm":
            sol = am.solve_lm(problem)
        else:
            if len(o.fw_box) != 3 or min(o.fw_box) <= 0:
                raise FitError("fw_box must be 3 positive half-widths [scale, angle, bias]")
            box = np.repeat(np.asarray(o.fw_box, dtype=float), 3)
            sol = am.solve_frank_wolfe(
                problem, box=box, max_iter=o.fw_max_iter, gap_rtol=o.fw_gap_rtol
            )
            if sol.info["at_box_bound"]:
                ctx.warn(
                    "frank_wolfe ended on the bound of its box: the optimum may lie outside; "
                    "widen fw_box"
                )
            if sol.info["stop"].startswith("max_iter"):
                ctx.warn(f"frank_wolfe did not meet its stopping rule: {sol.info['stop']}")
        unc = am.uncertainty(problem, sol.x)
        metrics["uncertainty"] = unc
        worst = max(unc.get("misalignment_std_rad", [np.inf]))
        if o.misalignment and (worst > 1e-3 or unc["condition_number"] > 1e4):
            ctx.warn(
                f"misalignment is poorly observable (angle std up to {worst:.2g} rad, condition "
                f"number {unc['condition_number']:.3g}): record more, better spread poses"
            )
        return sol.params, sol.info

    def _ferraris(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        o = self.options
        names = dict(o.ferraris_parts or {})
        unknown = set(names) - set(STATIC_PARTS + ROTATION_PARTS)
        if unknown:
            raise ctx.fail(f"ferraris_parts: unknown part(s) {sorted(unknown)}")
        if "label" not in table.column_names:
            raise ctx.fail("method 'ferraris' needs labelled segments: set csv.label")
        acc = sensor(table, "accel")
        gyro = sensor(table, "gyro")
        labels = table.column("label").take(pa.array(acc.rows))
        parts = {}
        try:
            for part in STATIC_PARTS + ROTATION_PARTS:
                mask = segment_mask(acc.t_s, labels, f"ferraris part {part}", names.get(part, part))
                parts[part] = (acc.values[mask], gyro.values[mask])
            fs = sample_rate(acc.t_ns)
        except FitError as exc:
            raise ctx.fail(str(exc)) from None
        cal = ferraris(parts, fs, o.gravity, o.ferraris_expected_angle_deg)
        static = np.vstack([parts[p][0] for p in STATIC_PARTS])
        pose_means = np.vstack([parts[p][0].mean(axis=0) for p in STATIC_PARTS])
        per_pose = norm_residual_mg(cal.calibrate_acc(pose_means), o.gravity)
        acc_step = LinearStep(
            type=self.type,
            sensor="accel",
            matrix=cal.accel_matrix,
            offset=cal.b_a,
            params={"method": "ferraris", "K_a": cal.K_a.tolist(), "R_a": cal.R_a.tolist()},
        )
        gyro_step = LinearStep(
            type=self.type,
            sensor="gyro",
            matrix=cal.gyro_matrix_dps * DEG,
            offset=cal.b_g,
            params={
                "method": "ferraris",
                "K_g": cal.K_g.tolist(),
                "R_g": cal.R_g.tolist(),
                "K_ga_not_applied": cal.K_ga.tolist(),
            },
        )
        ctx.warn(
            "ferraris: the gyro's acceleration sensitivity K_ga is reported but not applied by the "
            "chain (a linear step corrects each sensor on its own)"
        )
        results = {
            "method": "ferraris",
            "imucal": {**cal.to_json(), "acc_unit": "m/s^2", "gyr_unit": "deg/s"},
            "gravity": o.gravity,
            "sample_rate_hz": fs,
            "metrics": {
                "residual_mg": {
                    "means_rms": rms(per_pose),
                    "samples_rms": rms(norm_residual_mg(cal.calibrate_acc(static), o.gravity)),
                },
                "static_samples": len(static),
            },
        }
        return StageOutput(results=results, step=[acc_step, gyro_step])

    def _record(
        self,
        ctx: StageContext,
        t_ns: np.ndarray,
        raw: np.ndarray,
        params: am.NineParams,
        intervals: Intervals,
        per_pose: np.ndarray,
        g: float,
    ) -> None:
        rec = ctx.recorder
        if not rec.enabled:
            return
        static = np.where(intervals.mask(len(t_ns)), g, np.nan)  # g where still
        norm = dict(unit="m/s^2", plot="norm", title="|a|")
        rec.series(
            f"/{ctx.name}/norm/raw",
            t_ns,
            np.linalg.norm(raw, axis=1),
            ("|a| raw",),
            colors=[(150, 150, 150)],
            **(norm | {"unit": rec.input_unit(ctx.name, "accel")}),  # raw counts: a plot apart
        )
        rec.series(
            f"/{ctx.name}/norm/calibrated",
            t_ns,
            np.column_stack([np.linalg.norm(params.apply(raw), axis=1), static]),
            ("|a| calibrated", "still intervals (at g)"),
            colors=[(40, 100, 230), (230, 120, 20)],
            **norm,
        )
        rec.bars(
            f"/{ctx.name}/residual_per_pose",
            per_pose,
            ("|a| - g",),
            x_label="pose",
            unit="mg",
            title="|a| - g after calibration",
        )


def _middle_samples(samples: np.ndarray, intervals: Intervals, o: Any) -> np.ndarray:
    """Up to ``samples_per_interval`` samples from the middle of each interval (imu_tk)."""
    take = np.minimum(intervals.lengths, o.samples_per_interval)
    first = intervals.start + (intervals.lengths - take) // 2
    idx = np.repeat(first, take) + (np.arange(take.sum()) - np.repeat(np.cumsum(take) - take, take))
    return samples[idx]
