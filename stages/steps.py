"""Correction steps: what a fitted correction stage adds to the calibration chain.

A step is serialised into ``calibration.json``'s ``chain`` and read back to apply the same
correction in ``run`` and ``convert``. Every step entry has ``type`` (the stage type that made it),
``sensor`` and ``kind`` (how to apply it); linear steps also carry ``matrix`` and ``offset``.
A linear step written by hand as the chain format shows it (``type``, ``sensor``, ``matrix``,
``offset``, no ``kind``) is read as ``kind = "linear"``.

Reading a chain checks every entry (:func:`steps_from_json`): an object with a string ``type``, a
known ``sensor`` and ``kind``, every number finite, then the kind's own checks
(:meth:`Step.check_entry`: shapes, ranges); a failure is one
:class:`~imupipe.stages.errors.CalibrationError` line naming the entry and the field
(``chain[1].matrix: 3x3 numbers expected, got [[1, 0], [0, 1]]``).
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from imupipe.readers.table import SENSOR_COLUMNS, has_stream, replace_sensor, sensor
from imupipe.stages.errors import CalibrationError


class Step(ABC):
    """A correction that applies vectorised to a common table."""

    kind: ClassVar[str]
    type: str
    sensor: str

    @abstractmethod
    def apply(self, table: pa.Table) -> pa.Table:
        """The table with this correction applied (other columns unchanged)."""

    def apply_stream(self, batches: Iterable[pa.Table]) -> Iterator[pa.Table]:
        """Apply to a log read as consecutive batches (``iter_input``), with bounded memory.

        Yields batches that together hold every row of the input exactly once, in the same
        order, so that concatenating them equals :meth:`apply` on the whole log. The default
        applies each batch on its own (right for steps that correct each sample by itself); a
        step that needs context beyond one sample (the temperature stream around a stamp, a
        filter state) overrides this and may hold rows back until their context has arrived.
        """
        for batch in batches:
            yield self.apply(batch)

    @abstractmethod
    def to_json(self) -> dict[str, Any]:
        """The chain entry: ``type``, ``sensor``, ``kind`` and the step's parameters."""

    @classmethod
    @abstractmethod
    def from_json(cls, entry: dict[str, Any]) -> Step:
        """Inverse of :meth:`to_json`."""

    @classmethod
    def check_entry(cls, entry: dict[str, Any]) -> None:
        """The kind's own checks of a chain entry before :meth:`from_json`: raise
        :class:`EntryError` naming the field (``EntryError("matrix", "3x3 numbers expected,
        got ...")``). The default checks nothing beyond the generic checks of
        :func:`steps_from_json`."""
        return None


@dataclass
class LinearStep(Step):
    """``corrected = matrix @ (raw - offset)`` on a 3-axis sensor (SI units).

    ``params`` keeps the stage's native parametrisation (scale, misalignment, radii...) for the
    record; only ``matrix`` and ``offset`` are used to apply.
    """

    kind: ClassVar[str] = "linear"
    arrays: ClassVar[tuple[str, ...]] = ("matrix", "offset")
    """The entry's number arrays (the step's fields); its other keys are ``params``."""
    type: str
    sensor: str
    matrix: np.ndarray
    offset: np.ndarray
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.matrix = np.asarray(self.matrix, dtype=np.float64).reshape(3, 3)
        self.offset = np.asarray(self.offset, dtype=np.float64).reshape(3)

    def apply_values(self, values: np.ndarray) -> np.ndarray:
        """Apply to an (n, 3) array (see :func:`axis_products` for non-finite cells)."""
        with np.errstate(over="ignore", invalid="ignore"):  # damaged samples (Inf, 1e308)
            d = np.asarray(values, dtype=np.float64) - self.offset
        return axis_products(self.matrix, d)

    def apply(self, table: pa.Table) -> pa.Table:
        if len(SENSOR_COLUMNS[self.sensor]) != 3:
            raise ValueError(f"linear step on non-vector sensor {self.sensor}")
        from imupipe.readers.table import STREAM_OF_SENSOR

        if not has_stream(table, STREAM_OF_SENSOR[self.sensor]):
            return table
        data = sensor(table, self.sensor)
        return replace_sensor(table, self.sensor, data.rows, self.apply_values(data.values))

    def to_json(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "sensor": self.sensor,
            "kind": self.kind,
            "matrix": self.matrix.tolist(),
            "offset": self.offset.tolist(),
            **self.params,
        }

    @classmethod
    def check_entry(cls, entry: dict[str, Any]) -> None:
        if len(SENSOR_COLUMNS.get(entry["sensor"], ())) != 3:
            raise EntryError(
                "sensor", f"a linear step corrects gyro, accel or mag, not {entry['sensor']!r}"
            )
        for key, shape in (("matrix", (3, 3)), ("offset", (3,))):
            if key not in entry:
                raise EntryError(key, "missing")
            value = _numbers(entry[key], shape)
            if value is None:
                what = "3x3 numbers" if key == "matrix" else "3 numbers"
                raise EntryError(key, f"{what} expected, got {_short(entry[key])}")
            if (
                key == "matrix"
                and abs(np.linalg.det(value)) < 1e-12 * max(np.abs(value).max(), 1e-300) ** 3
            ):
                raise EntryError(key, f"singular (determinant {np.linalg.det(value):.3g})")

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> LinearStep:
        arrays = {k: np.array(entry[k], dtype=np.float64) for k in cls.arrays}
        skip = ("type", "sensor", "kind", *cls.arrays)
        params = {k: v for k, v in entry.items() if k not in skip}
        return cls(type=entry["type"], sensor=entry["sensor"], params=params, **arrays)


FLOAT_MAX = float(np.finfo(np.float64).max)
"""The largest finite float64: a finite result too large for a float is held at it."""


def axis_products(matrix: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values @ matrix.T`` for an (n, k) array, term by term, with the **non-finite rule**:

    - output axis ``i`` is the sum of ``matrix[i, j] * values[:, j]`` over the input axes ``j``
      whose coefficient is **not zero** only: a NaN or infinite input cell reaches the output
      axes that depend on it and no other (a diagonal matrix keeps every axis to itself:
      ``(nan, y, z)`` -> ``(nan, y', z')``, never ``(nan, nan, nan)``; 0 x NaN is not taken);
    - an output axis whose inputs are all finite is finite: a sum that overflows float64 is held
      at +-:data:`FLOAT_MAX` (sign kept) instead of becoming infinite.

    So NaN cells in equal NaN cells out whenever every non-finite input axis feeds only its own
    output axis. Summed term by term in a fixed order (not a matrix product, whose summation
    order BLAS may choose by the array's shape), so a sample's result does not depend on the
    batch it is corrected in: a log converted in batches equals the log corrected whole, bit for
    bit."""
    m = np.asarray(matrix, dtype=np.float64)
    d = np.asarray(values, dtype=np.float64)
    out = np.zeros((d.shape[0], m.shape[0]), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        for i in range(m.shape[0]):
            used = [j for j in range(m.shape[1]) if m[i, j] != 0.0]
            if not used:
                continue
            col = m[i, used[0]] * d[:, used[0]]
            for j in used[1:]:
                col = col + m[i, j] * d[:, j]
            bad = np.flatnonzero(~np.isfinite(col))
            if len(bad):  # finite inputs, a result past float64: held at the largest float
                blown = bad[np.isfinite(d[bad][:, used]).all(axis=1)]
                if len(blown):
                    col[blown] = _saturated(m[i, used], d[blown][:, used])
            out[:, i] = col
    return out


def _saturated(coefficients: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """+-:data:`FLOAT_MAX` for rows of finite inputs whose weighted sum overflowed: the sign of
    the sum computed at a scale where it cannot overflow."""
    scale = np.abs(rows).max(axis=1, keepdims=True)
    scale[scale == 0] = 1.0
    small = ((rows / scale) * coefficients).sum(axis=1)
    return np.where(small < 0, -FLOAT_MAX, FLOAT_MAX)


STEP_KINDS: dict[str, str] = {
    "linear": "imupipe.stages.steps:LinearStep",
    "temperature": "imupipe.stages.thermal.step:TemperatureStep",
    "thermal_matrix": "imupipe.stages.thermal.step:ThermalMatrixStep",
    "g_sensitivity": "imupipe.stages.multiposition.ferraris:GSensitivityStep",
    "baro_temperature": "imupipe.stages.thermal.baro:BaroTemperatureStep",
    "mag_current": "imupipe.stages.magnetometer.inflight:MagCurrentStep",
    "mag_throttle": "imupipe.stages.magnetometer.inflight:MagThrottleStep",
}
"""Step kind -> "module:Class". A new kind of correction registers here."""


SENSORS: tuple[str, ...] = tuple(SENSOR_COLUMNS)
"""The sensor names a step may correct."""


class EntryError(ValueError):
    """A chain entry's ``field`` is wrong (``reason``); :func:`steps_from_json` adds where."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _numbers(value: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    """``value`` as a float array of ``shape`` when it is nested lists of real numbers (not
    booleans), else None."""

    def ok(v: Any, dims: tuple[int, ...]) -> bool:
        if not dims:
            return isinstance(v, int | float) and not isinstance(v, bool)
        return isinstance(v, list) and len(v) == dims[0] and all(ok(x, dims[1:]) for x in v)

    return np.asarray(value, dtype=np.float64) if ok(value, shape) else None


MAX_MAGNITUDE = 1e12
"""The largest magnitude a calibration's real numbers may have: far beyond any scale, offset or
coefficient of an IMU correction (raw counts to SI are 1e-9 to 1e4), far below where products
with the data overflow to infinity; larger is a damaged or hostile file."""


def _non_finite(value: Any, path: str) -> str | None:
    """The path of the first real number inside ``value`` that is NaN, infinite or larger in
    magnitude than :data:`MAX_MAGNITUDE` (None when there is none)."""
    stack = [(value, path)]
    while stack:
        v, p = stack.pop()
        if isinstance(v, float) and not (np.isfinite(v) and abs(v) <= MAX_MAGNITUDE):
            return p
        if isinstance(v, dict):
            stack.extend((x, f"{p}.{k}") for k, x in reversed(list(v.items())))
        elif isinstance(v, list):
            stack.extend((x, f"{p}[{j}]") for j, x in reversed(list(enumerate(v))))
    return None


def step_class(kind: str) -> type[Step]:
    try:
        module, name = STEP_KINDS[kind].split(":")
    except KeyError:
        raise CalibrationError(
            f"calibration chain: unknown step kind '{kind}' (known: {', '.join(STEP_KINDS)})"
        ) from None
    return getattr(importlib.import_module(module), name)


def check_entry(entry: Any, i: int, where: str) -> dict[str, Any]:
    """The generic checks of chain entry ``i`` (see the module docstring); returns the entry with
    ``kind`` filled in for a hand-written linear step."""
    at = f"{where}: chain[{i}]"
    if not isinstance(entry, dict):
        raise CalibrationError(f"{at}: an object expected, got {_short(entry)}")
    if "kind" not in entry:
        if not {"type", "sensor", "matrix", "offset"} <= set(entry):
            raise CalibrationError(
                f"{at}: no 'kind', and not a linear step written as type, sensor, matrix, offset"
            )
        entry = {**entry, "kind": "linear"}
    for key in ("type", "sensor", "kind"):
        if not isinstance(entry.get(key), str):
            raise CalibrationError(f"{at}.{key}: a string expected, got {_short(entry.get(key))}")
    if entry["sensor"] not in SENSORS:
        raise CalibrationError(
            f"{at}.sensor: unknown sensor '{entry['sensor']}' (known: {', '.join(SENSORS)})"
        )
    if entry["kind"] not in STEP_KINDS:
        raise CalibrationError(
            f"{at}.kind: unknown step kind '{entry['kind']}' (known: {', '.join(STEP_KINDS)})"
        )
    bad = _non_finite(entry, f"chain[{i}]")
    if bad is not None:
        raise CalibrationError(
            f"{where}: {bad}: not a finite number of magnitude at most {MAX_MAGNITUDE:g}"
        )
    return entry


def steps_from_json(chain: Sequence[dict[str, Any]], where: str = "calibration") -> list[Step]:
    """Rebuild (and check, see the module docstring) the steps of a ``calibration.json``
    chain."""
    steps: list[Step] = []
    for i, raw in enumerate(chain):
        entry = check_entry(raw, i, where)
        cls = step_class(entry["kind"])
        try:
            cls.check_entry(entry)
            steps.append(cls.from_json(entry))
        except EntryError as exc:
            raise CalibrationError(f"{where}: chain[{i}].{exc.field}: {exc.reason}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(
                f"{where}: chain[{i}] ({entry.get('type')}) is malformed: {exc}"
            ) from None
    return steps


def apply_chain(table: pa.Table, steps: Sequence[Step]) -> pa.Table:
    """Apply every step in order."""
    for step in steps:
        table = step.apply(table)
    return table


def apply_chain_stream(batches: Iterable[pa.Table], steps: Sequence[Step]) -> Iterator[pa.Table]:
    """Apply every step in order to a stream of batches (see :meth:`Step.apply_stream`)."""
    stream: Iterable[pa.Table] = batches
    for step in steps:
        stream = step.apply_stream(stream)
    yield from stream
