"""The chamber calibrations ``imupipe survey`` compares each device's in-field thermal curve with
(``--chamber PATH``; the math is :mod:`imupipe.stages.survey.chamber`).

``PATH`` is a calibration file (``calibration.json`` of ``imupipe run``, or any file
``imupipe convert`` reads) or a folder of them:

- a file: its steps are every vehicle's chamber calibration;
- a folder: ``PATH/<vehicle>.json`` and ``PATH/<vehicle>/*.json`` are the chamber calibrations
  of the vehicle named (the name of the folder holding its logs, the dataset's ``vehicle``).

Within a vehicle, a chain entry is of the device whose ``topic`` it names (its ``device`` record,
else its ``fitted_on``: the topic of the chamber log); an entry that names no topic (a CSV chamber
log, a step imported from another tool) is of every device of the vehicle. A device's chamber
curve is made of its gyro and accelerometer thermal steps (``temperature``, ``thermal_matrix``)
and the linear steps of the same sensors; a sensor without a thermal step has none.

Without ``--chamber``, the thermal steps of ``--calibration`` (when it holds any) are every
device's chamber curve, by the same rule. The chamber files are read by the driver only (the
dataset's ``chamber_*`` columns, :func:`chamber_columns`, and the fleet view): giving, changing or
dropping them never surveys a log again.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.calibration_file import device, load_calibration
from imupipe.pipeline.errors import ConfigError
from imupipe.stages.steps import Step
from imupipe.stages.survey.chamber import ChamberModel, chamber_model, predicted
from imupipe.stages.thermal.step import WARN_MARGIN

Chambers = dict[str | None, list[tuple[str, dict[str, Any], list[Step]]]]
"""vehicle (None: every vehicle) -> (file, document, steps) of its chamber calibrations."""


def _has_thermal(source: str, doc: dict[str, Any], steps: list[Step]) -> bool:
    return chamber_model(source, steps, doc["chain"]) is not None


def load_chambers(path: Path) -> Chambers:
    """Read ``--chamber PATH`` (module docstring); one :class:`ConfigError` line when the path
    is missing, a file is not a calibration, or no file holds a gyro or accelerometer thermal
    step."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"--chamber {path}: no such file or folder")
    found: Chambers = {}
    if path.is_file():
        doc, steps = load_calibration(path)
        found[None] = [(str(path), doc, steps)]
    else:
        files = [(f.stem, f) for f in sorted(path.glob("*.json"))]
        files += [(f.parent.name, f) for f in sorted(path.glob("*/*.json"))]
        for vehicle, f in files:
            doc, steps = load_calibration(f)
            found.setdefault(vehicle, []).append((str(f), doc, steps))
    if not any(_has_thermal(*item) for items in found.values() for item in items):
        raise ConfigError(
            f"--chamber {path}: no temperature-compensation step (temperature, thermal_matrix) "
            "for a gyro or an accelerometer"
        )
    return found


def from_calibration(path: Path, doc: dict[str, Any], steps: list[Step]) -> Chambers:
    """The chamber curves of ``--calibration`` (every vehicle's), empty without a thermal step."""
    return {None: [(str(path), doc, steps)]} if _has_thermal(str(path), doc, steps) else {}


def _entry_topic(entry: Mapping[str, Any], step: Step) -> str | None:
    dev = entry.get("device")
    named = dict(dev) if isinstance(dev, Mapping) else device(entry.get("fitted_on"), step.sensor)
    topic = named.get("topic")
    return None if topic is None else str(topic)


def device_model(chambers: Chambers, vehicle: str, topic: str) -> ChamberModel | None:
    """The chamber model of the device ``vehicle``'s ``topic`` (module docstring), or None."""
    items = chambers.get(vehicle) or chambers.get(None) or []
    for source, doc, steps in items:
        chosen = [
            (s, e)
            for s, e in zip(steps, doc["chain"], strict=True)
            if _entry_topic(e, s) in (None, topic)
        ]
        model = chamber_model(source, [s for s, _ in chosen], [e for _, e in chosen])
        if model is not None:
            return model
    return None


CHAMBER_COLUMNS = (
    ("chamber_gyro_bias_x", "rad/s"),
    ("chamber_gyro_bias_y", "rad/s"),
    ("chamber_gyro_bias_z", "rad/s"),
    ("chamber_accel_norm_error", "m/s^2"),
)
"""The dataset's chamber columns (name, unit): the chamber's figure at each still period."""


def chamber_columns(table: pa.Table, chambers: Chambers) -> pa.Table:
    """``table`` (the survey dataset) with the chamber curve at each still period: the columns of
    :data:`CHAMBER_COLUMNS` (the chamber's gyro zero-rate output and ``|a| - g`` at the period's
    temperature and direction: :func:`imupipe.stages.survey.chamber.predicted`; NaN for a device
    without a chamber curve) and ``chamber_outside`` (the period lies more than 0.5 degC beyond
    the chamber's calibrated range, where its curve is extrapolated; null without a chamber)."""

    def col(name: str) -> np.ndarray:
        return table.column(name).to_numpy(zero_copy_only=False)

    n = table.num_rows
    out = {name: np.full(n, np.nan) for name, _ in CHAMBER_COLUMNS}
    outside, known = np.zeros(n, bool), np.zeros(n, bool)
    names, index = np.unique(col("device_id").astype(str), return_inverse=True)
    vehicle, topic = col("vehicle").astype(str), col("topic").astype(str)
    temp = col("temperature").astype(np.float64)
    accel = np.column_stack([col(f"accel_mean_{a}").astype(np.float64) for a in "xyz"])
    for i in range(len(names)):
        rows = np.flatnonzero(index == i)
        model = device_model(chambers, vehicle[rows[0]], topic[rows[0]])
        if model is None:
            continue
        for figure, values in predicted(model, temp[rows], accel[rows]).items():
            out["chamber_" + figure][rows] = values
        lo, hi = model.ranges["gyro" if "gyro" in model.ranges else "accel"]
        t = temp[rows]
        outside[rows] = (t < lo - WARN_MARGIN) | (t > hi + WARN_MARGIN)
        known[rows] = True
    for name, unit in CHAMBER_COLUMNS:
        field = pa.field(name, pa.float64(), metadata={"unit": unit})
        table = table.append_column(field, pa.array(out[name], pa.float64()))
    return table.append_column(
        pa.field("chamber_outside", pa.bool_()), pa.array(outside, pa.bool_(), mask=~known)
    )
