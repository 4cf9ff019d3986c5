"""The still moments of a log and what each one says about an IMU: the math of ``imupipe survey``.

**Still periods** (:func:`still_periods`): the static detector of
:mod:`imupipe.stages.static_detector` (Tedaldi et al. ICRA 2014: the norm of the per-axis variance
of the accelerometer over a centred ``window_s`` window, below ``k`` times the log's noise floor,
here its ``floor_quantile`` quantile), and the same rule on the gyro (a vehicle turning at a
constant rate has a quiet accelerometer), for runs of at least ``min_duration_s``.

**Per period** (:func:`period_stats`), vectorised over all periods at once with cumulative sums:

- gyro bias (rad/s, 3 axes): the period's mean rate. Its standard error by the method of batch
  means (``BATCHES`` contiguous batches, ``se = std(batch means) / sqrt(BATCHES)``; it holds for
  correlated noise, where ``std / sqrt(n)`` would be too small), floored by the white-noise
  value ``ADEV(tau) / sqrt(n tau0 / tau)``;
- accelerometer mean (m/s^2, 3 axes), ``|mean a| - g`` (m/s^2: the scale and offset error seen in
  the gravity magnitude, signed) and ``level``: the mean lies within ``level_deg`` of the body z
  axis, so its x and y components are the x and y offsets plus the (small) tilt;
- white-noise density of each axis (unit/sqrt(Hz)) from the period's own Allan deviation at
  ``tau`` (IEEE Std 952-1997 Annex C: on the -1/2 slope, ``N = ADEV(tau) sqrt(tau)``; computed on
  non-overlapping clusters of ``m = tau / tau0`` samples);
- temperature (degC): the mean of the temperature samples inside the period (NaN without any);
- start time (ns), duration (s) and sample count.

**Robust statistics** for the fleet view: :func:`mad_sigma` (1.4826 MAD: the standard deviation
of a normal sample, robust to outliers; Rousseeuw & Croux 1993), :func:`theil_sen` (median of
pairwise slopes; Sen 1968) and :func:`weighted_mean`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imupipe.stages.static_detector import Intervals, make_detector, moving_variance_norm, runs

G0 = 9.80665
BATCHES = 10
"""Batches of the batch-means standard error of a period's mean."""
MAD_TO_SIGMA = 1.4826
"""1 / Phi^-1(3/4): the MAD of a normal sample times this is its standard deviation."""


@dataclass(frozen=True)
class StillOptions:
    """The still-period rule (see the module docstring)."""

    min_duration_s: float = 5.0
    window_s: float = 1.0
    k: float = 4.0
    floor_quantile: float = 0.02
    tau_s: float = 0.1
    level_deg: float = 5.0


def still_periods(
    t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, opts: StillOptions
) -> Intervals:
    """The still periods of gyro rad/s and accel m/s^2 (n, 3) sampled at ``t_ns`` (increasing):
    sample ranges where both windowed variances lie below ``k`` times their noise floors, at least
    ``min_duration_s`` long. A log shorter than one window has none."""
    n = len(t_ns)
    if n < 3 or t_ns[-1] <= t_ns[0]:
        return Intervals(np.zeros(0, np.int64), np.zeros(0, np.int64))
    rate = (n - 1) / ((t_ns[-1] - t_ns[0]) * 1e-9)
    window = max(int(round(opts.window_s * rate)), 3)
    if n < window:
        return Intervals(np.zeros(0, np.int64), np.zeros(0, np.int64))
    detector = make_detector(
        t_ns,
        accel,
        window_s=opts.window_s,
        min_interval_s=opts.min_duration_s,
        floor_quantile=opts.floor_quantile,
    )
    quiet = detector.variance < opts.k * detector.reference
    gyro_var = moving_variance_norm(gyro, window)
    finite = gyro_var[np.isfinite(gyro_var)]
    gyro_floor = float(np.quantile(finite, opts.floor_quantile)) if len(finite) else 0.0
    if gyro_floor > 0:
        quiet &= gyro_var < opts.k * gyro_floor
    return runs(quiet, detector.min_samples)


def _segment_sums(values: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """(m, k) sums of ``values`` (n, k) over rows ``[start, stop)`` (cumulative sums, centred on
    the column means for precision)."""
    csum = np.vstack([np.zeros((1, values.shape[1])), np.cumsum(values, axis=0)])
    return csum[stop] - csum[start]


def batch_means_se(values: np.ndarray, intervals: Intervals, batches: int = BATCHES) -> np.ndarray:
    """(m, k) standard error of each period's mean of ``values`` (n, k) by the method of batch
    means (``batches`` contiguous batches of equal length; the remainder is left out)."""
    m = len(intervals)
    k = values.shape[1]
    if m == 0:
        return np.zeros((0, k))
    size = intervals.lengths // batches
    edges = intervals.start[:, None] + size[:, None] * np.arange(batches + 1)[None, :]
    centred = values - values.mean(axis=0)
    csum = np.vstack([np.zeros((1, k)), np.cumsum(centred, axis=0)])
    sums = csum[edges[:, 1:]] - csum[edges[:, :-1]]  # (m, batches, k)
    means = sums / np.maximum(size, 1)[:, None, None]
    se = means.std(axis=1, ddof=1) / np.sqrt(batches)
    se[size < 1] = np.nan
    return se


def cluster_adev(values: np.ndarray, intervals: Intervals, m: int) -> np.ndarray:
    """(p, k) Allan deviation at ``m`` samples of each period: non-overlapping clusters of ``m``
    samples inside the period, ``AVAR = mean((c[j+1] - c[j])^2) / 2`` (NaN with fewer than two
    clusters)."""
    p = len(intervals)
    k = values.shape[1]
    m = max(int(m), 1)
    count = intervals.lengths // m
    if p == 0:
        return np.zeros((0, k))
    owner = np.repeat(np.arange(p), count)
    first = np.cumsum(count) - count
    j = np.arange(int(count.sum())) - np.repeat(first, count)
    lo = intervals.start[owner] + j * m
    centred = values - values.mean(axis=0)
    csum = np.vstack([np.zeros((1, k)), np.cumsum(centred, axis=0)])
    means = (csum[lo + m] - csum[lo]) / m
    diff = np.diff(means, axis=0)
    same = owner[1:] == owner[:-1]
    sq = np.zeros((p, k))
    np.add.at(sq, owner[1:][same], diff[same] ** 2)
    pairs = np.bincount(owner[1:][same], minlength=p).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(sq / (2.0 * pairs[:, None]))


def period_means(
    t_ns: np.ndarray, values: np.ndarray, start_ns: np.ndarray, stop_ns: np.ndarray
) -> np.ndarray:
    """(m,) mean of samples ``values`` (n,) at ``t_ns`` (increasing) inside each
    ``[start_ns, stop_ns]`` (NaN where none)."""
    if len(t_ns) == 0:
        return np.full(len(start_ns), np.nan)
    lo = np.searchsorted(t_ns, start_ns, side="left")
    hi = np.searchsorted(t_ns, stop_ns, side="right")
    csum = np.r_[0.0, np.cumsum(values - values.mean())]
    with np.errstate(invalid="ignore", divide="ignore"):
        return (csum[hi] - csum[lo]) / (hi - lo) + values.mean()


def period_stats(
    t_ns: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    intervals: Intervals,
    opts: StillOptions,
    temperature: tuple[np.ndarray, np.ndarray] | None = None,
    g: float = G0,
) -> dict[str, np.ndarray]:
    """The figures of each still period (see the module docstring), as arrays of one row per
    period: ``start_ns``, ``stop_ns``, ``duration_s``, ``samples``, ``gyro_bias`` (m,3),
    ``gyro_bias_se`` (m,3), ``gyro_noise`` (m,3), ``accel_mean`` (m,3), ``accel_mean_se`` (m,3),
    ``accel_norm_error`` (m,), ``accel_norm_error_se`` (m,), ``accel_noise`` (m,3),
    ``level`` (m,) bool, ``tilt_deg`` (m,), ``temperature`` (m,) degC (``temperature``:
    (t_ns, values) of the temperature stream)."""
    n = len(t_ns)
    rate = (n - 1) / ((t_ns[-1] - t_ns[0]) * 1e-9)
    tau0 = 1.0 / rate
    m_tau = max(int(round(opts.tau_s * rate)), 1)
    lengths = intervals.lengths.astype(np.float64)
    start_ns = t_ns[intervals.start]
    stop_ns = t_ns[intervals.stop - 1]
    out: dict[str, np.ndarray] = {
        "start_ns": start_ns.astype(np.int64),
        "stop_ns": stop_ns.astype(np.int64),
        "duration_s": lengths * tau0,
        "samples": intervals.lengths.astype(np.int64),
    }
    for name, values in (("gyro", gyro), ("accel", accel)):
        mean = intervals.means(values) if len(intervals) else np.zeros((0, 3))
        adev = cluster_adev(values, intervals, m_tau)
        tau = m_tau * tau0
        white_se = adev / np.sqrt(np.maximum(lengths, 1.0) * tau0 / tau)[:, None]
        se = np.fmax(batch_means_se(values, intervals), white_se)
        out[f"{name}_bias" if name == "gyro" else "accel_mean"] = mean
        out[f"{name}_bias_se" if name == "gyro" else "accel_mean_se"] = se
        out[f"{name}_noise"] = adev * np.sqrt(tau)
    a = out["accel_mean"]
    norm = np.linalg.norm(a, axis=1)
    out["accel_norm_error"] = norm - g
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = a / norm[:, None]
        # propagated: d|a| = (a/|a|) . da, the axes' errors independent
        out["accel_norm_error_se"] = np.sqrt(np.sum((unit * out["accel_mean_se"]) ** 2, axis=1))
        tilt = np.degrees(np.arccos(np.clip(np.abs(unit[:, 2]), 0.0, 1.0)))
    out["tilt_deg"] = tilt
    out["level"] = tilt <= opts.level_deg
    if temperature is not None and len(temperature[0]):
        out["temperature"] = period_means(temperature[0], temperature[1], start_ns, stop_ns)
    else:
        out["temperature"] = np.full(len(intervals), np.nan)
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
