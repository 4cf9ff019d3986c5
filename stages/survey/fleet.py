"""The fleet view of ``imupipe survey``: each device's history of still periods, its drift, steps,
noise changes and in-field thermal curve, and robust outlier rules against its own history and
against the fleet.

Per device (the still periods of all its logs; with a calibration, the figures after it):

1. **Attitude** (:func:`attitude_term`): ``|a| - g ~ b . u`` for a period whose gravity direction
   is ``u``, so a period leaning by a few degrees sees the accelerometer's x and y offsets; they
   are fitted per device within logs and ``b_x u_x + b_y u_y`` is taken off each period (its
   error added to the period's). ``|a| - g`` is then taken from level periods only.
2. **Per log** (:func:`thermal_fit`): the inverse-variance weighted mean of each figure (gyro bias
   per axis, ``|a| - g``) and its standard error, and the mean temperature of the same periods
   with the same weights; the mean noise density over the axes (gyro, accel); the mean
   temperature and the log's date (days since the fleet's first period).
3. **In-field thermal slope** (unit/K) of each figure, always with its standard error: the
   inverse-variance mean of the *within-log* slope (:func:`within_log_slope`) and the
   *between-log* slope (:func:`between_log_slope`, whose error needs the fleet's step scale
   ``s``: the slopes and ``s`` are computed twice); a device without either takes the fleet's
   median slope with the fleet's robust spread of slopes as its error (:func:`_fleet_slope`).
   The per-log figures are referred to the device's median temperature with it (:func:`refer`).
   The chamber comparison (:mod:`imupipe.stages.survey.chamber`) uses the same estimate.
4. **Steps** between consecutive logs (that have the figure: a log without a level period is
   passed over, ``n`` the intervals spanned): ``|d| > k sqrt(n s_fleet^2 + se_1^2 + se_2^2 +
   (se_slope dT)^2)``, ``s_fleet`` the robust scale (1.4826 MAD) of every consecutive difference
   in the fleet (the ordinary log-to-log change: random walk, residual temperature error),
   ``se_slope dT`` the error of referring the two logs to one temperature (``dT``: the change of
   the figure's temperature).
5. **Noise**: a log whose log-noise departs from the median of the device's *earlier* logs (at
   least two) by more than ``k`` times the fleet's robust scale of that departure (floored at
   ``NOISE_FLOOR``, a 5 % relative change) is flagged (an increase: a loose mount, a failing
   part; a drop to near zero: a stuck output).
6. **Drift**: the Theil-Sen slope over calendar days of the per-log figure (unit/day), flagged
   when it departs from the fleet's median slope by more than ``k`` robust sigmas of the fleet's
   slopes and its change over the device's span exceeds ``k s_fleet sqrt(logs - 1)`` (the reach
   of the ordinary log-to-log change, a random walk, over that many logs). The flag names the log
   the drift starts at (:func:`drift_onset`) when one stands out.
7. **Moved**: the change of each figure from the first log to the last, in units of the fleet's
   step scale; the fleet table is sorted by it.
8. **Accelerometer offsets per axis** (:func:`accel_axes`, :data:`ACCEL_AXES`): per log, where
   the still periods' orientations tell them (a device set down on several faces), judged by
   the step and drift rules like the other per-log figures (:data:`LOG_FIGURES`).

(The drift test is :func:`fleet_flags`' generalised least squares, not the Theil-Sen slope of
6.; a single step between logs is kept as a step unless a line through the logs fits at least as
well, and across a long gap it is then a drift: :func:`_long_gap`.)

``k`` (default 5) is the number of robust standard deviations (1.4826 MAD, Rousseeuw & Croux
1993) beyond which a value is flagged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imupipe.stages.survey.stats import mad_sigma, weighted_mean

NOISE_FLOOR = 0.05
"""Smallest robust scale of a log's log-noise departure: 5 % (below it, a change is not
meaningful for a fleet's health)."""
DAY_NS = 86_400e9
MIN_DT = 3.0
"""K: the smallest temperature difference between two logs used for the between-log slope."""
MIN_PRIOR_DEVICES = 3
"""Devices with a thermal slope of a figure needed before the fleet's slopes stand in for a device
without one (fewer: such a device's figures are not referred, and the error of not referring
them is unknown)."""


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
    fits: dict[str, ThermalFit] = field(default_factory=dict)
    """figure -> its per-log values, their temperatures and thermal slopes (not referred)."""
    period: Periods | None = None
    """The still periods the figures come from (in time order)."""
    rejected: list[dict[str, Any]] = field(default_factory=list)
    """Candidate periods judged not still (:func:`still_judged`): log, start, noise ratios."""
    no_still: list[str] = field(default_factory=list)
    """Logs with candidates but no still period."""
    floors: dict[str, float] = field(default_factory=dict)
    """``gyro``, ``accel``: the device's noise floor (noise density)."""
    steady: dict[str, np.ndarray] = field(default_factory=dict)
    """figure -> the per-log figures with the steps between logs found taken out (the drift
    test's input; the in-log steps are out of ``figures`` already)."""
    power: dict[str, float] = field(default_factory=dict)
    """figure -> the smallest drift per day the drift test detects with 90 % probability."""
    axes: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 3)), np.zeros((0, 3)))
    """The accelerometer's offset per log and axis and its standard error, (logs, 3) m/s^2 (NaN
    where the log's orientations do not tell it: :func:`accel_axes`)."""
    axes_input: tuple[Any, ...] | None = None
    """:func:`accel_axes`'s arguments (fitted again with the fleet's in-log excess)."""


@dataclass
class Periods:
    """One device's still periods in time order: log index, start, temperature, figures and
    their standard errors, and the in-log steps taken out of each figure from their time on."""

    index: np.ndarray
    start_ns: np.ndarray
    temperature: np.ndarray
    values: dict[str, np.ndarray]
    se: dict[str, np.ndarray]
    offset: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in self.values:
            self.offset.setdefault(name, np.zeros(len(self.index)))


FIGURES = ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "accel_norm_error")
"""The figures of each still period (the per-log ones are their weighted means)."""
ACCEL_AXES = ("accel_bias_x", "accel_bias_y", "accel_bias_z")
"""The accelerometer's offset on each axis, per log, where the log's still periods lie in
orientations that tell it (:func:`accel_axes`)."""
LOG_FIGURES = FIGURES + ACCEL_AXES
"""Every per-log figure the steps between logs and the drift test judge."""
GROUPS = (FIGURES[:3], FIGURES[3:], ACCEL_AXES)
"""Figures that share a turn-on and random walk (the gyro's three axes: one die; the
accelerometer's offsets) in :func:`_walk_scales`."""
UNITS = {
    "gyro_bias_x": "rad/s",
    "gyro_bias_y": "rad/s",
    "gyro_bias_z": "rad/s",
    "accel_norm_error": "m/s^2",
    **dict.fromkeys(ACCEL_AXES, "m/s^2"),
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
    temperature: np.ndarray, values: np.ndarray, se: np.ndarray, step_scale: float = 0.0
) -> tuple[float, float]:
    """The thermal slope from consecutive logs and its standard error: the least-squares slope
    through the origin of the change of the per-log ``values`` between consecutive logs on the
    change of their ``temperature`` (the changes of a random walk are independent, its level is
    not; one step between two logs enters as one residual), its error from the scatter about it
    (``logs - 2`` degrees of freedom) and at least what the fleet's ordinary log-to-log change
    ``step_scale`` and the logs' own errors ``se`` give. NaN with fewer than three logs with a
    value and a temperature, or when no two consecutive ones are ``MIN_DT`` apart."""
    ok = np.isfinite(temperature) & np.isfinite(values)
    t, v, e = temperature[ok], values[ok], np.nan_to_num(se[ok])
    if len(t) < 3:
        return float("nan"), float("nan")
    dt, dv = np.diff(t), np.diff(v)
    if not np.max(np.abs(dt)) >= MIN_DT:
        return float("nan"), float("nan")
    sxx = float(dt @ dt)
    slope = float(dt @ dv) / sxx
    resid = dv - slope * dt
    floor = step_scale**2 + 2.0 * float(np.mean(e**2))
    var = max(float(resid @ resid) / (len(t) - 2), floor)
    return slope, float(np.sqrt(var / sxx))


def combined(estimates: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """The inverse-variance mean of independent (value, standard error) estimates and its
    standard error, the NaN ones left out (NaN, NaN when none is left)."""
    est = [(v, e) for v, e in estimates if np.isfinite(v) and np.isfinite(e) and e > 0]
    if not est:
        return float("nan"), float("nan")
    w = np.array([1.0 / e**2 for _, e in est])
    return float(np.sum(w * np.array([v for v, _ in est])) / w.sum()), float(1 / np.sqrt(w.sum()))


@dataclass
class ThermalFit:
    """One figure of one device per log (arrays of one entry per log, NaN for a log without a
    period that has the figure) and its thermal slopes (unit/K)."""

    value: np.ndarray
    """The inverse-variance weighted mean of the log's periods (not referred)."""
    se: np.ndarray
    temperature: np.ndarray
    """degC: the mean temperature of the same periods, with the same weights (the temperature
    ``value`` is at)."""
    within: float
    within_se: float
    between: float = float("nan")
    between_se: float = float("nan")
    slope: float = float("nan")
    slope_se: float = float("nan")

    def slopes(self, step_scale: float) -> tuple[float, float]:
        """Set ``between`` with the fleet's ``step_scale`` and ``slope``: the inverse-variance
        mean of the within-log and the between-log slopes (independent: one uses the periods'
        departures from their log's mean, the other the logs' means); returns (slope, se)."""
        self.between, self.between_se = between_log_slope(
            self.temperature, self.value, self.se, step_scale
        )
        self.slope, self.slope_se = combined(
            [(self.within, self.within_se), (self.between, self.between_se)]
        )
        return self.slope, self.slope_se


def thermal_fit(
    log_index: np.ndarray,
    n_logs: int,
    temperature: np.ndarray,
    values: np.ndarray,
    se: np.ndarray,
    step_scale: float = 0.0,
) -> ThermalFit:
    """Per log (``log_index`` in ``0 .. n_logs - 1`` per period) the weighted mean of ``values``
    (periods with a finite value and error), its error (:func:`weighted_mean`) and the mean
    temperature of the same periods with the same weights; the within-log slope
    (:func:`within_log_slope`) and the combined slope (:meth:`ThermalFit.slopes`)."""
    ok = np.isfinite(values) & np.isfinite(se) & (se > 0)
    value, err, temp = np.full(n_logs, np.nan), np.full(n_logs, np.nan), np.full(n_logs, np.nan)
    for j in range(n_logs):
        mine = ok & (log_index == j)
        if not mine.any():
            continue
        value[j], err[j] = weighted_mean(values[mine], se[mine])
        hot = mine & np.isfinite(temperature)
        if hot.any():
            temp[j] = float(np.average(temperature[hot], weights=1.0 / se[hot] ** 2))
    fit = ThermalFit(value, err, temp, *within_log_slope(log_index, temperature, values, se))
    fit.slopes(step_scale)
    return fit


def attitude_term(
    log_index: np.ndarray,
    direction: np.ndarray,
    temperature: np.ndarray,
    values: np.ndarray,
    se: np.ndarray,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The part of ``|a| - g`` that the attitude gives through the accelerometer's x and y
    offsets: ``|g u + b| - g ~ b . u``, so a period whose measured direction ``u`` (unit, (m, 3))
    leans by ``theta`` sees ``b_x u_x + b_y u_y`` (up to ``|b_xy| sin theta``: 2.6e-3 m/s^2 for
    0.03 m/s^2 offsets at 5 deg, more than the figure's own error). Estimated within logs from
    every still period (level or not): the weighted least-squares fit of ``values`` on
    ``(T, u_x, u_y)`` (``(u_x, u_y)`` when most periods have no temperature) with all demeaned
    per log (a free intercept per log: the bias random walk
    does not enter), its covariance scaled by ``chi2 / dof`` when above 1. Returns ``(b_x, b_y)``
    (unit) and its (2, 2) covariance; None with fewer than 2 degrees of freedom or when the
    periods' directions (or temperatures) do not vary within logs."""
    ok = np.isfinite(values) & np.isfinite(se) & (se > 0) & np.isfinite(direction).all(axis=1)
    hot = ok & np.isfinite(temperature)
    with_t = hot.sum() >= ok.sum() / 2  # temperature not logged: the fit without it
    ok = hot if with_t else ok
    g = np.unique(log_index[ok], return_inverse=True)[1]
    x = np.column_stack([temperature[ok], direction[ok, :2]] if with_t else [direction[ok, :2]])
    y, w = values[ok], 1.0 / se[ok] ** 2
    dof = len(y) - (int(g.max()) + 1 if len(g) else 0) - x.shape[1]
    if dof < 2:
        return None
    sw = np.bincount(g, w)
    dx = x - np.column_stack([np.bincount(g, w * c) for c in x.T])[g] / sw[g, None]
    dy = y - (np.bincount(g, w * y) / sw)[g]
    normal = (dx * w[:, None]).T @ dx
    if np.linalg.cond(normal) > 1e12:
        return None
    beta = np.linalg.solve(normal, (dx * w[:, None]).T @ dy)
    chi2 = float(np.sum(w * (dy - dx @ beta) ** 2)) / dof
    cov = np.linalg.inv(normal) * max(chi2, 1.0)
    first = x.shape[1] - 2
    return beta[first:], cov[first:, first:]


ACCEL_OFFSET_XY = 0.5
"""m/s^2: the size of a MEMS accelerometer's x and y offsets where the survey cannot fit them
(:func:`attitude_term` needs several periods): about 50 mg, the zero-g offset of consumer parts
(InvenSense MPU-6000 +-50 mg on x and y; Bosch BMI088 +-20 mg); times a period's lean it is the
error of taking ``|a| - g`` for the offset along gravity."""
ACCEL_AXIS_SE_MAX = 0.02
"""m/s^2 (2 mg): an axis's offset in a log is a figure of the survey when it is known to this
(a tenth of a consumer accelerometer's zero-g offset tolerance, Bosch BMI088 +-20 mg); a log
whose orientations do not tell it (a vehicle that rests level: the x and y offsets are seen
through its lean only, and the z offset together with the z scale) has none on that axis."""
ACCEL_SCALE_SD = 0.01
"""The prior standard deviation of an accelerometer axis's scale error (1 %; MEMS datasheets
give +-0.5 to +-3 %, InvenSense MPU-6000 +-3 %, Bosch BMI088 +-0.5 %) in :func:`accel_axes`."""


def _axes_solve(
    index: np.ndarray, n: int, u: np.ndarray, y: np.ndarray, w: np.ndarray, g: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The weighted least squares ``y ~ b_j . u + g (u * u) . s`` of :func:`accel_axes`
    (weights ``w``) with its priors (``b_j ~ N(0, ACCEL_OFFSET_XY^2)``, ``s ~ N(0,
    ACCEL_SCALE_SD^2)``), solved by eliminating the per-log offsets (the Schur complement of
    their 3x3 blocks): b (n, 3), s (3,), b's covariance (n, 3, 3), the residuals (m,) and each
    period's leverage (m,)."""
    q = g * u * u
    eye = np.eye(3)
    a = np.zeros((n, 3, 3)) + eye / ACCEL_OFFSET_XY**2
    c = np.zeros((n, 3, 3))
    r = np.zeros((n, 3))
    np.add.at(a, index, w[:, None, None] * u[:, :, None] * u[:, None, :])
    np.add.at(c, index, w[:, None, None] * u[:, :, None] * q[:, None, :])
    np.add.at(r, index, (w * y)[:, None] * u)
    ai = np.linalg.inv(a)
    aic = ai @ c
    schur = (q * w[:, None]).T @ q + eye / ACCEL_SCALE_SD**2 - np.einsum("nji,njk->ik", c, aic)
    si = np.linalg.inv(schur)
    rhs = (q * w[:, None]).T @ y - np.einsum("nji,nj->i", c, np.einsum("nij,nj->ni", ai, r))
    s = si @ rhs
    b = np.einsum("nij,nj->ni", ai, r - c @ s)
    cov_b = ai + aic @ si @ aic.transpose(0, 2, 1)
    cov_bs = -aic @ si  # cov(b_j, s)
    resid = y - np.einsum("mi,mi->m", u, b[index]) - q @ s
    lev = w * (
        np.einsum("mi,mij,mj->m", u, cov_b[index], u)
        + 2 * np.einsum("mi,mij,mj->m", u, cov_bs[index], q)
        + np.einsum("mi,ij,mj->m", q, si, q)
    )
    return b, s, cov_b, resid, lev


def accel_axes(
    index: np.ndarray,
    n: int,
    u: np.ndarray,
    y: np.ndarray,
    se: np.ndarray,
    extra: float = 0.0,
    g: float = 9.80665,
) -> tuple[np.ndarray, np.ndarray]:
    """The accelerometer's offset on each axis in each log, from its still periods' ``|a| - g``
    (``y``, m/s^2, error ``se``) and measured gravity directions ``u`` (unit, (m, 3)); periods
    of log ``index`` in ``0 .. n - 1``. Model (the multi-position calibration's, Ferraris et al.
    1995, restricted to offsets and a diagonal scale): each period's mean specific force ``a``
    satisfies ``|(I + S)^-1 (a - b_j)| = g``, the offset ``b_j`` free per log (it steps and
    walks between logs), the diagonal scale error ``S`` the device's; solved by Gauss-Newton
    (three steps from ``b = 0, S = 0``: the first is the linear ``|a| - g ~ b_j . u + g u^T S
    u``; the next take out its ``|b|^2 / 2g`` part, 10 mg for 0.45 m/s^2 offsets; the excess
    variance below is fitted at the last, with one more step), with weak
    priors (:data:`ACCEL_OFFSET_XY`, :data:`ACCEL_SCALE_SD`) on each step so that the
    orientations a log lacks leave its offsets' errors large instead of the fit singular (an
    axis seen on one face only tells its offset with its scale: both faces, in some log, part
    them). The periods scatter beyond their white-noise errors (the in-log bias instability):
    each period's variance is ``se^2 + extra`` (``extra``: the fleet's, from the in-log
    differences of ``|a| - g``), or more where the device's own residuals say so (the
    weighted sum of squares brought to its degrees of freedom: the periods less the trace of
    the fit's hat matrix). Returns (n, 3) offsets (m/s^2) and their standard errors, NaN on an
    axis whose error exceeds :data:`ACCEL_AXIS_SE_MAX` (its orientations do not tell it)."""
    ok = np.isfinite(y) & np.isfinite(se) & (se > 0) & np.isfinite(u).all(axis=1)
    out, err = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    if ok.sum() < 4:
        return out, err
    index, var = index[ok], se[ok] ** 2 + extra
    a = u[ok] * (y[ok] + g)[:, None]  # each period's mean specific force
    b, s = np.zeros((n, 3)), np.zeros(3)

    def step(more: float) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
        """The Gauss-Newton step at (b, s): (sum of squares, dof, db, ds, cov)."""
        fixed = (a - b[index]) / (1.0 + s)
        size = np.linalg.norm(fixed, axis=1)
        w = 1.0 / (var + more)
        db, ds, cov, resid, lev = _axes_solve(index, n, fixed / size[:, None], size - g, w, g)
        return float(np.sum(w * resid**2)), float(len(w) - lev.sum()), db, ds, cov

    for _ in range(3):
        _, _, db, ds, _ = step(0.0)
        b, s = b + db, s + ds
    ss, dof, db, ds, cov = step(0.0)
    if dof > 0.5 and ss > dof:  # bisect the excess variance: sum of squares = dof
        lo, hi = 0.0, float(np.var(a - b[index])) + float(np.max(var))
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            ss, dof, *_ = step(mid)
            lo, hi = (mid, hi) if ss > dof else (lo, mid)
        ss, dof, db, ds, cov = step(hi)
    b, s = b + db, s + ds
    e = np.sqrt(np.einsum("nii->ni", cov))
    keep = (e <= ACCEL_AXIS_SE_MAX) & (np.bincount(index, minlength=n) > 0)[:, None]
    out[keep], err[keep] = b[keep], e[keep]
    return out, err


UPRIGHT_DEG = 25.0
"""The periods the attitude term of ``|a| - g`` is fitted from (:func:`attitude_term`): those
within this of upright (``u_z >= cos 25 deg``), where ``b_z u_z`` is the log's intercept to 10 %
of ``b_z``; a vehicle set down on its side or upside down sees its offsets on every axis
(:func:`accel_axes`) instead."""
STILL_NOISE_RATIO = 5.0
"""A candidate still period whose gyro or accelerometer noise density exceeds this many times the
device's noise floor (:func:`still_judged`) is vibration, not stillness."""
FLOOR_QUANTILE = 0.25
"""The device's noise floor: this quantile over its logs of each log's quietest period."""
STILL_NOISE_CEILING = {"gyro": 1.75e-3, "accel": 0.039}
"""The most white noise (rad/s/sqrt(Hz), m/s^2/sqrt(Hz)) a still MEMS IMU shows: 0.1 deg/s/sqrt(Hz)
and 4 mg/sqrt(Hz), three to ten times the noisiest parts' datasheets (InvenSense MPU-6000
0.005 deg/s/sqrt(Hz) and 400 ug/sqrt(Hz); ST L3GD20 0.03 deg/s/sqrt(Hz); Analog Devices ADXL345
about 400 ug/sqrt(Hz); Bosch BMI088 0.014 deg/s/sqrt(Hz) and 175 ug/sqrt(Hz)). It judges a device
with one log, or only flights, where the device's own floor is its vibration (a quadcopter's
airframe: 0.01-0.02 rad/s/sqrt(Hz)); applied where the density is measured at ``tau_s`` (a rate
of at least ``1 / tau_s``: a slower topic's samples alias the sensor's whole band)."""


def still_judged(
    log_index: np.ndarray,
    noise: Mapping[str, np.ndarray],
    ratio: float = STILL_NOISE_RATIO,
    at_tau: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, float], dict[str, np.ndarray]]:
    """Which candidate periods of one device are still: a log's own noise floor cannot tell (in
    a log in motion throughout, its quietest stretch is the airframe's vibration), the device's
    floor over its logs can. Per sensor (``gyro``, ``accel``: (m,) mean noise density of the
    axes), the floor is the :data:`FLOOR_QUANTILE` quantile over the logs of each log's least
    noise (a still sensor's density is its own: a vibrating airframe's is tens to thousands of
    times more; a noise change of a few times, a loose mount, stays below ``ratio``); a period
    is still when both densities lie within ``ratio`` times their floors (a NaN density does not
    judge) and, where ``at_tau`` (m,) says the density is measured at ``tau_s``, below
    :data:`STILL_NOISE_CEILING`. Returns (still mask, floors, each period's ratio per sensor)."""
    keep = np.ones(len(log_index), bool)
    floors: dict[str, float] = {}
    ratios: dict[str, np.ndarray] = {}
    for sensor, v in noise.items():
        if at_tau is not None and sensor in STILL_NOISE_CEILING:
            keep &= ~(at_tau & (v > STILL_NOISE_CEILING[sensor]))
        ok = np.isfinite(v) & (v > 0)
        least = [float(np.min(v[ok & (log_index == i)])) for i in np.unique(log_index[ok])]
        if not least:
            floors[sensor], ratios[sensor] = float("nan"), np.full(len(v), np.nan)
            continue
        floors[sensor] = float(np.quantile(least, FLOOR_QUANTILE))
        ratios[sensor] = v / floors[sensor]
        keep &= ~(ratios[sensor] > ratio)
    return keep, floors, ratios


def device_history(
    device_id: str,
    log: Sequence[str],
    start_ns: np.ndarray,
    temperature: np.ndarray,
    values: Mapping[str, np.ndarray],
    se: Mapping[str, np.ndarray],
    noise: Mapping[str, np.ndarray],
    t0_ns: int,
    accel: np.ndarray | None = None,
    level: np.ndarray | None = None,
    at_tau: np.ndarray | None = None,
) -> DeviceHistory | None:
    """Per-log figures of one device from its candidate periods (``values``/``se``: figure ->
    (m,); ``noise``: ``gyro``/``accel`` -> (m,) mean noise density of the axes): the periods
    that are not still (:func:`still_judged`) left out (``h.rejected``; None when none is
    left), referred to the device's median temperature with slopes whose between-log part has no
    fleet scale yet (:func:`fleet_flags` refers them again with it). ``accel`` (m, 3): each
    period's mean specific force, m/s^2; with it ``|a| - g`` is referred to the level attitude
    (:func:`attitude_term`, its error added to each period's); ``level`` (m,): the periods
    ``|a| - g`` is taken from (default: all); ``at_tau`` (m,): the periods whose noise density
    is measured at ``tau_s`` (:func:`still_judged`)."""
    log = np.asarray(log).astype(str)
    all_logs, all_index = np.unique(log, return_inverse=True)
    keep, floors, ratios = still_judged(all_index, noise, at_tau=at_tau)
    rejected = [
        {
            "log": str(log[i]),
            "start_ns": int(start_ns[i]),
            **{f"{s}_ratio": float(r[i]) for s, r in ratios.items()},
        }
        for i in np.flatnonzero(~keep)
    ]
    if not keep.any():
        return None
    order = np.flatnonzero(keep)[np.argsort(start_ns[keep], kind="stable")]
    log, start_ns, temperature = log[order], start_ns[order], temperature[order]
    values = {f: np.asarray(v)[order] for f, v in values.items()}
    se = {f: np.asarray(v)[order] for f, v in se.items()}
    noise = {f: np.asarray(v)[order] for f, v in noise.items()}
    accel = None if accel is None else accel[order]
    level = None if level is None else level[order]
    names, index = np.unique(log, return_inverse=True)
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
    values, se = dict(values), dict(se)
    norm, norm_se = values["accel_norm_error"], se["accel_norm_error"]
    axes = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    axes_input = None
    if accel is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            u = accel / np.linalg.norm(accel, axis=1)[:, None]
        axes_input = (index, n, u, norm, norm_se)
        axes = accel_axes(*axes_input)
        # the side the device rests on (upside down, b_z reads as -b_z): near it, b_z u_z is
        # the log's intercept; beyond UPRIGHT_DEG it is not
        side = np.sign(np.nanmedian(u[:, 2])) or 1.0
        up = side * u[:, 2] >= np.cos(np.radians(UPRIGHT_DEG))
        found = attitude_term(index[up], u[up], temperature[up], norm[up], norm_se[up])
        if found is not None:
            b, cov = found
            norm = norm - u[:, :2] @ b
            norm_se = np.sqrt(norm_se**2 + np.einsum("mi,ij,mj->m", u[:, :2], cov, u[:, :2]))
        else:  # too few periods to fit it: the offsets' typical size times the lean
            lean = np.linalg.norm(u[:, :2], axis=1) * ACCEL_OFFSET_XY
            norm_se = np.sqrt(norm_se**2 + lean**2)
        if level is not None:
            level = level & up
    if level is not None:
        norm_se = np.where(level, norm_se, np.nan)
    values["accel_norm_error"], se["accel_norm_error"] = norm, norm_se
    day = np.array([(start_ns[index == i].mean() - t0_ns) / DAY_NS for i in range(n)])
    h = DeviceHistory(
        device_id,
        [str(x) for x in names],
        day,
        temps,
        {},
        {},
        {s: np.array([np.median(noise[s][index == i]) for i in range(n)]) for s in noise},
        {},
        t_ref,
        len(start_ns),
        period=Periods(index, start_ns, temperature, values, se),
        rejected=rejected,
        no_still=sorted(set(all_logs.astype(str)) - {str(x) for x in names}),
        floors=floors,
        axes=axes,
        axes_input=axes_input,
    )
    fit_periods(h)
    return h


def fit_periods(h: DeviceHistory) -> None:
    """The per-log figures of ``h`` from its periods, less the in-log steps found so far
    (``h.period.offset``): thermal fits, standard errors and referred figures."""
    p = h.period
    n = len(h.logs)
    h.fits = {
        name: thermal_fit(p.index, n, p.temperature, p.values[name] - p.offset[name], p.se[name])
        for name in FIGURES
    }
    h.se = {name: fit.se for name, fit in h.fits.items()}
    for name in FIGURES:
        refer(h, name)
    for i, name in enumerate(ACCEL_AXES):  # per log already; no thermal slope
        value, se = h.axes[0][:, i], h.axes[1][:, i]
        h.fits[name] = ThermalFit(value, se, h.temperature, float("nan"), float("nan"))
        h.se[name], h.figures[name] = se, value


def refer(h: DeviceHistory, name: str) -> None:
    """Refer the per-log figure ``name`` to ``h.t_ref`` with its fit's slope (``h.figures``,
    ``h.thermal``); a log without a temperature, or a figure without a slope, is left as it is."""
    fit = h.fits[name]
    slope = np.nan_to_num(fit.slope)
    h.thermal[name] = (fit.slope, fit.slope_se, fit.within, fit.within_se, fit.between)
    h.figures[name] = fit.value - slope * np.nan_to_num(fit.temperature - h.t_ref)


def add_flag(
    flags: list[dict[str, Any]],
    device_id: str,
    kind: str,
    figure: str,
    log: str | None,
    value: float,
    limit: float,
    why: str,
    **extra: Any,
) -> None:
    """Append one flag record (``fleet.json``'s ``flags``: the device, the rule's ``kind``, the
    figure, the log it names, the value against its ``threshold`` and the reason in words); every
    rule of the fleet view, the chamber comparison and the compass view records its flags so."""
    flags.append(
        {
            "device_id": device_id,
            "kind": kind,
            "figure": figure,
            "log": log,
            "value": float(value),
            "threshold": float(limit),
            "why": why,
            **extra,
        }
    )


def _step_scales(histories: Sequence[DeviceHistory]) -> dict[str, float]:
    """Per figure, ``s``: the robust scale of every consecutive difference of the referred per-log
    figures in the fleet."""
    out = {}
    for name in LOG_FIGURES:
        diffs = np.concatenate([np.diff(h.figures[name]) for h in histories] or [np.zeros(0)])
        out[name] = mad_sigma(diffs)
    return out


def _fleet_slope(slopes: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """What the fleet says of a device's thermal slope that its own logs cannot (no temperature
    change within or between its logs): the median of the devices' slopes and their robust
    scale as its error (the spread of the devices' true slopes and of their errors); NaN with
    fewer than :data:`MIN_PRIOR_DEVICES` slopes."""
    values = np.array([v for v, e in slopes if np.isfinite(v) and np.isfinite(e)])
    if len(values) < MIN_PRIOR_DEVICES:
        return float("nan"), float("nan")
    return float(np.median(values)), mad_sigma(values)


def _refer_all(histories: Sequence[DeviceHistory]) -> dict[str, float]:
    """Thermal slopes and step scales of the fleet (see the module docstring, 3 and 4)."""
    scales = _step_scales(histories)
    for _ in range(2):  # the between-log slopes' error needs the step scale, which needs them
        for name in FIGURES:
            prior = _fleet_slope([h.fits[name].slopes(scales[name]) for h in histories])
            for h in histories:
                fit = h.fits[name]
                if not np.isfinite(fit.slope):
                    fit.slope, fit.slope_se = prior
                refer(h, name)
        scales = _step_scales(histories)
    return scales


CHI2_1_MEDIAN = 0.454936423119572
"""The median of a chi-square variable with one degree of freedom."""
POWER_Z = 1.2815515655446004
"""z of 90 %: the drift test's stated power is the drift it flags with 90 % probability."""


def excess_scale(d: np.ndarray, var: np.ndarray) -> float:
    """The scale ``s`` of what differences ``d`` hold beyond their known variances ``var``: the
    ``s >= 0`` for which ``median(d^2 / (var + s^2))`` is the median of a chi-square with one
    degree of freedom (a robust, heteroscedastic 1.4826 MAD; 0 when ``var`` explains ``d``, NaN
    without any)."""
    ok = np.isfinite(d) & np.isfinite(var)
    d2, var = d[ok] ** 2, var[ok]
    if not len(d2):
        return float("nan")
    if np.median(d2 / np.maximum(var, 1e-300)) <= CHI2_1_MEDIAN:
        return 0.0
    lo, hi = 0.0, float(np.median(d2)) / CHI2_1_MEDIAN + 1e-300
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if np.median(d2 / (var + mid)) > CHI2_1_MEDIAN:
            lo = mid
        else:
            hi = mid
    return float(np.sqrt(hi))


def _inlog_pairs(
    h: DeviceHistory, name: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Consecutive still periods of one log: (first, second, the change of the figure referred to
    one temperature, its variance from the periods' errors and the slope's)."""
    p = h.period
    assert p is not None
    v, se = p.values[name] - p.offset[name], p.se[name]
    fit = h.fits[name]
    slope, slope_se = np.nan_to_num(fit.slope), np.nan_to_num(fit.slope_se)
    idx = np.flatnonzero(np.isfinite(v) & np.isfinite(se) & (se > 0))
    i, j = idx[:-1], idx[1:]
    same = p.index[i] == p.index[j]
    i, j = i[same], j[same]
    dtemp = np.nan_to_num(p.temperature[j] - p.temperature[i])
    d = v[j] - v[i] - slope * dtemp
    return i, j, d, se[i] ** 2 + se[j] ** 2 + (slope_se * dtemp) ** 2


def inlog_steps(histories: Sequence[DeviceHistory], k: float) -> dict[str, float]:
    """Change points inside a log (module docstring, 4a): consecutive still periods of one log
    whose figures differ by more than ``k sqrt(se_1^2 + se_2^2 + (se_slope dT)^2 + s_in^2)``,
    ``s_in`` the fleet's excess scale (:func:`excess_scale`) of such differences (the in-log bias
    instability). Each is flagged as a ``step`` at its log with the time (``t_ns``: the start of
    the first still period after it; ``after_ns``: of the last one before) and taken out of the
    device's later periods (``period.offset``), so that a step is reported once: not again as a
    step between logs, nor as a drift. Returns ``s_in`` per figure."""
    import datetime

    scales = {}
    for name in FIGURES:
        pairs = [_inlog_pairs(h, name) for h in histories]
        d = np.concatenate([x[2] for x in pairs] or [np.zeros(0)])
        var = np.concatenate([x[3] for x in pairs] or [np.zeros(0)])
        s_in = np.nan_to_num(excess_scale(d, var))
        scales[name] = float(s_in)
        for h, (i, j, d_h, var_h) in zip(histories, pairs, strict=True):
            p = h.period
            assert p is not None
            limit = k * np.sqrt(var_h + s_in**2)
            for a, b, step, lim in zip(i, j, d_h, limit, strict=True):
                if not abs(step) > lim:
                    continue
                p.offset[name][b:] += step
                when = [
                    datetime.datetime.fromtimestamp(int(x) / 1e9, datetime.UTC).strftime(
                        "%Y-%m-%d %H:%M:%S"
                    )
                    for x in (p.start_ns[a], p.start_ns[b])
                ]
                add_flag(
                    h.flags,
                    h.device_id,
                    "step",
                    name,
                    h.logs[int(p.index[b])],
                    step,
                    lim,
                    f"{name} stepped by {step:+.3g} {UNITS[name]} inside {h.logs[int(p.index[b])]} "
                    f"between the still periods starting {when[0]} and {when[1]} UTC "
                    f"(limit {lim:.2g})",
                    t_ns=int(p.start_ns[b]),
                    after_ns=int(p.start_ns[a]),
                )
    return scales


def _walk_scales(histories: Sequence[DeviceHistory], names: Sequence[str]) -> tuple[float, float]:
    """(sigma_w, q): the fleet's log-to-log scatter of figures ``names`` (the gyro's three axes: one
    die) beyond the logs' own errors, as a
    white part ``sigma_w`` (turn-on repeatability, unit) and a random walk ``q`` (unit per
    sqrt(day)): the restricted maximum likelihood (REML; Patterson & Thompson 1971) of the
    covariance of :func:`drift_gls` over every device at once, each with its own level and drift
    (so a drifting device does not read as scatter), on a grid (0 and half-decade steps over four
    decades about the fleet's consecutive-log change, then fifth-decade steps about the best)."""
    series = []
    for h, name in ((h, name) for name in names for h in histories):
        f, se = h.steady[name], h.se[name]
        ok = np.isfinite(f) & np.isfinite(se)
        if ok.sum() >= 3:
            t = h.day[ok] - h.day[ok][0]
            dtemp = np.nan_to_num((h.fits[name].temperature - h.t_ref)[ok])
            slope_se = float(np.nan_to_num(h.fits[name].slope_se))
            base = np.diag(se[ok] ** 2) + slope_se**2 * np.outer(dtemp, dtemp)
            series.append((t, f[ok], base))
    if not series:
        return float("nan"), float("nan")
    diffs = np.concatenate([np.diff(y) for _, y, _ in series])
    span = float(np.mean(np.concatenate([np.diff(t) for t, _, _ in series])))
    ref = float(np.nan_to_num(mad_sigma(diffs))) or 1e-12

    # the devices with as many logs stacked: one batched call per length, not per device
    by_length: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for item in series:
        by_length.setdefault(len(item[0]), []).append(item)
    stacks = [
        (
            np.stack([t for t, _, _ in group]),
            np.stack([y for _, y, _ in group]),
            np.stack([b for _, _, b in group]),
        )
        for group in by_length.values()
    ]

    def loglik(w: float, q: float) -> float:
        total = 0.0
        for t, y, base in stacks:  # (k, n), (k, n), (k, n, n)
            n = t.shape[1]
            cov = base + w**2 * np.eye(n) + q**2 * np.minimum(t[:, :, None], t[:, None, :])
            sign, logdet = np.linalg.slogdet(cov)
            if np.any(sign <= 0):
                return -np.inf
            ci = np.linalg.inv(cov)
            x = np.stack([np.ones_like(t), t], axis=2)  # (k, n, 2)
            xt_ci = np.swapaxes(x, 1, 2) @ ci
            info = xt_ci @ x
            sign2, logdet2 = np.linalg.slogdet(info)
            keep = sign2 > 0  # a device whose design is singular adds nothing
            if not keep.any():
                continue
            beta = np.linalg.solve(info[keep], (xt_ci[keep] @ y[keep][:, :, None]))
            r = y[keep] - (x[keep] @ beta)[:, :, 0]
            quad = np.einsum("ki,kij,kj->k", r, ci[keep], r)
            total -= 0.5 * float(np.sum(logdet[keep] + logdet2[keep] + quad))
        return total

    q_ref = ref / np.sqrt(max(span, 1e-6))
    coarse = np.r_[
        0.0, np.logspace(-3, 1, 9)
    ]  # half-decade steps, then a finer grid about the best
    _, w0, q0 = max((loglik(ref * a, q_ref * b), a, b) for a in coarse for b in coarse)
    fine = np.logspace(-0.5, 0.5, 5)
    grid_w = [0.0] if w0 == 0 else w0 * fine
    grid_q = [0.0] if q0 == 0 else q0 * fine
    _, w, q = max((loglik(ref * a, q_ref * b), a, b) for a in grid_w for b in grid_q)
    arg = (float(ref * w), float(q_ref * q))
    return arg


def drift_gls(
    day: np.ndarray,
    f: np.ndarray,
    se: np.ndarray,
    sigma_w: float,
    q: float,
    dtemp: np.ndarray | None = None,
    slope_se: float = 0.0,
    column: np.ndarray | None = None,
) -> tuple[float, float, float]:
    """The drift (unit/day) of one device's per-log figure and its standard error: generalised
    least squares of ``f = a + b day`` with the covariance ``diag(se^2 + sigma_w^2) + q^2
    min(day_i, day_j) + slope_se^2 dT_i dT_j`` (days from the first log: a random walk from it;
    ``dT``: each log's temperature less the reference the figures are referred to, whose slope's
    error is common to all logs); the error scaled by ``sqrt(chi2 / dof)`` when the logs scatter
    more than the model says. Returns (drift, its error, chi2 / dof); NaN with fewer than three
    logs. ``column`` (one value per log): fit ``f = a + b column`` instead (a step: 0 before the
    log it steps at, 1 from it), its ``b`` returned."""
    ok = np.isfinite(f) & np.isfinite(se)
    if ok.sum() < 3:
        return float("nan"), float("nan"), float("nan")
    t, y = day[ok] - day[ok][0], f[ok]
    cov = np.diag(se[ok] ** 2 + sigma_w**2) + q**2 * np.minimum.outer(t, t)
    if dtemp is not None and np.isfinite(slope_se):
        d = np.nan_to_num(dtemp[ok])
        cov += slope_se**2 * np.outer(d, d)
    x = np.column_stack([np.ones(len(t)), t if column is None else column[ok]])
    ci = np.linalg.pinv(cov)
    info = x.T @ ci @ x
    if np.linalg.cond(info) > 1e14:
        return float("nan"), float("nan"), float("nan")
    inv = np.linalg.inv(info)
    beta = inv @ x.T @ ci @ y
    r = y - x @ beta
    birge = float(r @ ci @ r) / max(len(y) - 2, 1)
    return float(beta[1]), float(np.sqrt(inv[1, 1] * max(birge, 1.0))), birge


def _long_gap(h: DeviceHistory, step: dict[str, Any]) -> str:
    """For a step flagged between two logs more than twice the device's median log spacing
    apart, the words that say a drift explains it (the jump and the gap); else ``""``."""
    i, j = h.logs.index(step["after_log"]), h.logs.index(step["log"])
    spacing = np.diff(h.day)
    days = float(h.day[j] - h.day[i])
    if not len(spacing) or not days > 2.0 * float(np.median(spacing)):
        return ""
    return (
        f"; the jump of {step['value']:+.3g} across the {days:.0f} days between {step['after_log']}"
        f" and {step['log']} is this drift, not a step (a line through every log fits it as well)"
    )


def drift_onset(day: np.ndarray, f: np.ndarray, w: np.ndarray, k: float) -> int:
    """The log a drift starts at: the hinge ``f = a + b max(day - day_j, 0)`` that fits best
    (weights ``w``), when it fits better than a line from the first log by more than ``k^2`` in
    weighted squared residuals; else the first log (0)."""
    ok = np.flatnonzero(np.isfinite(f) & np.isfinite(w))
    if len(ok) < 4:
        return int(ok[0]) if len(ok) else 0

    def sse(x: np.ndarray) -> float:
        a = np.column_stack([np.ones(len(ok)), x]) * np.sqrt(w[ok])[:, None]
        beta, *_ = np.linalg.lstsq(a, f[ok] * np.sqrt(w[ok]), rcond=None)
        r = f[ok] * np.sqrt(w[ok]) - a @ beta
        return float(r @ r)

    line = sse(day[ok] - day[ok][0])
    hinges = [(sse(np.maximum(day[ok] - day[j], 0.0)), j) for j in ok[1:-1]]
    best, j = min(hinges)
    return int(j) if line - best > k**2 else int(ok[0])


def fleet_flags(histories: Sequence[DeviceHistory], k: float) -> dict[str, Any]:
    """Apply the rules of the module docstring to every device (fills ``flags``, ``drift`` and
    ``moved``); returns the fleet's scales."""
    _refer_all(histories)
    inlog = inlog_steps(histories, k)
    extra = float(np.nan_to_num(inlog["accel_norm_error"])) ** 2 / 2  # per period, of a difference
    for h in histories:
        p = h.period
        if h.axes_input is not None and extra > 0:
            h.axes = accel_axes(*h.axes_input, extra=extra)
        if (p is not None and any(p.offset[name].any() for name in FIGURES)) or extra > 0:
            fit_periods(h)
    scales = _refer_all(histories)
    scales.update({f"{name}_in_log": v for name, v in inlog.items()})
    noise_dev: dict[str, list[float]] = {"gyro": [], "accel": []}
    for h in histories:
        for s in noise_dev:
            ln = np.log(np.maximum(h.noise[s], 1e-300))
            for j in range(2, len(ln)):
                noise_dev[s].append(ln[j] - np.median(ln[:j]))
    for s, devs in noise_dev.items():
        scales[f"{s}_noise"] = max(mad_sigma(np.array(devs)), NOISE_FLOOR) if devs else NOISE_FLOOR
    pending: dict[tuple[str, str], list[dict[str, Any]]] = {}  # steps between logs
    for h in histories:
        for name in LOG_FIGURES:
            unit = UNITS[name]
            f, se = h.figures[name], h.se[name]
            base = np.nan_to_num(scales[name])
            temps = h.fits[name].temperature
            steady = f.copy()
            have = np.flatnonzero(np.isfinite(f))  # a log without the figure is passed over
            for i, j in zip(have[:-1], have[1:], strict=True):
                d = f[j] - f[i]
                dtemp = np.nan_to_num(temps[j] - temps[i])
                # the slope's error over the change of temperature; the walk over j - i intervals
                referred = (np.nan_to_num(h.fits[name].slope_se) * dtemp) ** 2
                limit = k * np.sqrt(base**2 * (j - i) + se[j] ** 2 + se[i] ** 2 + referred)
                if abs(d) > limit:
                    steady[j:] -= d
                    add_flag(
                        pending.setdefault((h.device_id, name), []),
                        h.device_id,
                        "step",
                        name,
                        h.logs[j],
                        d,
                        limit,
                        f"{name} stepped by {d:+.3g} {unit} between {h.logs[i]} and {h.logs[j]} (limit "
                        f"{limit:.2g}; temperature {temps[i]:.1f} -> {temps[j]:.1f} degC)",
                        after_log=h.logs[i],
                    )
            h.steady[name] = steady
            ends = f[have[[0, -1]]] if len(have) > 1 else np.zeros(2)  # first and last with it
            h.moved[name] = float((ends[1] - ends[0]) / base) if base > 0 else 0.0
    # the gyro's three axes share one die: one turn-on and walk, fitted to the three at once
    walk = {
        name: np.nan_to_num(_walk_scales(histories, group)) for group in GROUPS for name in group
    }
    fitted: dict[str, tuple[Any, list[tuple[float, float, float]], float]] = {}
    for name in LOG_FIGURES:
        sw, q = (float(v) for v in walk[name])
        scales[f"{name}_turn_on"], scales[f"{name}_walk_per_sqrt_day"] = sw, q

        def gls(
            h: DeviceHistory,
            f: np.ndarray,
            name: str = name,
            sw: float = sw,
            q: float = q,
            column: np.ndarray | None = None,
        ) -> tuple[float, float, float]:
            fit = h.fits[name]
            slope_se = float(np.nan_to_num(fit.slope_se))
            dtemp = fit.temperature - h.t_ref
            return drift_gls(h.day, f, h.se[name], sw, q, dtemp, slope_se, column)

        fits = [gls(h, h.steady[name]) for h in histories]
        slopes = np.array([b for b, _, _ in fits])
        finite = slopes[np.isfinite(slopes)]
        fitted[name] = (gls, fits, float(np.median(finite)) if len(finite) else float("nan"))
    # the devices' true drifts scatter beyond their errors (a random walk that looks like a drift
    # over few logs): the fleet's excess scale of the slopes, a random effect (the gyro's axes
    # pooled: one die)
    spread = {}
    for group in GROUPS:
        d = np.concatenate([[b - fitted[n][2] for b, _, _ in fitted[n][1]] for n in group])
        var = np.concatenate([[e**2 for _, e, _ in fitted[n][1]] for n in group])
        pooled = float(np.nan_to_num(excess_scale(np.asarray(d), np.asarray(var))))
        for n in group:  # the larger of the pooled and the figure's own
            own = excess_scale(
                np.array([b - fitted[n][2] for b, _, _ in fitted[n][1]]),
                np.array([e**2 for _, e, _ in fitted[n][1]]),
            )
            spread[n] = max(pooled, float(np.nan_to_num(own)))
    for name in LOG_FIGURES:
        gls, fits, med = fitted[name]
        sw = scales[f"{name}_turn_on"]
        finite = np.array([b for b, _, _ in fits if np.isfinite(b)])
        tau = spread[name]
        scales[f"{name}_drift_spread_per_day"] = tau
        # the median's own error: pi/2 times a mean's variance (large-sample)
        widen = np.sqrt(1.0 + np.pi / 2.0 / max(len(finite), 1))
        unit = UNITS[name]
        for h, (b, e, _) in zip(histories, fits, strict=True):
            e = float(np.hypot(e, tau)) * widen
            h.power[name] = float((k + POWER_Z) * e)
            steps = pending.get((h.device_id, name), [])
            gap = ""
            if steps:  # a drift over a long gap between logs reads as a step: which is it?
                b_f, e_f, chi2 = gls(h, h.figures[name])
                e_f = float(np.hypot(e_f, tau)) * widen
                dof = max(int(np.isfinite(h.figures[name]).sum()) - 2, 1)
                line = chi2 <= 1.0 + k * np.sqrt(2.0 / dof)  # a line through every log fits
                if line and len(steps) == 1:  # and at least as well as the one step?
                    col = (np.arange(len(h.logs)) >= h.logs.index(steps[0]["log"])).astype(float)
                    line = chi2 <= gls(h, h.figures[name], column=col)[2]
                if line and abs(b_f - med) > k * e_f:
                    steps, h.steady[name], b, e = [], h.figures[name], b_f, e_f
                elif line and len(steps) == 1 and (gap := _long_gap(h, steps[0])):
                    # the one jump spans a long gap: a drift explains it as well as a step
                    steps, h.steady[name], b, e = [], h.figures[name], b_f, e_f
                h.flags.extend(steps)
            h.drift[name] = b
            significant = np.isfinite(b) and np.isfinite(med) and abs(b - med) > k * e
            if not (significant or gap):
                continue
            j = drift_onset(h.day, h.steady[name], 1.0 / (h.se[name] ** 2 + sw**2), k)
            add_flag(
                h.flags,
                h.device_id,
                "drift",
                name,
                h.logs[j],
                b,
                med + np.sign(b - med) * k * e,
                f"{name} drifts {7 * b:+.3g} {unit}/week from {h.logs[j]} on (fleet median "
                f"{7 * med:+.3g}, limit +-{7 * k * e:.2g}; the smallest drift this test finds "
                f"with 90 % probability: {7 * h.power[name]:.2g} {unit}/week){gap}",
            )
    for h in histories:  # an offset step seen on its axis is not flagged again as |a| - g's
        on_axis = {f["log"] for f in h.flags if f["kind"] == "step" and f["figure"] in ACCEL_AXES}
        h.flags = [
            f
            for f in h.flags
            if not (
                f["figure"] == "accel_norm_error" and f["kind"] == "step" and f["log"] in on_axis
            )
        ]
    for h in histories:
        for s in ("gyro", "accel"):
            ln = np.log(np.maximum(h.noise[s], 1e-300))
            for j in range(2, len(ln)):
                d = ln[j] - np.median(ln[:j])
                limit = k * scales[f"{s}_noise"]
                if abs(d) > limit:
                    word = "rose" if d > 0 else "fell"
                    add_flag(
                        h.flags,
                        h.device_id,
                        "noise",
                        f"{s}_noise",
                        h.logs[j],
                        float(np.exp(d)),
                        float(np.exp(limit)),
                        f"{s} noise density {word} x{np.exp(d):.2f} against its earlier logs in {h.logs[j]} (limit x{np.exp(limit):.2f})",
                    )
    return {"k": k, "scales": scales}
