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
device's chamber curve, by the same rule. The chamber files are read by the fleet view only:
giving, changing or dropping them never surveys a log again.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from imupipe.pipeline.calibration_file import device, load_calibration
from imupipe.pipeline.errors import ConfigError
from imupipe.stages.steps import Step
from imupipe.stages.survey.chamber import ChamberModel, chamber_model

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
