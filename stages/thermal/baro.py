"""``baro_temperature`` stage: a barometer's pressure error against its own temperature, the
thermal compensation PX4 applies to barometers (``TC_Bn_*``).

**Model** (PX4-Autopilot ``src/modules/temperature_compensation``, ``calc_thermal_offsets_1D``;
fitted by PX4's ``Tools/process_sensor_caldata.py`` to 5th order)::

    offset(T) = sum_{k=0..order} X_k (clamp(T, TMIN, TMAX) - TREF)^k        Pa, T in degC
    corrected = pressure - offset(T)                                         Pa

on the rows of the temperature stream read from a barometer (the common table's ``pressure``
column, Pa, with the barometer's own temperature on the same row: ULog ``sensor_baro``,
DataFlash ``BARO``). A thermal-calibration log is a board warming up at rest in still air at
constant pressure, so what changes with temperature is the sensor's error. The absolute
pressure of the room is not observable: ``X_0`` is chosen, as PX4's script does, so that the
offset is the pressure relative to the median pressure of the log (corrected pressures are the
log's median pressure plus noise).

**Fit.** ``TREF`` is the middle of the logged range ``[TMIN, TMAX]`` (PX4's choice). The
pressures (minus their median) are averaged in ``bins`` equal-width temperature bins (PX4's
script resamples the same way, 2000 bins, so that the slow end of a warm-up, where most samples
lie, does not outweigh the rest of the range); the polynomial of degree ``order`` is the
least-squares fit to the bin means, solved in the scaled variable ``(T - TREF) / half-span``
for conditioning and returned in powers of ``T - TREF``.

**Quality checks** (``ctx.check``): the temperature must span ``min_span`` degC (a flat log
fixes no curve), and the bins must hold at least ``3 (order + 1)`` non-empty ones.
Figures in ``metrics``: the RMS of the pressure about the fit (Pa; the sensor noise when the
model holds), the largest bin-mean residual (Pa), the correction's range over the logged
temperatures (Pa).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from imupipe.readers.table import arrow_array, has_stream, sensor, to_numpy, usable, valid_mask
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.steps import EntryError, Step, _numbers

MAX_ORDER = 5
"""PX4's barometer polynomial has X0..X5."""
COLUMN = "pressure"


def baro_samples(table: pa.Table) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(rows, stamps, temperature degC, pressure Pa) of the temperature rows that hold a usable
    pressure and temperature (empty when the input has no barometer)."""
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    if COLUMN not in table.column_names or not has_stream(table, "temperature"):
        return empty
    temp = sensor(table, "temperature")
    col = table.column(COLUMN)
    p = to_numpy(col)  # NaN at nulls
    p = np.asarray(p, dtype=np.float64)[temp.rows]
    t = temp.values[:, 0]
    ok = usable(p) & usable(t)
    return temp.rows[ok], temp.t_ns[ok], t[ok], p[ok]


def offset_at(coefficients: np.ndarray, tref: float, t_range: tuple[float, float], temp):
    """PX4's ``calc_thermal_offsets_1D``: the polynomial in ``clamp(T) - tref``, Pa."""
    x = np.clip(np.asarray(temp, dtype=np.float64), t_range[0], t_range[1]) - tref
    return np.polynomial.polynomial.polyval(x, np.asarray(coefficients, dtype=np.float64))


@dataclass
class BaroTemperatureStep(Step):
    """``pressure -= offset(T)`` on the barometer rows (module docstring); ``coefficients``
    X0..X5 (Pa / degC^k), ``t_range`` [TMIN, TMAX] degC. The chain entry's ``sensor`` is
    ``temperature`` (the stream whose rows carry the pressure) and ``column`` is ``pressure``."""

    kind: ClassVar[str] = "baro_temperature"
    type: str
    tref: float
    coefficients: np.ndarray
    t_range: tuple[float, float]
    sensor: str = "temperature"
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        c = np.zeros(MAX_ORDER + 1)
        given = np.asarray(self.coefficients, dtype=np.float64).reshape(-1)
        c[: len(given)] = given
        self.coefficients = c
        self.t_range = (float(self.t_range[0]), float(self.t_range[1]))

    def apply(self, table: pa.Table) -> pa.Table:
        rows, _, t, p = baro_samples(table)
        if len(rows) == 0:
            return table
        col = table.column(COLUMN)
        full = np.array(to_numpy(col), dtype=np.float64)  # a copy, NaN at nulls
        full[rows] = p - offset_at(self.coefficients, self.tref, self.t_range, t)
        index = table.column_names.index(COLUMN)
        valid = valid_mask(col)
        array = arrow_array(full, pa.float64(), ~valid)
        return table.set_column(index, table.schema.field(COLUMN), array)

    def to_json(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "sensor": self.sensor,
            "kind": self.kind,
            "column": COLUMN,
            "tref": self.tref,
            "coefficients": self.coefficients.tolist(),
            "range": list(self.t_range),
            **self.params,
        }

    @classmethod
    def check_entry(cls, entry: dict[str, Any]) -> None:
        if entry["sensor"] != "temperature" or entry.get("column", COLUMN) != COLUMN:
            raise EntryError("sensor", "a barometer step corrects the pressure of temperature rows")
        if _numbers(entry.get("tref"), ()) is None:
            raise EntryError("tref", f"a number expected, got {entry.get('tref')!r}")
        c = entry.get("coefficients")
        if not isinstance(c, list) or not 1 <= len(c) <= MAX_ORDER + 1:
            raise EntryError("coefficients", f"1 to {MAX_ORDER + 1} numbers expected")
        if _numbers(c, (len(c),)) is None:
            raise EntryError("coefficients", "numbers expected")
        r = _numbers(entry.get("range"), (2,))
        if r is None or r[1] < r[0]:
            raise EntryError("range", "[TMIN, TMAX] with TMIN <= TMAX expected")

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> BaroTemperatureStep:
        own = ("type", "sensor", "kind", "column", "tref", "coefficients", "range")
        return cls(
            type=entry["type"],
            tref=float(entry["tref"]),
            coefficients=np.asarray(entry["coefficients"], dtype=np.float64),
            t_range=tuple(entry["range"]),  # type: ignore[arg-type]
            params={k: v for k, v in entry.items() if k not in own},
        )


@dataclass(frozen=True)
class BaroFit:
    """A fitted barometer model: ``coefficients`` X0..X5 in powers of ``T - tref`` (Pa),
    ``t_range`` the logged range, the bin centres and means it was fitted to, the median
    pressure it is relative to (Pa)."""

    tref: float
    coefficients: np.ndarray
    t_range: tuple[float, float]
    bin_t: np.ndarray
    bin_p: np.ndarray
    median: float


def fit_baro(temp: np.ndarray, pressure: np.ndarray, order: int, bins: int) -> BaroFit:
    """The binned least-squares fit of the module docstring (``temp`` degC, ``pressure`` Pa)."""
    lo, hi = float(temp.min()), float(temp.max())
    tref = 0.5 * (lo + hi)
    half = max(0.5 * (hi - lo), 1e-9)
    median = float(np.median(pressure))
    y = pressure - median
    idx = np.minimum(((temp - lo) / (hi - lo + 1e-300) * bins).astype(np.int64), bins - 1)
    count = np.bincount(idx, minlength=bins)
    keep = count > 0
    bin_t = (np.bincount(idx, temp, bins)[keep]) / count[keep]
    bin_p = (np.bincount(idx, y, bins)[keep]) / count[keep]
    u = (bin_t - tref) / half
    design = u[:, None] ** np.arange(order + 1)
    scaled, *_ = np.linalg.lstsq(design, bin_p, rcond=None)
    coef = np.zeros(MAX_ORDER + 1)
    coef[: order + 1] = scaled / half ** np.arange(order + 1)
    return BaroFit(tref, coef, (lo, hi), bin_t, bin_p, median)


class BaroTemperatureStage(Stage):
    type = "baro_temperature"
    sensors = ("temperature",)
    corrects = True

    @dataclass
    class Options:
        order: int = field(default=5, metadata={"min": 1, "max": MAX_ORDER})
        """Degree of the polynomial in T - TREF (PX4's ``TC_B*`` hold up to 5, its script fits
        5)."""
        bins: int = field(default=2000, metadata={"min": 10, "max": 100000})
        """Equal-width temperature bins whose mean pressures are fitted (PX4's script: 2000)."""
        min_span: float = field(default=10.0, metadata={"min": 0.0})
        """degC: the smallest temperature range that fixes a curve (quality check)."""

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        rows, t_ns, temp, p = baro_samples(table)
        if len(rows) == 0:
            raise ctx.fail(
                "no barometer pressure in the input: read the temperature stream from a "
                'barometer (temperature_topic = "sensor_baro" for a ULog, "BARO" for a '
                "DataFlash log)"
            )
        order, bins = int(self.options.order), int(self.options.bins)
        if len(rows) < 3 * (order + 1):
            raise ctx.fail(f"{len(rows)} barometer samples; a degree-{order} fit needs more")
        result = fit_baro(temp, p, order, bins)
        span = result.t_range[1] - result.t_range[0]
        fitted = offset_at(result.coefficients, result.tref, result.t_range, temp)
        residual = (p - result.median) - fitted
        bin_res = result.bin_p - offset_at(
            result.coefficients, result.tref, result.t_range, result.bin_t
        )
        grid = np.linspace(*result.t_range, 200)
        curve = offset_at(result.coefficients, result.tref, result.t_range, grid)
        if ctx.recorder.enabled:
            ctx.recorder.curve(
                f"/{ctx.name}/pressure_vs_temperature",
                result.bin_t,
                result.bin_p[:, None],
                ("pressure minus its median, bin means",),
                unit="Pa",
                x_label="temperature",
                x_unit="degC",
                title="barometer pressure against temperature",
                points=True,
            )
            ctx.recorder.curve(
                f"/{ctx.name}/fit",
                grid,
                curve[:, None],
                (f"fitted offset (degree {order})",),
                unit="Pa",
                x_label="temperature",
                x_unit="degC",
                plot=f"/{ctx.name}/pressure_vs_temperature",
                title="barometer pressure against temperature",
            )
        step = BaroTemperatureStep(
            type=self.type,
            tref=result.tref,
            coefficients=result.coefficients,
            t_range=result.t_range,
        )
        results = {
            "tref": result.tref,
            "coefficients": result.coefficients.tolist(),
            "range": list(result.t_range),
            "median_pressure": result.median,
            "metrics": {
                "samples": int(len(rows)),
                "bins": int(len(result.bin_t)),
                "duration_s": float((t_ns[-1] - t_ns[0]) * 1e-9),
                "temperature_span": float(span),
                "residual_rms_pa": float(np.sqrt(np.mean(residual**2))),
                "bin_residual_max_pa": float(np.abs(bin_res).max()),
                "correction_span_pa": float(curve.max() - curve.min()),
            },
        }
        ctx.check(
            span >= self.options.min_span,
            f"the barometer's temperature spans {span:.2f} degC < min_span "
            f"{self.options.min_span:g} degC: too little to fix a curve (log a warm-up)",
        )
        ctx.check(
            len(result.bin_t) >= 3 * (order + 1),
            f"{len(result.bin_t)} non-empty temperature bins < {3 * (order + 1)} for a "
            f"degree-{order} fit",
        )
        return StageOutput(results=results, step=step)
