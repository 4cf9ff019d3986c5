"""``accel_calibration`` stage: accelerometer scale, non-orthogonality and bias from a
multi-position session (Tedaldi, Pretto and Menegatti, ICRA 2014, as imu_tk implements it; the
six-position method; Xiangtan University's Frank-Wolfe patent; Ferraris et al. 1995 as imucal
implements it).

Static intervals are detected automatically (:mod:`imupipe.stages.static_detector`): the
threshold is ``k`` times the noise floor of the log itself (or, with ``init_static_s``, imu_tk's
variance of an initial rest), and every ``k`` of ``thresholds`` is tried. At each ``k`` the
candidate models are fitted on the pose means and the one predicting left-out poses and all
orientations best is kept (:func:`imupipe.stages.multiposition.accel_models.choose_model`); among the ``k``
whose kept model can be checked (:func:`checkable`), the one with the smallest *predicted error*
(the RMS over all orientations of the calibrated |a|'s standard deviation, mg) wins: the
threshold that gives the best-determined calibration. Holds of 1 to 2 s: when no ``k`` gives a
fit that can be checked, every sample of a quiet window is taken as static. Then ``method``:

- ``lm``: the chosen model ``a = S K (a_t - b)`` (:mod:`imupipe.stages.multiposition.accel_models`; 9
  parameters, or 6 without the three misalignment angles) by scipy's Levenberg-Marquardt.
- ``frank_wolfe``: the same model by Frank-Wolfe over a box around the data-derived start (the
  patent's method); a box bound that stops it is enlarged and the problem solved again.
- ``six_position``: per axis ``b = (max + min) / 2``, ``k = 2 g / (max - min)`` over the static
  means; ``matrix = diag(k)``, ``offset = b``. Needs all six faces.
- ``ferraris``: imucal's Ferraris calibration from *labelled* (``csv.label``) or timed segments:
  six static poses and three turns; adds an accelerometer and a gyroscope step, and with
  ``apply_g_sensitivity`` the gyro's measured g-sensitivity (:mod:`imupipe.stages.multiposition.ferraris`).

``misalignment = "auto"`` (default) lets the data choose between the 9- and the 6-parameter
model; ``true`` or ``false`` forces one. The start of lm and frank_wolfe comes from the data
(bias = sphere centre of the static means, scale = g / their median radius), so raw counts need
no hand-made guess. Output ``matrix``/``offset`` are SI: ``a [m/s^2] = matrix @ (raw - offset)``.
Metrics in mg (1 mg = 9.80665e-3 m/s^2) are | |a| - g | over the static intervals:
``raw_means_rms`` of the raw pose means (before calibration; None for raw counts),
``start_means_rms`` of the data-derived start, ``means_rms`` after calibration; ``error_95_mg``
is the 95 % bound of the calibrated | |a| - g | RMS over all orientations.

Quality checks (``ctx.check``; ``accept_failed_checks = true`` keeps a fit that fails them):
the residual over the pose means must stay within :data:`NOISE_FACTOR` times the noise of one
still sample, and the poses must determine the calibration: predicted error at most
:data:`MAX_PREDICTED_ERROR_MG` mg over all orientations (``six_position`` checks its coverage
itself: it needs every face).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import SensorData, has_stream, imu_pairs, sensor
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.errors import FitError
from imupipe.stages.multiposition import accel_models as am
from imupipe.stages.multiposition.ferraris import (
    ROTATION_PARTS,
    STATIC_PARTS,
    GSensitivityStep,
    ferraris,
)
from imupipe.stages.static_detector import (
    Detector,
    Intervals,
    Poses,
    make_detector,
    sample_rate,
    segment_mask,
)
from imupipe.stages.steps import LinearStep, Step

DEG = np.pi / 180
NOISE_FACTOR = 3.0
"""The | |a| - g | RMS over the pose means may be at most this many times the noise of one still
sample (from the noise floor): a mean over a second or more at rest is far more precise than one
sample, so a larger residual is a misfit (real sessions measured: 0.12 to 0.47 times)."""
MERGE_ANGLE_DEG = 2.0
"""deg: consecutive static intervals whose mean specific force turned by less than this are the
same pose (held, disturbed, held again), not two independent ones."""
MAX_PREDICTED_ERROR_MG = 3.0
"""mg: the largest predicted error over all orientations of a calibration the poses determine."""
MIN_SPARE_POSES = 3
"""Poses beyond the model's parameters needed to check a fit: the residual variance behind the
predicted error has this many degrees of freedom (with 1 or 2 it can be near zero by chance)."""
MAX_SCALE_RATIO = 1.5
"""The largest ratio of the three axes' fitted scales: the axes of one accelerometer share their
sensitivity within a few per cent (datasheets: +-3 % to +-10 %; a grossly mis-set axis of +15 %
beside one of -10 % is 1.28); a spread of half again is a fit of poses that were not still, or of
too few of them."""
MISALIGNMENT_MODELS: dict[str, list[str]] = {
    "auto": ["9-parameter", "6-parameter"],
    "true": ["9-parameter"],
    "false": ["6-parameter"],
}


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def raw_residual_mg(means: np.ndarray, g: float) -> float | None:
    """| |a| - g | RMS (mg) of the raw pose means, where they are in m/s^2 (their median norm
    within 20 % of g); None for raw counts, which have no such figure."""
    norm = np.linalg.norm(means, axis=1)
    if not abs(float(np.median(norm)) / g - 1) <= 0.2:
        return None
    return rms(norm_residual_mg(means, g))


def norm_residual_mg(values: np.ndarray, g: float) -> np.ndarray:
    """| |a| - g | per row of ``values`` (n, 3) m/s^2, in mg (signed)."""
    return (np.linalg.norm(values, axis=1) - g) / am.MG


@dataclass
class StaticSetup:
    """The detection options shared by the accelerometer and gyroscope stages."""

    window_s: float = 1.0
    """Variance window, s."""
    init_static_s: float | None = None
    """Optional: the log starts with this many seconds at rest; its variance is the threshold
    reference (imu_tk's rule) instead of the noise floor measured on the whole log."""
    min_interval_s: float = 1.0
    """Shortest static interval kept, s."""
    thresholds: list[float] = field(default_factory=lambda: [2, 3, 4, 5, 7, 10, 15, 20, 30])
    """Candidate k (threshold = k x the reference variance); the best is chosen."""
    noise_quantile: float = 0.1
    """The quantile of the windowed variance taken as the noise floor (the log must be at rest
    for more than this fraction of its length)."""
    misalignment: Literal["auto"] | bool = "auto"
    """Fit the three misalignment angles (true), not (false: 6 parameters, scale and bias), or
    let the poses decide by the prediction of left-out poses ("auto")."""


@dataclass
class Detection:
    """The chosen static intervals grouped into poses, the model fitted on the pose means, and
    how both were chosen."""

    poses: Poses
    fit: am.ModelFit
    reason: str
    candidates: list[am.ModelFit]
    report: dict[str, Any]

    @property
    def intervals(self) -> Intervals:
        return self.poses.intervals


def group_poses(intervals: Intervals, accel: np.ndarray) -> Poses:
    """Consecutive intervals whose mean specific force (about the sphere centre of the means,
    so raw counts work) turned by less than :data:`MERGE_ANGLE_DEG` are one pose."""
    means = intervals.means(accel)
    centre = am.sphere_centre(means) if len(means) >= 4 else np.zeros(3)
    if not np.all(np.isfinite(centre)):
        centre = np.zeros(3)
    unit = means - centre
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-300)[:, None]
    turn = np.degrees(np.arccos(np.clip(np.sum(unit[1:] * unit[:-1], axis=1), -1.0, 1.0)))
    group = np.r_[0, np.cumsum(turn >= MERGE_ANGLE_DEG)].astype(np.int64)
    return Poses(intervals, group)


def detect_intervals(
    t_ns: np.ndarray, accel: np.ndarray, setup: Any, g: float, models: list[str] | None = None
) -> Detection:
    """Static intervals and the accelerometer model fitted on their means: for every ``k`` of
    ``setup.thresholds`` the candidate ``models`` (default by ``setup.misalignment``) are fitted
    and the one predicting left-out poses best is kept; the ``k`` whose kept model can be checked
    and has the smallest predicted error wins. Where no ``k`` gives a fit that can be checked
    (holds of 1 to 2 s, shorter than a window plus ``min_interval_s``), the detection runs again
    with every sample of a quiet window static (:meth:`Detector.detect`'s ``whole_windows``)."""
    if setup.noise_quantile <= 0 or setup.noise_quantile >= 1:
        raise FitError(f"noise_quantile must be in (0, 1), got {setup.noise_quantile}")
    if setup.init_static_s is not None and setup.init_static_s <= 0:
        raise FitError(f"init_static_s must be > 0 s, got {setup.init_static_s}")
    if not setup.thresholds or min(setup.thresholds) <= 0:
        raise FitError("thresholds must be a non-empty list of k > 0")
    detector = make_detector(
        t_ns,
        accel,
        window_s=setup.window_s,
        init_static_s=setup.init_static_s,
        min_interval_s=setup.min_interval_s,
        floor_quantile=setup.noise_quantile,
    )
    if models is None:
        models = MISALIGNMENT_MODELS[str(setup.misalignment).lower()]
    need = min(int(am.MODEL_FREE[m].sum()) for m in models)
    table: dict[str, Any] = {}
    best: tuple[tuple[int, float], float, bool, Detection] | None = None
    for whole in (False, True):
        if best is not None and best[0][0] == 0:
            break
        for k in setup.thresholds:
            intervals = detector.detect(k, whole_windows=whole)
            row: dict[str, Any] = {"intervals": len(intervals)}
            table[f"{k:g}" + (" (whole windows)" if whole else "")] = row
            poses = group_poses(intervals, accel) if len(intervals) else None
            row["poses"] = len(poses) if poses is not None else 0
            if poses is None or len(poses) < need:
                continue
            means = poses.means(accel)
            try:
                start = am.initial_guess(means, g)
                noise = pose_mean_noise(poses, accel, start, g)
                fits = [
                    am.fit_model(means, g, m, start, noise)
                    for m in models
                    if len(means) >= am.MODEL_FREE[m].sum()
                ]
            except (FitError, np.linalg.LinAlgError, ValueError):
                continue
            chosen, reason = am.choose_model(fits, models)
            predicted = chosen.predicted_error_mg()
            # a threshold whose fit can be checked beats one whose cannot, whatever the figures
            score = (0 if checkable(chosen) else 1, predicted)
            row.update({"model": chosen.name, "predicted_error_mg": am.finite_or_none(predicted)})
            if best is None or score < best[0]:
                best = (score, k, whole, Detection(poses, chosen, reason, fits, {}))
    if best is None:
        raise FitError(too_few_poses(max(row["poses"] for row in table.values()), need))
    _, k, whole, chosen = best
    chosen.report = {
        **detector.describe(k),
        "whole_windows": whole,
        "window_s": setup.window_s,
        "min_interval_s": setup.min_interval_s,
        "noise_sigma_per_axis": detector_noise(detector),
        "rule": (
            "the k whose intervals give the smallest predicted calibration error over all "
            "orientations, among those leaving a fit that can be checked (its model chosen by "
            "the prediction of left-out poses)"
        ),
        "candidates": table,
    }
    return chosen


def too_few_poses(found: int, need: int) -> str:
    """The one line for a log whose still poses cannot support the fit: how many orientations
    were found (the most over every detection threshold), how many the model needs, and what to
    record instead."""
    if found >= need:
        what = (
            f"found {found} still orientations, but none of the fits on them could be made "
            "(the orientations too close to one another?)"
        )
    else:
        what = (
            f"found {found} still orientation{'s' if found != 1 else ''}; this calibration "
            f"needs the IMU held still in at least {need} different orientations"
        )
    return (
        f"too few static poses: {what}. Record a session of 12 or more orientations (each axis "
        "up and down, and some in between), each held still for 2 s or more, or lower "
        "min_interval_s if the holds are short (docs/how-to/multi-position-session.md)"
    )


def six_faces(means: np.ndarray, max_angle_deg: float = 30.0) -> bool:
    """Whether the poses are the six faces (each axis up and down, every pose within
    ``max_angle_deg`` of one): the session PX4 and ArduPilot record, which determines scale and
    bias exactly and cannot see misalignment."""
    centred = means - am.sphere_centre(means)
    unit = centred / np.maximum(np.linalg.norm(centred, axis=1), 1e-300)[:, None]
    cos_max = np.cos(np.radians(max_angle_deg))
    near = np.abs(unit).max(axis=1) >= cos_max
    faces = {(int(np.argmax(np.abs(u))), bool(u[np.argmax(np.abs(u))] > 0)) for u in unit[near]}
    return bool(near.all()) and len(faces) == 6


def checkable(fit: am.ModelFit) -> bool:
    """Whether a fit's residual can check it: :data:`MIN_SPARE_POSES` spare poses, or one or two
    whose residual agrees with the measured noise of a pose mean (the noise is then known, not
    taken from those few degrees of freedom), or a 6-parameter fit of the six faces (exact; what
    the six-position method computes)."""
    if fit.dof >= MIN_SPARE_POSES:
        return True
    noise = fit.mean_noise
    rms_fit = float(np.sqrt(fit.rss / fit.dof)) if fit.dof > 0 else float("inf")
    if fit.dof >= 1 and noise > 0 and rms_fit <= am.ADEQUATE_FACTOR * noise:
        return True
    return fit.name == "6-parameter" and six_faces(fit.problem.samples)


def pose_mean_noise(poses: Poses, accel: np.ndarray, start: am.NineParams, g: float) -> float:
    """Noise of one pose mean along gravity, as a fraction of g, measured on the poses: the
    difference of the two halves of each still interval, along its mean direction, is twice a
    half's noise; a pose's mean averages its intervals. Drift and tremor slower than a hold are
    partly seen, white noise fully."""
    iv = poses.intervals
    half = iv.lengths // 2
    first = Intervals(iv.start, iv.start + half)
    second = Intervals(iv.start + half, iv.start + 2 * half)
    ok = half > 0
    if not ok.any():
        return 0.0
    centred = iv.means(accel) - start.bias
    unit = centred / np.maximum(np.linalg.norm(centred, axis=1), 1e-300)[:, None]
    diff = np.einsum("ij,ij->i", first.means(accel) - second.means(accel), unit)
    # var(half mean) = diff^2 / 2; the interval mean averages two halves: diff^2 / 4
    var = np.where(ok, diff**2 / 4, 0.0) * float(np.mean(start.scale)) ** 2
    count = np.bincount(poses.group, weights=ok.astype(float))
    per_pose = np.bincount(poses.group, weights=var) / np.maximum(count, 1) ** 2
    return float(np.sqrt(np.mean(per_pose[count > 0]))) / g


def detector_noise(detector: Detector) -> float:
    """Standard deviation of one still sample per axis implied by the reference variance (input
    units): the reference is the norm of three per-axis variances."""
    return float(np.sqrt(detector.reference / np.sqrt(3.0)))


class AccelCalibrationStage(Stage):
    type = "accel_calibration"
    sensors = ("accel",)
    corrects = True

    @dataclass
    class Options(StaticSetup):
        method: Literal["six_position", "lm", "frank_wolfe", "ferraris"] = "lm"
        """How the model is solved: ``lm`` (Levenberg-Marquardt on the pose means, 9 or 6
        parameters as ``misalignment`` says), ``six_position`` (per axis ``b = (max + min) / 2``,
        ``k = 2g / (max - min)``: needs every face, no misalignment), ``frank_wolfe`` (the same
        model by the conditional-gradient method of Xiangtan University's patent; slower, for
        comparison) or ``ferraris`` (Ferraris et al. 1995 as imucal computes it, from six labelled
        faces and three labelled turns; also fits the gyroscope)."""
        gravity: float = 9.80665
        """Local g, m/s^2."""
        fit_on: Literal["means", "samples"] = "means"
        """Fit on the static-interval means, or on up to ``samples_per_interval`` samples from the
        middle of each interval (imu_tk's acc_use_means = false)."""
        samples_per_interval: int = 100
        """With ``fit_on = "samples"``: samples taken from the middle of each interval."""
        fw_box: list[float] = field(default_factory=lambda: [0.05, 0.05, 0.05])
        """Frank-Wolfe box half-widths around the start: relative scale, angles (rad), bias
        (relative to g); a half-width the solution ends on is doubled and the problem solved
        again (up to 8 times)."""
        fw_max_iter: int = 20000
        """Frank-Wolfe: iterations allowed per solve."""
        fw_gap_rtol: float = 1e-2
        """Frank-Wolfe stops when its duality gap is below this fraction of the cost."""
        ferraris_parts: dict[str, Any] | None = None
        """ferraris: imucal part name (x_p ... z_rot) -> its label in the data, or
        [start_s, end_s] (default: the label of the same name)."""
        ferraris_expected_angle_deg: float = -360.0
        """ferraris: the angle of each turn (imucal's default -360: clockwise)."""
        apply_g_sensitivity: bool = False
        """ferraris: also correct the gyro's measured g-sensitivity ``K_ga`` (a step that reads
        the calibrated accelerometer of each sample)."""

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
        acc = ctx.finite(sensor(table, "accel"), "accelerometer", minimum=2)
        ctx.dead_axes(acc, "accel")  # the pose models couple the axes
        g = o.gravity
        models = None if o.method != "six_position" else ["6-parameter"]
        try:
            found = detect_intervals(acc.t_ns, acc.values, o, g, models)
            params, solver, problem = self._solve(found, acc, ctx)
        except FitError as exc:
            raise ctx.fail(str(exc)) from None
        intervals, means = found.intervals, found.poses.means(acc.values)
        model = found.fit.name if o.method != "six_position" else "six-position"
        if o.method != "six_position" and o.misalignment == "auto" and model == "6-parameter":
            ctx.warn(
                "misalignment not fitted: the poses do not support the 9-parameter model, so the "
                f"6-parameter model (scale, bias) is used ({found.reason})"
            )
        inside = intervals.mask(len(acc))
        per_pose = norm_residual_mg(params.apply(means), g)
        per_sample = norm_residual_mg(params.apply(acc.values[inside]), g)
        noise_mg = found.report["noise_sigma_per_axis"] * float(np.mean(params.scale)) / am.MG
        residual = {
            "means_rms": rms(per_pose),
            "means_max": float(np.abs(per_pose).max()),
            "samples_rms": rms(per_sample),
            "raw_means_rms": raw_residual_mg(means, g),
            "start_means_rms": rms(norm_residual_mg(found.fit.problem.start.apply(means), g)),
            "noise_per_sample": noise_mg,
        }
        metrics: dict[str, Any] = {
            "intervals": len(intervals),
            "poses": len(means),
            "distinct_poses": am.distinct_poses(means),
            "threshold": found.report,
            "residual_mg": residual,
            "predicted_error_mg": am.finite_or_none(found.fit.predicted_error_mg()),
            "error_95_mg": am.finite_or_none(found.fit.error_95_mg()),
            "pose_mean_noise_mg": found.fit.mean_noise * g / am.MG,
        }
        if solver:
            metrics["solver"] = solver
        results: dict[str, Any] = {"method": o.method}
        if problem is not None:
            sigma2 = found.fit.sigma2 if problem is found.fit.problem else None
            unc = am.uncertainty(problem, problem_x(problem, params), sigma2)
            metrics["uncertainty"] = unc
            loo = found.fit.leave_one_out_mg()
            results["model"] = {
                "chosen": model,
                "reason": found.reason,
                "candidates": {f.name: f.summary() for f in found.candidates},
                "leave_one_pose_out_mg_rms": _loo_rms(loo),
            }
            results["standard_errors"] = {
                "scale": unc.get("scale_std"),
                "misalignment_rad": unc.get("misalignment_std_rad"),
                "bias": unc.get("bias_std"),
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
        ctx.check(
            residual["means_rms"] <= NOISE_FACTOR * noise_mg,
            f"residual far above the noise: | |a| - g | RMS over the pose means "
            f"{residual['means_rms']:.3g} mg > {NOISE_FACTOR:g} x the noise of one still sample "
            f"({noise_mg:.3g} mg): "
            + (
                "the 6-parameter model does not fit these poses (a misaligned sensor: record 12 "
                "or more poses spread over the sphere for the 9-parameter model, or six faces "
                "only)"
                if model == "6-parameter" and len(found.candidates) == 1
                else "motion in the static intervals, a wrong gravity, or a sensor the model "
                "does not fit"
            ),
        )
        predicted = found.fit.predicted_error_mg()
        spare = len(means) - found.fit.n_params
        can_check = checkable(found.fit)
        most = max(int(am.MODEL_FREE[c.name].sum()) for c in found.candidates)
        if o.misalignment == "auto" and o.method != "six_position":
            most = int(am.MODEL_FREE["9-parameter"].sum())  # what a misaligned sensor needs
        if can_check and spare < MIN_SPARE_POSES:
            ctx.warn(
                f"{len(means)} poses for {found.fit.n_params} parameters leave {spare} degree(s) "
                "of freedom: "
                + (
                    "the six faces determine scale and bias exactly and nothing checks them; "
                    "record a few tilted poses to check the fit"
                    if spare == 0
                    else "the fit is checked against the measured noise of a pose mean only"
                )
            )
        ctx.check(
            (can_check and predicted <= MAX_PREDICTED_ERROR_MG) or o.method == "six_position",
            (
                f"pose coverage: {len(means)} poses for {found.fit.n_params} parameters leave "
                f"{max(spare, 0)} degree(s) of freedom, too few to check the fit ({found.reason}); "
                f"record at least {most + MIN_SPARE_POSES} poses spread over the sphere, or the "
                "six faces only (methods six_position and ferraris fit exactly the six faces)"
            )
            if not (can_check and np.isfinite(predicted))
            else (
                f"pose coverage: the {len(means)} poses leave the calibration undetermined "
                f"(predicted error over all orientations {predicted:.3g} mg > "
                f"{MAX_PREDICTED_ERROR_MG:g} mg); record more poses, spread over the sphere"
                + (", or set misalignment = false" if model == "9-parameter" else "")
            ),
        )
        ratio = float(np.max(params.scale) / np.min(params.scale))
        ctx.check(
            ratio <= MAX_SCALE_RATIO or o.method == "ferraris",
            f"implausible scales: the axes' fitted scales {np.array2string(params.scale, precision=4)} "
            f"differ by a factor {ratio:.3g} > {MAX_SCALE_RATIO:g}; the axes of one "
            "accelerometer share their sensitivity within a few per cent: were the intervals "
            "still?",
        )
        step = LinearStep(
            type=self.type,
            sensor="accel",
            matrix=params.matrix,
            offset=params.bias,
            params={
                "method": o.method,
                "model": model,
                "scale": params.scale.tolist(),
                "misalignment_rad": params.angles.tolist(),
                "bias": params.bias.tolist(),
            },
        )
        return StageOutput(results=results, step=step)

    # -- methods -----------------------------------------------------------------------------
    def _solve(
        self, found: Detection, acc: SensorData, ctx: StageContext
    ) -> tuple[am.NineParams, dict[str, Any] | None, am.NormProblem | None]:
        o = self.options
        means = found.poses.means(acc.values)
        if o.method == "six_position":
            params = am.six_position(means, o.gravity)
            ctx.warn(
                "six_position fits scale and bias only: axis misalignment is not estimated "
                "(use lm or frank_wolfe on nine or more distinct poses)"
            )
            return params, None, None
        if o.fit_on == "means":
            problem = found.fit.problem
        else:
            data = _middle_samples(acc.values, found.intervals, o)
            problem = am.NormProblem(
                data, o.gravity, found.fit.problem.start, found.fit.problem.free
            )
        if o.method == "lm":
            sol = found.fit.solution if o.fit_on == "means" else am.solve_lm(problem)
            return sol.params, sol.info, problem
        if len(o.fw_box) != 3 or min(o.fw_box) <= 0:
            raise FitError("fw_box must be 3 positive half-widths [scale, angle, bias]")
        sol = am.solve_frank_wolfe_enlarging(
            problem,
            box=np.repeat(np.asarray(o.fw_box, dtype=float), 3),
            max_iter=o.fw_max_iter,
            gap_rtol=o.fw_gap_rtol,
        )
        if sol.info["box_enlargements"]:
            ctx.warn(
                f"frank_wolfe: the solution reached its box {sol.info['box_enlargements']} "
                "time(s); the box was enlarged and the problem solved again (final half-widths "
                f"{np.round(sol.info['box'], 4).tolist()})"
            )
        if sol.info["stop"].startswith("max_iter"):
            ctx.warn(f"frank_wolfe did not meet its stopping rule: {sol.info['stop']}")
        return sol.params, sol.info, problem

    def _ferraris(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        o = self.options
        names = dict(o.ferraris_parts or {})
        unknown = set(names) - set(STATIC_PARTS + ROTATION_PARTS)
        if unknown:
            raise ctx.fail(f"ferraris_parts: unknown part(s) {sorted(unknown)}")
        labelled = any(isinstance(names.get(p, p), str) for p in STATIC_PARTS + ROTATION_PARTS)
        if labelled and "label" not in table.column_names:
            raise ctx.fail(
                "method 'ferraris' needs labelled segments: set csv.label (or give every part "
                "as [start_s, end_s] in ferraris_parts)"
            )
        gyro, acc, note = imu_pairs(table, on="accel")
        if note:
            ctx.warn(note)
        labels = table.column("label").take(pa.array(acc.rows)) if labelled else None
        parts = {}
        try:
            for part in STATIC_PARTS + ROTATION_PARTS:
                mask = segment_mask(acc.t_s, labels, f"ferraris part {part}", names.get(part, part))
                ok = (
                    mask
                    & np.isfinite(acc.values).all(axis=1)
                    & np.isfinite(gyro.values).all(axis=1)
                )
                if not ok.any():
                    raise FitError(f"ferraris part {part}: no finite samples")
                parts[part] = (acc.values[ok], gyro.values[ok])
            fs = sample_rate(acc.t_ns)
        except FitError as exc:
            raise ctx.fail(str(exc)) from None
        cal = ferraris(parts, fs, o.gravity, o.ferraris_expected_angle_deg)
        static = np.vstack([parts[p][0] for p in STATIC_PARTS])
        pose_means = np.vstack([parts[p][0].mean(axis=0) for p in STATIC_PARTS])
        per_pose = norm_residual_mg(cal.calibrate_acc(pose_means), o.gravity)
        steps: list[Step] = [
            LinearStep(
                type=self.type,
                sensor="accel",
                matrix=cal.accel_matrix,
                offset=cal.b_a,
                params={"method": "ferraris", "K_a": cal.K_a.tolist(), "R_a": cal.R_a.tolist()},
            )
        ]
        if o.apply_g_sensitivity:
            steps.append(GSensitivityStep(type=self.type, sensor="gyro", k_ga=cal.K_ga))
        steps.append(
            LinearStep(
                type=self.type,
                sensor="gyro",
                matrix=cal.gyro_matrix_dps * DEG,
                offset=cal.b_g,
                params={
                    "method": "ferraris",
                    "K_g": cal.K_g.tolist(),
                    "R_g": cal.R_g.tolist(),
                    "K_ga_applied": o.apply_g_sensitivity,
                },
            )
        )
        if not o.apply_g_sensitivity:
            ctx.warn(
                "ferraris: the gyro's g-sensitivity K_ga is reported but not applied (set "
                "apply_g_sensitivity = true to correct it)"
            )
        results = {
            "method": "ferraris",
            "imucal": {**cal.to_json(), "acc_unit": "m/s^2", "gyr_unit": "deg/s"},
            "g_sensitivity_applied": o.apply_g_sensitivity,
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
        return StageOutput(results=results, step=steps)

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
            under=True,
            **(norm | {"unit": rec.input_unit(ctx.name, "accel")}),  # raw counts: a plot apart
        )
        rec.series(  # a wide orange stroke at g beneath |a| where the IMU was still
            f"/{ctx.name}/norm/still",
            t_ns,
            static,
            ("still intervals (at g)",),
            colors=[(230, 120, 20)],
            highlight=True,
            **norm,
        )
        rec.series(
            f"/{ctx.name}/norm/calibrated",
            t_ns,
            np.linalg.norm(params.apply(raw), axis=1),
            ("|a| calibrated",),
            colors=[(40, 100, 230)],
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


def problem_x(problem: am.NormProblem, params: am.NineParams) -> np.ndarray:
    """The normalised unknowns of ``problem`` that give ``params``."""
    return np.concatenate(
        [
            params.scale / problem.start.scale - 1,
            params.angles,
            (params.bias - problem.start.bias) / problem.radius,
        ]
    )


def _loo_rms(values: np.ndarray) -> float | None:
    ok = np.isfinite(values)
    return rms(values[ok]) if ok.any() else None


def _middle_samples(samples: np.ndarray, intervals: Intervals, o: Any) -> np.ndarray:
    """Up to ``samples_per_interval`` samples from the middle of each interval (imu_tk)."""
    take = np.minimum(intervals.lengths, o.samples_per_interval)
    first = intervals.start + (intervals.lengths - take) // 2
    idx = np.repeat(first, take) + (np.arange(take.sum()) - np.repeat(np.cumsum(take) - take, take))
    return samples[idx]
