"""In-field thermal curves against the chamber calibration: the math of ``imupipe survey
--chamber``.

**The chamber curve** of a sensor (gyro, accelerometer) is what the device's calibration steps say
the raw output is when the true rate is zero (gyro) or the true specific force is ``g`` along a
direction (accelerometer), at a steady temperature: the thermal steps (``temperature``: the
``poly``, ``lag``, ``six_term``, ``piecewise`` and ``stepwise`` models of
:mod:`imupipe.stages.thermal.models`; ``thermal_matrix``: the soak method) with their rates at zero
(``dT = dTa = dTs = 0``), the sensing element at the measured temperature (``Ts = T``) and the
ambient at it too (``Ta = T``), and the linear steps of the same sensor. Each step is an affine map
``x_out = A(T) (x_in - o(T))`` (a temperature step: ``A = diag(1/sf(T))``, ``o = f(T)``; a
linear step: ``A = matrix``, ``o = offset``; a thermal-matrix step: its scale and misalignment at
``T`` and its bias), so the raw output for a corrected value ``c`` is
``o_1 + A_1^-1 (o_2 + A_2^-1 (... (o_n + A_n^-1 c)))``, solved per still period. Outside the
chamber's calibrated range the model's terms are *extrapolated* (evaluated beyond it, a
``piecewise`` model's hats holding their end values; the correction itself holds the temperature
at the range's end), and those periods are named.

**The comparison** (:func:`compare`), per figure (``gyro_bias_x|y|z``: the raw bias against the
chamber's zero-rate output; ``accel_norm_error``: the raw ``|a| - g`` against the chamber's
``|raw| - g`` for the period's direction), on the residuals ``r = measured - chamber`` of the
device's still periods:

- **slope difference** ``ds`` (unit/K: the in-field curve's slope minus the chamber's): the
  inverse-variance combination of the *within-log* slope (per-log intercepts, so the bias random
  walk between logs does not enter; :func:`imupipe.stages.survey.fleet.within_log_slope`) and
  the *between-log* slope: the least-squares slope through the origin of the change of the
  per-log mean residual between consecutive logs on the change of their mean temperature (the
  changes of a random walk are independent, its level is not), its error from the scatter
  about it, at least what the fleet's ordinary log-to-log change ``s`` and the logs' own errors
  give (:func:`imupipe.stages.survey.fleet.thermal_fit`, the fleet view's own slope: a log's
  temperature is the mean of its periods' with the weights of its mean residual);
- **offset** (unit: the in-field curve minus the chamber's at ``t_centre``, the mean of the
  per-log temperatures): the mean over logs of ``r_log - ds (T_log - t_centre)``, its standard
  error the scatter of those values over ``sqrt(logs)`` (at least the per-log errors': the
  ordinary log-to-log change is in it);
- **the departure over the range flown**: ``d(T) = offset + ds (T - t_centre)`` at the lowest
  and highest period temperature; the larger is named (``worst_t``, ``worst``).

**The rule** (:func:`chamber_flags`, with the survey's ``k``): the offset is flagged when
``|offset| > k c sqrt(se^2 + reach^2)``: ``reach = s sqrt(m)`` is how far the ordinary log-to-log
change (``s``: the fleet's robust scale of consecutive per-log differences, the step rule's) goes
in the ``m`` log intervals between the chamber and the device's logs (the bias random walk since
the chamber: expected, not a fault); the slope difference when ``|ds| > k c se_ds``. ``c`` is the
robust scale (1.4826 MAD) of the fleet's standardised departures, floored at 1, when six devices
or more have a chamber calibration (stated errors that are too small widen the limit for all),
else 1. The offset is judged only when the fleet has ``MIN_PAIRS`` consecutive log pairs or more
(else ``s``, and with it what the random walk since the chamber reaches, is unknown: the limit
is null); the slope difference always.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from imupipe.stages.steps import LinearStep, Step
from imupipe.stages.survey.fleet import DAY_NS, add_flag, thermal_fit
from imupipe.stages.survey.stats import G0, mad_sigma
from imupipe.stages.thermal import models as tm
from imupipe.stages.thermal.step import (
    MATRIX_FORMS,
    WARN_MARGIN,
    TemperatureStep,
    ThermalMatrixStep,
    apply_matrix_form,
)

THERMAL = (TemperatureStep, ThermalMatrixStep)
"""The steps that make a chamber curve (a sensor without one has no chamber comparison)."""
MIN_ROBUST_DEVICES = 6
"""Devices with a chamber calibration needed before their standardised departures' robust scale
widens the limits (fewer: ``c = 1``)."""
WALL_CLOCK_NS = 946_684_800 * 10**9
"""2000-01-01 in Unix ns: a chamber date before it is a log's own clock, not a date."""
MIN_PAIRS = 3
"""Consecutive log pairs the fleet needs before the offset is judged (``s`` estimable)."""
CHAMBER_FIGURES = ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "accel_norm_error")


@dataclass
class ChamberModel:
    """One device's chamber calibration: per sensor (``gyro``, ``accel``) its steps in chain
    order (thermal and linear; at least one thermal), the calibrated temperature range (degC,
    the intersection of its thermal steps' ranges) and when the chamber ran (int64 ns, the
    thermal step's ``fitted_on.t_end_ns``; None when the file does not say)."""

    source: str
    steps: dict[str, list[Step]]
    ranges: dict[str, tuple[float, float]]
    t_ns: int | None = None


def chamber_model(
    source: str, steps: Sequence[Step], entries: Sequence[Mapping[str, Any]]
) -> ChamberModel | None:
    """The chamber model of the steps of one device (its chain entries give ``fitted_on``);
    None without a thermal step on the gyro or the accelerometer."""
    by: dict[str, list[Step]] = {}
    ranges: dict[str, tuple[float, float]] = {}
    when: int | None = None
    for step, entry in zip(steps, entries, strict=True):
        if step.sensor not in ("gyro", "accel") or not isinstance(step, (*THERMAL, LinearStep)):
            continue
        by.setdefault(step.sensor, []).append(step)
        if isinstance(step, THERMAL):
            lo, hi = step.ranges["T"] if isinstance(step, TemperatureStep) else step.range
            old = ranges.get(step.sensor, (-np.inf, np.inf))
            ranges[step.sensor] = (max(old[0], lo), min(old[1], hi))
            end = (entry.get("fitted_on") or {}).get("t_end_ns")
            if isinstance(end, int | float) and np.isfinite(end):
                when = int(end) if when is None else max(when, int(end))
    by = {s: v for s, v in by.items() if s in ranges}
    return ChamberModel(source, by, ranges, when) if by else None


def _affine(step: Step, temp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A (n, 3, 3), o (n, 3)) of ``x_out = A (x_in - o)`` at steady temperatures ``temp``."""
    n = len(temp)
    if isinstance(step, LinearStep):
        return np.broadcast_to(step.matrix, (n, 3, 3)), np.broadcast_to(step.offset, (n, 3))
    if isinstance(step, TemperatureStep):
        x = temp - step.tref
        zero = np.zeros(n)
        variables = {"T": x, "dT": zero, "Ta": x, "dTa": zero, "Ts": x, "dTs": zero}
        o = step.bias(variables)
        sf = np.ones((n, 3))
        for axis, model in (step.scale or {}).items():
            sf[:, "xyz".index(axis)] = step.scale_factor(model, variables)
        return np.einsum("ij,ni->nij", np.eye(3), 1.0 / sf), o
    assert isinstance(step, ThermalMatrixStep)
    x = {"T": temp - step.tref}
    p: dict[str, np.ndarray] = {}
    for name, default in (("scale", 1.0), ("misalignment", 0.0), ("bias", 0.0)):
        comps = step.parameters.get(name)
        k = MATRIX_FORMS[step.form][0] if name == "misalignment" else 3
        p[name] = (
            np.full((n, k), default)
            if comps is None
            else np.column_stack([tm.evaluate(c["terms"], c["coefficients"], x) for c in comps])
        )
    cols = [
        apply_matrix_form(
            step.form, np.tile(e, (n, 1)), p["scale"], p["misalignment"], np.zeros((n, 3))
        )
        for e in np.eye(3)
    ]
    return np.stack(cols, axis=2), p["bias"]


def raw_output(steps: Sequence[Step], temp: np.ndarray, corrected: np.ndarray) -> np.ndarray:
    """(n, 3) raw output the steps map to ``corrected`` (n, 3) at steady temperatures ``temp``
    (degC; see the module docstring)."""
    x = np.asarray(corrected, dtype=np.float64)
    for step in reversed(steps):
        a, o = _affine(step, temp)
        x = o + np.linalg.solve(a, x[..., None])[..., 0]
    return x


def forward(steps: Sequence[Step], temp: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """(n, 3) the steps applied to ``raw`` at steady temperatures ``temp``."""
    x = np.asarray(raw, dtype=np.float64)
    for step in steps:
        a, o = _affine(step, temp)
        x = np.einsum("nij,nj->ni", a, x - o)
    return x


def predicted(
    model: ChamberModel, temp: np.ndarray, accel_mean: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """The chamber's figures at still periods of temperatures ``temp`` (degC): ``gyro_bias_x|y|z``
    (rad/s, the zero-rate raw output) and, given the periods' raw mean specific force
    ``accel_mean`` (n, 3), ``accel_norm_error`` (m/s^2: ``|raw| - g`` for ``g`` along the
    period's corrected direction). Sensors without a chamber curve are left out."""
    temp = np.asarray(temp, dtype=np.float64)
    n = len(temp)
    out: dict[str, np.ndarray] = {}
    ok = np.isfinite(temp)
    t = np.where(ok, temp, 0.0)
    if "gyro" in model.steps:
        zero = raw_output(model.steps["gyro"], t, np.zeros((n, 3)))
        for i, a in enumerate("xyz"):
            out[f"gyro_bias_{a}"] = np.where(ok, zero[:, i], np.nan)
    if "accel" in model.steps and accel_mean is not None:
        steps = model.steps["accel"]
        c = forward(steps, t, np.nan_to_num(accel_mean))
        norm = np.linalg.norm(c, axis=1, keepdims=True)
        up = c / np.where(norm > 0, norm, 1.0)
        raw = raw_output(steps, t, G0 * up)
        good = ok & np.isfinite(accel_mean).all(axis=1) & (norm[:, 0] > 0)
        out["accel_norm_error"] = np.where(good, np.linalg.norm(raw, axis=1) - G0, np.nan)
    return out


def compare(
    log_index: np.ndarray,
    temp: np.ndarray,
    measured: np.ndarray,
    se: np.ndarray,
    chamber: np.ndarray,
    step_scale: float = 0.0,
) -> dict[str, float]:
    """The in-field curve of one figure against the chamber's (module docstring): ``offset``,
    ``offset_se``, ``t_centre``, ``slope`` (the difference), ``slope_se``, ``slope_within``,
    ``slope_between`` (NaN when not estimable), ``t_lo``, ``t_hi`` (the periods' range),
    ``worst_t``, ``worst`` (the departure there), ``worst_se``, ``periods``, ``logs``."""
    ok = np.isfinite(temp) & np.isfinite(measured) & np.isfinite(se) & (se > 0)
    ok &= np.isfinite(chamber)
    nan = float("nan")
    out = dict.fromkeys(
        ("offset", "offset_se", "t_centre", "slope", "slope_se", "slope_within",
         "slope_between", "t_lo", "t_hi", "worst_t", "worst", "worst_se"), nan,
    )  # fmt: skip
    out["periods"], out["logs"] = int(ok.sum()), 0
    if not ok.any():
        return out
    _, g = np.unique(log_index[ok], return_inverse=True)
    t, r, s = temp[ok], measured[ok] - chamber[ok], se[ok]
    n_logs = int(g.max()) + 1
    fit = thermal_fit(g, n_logs, t, r, s, step_scale)
    rl, sl, tl = fit.value, fit.se, fit.temperature
    within, between = fit.within, fit.between
    slope, slope_se = (fit.slope, fit.slope_se) if np.isfinite(fit.slope) else (0.0, nan)
    centre = float(tl.mean())
    level = rl - slope * (tl - centre)
    floor = float(np.sqrt(np.mean(sl**2) / n_logs))
    spread = float(np.std(level, ddof=1) / np.sqrt(n_logs)) if n_logs > 1 else 0.0
    offset, offset_se = float(level.mean()), max(spread, floor)
    lo, hi = float(t.min()), float(t.max())
    ends = np.array([lo, hi])
    dep = offset + slope * (ends - centre)
    dep_se = np.sqrt(offset_se**2 + (np.nan_to_num(slope_se) * (ends - centre)) ** 2)
    i = int(np.argmax(np.abs(dep)))
    out.update(
        offset=offset, offset_se=offset_se, t_centre=centre, slope=slope, slope_se=slope_se,
        slope_within=within, slope_between=between, t_lo=lo, t_hi=hi, worst_t=float(ends[i]),
        worst=float(dep[i]), worst_se=float(dep_se[i]), logs=n_logs,
    )  # fmt: skip
    return out


def outside(temp: np.ndarray, calibrated: tuple[float, float]) -> dict[str, Any]:
    """The still periods whose temperature lies more than ``WARN_MARGIN`` outside the chamber's
    calibrated range (where its curve is extrapolated): count and their temperature span."""
    t = np.asarray(temp, dtype=np.float64)
    t = t[np.isfinite(t)]
    far = t[(t < calibrated[0] - WARN_MARGIN) | (t > calibrated[1] + WARN_MARGIN)]
    return {
        "range": [float(calibrated[0]), float(calibrated[1])],
        "outside": int(len(far)),
        "outside_span": [float(far.min()), float(far.max())] if len(far) else None,
    }


def steps_since(chamber_ns: int | None, day: np.ndarray, t0_ns: int) -> float:
    """``m``: the log intervals between the chamber and the device's logs (their mean day),
    in units of the device's median interval between logs; when the chamber's date is unknown
    (or before :data:`WALL_CLOCK_NS`: a log timed from its own start), as if it ran one interval
    before the first log. At least 1."""
    day = np.asarray(day, dtype=np.float64)
    if chamber_ns is not None and chamber_ns < WALL_CLOCK_NS:  # the chamber log's own clock
        chamber_ns = None
    if len(day) < 2:
        return 1.0
    gap = float(np.median(np.diff(day)))
    if not gap > 0:
        return 1.0
    start = day[0] - gap if chamber_ns is None else (chamber_ns - t0_ns) / DAY_NS
    return max(1.0, float((day.mean() - start) / gap))


def _text(figure: str, value: float) -> str:
    """A figure's value in its display unit (gyro in mrad/s)."""
    if figure.startswith("gyro"):
        return f"{value * 1e3:.2g} mrad/s"
    return f"{value:.2g} m/s^2"


def _name(figure: str) -> str:
    return f"gyro {figure[-1]} bias" if figure.startswith("gyro") else "|a| - g"


def chamber_flags(
    devices: Sequence[dict[str, Any]], scales: Mapping[str, float], k: float
) -> dict[str, Any]:
    """Apply the rule of the module docstring to every device with a ``chamber`` dict
    (``figures``: figure -> :func:`compare` result; ``m``; ``ranges``: sensor -> calibrated
    range): each figure gets ``reach``, ``limit_offset`` and ``limit_slope``, and the flags
    (``chamber_offset``, ``chamber_slope``) go to ``device["flags"]``. Returns, per figure,
    ``{"offset": c, "slope": c}``: the widening ``c`` of each limit."""
    with_chamber = [d for d in devices if d.get("chamber")]
    pairs = sum(max(len(d["logs"]) - 1, 0) for d in devices)

    def reach(figure: str, m: float) -> float:
        s = scales.get(figure, float("nan"))
        return float(s * np.sqrt(m)) if pairs >= MIN_PAIRS and np.isfinite(s) else float("nan")

    widen: dict[str, dict[str, float]] = {}
    for figure in CHAMBER_FIGURES:
        z_off, z_slope = [], []
        for d in with_chamber:
            c = d["chamber"]["figures"].get(figure)
            if c is None or not np.isfinite(c["offset"]):
                continue
            r = reach(figure, d["chamber"]["m"])
            if np.isfinite(r):
                z_off.append(c["offset"] / np.hypot(c["offset_se"], r))
            if np.isfinite(c["slope_se"]) and c["slope_se"] > 0:
                z_slope.append(c["slope"] / c["slope_se"])
        widen[figure] = {
            "offset": max(1.0, mad_sigma(np.array(z_off))) if len(z_off) >= MIN_ROBUST_DEVICES else 1.0,
            "slope": max(1.0, mad_sigma(np.array(z_slope))) if len(z_slope) >= MIN_ROBUST_DEVICES else 1.0,
        }  # fmt: skip
    for d in with_chamber:
        ch = d["chamber"]
        for figure, c in ch["figures"].items():
            if not np.isfinite(c["offset"]):
                continue
            c["reach"] = reach(figure, ch["m"])
            c["limit_offset"] = float(
                k * widen[figure]["offset"] * np.hypot(c["offset_se"], c["reach"])
            )
            c["limit_slope"] = float(k * widen[figure]["slope"] * c["slope_se"])
            where = (
                f"{_name(figure)} {_text(figure, abs(c['worst']))} "
                f"{'above' if c['worst'] > 0 else 'below'} its chamber curve at {c['worst_t']:.0f} degC"
            )
            lo, hi = ch["ranges"]["gyro" if figure.startswith("gyro") else "accel"]
            if not lo - WARN_MARGIN <= c["worst_t"] <= hi + WARN_MARGIN:
                where += f" (beyond the chamber's {lo:.0f}..{hi:.0f} degC: extrapolated)"
            unit = "rad/s" if figure.startswith("gyro") else "m/s^2"
            if np.isfinite(c["limit_offset"]) and abs(c["offset"]) > c["limit_offset"]:
                add_flag(
                    d["flags"], d["device_id"], "chamber_offset", figure, None, c["offset"],
                    c["limit_offset"],
                    f"in-field {where} (moved since the chamber: offset "
                    f"{c['offset']:+.3g} +- {c['offset_se']:.2g} {unit} at {c['t_centre']:.0f} "
                    f"degC, limit {c['limit_offset']:.2g})",
                )  # fmt: skip
            if np.isfinite(c["limit_slope"]) and abs(c["slope"]) > c["limit_slope"]:
                add_flag(
                    d["flags"], d["device_id"], "chamber_slope", figure, None, c["slope"],
                    c["limit_slope"],
                    f"in-field {where} (thermal slope {c['slope']:+.2g} +- "
                    f"{c['slope_se']:.1g} {unit}/K off the chamber's, limit {c['limit_slope']:.1g})",
                )  # fmt: skip
    return widen
