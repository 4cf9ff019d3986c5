"""``allan`` stage: IMU noise identification from a long static recording (IEEE Std 952-1997
Annex C; the imu_utils / Kalibr workflow).

Computes a stability deviation (overlapping Allan deviation by default; see
:mod:`imupipe.stages.allan.estimators`) of every gyro and accelerometer axis at once, its 68 %
chi-square confidence bounds, and fits the five-term model of :mod:`imupipe.stages.allan.fit`
(``3Q^2/tau^2 + N^2/tau + B^2 2ln2/pi + K^2 tau/3 + R^2 tau^2/2``) in log space weighted by the
confidence. All results are continuous-time SI:

| term | gyro | accel |
|---|---|---|
| Q quantisation | rad | m/s |
| N white noise density | rad/s/sqrt(Hz) | m/s^2/sqrt(Hz) |
| B bias instability | rad/s | m/s^2 |
| K random walk density | rad/s^2/sqrt(Hz) | m/s^3/sqrt(Hz) |
| R rate ramp | rad/s^2 | m/s^3 |

Outputs: ``results[<name>]`` = ``{"gyro": {"x": {N, B, K, Q, R}, ...}, "accel": {...},
"metrics": {...}}``; artifact ``<name>_curves.csv`` (the pipeline exports ``imu.yaml`` for
Kalibr and ``<name>_imu_utils.yaml`` from these results); Rerun: per axis the log10 deviation with its
bounds, the fitted model and each fitted term's line over ``log10(tau) * 1000``.

Input. Samples with a NaN or Inf are left out (one counted warning). The stamps are read as a
sample clock (:mod:`imupipe.stages.sample_clock`): timestamp jitter is told apart from lost
samples, the lost ones are filled by linear interpolation on the nominal clock (one counted
warning), and a gap longer than ``max_gap`` periods cuts the recording: the deviations use the
longest stretch without one (a warning). Time not increasing, or a recording too short to give
the fit more taus than terms, is an error; motion (1 s gyro means further than
``motion_threshold`` from the mean, or accel-norm 1 s means spreading more than 0.05 g) is a
failed check (``accept_failed_checks = true`` fits anyway), and so is a jump of the gyro bias
(:func:`bias_jump`: a knock or a power event, whose Allan deviation reads as a random walk);
under two hours is a warning.

Tau grid (``taus``): ``auto`` (default) computes the octave grid, then refines to thirds of an
octave where the curve bends (the transitions between noise types, where the slope readings and
the fit's term boundaries are): about 20-30 taus for two hours at 400 Hz, where ``log``'s 10 per
decade gives 60 at the same accuracy of the fitted terms (each tau costs one pass over the data).
An analysis stage: it adds nothing to the calibration chain.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import (
    SENSOR_UNITS,
    SensorData,
    has_sensor,
    has_stream,
    imu_pairs,
    sensor_columns,
    split_imu,
    usable,
)
from imupipe.stages.allan import estimators as est
from imupipe.stages.allan.fit import TERMS, AllanFit, fit_allan, slope_readings, term_variance
from imupipe.stages.base import Stage, StageContext, StageOutput, dead_value, is_dead
from imupipe.stages.gyro_bias import select_interval
from imupipe.stages.sample_clock import SampleClock, fill_lost, longest_run, sample_clock
from imupipe.stages.stillness import stillness

AXES = ("x", "y", "z")


@dataclass
class ImuSeries:
    """The IMU samples an Allan run uses: stamps, gyro and accel (three columns each), their
    sample clock, and the mean rate over the clock's slots (Hz)."""

    t_ns: np.ndarray
    data: dict[str, list[np.ndarray]]
    clock: SampleClock
    rate_hz: float

    @property
    def duration_s(self) -> float:
        """From the first stamp to the last."""
        return float((self.t_ns[-1] - self.t_ns[0]) * 1e-9)

    @property
    def span_s(self) -> float:
        """Slots times the period: what the deviations cover (2 h at 400 Hz: 2.88 M slots)."""
        return float(self.clock.n_slots / self.rate_hz)


UNITS = {
    "gyro": {
        "Q": "rad",
        "N": "rad/s/sqrt(Hz)",
        "B": "rad/s",
        "K": "rad/s^2/sqrt(Hz)",
        "R": "rad/s^2",
    },
    "accel": {"Q": "m/s", "N": "m/s^2/sqrt(Hz)", "B": "m/s^2", "K": "m/s^3/sqrt(Hz)", "R": "m/s^3"},
}
FIT_KINDS = ("oadev", "adev")
"""Deviations the five-term (Allan variance) model describes; other kinds are shown, and the
fit runs on the OADEV at the same taus."""


class AllanStage(Stage):
    type = "allan"
    sensors = ("gyro", "accel")

    @dataclass
    class Options:
        kind: Literal["oadev", "adev", "mdev", "hdev", "ohdev", "totdev"] = "oadev"
        """Deviation shown and written: oadev (overlapping Allan), adev, mdev (modified), hdev
        (Hadamard), ohdev (overlapping Hadamard), totdev (total). The five-term model is the Allan
        variance's, so with mdev, hdev, ohdev or totdev it is fitted on the OADEV at the same
        taus (also written)."""
        taus: Literal["auto", "log", "octave", "decade", "all"] = "auto"
        """Tau grid: auto (octaves, refined to thirds of an octave where the curve bends), log
        (``points_per_decade`` per decade), octave, decade, all."""
        points_per_decade: int = 10
        """Taus per decade with ``taus = "log"``."""
        terms: list[str] = field(default_factory=lambda: list(TERMS))
        """Model terms to fit (subset of Q, N, B, K, R); a term the curve does not support comes
        out zero. K, when listed, is always fitted (it may come out zero, with its 68 %
        interval)."""
        penalty: float = 10.0
        """Information-criterion cost of one more term (log-space weighted residual units)."""
        model_error: float = 0.05
        """Relative model error added to each point's uncertainty (caps the short-tau weights)."""
        slope_tolerance: float = 0.25
        """Flag a slope reading that differs from the fit by more than this fraction."""
        interval: list[float] | None = None
        """[start_s, end_s] seconds from the first sample; default the whole input."""
        max_gap: float = 10.0
        """Sample periods: a step that spans more (timestamp jitter told apart from missing
        samples) is a gap; the deviations use the longest stretch without one (a warning).
        Missing samples in shorter steps are filled by linear interpolation (counted)."""
        motion_threshold: float = 0.02
        """rad/s: a 1 s gyro mean further than this from the overall mean is motion, a failed
        check (``accept_failed_checks = true`` to fit anyway)."""

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        opts = self.options
        self._check_options(ctx)
        if not has_stream(table, "imu"):
            raise ctx.fail("the input has no IMU samples")
        if opts.interval is not None and (
            len(opts.interval) != 2 or opts.interval[1] <= opts.interval[0]
        ):
            raise ctx.fail("'interval' must be [start_s, end_s] with end_s > start_s")
        if not split_imu(table):
            return self._fit(table, ctx, self.sensors, None)
        present = tuple(s for s in self.sensors if has_sensor(table, s))
        if len(present) == 1:  # one topic of the two read: that sensor alone
            return self._fit(table, ctx, present, None)
        # gyro and accelerometer sampled apart (a camera's two topics): each from its own
        # samples at its own rate (interpolating one onto the other's clock would smooth its
        # white noise); the stillness test, which needs both, on the gyro's stamps
        _, accel, note = imu_pairs(table)
        ctx.warn(
            f"{note} for the stillness test only; each sensor's deviations use its own samples"
        )
        gyro = self._fit(table, ctx, ("gyro",), accel)
        both = self._fit(table, ctx, ("accel",), None)
        results = {**gyro.results, **both.results}
        metrics = {**gyro.results["metrics"], **both.results["metrics"]}
        metrics["per_sensor"] = {
            **gyro.results["metrics"]["per_sensor"],
            **both.results["metrics"]["per_sensor"],
        }
        for key in ("samples", "duration_s", "rate_hz", "taus", "tau_range_s"):
            metrics[key] = gyro.results["metrics"][key]  # the gyro's, as exports read them
        metrics["static"] = gyro.results["metrics"]["static"]
        results["metrics"] = metrics
        return StageOutput(results=results, artifacts={**gyro.artifacts, **both.artifacts})

    def _fit(
        self,
        table: pa.Table,
        ctx: StageContext,
        sensors: tuple[str, ...],
        accel_on_gyro: SensorData | None,
    ) -> StageOutput:
        """The deviations and fits of ``sensors`` from their own rows (all of them on one
        clock: an IMU whose samples hold both, or one sensor of a split IMU). ``accel_on_gyro``:
        for a split IMU's gyro, the accelerometer on its stamps, for the stillness test."""
        opts = self.options
        split = len(sensors) < len(self.sensors)
        series = self._samples(table, ctx, sensors)
        t_ns, data, clock = series.t_ns, series.data, series.clock
        rate_hz, duration, span = series.rate_hz, series.duration_s, series.span_s
        live = [(s, i) for s in sensors for i in range(3)]
        dead = [(s, i) for s, i in live if is_dead(data[s][i])]
        if dead:
            names = ", ".join(f"{s} {AXES[i]} ({dead_value(data[s][i])})" for s, i in dead)
            if len(dead) == len(live):
                raise ctx.fail(ctx.dead_text(names))
            ctx.warn(ctx.dead_text(names, fitted_others=True))
            live = [c for c in live if c not in dead]
        static = True
        if "gyro" in data:  # (a split IMU's accelerometer: judged with its gyro)
            still = {  # a dead axis counts as still
                s: [np.zeros_like(c) if (s, i) in dead else c for i, c in enumerate(v)]
                for s, v in data.items()
            }
            if accel_on_gyro is not None:  # on the gyro's stamps (gaps cut as the gyro's)
                acc = accel_on_gyro.values[np.isin(accel_on_gyro.t_ns, t_ns)]
                ok = usable(acc).all(axis=1)
                if ok.any():
                    acc = np.where(ok[:, None], acc, np.median(acc[ok], axis=0))
                still["accel"] = [acc[:, i] for i in range(3)]
            if "accel" in still and len(still["accel"][0]) == len(t_ns):
                gyro_means = [c.mean() for c in still["gyro"]]
                static = self._check_static(t_ns, still, ctx, gyro_means)
        # without lost samples the phase is of these same columns: each mean computed once
        means = None if clock.n_lost else [data[s][i].mean() for s, i in live]
        x = est.rate_to_phase([fill_lost(clock, data[s][i]) for s, i in live], 1.0 / rate_hz, means)
        del data, series  # the phase (k, n + 1) is all the estimators need
        top = est.max_af(opts.kind, x.shape[1])
        if opts.kind not in FIT_KINDS:  # the fit runs on OADEV at the same taus
            top = min(top, est.max_af("oadev", x.shape[1]))
        m = est.tau_grid(opts.taus, top, opts.points_per_decade)
        if len(m) < len(opts.terms) + 2:
            raise ctx.fail(
                f"{len(t_ns)} samples ({duration:.1f} s at {rate_hz:.1f} Hz) give only {len(m)} "
                f"taus on the '{opts.taus}' grid; fitting {len(opts.terms)} terms needs at least "
                f"{len(opts.terms) + 2} (record longer, or use a denser grid / fewer terms)"
            )
        if span < 7200.0:
            ctx.warn(
                f"the recording lasts {duration / 60:.1f} min; Allan fits want two hours or more "
                "(B, K and R are poorly determined from a short recording)"
            )
        tau0, grid, ppd = 1.0 / rate_hz, opts.taus, opts.points_per_decade
        if opts.kind in FIT_KINDS:
            dev, conf = est.curve(x, tau0, opts.kind, grid, ppd, top=top)
            fdev, fconf = dev, conf
        else:  # the five-term model is the Allan variance's: its grid, the other kind shown
            fdev, fconf = est.curve(x, tau0, "oadev", grid, ppd, top=top)
            dev, conf = est.curve(x, tau0, opts.kind, m=fdev.m)
        del x

        results: dict[str, Any] = {}
        metrics: dict[str, Any] = {
            "samples": int(len(t_ns)),
            "duration_s": float(duration),
            "rate_hz": float(rate_hz),
            "kind": opts.kind,
            "fit_kind": fdev.kind,
            "taus": int(len(dev.m)),
            "tau_range_s": [float(dev.taus[0]), float(dev.taus[-1])],
            "static": static,
            "missing_samples": clock.n_lost,
            "gaps_filled": clock.n_gaps,
            "timestamp_jitter": clock.jitter,
            "units": UNITS,
        }
        fits: dict[tuple[str, int], AllanFit] = {}
        disagreements: list[str] = []
        unresolved: list[str] = []
        for col, (name, i) in enumerate(live):
            f = fit_allan(
                fdev.taus,
                fdev.dev[:, col],
                fconf.edf[:, col],
                tuple(opts.terms),
                opts.penalty,
                opts.model_error,
            )
            fits[(name, i)] = f
            results.setdefault(name, {})[AXES[i]] = dict(f.params)
            reading = slope_readings(fdev.taus, fdev.dev[:, col])
            disagree = [
                k
                for k, v in reading.items()
                if v is not None
                and f.params[k] > 0
                and abs(v / f.params[k] - 1.0) > opts.slope_tolerance
            ]
            metrics.setdefault(name, {})[AXES[i]] = {
                "fitted_terms": [t for t in TERMS if f.params[t] > 0],
                "fit_rms_log10": f.rms_log10,
                "fit_cost": f.cost,
                "slope_readings": reading,
                "slope_disagrees": disagree,
                "min_deviation": float(np.min(fdev.dev[:, col])),
                "tau_at_min_s": float(fdev.taus[int(np.argmin(fdev.dev[:, col]))]),
                "K_range_68": list(f.ranges["K"]) if "K" in f.ranges else None,
                "K_upper_68": k_upper(f, fdev.taus, fconf.hi[:, col]),
                "N_upper": n_upper(fdev.taus, fdev.dev[:, col]),
            }
            if not f.params["N"] > 0:
                unresolved.append(f"{name} {AXES[i]}")
            if disagree:
                disagreements.append(f"{name} {AXES[i]} ({', '.join(disagree)})")
        if disagreements:
            ctx.warn(
                f"the IEEE slope readings differ from the fit by more than "
                f"{opts.slope_tolerance:.0%} on {'; '.join(disagreements)} (slope_readings in "
                "the metrics)"
            )
        if unresolved:
            ctx.warn(
                f"white noise not resolved on {', '.join(unresolved)} (the shortest tau, "
                f"{fdev.taus[0]:.3g} s, is already dominated by slower noise: low-pass filtered or "
                "decimated data?): the exports write the upper bound N_upper from the shortest "
                "taus instead of a zero; record at the sensor's full rate without filtering to "
                "measure N"
            )
        metrics["per_sensor"] = {
            s: {"samples": int(len(t_ns)), "rate_hz": float(rate_hz), "duration_s": duration}
            for s in sensors
        }
        if dead:
            metrics["dead_axes"] = [f"{s} {AXES[i]}" for s, i in dead]
        results["metrics"] = metrics
        self._record(ctx, dev, conf, fits, fdev, live)
        # imu.yaml and the imu_utils layout are written from these results by the pipeline's
        # exports (imupipe.pipeline.exports.kalibr, .imu_utils)
        name = f"{ctx.name}_{sensors[0]}_curves.csv" if split else f"{ctx.name}_curves.csv"
        artifacts = {name: curves_csv(dev, conf, fits, live, fdev)}
        return StageOutput(results=results, artifacts=artifacts)

    # -- checks ------------------------------------------------------------------------------
    def _check_options(self, ctx: StageContext) -> None:
        opts = self.options
        if opts.kind not in est.KINDS:
            raise ctx.fail(f"kind '{opts.kind}' is not one of {', '.join(est.KINDS)}")
        if opts.taus not in est.GRIDS:
            raise ctx.fail(f"taus '{opts.taus}' is not one of {', '.join(est.GRIDS)}")
        if opts.points_per_decade < 1:
            raise ctx.fail("points_per_decade must be >= 1")
        bad = [t for t in opts.terms if t not in TERMS]
        if bad or not opts.terms:
            raise ctx.fail(f"terms {opts.terms} must be a non-empty subset of {', '.join(TERMS)}")
        if opts.max_gap < 2.0:
            raise ctx.fail(f"max_gap must be >= 2 (sample periods), got {opts.max_gap}")

    def _samples(
        self, table: pa.Table, ctx: StageContext, sensors: tuple[str, ...] = ("gyro", "accel")
    ) -> ImuSeries:
        """The IMU samples the deviations are computed on: the ``interval``, without non-finite
        samples (one counted warning), on their sample clock (lost samples counted and filled,
        jitter told apart from gaps: :mod:`imupipe.stages.sample_clock`), cut to the longest
        stretch without a gap longer than ``max_gap`` periods (a warning)."""
        opts = self.options
        # column by column, views of the table where it can: no (n, 3) copy
        t_ns, cols = sensor_columns(table, sensors[0])
        for other in sensors[1:]:
            cols = cols + sensor_columns(table, other)[1]  # gyro x, y, z, accel x, y, z
        number = None  # IMU sample numbers of the input, for messages (None: 0, 1, 2, ...)
        if opts.interval is not None:
            everyone = np.arange(len(t_ns))
            keep = select_interval(
                SensorData(t_ns, np.zeros((len(t_ns), 0)), everyone), opts.interval
            )
            t_ns, cols = t_ns[keep], [c[keep] for c in cols]
            number = np.flatnonzero(keep)
        # one reduction per column tells whether any value is NaN, Inf or huge (no mask); a
        # column without any usable value is a dead axis (left out later), not a reason to drop
        # every row
        if not all(usable(c.min()) and usable(c.max()) for c in cols):
            alive = [c for c in cols if usable(c).any()]
            ok = np.logical_and.reduce([usable(c) for c in alive]) if alive else None
            if ok is not None and not ok.all():
                rows = np.arange(len(t_ns)) if number is None else number
                both = SensorData(t_ns, np.column_stack(alive), rows)
                what = "IMU (gyro and accel)" if len(sensors) > 1 else sensors[0]
                number = ctx.finite(both, what, minimum=3).rows
                t_ns, cols = t_ns[ok], [c[ok] for c in cols]

        def num(i: int) -> int:
            return int(i if number is None else number[i])

        if len(t_ns) < 3:
            raise ctx.fail(f"only {len(t_ns)} IMU samples")
        dt = np.diff(t_ns)
        if dt.min() <= 0:
            i = int(np.flatnonzero(dt <= 0)[0])
            raise ctx.fail(f"time does not increase at IMU sample {num(i + 1)} (step {dt[i]} ns)")
        data = {s: cols[3 * k : 3 * k + 3] for k, s in enumerate(sensors)}
        clock = sample_clock(t_ns, dt)
        breaks = np.flatnonzero(clock.lost + 1 > opts.max_gap) if clock.n_lost else []
        if len(breaks):
            start, stop = longest_run(breaks, len(t_ns))
            worst = int(breaks[np.argmax(clock.lost[breaks])])
            whole = (t_ns[-1] - t_ns[0]) * 1e-9
            ctx.warn(
                f"{len(breaks)} gap(s) longer than max_gap = {opts.max_gap:g} sample periods (the "
                f"longest: {dt[worst] * 1e-9:.3f} s, {clock.lost[worst]} samples missing, after "
                f"IMU sample {num(worst)} at t = {(t_ns[worst] - t_ns[0]) * 1e-9:.3f} s); the "
                f"deviations use the longest stretch without one: IMU samples {num(start)} to "
                f"{num(stop - 1)}, {(t_ns[stop - 1] - t_ns[start]) * 1e-9:.1f} s of "
                f"{whole:.1f} s (set interval to choose another)"
            )
            number = np.arange(start, stop) if number is None else number[start:stop]
            t_ns = t_ns[start:stop]
            data = {k: [c[start:stop] for c in v] for k, v in data.items()}
            clock = sample_clock(t_ns)
        rate_hz = float((clock.n_slots - 1) / ((t_ns[-1] - t_ns[0]) * 1e-9))
        if clock.n_lost:
            worst = int(np.argmax(clock.lost))
            ctx.warn(
                f"{clock.n_lost} IMU samples missing in {clock.n_gaps} gap(s) "
                f"({100 * clock.n_lost / clock.n_slots:.2g} % of the "
                f"{rate_hz:.4g} Hz clock; the longest: {clock.lost[worst]} after IMU sample "
                f"{num(worst)}) are filled by linear interpolation; timestamp jitter "
                f"({100 * clock.jitter:.2g} % of the period, RMS) is not counted as missing"
            )
        return ImuSeries(t_ns, data, clock, rate_hz)

    def _check_static(
        self,
        t_ns: np.ndarray,
        data: dict[str, list[np.ndarray]],
        ctx: StageContext,
        gyro_means: list[float] | None = None,
    ) -> bool:
        still = stillness(t_ns, data["gyro"], data["accel"], increasing=True, gyro_means=gyro_means)
        static = still.static(self.options.motion_threshold)
        ctx.check(
            static,
            f"the data does not look static: {still.describe(self.options.motion_threshold)}: "
            "motion, or a jump of the bias (a knock, a power event); an Allan deviation of either "
            "measures it, not the noise: record the IMU untouched, or give the still part as "
            "interval",
        )
        if static:
            jump = bias_jump(still.gyro_1s.means)
            if jump is not None:
                ratio, block, size = jump
                ctx.check(
                    ratio <= JUMP_RATIO,
                    f"the gyro bias jumps by {size:.3g} rad/s about {block} s into the recording "
                    f"({ratio:.3g} times the scatter of {JUMP_WINDOW_S} s means, > {JUMP_RATIO:g}):"
                    " a knock or a power event; its Allan deviation reads as a random walk many "
                    "times the sensor's: give the part before or after it as interval",
                )
        return static

    # -- Rerun -------------------------------------------------------------------------------
    def _record(
        self,
        ctx: StageContext,
        dev: est.Deviation,
        conf: est.Confidence,
        fits: dict[tuple[str, int], AllanFit],
        fdev: est.Deviation,
        live: list[tuple[str, int]],
    ) -> None:
        rec = ctx.recorder
        if not getattr(rec, "enabled", False):
            return
        dense = np.logspace(np.log10(dev.taus[0]), np.log10(dev.taus[-1]), 200)
        for col, (name, i) in enumerate(live):
            base = f"/{ctx.name}/{name}/{AXES[i]}"
            plot = dict(
                plot=f"{name}/{AXES[i]}",
                title=f"{name} {AXES[i]} Allan deviation",
                unit=SENSOR_UNITS[name],
                x_label="tau",
                x_unit="s",
                log_x=True,
                log_y=True,
            )
            band = np.column_stack([conf.lo[:, col], conf.hi[:, col]])
            rec.curve(f"{base}/band", dev.taus, band, ("68% confidence",), band=True, **plot)
            rec.curve(
                f"{base}/measured",
                dev.taus,
                dev.dev[:, col],
                (f"measured {dev.kind}",),
                points=True,
                **plot,
            )
            if fdev is not dev:
                rec.curve(
                    f"{base}/fitted_kind",
                    fdev.taus,
                    fdev.dev[:, col],
                    (f"{fdev.kind} (fitted)",),
                    points=True,
                    **plot,
                )
            f = fits[(name, i)]
            rec.curve(f"{base}/model", dense, f.deviation(dense), ("fit",), **plot)
            terms = [t for t in TERMS if f.params[t] > 0]
            lines = [np.sqrt(term_variance(t, f.params[t], dense)) for t in terms]
            if terms:
                rec.curve(f"{base}/terms", dense, np.column_stack(lines), terms, guide=True, **plot)


# -- artifacts ---------------------------------------------------------------------------------
JUMP_WINDOW_S = 10
"""s: a bias jump is the difference of the gyro's means over this long before and after each
second (:func:`bias_jump`)."""
JUMP_RATIO = 8.0
"""The largest such difference, in robust standard deviations of all of them, still taken as
noise: white, flicker and random-walk noise give about 4 (simulated two hours at 100 Hz, with
and without bias instability); a step of one sample's noise at 100 Hz gives 25, of a fifth of it
6 to 7 (not caught: it reads as a random walk about twice the truth's)."""


def bias_jump(means: np.ndarray) -> tuple[float, int, float] | None:
    """The largest jump of the gyro bias: ``D_i`` = mean of the 1 s means ``means`` (m, 3) over
    the :data:`JUMP_WINDOW_S` seconds after second ``i`` minus that over the seconds before;
    returns (largest ``|D_i - median|`` over the axes in units of ``1.4826 MAD``, its second,
    its size rad/s), or None when the recording is too short or the means do not vary."""
    w = JUMP_WINDOW_S
    if len(means) < 4 * w:
        return None
    c = np.vstack([np.zeros((1, means.shape[1])), np.cumsum(means, axis=0)])
    after = (c[2 * w :] - c[w:-w]) / w
    before = (c[w:-w] - c[: -2 * w]) / w
    d = after - before
    dev = np.abs(d - np.median(d, axis=0))
    scale = 1.4826 * np.median(dev, axis=0)
    if not np.all(scale > 0):
        return None
    z = dev / scale
    i, axis = np.unravel_index(int(np.argmax(z)), z.shape)
    return float(z[i, axis]), int(i + w), float(d[i, axis])


N_UPPER_SPAN = 4.0
"""The taus up to this many times the shortest give :func:`n_upper`."""


def n_upper(taus: np.ndarray, dev: np.ndarray) -> float:
    """Upper bound of the white-noise density N (per sqrt(Hz)) from the shortest taus: every term
    of the Allan variance is positive, so ``N^2 / tau <= sigma^2(tau)`` and ``N <= sigma(tau)
    sqrt(tau)``. The largest of these over the taus up to :data:`N_UPPER_SPAN` times the
    shortest: a low-pass filter lowers sigma at the very shortest tau below the white noise's
    line, so the bound is taken where the filter no longer does."""
    near = taus <= N_UPPER_SPAN * taus[0]
    return float(np.max(dev[near] * np.sqrt(taus[near])))


def k_upper(fit: AllanFit, taus: np.ndarray, hi: np.ndarray) -> float:
    """An upper bound of the random-walk density K: the upper end of the fit's 68 % profile
    interval of K (:func:`imupipe.stages.allan.fit.profile_interval`: the other fitted terms
    re-fitted at every K, so a bias instability that could hide a random walk widens it); when
    K is not among the fitted terms, the largest K whose deviation K sqrt(tau / 3) stays under
    the upper 68 % bound at every tau."""
    if "K" in fit.ranges:
        return fit.ranges["K"][1]
    return float(np.min(hi * np.sqrt(3.0 / taus)))


def curves_csv(
    dev: est.Deviation,
    conf: est.Confidence,
    fits: dict[tuple[str, int], AllanFit],
    columns: list[tuple[str, int]],
    fdev: est.Deviation,
) -> str:
    """tau_s, then per sensor axis: deviation, 68 % bounds, fitted model, EDF, noise alpha (and
    the OADEV the model was fitted to, when the curve is another kind)."""
    cols = [dev.taus]
    header = ["tau_s", "m", "terms"]
    cols += [dev.m.astype(np.float64), dev.n.astype(np.float64)]
    for col, (name, i) in enumerate(columns):
        p = f"{name}_{AXES[i]}"
        header += [
            f"{p}_{dev.kind}",
            f"{p}_lo68",
            f"{p}_hi68",
            f"{p}_fit",
            f"{p}_edf",
            f"{p}_alpha",
        ]
        cols += [
            dev.dev[:, col],
            conf.lo[:, col],
            conf.hi[:, col],
            fits[(name, i)].deviation(dev.taus),
            conf.edf[:, col],
            conf.alpha[:, col].astype(np.float64),
        ]
        if fdev is not dev:
            header.append(f"{p}_{fdev.kind}")
            cols.append(fdev.dev[:, col])
    buf = io.StringIO()
    np.savetxt(
        buf, np.column_stack(cols), delimiter=",", header=",".join(header), comments="", fmt="%.10g"
    )
    return buf.getvalue()
