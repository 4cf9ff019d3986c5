"""The fleet view of ``imupipe survey``: each device's history of still periods, its drift, steps,
noise changes and in-field thermal curve, and robust outlier rules against its own history and
against the fleet.

Per device (the still periods of all its logs; with a calibration, the figures after it):

1. **In-field thermal slope** (unit/K) of the gyro bias (each axis) and of ``|a| - g``, from two
   estimates: *between logs*, the median over consecutive logs of ``d figure / d temperature``
   (pairs at least ``MIN_DT`` apart; one step between two logs does not move a median), and
   *within logs*, the weighted least-squares slope of the figure on temperature with both
   demeaned per log (used when there are too few pairs and it exceeds 3 standard errors). The
   per-log figures are referred to the device's median temperature with it. ``|a| - g`` is taken
   from level periods only (elsewhere the accelerometer's x and y offsets project onto gravity
   with the tilt).
2. **Per log**: the inverse-variance weighted mean of the referred figures (gyro bias per axis,
   ``|a| - g``) and its standard error; the mean noise density over the axes (gyro, accel); the
   mean temperature and the log's date (days since the fleet's first period).
3. **Steps** between consecutive logs: ``|d| > k sqrt(s_fleet^2 + se_1^2 + se_2^2 +
   (se_slope dT)^2)``, ``s_fleet`` the robust scale (1.4826 MAD) of every consecutive difference
   in the fleet (the ordinary log-to-log change: random walk, residual temperature error),
   ``se_slope dT`` the error of referring the two logs to one temperature.
4. **Noise**: a log whose log-noise departs from the median of the device's *earlier* logs (at
   least two) by more than ``k`` times the fleet's robust scale of that departure (floored at
   ``NOISE_FLOOR``, a 5 % relative change) is flagged (an increase: a loose mount, a failing
   part; a drop to near zero: a stuck output).
5. **Drift**: the Theil-Sen slope over calendar days of the per-log figure (unit/day), flagged
   when it departs from the fleet's median slope by more than ``k`` robust sigmas of the fleet's
   slopes and its change over the device's span exceeds ``k s_fleet sqrt(logs - 1)`` (the reach
   of the ordinary log-to-log change, a random walk, over that many logs). The flag names the log
   the drift starts at (:func:`drift_onset`) when one stands out.
6. **Moved**: the change of each figure from the first log to the last, in units of the fleet's
   step scale; the fleet table is sorted by it.

``k`` (default 5) is the number of robust standard deviations (1.4826 MAD, Rousseeuw & Croux
1993) beyond which a value is flagged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imupipe.stages.survey.stats import mad_sigma, theil_sen, weighted_mean

NOISE_FLOOR = 0.05
"""Smallest robust scale of a log's log-noise departure: 5 % (below it, a change is not
meaningful for a fleet's health)."""
DAY_NS = 86_400e9
MIN_DT = 3.0
"""K: the smallest temperature difference between two logs used for the between-log slope."""
THERMAL_SIGNIFICANCE = 3.0
"""A thermal slope is used to refer figures to the reference temperature when it exceeds this
many standard errors."""


@dataclass
class DeviceHistory:
    """One device's per-log figures (see the module docstring); arrays of one entry per log."""

    device_id: str
    logs: list[str]
    day: np.ndarray
    temperature: np.ndarray
    figures: dict[str, np.ndarray]
    """figure name -> (logs,) value referred to the reference temperature."""
    se: dict[str, np.ndarray]
    noise: dict[str, np.ndarray]
    """``gyro``, ``accel`` -> (logs,) mean noise density over the axes."""
    thermal: dict[str, tuple[float, float, float, float, float]]
    """figure -> (slope used per K, its standard error, within-log slope, its standard error,
    between-log slope)."""
    t_ref: float
    periods: int
    flags: list[dict[str, Any]] = field(default_factory=list)
    drift: dict[str, float] = field(default_factory=dict)
    moved: dict[str, float] = field(default_factory=dict)


FIGURES = ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "accel_norm_error")
UNITS = {
    "gyro_bias_x": "rad/s",
    "gyro_bias_y": "rad/s",
    "gyro_bias_z": "rad/s",
    "accel_norm_error": "m/s^2",
}


def within_log_slope(
    log_index: np.ndarray, x: np.ndarray, y: np.ndarray, se: np.ndarray
) -> tuple[float, float]:
    """Weighted slope of ``y`` on ``x`` from their variation within each log (both demeaned per
    log with the weights ``1/se^2``) and its standard error; NaN when x does not vary."""
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(se) & (se > 0)
    if ok.sum() < 3:
        return float("nan"), float("nan")
    g, x, y, w = log_index[ok], x[ok], y[ok], 1.0 / se[ok] ** 2
    sw = np.bincount(g, w)
    xm = np.bincount(g, w * x) / np.where(sw > 0, sw, 1)
    ym = np.bincount(g, w * y) / np.where(sw > 0, sw, 1)
    dx, dy = x - xm[g], y - ym[g]
    sxx = float(np.sum(w * dx * dx))
    if not sxx > 0:
        return float("nan"), float("nan")
    slope = float(np.sum(w * dx * dy) / sxx)
    dof = max(len(x) - len(np.unique(g)) - 1, 1)
    chi2 = float(np.sum(w * (dy - slope * dx) ** 2)) / dof
    return slope, float(np.sqrt(max(chi2, 1.0) / sxx))


def between_log_slope(
    temperature: np.ndarray, values: np.ndarray, min_dt: float = MIN_DT
) -> tuple[float, float]:
    """The thermal slope from consecutive logs and its standard error: the median of
    ``d value / d temperature`` over consecutive pairs whose temperatures differ by at least
    ``min_dt`` K (at least three pairs, else NaN), its error ``1.2533 s / sqrt(pairs)`` (the
    median's, ``s`` the ratios' robust scale). A median of ratios: one step (a crash) between
    two logs does not move it."""
    dv, dt = np.diff(values), np.diff(temperature)
    ok = np.isfinite(dv) & np.isfinite(dt) & (np.abs(dt) >= min_dt)
    if ok.sum() < 3:
        return float("nan"), float("nan")
    ratios = dv[ok] / dt[ok]
    return float(np.median(ratios)), float(1.2533 * mad_sigma(ratios) / np.sqrt(len(ratios)))


def device_history(
    device_id: str,
    log: Sequence[str],
    start_ns: np.ndarray,
    temperature: np.ndarray,
    values: Mapping[str, np.ndarray],
    se: Mapping[str, np.ndarray],
    noise: Mapping[str, np.ndarray],
    t0_ns: int,
) -> DeviceHistory:
    """Per-log figures of one device from its periods (``values``/``se``: figure -> (m,);
    ``noise``: ``gyro``/``accel`` -> (m,) mean noise density of the axes)."""
    names, index = np.unique(np.asarray(log), return_inverse=True)
    order = np.argsort([start_ns[index == i].min() for i in range(len(names))])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[index]
    names = names[order]
    n = len(names)
    finite_t = temperature[np.isfinite(temperature)]
    t_ref = float(np.median(finite_t)) if len(finite_t) else float("nan")
    with np.errstate(invalid="ignore"):
        temps = np.array(
            [
                np.nanmean(temperature[index == i])
                if np.isfinite(temperature[index == i]).any()
                else np.nan
                for i in range(n)
            ]
        )
    figures, ses, thermal = {}, {}, {}
    for name in FIGURES:
        within = within_log_slope(index, temperature, values[name], se[name])
        per = [weighted_mean(values[name][index == i], se[name][index == i]) for i in range(n)]
        raw = np.array([p[0] for p in per])
        between, between_se = between_log_slope(temps, raw)
        slope, slope_se = between, between_se
        if (
            not np.isfinite(slope)
            and np.isfinite(within[0])
            and abs(within[0]) > THERMAL_SIGNIFICANCE * within[1]
        ):
            slope, slope_se = within
        thermal[name] = (slope, np.nan_to_num(slope_se), within[0], within[1], between)
        figures[name] = raw - (np.nan_to_num(slope) * np.nan_to_num(temps - t_ref))
        ses[name] = np.array([p[1] for p in per])
    day = np.array([(start_ns[index == i].mean() - t0_ns) / DAY_NS for i in range(n)])
    return DeviceHistory(
        device_id,
        [str(x) for x in names],
        day,
        temps,
        figures,
        ses,
        {s: np.array([np.median(noise[s][index == i]) for i in range(n)]) for s in noise},
        thermal,
        t_ref,
        len(start_ns),
    )


def _flag(
    h: DeviceHistory, kind: str, figure: str, log: str | None, value: float, limit: float, why: str
) -> None:
    h.flags.append(
        {
            "device_id": h.device_id,
            "kind": kind,
            "figure": figure,
            "log": log,
            "value": float(value),
            "threshold": float(limit),
            "why": why,
        }
    )


def drift_onset(f: np.ndarray, se: np.ndarray, scale: float, k: float, sign: float) -> int | None:
    """The log a drift starts at: the first log ``j`` from which every log departs from the
    median of the logs before ``j``, on the drift's side (``sign``), by more than
    ``k sqrt(scale^2 + se^2)`` (the step rule's limit); None when there is none (a drift from
    the first log on, or one that comes and goes)."""
    for j in range(1, len(f)):
        departure = sign * (f[j:] - np.median(f[:j]))
        if np.all(departure > k * np.sqrt(scale**2 + se[j:] ** 2)):
            return j
    return None


def fleet_flags(histories: Sequence[DeviceHistory], k: float) -> dict[str, Any]:
    """Apply the rules of the module docstring to every device (fills ``flags``, ``drift`` and
    ``moved``); returns the fleet's scales."""
    scales: dict[str, float] = {}
    for name in FIGURES:
        diffs = np.concatenate([np.diff(h.figures[name]) for h in histories] or [np.zeros(0)])
        scales[name] = mad_sigma(diffs)
    noise_dev: dict[str, list[float]] = {"gyro": [], "accel": []}
    for h in histories:
        for s in noise_dev:
            ln = np.log(np.maximum(h.noise[s], 1e-300))
            for j in range(2, len(ln)):
                noise_dev[s].append(ln[j] - np.median(ln[:j]))
    for s, devs in noise_dev.items():
        scales[f"{s}_noise"] = max(mad_sigma(np.array(devs)), NOISE_FLOOR) if devs else NOISE_FLOOR
    slopes: dict[str, np.ndarray] = {}
    for name in FIGURES:
        for h in histories:
            h.drift[name] = theil_sen(h.day, h.figures[name]) if len(h.day) >= 3 else float("nan")
        slopes[name] = np.array([h.drift[name] for h in histories])
    for h in histories:
        for name in FIGURES:
            unit = UNITS[name]
            f, se = h.figures[name], h.se[name]
            base = np.nan_to_num(scales[name])
            for j in range(1, len(f)):
                d = f[j] - f[j - 1]
                dtemp = np.nan_to_num(h.temperature[j] - h.temperature[j - 1])
                referred = (h.thermal[name][1] * dtemp) ** 2  # the slope's error over the change
                limit = k * np.sqrt(base**2 + se[j] ** 2 + se[j - 1] ** 2 + referred)
                if np.isfinite(d) and abs(d) > limit:
                    _flag(
                        h,
                        "step",
                        name,
                        h.logs[j],
                        d,
                        limit,
                        f"{name} stepped by {d:+.3g} {unit} between {h.logs[j - 1]} and {h.logs[j]} (limit "
                        f"{limit:.2g}; temperature {h.temperature[j - 1]:.1f} -> {h.temperature[j]:.1f} degC)",
                    )
            h.moved[name] = float((f[-1] - f[0]) / base) if len(f) > 1 and base > 0 else 0.0
            finite = slopes[name][np.isfinite(slopes[name])]
            med = float(np.median(finite)) if len(finite) else float("nan")
            sig = mad_sigma(finite)
            span = h.day[-1] - h.day[0] if len(h.day) else 0.0
            s = h.drift[name]
            walk = k * base * np.sqrt(max(len(f) - 1, 1))  # a random walk's reach over the logs
            if (
                np.isfinite(s)
                and np.isfinite(sig)
                and abs(s - med) > k * sig
                and abs(s - med) * span > walk
            ):
                j = drift_onset(f, se, base, k, float(np.sign(s - med)))
                since = "" if j is None else f" from {h.logs[j]} on"
                _flag(
                    h,
                    "drift",
                    name,
                    None if j is None else h.logs[j],
                    s,
                    med + k * sig,
                    f"{name} drifts {s:+.3g} {unit}/day{since} (fleet median {med:+.3g}, limit +-{k * sig:.2g})",
                )
        for s in ("gyro", "accel"):
            ln = np.log(np.maximum(h.noise[s], 1e-300))
            for j in range(2, len(ln)):
                d = ln[j] - np.median(ln[:j])
                limit = k * scales[f"{s}_noise"]
                if abs(d) > limit:
                    word = "rose" if d > 0 else "fell"
                    _flag(
                        h,
                        "noise",
                        f"{s}_noise",
                        h.logs[j],
                        float(np.exp(d)),
                        float(np.exp(limit)),
                        f"{s} noise density {word} x{np.exp(d):.2f} against its earlier logs in {h.logs[j]} (limit x{np.exp(limit):.2f})",
                    )
    return {"k": k, "scales": scales}
