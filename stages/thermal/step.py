"""Corrections driven by the temperature at every IMU sample (applied by ``run`` and ``convert``),
on a whole log or batch by batch with the same result bit for bit.

:class:`ThermalStep` is the base: it reads the temperature stream (and the ambient temperature
when the model uses it) through a :class:`~imupipe.stages.thermal.track.Track`, which gives each
IMU sample its temperature, the temperature's rate and the sensing element's lagged temperature,
and holds rows back until those are final (:meth:`ThermalStep.apply_stream`). A subclass says
what it needs (:meth:`ThermalStep.track_spec`) and how it corrects (:meth:`ThermalStep.correct`).

:class:`TemperatureStep` (kind ``temperature``): ``corrected = raw - f(T, dT [, Ta, dTa, Ts,
dTs])`` per axis, divided by a scale factor ``sf(T)`` on turned gyro axes; the models, their units
and references are described in :mod:`imupipe.stages.thermal.temperature` and
:mod:`imupipe.stages.thermal.models`. Temperatures (T, Ta, Ts) are clamped to the fitted range;
rates are extrapolated; one warning per log counts the samples outside.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from imupipe.readers.table import (
    STREAM_OF_SENSOR,
    has_stream,
    metadata,
    replace_sensor,
    sensor,
    stream_mask,
    to_numpy,
    usable,
)
from imupipe.stages.errors import CalibrationError
from imupipe.stages.steps import Step
from imupipe.stages.thermal import models as tm
from imupipe.stages.thermal.track import Blocking, Track, TrackSpec, Variables

WARN_MARGIN = 0.5
"""degC: temperatures further than this outside the fitted range are warned about (all are
clamped); rates more than 10 % of their fitted span outside it are warned about (not clamped:
a rate term extrapolates linearly)."""
AXES = ("x", "y", "z")
CHANNEL_COLUMN = {"T": "temperature", "Ta": "ambient_temperature"}


def temperature_samples(table: pa.Table, column: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, values) of the usable samples (:func:`~imupipe.readers.table.usable`: finite,
    not a damaged 1e308) of ``temperature`` or ``ambient_temperature``."""
    if column not in table.column_names or len(table) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    if column == "temperature":
        if not has_stream(table, "temperature"):
            return np.zeros(0, np.int64), np.zeros(0)
        data = sensor(table, "temperature")
        t, v = data.t_ns, data.values[:, 0]
    else:
        t = to_numpy(table.column("t_ns"))
        v = to_numpy(table.column(column)).astype(np.float64)
    ok = usable(v)
    return t[ok], v[ok]


def imu_stamps(table: pa.Table, stream: str = "imu") -> tuple[np.ndarray, np.ndarray]:
    """(mask of the rows of ``stream``, the IMU's by default, their stamps)."""
    if len(table) == 0 or not has_stream(table, stream):
        return np.zeros(len(table), dtype=bool), np.zeros(0, np.int64)
    mask = stream_mask(table, stream)
    return mask, to_numpy(table.column("t_ns"))[mask]


def take_variables(v: Variables, start: int, stop: int) -> Variables:
    return Variables(
        *(getattr(v, k)[start:stop] for k in Variables.__dataclass_fields__)  # type: ignore[arg-type]
    )


@dataclass
class RangeStats:
    """Samples outside the fitted range of each variable, over one application."""

    total: int = 0
    outside: dict[str, int] = field(default_factory=dict)
    seen: dict[str, list[float]] = field(default_factory=dict)

    def add(self, name: str, values: np.ndarray, far: int) -> None:
        if not len(values):
            return
        lo, hi = float(values.min()), float(values.max())
        old = self.seen.get(name, [lo, hi])
        self.seen[name] = [min(old[0], lo), max(old[1], hi)]
        self.outside[name] = self.outside.get(name, 0) + far


class ThermalStep(Step):
    """A correction of ``sensor`` from the temperature at each sample (see the module docstring).

    Subclasses are dataclasses with ``type``, ``sensor``, ``quiet`` and ``warnings`` fields."""

    quiet: bool
    warnings: list[str]

    def track_spec(self) -> TrackSpec:
        """The temperatures this correction needs at each sample."""
        raise NotImplementedError

    def correct(self, values: np.ndarray, variables: Variables, stats: RangeStats) -> np.ndarray:
        """``values`` (n, 3) corrected, given the samples' :class:`Variables`."""
        raise NotImplementedError

    def range_warning(self, stats: RangeStats) -> str | None:
        """The one warning about samples outside the fitted ranges, or None."""
        return None

    @property
    def stream(self) -> str:
        """The stream whose rows this step corrects (``imu``; ``mag`` for a magnetometer)."""
        return STREAM_OF_SENSOR.get(self.sensor, "imu")

    def apply(self, table: pa.Table) -> pa.Table:
        if not has_stream(table, self.stream):
            return table
        source = metadata(table).get("source", "the log")
        missing = [
            column
            for column in self.track_spec().channels
            if not len(temperature_samples(table, column)[0])
        ]
        if missing:
            raise self._missing(source, missing)
        parts = list(self.apply_stream([table]))
        return parts[0] if len(parts) == 1 else pa.concat_tables(parts)

    def apply_stream(self, batches: Iterable[pa.Table]) -> Iterator[pa.Table]:
        """Rows are held until the temperature after them (and, for rates and the lag, the
        blocks around them) has arrived; every row is yielded once, in order, and the values
        equal :meth:`apply` on the whole log bit for bit. Memory: the rows held (about three
        blocks and the time to the next temperature sample) and the batch."""
        spec = self.track_spec()
        track = Track(spec)
        stats = RangeStats()
        pending: list[tuple[pa.Table, np.ndarray]] = []
        source: str | None = None
        first: pa.Table | None = None
        yielded = False
        for batch in batches:
            if first is None:
                first = batch
            if source is None and len(batch):
                source = metadata(batch).get("source", "the log")
            mask, stamps = imu_stamps(batch, self.stream)
            temps = [temperature_samples(batch, column) for column in spec.channels]
            ready = track.push(stamps, temps)
            pending.append((batch, mask))
            for part in self._release(pending, ready, stats):
                yielded = True
                yield part
        ready = track.finish()
        if track.missing_channels() and len(track.t):
            raise self._missing(source or "the log", track.missing_channels())
        for part in self._release(pending, ready, stats):
            yielded = True
            yield part
        if not yielded and first is not None:
            yield first
        message = self.range_warning(stats)
        if message:  # named by its log: run and convert correct several at once
            self._warn(f"{source}: {message}" if source else message)

    def _missing(self, source: str, columns: list[str]) -> CalibrationError:
        what = " and ".join(
            "temperature samples" if c == "temperature" else f"{c} column" for c in columns
        )
        return CalibrationError(
            f"{source}: no {what}; the {self.sensor} temperature correction needs "
            f"{'them' if len(columns) > 1 else 'it'}"
        )

    def _release(
        self, pending: list[tuple[pa.Table, np.ndarray]], ready: Variables, stats: RangeStats
    ) -> Iterator[pa.Table]:
        """Yield the pending rows before the first IMU row not yet ready, corrected."""
        need, used = len(ready), 0
        while pending:
            table, mask = pending[0]
            count = int(np.count_nonzero(mask))
            if count <= need:
                pending.pop(0)
                part, part_count = table, count
            else:
                cut = int(np.flatnonzero(mask)[need])
                part, part_count = table.slice(0, cut), need
                pending[0] = (table.slice(cut), mask[cut:])
            if len(part):
                if part_count:
                    data = sensor(part, self.sensor)
                    v = take_variables(ready, used, used + part_count)
                    part = replace_sensor(
                        part, self.sensor, data.rows, self.correct(data.values, v, stats)
                    )
                yield part
            need -= part_count
            used += part_count
            if count > part_count:
                break

    def _warn(self, message: str) -> None:
        """Print a warning once per step (the chain is applied to the same log several times)."""
        if message not in self.warnings:
            self.warnings.append(message)
            if not self.quiet:
                print(f"imupipe: warning: [{self.type} {self.sensor}] {message}", file=sys.stderr)


@dataclass
class TemperatureStep(ThermalStep):
    """``corrected = raw - f(T, dT [, Ta, dTa, Ts, dTs])`` per axis; see the module docstring.

    ``axes`` holds, per axis x, y, z, ``{"terms": [...], "coefficients": [...]}``; ``ranges``
    the fitted range of each variable (absolute degC for T, Ta and Ts, degC/s for the rates),
    used to clamp; ``knots`` (absolute degC) the piecewise model's segment ends; ``lag_s`` the
    time constant of the sensing element's lag (``Ts``, ``dTs``), None without one.
    """

    kind: ClassVar[str] = "temperature"
    type: str
    sensor: str
    model: str
    tref: float
    window: int | None
    window_s: float | None
    axes: list[dict[str, Any]]
    ranges: dict[str, list[float]]
    knots: list[float] | None = None
    lag_s: float | None = None
    scale: dict[str, dict[str, Any]] | None = None
    """Gyro scale factor against temperature per axis that was turned (turntable runs): axis ->
    ``{"terms", "coefficients"}`` of ``sf(T)``; ``corrected = (raw - f) / sf(T)`` there."""
    params: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    quiet: bool = False
    """Collect warnings without printing them (``run --quiet``); not part of the chain entry."""

    # -- what the correction needs -----------------------------------------------------------
    def used_variables(self) -> set[str]:
        terms = [t for ax in self.axes for t in ax["terms"]]
        terms += [t for m in (self.scale or {}).values() for t in m["terms"]]
        used = tm.term_variables(terms)
        if any(name.startswith("hat") for t in terms for name, _ in tm.parse_term(t)):
            used.add("T")
        return used | {"T"}

    def track_spec(self) -> TrackSpec:
        used = self.used_variables()
        channels = ("temperature", "ambient_temperature") if used & {"Ta", "dTa"} else None
        blocking = None
        if used & {"dT", "dTa", "Ts", "dTs"}:
            blocking = Blocking(self.window, None if self.window is not None else self.window_s)
        return TrackSpec(
            channels=channels or ("temperature",),
            blocking=blocking,
            lag_s=self.lag_s if used & {"Ts", "dTs"} else None,
        )

    def model_variables(self, v: Variables, stats: RangeStats | None = None) -> dict[str, Any]:
        """The model's variables at the samples of ``v``: temperatures clamped to the fitted
        range and made relative to Tref, rates as they are (counted in ``stats`` when outside)."""
        used = self.used_variables()
        out: dict[str, np.ndarray] = {"T": v.T[:, 0]}
        if "dT" in used:
            out["dT"] = v.rate[:, 0]
        if "Ta" in used:
            out["Ta"] = v.T[:, 1]
        if "dTa" in used:
            out["dTa"] = v.rate[:, 1]
        if "Ts" in used:
            out["Ts"] = v.lagged
        if "dTs" in used:
            out["dTs"] = v.lag_rate
        for name, values in out.items():
            lo, hi = self.ranges[name]
            if name in tm.TEMPERATURES:
                far = (values < lo - WARN_MARGIN) | (values > hi + WARN_MARGIN)
                out[name] = np.clip(values, lo, hi) - self.tref
            else:
                pad = 0.1 * (hi - lo)
                far = (values < lo - pad) | (values > hi + pad)
            if stats is not None:
                stats.add(name, values, int(np.count_nonzero(far)))
        if stats is not None:
            stats.total += len(v)
        return out

    def range_warning(self, stats: RangeStats) -> str | None:
        notes = []
        for name, far in stats.outside.items():
            if far:
                lo, hi = self.ranges[name]
                seen = stats.seen[name]
                if name in tm.TEMPERATURES:
                    what, unit, k = f"{name} clamped to", "degC", 1.0
                else:  # rates in degC/min, as the summary and the docs give them
                    what, unit, k = f"{name} (temperature rate) extrapolated beyond", "degC/min", 60
                notes.append(
                    f"{what} the fitted range {lo * k:.3g} .. {hi * k:.3g} {unit} at {far} of "
                    f"{stats.total} samples ({100 * far / max(stats.total, 1):.0f} %; seen "
                    f"{seen[0] * k:.3g} .. {seen[1] * k:.3g} {unit})"
                )
        return "; ".join(notes) or None

    # -- the model ---------------------------------------------------------------------------
    def _knots(self) -> np.ndarray | None:
        return None if self.knots is None else np.asarray(self.knots) - self.tref

    def bias(self, variables: dict[str, np.ndarray]) -> np.ndarray:
        """(n, 3) modelled bias at the given variables (temperatures relative to Tref)."""
        return np.column_stack(
            [
                tm.evaluate(ax["terms"], ax["coefficients"], variables, self._knots())
                for ax in self.axes
            ]
        )

    def scale_factor(self, model: dict[str, Any], variables: dict[str, np.ndarray]) -> np.ndarray:
        """sf(T) of one axis at the given variables."""
        return tm.evaluate(model["terms"], model["coefficients"], variables, self._knots())

    def correct(self, values: np.ndarray, variables: Variables, stats: RangeStats) -> np.ndarray:
        model = self.model_variables(variables, stats)
        corrected = values - self.bias(model)
        for axis, sf in (self.scale or {}).items():
            i = AXES.index(axis)
            corrected[:, i] /= self.scale_factor(sf, model)
        return corrected

    # -- the chain entry ---------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "sensor": self.sensor,
            "kind": self.kind,
            "model": self.model,
            "tref": self.tref,
            "window": self.window,
            "window_s": self.window_s,
            "lag_s": self.lag_s,
            "ranges": self.ranges,
            "knots": self.knots,
            "scale": None
            if self.scale is None
            else {
                axis: {
                    "terms": list(m["terms"]),
                    "coefficients": [float(c) for c in m["coefficients"]],
                }
                for axis, m in self.scale.items()
            },
            "axes": [
                {"terms": list(ax["terms"]), "coefficients": [float(c) for c in ax["coefficients"]]}
                for ax in self.axes
            ],
            **self.params,
        }

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> TemperatureStep:
        known = {"type", "sensor", "kind", "model", "tref", "window", "window_s", "ranges"}
        known |= {"knots", "axes", "scale", "lag_s"}
        axes = entry["axes"]
        if len(axes) != 3:
            raise ValueError("'axes' must hold 3 entries (x, y, z)")
        for ax in axes:
            for term in ax["terms"]:
                tm.parse_term(term)
            if len(ax["terms"]) != len(ax["coefficients"]):
                raise ValueError("terms and coefficients differ in length")
        step = cls(
            type=entry["type"],
            sensor=entry["sensor"],
            model=entry["model"],
            tref=float(entry["tref"]),
            window=entry.get("window"),
            window_s=entry.get("window_s"),
            axes=[
                {"terms": list(ax["terms"]), "coefficients": np.asarray(ax["coefficients"], float)}
                for ax in axes
            ],
            ranges={k: [float(v[0]), float(v[1])] for k, v in entry["ranges"].items()},
            knots=entry.get("knots"),
            lag_s=None if entry.get("lag_s") is None else float(entry["lag_s"]),
            scale=None
            if entry.get("scale") is None
            else {
                axis: {
                    "terms": list(m["terms"]),
                    "coefficients": np.asarray(m["coefficients"], float),
                }
                for axis, m in entry["scale"].items()
            },
            params={k: v for k, v in entry.items() if k not in known},
        )
        missing = step.used_variables() - set(step.ranges)
        if missing:
            raise ValueError(f"'ranges' lacks {', '.join(sorted(missing))}")
        if step.used_variables() & {"Ts", "dTs"} and not (step.lag_s and step.lag_s > 0):
            raise ValueError("terms in Ts or dTs need 'lag_s' > 0")
        if step.track_spec().blocking is None and step.used_variables() - {"T"}:
            raise ValueError("rate terms need 'window' or 'window_s'")
        return step


MATRIX_FORMS: dict[str, tuple[int, str]] = {
    "accel": (3, "a = diag(s) K (raw - b), K = [[1, -yz, zy], [0, 1, -zx], [0, 0, 1]]"),
    "gyro": (6, "w = T diag(s) (raw - b), T = [[1, -yz, zy], [xz, 1, -zx], [-xy, yx, 1]]"),
}
"""Per form: the number of misalignment angles and the model (imupipe's accelerometer and
gyroscope calibration models: :mod:`imupipe.stages.multiposition.accel_models`, :mod:`imupipe.stages.multiposition.gyro_models`)."""


def apply_matrix_form(
    form: str, raw: np.ndarray, scale: np.ndarray, angles: np.ndarray, bias: np.ndarray
) -> np.ndarray:
    """The calibration model ``form`` with per-sample parameters ((n, 3), (n, 3 or 6), (n, 3)),
    elementwise (no per-sample matrix)."""
    v = raw - bias
    if form == "accel":
        yz, zy, zx = angles.T
        u = np.column_stack(
            [v[:, 0] - yz * v[:, 1] + zy * v[:, 2], v[:, 1] - zx * v[:, 2], v[:, 2]]
        )
        return scale * u
    yz, zy, zx, xz, xy, yx = angles.T
    w = scale * v
    return np.column_stack(
        [
            w[:, 0] - yz * w[:, 1] + zy * w[:, 2],
            xz * w[:, 0] + w[:, 1] - zx * w[:, 2],
            -xy * w[:, 0] + yx * w[:, 1] + w[:, 2],
        ]
    )


@dataclass
class ThermalMatrixStep(ThermalStep):
    """A calibration whose parameters are polynomials in the temperature (the soak method):
    ``parameters`` maps ``scale`` (3), ``misalignment`` (3 for ``form = "accel"``, 6 for
    ``"gyro"``, in the order of :data:`MATRIX_FORMS`) and ``bias`` (3) to one
    ``{"terms", "coefficients"}`` per component, in ``T`` = temperature - ``tref`` (degC); a
    missing quantity is 1 (scale) or 0. The temperature is clamped to ``range`` (the soaks')."""

    kind: ClassVar[str] = "thermal_matrix"
    type: str
    sensor: str
    form: str
    tref: float
    range: list[float]
    parameters: dict[str, list[dict[str, Any]]]
    params: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    quiet: bool = False

    def track_spec(self) -> TrackSpec:
        return TrackSpec()

    def values_at(self, temp: np.ndarray) -> dict[str, np.ndarray]:
        """Each quantity (n, k) at absolute temperatures ``temp`` (clamped to ``range``)."""
        x = {"T": np.clip(temp, *self.range) - self.tref}
        size = {"scale": 3, "misalignment": MATRIX_FORMS[self.form][0], "bias": 3}
        out = {}
        for name, k in size.items():
            comps = self.parameters.get(name)
            if comps is None:
                out[name] = np.full((len(temp), k), 1.0 if name == "scale" else 0.0)
            else:
                out[name] = np.column_stack(
                    [tm.evaluate(c["terms"], c["coefficients"], x) for c in comps]
                )
        return out

    def correct(self, values: np.ndarray, variables: Variables, stats: RangeStats) -> np.ndarray:
        temp = variables.T[:, 0]
        lo, hi = self.range
        stats.add(
            "T", temp, int(np.count_nonzero((temp < lo - WARN_MARGIN) | (temp > hi + WARN_MARGIN)))
        )
        stats.total += len(temp)
        p = self.values_at(temp)
        return apply_matrix_form(self.form, values, p["scale"], p["misalignment"], p["bias"])

    def range_warning(self, stats: RangeStats) -> str | None:
        far = stats.outside.get("T", 0)
        if not far:
            return None
        seen = stats.seen["T"]
        return (
            f"T clamped to the soaks' range [{self.range[0]:.4g}, {self.range[1]:.4g}] at {far} "
            f"of {stats.total} samples (seen {seen[0]:.4g}..{seen[1]:.4g})"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "sensor": self.sensor,
            "kind": self.kind,
            "form": self.form,
            "model": MATRIX_FORMS[self.form][1],
            "tref": self.tref,
            "range": list(self.range),
            "parameters": {
                name: [
                    {
                        "terms": list(c["terms"]),
                        "coefficients": [float(v) for v in c["coefficients"]],
                    }
                    for c in comps
                ]
                for name, comps in self.parameters.items()
            },
            **self.params,
        }

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> ThermalMatrixStep:
        known = {"type", "sensor", "kind", "form", "model", "tref", "range", "parameters"}
        form = entry["form"]
        if form not in MATRIX_FORMS:
            raise ValueError(f"unknown form '{form}' (known: {', '.join(MATRIX_FORMS)})")
        size = {"scale": 3, "misalignment": MATRIX_FORMS[form][0], "bias": 3}
        parameters = {}
        for name, comps in entry["parameters"].items():
            if name not in size or len(comps) != size[name]:
                raise ValueError(f"parameters.{name}: expected {size.get(name, 'no')} components")
            for c in comps:
                if tm.term_variables(c["terms"]) - {"T"} or len(c["terms"]) != len(
                    c["coefficients"]
                ):
                    raise ValueError(f"parameters.{name}: terms in T with one coefficient each")
            parameters[name] = [
                {"terms": list(c["terms"]), "coefficients": np.asarray(c["coefficients"], float)}
                for c in comps
            ]
        lo, hi = (float(v) for v in entry["range"])
        return cls(
            type=entry["type"],
            sensor=entry["sensor"],
            form=form,
            tref=float(entry["tref"]),
            range=[lo, hi],
            parameters=parameters,
            params={k: v for k, v in entry.items() if k not in known},
        )


@dataclass
class Prepared:
    """Complete blocks of one input: centres ``t_ns``, ``bias`` (m, 3) = means - reference,
    ``variables`` (absolute ``T``, ``dT``, maybe ``Ta``, ``dTa``), ``direction`` (+1 heating,
    -1 cooling, 0 soak), sample ``counts``; ``centre_all``/``temp_all`` every block of the log
    (the lag runs over them) and ``keep`` the indices of the complete ones."""

    t_ns: np.ndarray
    bias: np.ndarray
    variables: dict[str, np.ndarray]
    direction: np.ndarray
    reference: np.ndarray
    counts: np.ndarray
    centre_all: np.ndarray
    temp_all: np.ndarray
    keep: np.ndarray
    pairs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    """Turntable runs per turned axis: (temperature degC, scale factor) of each +/-rate pair."""
    moving: int = 0
    """Complete blocks left out because less than half their samples were still."""
    accel: np.ndarray | None = None
    """(m, 3) mean specific force of each kept block's still samples (m/s^2), when the log has
    an accelerometer: the orientation of the IMU."""
    noise: np.ndarray | None = None
    """(m, 3) the variance of each block mean from noise (SI^2; NaN where a block's halves
    cannot be compared)."""
    t_range: tuple[float, float] | None = None
    """degC: the lowest and highest temperature of the samples that entered the kept blocks
    (the logged range of raw samples, as PX4's ``process_sensor_caldata.py`` takes its
    ``TMIN``/``TMAX``); the block means lie inside it."""
