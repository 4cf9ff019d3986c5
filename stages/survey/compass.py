"""The compass's fleet view in ``imupipe survey``: each compass's in-flight calibration across its
flights (the per-flight fits are the ``mag_inflight`` stage's, made by the survey's worker).

Per compass device (its fitted flights in date order; vectors in uT):

1. **Steps** between consecutive flights of the offsets (the calibration the flight says the
   vehicle should use) and, where both flights fitted it, of the motor term (uT/A, or uT at full
   throttle for a compass whose motor term follows the throttle; its fleet scale among the
   compasses of the same source): flagged on
   the axis where ``|d| > k sqrt(s_fleet^2 + se_1^2 + se_2^2)`` by the most, ``s_fleet`` the
   robust scale (1.4826 MAD, :func:`~imupipe.stages.survey.stats.mad_sigma`) of every
   consecutive difference of that axis in the fleet (the ordinary flight-to-flight change:
   attitude and model errors), ``se`` each flight's standard error. A new payload, a changed
   frame or a magnetised part is a step. An offset step is also flagged when it exceeds
   ``OFFSET_STEP_FRACTION`` (20 %) of the earth field and 5 standard errors on an axis, the
   ``mag_inflight`` stage's rule for flights fitted together, whatever the fleet's scale: in a
   fleet of a few flights the step itself inflates ``s_fleet``.
2. **Outliers**: a flight whose step in and step out are both flagged, opposite and of similar
   size (the second within a factor two of the first), is one odd flight (a magnetised tool
   aboard, a bad attitude estimate), reported as an outlier instead of two steps.
3. **Drift**: the Theil-Sen slope (:func:`~imupipe.stages.survey.stats.theil_sen`) of each
   offset axis over calendar days (uT/day) since the last step (three flights or more), flagged when it departs from
   the fleet's median slope by more than ``k`` robust sigmas of the fleet's slopes and its
   change over the device's span exceeds ``k s_fleet sqrt(flights - 1)`` (the reach of the
   ordinary change over that many flights), as the IMU fleet view's rule.
4. **The calibration in use**: on the device's last fitted flight, the RMS difference between
   the field corrected by the vehicle's own parameters and by the flight's fit
   (``calibration_error_ut``) is flagged when it exceeds the larger of ``OFF_FRACTION`` of the
   field and the flight's own residual after its fit: "the compass calibration in use is off
   by X uT".
5. **Moved**: the offsets' change from the first flight to the last (uT), which sorts the table.

Refused flights (the flight could not separate the terms, or had no GPS date) are counted per
device with their reasons, never flagged.

``k`` (the survey's ``--k``, default 5) is the number of robust standard deviations beyond
which a change is flagged (Rousseeuw & Croux 1993 for the MAD; Sen 1968 for the slope).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imupipe.stages.magnetometer.inflight import OFFSET_STEP_FRACTION, hard_iron_stepped
from imupipe.stages.survey.fleet import add_flag
from imupipe.stages.survey.stats import mad_sigma, theil_sen, weighted_mean

OFF_FRACTION = 0.05
"""The calibration in use is flagged when it is off by more than this fraction of the earth
field (5 %: about 2.5 uT, a heading error of several degrees at mid latitudes)."""
DAY_NS = 86_400e9
OUTLIER_RATIO = 2.0
"""An in-and-out pair of steps within this ratio of each other is one odd flight."""


@dataclass
class CompassHistory:
    """One compass's fitted flights in date order (arrays: one row per flight; vectors (n, 3))."""

    device_id: str
    logs: list[str]
    day: np.ndarray
    offset: np.ndarray
    offset_se: np.ndarray
    motor: np.ndarray
    """(n, 3) uT/A (``motor_source = "current"``) or uT at full throttle (``"throttle"``), NaN
    where the flight did not fit the motor term on that source."""
    motor_se: np.ndarray
    calibration_error: np.ndarray
    """(n,) uT: the vehicle's own calibration against the flight's fit (NaN where unknown)."""
    residual_after: np.ndarray
    field: np.ndarray
    domain: str
    """``sensor`` (offsets the vehicle should use) or ``logged`` (fits on the field as logged,
    where the log's own calibration could not be composed with the fit)."""
    refused: list[tuple[str, str]] = field(default_factory=list)
    flags: list[dict[str, Any]] = field(default_factory=list)
    drift: list[float] = field(default_factory=list)
    moved: float = 0.0
    mean_offset: list[float] = field(default_factory=list)
    motor_source: str = "current"
    """What the motor term multiplies: the battery current or the throttle (0..1)."""


def compass_history(
    device_id: str,
    logs: Sequence[str],
    start_ns: np.ndarray,
    offset: np.ndarray,
    offset_se: np.ndarray,
    motor: np.ndarray,
    motor_se: np.ndarray,
    calibration_error: np.ndarray,
    residual_after: np.ndarray,
    field_ut: np.ndarray,
    t0_ns: int,
    domain: str = "sensor",
    refused: Sequence[tuple[str, str]] = (),
    motor_source: str = "current",
) -> CompassHistory:
    """A compass's history from its fitted flights (any order; sorted by ``start_ns``)."""
    order = np.argsort(np.asarray(start_ns, dtype=np.float64), kind="stable")
    take = lambda a: np.asarray(a, dtype=np.float64)[order]  # noqa: E731
    h = CompassHistory(
        device_id,
        [str(logs[i]) for i in order],
        (take(start_ns) - t0_ns) / DAY_NS,
        take(offset),
        take(offset_se),
        take(motor),
        take(motor_se),
        take(calibration_error),
        take(residual_after),
        take(field_ut),
        domain,
        list(refused),
        motor_source=motor_source,
    )
    h.mean_offset = [weighted_mean(h.offset[:, i], h.offset_se[:, i])[0] for i in range(3)]
    return h


def _steps(
    h: CompassHistory,
    values: np.ndarray,
    se: np.ndarray,
    scale: np.ndarray,
    k: float,
    field: np.ndarray | None = None,
):
    """(j, d (3,), ratio, limit, axis, whole) of each flagged step into flight j: the axis with
    the largest ``|d| / limit`` above 1 (``whole`` False); or, given each flight's earth
    ``field`` (offsets), a change the hard iron made beyond any one calibration
    (:func:`~imupipe.stages.magnetometer.inflight.hard_iron_stepped`, the ``mag_inflight``
    stage's rule for flights fitted together) where the fleet's scale hides it (a small fleet
    whose few flight-to-flight changes include the step itself): ``limit`` that fraction of the
    field, ``whole`` True."""
    out = []
    for j in range(1, len(values)):
        d = values[j] - values[j - 1]
        se_d = np.sqrt(se[j] ** 2 + se[j - 1] ** 2)
        limit = k * np.sqrt(np.nan_to_num(scale) ** 2 + se_d**2)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.abs(d) / limit
        if np.isfinite(ratio).any() and np.nanmax(ratio) > 1:
            axis = int(np.nanargmax(ratio))
            out.append((j, d, float(ratio[axis]), float(limit[axis]), axis, False))
        elif (
            field is not None
            and np.isfinite(field[j])
            and np.isfinite(d).all()
            and hard_iron_stepped(d, se_d, float(field[j]))
        ):
            whole = OFFSET_STEP_FRACTION * float(field[j])
            axis = int(np.argmax(np.abs(d)))
            out.append((j, d, float(np.linalg.norm(d)) / whole, whole, axis, True))
    return out


def _vec(d: np.ndarray, unit: str) -> str:
    return "(" + ", ".join(f"{v:+.2f}" for v in d) + f") {unit}"


def _step_flags(
    h: CompassHistory, name: str, values: np.ndarray, se: np.ndarray, scale: np.ndarray,
    k: float, unit: str,
) -> None:  # fmt: skip
    steps = _steps(h, values, se, scale, k, h.field if unit == "uT" else None)
    by_j = {s[0]: s for s in steps}
    skip: set[int] = set()
    for j, d, _ratio, limit, axis, whole in steps:
        if j in skip:
            continue
        nxt = by_j.get(j + 1)
        if nxt is not None:
            d2 = nxt[1]
            opposite = np.sign(d[axis]) == -np.sign(d2[axis])
            similar = (
                1 / OUTLIER_RATIO <= abs(d2[axis]) / max(abs(d[axis]), 1e-300) <= OUTLIER_RATIO
            )
            if opposite and similar:
                skip.add(j + 1)
                add_flag(
                    h.flags, h.device_id, "outlier", name, h.logs[j], float(d[axis]), limit,
                    f"{name} of {h.logs[j]} depart from the flights before and after by "
                    f"{_vec(d, unit)} (limit {limit:.2g} {unit}): one odd flight",
                )  # fmt: skip
                continue
        norm = float(np.linalg.norm(np.nan_to_num(d)))
        share = (
            f", {100 * norm / h.field[j]:.0f} % of the field"
            if unit == "uT" and np.isfinite(h.field[j]) and h.field[j] > 0
            else ""
        )
        add_flag(
            h.flags, h.device_id, "step", name, h.logs[j], norm if whole else float(d[axis]), limit,
            f"{name} stepped by {_vec(d, unit)}{share} between {h.logs[j - 1]} and {h.logs[j]} "
            + (
                f"(limit {limit:.2g} {unit} in all, {100 * OFFSET_STEP_FRACTION:.0f} % of the "
                "field: no one calibration serves both)"
                if whole
                else f"(limit {limit:.2g} {unit} on {'xyz'[axis]})"
            ),
        )  # fmt: skip


def compass_flags(histories: Sequence[CompassHistory], k: float) -> dict[str, Any]:
    """Apply the module docstring's rules to every compass (fills ``flags``, ``drift``,
    ``moved``); returns the fleet's scales (``offset`` uT per axis, ``motor`` uT/A per axis,
    ``motor_throttle`` uT at full throttle per axis)."""
    scales: dict[str, list[float]] = {}
    groups = {"offset": ("offset", None), "motor": ("motor", "current")}
    groups["motor_throttle"] = ("motor", "throttle")
    for name, (attr, src) in groups.items():
        diffs = [
            np.diff(getattr(h, attr), axis=0)
            for h in histories
            if len(getattr(h, attr)) > 1 and src in (None, h.motor_source)
        ]
        all_d = np.vstack(diffs) if diffs else np.zeros((0, 3))
        scales[name] = [mad_sigma(all_d[:, i]) if len(all_d) else float("nan") for i in range(3)]
    s_off = np.nan_to_num(np.asarray(scales["offset"]))
    s_mots = {
        "current": np.nan_to_num(np.asarray(scales["motor"])),
        "throttle": np.nan_to_num(np.asarray(scales["motor_throttle"])),
    }
    since: dict[str, int] = {}
    for h in histories:
        _step_flags(h, "offsets", h.offset, h.offset_se, s_off, k, "uT")
        stepped = [h.logs.index(f["log"]) for f in h.flags if f["kind"] == "step"]
        since[h.device_id] = max(stepped, default=0)
    slopes = []
    for h in histories:  # the drift since the last step (a step is not a drift)
        a = since[h.device_id]
        h.drift = [
            theil_sen(h.day[a:], h.offset[a:, i]) if len(h.day) - a >= 3 else float("nan")
            for i in range(3)
        ]
        slopes.append(h.drift)
    slope_arr = np.asarray(slopes, dtype=np.float64).reshape(-1, 3)
    for h in histories:
        both = np.isfinite(h.motor).all(axis=1)
        if both.sum() > 1:
            idx = np.flatnonzero(both)
            sub = CompassHistory(
                h.device_id, [h.logs[i] for i in idx], h.day[idx], h.offset[idx], h.offset_se[idx],
                h.motor[idx], h.motor_se[idx], h.calibration_error[idx], h.residual_after[idx],
                h.field[idx], h.domain,
            )  # fmt: skip
            unit = "uT/A" if h.motor_source == "current" else "uT at full throttle"
            s_mot = s_mots[h.motor_source]
            _step_flags(sub, "motor term", h.motor[idx], h.motor_se[idx], s_mot, k, unit)
            h.flags += sub.flags
        n = len(h.day)
        h.moved = float(np.linalg.norm(h.offset[-1] - h.offset[0])) if n > 1 else 0.0
        a = since[h.device_id]
        span = h.day[-1] - h.day[a] if n else 0.0
        for i in range(3):
            finite = slope_arr[:, i][np.isfinite(slope_arr[:, i])]
            s = h.drift[i]
            if not len(finite) or not np.isfinite(s):
                continue
            med, sig = float(np.median(finite)), mad_sigma(finite)
            walk = k * s_off[i] * np.sqrt(max(n - a - 1, 1))
            if abs(s - med) > k * sig and abs(s - med) * span > walk:
                add_flag(
                    h.flags, h.device_id, "drift", f"offset_{'xyz'[i]}", None, s, med + k * sig,
                    f"offset {'xyz'[i]} drifts {s:+.3g} uT/day over {span:.0f} days (fleet median "
                    f"{med:+.3g}, limit +-{k * sig:.2g})",
                )  # fmt: skip
        if n and np.isfinite(h.calibration_error[-1]):
            err = float(h.calibration_error[-1])
            limit = max(OFF_FRACTION * float(h.field[-1]), float(h.residual_after[-1]))
            if err > limit:
                add_flag(
                    h.flags, h.device_id, "calibration", "calibration_error_ut", h.logs[-1], err, limit,
                    f"the compass calibration in use is off by {err:.1f} uT in {h.logs[-1]} "
                    f"(limit {limit:.1f} uT: {100 * OFF_FRACTION:.0f} % of the field or the "
                    "flight's own residual)",
                )  # fmt: skip
    return {"k": k, "scales": scales}
