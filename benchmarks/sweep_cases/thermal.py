"""Accuracy sweep, thermal family (issue 25): the ``temperature`` stage with default options on
the thermal histories users record, against the simulated truth.

Each case simulates a log to fit (``imupipe simulate thermal``, post-processed for handling,
orientation changes, gaps and drifts the simulator does not make) and a *check* log from the
same sensor (same truth, another seed: the next session a user would correct). The stage fits
the first with default options (gyro); then

- an **answer** is judged on the check log, simulated without sensor noise: per axis the RMS of
  the corrected 10 s block means minus the true output (accelerometer: minus their mean, since
  one orientation cannot tell a constant bias from a tilt) (the bias the correction leaves, the
  quantity the stage states as ``remaining_rms``). It is *within tolerance* when that RMS is at
  most the upper end of the stage's stated 95 % interval (``remaining_rms_95``, which holds on
  the three axes at once) on every axis, else a *wrong answer* (a confident claim the data do
  not keep); *covered* when it lies inside the interval on every axis;
- a **refusal** is a *right-cause refusal* when its message names the case's true cause (the
  words listed with each case) and says what to record, else a *wrong-cause refusal*.

``run(quick=True)``: a handful of small cases for CI (tests/test_sweep_thermal.py); the full
sweep covers element lags 0 to 600 s, one-way ramps, soaks, handling and orientation changes
between soaks, gaps, and 1 to 400 Hz. Run alone: ``python benchmarks/sweep_cases/thermal.py
[--quick]``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa

FAMILY = "thermal"
G = 9.80665
GYRO_SENSITIVITY = np.array(
    [[2.0e-3, 0.4e-3, 0.0], [-0.3e-3, 1.5e-3, 0.2e-3], [0.0, 0.5e-3, 1.0e-3]]
)
"""rad/s per (m/s^2 / g): a MEMS gyro's g-sensitivity (0.06-0.1 deg/s/g)."""
SHORT = {"t_min": 0.0, "t_max": 40.0, "hold_s": 600.0, "lag_s": 120.0}
"""A 40 degC chamber program (short enough for CI)."""
# the chamber's bias polynomial about 25 degC, scaled to a 40 degC span (rad/s)
SHORT_POLY = [
    [2.0e-3, 1.5e-4, -4.0e-6, -2.0e-7],
    [-1.0e-3, -1.0e-4, 5.0e-6, 1.0e-7],
    [5.0e-4, 8.0e-5, 3.0e-6, -2.0e-7],
]


@dataclass
class Case:
    name: str
    params: dict[str, Any]
    quick: bool = False
    edit: Callable[[pa.Table, np.random.Generator], pa.Table] | None = None
    """Post-processing of both logs (handling, orientation changes, gaps, drift)."""
    check_params: dict[str, Any] = field(default_factory=dict)
    """Overrides for the check log (default: the fit log's program, another seed)."""
    sensor: str = "gyro"
    """The sensor fitted (``accel``: the true output is gravity, z up)."""
    cause: tuple[str, ...] = ()
    """Words a refusal must hold to name the true cause and what to record (empty: an answer is
    expected, and any refusal blames a wrong cause)."""


def _rows(table: pa.Table) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    from imupipe.readers.table import sensor

    g, a = sensor(table, "gyro"), sensor(table, "accel")
    temp = sensor(table, "temperature").values[:, 0]
    return g.t_ns, g.values.copy(), a.values.copy(), temp


def _table(t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, temp: np.ndarray) -> pa.Table:
    from imupipe.readers.table import make_table

    return make_table(t_ns, gyro=gyro, accel=accel, temperature=temp)


def _segments(t_s: np.ndarray, count: int) -> list[tuple[float, float]]:
    """``count`` handling periods of 120 s spread over the log (between soaks)."""
    span = float(t_s[-1])
    centres = span * (np.arange(1, count + 1) / (count + 1))
    return [(c - 60.0, c + 60.0) for c in centres]


def handling(count: int, turn: bool) -> Callable[[pa.Table, np.random.Generator], pa.Table]:
    """``count`` 2-minute handling periods (picked up, carried, put down: rotation rates to 2
    rad/s, accelerations to 3 m/s^2); with ``turn`` the IMU is put down in another orientation
    each time (gravity on another axis, the gyro's g-sensitivity with it)."""

    def edit(table: pa.Table, rng: np.random.Generator) -> pa.Table:
        t_ns, gyro, accel, temp = _rows(table)
        t_s = (t_ns - t_ns[0]) * 1e-9
        orientations = [np.eye(3), np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]]),
                        np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]]),
                        np.array([[-1, 0, 0], [0, 1, 0], [0, 0, -1.0]])]  # fmt: skip
        pieces = _segments(t_s, count)
        pose = np.zeros(len(t_s), dtype=int)
        for k, (a, b) in enumerate(pieces):
            moving = (t_s >= a) & (t_s < b)
            n = int(moving.sum())
            gyro[moving] += rng.normal(0.0, 1.0, (n, 3))
            accel[moving] += rng.normal(0.0, 3.0, (n, 3))
            if turn:
                pose[t_s >= b] = (k + 1) % len(orientations)
        if turn:
            up = np.array([0.0, 0.0, G])
            for k in np.unique(pose):
                sel = pose == k
                g_body = orientations[k] @ up
                accel[sel] += g_body - up
                gyro[sel] += GYRO_SENSITIVITY @ (g_body / G) - GYRO_SENSITIVITY @ (up / G)
        return _table(t_ns, gyro, accel, temp)

    return edit


def bursts(on_s: float, every_s: float) -> Callable[[pa.Table, np.random.Generator], pa.Table]:
    """Keep ``on_s`` seconds every ``every_s`` (a logger that wakes up to record)."""

    def edit(table: pa.Table, rng: np.random.Generator) -> pa.Table:
        t_ns = table.column("t_ns").to_numpy()
        keep = np.mod((t_ns - t_ns[0]) * 1e-9, every_s) < on_s
        return table.filter(pa.array(keep))

    return edit


def heating_only(table: pa.Table, rng: np.random.Generator) -> pa.Table:
    """The first heating ramp only (to the top hold): a one-way ramp."""
    t_ns, gyro, accel, temp = _rows(table)
    stop = int(np.argmax(temp)) + 1
    return _table(t_ns[:stop], gyro[:stop], accel[:stop], temp[:stop])


def drifting(table: pa.Table, rng: np.random.Generator) -> pa.Table:
    """A bias random walk (5e-6 rad/s/sqrt(s)) much larger than the (zero) thermal bias."""
    t_ns, gyro, accel, temp = _rows(table)
    dt = float(np.median(np.diff(t_ns))) * 1e-9
    walk = np.cumsum(rng.normal(0.0, 5e-6 * np.sqrt(dt), (len(t_ns), 3)), axis=0)
    return _table(t_ns, gyro + walk, accel, temp)


def tag_day(table: pa.Table, rng: np.random.Generator) -> pa.Table:
    """The issue's tag log: 1 Hz, three long still periods in three orientations, handled by
    hand between them, warming slowly; flicker-like bias wander."""
    turned = handling(2, turn=True)(table, rng)
    return drifting(turned, rng)


def kinked(table: pa.Table, rng: np.random.Generator) -> pa.Table:
    """A bias whose slope changes at 20 degC (0.02 -> 0.1 mrad/s/degC on x, other signs on y,
    z): no polynomial of low order has that shape."""
    t_ns, gyro, accel, temp = _rows(table)
    x = temp - 20.0
    slope = np.where(x[:, None] < 0, [2e-5, -1e-5, 3e-5], [1e-4, 6e-5, -5e-5])
    return _table(t_ns, gyro + slope * x[:, None], accel, temp)


def quantised(step: float) -> Callable[[pa.Table, np.random.Generator], pa.Table]:
    """The temperature as a sensor with ``step`` degC resolution reports it."""

    def edit(table: pa.Table, rng: np.random.Generator) -> pa.Table:
        t_ns, gyro, accel, temp = _rows(table)
        return _table(t_ns, gyro, accel, np.round(temp / step) * step)

    return edit


ZERO_RATE = [0.0, 0.0, 0.0]
TACTICAL = {"gyro_N": [2e-6] * 3, "temperature_noise": 0.002}
"""A tactical-grade gyro (white noise 100x below the consumer default) and a finer sensor: the
model's own error, not the noise, sets what is left."""
CASES = [
    Case("lag 0 s, cycles 1 + 0.5 degC/min, 2 Hz", {"rate_hz": 2.0, "heating_rates": [1.0, 0.5]}),
    Case(
        "lag 200 s, cycles 1 + 0.5 degC/min, 2 Hz",
        {
            "rate_hz": 2.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 200.0,
            "gyro_rate_coef": ZERO_RATE,
        },
    ),  # fmt: skip
    Case(
        "lag 200 s, fit 1 + 0.5, check at 2 degC/min, 2 Hz",
        {
            "rate_hz": 2.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 200.0,
            "gyro_rate_coef": ZERO_RATE,
        },
        check_params={"heating_rates": [2.0]},
    ),  # fmt: skip
    Case(
        "lag 100 s, short cycles 1 + 0.5 degC/min, 1 Hz",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 100.0,
            "gyro_rate_coef": ZERO_RATE,
        },
        quick=True,
    ),  # fmt: skip
    Case(
        "lag 600 s, cycles 1 + 0.5 degC/min, 2 Hz",
        {
            "rate_hz": 2.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 600.0,
            "gyro_rate_coef": ZERO_RATE,
        },
    ),  # fmt: skip
    Case(
        "one-way ramp 40 degC at 0.5 degC/min, 1 Hz",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 1.0,
            "heating_rates": [0.5],
            "gyro_rate_coef": ZERO_RATE,
        },
        quick=True,
        edit=heating_only,
    ),  # fmt: skip
    Case(
        "soaks every 10 degC, 2 Hz",
        {"rate_hz": 2.0, "heating_rates": [1.0], "soak_step": 10.0, "hold_s": 900.0},
    ),
    Case(
        "handling between soaks, one orientation, 1 Hz",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "soak_step": 10.0,
        },
        quick=True,
        edit=handling(4, turn=False),
    ),  # fmt: skip
    Case(
        "orientation changes between soaks, 1 Hz",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "soak_step": 10.0,
        },
        edit=handling(3, turn=True),
        cause=("turned between", "record"),
    ),  # fmt: skip
    Case(
        "tag day: 3 orientations, handling, 5 -> 24 degC, 1 Hz",
        {
            "rate_hz": 1.0,
            "t_min": 5.0,
            "t_max": 24.0,
            "heating_rates": [0.01],
            "cooling_rates": [1.0],
            "hold_s": 3600.0,
            "lag_s": 1800.0,
            "gyro_poly": [[2e-3, 2e-5, 0, 0], [-1e-3, 1e-5, 0, 0], [5e-4, -1e-5, 0, 0]],
            "gyro_rate_coef": ZERO_RATE,
            "gyro_N": [2e-3] * 3,
        },
        quick=True,
        edit=tag_day,
        cause=("turned between", "record"),
    ),  # fmt: skip
    Case(
        "z axis without thermal bias, 1 Hz",
        {
            **SHORT,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "gyro_poly": [SHORT_POLY[0], SHORT_POLY[1], [1e-3, 0, 0, 0]],
            "gyro_rate_coef": ZERO_RATE,
        },
        quick=True,
    ),  # fmt: skip
    Case(
        "bias random walk, no thermal bias, 2 Hz",
        {
            **SHORT,
            "rate_hz": 2.0,
            "heating_rates": [1.0, 0.5],
            "gyro_poly": [[1e-3, 0, 0, 0]] * 3,
            "gyro_rate_coef": ZERO_RATE,
        },
        quick=True,
        edit=drifting,
        cause=("than no compensation", "does not follow the temperature", "record"),
    ),  # fmt: skip
    Case(
        "rate term (hysteresis), fit 1 + 0.5, check at 2 degC/min, 2 Hz",
        {"rate_hz": 2.0, "heating_rates": [1.0, 0.5]},
        check_params={"heating_rates": [2.0]},
    ),
    Case(
        "kinked bias (slope changes at 20 degC), 1 Hz",
        {
            **SHORT,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "gyro_poly": [[0, 0, 0, 0]] * 3,
            "gyro_rate_coef": ZERO_RATE,
        },
        edit=kinked,
    ),  # fmt: skip
    Case(
        "temperature quantised to 0.5 degC, 1 Hz",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 100.0,
            "gyro_rate_coef": ZERO_RATE,
        },
        edit=quantised(0.5),
    ),  # fmt: skip
    Case(
        "three soaks (0, 20, 40 degC), 2 Hz",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 2.0,
            "heating_rates": [2.0],
            "soak_step": 20.0,
            "hold_s": 1800.0,
        },
    ),  # fmt: skip
    Case(
        "span 0.6 degC (a room), 2 Hz",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 2.0,
            "t_min": 20.0,
            "t_max": 20.6,
            "heating_rates": [0.05],
        },
        quick=True,
        cause=("spans only", "heat or cool"),
    ),  # fmt: skip
    Case(
        "tactical noise, kinked bias, 1 Hz",
        {
            **SHORT,
            **TACTICAL,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "gyro_poly": [[0, 0, 0, 0]] * 3,
            "gyro_rate_coef": ZERO_RATE,
        },
        edit=kinked,
    ),  # fmt: skip
    Case(
        "tactical noise, temperature quantised to 0.5 degC, lag 100 s, 1 Hz",
        {
            **SHORT,
            **TACTICAL,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 100.0,
            "gyro_rate_coef": ZERO_RATE,
        },
        edit=quantised(0.5),
    ),  # fmt: skip
    Case(
        "tactical noise, lag 200 s, check at 2 degC/min, 2 Hz",
        {
            **TACTICAL,
            "rate_hz": 2.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 200.0,
            "gyro_rate_coef": ZERO_RATE,
        },
        check_params={"heating_rates": [2.0]},
    ),  # fmt: skip
    Case(
        "accel, cycles 1 + 0.5 degC/min, 2 Hz",
        {"rate_hz": 2.0, "heating_rates": [1.0, 0.5]},
        sensor="accel",
    ),
    Case(
        "accel, lag 200 s, short cycles, 1 Hz",
        {
            **SHORT,
            "rate_hz": 1.0,
            "heating_rates": [1.0, 0.5],
            "element_lag_s": 200.0,
            "accel_rate_coef": ZERO_RATE,
        },
        sensor="accel",
    ),  # fmt: skip
    Case(
        "accel, handling between soaks, one orientation, 1 Hz",
        {**SHORT, "rate_hz": 1.0, "heating_rates": [1.0, 0.5], "soak_step": 10.0},
        sensor="accel",
        edit=handling(4, turn=False),
    ),
    Case(
        "gaps: 5 s every 60 s, 50 Hz",
        {**SHORT, "gyro_poly": SHORT_POLY, "rate_hz": 50.0, "heating_rates": [2.0, 1.0]},
        edit=bursts(5.0, 60.0),
    ),  # fmt: skip
    Case(
        "100 Hz, cycles 2 + 1 degC/min, lag 60 s",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 100.0,
            "heating_rates": [2.0, 1.0],
            "element_lag_s": 60.0,
            "gyro_rate_coef": ZERO_RATE,
        },
    ),  # fmt: skip
    Case(
        "400 Hz, cycle 2 + 1 degC/min",
        {
            **SHORT,
            "gyro_poly": SHORT_POLY,
            "rate_hz": 400.0,
            "heating_rates": [2.0, 1.0],
            "hold_s": 300.0,
        },
    ),  # fmt: skip
]


def _block_rms(
    table: pa.Table, reference: np.ndarray, name: str = "gyro", mean: bool = False
) -> np.ndarray:
    """Per axis RMS of the 10 s block means (complete blocks) of sensor ``name`` minus
    ``reference`` (``mean``: their mean instead)."""
    from imupipe.readers.table import sensor
    from imupipe.stages.blocks import block_means

    g = sensor(table, name)
    blocks = block_means(g.t_ns, g.values - reference, window_s=10.0)
    full = blocks.counts >= 0.9 * np.median(blocks.counts)
    if mean:
        return blocks.means[full].mean(axis=0)
    return np.sqrt(np.mean(blocks.means[full] ** 2, axis=0))


def _still_rows(table: pa.Table) -> pa.Table:
    """The check log without its handling (the truth is judged where the IMU is still)."""
    from imupipe.readers.table import sensor

    g = sensor(table, "gyro").values
    return table.filter(pa.array(np.abs(g).max(axis=1) < 0.05))


def judge(case: Case, seed: int = 0) -> dict[str, Any]:
    from imupipe.pipeline.simulate import simulate
    from imupipe.stages.base import StageContext
    from imupipe.stages.errors import FitError
    from imupipe.stages.thermal.temperature import TemperatureStage

    fit_log, _ = simulate("thermal", case.params, seed=100 + seed)
    # the check log without sensor noise: what the correction leaves is the calibration's error
    check = {**case.params, **case.check_params, f"{case.sensor}_N": [0.0, 0.0, 0.0]}
    check_log, _ = simulate("thermal", check, seed=200 + seed)
    if case.edit is not None:
        fit_log = case.edit(fit_log, np.random.default_rng(300 + seed))
        check_log = case.edit(check_log, np.random.default_rng(400 + seed))
    row: dict[str, Any] = {"family": FAMILY, "case": case.name}
    stage = TemperatureStage(TemperatureStage.Options(sensor=case.sensor))
    ctx = StageContext(name="temperature", input_name="fit", quiet=True)
    try:
        out = stage.fit(fit_log, ctx)
    except FitError as err:
        message = str(err)
        named = bool(case.cause) and all(w in message for w in case.cause)
        row.update(outcome="refused", error="-", stated="-", covered=None, message=message)
        # where an answer was expected (no cause listed), any refusal blames the wrong cause
        row["verdict"] = "right-cause refusal" if named else "wrong-cause refusal"
        return row
    metrics = out.results["metrics"]
    corrected = out.step.apply(_still_rows(check_log))
    reference = np.zeros(3)
    if case.sensor == "accel":
        # one orientation cannot tell a constant accel bias from a tilt (the stage's reference
        # is gravity along the mean): the accel is judged on what varies, about its mean
        reference = _block_rms(corrected, np.zeros(3), "accel", mean=True)
    truth = _block_rms(corrected, reference, case.sensor)
    lo = np.array([metrics[a]["remaining_rms_95"][0] for a in "xyz"])
    hi = np.array([metrics[a]["remaining_rms_95"][1] for a in "xyz"])
    within = bool((truth <= hi).all())
    # where the case's truth cannot be fitted (a cause listed), any answer is wrong
    verdict = "within tolerance" if within and not case.cause else "wrong answer"
    worst = int(np.argmax(truth / hi))
    scale, unit = (1e3, "mrad/s") if case.sensor == "gyro" else (1e3 / G, "mg")
    row.update(
        outcome="answer",
        verdict=verdict,
        error=f"{truth[worst] * scale:.3g} {unit} ({'xyz'[worst]}; max of {', '.join(f'{v * scale:.3g}' for v in truth)})",
        stated=f"<= {hi[worst] * scale:.3g} {unit} (95 % [{lo[worst] * scale:.3g}, {hi[worst] * scale:.3g}])",
        covered=bool(((truth >= lo) & (truth <= hi)).all()),
        model=out.results["model"],
        reduction=[
            float(v)
            for v in _block_rms(_still_rows(check_log), np.zeros(3)) / np.maximum(truth, 1e-12)
        ],
    )
    return row


def run(quick: bool) -> list[dict[str, Any]]:
    """Every case (``quick``: the CI subset) judged with default options; one dict per case."""
    return [judge(c) for c in CASES if c.quick or not quick]


if __name__ == "__main__":
    rows = []
    for case in CASES:
        if "--quick" in sys.argv and not case.quick:
            continue
        start = time.perf_counter()
        row = judge(case)
        rows.append(row)
        extra = row.get("model") or row.get("message", "")[:160]
        print(
            f"{row['case'][:50]:50s} {row['outcome']:8s} {row['verdict']:20s} "
            f"{row['error']:40s} {row['stated']:40s} {row['covered']!s:5s} "
            f"{time.perf_counter() - start:5.1f}s {extra}",
            flush=True,
        )
    verdicts = [r["verdict"] for r in rows]
    covered = [r["covered"] for r in rows if r["covered"] is not None]
    print(
        f"within tolerance {verdicts.count('within tolerance')}, right-cause refusals "
        f"{verdicts.count('right-cause refusal')}, wrong answers {verdicts.count('wrong answer')}, "
        f"wrong-cause refusals {verdicts.count('wrong-cause refusal')}; coverage "
        f"{sum(covered)}/{len(covered)}"
    )
