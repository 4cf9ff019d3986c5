"""``temperature`` stage: bias of the gyro or accel against temperature (seeds 000 and 004).

Model, per axis: ``bias = f(T, dT [, Ta, dTa])`` with T the device temperature (degC), dT its
rate dT/dt (degC/s), Ta/dTa the ambient temperature and its rate when the log has an
``ambient_temperature`` column; f is linear in named terms (:mod:`imupipe.stages.thermal_models`).
``corrected = raw - f(T, dT)`` in the sensor's SI unit (rad/s or m/s^2).

Preprocessing: the temperature stream is interpolated onto the IMU timestamps
(:func:`imupipe.readers.table.interpolate`); sensor and temperature are block-averaged
(seed 000's ``ImuDataSum``: :func:`imupipe.stages.blocks.block_means`, ``window`` samples or
``window_s`` seconds, default 10 s); dT is the gradient of the block-mean temperature over the
block centres. The bias of a block is its mean minus the ``reference`` (the true output: zero for
a gyro; for an accelerometer, by default gravity, 9.80665 m/s^2 along the mean specific force).
Blocks are weighted by temperature bin (``bin_width`` degC, heating, cooling and soak apart) so
that slow parts of a ramp and long soaks do not outweigh fast ones (PX4 resamples by temperature
for the same reason).

The correction (:class:`TemperatureStep`) recomputes T and dT the same way on any log, clamps
T (and Ta) to the fitted range and warns when a sample lies more than 0.5 degC outside it; rates
outside the fitted range are extrapolated, with a warning. A fitted span under 10 degC is
refused, under 24 degC warned about (ArduPilot asks for 10 degC at least).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import (
    SENSOR_UNITS,
    has_stream,
    sensor,
)
from imupipe.stages import thermal_models as tm
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.blocks import block_means
from imupipe.stages.stepwise import candidate_terms, stepwise
from imupipe.stages.stillness import G0
from imupipe.stages.temperature_step import (
    AXES,
    Prepared,
    TemperatureStep,
    temperature_at,
)

MIN_SPAN = 10.0
"""degC: a narrower fitted temperature span is refused."""
WARN_SPAN = 24.0
"""degC: a narrower span is warned about."""
SOAK_RATE = 0.05 / 60.0
"""degC/s: blocks with |dT| below this count as soak (neither heating nor cooling)."""


def bin_weights(temp: np.ndarray, direction: np.ndarray, width: float) -> np.ndarray:
    """1 / (blocks in the same temperature bin and direction), normalised to mean 1."""
    if width <= 0:
        return np.ones(len(temp))
    cell = np.floor(temp / width).astype(np.int64) * 3 + direction + 1
    _, inverse, count = np.unique(cell, return_inverse=True, return_counts=True)
    w = 1.0 / count[inverse]
    return w * (len(w) / w.sum())


class TemperatureStage(Stage):
    type = "temperature"
    corrects = True

    @dataclass
    class Options:
        sensor: Literal["gyro", "accel"] = "gyro"
        """Which sensor to compensate (every axis)."""
        model: Literal["poly", "seed000", "piecewise", "stepwise"] = "poly"
        order: int = 3
        """poly: polynomial order in T - Tref (0..5); stepwise: highest power of T offered."""
        rate_terms: list[str] = field(default_factory=lambda: ["dT"])
        """poly: rate terms among dT, dT^2, T*dT (empty: a plain polynomial in T)."""
        tref: float | None = None
        """degC; default the middle of the fitted range (seed000: 0, the formula as written)."""
        window: int | None = None
        """Samples per block (seed 000 uses 500)."""
        window_s: float | None = None
        """Seconds per block (default 10 s when neither is given)."""
        bin_width: float = 1.0
        """degC; temperature bins for weighting (0: every block weighs the same)."""
        segment_width: float = 10.0
        """piecewise: degC between knots."""
        criterion: Literal["f_test", "adj_r2"] = "f_test"
        """stepwise: how terms are chosen."""
        alpha_in: float = 0.05
        alpha_out: float = 0.10
        reference: list[float] | None = None
        """The true sensor output during the recording (3 values, SI); default zero for a gyro,
        gravity along the mean specific force for an accelerometer."""
        validate: str | None = None
        """An input to evaluate the fitted correction on (held out from the fit)."""
        write_blocks: bool = False
        """Also write the block means used by the fit as ``<name>_blocks.csv``."""
        turntable_rate: float | None = None
        """rad/s: the log holds turntable runs at +rate and -rate (gyro only, seed 004); fit the
        scale factor of each turned axis against temperature; blocks with turning are left out of
        the bias fit."""
        scale_order: int = 2
        """Polynomial order of the scale factor in T - Tref (piecewise model: linear per segment)."""

    @classmethod
    def sensors_for(cls, options: Any) -> tuple[str, ...]:
        return (options.sensor, "temperature")

    # -- helpers -------------------------------------------------------------------------------
    def _window(self) -> tuple[int | None, float | None]:
        o = self.options
        if o.window is None and o.window_s is None:
            return None, 10.0
        return o.window, o.window_s

    def prepare(self, table: pa.Table, ctx: StageContext, input_name: str) -> Prepared:
        """Block means and rates of ``table`` (see the module docstring)."""
        o = self.options
        if not has_stream(table, "imu"):
            raise ctx.fail(f"input '{input_name}' has no IMU samples")
        if not has_stream(table, "temperature"):
            raise ctx.fail(
                f"input '{input_name}' has no temperature samples (map csv.temperature or set "
                "temperature_topic)"
            )
        data = sensor(table, o.sensor)
        if not np.isfinite(data.values).all():
            bad = int(np.flatnonzero(~np.isfinite(data.values).all(axis=1))[0])
            raise ctx.fail(f"input '{input_name}': non-finite {o.sensor} sample at sample {bad}")
        window, window_s = self._window()
        temp = temperature_at(table, data.t_ns)
        columns = [data.values, temp[:, None]]
        has_ambient = "ambient_temperature" in table.column_names and table.column(
            "ambient_temperature"
        ).null_count < len(table)
        if has_ambient:
            columns.append(temperature_at(table, data.t_ns, "ambient_temperature")[:, None])
        blocks = block_means(data.t_ns, np.hstack(columns), window, window_s)
        if len(blocks.t_ns) < 2:
            raise ctx.fail(f"input '{input_name}': fewer than 2 blocks of {window or window_s}")
        t_s = (blocks.t_ns - blocks.t_ns[0]).astype(np.float64) * 1e-9
        means = blocks.means[:, :3]
        variables = {"T": blocks.means[:, 3], "dT": np.gradient(blocks.means[:, 3], t_s)}
        if has_ambient:
            variables["Ta"] = blocks.means[:, 4]
            variables["dTa"] = np.gradient(blocks.means[:, 4], t_s)
        direction = np.where(
            variables["dT"] > SOAK_RATE, 1, np.where(variables["dT"] < -SOAK_RATE, -1, 0)
        )
        pairs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        keep = np.ones(len(blocks.t_ns), dtype=bool)
        if o.turntable_rate is not None:
            rate = float(o.turntable_rate)
            turning = (np.abs(data.values) > rate / 2).any(axis=1)
            busy = block_means(data.t_ns, turning.astype(np.float64), window, window_s).means > 0
            keep = ~(busy | np.r_[busy[1:], False] | np.r_[False, busy[:-1]])
            for i, axis in enumerate(AXES):
                pair_t, pair_sf = tm.turntable_pairs(data.t_ns, data.values[:, i], temp, rate)
                if len(pair_t):
                    pairs[axis] = (pair_t, pair_sf)
        variables = {k: v[keep] for k, v in variables.items()}
        means, direction = means[keep], direction[keep]
        reference = self._reference(means)
        return Prepared(
            blocks.t_ns[keep], means - reference, variables, direction, reference, pairs
        )

    def _reference(self, means: np.ndarray) -> np.ndarray:
        if self.options.reference is not None:
            return np.asarray(self.options.reference, dtype=np.float64)
        if self.options.sensor == "gyro":
            return np.zeros(3)
        mean = means.mean(axis=0)
        return G0 * mean / np.linalg.norm(mean)

    # -- fit -----------------------------------------------------------------------------------
    def check_options(self, ctx: StageContext) -> list[str]:
        """Raise on an option value that cannot work; returns the poly model's terms."""
        o = self.options
        problems = [
            (o.reference is not None and len(o.reference) != 3, "'reference' must hold 3 values"),
            (
                o.window is not None and o.window_s is not None,
                "give 'window' or 'window_s', not both",
            ),
            (o.window is not None and o.window < 1, "'window' must be >= 1 sample"),
            (o.window_s is not None and o.window_s <= 0, "'window_s' must be > 0"),
            (o.bin_width < 0, "'bin_width' must be >= 0 degC"),
            (o.segment_width <= 0, "'segment_width' must be > 0 degC"),
            (o.scale_order < 0, "'scale_order' must be >= 0"),
            (not 0 < o.alpha_in <= o.alpha_out < 1, "need 0 < alpha_in <= alpha_out < 1"),
            (
                o.turntable_rate is not None and o.turntable_rate <= 0,
                "'turntable_rate' must be > 0",
            ),
            (
                o.model == "stepwise" and not 2 <= o.order <= tm.MAX_ORDER,
                "stepwise 'order' must be 2..5",
            ),
        ]
        for bad, message in problems:
            if bad:
                raise ctx.fail(message)
        if o.validate is not None and o.validate not in ctx.tables:
            raise ctx.fail(
                f"validate: unknown input '{o.validate}' (inputs: {', '.join(ctx.tables)})"
            )
        try:
            return tm.poly_terms(o.order, o.rate_terms) if o.model == "poly" else []
        except ValueError as exc:
            raise ctx.fail(str(exc)) from None

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        o = self.options
        base_terms = self.check_options(ctx)
        prep = self.prepare(table, ctx, ctx.input_name)
        temp = prep.variables["T"]
        lo, hi = float(temp.min()), float(temp.max())
        if hi - lo < MIN_SPAN:
            raise ctx.fail(
                f"the temperature spans only {hi - lo:.3g} degC ({lo:.4g}..{hi:.4g}); a temperature "
                f"fit needs at least {MIN_SPAN:g} degC (heat or cool the IMU while recording)"
            )
        if hi - lo < WARN_SPAN:
            ctx.warn(
                f"the temperature spans only {hi - lo:.3g} degC; the correction is clamped outside "
                f"{lo:.4g}..{hi:.4g} degC"
            )
        tref = o.tref if o.tref is not None else (0.0 if o.model == "seed000" else (lo + hi) / 2)
        weights = bin_weights(temp, prep.direction, o.bin_width)
        rel = self._relative(prep.variables, tref)
        knots = None
        if o.model == "piecewise":
            knots = tm.segment_knots(lo, hi, o.segment_width)
        axes, selection_log = [], {}
        for i, axis in enumerate(AXES):
            y = prep.bias[:, i]
            if o.model == "piecewise":
                terms, coef = tm.fit_piecewise(rel, y, weights, knots - tref)
            elif o.model == "stepwise":
                names = candidate_terms([v for v in tm.VARIABLES if v in rel], o.order)
                sel = stepwise(
                    tm.design(names, rel),
                    y,
                    names,
                    weights,
                    criterion=o.criterion,
                    alpha_in=o.alpha_in,
                    alpha_out=o.alpha_out,
                )
                terms, coef = sel.terms, sel.coef
                selection_log[axis] = {"adj_r2": sel.adj_r2, "steps": sel.history}
            else:
                terms = list(tm.SEED000_TERMS) if o.model == "seed000" else base_terms
                coef = tm.weighted_lstsq(tm.design(terms, rel), y, weights)
            axes.append({"terms": terms, "coefficients": np.asarray(coef)})
        ranges = {k: [float(v.min()), float(v.max())] for k, v in prep.variables.items()}
        step = TemperatureStep(
            type=self.type,
            sensor=o.sensor,
            model=o.model,
            tref=float(tref),
            window=self._window()[0],
            window_s=self._window()[1],
            axes=axes,
            ranges=ranges,
            knots=None if knots is None else knots.tolist(),
            scale=self._fit_scale(prep, tref, ctx) if o.turntable_rate is not None else None,
            params={"reference": prep.reference.tolist()},
            quiet=ctx.quiet,
        )
        fitted = step.bias(rel)
        metrics = self._metrics(prep.bias, fitted)
        results: dict[str, Any] = {
            "sensor": o.sensor,
            "unit": SENSOR_UNITS[o.sensor],
            "model": o.model,
            "tref": float(tref),
            "temperature_range": [lo, hi],
            "rate_range": ranges["dT"],
            "blocks": len(prep.t_ns),
            "terms": {ax: step.axes[i]["terms"] for i, ax in enumerate(AXES)},
            "coefficients": {
                ax: [float(c) for c in step.axes[i]["coefficients"]] for i, ax in enumerate(AXES)
            },
            "metrics": metrics,
        }
        if selection_log:
            results["selection"] = selection_log
        if step.scale is not None:
            results["scale"] = self._scale_metrics(prep, step)
        if o.validate is not None:
            results["metrics"]["validate"] = self._validate(step, ctx)
        artifacts = {}
        if o.write_blocks:
            artifacts[f"{ctx.name}_blocks.csv"] = self._blocks_csv(prep, weights)
        if getattr(ctx.recorder, "enabled", False):
            from imupipe.stages.temperature_rerun import record_fit  # imports rerun lazily

            record_fit(ctx, prep, step, fitted)
        return StageOutput(results=results, step=step, artifacts=artifacts)

    def _fit_scale(
        self, prep: Prepared, tref: float, ctx: StageContext
    ) -> dict[str, dict[str, Any]]:
        """sf(T) per turned axis: a polynomial of order ``scale_order`` (at most pairs - 1)."""
        if self.options.sensor != "gyro":
            raise ctx.fail("'turntable_rate' applies to sensor = \"gyro\" only")
        if not prep.pairs:
            raise ctx.fail(
                f"turntable_rate = {self.options.turntable_rate} rad/s, but no gyro axis has a "
                "+rate run next to a -rate run (a run reads beyond rate/2)"
            )
        scale = {}
        for axis, (pair_t, pair_sf) in prep.pairs.items():
            order = max(0, min(self.options.scale_order, len(pair_t) - 1))
            terms = tm.poly_terms(order)
            coef = tm.weighted_lstsq(tm.design(terms, {"T": pair_t - tref}), pair_sf)
            scale[axis] = {"terms": terms, "coefficients": coef}
        return scale

    @staticmethod
    def _scale_metrics(prep: Prepared, step: TemperatureStep) -> dict[str, Any]:
        """Per turned axis: pairs, the measured scale factors' range and the fit's RMSE."""
        out = {}
        for axis, model in (step.scale or {}).items():
            pair_t, pair_sf = prep.pairs[axis]
            fit = step.scale_factor(model, {"T": pair_t - step.tref})
            out[axis] = {
                "pairs": len(pair_t),
                "scale_range": [float(pair_sf.min()), float(pair_sf.max())],
                "rmse": float(np.sqrt(np.mean((pair_sf - fit) ** 2))),
            }
        return out

    @staticmethod
    def _relative(variables: dict[str, np.ndarray], tref: float) -> dict[str, np.ndarray]:
        rel = dict(variables)
        rel["T"] = variables["T"] - tref
        if "Ta" in rel:
            rel["Ta"] = variables["Ta"] - tref
        return rel

    @staticmethod
    def _metrics(bias: np.ndarray, fitted: np.ndarray | None) -> dict[str, Any]:
        """Per axis: RMS and peak-to-peak of the block bias before and after; RMSE and R^2."""
        out: dict[str, Any] = {}
        after = bias - fitted if fitted is not None else None
        for i, axis in enumerate(AXES):
            b = bias[:, i]
            m = {"rms_before": float(np.sqrt(np.mean(b * b))), "p2p_before": float(np.ptp(b))}
            if after is not None:
                r = after[:, i]
                ss = float(np.sum((b - b.mean()) ** 2)) or 1.0
                m |= {
                    "rms_after": float(np.sqrt(np.mean(r * r))),
                    "p2p_after": float(np.ptp(r)),
                    "rmse": float(np.sqrt(np.mean(r * r))),
                    "r2": 1.0 - float(np.sum(r * r)) / ss,
                }
                m["reduction"] = m["rms_before"] / max(m["rms_after"], 1e-300)
            out[axis] = m
        return out

    def _validate(self, step: TemperatureStep, ctx: StageContext) -> dict[str, Any]:
        """The same metrics on the ``validate`` input: blocks before and after the step."""
        name = self.options.validate
        table = ctx.tables[name]
        before = self.prepare(table, ctx, name)
        after = self.prepare(step.apply(table), ctx, name)
        metrics = self._metrics(before.bias, before.bias - after.bias)
        for axis, (_, sf_after) in after.pairs.items():
            sf_before = before.pairs[axis][1]
            metrics[axis] |= {
                "scale_error_before": float(np.max(np.abs(sf_before - 1.0))),
                "scale_error_after": float(np.max(np.abs(sf_after - 1.0))),
            }
        metrics["input"] = name
        metrics["blocks"] = len(before.t_ns)
        return metrics

    @staticmethod
    def _blocks_csv(prep: Prepared, weights: np.ndarray) -> str:
        """The fit's data: block centre, bias per axis (SI), T (degC), dT (degC/s) [, Ta, dTa],
        the block's weight."""
        names = ["t_ns", "bias_x", "bias_y", "bias_z", *prep.variables, "weight"]
        cols = [prep.t_ns.astype(np.float64), *prep.bias.T, *prep.variables.values(), weights]
        rows = np.column_stack(cols)
        lines = [",".join(names)]
        lines += [f"{int(r[0])}," + ",".join(f"{v:.17g}" for v in r[1:]) for r in rows]
        return "\n".join(lines) + "\n"
