"""Correction steps: what a fitted correction stage adds to the calibration chain.

A step is serialised into ``calibration.json``'s ``chain`` and read back to apply the same
correction in ``run`` and ``convert``. Every step entry has ``type`` (the stage type that made it),
``sensor`` and ``kind`` (how to apply it); linear steps also carry ``matrix`` and ``offset``.
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


@dataclass
class LinearStep(Step):
    """``corrected = matrix @ (raw - offset)`` on a 3-axis sensor (SI units).

    ``params`` keeps the stage's native parametrisation (scale, misalignment, radii...) for the
    record; only ``matrix`` and ``offset`` are used to apply.
    """

    kind: ClassVar[str] = "linear"
    type: str
    sensor: str
    matrix: np.ndarray
    offset: np.ndarray
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.matrix = np.asarray(self.matrix, dtype=np.float64).reshape(3, 3)
        self.offset = np.asarray(self.offset, dtype=np.float64).reshape(3)

    def apply_values(self, values: np.ndarray) -> np.ndarray:
        """Apply to an (n, 3) array."""
        return (np.asarray(values, dtype=np.float64) - self.offset) @ self.matrix.T

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
    def from_json(cls, entry: dict[str, Any]) -> LinearStep:
        params = {
            k: v
            for k, v in entry.items()
            if k not in ("type", "sensor", "kind", "matrix", "offset")
        }
        return cls(
            type=entry["type"],
            sensor=entry["sensor"],
            matrix=np.array(entry["matrix"], dtype=np.float64),
            offset=np.array(entry["offset"], dtype=np.float64),
            params=params,
        )


STEP_KINDS: dict[str, str] = {
    "linear": "imupipe.stages.steps:LinearStep",
    "temperature": "imupipe.stages.temperature_step:TemperatureStep",
    "g_sensitivity": "imupipe.stages.ferraris:GSensitivityStep",
}
"""Step kind -> "module:Class". A new kind of correction registers here."""


def step_class(kind: str) -> type[Step]:
    try:
        module, name = STEP_KINDS[kind].split(":")
    except KeyError:
        raise CalibrationError(
            f"calibration chain: unknown step kind '{kind}' (known: {', '.join(STEP_KINDS)})"
        ) from None
    return getattr(importlib.import_module(module), name)


def steps_from_json(chain: Sequence[dict[str, Any]], where: str = "calibration") -> list[Step]:
    """Rebuild the steps of a ``calibration.json`` chain."""
    steps: list[Step] = []
    for i, entry in enumerate(chain):
        if not isinstance(entry, dict) or "kind" not in entry:
            raise CalibrationError(f"{where}: chain[{i}] has no 'kind'")
        try:
            steps.append(step_class(entry["kind"]).from_json(entry))
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
