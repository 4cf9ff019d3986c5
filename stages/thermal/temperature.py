"""``temperature`` stage: bias of the gyro or accel against temperature.

Model, per axis: ``bias = f(T, dT [, Ta, dTa] | Ts, dTs)`` with T the measured temperature
(degC), dT its rate (degC/s), Ta/dTa the ambient temperature and its rate when the log has an
``ambient_temperature`` column, Ts/dTs the sensing element's lagged temperature and its rate (the
``lag`` model); f is linear in named terms (:mod:`imupipe.stages.thermal.models`).
``corrected = raw - f(...)`` in the sensor's SI unit (rad/s or m/s^2).

Preprocessing (:mod:`imupipe.stages.thermal.track`, shared with the correction): the temperature
stream is interpolated onto the IMU stamps; samples are grouped into blocks (``window`` samples,
or ``window_s`` seconds within each burst of a gappy log; default 10 s), each replaced by its mean
(the block means of the MATLAB example in "MEMS 惯性测量组件的温度误差补偿模型研究"); dT is the
three-point derivative of the block temperatures over the block centres. Only **complete** blocks
enter the fit and the metrics (a log's trailing partial block does not). The bias of a block is
its mean minus the ``reference`` (the true output: zero for a gyro; for an accelerometer, by
default gravity, 9.80665 m/s^2, along the mean specific force). Blocks are weighted by their
sample count and by temperature bin (``bin_width`` degC, heating, cooling and soak apart) so that
slow parts of a ramp and long soaks do not outweigh fast ones (PX4 resamples by temperature for
the same reason).

What the data support: a span under 10 degC (ArduPilot's minimum) is warned about, one under
``MIN_SPAN`` refused; rate terms and the lag need the temperature to rise and fall over a common
range (at one temperature, two rates): from a one-direction ramp or soaks they cannot be
identified, and the fit falls back to the terms in T with a warning naming what was dropped.
Unless ``order`` is given, the polynomial order (0..3) and whether the rate term enters are chosen
per axis by the small-sample Akaike criterion.

What enters and what is applied (issue 25, :mod:`imupipe.stages.thermal.choice`): only still
samples enter the blocks (the static-interval detector on the gyro and the accelerometer), so
handling between soaks never enters the fit. The default ``model = "auto"`` fits ``poly``,
``lag`` (where heating and cooling identify it) and ``piecewise`` on all segments of the log but
one and predicts that one, in turn; the model with the lowest held-out error wins (poly unless
another is 10 % better), and ``results.choice`` says which and why. Every fit states the bias it
leaves on another log like this one (``remaining_rms`` with a 95 % interval), and is refused (a
failed quality check, one line with the figures) when it does not predict the held-out segments
better than no compensation (worse by more than 10 % on an axis, or not 10 % better on any), or
when the still periods hold several orientations.

The correction (:class:`~imupipe.stages.thermal.step.TemperatureStep`) recomputes the
variables the same way on any log, clamps temperatures to the fitted range and warns when a
sample lies more than 0.5 degC outside it. The fitted range of T is the lowest and highest
temperature of the samples that entered the fit (the logged range of raw samples, as PX4's
``Tools/process_sensor_caldata.py`` takes ``TMIN``/``TMAX``), not the narrower range of the
block means: the curve holds where the log's samples were, and the exports' ``TC_*_TMIN/TMAX``
and ``INS_TCALi_TMIN/TMAX`` are that range; rates outside the fitted range are extrapolated, with
a warning.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import (
    SENSOR_UNITS,
    STREAM_OF_SENSOR,
    has_stream,
    imu_pairs,
    sensor,
    usable,
)
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.stillness import G0
from imupipe.stages.thermal import choice as tc
from imupipe.stages.thermal import models as tm
from imupipe.stages.thermal.step import (
    AXES,
    Prepared,
    TemperatureStep,
    temperature_samples,
)
from imupipe.stages.thermal.stepwise import candidate_terms, stepwise
from imupipe.stages.thermal.track import Blocking, Track, TrackSpec, Variables

MIN_SPAN = 1.0
"""degC: a narrower fitted temperature span is refused (no temperature term is identifiable)."""
WARN_SPAN = 10.0
"""degC: a narrower span is warned about (ArduPilot asks for 10 degC at least)."""
SOAK_RATE = 0.05 / 60.0
"""degC/s: blocks with |dT| below this count as soak (neither heating nor cooling)."""
MAX_AUTO_ORDER = 3
"""Highest polynomial order tried when the order is chosen by the data."""
MIN_DIRECTION_SHARE = 0.1
"""Heating and cooling must each hold this share of the blocks ..."""
HELD_OUT_MARGIN = 0.1
"""The fit is refused when its held-out RMS exceeds no compensation's by more than this share on
an axis, or is not below it by this share on any axis (an axis without a temperature
dependence reads about 1: equal, not a failure)."""
SWITCH_MARGIN = 0.9
"""``model = "auto"``: lag or piecewise replaces poly when its held-out error (geometric mean over
the axes, relative to no compensation) is below this share of poly's."""
MAG_TURN_DEG = 2.0
"""deg: a magnetometer's corrected field may change direction by this much across a gap between
still periods (its thermal offset over the gap is corrected; the field is tens of uT, a block
mean's noise hundredths of a degree); more: it was turned (refused)."""
TURN_BLOCKS = 3
"""Kept blocks on either side of a gap whose mean field is compared."""
MIN_OVERLAP = 0.25
"""... over temperature ranges that overlap by this share of the span, for a rate term or a lag
to be identifiable (at one temperature, two rates)."""


def bin_weights(temp: np.ndarray, direction: np.ndarray, width: float) -> np.ndarray:
    """1 / (blocks in the same temperature bin and direction), normalised to mean 1."""
    if width <= 0:
        return np.ones(len(temp))
    cell = np.floor(temp / width).astype(np.int64) * 3 + direction + 1
    _, inverse, count = np.unique(cell, return_inverse=True, return_counts=True)
    w = 1.0 / count[inverse]
    return w * (len(w) / w.sum())


def directions_identify_rate(
    temp: np.ndarray, direction: np.ndarray, rate: np.ndarray | None = None
) -> str | None:
    """None when heating and cooling both cover a common temperature range (see
    ``MIN_DIRECTION_SHARE``, ``MIN_OVERLAP``), else why not (for the warning), in words that
    match the data: ``only`` when no block goes the other way, else how many do, with the rate
    range (``rate``: the blocks' degC/s, shown in degC/min)."""
    n = len(temp)
    span = float(np.ptp(temp)) if n else 0.0
    heat, cool = temp[direction > 0], temp[direction < 0]
    rates = (
        ""
        if rate is None or not len(rate)
        else f", at {60 * float(rate.min()):.3g}..{60 * float(rate.max()):.3g} degC/min"
    )
    if len(heat) < MIN_DIRECTION_SHARE * n or len(cool) < MIN_DIRECTION_SHARE * n:
        if len(heat) < MIN_DIRECTION_SHARE * n and len(cool) < MIN_DIRECTION_SHARE * n:
            return (
                f"the temperature is held (soaks), not ramped ({len(heat)} heating and "
                f"{len(cool)} cooling blocks of {n}){rates}"
            )
        falls = len(cool) >= len(heat)
        start, end = (temp.max(), temp.min()) if falls else (temp.min(), temp.max())
        other = len(heat) if falls else len(cool)
        word = "falls" if falls else "rises"
        if other == 0:
            return f"the temperature only {word} ({start:.4g} -> {end:.4g} degC){rates}"
        return (
            f"the temperature mostly {word} ({start:.4g} -> {end:.4g} degC; {other} of {n} "
            f"blocks go the other way, under {MIN_DIRECTION_SHARE:.0%}){rates}"
        )
    overlap = min(heat.max(), cool.max()) - max(heat.min(), cool.min())
    if overlap < MIN_OVERLAP * span:
        return (
            f"heating ({heat.min():.4g}..{heat.max():.4g} degC) and cooling "
            f"({cool.min():.4g}..{cool.max():.4g} degC) overlap over {max(overlap, 0):.3g} degC"
        )
    return None


class TemperatureStage(Stage):
    type = "temperature"
    corrects = True

    @dataclass
    class Options:
        sensor: Literal["gyro", "accel", "mag"] = "gyro"
        """Which sensor to compensate (every axis): ``gyro`` (rad/s), ``accel`` (m/s^2) or
        ``mag`` (tesla; the field of a magnetometer held in one fixed orientation, as in a
        thermal chamber: still periods are judged on the magnetometer itself, the corrected
        field of every still period must point the same way, and the model is normalised to
        zero at ``tref``, PX4's ``TC_M*``)."""
        model: Literal["auto", "poly", "lag", "six_term", "piecewise", "stepwise"] = "auto"
        """The bias model. ``auto`` (default): the one of ``poly``, ``lag`` and ``piecewise``
        that predicts held-out segments of the log best (``lag`` only where heating and cooling
        identify it; another model replaces ``poly`` only when its held-out error, geometric
        mean over the axes, is at least 10 % lower); the choice and its figures are in
        ``results.choice``. ``rate_terms`` or ``turntable_rate`` given with ``auto`` mean
        ``poly``, ``lag_s`` means ``lag``. Or one named: ``poly`` (a polynomial in T, its order and the ``dT`` term chosen by
        AICc), ``lag`` (a polynomial in the sensing element's temperature Ts, a first-order lag
        of T whose time constant is fitted), ``six_term`` (``a1 T^2 + a2 T + a3 dT^2 + a4 dT +
        a5 T dT + a6``, the MATLAB example of the temperature-calibration method), ``piecewise``
        (linear per temperature segment plus ``k_dt x dT``, the gyro patent's model) or
        ``stepwise`` (terms in T, dT and the ambient Ta, dTa chosen by stepwise regression)."""
        order: int | None = None
        """poly, lag: polynomial order (0..5); default: chosen per axis by the data (0..3).
        stepwise: highest power of T offered (default 3)."""
        rate_terms: list[str] | None = None
        """poly: rate terms among dT, dT^2, T*dT; lag: dTs. Default: dT (poly) or dTs (lag),
        kept where the data choose it; a list given is fitted as given; [] leaves them out."""
        lag_s: float | None = None
        """lag: the sensing element's time constant, s (default: fitted)."""
        tref: float | None = None
        """degC; default the middle of the fitted range (six_term: 0, the formula as written)."""
        window: int | None = None
        """Samples per block."""
        window_s: float | None = None
        """Seconds per block (default 10 s when neither is given)."""
        bin_width: float = 1.0
        """degC; blocks are weighted by their sample count / the blocks in the same temperature
        bin and direction (heating, cooling), so slow stretches and long soaks do not outweigh
        fast ones; 0: by the sample count only."""
        segment_width: float = 10.0
        """piecewise: degC between knots."""
        criterion: Literal["f_test", "adj_r2"] = "f_test"
        """stepwise: how terms are chosen, ``f_test`` (forward-backward by the F-test's p-value,
        ``alpha_in``/``alpha_out``) or ``adj_r2`` (while the adjusted R^2 rises)."""
        alpha_in: float = 0.05
        """stepwise, f_test: a term enters when its p-value is below this."""
        alpha_out: float = 0.10
        """stepwise, f_test: a term leaves when its p-value rises above this."""
        reference: list[float] | None = None
        """The true sensor output during the recording (3 values, SI); default zero for a gyro,
        gravity along the mean specific force for an accelerometer."""
        validate: str | None = None
        """An input to evaluate the fitted correction on (held out from the fit, as corrected by
        the stages before); a correction that raises its temperature-driven variation on an axis
        fails a quality check."""
        write_blocks: bool = False
        """Also write the fit's data (block bias, T, dT [, Ts, dTs], samples, weight) as
        ``<name>_blocks.csv``."""
        turntable_rate: float | None = None
        """rad/s: the log holds turntable runs at +rate and -rate (gyro only; the gyro patent's
        method); fit the scale factor of each turned axis against temperature; blocks with
        turning are left out of the bias fit."""
        scale_order: int = 2
        """Polynomial order of the scale factor in T - Tref."""
        still_threshold: float = field(default=tc.STILL_K, metadata={"min": 0.0})
        """Only still samples enter the fit: a sample is still where the windowed variance of
        the accelerometer and of the gyroscope (1 s, or 10 samples on slower logs) is below this
        many times its noise floor (the static-interval detector of the multi-position stages);
        handling and moves between soaks are left out, and a block enters when half its samples
        are still. 0: every sample enters (as before issue 25)."""

    @classmethod
    def sensors_for(cls, options: Any) -> tuple[str, ...]:
        return (options.sensor, "temperature")

    # -- helpers -------------------------------------------------------------------------------
    def blocking(self) -> Blocking:
        o = self.options
        if o.window is None and o.window_s is None:
            return Blocking(window_s=10.0)
        return Blocking(o.window, o.window_s)

    def prepare(self, table: pa.Table, ctx: StageContext, input_name: str) -> Prepared:
        """Complete blocks of ``table`` (see the module docstring)."""
        o = self.options
        stream = STREAM_OF_SENSOR[o.sensor]
        if not has_stream(table, stream):
            what = "IMU" if stream == "imu" else "magnetometer"
            raise ctx.fail(f"input '{input_name}' has no {what} samples")
        if not len(temperature_samples(table, "temperature")[0]):
            raise ctx.fail(
                f"input '{input_name}' has no temperature samples (map csv.temperature or set "
                "temperature_topic)"
            )
        data = sensor(table, o.sensor)
        what = {"gyro": "gyroscope", "accel": "accelerometer", "mag": "magnetometer"}[o.sensor]
        # an axis with no finite value is named; a constant one fits a zero drift (each axis
        # has its own model)
        axes = [f"{o.sensor} {a}" for a in AXES]
        ctx.finite(data, f"{what} ({input_name})", minimum=2, axes=axes)
        finite = usable(data.values).all(axis=1)
        channels = ["temperature"]
        if len(temperature_samples(table, "ambient_temperature")[0]):
            channels.append("ambient_temperature")
        blocking = self.blocking()
        track = Track(TrackSpec(tuple(channels), blocking, keep_blocks=True))
        temps = [temperature_samples(table, c) for c in channels]
        v = Variables.concat([track.push(data.t_ns, temps), track.finish()])
        b = track.blocks
        ids = v.block - b.id[0]
        m = len(b)

        def block_sums(mask: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """Per block: the samples in ``mask`` and their sums (m, 3)."""
            count = np.bincount(ids, weights=mask, minlength=m)
            sums = np.column_stack(
                [np.bincount(ids, weights=np.where(mask, c, 0.0), minlength=m) for c in values.T]
            )
            return count, sums

        n_finite, sums = block_sums(finite, data.values)
        complete = b.complete(blocking) & (n_finite >= 0.5 * b.count)
        still = self._still(table, data, finite)
        keep, moving = complete, 0
        if still is not None:
            finite = finite & still
            n_finite, sums = block_sums(finite, data.values)
            keep = complete & (n_finite >= tc.MIN_STILL_SHARE * b.count)
            moving = int(np.count_nonzero(complete & ~keep))
        # the noise of a block mean: its two halves' means differ by noise alone (drift inside
        # a block is far smaller), E[(m1 - m2)^2] / 4 = var(mean), correlated noise included
        first = data.t_ns < b.centre[ids]
        n1, s1 = block_sums(finite & first, data.values)
        n2, s2 = block_sums(finite & ~first, data.values)
        noise = (s1 / np.maximum(n1, 1)[:, None] - s2 / np.maximum(n2, 1)[:, None]) ** 2 / 4
        noise[(n1 == 0) | (n2 == 0)] = np.nan
        accel_means = None
        # the IMU's orientation from gravity (a magnetometer's: its corrected field, after the fit)
        acc = data.values
        if o.sensor == "gyro":  # sampled apart: the accelerometer on the gyro's stamps
            _, accel, note = imu_pairs(table)
            acc = accel.values
            if note:
                ctx.warn(note)
        acc_ok = finite & usable(acc).all(axis=1)
        if acc_ok.any() and o.sensor != "mag":
            n_acc, acc_sums = block_sums(acc_ok, acc)
            accel_means = acc_sums / np.maximum(n_acc, 1)[:, None]
        pairs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if o.turntable_rate is not None:
            rate = float(o.turntable_rate)
            turning = (np.abs(np.nan_to_num(data.values)) > rate / 2).any(axis=1)
            busy = np.bincount(ids, weights=turning, minlength=m) > 0
            keep &= ~(busy | np.r_[busy[1:], False] | np.r_[False, busy[:-1]])
            for i, axis in enumerate(AXES):
                ok = finite
                pair_t, pair_sf = tm.turntable_pairs(
                    data.t_ns[ok], data.values[ok, i], v.T[ok, 0], rate
                )
                if len(pair_t):
                    pairs[axis] = (pair_t, pair_sf)
        keep_idx = np.flatnonzero(keep)
        if len(keep_idx) < 2:
            raise ctx.fail(
                f"input '{input_name}': {len(keep_idx)} complete blocks of "
                f"{blocking.window or blocking.window_s}{'' if blocking.window else ' s'}; "
                "the fit needs at least 2 (record longer or use smaller blocks)"
            )
        means = sums[keep_idx] / n_finite[keep_idx, None]
        entered = finite & np.isin(ids, keep_idx) & np.isfinite(v.T[:, 0])
        raw_t = v.T[entered, 0]
        t_range = (float(raw_t.min()), float(raw_t.max())) if len(raw_t) else None
        variables = {"T": b.temps[keep_idx, 0], "dT": b.rate[keep_idx, 0]}
        if len(channels) > 1:
            variables["Ta"], variables["dTa"] = b.temps[keep_idx, 1], b.rate[keep_idx, 1]
        direction = np.where(
            variables["dT"] > SOAK_RATE, 1, np.where(variables["dT"] < -SOAK_RATE, -1, 0)
        )
        reference = self._reference(means)
        return Prepared(
            t_ns=b.centre[keep_idx],
            bias=means - reference,
            variables=variables,
            direction=direction,
            reference=reference,
            counts=b.count[keep_idx],
            centre_all=b.centre,
            temp_all=b.temps[:, 0],
            keep=keep_idx,
            pairs=pairs,
            moving=moving,
            accel=None if accel_means is None else accel_means[keep_idx],
            noise=noise[keep_idx],
            t_range=t_range,
        )

    def _still(self, table: pa.Table, data: Any, finite: np.ndarray) -> np.ndarray | None:
        """(n,) the still samples (:func:`~imupipe.stages.thermal.choice.still_samples` on the
        gyro and the accelerometer), or None when not judged (``still_threshold = 0``, a
        turntable log, or no noise floor)."""
        o = self.options
        if not o.still_threshold or o.turntable_rate is not None:
            return None
        signals = []
        # a magnetometer's rows are not the IMU's: it is judged on its own field (turning it
        # moves the field by up to twice its strength, far beyond its noise)
        pair = None if o.sensor == "mag" else imu_pairs(table, on=o.sensor)
        for name in ("mag",) if o.sensor == "mag" else ("gyro", "accel"):
            values = data.values if pair is None else pair[name == "accel"].values
            ok = usable(values).all(axis=1)
            if np.count_nonzero(ok) < 3:
                continue
            if not ok.all():
                values = np.where(ok[:, None], values, np.median(values[ok], axis=0))
            signals.append(values)
        return tc.still_samples(data.t_ns, signals, float(o.still_threshold))

    def _reference(self, means: np.ndarray) -> np.ndarray:
        if self.options.reference is not None:
            return np.asarray(self.options.reference, dtype=np.float64)
        if self.options.sensor == "gyro":
            return np.zeros(3)
        if self.options.sensor == "mag":  # the field in the log's one orientation; the fit's
            return means.mean(axis=0)  # value at tref is moved into it (:meth:`_zero_at_tref`)
        mean = means.mean(axis=0)
        return G0 * mean / np.linalg.norm(mean)

    def weights(self, prep: Prepared) -> np.ndarray:
        """Sample count x temperature-bin weight, normalised to mean 1."""
        w = bin_weights(prep.variables["T"], prep.direction, self.options.bin_width)
        w = w * prep.counts
        return w * (len(w) / w.sum())

    # -- fit -----------------------------------------------------------------------------------
    def check_options(self, ctx: StageContext) -> None:
        """Raise on an option value that cannot work."""
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
            (o.lag_s is not None and o.lag_s <= 0, "'lag_s' must be > 0"),
            (o.lag_s is not None and o.model != "lag", "'lag_s' applies to model = \"lag\""),
            (
                o.order is not None and not 0 <= o.order <= tm.MAX_ORDER,
                f"'order' must be 0..{tm.MAX_ORDER}",
            ),
            (
                o.model == "stepwise" and o.order is not None and o.order < 2,
                "stepwise 'order' must be 2..5",
            ),
        ]
        for bad, message in problems:
            if bad:
                raise ctx.fail(message)
        allowed = {"lag": ("dTs",), "poly": tm.RATE_TERMS}.get(o.model)
        if o.rate_terms is not None:
            if allowed is None:
                raise ctx.fail(f'\'rate_terms\' applies to model = "poly" or "lag", not {o.model}')
            bad = [t for t in o.rate_terms if t not in allowed]
            if bad:
                raise ctx.fail(f"unknown rate term(s) {bad} (known: {', '.join(allowed)})")
        if o.validate is not None and o.validate not in ctx.tables:
            raise ctx.fail(
                f"validate: unknown input '{o.validate}' (inputs: {', '.join(ctx.tables)})"
            )

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        if self.options.model == "auto":  # options that name a model's own terms name the model
            if self.options.lag_s is not None:
                self.options = replace(self.options, model="lag")
            elif self.options.rate_terms is not None or self.options.turntable_rate is not None:
                self.options = replace(self.options, model="poly")
        o = self.options
        self.check_options(ctx)
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
                f"the temperature spans only {hi - lo:.3g} degC ({lo:.4g}..{hi:.4g}), less than "
                f"the {WARN_SPAN:g} degC recommended; the correction is clamped outside this range"
            )
        tref = o.tref if o.tref is not None else (0.0 if o.model == "six_term" else (lo + hi) / 2)
        weights = self.weights(prep)
        no_rate = directions_identify_rate(temp, prep.direction, prep.variables["dT"])
        labels = tc.segment_labels(prep.keep)
        if prep.moving:
            ctx.warn(
                f"{prep.moving} of {prep.moving + len(prep.keep)} complete blocks were left out: "
                "less than half their samples still (handling or motion; still_threshold = "
                f"{o.still_threshold:g})"
            )
        choice: dict[str, Any] | None = None
        if o.model == "auto":
            model, lag, notes, choice, cached = self._choose(
                prep, weights, tref, no_rate, labels, ctx
            )
        else:
            model, lag, notes = self._fallback(no_rate, ctx)
            cached = None
        knots = tm.segment_knots(lo, hi, o.segment_width) if model == "piecewise" else None
        ranges = {k: [float(v.min()), float(v.max())] for k, v in prep.variables.items()}
        if prep.t_range is not None:  # clamp at the logged samples' extremes (PX4's TMIN/TMAX)
            ranges["T"] = [min(prep.t_range[0], lo), max(prep.t_range[1], hi)]
        if cached is not None:
            rel, lag_s, lag_info = cached
        else:
            rel, lag_s, lag_info = self._variables(prep, weights, tref, no_rate, lag, ctx)
        if lag:
            for name in ("Ts", "dTs"):
                value = rel[name] + (tref if name == "Ts" else 0.0)
                ranges[name] = [float(value.min()), float(value.max())]
        selection: dict[str, Any] = {}
        if choice is not None:
            held = choice.pop("_held")
        else:
            held = self._held_out(model, rel, prep.bias, weights, labels, tref, prep.noise)
        axes = []
        for i, axis in enumerate(AXES):
            terms, coef, info = self._fit_axis(model, rel, prep.bias[:, i], weights, knots, tref)
            axes.append({"terms": terms, "coefficients": np.asarray(coef)})
            if info:
                selection[axis] = info
        step = TemperatureStep(
            type=self.type,
            sensor=o.sensor,
            model=model,
            tref=float(tref),
            window=self.blocking().window,
            window_s=self.blocking().window_s,
            axes=axes,
            ranges=ranges,
            knots=None if knots is None else knots.tolist(),
            lag_s=lag_s,
            scale=self._fit_scale(prep, tref, ctx) if o.turntable_rate is not None else None,
            params={"reference": prep.reference.tolist()},
            quiet=ctx.quiet,
        )
        used = step.used_variables()
        step.ranges = {k: v for k, v in ranges.items() if k in used}
        if o.sensor == "mag" and o.reference is None:
            self._zero_at_tref(step, rel, prep)
        fitted = step.bias(rel)
        results: dict[str, Any] = {
            "sensor": o.sensor,
            "unit": SENSOR_UNITS[o.sensor],
            "model": model,
            "tref": float(tref),
            "temperature_range": list(ranges["T"]),
            "block_temperature_range": [lo, hi],
            "rate_range": [60.0 * ranges["dT"][0], 60.0 * ranges["dT"][1]],
            "blocks": len(prep.t_ns),
            "terms": {ax: step.axes[i]["terms"] for i, ax in enumerate(AXES)},
            "coefficients": {
                ax: [float(c) for c in step.axes[i]["coefficients"]] for i, ax in enumerate(AXES)
            },
            "metrics": self.metrics(prep.bias, prep.bias - fitted),
        }
        self._held_out_metrics(results["metrics"], held)
        if choice is not None:
            results["choice"] = choice
        if prep.moving:
            results["moving_blocks"] = prep.moving
        if notes:
            results["fallback"] = notes
        if lag_info is not None:
            results["lag"] = lag_info
        if selection:
            results["selection"] = selection
        if step.scale is not None:
            results["scale"] = self._scale_metrics(prep, step)
        self._check_held_out(held, prep, ctx, fitted)
        if o.validate is not None:
            results["metrics"]["validate"] = self._validate(step, ctx)
        artifacts = {}
        if o.write_blocks:
            artifacts[f"{ctx.name}_blocks.csv"] = self._blocks_csv(prep, weights, rel)
        if getattr(ctx.recorder, "enabled", False):
            from imupipe.stages.thermal.rerun import record_fit  # imports rerun lazily

            record_fit(ctx, prep, step, fitted, rel, lag_info)
        return StageOutput(results=results, step=step, artifacts=artifacts)

    def _variables(
        self,
        prep: Prepared,
        weights: np.ndarray,
        tref: float,
        no_rate: str | None,
        lag: bool,
        ctx: StageContext,
        strict: bool = True,
    ) -> tuple[dict[str, np.ndarray], float | None, dict[str, Any] | None]:
        """The fit's variables relative to ``tref`` (without the rates when ``no_rate``), with
        the lag's Ts, dTs when ``lag``: (variables, lag s, lag results)."""
        rel = self._relative(prep.variables, tref)
        if no_rate is not None:
            rel = {k: v for k, v in rel.items() if k in ("T", "Ta")}
        if not lag:
            return rel, None, None
        lag_s, lag_info, rel = self._fit_lag(prep, weights, tref, ctx, strict)
        return rel, lag_s, lag_info

    def _choose(
        self,
        prep: Prepared,
        weights: np.ndarray,
        tref: float,
        no_rate: str | None,
        labels: np.ndarray,
        ctx: StageContext,
    ) -> tuple[str, bool, list[str], dict[str, Any], Any]:
        """``model = "auto"``: poly, lag (where heating and cooling identify it) and piecewise,
        each predicting every held-out segment from the others; the lowest geometric-mean
        held-out error wins, poly unless another is ``SWITCH_MARGIN`` better. Returns (model,
        lag fitted, notes, results.choice with the chosen HeldOut under ``_held``, the chosen
        model's (variables, lag s, lag results))."""
        notes: list[str] = []
        if no_rate is not None:
            note = (
                f"the lag and dT cannot be identified: {no_rate}; chose among a polynomial and "
                "the piecewise-linear bias in T, which hold at the rates fitted: a lag this log "
                "cannot show adds error at other rates (heat and cool the IMU over a common "
                "range, at several rates, to fit them)"
            )
            ctx.warn(note)
            notes.append(note)
        plain = self._variables(prep, weights, tref, no_rate, False, ctx)
        tried: dict[str, tuple[tc.HeldOut, Any]] = {}
        for model in ("poly", "piecewise"):
            tried[model] = (
                self._held_out(model, plain[0], prep.bias, weights, labels, tref, prep.noise),
                plain,
            )
        skipped = None
        if no_rate is None:
            lagged = self._variables(prep, weights, tref, None, True, ctx, strict=False)
            info = lagged[2] or {}
            if info.get("at_bound"):
                skipped = (
                    f"lag not tried: its time constant sits at the {info['at_bound']} end of "
                    f"the search ({lagged[1]:.4g} s)"
                )
            else:
                held = self._held_out(
                    "lag", lagged[0], prep.bias, weights, labels, tref, prep.noise
                )
                tried["lag"] = (held, lagged)
        scores = {m: h.score for m, (h, _) in tried.items()}
        best = min(scores, key=lambda m: scores[m])
        if best != "poly" and not scores[best] < SWITCH_MARGIN * scores["poly"]:
            best = "poly"
        held, cached = tried[best]
        figures = ", ".join(f"{m} {scores[m]:.3g}" for m in tried)
        why = (
            f"{best} predicts the {held.segments} held-out segments best: held-out RMS / no "
            f"compensation's, geometric mean over the axes, {figures}"
        )
        if best == "poly" and len(tried) > 1:
            why += f" (another model replaces poly only when {1 - SWITCH_MARGIN:.0%} lower)"
        if skipped:
            why += f"; {skipped}"
        choice: dict[str, Any] = {
            "model": best,
            "reason": why,
            "segments": held.segments,
            "scores": scores,
            "held_out_rms": {
                m: {a: float(h.rms[i]) for i, a in enumerate(AXES)} for m, (h, _) in tried.items()
            },
            "baseline_rms": {a: float(held.baseline[i]) for i, a in enumerate(AXES)},
            "_held": held,
        }
        return best, best == "lag", notes, choice, cached

    def _held_out(
        self,
        model: str,
        rel: dict[str, np.ndarray],
        bias: np.ndarray,
        w: np.ndarray,
        labels: np.ndarray,
        tref: float,
        noise: np.ndarray | None = None,
    ) -> tc.HeldOut:
        """Leave-one-segment-out prediction of the block bias by ``model`` on ``rel``
        (:func:`~imupipe.stages.thermal.choice.held_out`): temperatures clamped to the training
        blocks' range, the piecewise knots over it; a lag's time constant stays the one fitted
        on every block."""
        width = self.options.segment_width

        def fit_predict(train: np.ndarray, test: np.ndarray) -> np.ndarray:
            tr = {k: v[train] for k, v in rel.items()}
            te = {k: v[test] for k, v in rel.items()}
            for name in tm.TEMPERATURES:
                if name in te:
                    te[name] = np.clip(te[name], tr[name].min(), tr[name].max())
            t_lo, t_hi = float(tr["T"].min()), float(tr["T"].max())
            out = np.empty((int(np.count_nonzero(test)), bias.shape[1]))
            knots = None
            if model == "piecewise":
                if t_hi - t_lo <= 1e-9:
                    out[:] = (w[train] @ bias[train]) / w[train].sum()
                    return out
                knots = tm.segment_knots(t_lo + tref, t_hi + tref, width)
            for i in range(bias.shape[1]):
                terms, coef, _ = self._fit_axis(model, tr, bias[train, i], w[train], knots, tref)
                out[:, i] = tm.evaluate(terms, coef, te, None if knots is None else knots - tref)
            return out

        return tc.held_out(fit_predict, bias, w, labels, rel["T"], noise)

    @staticmethod
    @staticmethod
    def _held_out_metrics(metrics: dict[str, Any], held: tc.HeldOut) -> None:
        """Per axis (SI): ``held_out_rms`` the model's error on held-out segments,
        ``held_out_baseline`` no compensation's; ``remaining_rms`` the bias the correction
        leaves (block-mean noise taken out) and ``remaining_rms_95`` its 95 % interval (the
        three axes at once), on another log like this one."""
        for i, axis in enumerate(AXES):
            if not np.isfinite(held.rms[i]):
                continue
            metrics[axis]["held_out_rms"] = float(held.rms[i])
            metrics[axis]["held_out_baseline"] = float(held.baseline[i])
            remaining, interval = held.remaining(i)
            if np.isfinite(remaining):
                metrics[axis]["remaining_rms"] = remaining
                metrics[axis]["remaining_rms_95"] = interval
        metrics["held_out_segments"] = held.segments
        metrics["held_out_blocks"] = held.blocks

    def _zero_at_tref(
        self, step: TemperatureStep, rel: dict[str, np.ndarray], prep: Prepared
    ) -> None:
        """A magnetometer's model minus its value at ``tref`` (rates zero), that value moved into
        the reference (the field in the log's orientation, which a thermal log cannot tell from
        the hard iron): the correction removes only the temperature-driven change and keeps
        the vehicle's ``CAL_MAG*`` offsets valid at ``tref``, as PX4's own magnetometer thermal
        calibration normalises ``TC_M*`` (``X0 = 0``). ``prep.bias`` and ``prep.reference`` are
        shifted alike, so the residuals stay as fitted."""
        at = {k: np.zeros(1) for k in rel}
        shift = step.bias(at)[0]
        for i, ax in enumerate(step.axes):
            terms = list(ax["terms"])
            coef = np.asarray(ax["coefficients"], dtype=np.float64).copy()
            if "1" in terms:
                coef[terms.index("1")] -= shift[i]
            else:
                terms, coef = [*terms, "1"], np.r_[coef, -shift[i]]
            step.axes[i] = {"terms": terms, "coefficients": coef}
        prep.bias = prep.bias - shift
        prep.reference = prep.reference + shift
        step.params = {**step.params, "reference": prep.reference.tolist()}

    @staticmethod
    def _field_turn(prep: Prepared, fitted: np.ndarray) -> float:
        """deg: the largest change of the corrected field's direction across a gap between
        still periods (the mean of the ``TURN_BLOCKS`` kept blocks before it against those
        after it). The temperature barely moves across a gap and its effect is corrected, so
        a magnetometer held in one orientation reads about 0; a turn shows in full (over
        whole still periods a smooth fit absorbs part of it)."""
        field = prep.bias - fitted + prep.reference
        gaps = np.flatnonzero(np.diff(prep.keep) > 1) + 1
        turn = 0.0
        for g in gaps:
            before = field[max(0, g - TURN_BLOCKS) : g].mean(axis=0)
            after = field[g : g + TURN_BLOCKS].mean(axis=0)
            turn = max(turn, tc.orientation_spread(np.vstack([before, after])) * 2)
        return turn

    def _check_held_out(
        self, held: tc.HeldOut, prep: Prepared, ctx: StageContext, fitted: np.ndarray
    ) -> None:
        """The quality checks on what the fit may be applied to: one orientation (gravity's
        direction; a magnetometer's corrected field), and a correction that predicts held-out
        segments better than no compensation on every axis."""
        sensor_name = self.options.sensor
        unit = SENSOR_UNITS[sensor_name]
        figures = ", ".join(
            f"{a} {held.rms[i]:.3g} vs {held.baseline[i]:.3g}" for i, a in enumerate(AXES)
        )
        if sensor_name == "mag":
            turn = self._field_turn(prep, fitted)
            ctx.check(
                turn <= MAG_TURN_DEG,
                f"the magnetometer was turned between its still periods (its corrected field's "
                f"direction changes by up to {turn:.3g} deg across the gaps between them): the "
                "field in the sensor's frame turns with it, and a temperature fit across "
                "orientations takes the turn for a thermal offset (held-out RMS "
                f"{figures} {unit} without compensation); record the thermal log in one fixed "
                "orientation, or give each orientation's part as its own input",
            )
        elif prep.accel is not None and len(prep.accel):
            runs = np.r_[0, np.cumsum(np.diff(prep.keep) > 1)]
            counts = np.bincount(runs)
            means = np.column_stack([np.bincount(runs, weights=c) for c in prep.accel.T])
            spread = tc.orientation_spread(means / counts[:, None])
            ctx.check(
                spread <= tc.ORIENTATION_DEG,
                f"the IMU was turned between its still periods (their gravity directions differ "
                f"by up to {spread:.3g} deg from their mean): the {sensor_name} bias "
                "changes with orientation (g-sensitivity, gravity itself) as well as with "
                "temperature, and a temperature fit across orientations takes one for the other "
                f"(held-out RMS {figures} {unit} without compensation); record the thermal log "
                "in one fixed orientation, or give each orientation's part as its own input",
            )
        if held.segments < 2 or not np.isfinite(held.rms).all():
            return
        ratio = held.ratio
        worse = [a for i, a in enumerate(AXES) if ratio[i] > 1.0 + HELD_OUT_MARGIN]
        better = [a for i, a in enumerate(AXES) if ratio[i] < 1.0 - HELD_OUT_MARGIN]
        where = (
            f"worse than no compensation on {', '.join(worse)}"
            if worse
            else "no better than no compensation on any axis"
        )
        ctx.check(
            not worse and bool(better),
            f"the temperature fit predicts held-out segments {where} (held-out RMS over "
            f"{held.segments} segments: {figures} {unit} without compensation; "
            f"{HELD_OUT_MARGIN:.0%} either way counts as equal): the bias does not follow the "
            "temperature there (drift, steps, or changes the temperature does not explain); "
            "record a ramp that heats and cools the still IMU over 10 degC or more, in one "
            "orientation",
        )

    def _fallback(self, no_rate: str | None, ctx: StageContext) -> tuple[str, bool, list[str]]:
        """The model the data support: (model, whether the lag is fitted, what was dropped)."""
        o = self.options
        model = o.model
        if no_rate is None or (o.model == "poly" and o.rate_terms == []):
            return model, model == "lag", []
        dropped = {
            "poly": f"the rate term(s) {', '.join(o.rate_terms or ['dT'])}",
            "lag": "the sensing element's lag (and dTs)",
            "six_term": "the rate terms dT, dT^2, T*dT of the six-term model",
            "piecewise": "the hysteresis term k_dt * dT",
            "stepwise": "the rate candidates dT (and dTa)",
        }[model]
        fitted = {
            "poly": "a polynomial in T",
            "lag": "a polynomial in T",
            "six_term": "T^2, T, 1",
            "piecewise": "the piecewise-linear bias in T",
            "stepwise": "a stepwise choice among the terms in T",
        }[model]
        note = (
            f"{dropped} cannot be identified: {no_rate}; fitted {fitted} instead (heat and cool "
            "the IMU over a common range, at several rates, to fit it)"
        )
        ctx.warn(note)
        return ("poly" if model in ("lag", "six_term") else model), False, [note]

    def _fit_axis(
        self,
        model: str,
        rel: dict[str, np.ndarray],
        y: np.ndarray,
        w: np.ndarray,
        knots: np.ndarray | None,
        tref: float,
    ) -> tuple[list[str], np.ndarray, dict[str, Any]]:
        """Terms, coefficients and (when chosen by the data) the selection of one axis."""
        o = self.options
        if model == "piecewise":
            terms, coef = tm.fit_piecewise(rel, y, w, knots - tref)
            return terms, coef, {}
        if model == "stepwise":
            names = candidate_terms([v for v in ("T", "dT", "Ta", "dTa") if v in rel], o.order or 3)
            sel = stepwise(
                tm.design(names, rel),
                y,
                names,
                w,
                criterion=o.criterion,
                alpha_in=o.alpha_in,
                alpha_out=o.alpha_out,
            )
            return sel.terms, sel.coef, {"adj_r2": sel.adj_r2, "steps": sel.history}
        if model == "six_term":
            terms = list(tm.SIX_TERMS) if "dT" in rel else ["T^2", "T", "1"]
            return terms, tm.weighted_lstsq(tm.design(terms, rel), y, w), {}
        var = "Ts" if model == "lag" else "T"
        rates = "dTs" if model == "lag" else "dT"
        if rates not in rel:
            offered: list[str] = []
        else:
            offered = list(o.rate_terms) if o.rate_terms is not None else [rates]
        orders = [o.order] if o.order is not None else range(MAX_AUTO_ORDER + 1)
        base = [
            ["1"] + [(var if p == 1 else f"{var}^{p}") for p in range(1, k + 1)] for k in orders
        ]
        if o.rate_terms is not None:  # given: fitted as given
            candidates = [b + offered for b in base]
        else:
            candidates = base + ([b + offered for b in base] if offered else [])
        if len(candidates) == 1:
            return candidates[0], tm.weighted_lstsq(tm.design(candidates[0], rel), y, w), {}
        choice = tm.select_terms(candidates, rel, y, w)
        return choice.terms, choice.coef, {"aicc": choice.scores}

    def _fit_lag(
        self, prep: Prepared, w: np.ndarray, tref: float, ctx: StageContext, strict: bool = True
    ) -> tuple[float, dict[str, Any], dict[str, np.ndarray]]:
        """The sensing element's time constant (given, or fitted on every axis at once with the
        richest candidate model), and the variables with Ts, dTs at it. ``strict = False``
        (the ``auto`` choice): a time constant at an end of the search is reported in the
        results' ``at_bound``, not warned about or refused."""
        o = self.options
        spacing = (
            float(np.median(np.diff(prep.centre_all))) * 1e-9 if len(prep.centre_all) > 1 else 1.0
        )
        duration = float(prep.centre_all[-1] - prep.centre_all[0]) * 1e-9
        bounds = (max(0.5 * spacing, 1e-3), max(duration / 2, spacing))
        order = o.order if o.order is not None else MAX_AUTO_ORDER
        terms = ["1"] + [("Ts" if p == 1 else f"Ts^{p}") for p in range(1, order + 1)]
        terms += list(o.rate_terms) if o.rate_terms is not None else ["dTs"]
        if o.lag_s is not None:
            tau = float(o.lag_s)
            info: dict[str, Any] = {"lag_s": tau, "fitted": False}
        else:
            fit = tm.fit_lag(
                prep.centre_all, prep.temp_all, prep.keep, prep.bias, w, terms, tref, bounds
            )
            tau = fit.tau_s
            info = {
                "lag_s": tau,
                "fitted": True,
                "search_s": list(bounds),
                "profile": {"lag_s": fit.taus.tolist(), "cost": fit.costs.tolist()},
            }
            if not strict:
                info["at_bound"] = fit.at_bound
            elif fit.at_bound == "low":
                ctx.warn(
                    f"the sensing element's time constant is at or below the block spacing "
                    f"({tau:.3g} s): no lag is resolved, the model is a polynomial in T with dT"
                )
            ctx.check(
                not strict or fit.at_bound != "high",
                f"the sensing element's time constant sits at the top of the search "
                f"({tau:.4g} s of {bounds[1]:.3g} s): the data do not pin it down",
            )
        rel = self._relative(prep.variables, tref)
        rel.update(tm.lag_variables(prep.centre_all, prep.temp_all, prep.keep, tau, tref))
        return tau, info, rel

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
        for name in tm.TEMPERATURES:
            if name in rel:
                rel[name] = variables[name] - tref
        return rel

    @staticmethod
    def metrics(bias: np.ndarray, residual: np.ndarray) -> dict[str, Any]:
        """Per axis, over the complete blocks (SI): the constant part of the bias before and
        after (``constant_before``: the mean block bias; ``constant_after``: the mean residual),
        and the temperature-driven part: ``rms_before``/``rms_after`` the RMS about those means,
        ``p2p_before``/``p2p_after`` the peak-to-peak, ``reduction`` their RMS ratio; ``rmse``
        the RMS residual about zero and ``r2`` = 1 - sum(residual^2) / sum((bias - mean)^2)."""
        out: dict[str, Any] = {}
        for i, axis in enumerate(AXES):
            b, r = bias[:, i], residual[:, i]
            before, after = float(np.std(b)), float(np.std(r))
            ss = float(np.sum((b - b.mean()) ** 2)) or 1.0
            out[axis] = {
                "constant_before": float(b.mean()),
                "constant_after": float(r.mean()),
                "rms_before": before,
                "rms_after": after,
                "p2p_before": float(np.ptp(b)),
                "p2p_after": float(np.ptp(r)),
                "reduction": before / max(after, 1e-300),
                "rmse": float(np.sqrt(np.mean(r * r))),
                "r2": 1.0 - float(np.sum(r * r)) / ss,
            }
        return out

    def _validate(self, step: TemperatureStep, ctx: StageContext) -> dict[str, Any]:
        """The same metrics on the ``validate`` input: blocks before and after the step; a
        quality check that the correction did not raise the temperature-driven variation."""
        name = self.options.validate
        table = ctx.tables[name]
        before = self.prepare(table, ctx, name)
        after = self.prepare(step.apply(table), ctx, name)
        metrics = self.metrics(before.bias, after.bias)
        worse = [
            f"{axis} {metrics[axis]['rms_before']:.3g} -> {metrics[axis]['rms_after']:.3g}"
            for axis in AXES
            if metrics[axis]["rms_after"] > metrics[axis]["rms_before"]
        ]
        ctx.check(
            not worse,
            f"on the held-out input '{name}' the correction raised the temperature-driven bias "
            f"RMS ({', '.join(worse)} {SENSOR_UNITS[self.options.sensor]})",
        )
        for axis, (_, sf_after) in after.pairs.items():
            sf_before = before.pairs[axis][1]
            metrics[axis] |= {
                "scale_error_before": float(np.max(np.abs(sf_before - 1.0))),
                "scale_error_after": float(np.max(np.abs(sf_after - 1.0))),
            }
        if ctx.recorder.enabled:  # the held-out run's residual, beside the fitted run's
            sensor = self.options.sensor
            ctx.recorder.series(
                f"/{ctx.name}/residual_{name}",
                after.t_ns,
                after.bias,
                [f"{sensor} {a} residual, held-out {name}" for a in AXES],
                unit=SENSOR_UNITS[sensor],
                title=f"{sensor} residual on the held-out run {name}",
            )
        metrics["input"] = name
        metrics["blocks"] = len(before.t_ns)
        return metrics

    @staticmethod
    def _blocks_csv(prep: Prepared, weights: np.ndarray, rel: dict[str, np.ndarray]) -> str:
        """The fit's data: block centre, bias per axis (SI), T (degC), dT (degC/s) [, Ta, dTa]
        [, Ts (degC), dTs], samples in the block, the block's weight."""
        variables = dict(prep.variables)
        if "Ts" in rel:
            variables["Ts"] = rel["Ts"] + (prep.variables["T"] - rel["T"])
            variables["dTs"] = rel["dTs"]
        names = ["t_ns", "bias_x", "bias_y", "bias_z", *variables, "samples", "weight"]
        cols = [prep.t_ns.astype(np.float64), *prep.bias.T, *variables.values()]
        cols += [prep.counts.astype(np.float64), weights]
        rows = np.column_stack(cols)
        lines = [",".join(names)]
        lines += [f"{int(r[0])}," + ",".join(f"{v:.17g}" for v in r[1:]) for r in rows]
        return "\n".join(lines) + "\n"
