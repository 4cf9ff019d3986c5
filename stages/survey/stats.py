"""The still moments of a log and what each one says about an IMU: the math of ``imupipe survey``.

**Still periods** (:func:`still_periods`): the static detector of
:mod:`imupipe.stages.static_detector` (Tedaldi et al. ICRA 2014: the norm of the per-axis variance
of the accelerometer over a centred ``window_s`` window, below ``k`` times the log's noise floor,
here its ``floor_quantile`` quantile, read from a fine log-spaced histogram), and the same rule on
the gyro (a vehicle turning at a constant rate has a quiet accelerometer), for runs of at least
``min_duration_s`` and ``MIN_PERIOD_SAMPLES`` samples at the sensor's own rate, with a window of
at least ``MIN_WINDOW_SAMPLES`` samples. The log's own floor cannot tell a vibrating airframe
from a still one (in a log in motion throughout its quietest stretch is the vibration): the
fleet view judges each candidate against the device's floor across its logs
(:func:`imupipe.stages.survey.fleet.still_judged`).

**Per period** (:func:`figures`, from the running sums of
:mod:`imupipe.stages.survey.streaming`), vectorised over all periods at once:

- gyro bias (rad/s, 3 axes): the period's mean rate. Its standard error by the method of batch
  means (``BATCHES`` to ``2 BATCHES - 1`` contiguous blocks of a power-of-two length,
  ``se = std(block means) / sqrt(blocks)``; it holds for correlated noise, where
  ``std / sqrt(n)`` would be too small), floored by the white-noise value
  ``ADEV(tau) / sqrt(n tau0 / tau)``;
- accelerometer mean (m/s^2, 3 axes), ``|mean a| - g`` (m/s^2: the scale and offset error seen in
  the gravity magnitude, signed) and ``level``: the mean lies within ``level_deg`` of the body z
  axis, so its x and y components are the x and y offsets plus the (small) tilt;
- white-noise density of each axis (unit/sqrt(Hz)) from the period's own Allan deviation at
  ``tau`` (IEEE Std 952-1997 Annex C: on the -1/2 slope, ``N = ADEV(tau) sqrt(tau)``; computed on
  non-overlapping clusters of ``m = tau / tau0`` samples, ``tau = max(tau_s, tau0)`` at the
  sensor's real rate: a 1 Hz topic's density is at 1 s, not 0.1 s);
- temperature (degC): the mean of the temperature samples inside the period (NaN without any);
- start time (ns), duration (s) and sample count.

**One way**: :func:`still_periods`, :func:`period_stats`, :func:`batch_means_se` and
:func:`cluster_adev` take a log held whole and run it as one batch through the streaming code;
the survey streams the same code batch by batch (:mod:`imupipe.pipeline.survey.stream`).

**Robust statistics** for the fleet view: :func:`mad_sigma` (1.4826 MAD: the standard deviation
of a normal sample, robust to outliers; Rousseeuw & Croux 1993), :func:`theil_sen` (median of
pairwise slopes; Sen 1968) and :func:`weighted_mean`.
"""

from __future__ import annotations

import numpy as np

from imupipe.stages.static_detector import Intervals
from imupipe.stages.survey.streaming import (
    BATCHES,
    Acc,
    FloorPass,
    PeriodPass,
    Rule,
    StillOptions,
    assign,
    cumsum0,
    extend,
    rate_of,
)

__all__ = [
    "BATCHES",
    "G0",
    "StillOptions",
    "batch_means_se",
    "cluster_adev",
    "figures",
    "mad_sigma",
    "period_stats",
    "still_periods",
    "theil_sen",
    "weighted_mean",
]

G0 = 9.80665
MAD_TO_SIGMA = 1.4826
"""1 / Phi^-1(3/4): the MAD of a normal sample times this is its standard deviation."""


def _none() -> Intervals:
    return Intervals(np.zeros(0, np.int64), np.zeros(0, np.int64))


def still_periods(
    t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, opts: StillOptions
) -> Intervals:
    """The still periods of gyro rad/s and accel m/s^2 (n, 3) sampled at ``t_ns`` (increasing):
    sample ranges where both windowed variances lie below ``k`` times their noise floors, at least
    ``min_duration_s`` long. A log shorter than one window has none. The log as one batch of
    :mod:`imupipe.stages.survey.streaming` (its two passes share the windowed variances)."""
    rate = rate_of(len(t_ns), int(t_ns[0]), int(t_ns[-1])) if len(t_ns) else None
    if rate is None:
        return _none()
    rule = Rule.at(opts, rate)
    if len(t_ns) < rule.window:
        return _none()
    x = np.column_stack([gyro, accel]).astype(np.float64)
    floor = FloorPass(rule.half, keep=True)
    floor.feed(t_ns, x)
    periods = PeriodPass(rule, floor.floors(opts), opts, 6, floor.reference)
    periods.classified(*floor.kept())
    found = periods.finish()
    return Intervals(found.flat("start"), found.flat("stop"))


def batch_means_se(values: np.ndarray, intervals: Intervals, batches: int = BATCHES) -> np.ndarray:
    """(m, k) standard error of each period's mean of ``values`` (n, k) by the method of batch
    means: between ``batches`` and ``2 batches - 1`` contiguous blocks of ``s`` samples, ``s``
    the least power of two giving fewer than ``2 batches`` (the remainder is left out; see
    :mod:`imupipe.stages.survey.streaming`)."""
    return _sums(values, intervals, 1, batches).batch_se()


def cluster_adev(values: np.ndarray, intervals: Intervals, m: int) -> np.ndarray:
    """(p, k) Allan deviation at ``m`` samples of each period: non-overlapping clusters of ``m``
    samples inside the period, ``AVAR = mean((c[j+1] - c[j])^2) / 2`` (NaN with fewer than two
    clusters)."""
    return _sums(values, intervals, max(int(m), 1)).adev()


def _sums(values: np.ndarray, intervals: Intervals, m: int, batches: int = BATCHES) -> Acc:
    values = np.asarray(values, dtype=np.float64)
    p, k = len(intervals), values.shape[1]
    cs = cumsum0(values - values.mean(axis=0)) if len(values) else np.zeros((1, k))
    return extend(Acc.empty(p, k, batches), cs, intervals.start, intervals.stop, m)


def period_stats(
    t_ns: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    intervals: Intervals,
    opts: StillOptions,
    temperature: tuple[np.ndarray, np.ndarray] | None = None,
    g: float = G0,
) -> dict[str, np.ndarray]:
    """The figures of each still period of a log held whole (see :func:`figures`;
    ``temperature``: (t_ns, values) of the temperature stream)."""
    rate = rate_of(len(t_ns), int(t_ns[0]), int(t_ns[-1])) if len(t_ns) else None
    rule = Rule.at(opts, rate or 1.0)
    x = np.column_stack([gyro, accel]).astype(np.float64)
    ref = x.mean(axis=0)
    acc = extend(
        Acc.empty(len(intervals), 6), cumsum0(x - ref), intervals.start, intervals.stop, rule.m_tau
    )
    start_ns = t_ns[intervals.start].astype(np.int64)
    stop_ns = t_ns[intervals.stop - 1].astype(np.int64)
    if temperature is not None:
        tsum, tcount = assign(temperature[0], temperature[1], start_ns, stop_ns)
    else:
        tsum, tcount = np.zeros(len(intervals)), np.zeros(len(intervals), np.int64)
    return figures(start_ns, stop_ns, acc, ref, tsum, tcount, rule, opts, g)


def figures(
    start_ns: np.ndarray,
    stop_ns: np.ndarray,
    acc: Acc,
    reference: np.ndarray,
    temp_sum: np.ndarray,
    temp_count: np.ndarray,
    rule: Rule,
    opts: StillOptions,
    g: float = G0,
    columns: slice = slice(0, 6),
) -> dict[str, np.ndarray]:
    """The figures of each still period (see the module docstring) from its sums
    (:class:`~imupipe.stages.survey.streaming.Acc`, over ``columns``: gyro then accelerometer,
    centred on ``reference``), as arrays of one row per period: ``start_ns``, ``stop_ns``,
    ``duration_s``, ``samples``, ``gyro_bias`` (m,3), ``gyro_bias_se`` (m,3), ``gyro_noise``
    (m,3), ``accel_mean`` (m,3), ``accel_mean_se`` (m,3), ``accel_norm_error`` (m,),
    ``accel_norm_error_se`` (m,), ``accel_noise`` (m,3), ``level`` (m,) bool, ``tilt_deg``
    (m,), ``temperature`` (m,) degC (NaN without a temperature sample in the period)."""
    tau0 = 1.0 / rule.rate
    lengths = acc.n.astype(np.float64)
    mean = acc.mean()[:, columns] + np.asarray(reference)[columns]
    batch = acc.batch_se()[:, columns]
    adev = acc.adev()[:, columns]
    tau = rule.m_tau * tau0
    white_se = adev / np.sqrt(np.maximum(lengths, 1.0) * tau0 / tau)[:, None]
    se = np.fmax(batch, white_se)
    noise = adev * np.sqrt(tau)
    out: dict[str, np.ndarray] = {
        "start_ns": np.asarray(start_ns, np.int64),
        "stop_ns": np.asarray(stop_ns, np.int64),
        "duration_s": lengths * tau0,
        "samples": acc.n.astype(np.int64),
        "gyro_bias": mean[:, :3],
        "gyro_bias_se": se[:, :3],
        "gyro_noise": noise[:, :3],
        "accel_mean": mean[:, 3:],
        "accel_mean_se": se[:, 3:],
        "accel_noise": noise[:, 3:],
    }
    a = out["accel_mean"]
    norm = np.linalg.norm(a, axis=1)
    out["accel_norm_error"] = norm - g
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = a / norm[:, None]
        # propagated: d|a| = (a/|a|) . da, the axes' errors independent
        out["accel_norm_error_se"] = np.sqrt(np.sum((unit * out["accel_mean_se"]) ** 2, axis=1))
        tilt = np.degrees(np.arccos(np.clip(np.abs(unit[:, 2]), 0.0, 1.0)))
        out["temperature"] = np.where(temp_count > 0, temp_sum / np.maximum(temp_count, 1), np.nan)
    out["tilt_deg"] = tilt
    out["level"] = tilt <= opts.level_deg
    return out


# -- robust statistics for the fleet view ---------------------------------------------------------


def mad_sigma(x: np.ndarray) -> float:
    """1.4826 times the median absolute deviation from the median of the finite ``x`` (NaN when
    empty)."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan")
    return float(MAD_TO_SIGMA * np.median(np.abs(x - np.median(x))))


def theil_sen(x: np.ndarray, y: np.ndarray) -> float:
    """The Theil-Sen slope of ``y`` on ``x``: the median of the slopes of every pair with distinct
    x (NaN with fewer than two distinct x)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    i, j = np.triu_indices(len(x), 1)
    dx = x[j] - x[i]
    keep = dx != 0
    if not keep.any():
        return float("nan")
    return float(np.median((y[j] - y[i])[keep] / dx[keep]))


def weighted_mean(values: np.ndarray, se: np.ndarray) -> tuple[float, float]:
    """Inverse-variance weighted mean of ``values`` with standard errors ``se`` and its standard
    error, scaled up by the Birge ratio ``sqrt(chi2 / (n - 1))`` when the values scatter more
    than their errors say (NaN entries left out; NaN when none is left)."""
    ok = np.isfinite(values) & np.isfinite(se) & (se > 0)
    if not ok.any():
        return float("nan"), float("nan")
    w = 1.0 / se[ok] ** 2
    mean = float(np.sum(w * values[ok]) / w.sum())
    n = int(ok.sum())
    birge = float(np.sum(w * (values[ok] - mean) ** 2)) / (n - 1) if n > 1 else 1.0
    return mean, float(np.sqrt(max(birge, 1.0) / w.sum()))
