"""``thermal_soak`` stage: accelerometer (and gyroscope) bias, scale and misalignment against
temperature, from multi-position sessions recorded at several held chamber temperatures.

The soak method of "MEMS 惯性测量组件的温度误差补偿模型研究" (温度标定: obtain the calibration
parameters -- bias, scale, orthogonality -- at each temperature, draw them as curves and fit them):

1. **Soaks**: the temperature's 10 s blocks (:mod:`imupipe.stages.thermal.track`) whose rate is
   under ``stable_rate`` degC/min are settled; runs of settled blocks that stay within
   ``soak_tolerance`` degC and last ``min_soak_s`` or more are the soaks (neighbours within the
   tolerance are merged).
2. **Static intervals** (:mod:`imupipe.stages.static_detector`, imu_tk's detector, Tedaldi et al.
   ICRA 2014) over the whole log, cut to the soaks; the threshold ``k`` with the lowest residual
   per degree of freedom of the per-soak fits wins.
3. **At each soak**: the 9-parameter accelerometer model ``a = diag(s) K (raw - b)``
   (:mod:`imupipe.stages.multiposition.accel_models`, Levenberg-Marquardt on the interval means, with its
   standard deviations); the gyro bias (mean over the intervals); and, where the rotations
   between the poses were recorded and observe them (``gyro_matrix``; condition number under
   1e4, nine or more transitions), the gyro scale and six misalignment angles from the pose
   transitions (:func:`imupipe.stages.multiposition.gyro_models.fit_static_poses`).
4. **Against temperature**: each parameter component is a polynomial in ``T - tref`` whose order
   (0..3, below the number of soaks) the small-sample Akaike criterion chooses, weighted by the
   soak values' inverse variances, unless ``order`` is given.

The correction (:class:`~imupipe.stages.thermal.step.ThermalMatrixStep`, applied per sample by
``run`` and ``convert``, batch by batch too) evaluates the polynomials at each sample's
temperature (clamped to the soaks' range) and applies the model. Units: scale (m/s^2 or rad/s
per raw unit), angles rad, bias in the raw unit; temperatures degC.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import has_stream, imu_pairs
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.errors import FitError
from imupipe.stages.multiposition import accel_models as am
from imupipe.stages.multiposition import gyro_models as gm
from imupipe.stages.static_detector import (
    Intervals,
    choose_threshold,
    make_detector,
    sample_clock,
)
from imupipe.stages.thermal import models as tm
from imupipe.stages.thermal.step import (
    ThermalMatrixStep,
    apply_matrix_form,
    temperature_samples,
)
from imupipe.stages.thermal.track import Blocking, Track, TrackSpec, Variables

MAX_ORDER = 3
FULL_GYRO_MODEL = "9-parameter"
"""The gyro model fitted at each soak: scale and misalignment are both followed in temperature."""
GYRO_MAX_CONDITION = 1e4
GYRO_MIN_TRANSITIONS = 9
ACCEL_NAMES = {
    "scale": ("x", "y", "z"),
    "misalignment": ("yz", "zy", "zx"),
    "bias": ("x", "y", "z"),
}
GYRO_NAMES = {
    "scale": ("x", "y", "z"),
    "misalignment": ("yz", "zy", "zx", "xz", "xy", "yx"),
    "bias": ("x", "y", "z"),
}


@dataclass
class Soak:
    """One held temperature: its sample range ``[start, stop)``, mean temperature, static
    intervals, and what was fitted there."""

    start: int
    stop: int
    temperature: float = float("nan")
    intervals: Intervals | None = None
    accel: dict[str, np.ndarray] = field(default_factory=dict)
    accel_std: dict[str, np.ndarray] = field(default_factory=dict)
    gyro: dict[str, np.ndarray] = field(default_factory=dict)
    gyro_std: dict[str, np.ndarray] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)


def find_soaks(
    centre: np.ndarray,
    temp: np.ndarray,
    rate: np.ndarray,
    t_ns: np.ndarray,
    stable_rate: float,
    tolerance: float,
    min_s: float,
) -> list[tuple[int, int, float]]:
    """(first sample, stop sample, median temperature) of each soak; see the module docstring.
    ``centre``/``temp``/``rate``: the blocks (ns, degC, degC/s); ``t_ns``: the samples."""
    settled = np.abs(rate) < stable_rate / 60.0
    edges = np.diff(np.r_[0, settled.astype(np.int8), 0])
    runs = zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True)
    pieces: list[tuple[int, int]] = []
    for a, b in runs:  # runs of settled blocks (a few per soak), not samples
        level = np.floor((temp[a:b] - temp[a]) / tolerance + 0.5)
        cuts = np.flatnonzero(np.diff(level) != 0) + 1 + a
        pieces += list(zip(np.r_[a, cuts], np.r_[cuts, b], strict=True))
    merged: list[list[int]] = []
    for a, b in pieces:
        if (
            merged
            and abs(np.median(temp[a:b]) - np.median(temp[merged[-1][0] : merged[-1][1]]))
            < tolerance
        ):
            merged[-1][1] = b
        else:
            merged.append([a, b])
    out = []
    for a, b in merged:
        if (centre[b - 1] - centre[a]) * 1e-9 < min_s:
            continue
        first = int(np.searchsorted(t_ns, centre[a], side="left"))
        stop = int(np.searchsorted(t_ns, centre[b - 1], side="right"))
        out.append((first, stop, float(np.median(temp[a:b]))))
    return out


def cut_to_soaks(intervals: Intervals, soaks: list[Soak], min_samples: int) -> list[Intervals]:
    """The parts of the static intervals inside each soak (at least ``min_samples`` long)."""
    out = []
    for s in soaks:
        start = np.maximum(intervals.start, s.start)
        stop = np.minimum(intervals.stop, s.stop)
        keep = (stop - start) >= max(min_samples, 1)
        out.append(Intervals(start[keep], stop[keep]))
    return out


class ThermalSoakStage(Stage):
    type = "thermal_soak"
    corrects = True

    @dataclass
    class Options:
        sensor: Literal["both", "accel"] = "both"
        """``accel``: the accelerometer only; ``both``: and the gyroscope (bias, plus scale and
        misalignment where the data allow)."""
        gravity: float = 9.80665
        """Local gravity g, m/s^2."""
        window_s: float = 1.0
        """Static detection: variance window, s."""
        init_static_s: float = 30.0
        """Static detection: the log's initial static period (threshold reference), s."""
        min_interval_s: float = 1.0
        """Static detection: shortest static interval kept, s."""
        thresholds: list[float] = field(default_factory=lambda: [2, 3, 4, 5, 6, 7, 8, 9, 10])
        """Static detection: candidate k (threshold = k x variance of the initial period)."""
        stable_rate: float = 0.1
        """degC/min: the temperature is settled where its rate is below this."""
        soak_tolerance: float = 1.0
        """degC: a soak stays within this of its start."""
        min_soak_s: float = 60.0
        """s: shorter settled stretches are not soaks."""
        order: int | None = None
        """Polynomial order of every parameter in T - tref; default chosen per component."""
        tref: float | None = None
        """degC; default the middle of the soaks' temperatures."""
        misalignment: bool = True
        """Fit the accelerometer's three misalignment angles (needs 9 distinct poses per soak)."""
        gyro_matrix: bool = True
        """Fit the gyroscope's scale and misalignment at each soak where the pose transitions
        allow (else its bias only)."""

    @classmethod
    def sensors_for(cls, options: Any) -> tuple[str, ...]:
        return (
            ("accel", "gyro", "temperature")
            if options.sensor == "both"
            else ("accel", "temperature")
        )

    # -- fit -----------------------------------------------------------------------------------
    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        o = self.options
        if not has_stream(table, "imu"):
            raise ctx.fail("the input has no IMU samples")
        if not len(temperature_samples(table, "temperature")[0]):
            raise ctx.fail(
                "the input has no temperature samples (map csv.temperature or set temperature_topic)"
            )
        if o.order is not None and not 0 <= o.order <= MAX_ORDER:
            raise ctx.fail(f"'order' must be 0..{MAX_ORDER}")
        gyro, acc, note = imu_pairs(table, on="accel")
        if note:
            ctx.warn(note)
        ctx.dead_axes(acc, "accel")  # the pose models couple the axes
        ctx.dead_axes(gyro, "gyro")
        bad = ~(np.isfinite(acc.values).all(axis=1) & np.isfinite(gyro.values).all(axis=1))
        if bad.any():
            raise ctx.fail(f"non-finite IMU sample at sample {int(np.flatnonzero(bad)[0])}")
        track = Track(TrackSpec(blocking=Blocking(window_s=10.0), keep_blocks=True))
        v = Variables.concat(
            [track.push(acc.t_ns, [temperature_samples(table, "temperature")]), track.finish()]
        )
        b = track.blocks
        spans = find_soaks(
            b.centre,
            b.temps[:, 0],
            b.rate[:, 0],
            acc.t_ns,
            o.stable_rate,
            o.soak_tolerance,
            o.min_soak_s,
        )
        soaks = [Soak(a, z) for a, z, _ in spans]
        if len(soaks) < 2:
            raise ctx.fail(
                f"{len(soaks)} soak(s) found (settled under {o.stable_rate:g} degC/min within "
                f"{o.soak_tolerance:g} degC for {o.min_soak_s:g} s); a thermal calibration needs "
                "multi-position sessions at 2 or more held temperatures"
            )
        n_params = 9 if o.misalignment else 6
        try:
            per_soak, detection = self._detect(acc.t_ns, acc.values, soaks, n_params)
        except FitError as exc:
            raise ctx.fail(str(exc)) from None
        fitted = []
        for s, iv in zip(soaks, per_soak, strict=True):
            s.intervals = iv
            if len(iv):
                s.temperature = float(iv.means(v.T[:, :1])[:, 0] @ iv.lengths / iv.lengths.sum())
            why = self._fit_accel(s, acc.values, n_params)
            if why:
                ctx.warn(f"soak at {np.median(v.T[s.start : s.stop, 0]):.4g} degC left out: {why}")
                continue
            if o.sensor == "both":
                self._fit_gyro(s, acc.t_ns, acc.values, gyro.values)
            fitted.append(s)
        if len(fitted) < 2:
            raise ctx.fail(
                f"{len(fitted)} soak(s) with a full multi-position session; a thermal calibration "
                "needs 2 or more"
            )
        temps = np.array([s.temperature for s in fitted])
        tref = float(o.tref) if o.tref is not None else float((temps.min() + temps.max()) / 2)
        rng = [float(temps.min()), float(temps.max())]
        steps, results = (
            [],
            {"soaks": [], "tref": tref, "temperature_range": rng, "detection": detection},
        )
        sensors = {"accel": ACCEL_NAMES}
        if o.sensor == "both":
            sensors["gyro"] = self._gyro_quantities(fitted, ctx)
        for which, names in sensors.items():
            poly, selection = self._polynomials(fitted, which, tref, names, ctx)
            steps.append(
                ThermalMatrixStep(
                    type=self.type, sensor=which, form=which, tref=tref, range=rng,
                    parameters=poly, quiet=ctx.quiet,
                )
            )  # fmt: skip
            results[which] = {"parameters": selection}
        results["soaks"] = [self._soak_record(s) for s in fitted]
        results["metrics"] = self._metrics(fitted, steps, acc.values, gyro.values, v.T[:, 0], ctx)
        if getattr(ctx.recorder, "enabled", False):
            self._record(ctx, fitted, steps)
        return StageOutput(results=results, step=steps)

    # -- soaks -------------------------------------------------------------------------------
    def _detect(
        self, t_ns: np.ndarray, accel: np.ndarray, soaks: list[Soak], n_params: int
    ) -> tuple[list[Intervals], dict[str, Any]]:
        """Static intervals cut to the soaks, the threshold chosen by the lowest residual per
        degree of freedom of the per-soak fits."""
        o = self.options
        detector = make_detector(
            t_ns, accel, window_s=o.window_s, init_static_s=o.init_static_s,
            min_interval_s=o.min_interval_s,
        )  # fmt: skip
        free = np.ones(9, dtype=bool)
        free[3:6] = n_params == 9

        def score(intervals: Intervals) -> float | None:
            rss, dof = 0.0, 0
            for iv in cut_to_soaks(intervals, soaks, detector.min_samples):
                means = iv.means(accel)
                if len(iv) <= n_params or am.distinct_poses(means) < n_params:
                    continue
                try:
                    problem = am.NormProblem(
                        means, o.gravity, am.initial_guess(means, o.gravity), free
                    )
                    r = problem.residual(am.solve_lm(problem, xtol=1e-8).x) * o.gravity / am.MG
                except (FitError, np.linalg.LinAlgError, ValueError):
                    continue
                rss, dof = rss + float(r @ r), dof + len(r) - n_params
            return rss / dof if dof > 0 else None

        choice = choose_threshold(detector, o.thresholds, score, n_params)
        info = {
            "threshold_k": choice.k,
            "threshold_scores": {f"{k:g}": s for k, s in choice.scores.items()},
        }
        return cut_to_soaks(choice.intervals, soaks, detector.min_samples), info

    def _fit_accel(self, s: Soak, accel: np.ndarray, n_params: int) -> str | None:
        """The 9- (or 6-) parameter model at one soak; returns why not, or None."""
        o = self.options
        iv = s.intervals
        if iv is None or len(iv) <= n_params:
            return f"{0 if iv is None else len(iv)} static intervals (need more than {n_params})"
        means = iv.means(accel)
        distinct = am.distinct_poses(means)
        if distinct < n_params:
            return f"{distinct} distinct poses (need {n_params})"
        free = np.ones(9, dtype=bool)
        free[3:6] = o.misalignment
        try:
            problem = am.NormProblem(means, o.gravity, am.initial_guess(means, o.gravity), free)
            sol = am.solve_lm(problem)
        except (FitError, np.linalg.LinAlgError, ValueError) as exc:
            return f"the accelerometer fit failed ({exc})"
        unc = am.uncertainty(problem, sol.x)
        p = sol.params
        s.accel = {"scale": p.scale, "misalignment": p.angles, "bias": p.bias}
        s.accel_std = {
            "scale": np.asarray(unc.get("scale_std", [np.nan] * 3)),
            "misalignment": np.asarray(unc.get("misalignment_std_rad", [np.nan] * 3)),
            "bias": np.asarray(unc.get("bias_std", [np.nan] * 3)),
        }
        residual = (np.linalg.norm(p.apply(means), axis=1) - o.gravity) / am.MG
        s.info |= {
            "intervals": len(iv),
            "distinct_poses": distinct,
            "accel_residual_mg": float(np.sqrt(np.mean(residual**2))),
            "condition_number": unc["condition_number"],
        }
        return None

    def _fit_gyro(self, s: Soak, t_ns: np.ndarray, accel: np.ndarray, gyro: np.ndarray) -> None:
        """Gyro bias at one soak (mean over the static intervals) and, where the pose
        transitions observe them, its scale and misalignment."""
        iv = s.intervals
        means = iv.means(gyro)
        w = iv.lengths / iv.lengths.sum()
        bias = w @ means
        inside = iv.mask(len(gyro))
        std = gyro[inside].std(axis=0) / np.sqrt(max(int(inside.sum()), 1))
        s.gyro, s.gyro_std = {"bias": bias}, {"bias": std}
        if not self.options.gyro_matrix:
            return
        if len(iv) - 1 < GYRO_MIN_TRANSITIONS:
            s.info["gyro_matrix"] = f"{len(iv) - 1} pose transitions (need {GYRO_MIN_TRANSITIONS})"
            return
        p = am.NineParams(s.accel["scale"], s.accel["misalignment"], s.accel["bias"])
        seg = slice(int(iv.start[0]), int(iv.stop[-1]))
        local = Intervals(iv.start - seg.start, iv.stop - seg.start)
        t_s, _ = sample_clock(t_ns[seg])
        moves = gm.PoseTransitions.build(t_s, gyro[seg], p.apply(accel[seg]), local)
        fit = gm.fit_static_poses(moves, bias, models=[FULL_GYRO_MODEL])
        condition = fit["fit"].condition_number()
        s.info["gyro_condition_number"] = condition
        s.info["gyro_transition_residual_deg"] = float(np.sqrt(np.mean(fit["residual_deg"] ** 2)))
        if not condition < GYRO_MAX_CONDITION:
            s.info["gyro_matrix"] = f"condition number {condition:.3g}"
            return
        s.gyro |= {
            "scale": np.asarray(fit["fit"].scale),
            "misalignment": np.asarray(fit["fit"].x[3:]),
        }

    # -- against temperature -----------------------------------------------------------------
    def _gyro_quantities(self, soaks: list[Soak], ctx: StageContext) -> dict[str, tuple[str, ...]]:
        """The gyro quantities to fit against temperature: all three where 2 or more soaks
        observe the scale and misalignment, else the bias alone (with a warning)."""
        with_matrix = [s for s in soaks if "scale" in s.gyro]
        if len(with_matrix) >= 2 and self.options.gyro_matrix:
            return dict(GYRO_NAMES)
        if self.options.gyro_matrix:
            reasons = sorted({s.info.get("gyro_matrix", "") for s in soaks} - {""})
            ctx.warn(
                f"gyro scale and misalignment not fitted ({len(with_matrix)} soak(s) observe "
                f"them: {'; '.join(reasons) or 'no pose transitions'}); the gyro step corrects "
                "its bias only"
            )
        for s in soaks:
            s.gyro = {"bias": s.gyro["bias"]}
            s.gyro_std = {"bias": s.gyro_std["bias"]}
        return {"bias": GYRO_NAMES["bias"]}

    def _polynomials(
        self,
        soaks: list[Soak],
        which: str,
        tref: float,
        names: dict[str, tuple[str, ...]],
        ctx: StageContext,
    ) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
        """Each parameter component as a polynomial in T - tref (see the module docstring)."""
        o = self.options
        poly: dict[str, list[dict[str, Any]]] = {}
        info: dict[str, Any] = {}
        for quantity, labels in names.items():
            have = [s for s in soaks if quantity in getattr(s, which)]  # the gyro matrix: where
            x = {"T": np.array([s.temperature for s in have]) - tref}  # the poses observe it
            m = len(have)
            if o.order is not None and o.order > m - 1:
                raise ctx.fail(f"order {o.order} needs {o.order + 1} soaks; found {m}")
            orders = [o.order] if o.order is not None else range(min(MAX_ORDER, m - 1) + 1)
            candidates = [tm.poly_terms(k) for k in orders]
            values = np.array([getattr(s, which)[quantity] for s in have])
            stds = np.array(
                [
                    getattr(s, f"{which}_std").get(quantity, np.full(len(labels), np.nan))
                    for s in have
                ]
            )
            comps, info[quantity] = [], {}
            for j, label in enumerate(labels):
                sd = stds[:, j] if stds.ndim == 2 else np.full(m, np.nan)
                w = 1.0 / sd**2 if np.all(np.isfinite(sd)) and np.all(sd > 0) else np.ones(m)
                if len(candidates) == 1:
                    choice = tm.Choice(
                        candidates[0],
                        tm.weighted_lstsq(tm.design(candidates[0], x), values[:, j], w),
                    )
                else:
                    choice = tm.select_terms(candidates, x, values[:, j], w)
                comps.append({"terms": choice.terms, "coefficients": np.asarray(choice.coef)})
                info[quantity][label] = {
                    "terms": choice.terms,
                    "coefficients": [float(c) for c in choice.coef],
                    **({"aicc": choice.scores} if choice.scores else {}),
                }
            poly[quantity] = comps
        return poly, info

    # -- outputs -----------------------------------------------------------------------------
    @staticmethod
    def _soak_record(s: Soak) -> dict[str, Any]:
        out: dict[str, Any] = {"temperature": s.temperature, "samples": [s.start, s.stop], **s.info}
        for which in ("accel", "gyro"):
            values = getattr(s, which)
            if values:
                out[which] = {k: v.tolist() for k, v in values.items()}
                out[f"{which}_std"] = {k: v.tolist() for k, v in getattr(s, f"{which}_std").items()}
        return out

    def _metrics(
        self,
        soaks: list[Soak],
        steps: list[ThermalMatrixStep],
        accel: np.ndarray,
        gyro: np.ndarray,
        temp: np.ndarray,
        ctx: StageContext,
    ) -> dict[str, Any]:
        """RMS over every soak's static-interval means of | |a| - g | (mg) raw, with each soak's
        own fit, with the thermal model at each interval's temperature, and with the calibration
        of the soak nearest tref used at every temperature; likewise the gyro's residual bias."""
        g = self.options.gravity
        nearest = min(soaks, key=lambda s: abs(s.temperature - steps[0].tref))
        one = am.NineParams(
            nearest.accel["scale"], nearest.accel["misalignment"], nearest.accel["bias"]
        )
        rows: dict[str, list[np.ndarray]] = {k: [] for k in ("raw", "soak", "thermal", "one")}
        gyro_rows: dict[str, list[np.ndarray]] = {k: [] for k in ("raw", "thermal", "one")}
        for s in soaks:
            iv = s.intervals
            means = iv.means(accel)
            t_iv = iv.means(temp[:, None])[:, 0]
            own = am.NineParams(s.accel["scale"], s.accel["misalignment"], s.accel["bias"])
            p = steps[0].values_at(t_iv)
            thermal = apply_matrix_form("accel", means, p["scale"], p["misalignment"], p["bias"])
            for key, values in (
                ("raw", means),
                ("soak", own.apply(means)),
                ("thermal", thermal),
                ("one", one.apply(means)),
            ):
                rows[key].append((np.linalg.norm(values, axis=1) - g) / am.MG)
            if len(steps) > 1:
                gyro_means = iv.means(gyro)
                q = steps[1].values_at(t_iv)
                gyro_rows["raw"].append(gyro_means)
                gyro_rows["thermal"].append(
                    apply_matrix_form("gyro", gyro_means, q["scale"], q["misalignment"], q["bias"])
                )
                gyro_rows["one"].append(gyro_means - nearest.gyro["bias"])

        def rms(parts: list[np.ndarray]) -> float:
            x = np.concatenate(parts)
            return float(np.sqrt(np.mean(x**2)))

        accel_m = {
            "raw": rms(rows["raw"]),
            "per_soak_fits": rms(rows["soak"]),
            "thermal_model": rms(rows["thermal"]),
            "one_temperature": rms(rows["one"]),
            "one_temperature_at": nearest.temperature,
        }
        out: dict[str, Any] = {"soaks": len(soaks), "accel_norm_residual_mg": accel_m}
        if len(steps) > 1:
            out["gyro_static_residual_rad_s"] = {
                k: [float(v) for v in np.sqrt(np.mean(np.vstack(parts) ** 2, axis=0))]
                for k, parts in gyro_rows.items()
            }
        bound = 2.0 * accel_m["per_soak_fits"] + 0.05
        ctx.check(
            accel_m["thermal_model"] <= bound,
            f"the polynomials in temperature leave {accel_m['thermal_model']:.3g} mg of | |a| - g | "
            f"at the soaks > {bound:.3g} mg (2 x the per-soak fits' {accel_m['per_soak_fits']:.3g} "
            "mg + 0.05)",
        )
        return out

    def _record(self, ctx: StageContext, soaks: list[Soak], steps: list[ThermalMatrixStep]) -> None:
        from imupipe.stages.thermal.rerun import record_soak  # imports rerun lazily

        temps = np.array([s.temperature for s in soaks])
        grid = np.linspace(temps.min(), temps.max(), 100)
        for step in steps:
            which = step.sensor
            at = step.values_at(grid)
            unit = "m/s^2" if which == "accel" else "rad/s"
            values, curves = {}, {}
            labels = ACCEL_NAMES if which == "accel" else GYRO_NAMES
            for quantity in step.parameters:
                data = np.array([getattr(s, which)[quantity] for s in soaks])
                scale = 1e3 if quantity == "misalignment" else 1.0
                qunit = {
                    "scale": f"{unit} per raw unit",
                    "misalignment": "mrad",
                    "bias": "raw unit",
                }[quantity]
                values[quantity] = (
                    data * scale,
                    [f"{which} {c} {quantity}" for c in labels[quantity]],
                    qunit,
                )
                curves[quantity] = at[quantity] * scale
            record_soak(ctx, which, temps, values, curves, grid)
