"""``allan`` stage: IMU noise identification from a long static recording (seed 001).

Computes a stability deviation (overlapping Allan deviation by default; see
:mod:`imupipe.stages.allan_estimators`) of every gyro and accelerometer axis at once, its 68 %
chi-square confidence bounds, and fits the five-term model of :mod:`imupipe.stages.allan_fit`
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
"metrics": {...}}``; artifacts ``imu.yaml`` (Kalibr), ``<name>_imu_utils.yaml`` (imu_utils
layout, meanings stated) and ``<name>_curves.csv``; Rerun: per axis the log10 deviation with its
bounds, the fitted model and each fitted term's line over ``log10(tau) * 1000``.

Input checks: NaN samples and time jumps (a step longer than ``max_gap`` nominal periods, or
time not increasing) are errors naming the sample; a recording too short to give the fit more
taus than terms is an error; motion (1 s gyro means further than ``motion_threshold`` from the
mean, or accel-norm 1 s means spreading more than 0.05 g) and a recording under two hours are
warnings. An analysis stage: it adds nothing to the calibration chain.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import SENSOR_UNITS, has_stream, metadata, sensor
from imupipe.stages import allan_estimators as est
from imupipe.stages.allan_fit import TERMS, AllanFit, fit_allan, slope_readings, term_variance
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.gyro_bias import select_interval
from imupipe.stages.stillness import stillness

AXES = ("x", "y", "z")
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
        """Deviation: oadev (overlapping Allan, default), adev, mdev, hdev, ohdev, totdev."""
        taus: Literal["log", "octave", "decade", "all"] = "log"
        """Tau grid: log (``points_per_decade`` per decade), octave, decade, all."""
        points_per_decade: int = 10
        terms: list[str] = field(default_factory=lambda: list(TERMS))
        """Model terms to fit (subset of Q, N, B, K, R); unsupported ones come out zero."""
        penalty: float = 10.0
        """Information-criterion cost of one more term (log-space weighted residual units)."""
        model_error: float = 0.05
        """Relative model error added to each point's uncertainty (caps the short-tau weights)."""
        slope_tolerance: float = 0.25
        """Flag a slope reading that differs from the fit by more than this fraction."""
        interval: list[float] | None = None
        """[start_s, end_s] seconds from the first sample; default the whole input."""
        max_gap: float = 2.0
        """A time step longer than this many nominal sample periods is an error (a gap)."""
        motion_threshold: float = 0.02
        """rad/s: a 1 s gyro mean further than this from the overall mean warns of motion."""

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        opts = self.options
        self._check_options(ctx)
        if not has_stream(table, "imu"):
            raise ctx.fail("the input has no IMU samples")
        gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
        if opts.interval is not None and (
            len(opts.interval) != 2 or opts.interval[1] <= opts.interval[0]
        ):
            raise ctx.fail("'interval' must be [start_s, end_s] with end_s > start_s")
        if opts.interval is None:  # no copies: the whole input
            t_ns, data = gyro.t_ns, {"gyro": gyro.values, "accel": accel.values}
        else:
            mask = select_interval(gyro, opts.interval)
            t_ns, data = gyro.t_ns[mask], {"gyro": gyro.values[mask], "accel": accel.values[mask]}
        del gyro, accel
        rate_hz = self._check_samples(t_ns, data, ctx)
        duration = (t_ns[-1] - t_ns[0]) * 1e-9
        static = self._check_static(t_ns, data, ctx)

        x = est.rate_to_phase(
            [data[s][:, i] for s in self.sensors for i in range(3)], 1.0 / rate_hz
        )
        del data  # the phase (6, n + 1) is all the estimators need
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
        if len(t_ns) / rate_hz < 7200.0:  # n sample periods: 2 h at 400 Hz is 2.88 M samples
            ctx.warn(
                f"the recording lasts {duration / 60:.1f} min; Allan fits want two hours or more "
                "(B, K and R are poorly determined from a short recording)"
            )
        dev = est.deviation_of_phase(x, 1.0 / rate_hz, opts.kind, m)
        conf = est.confidence(dev, x)
        fdev, fconf = dev, conf
        if opts.kind not in FIT_KINDS:  # the five-term model is the Allan variance's
            fdev = est.deviation_of_phase(x, 1.0 / rate_hz, "oadev", m)
            fconf = est.confidence(fdev, x)
        del x

        results: dict[str, Any] = {}
        metrics: dict[str, Any] = {
            "samples": int(len(t_ns)),
            "duration_s": float(duration),
            "rate_hz": float(rate_hz),
            "kind": opts.kind,
            "fit_kind": fdev.kind,
            "taus": int(len(m)),
            "tau_range_s": [float(dev.taus[0]), float(dev.taus[-1])],
            "static": static,
            "units": UNITS,
        }
        fits: dict[tuple[str, int], AllanFit] = {}
        for col, (name, i) in enumerate((s, i) for s in self.sensors for i in range(3)):
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
                "K_upper_68": k_upper(fdev.taus, fconf.hi[:, col]),
            }
            if disagree:
                ctx.warn(
                    f"{name} {AXES[i]}: the IEEE slope reading of {', '.join(disagree)} differs "
                    f"from the fit by more than {opts.slope_tolerance:.0%} (see metrics)"
                )
        results["metrics"] = metrics
        self._record(ctx, dev, conf, fits, fdev)
        meta = metadata(table)
        topic = (meta.get("topics") or {}).get("imu") or "/imu/data"
        artifacts = {
            "imu.yaml": kalibr_yaml(results, topic, rate_hz, ctx.input_name, fdev.kind),
            f"{ctx.name}_imu_utils.yaml": imu_utils_yaml(results, ctx.input_name),
            f"{ctx.name}_curves.csv": curves_csv(dev, conf, fits, self.sensors, fdev),
        }
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
        if opts.max_gap <= 1.0:
            raise ctx.fail("max_gap must be > 1 (sample periods)")

    def _check_samples(
        self, t_ns: np.ndarray, data: dict[str, np.ndarray], ctx: StageContext
    ) -> float:
        """Errors on NaN samples and gaps; returns the mean sample rate, Hz."""
        if len(t_ns) < 3:
            raise ctx.fail(f"only {len(t_ns)} IMU samples")
        for name, values in data.items():
            bad = ~np.isfinite(values).all(axis=1)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ctx.fail(
                    f"{name} sample {i} (t = {(t_ns[i] - t_ns[0]) * 1e-9:.6f} s) is not finite "
                    f"({int(bad.sum())} such samples); Allan variance needs gap-free data"
                )
        dt = np.diff(t_ns)
        if np.any(dt <= 0):
            i = int(np.flatnonzero(dt <= 0)[0])
            raise ctx.fail(f"time does not increase at sample {i + 1} (step {dt[i]} ns)")
        nominal = float(np.median(dt))
        jumps = dt > self.options.max_gap * nominal
        if jumps.any():
            i = int(np.flatnonzero(jumps)[0])
            raise ctx.fail(
                f"time jump of {dt[i] * 1e-9:.6f} s ({dt[i] / nominal:.1f} sample periods) after "
                f"sample {i} (t = {(t_ns[i] - t_ns[0]) * 1e-9:.3f} s); {int(jumps.sum())} gap(s) "
                f"longer than max_gap = {self.options.max_gap} periods"
            )
        return (len(t_ns) - 1) / ((t_ns[-1] - t_ns[0]) * 1e-9)

    def _check_static(
        self, t_ns: np.ndarray, data: dict[str, np.ndarray], ctx: StageContext
    ) -> bool:
        still = stillness(t_ns, data["gyro"], data["accel"])
        static = still.static(self.options.motion_threshold)
        if not static:
            ctx.warn(
                f"{still.describe(self.options.motion_threshold)}; motion inflates every noise term"
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
    ) -> None:
        rec = ctx.recorder
        if not getattr(rec, "enabled", False):
            return
        dense = np.logspace(np.log10(dev.taus[0]), np.log10(dev.taus[-1]), 200)
        for col, (name, i) in enumerate((s, i) for s in self.sensors for i in range(3)):
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
def _largest(results: dict[str, Any], name: str, term: str) -> tuple[float, str]:
    axis = max(AXES, key=lambda a: results[name][a][term])
    return results[name][axis][term], axis


def k_upper(taus: np.ndarray, hi: np.ndarray) -> float:
    """The largest random-walk density K whose Allan deviation K sqrt(tau / 3) stays under the
    upper 68 % bound at every tau (an upper bound when the fit finds no random walk)."""
    return float(np.min(hi * np.sqrt(3.0 / taus)))


def kalibr_yaml(
    results: dict[str, Any], topic: str, rate_hz: float, input_name: str, kind: str
) -> str:
    """Kalibr's IMU noise file (continuous time; the largest axis of each sensor)."""
    lines = [
        f"# Kalibr IMU noise model from imupipe's allan stage (input '{input_name}', {kind} fit).",
        "# Continuous-time SI: noise densities per sqrt(Hz), random walks per second per sqrt(Hz).",
        "# Kalibr takes one value per sensor: each line is the LARGEST of the three axes (named).",
    ]
    for name, prefix, units in (
        ("accel", "accelerometer", ("m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)")),
        ("gyro", "gyroscope", ("rad/s/sqrt(Hz)", "rad/s^2/sqrt(Hz)")),
    ):
        if name not in results:
            continue
        n, na = _largest(results, name, "N")
        k, ka = _largest(results, name, "K")
        note = f"axis {ka}"
        if k == 0.0:  # no random walk resolved: a zero would make Kalibr overconfident
            upper = results["metrics"][name]
            ka = max(AXES, key=lambda a: upper[a]["K_upper_68"])
            k = upper[ka]["K_upper_68"]
            note = f"axis {ka}: the fit resolved no random walk; upper bound from the 68 % band"
        lines.append(f"{prefix}_noise_density: {n:.6e}  # {units[0]}, axis {na}")
        lines.append(f"{prefix}_random_walk: {k:.6e}  # {units[1]}, {note}")
    lines.append(f'rostopic: "{topic}"')
    lines.append(f"update_rate: {rate_hz:.6g}  # Hz, measured from the timestamps")
    return "\n".join(lines) + "\n"


def imu_utils_yaml(results: dict[str, Any], input_name: str) -> str:
    """imu_utils's layout (``gyr_n``, ``gyr_w``, ``acc_n``, ``acc_w``) with honest meanings."""
    out = [
        "%YAML:1.0",
        "---",
        "# imu_utils layout, written by imupipe's allan stage. Continuous-time SI, per axis:",
        "#   gyr_n / acc_n: white noise density N (rad/s/sqrt(Hz), m/s^2/sqrt(Hz))",
        "#   gyr_w / acc_w: random walk density K (rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz)), the",
        "#     meaning VINS and Kalibr expect. NOT what imu_utils writes there (the minimum of the",
        "#     Allan deviation, i.e. bias instability 0.664 B, in rad/s): that is gyr_b / acc_b",
        "#     here, the bias instability B itself (rad/s, m/s^2).",
        "#   avg-axis: the mean of the three axes.",
        "type: IMU",
        f"name: {input_name}",
    ]
    for name, section, p, unit in (
        ("gyro", "Gyr", "gyr", "rad/s"),
        ("accel", "Acc", "acc", "m/s^2"),
    ):
        if name not in results:
            continue
        out += [f"{section}:", f'   unit: " {unit}"']
        rows = [
            ("avg-axis", {t: float(np.mean([results[name][a][t] for a in AXES])) for t in TERMS})
        ]
        rows += [(f"{a}-axis", results[name][a]) for a in AXES]
        for label, vals in rows:
            out += [
                f"   {label}:",
                f"      {p}_n: {vals['N']:.16e}",
                f"      {p}_w: {vals['K']:.16e}",
                f"      {p}_b: {vals['B']:.16e}",
            ]
    return "\n".join(out) + "\n"


def curves_csv(
    dev: est.Deviation,
    conf: est.Confidence,
    fits: dict[tuple[str, int], AllanFit],
    sensors: tuple[str, ...],
    fdev: est.Deviation,
) -> str:
    """tau_s, then per sensor axis: deviation, 68 % bounds, fitted model, EDF, noise alpha (and
    the OADEV the model was fitted to, when the curve is another kind)."""
    cols = [dev.taus]
    header = ["tau_s", "m", "terms"]
    cols += [dev.m.astype(np.float64), dev.n.astype(np.float64)]
    for col, (name, i) in enumerate((s, i) for s in sensors for i in range(3)):
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
