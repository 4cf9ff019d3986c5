"""``calibration.json``: what a calibration records about where it was fitted, and reading one
back with every field checked.

**Provenance.** Every chain entry (and every stage's results) carries ``fitted_on``, taken from
the common table the stage fitted on (the readers put ``source``, ``format``, ``topics``,
``frame_id`` and, for a ULog, ``instance`` and ``device_id`` in its metadata)::

    {"input": "static", "path": "logs/static.mcap", "format": "mcap",
     "topics": {"imu": "/imu/data"}, "frame_id": {"imu": "imu_link"},
     "instance": {"imu": 1}, "device_id": {"imu": 3670050},
     "t_start_ns": ..., "t_end_ns": ..., "rate_hz": {"imu": 199.9},
     "px4": {"calibrated": {"imu": false}, "parameters": {"CAL_GYRO1_XOFF": ...}}}

``instance``, ``device_id`` and ``px4`` appear only where the log has them (PX4 ULog; a
DataFlash log's parameters under ``ardupilot.parameters``);
``px4.parameters`` keeps the log's ``CAL_*``/``TC_*``/``SENS_BOARD_*`` values, which the PX4
export needs when the data were already corrected by PX4. A step imported from another tool
(``imupipe import``) has ``{"input": null, "path": <its file>, "format": <the tool>}``.

**Device.** Every chain entry also names the device it corrects (:func:`device`), taken from
``fitted_on`` for the step's stream: ``{"stream": "imu", "topic": "sensor_gyro_1",
"instance": 1, "device_id": 3670050, "frame_id": ...}`` (keys present where known). Two
entries are of different devices when both name a ``device_id`` and they differ, else when
both name an ``instance`` and they differ, else when both come from message logs (MCAP, ROS 1,
ROS 2: the topic is their only identity, a PX4 or ArduPilot topic is not) and name different
topics (:func:`same_device`): two IMUs of one bag on ``/imu0/data`` and ``/imu1/data`` are two
devices. An entry that names none (CSV, a step imported from another tool) may be of any
device and applies to every one.
Steps of one device compose; a step is never applied to another device's data
(:class:`OnDevice`): in ``run``, a stage on ``sensor_gyro_1`` fits on data corrected only by
``sensor_gyro_1``'s earlier steps.

**Loading** (:func:`load_calibration`): the file must be under :data:`MAX_BYTES`, UTF-8 JSON
nested at most :data:`MAX_DEPTH` deep, an object with a ``chain`` list; every chain entry is
checked by :func:`imupipe.stages.steps.steps_from_json` (known sensor and kind, finite numbers,
3x3 ``matrix`` and 3 ``offset`` for linear steps, which may be written by hand without
``kind``) and ``fitted_on``, when present, must be an object. Any failure is one
:class:`~imupipe.stages.errors.CalibrationError` line naming the file, the entry and the field.
"""

from __future__ import annotations

import json
import math
import stat
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from itertools import chain as chained
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import to_numpy
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import (
    STREAM_OF_SENSOR,
    STREAMS,
    metadata,
    sensor_mask,
    split_imu,
    stream_mask,
)
from imupipe.stages.errors import CalibrationError
from imupipe.stages.steps import Step, steps_from_json

MAX_BYTES = 64 * 1024 * 1024
"""A calibration larger than this is refused (a real one is a few kB to a few MB)."""
MAX_DEPTH = 64
"""Deepest JSON nesting accepted (a calibration nests about 6 deep)."""
PROVENANCE_KEYS = ("topics", "frame_id", "instance", "device_id", "px4", "ardupilot")
"""Table metadata keys copied into ``fitted_on`` when present."""
DEVICE_KEYS = (("topics", "topic"), ("instance", "instance"), ("device_id", "device_id"))
"""(``fitted_on`` key, device key): the stream's value of each names the device."""


def fitted_on(input_name: str, spec: InputSpec, table: pa.Table) -> dict[str, Any]:
    """Where a stage fitted: the input's name, file and format, its topics, frames and sensor
    instances, the time span of the table and each stream's mean rate (see the module
    docstring)."""
    meta = metadata(table)
    out: dict[str, Any] = {
        "input": input_name,
        "path": str(spec.path),
        "format": meta.get("format", "csv"),
    }
    for key in PROVENANCE_KEYS:
        if meta.get(key):
            out[key] = meta[key]
    t = to_numpy(table.column("t_ns"))
    if len(t):
        out["t_start_ns"], out["t_end_ns"] = int(t.min()), int(t.max())
    rates: dict[str, float] = {}
    apart = ("gyro", "accel") if len(t) and split_imu(table) else ()  # each sensor's own rate
    for stream in STREAMS + apart:
        if len(t) < 2:
            break
        mask = sensor_mask(table, stream) if stream in apart else stream_mask(table, stream)
        n = int(np.count_nonzero(mask))
        if n == len(t):  # every row (an IMU-only log): the table's span, without a copy of t
            first, last = out["t_start_ns"], out["t_end_ns"]
        elif n > 1:
            stamps = t[mask]
            first, last = int(stamps.min()), int(stamps.max())
        else:
            continue
        span = (last - first) * 1e-9
        if span > 0:
            rates[stream] = (n - 1) / span
    out["rate_hz"] = rates
    return out


def device(where: Mapping[str, Any] | None, sensor: str) -> dict[str, Any]:
    """The device ``sensor`` was fitted on, from a ``fitted_on`` record or a table's metadata
    (same keys): ``stream`` and, where known, ``topic``, ``instance``, ``device_id`` (a
    per-sensor value, ``device_id.gyro``, wins over the stream's), ``frame_id`` and
    ``format``."""
    stream = STREAM_OF_SENSOR[sensor]
    where = where or {}
    out: dict[str, Any] = {"stream": stream}
    for key, name in (*DEVICE_KEYS, ("frame_id", "frame_id")):
        per = where.get(key)
        if isinstance(per, Mapping):
            value = per.get(sensor, per.get(stream))
            if value is not None:
                out[name] = value
    if where.get("format"):
        out["format"] = where["format"]
    return out


UNNAMED: tuple[str] = ("unnamed",)
"""The key of an entry that names no device (it may be any)."""
FLIGHT_LOG_FORMATS = ("ulog", "dataflash")
"""Formats whose topics are not devices (``sensor_combined`` fuses several IMUs; their devices
are named by ``instance`` and ``device_id``)."""


def _topic(dev: Mapping[str, Any]) -> str | None:
    """The topic that names a message log's device (MCAP, ROS 1, ROS 2): None for a device with
    a ``device_id`` or ``instance``, for a flight log's topic, and where no topic is known."""
    if dev.get("device_id") is not None or dev.get("instance") is not None:
        return None
    if dev.get("format") in FLIGHT_LOG_FORMATS or not dev.get("topic"):
        return None
    return str(dev["topic"])


def device_key(dev: Mapping[str, Any]) -> tuple[Any, ...]:
    """What tells devices apart (module docstring): ``("device_id", id)``, else
    ``("instance", n)``, else a message log's ``("topic", name)``, else :data:`UNNAMED`."""
    if dev.get("device_id") is not None:
        return ("device_id", int(dev["device_id"]))
    if dev.get("instance") is not None:
        return ("instance", int(dev["instance"]))
    topic = _topic(dev)
    return UNNAMED if topic is None else ("topic", topic)


def same_device(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Whether two devices may be the same: by ``device_id`` when both name one, else by
    ``instance`` when both name one, else by a message log's topic when both name one, else
    true (a device not named may be any)."""
    if a.get("device_id") is not None and b.get("device_id") is not None:
        return int(a["device_id"]) == int(b["device_id"])
    if a.get("instance") is not None and b.get("instance") is not None:
        return int(a["instance"]) == int(b["instance"])
    ta, tb = _topic(a), _topic(b)
    if ta is not None and tb is not None:
        return ta == tb
    return True


@dataclass
class OnDevice(Step):
    """``step``, applied only to data of its own ``device`` (see the module docstring); its
    chain entry is the step's own (with ``device`` added). ``lenient``: data of a device the
    calibration does not know at all (another board's log) are corrected anyway, as before
    devices were recorded (``convert`` of a one-device calibration: the provenance check
    reports the difference)."""

    kind: ClassVar[str] = "on_device"
    step: Step
    device: dict[str, Any]
    lenient: bool = False
    known: tuple[dict[str, Any], ...] = ()

    @property
    def type(self) -> str:  # type: ignore[override]
        return self.step.type

    @property
    def sensor(self) -> str:  # type: ignore[override]
        return self.step.sensor

    def applies(self, table: pa.Table) -> bool:
        theirs = device(metadata(table), self.sensor)
        if same_device(self.device, theirs):
            return True
        return self.lenient and not any(same_device(k, theirs) for k in self.known)

    def apply(self, table: pa.Table) -> pa.Table:
        return self.step.apply(table) if self.applies(table) else table

    def apply_stream(self, batches: Iterable[pa.Table]) -> Iterator[pa.Table]:
        it = iter(batches)
        first = next(it, None)
        if first is None:
            return
        rest = chained([first], it)
        yield from (self.step.apply_stream(rest) if self.applies(first) else rest)

    def to_json(self) -> dict[str, Any]:
        return {**self.step.to_json(), "device": self.device}

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> Step:
        """The entry's own step (its ``kind``) on the entry's device."""
        (step,) = steps_from_json([entry])
        return cls(step, device(entry.get("fitted_on"), step.sensor) | entry.get("device", {}))


def on_device(
    steps: Sequence[Step], entries: Sequence[Mapping[str, Any]], lenient: bool = False
) -> list[Step]:
    """``steps`` each wrapped in :class:`OnDevice` with the device of its chain entry
    (``entries[i]``: a chain entry with ``device`` or ``fitted_on``, or a ``fitted_on``
    record); ``lenient`` only where the chain names one device per sensor."""
    devices = [
        dict(e["device"])
        if isinstance(e.get("device"), Mapping)
        else device(e.get("fitted_on", e), s.sensor)
        for s, e in zip(steps, entries, strict=True)
    ]
    out: list[Step] = []
    for s, dev in zip(steps, devices, strict=True):
        same = [d for t, d in zip(steps, devices, strict=True) if t.sensor == s.sensor]
        one = len({device_key(d) for d in same} - {UNNAMED}) <= 1
        out.append(OnDevice(s, dev, lenient and one, tuple(same)))
    return out


def applying(steps: Sequence[Step], table: pa.Table) -> list[Step]:
    """The steps that apply to ``table``'s device (every step that is not an :class:`OnDevice`
    of another device)."""
    return [s for s in steps if not isinstance(s, OnDevice) or s.applies(table)]


def calibration_json(doc: Mapping[str, Any]) -> str:
    """``doc`` as the text of a ``calibration.json``: standard JSON (RFC 8259), so a float that
    is not finite (a metric of a fit that overflowed, accepted with ``accept_failed_checks``) is
    written as ``null``, not as Python's ``Infinity`` or ``NaN``, which strict readers refuse.
    Chain entries never hold one (:func:`check_calibration` requires finite numbers).

    A document whose last key is ``conversion`` (what ``imupipe convert`` attaches to every log:
    the same calibration, then the log's own conversion record) reuses the text of the rest,
    kept from the previous call with the same rest: ``json.dumps`` with ``indent`` runs in
    pure Python (3 ms a log for a calibration with its results). The text is the same either
    way (``tests/test_calibration_file.py``)."""
    keys = list(doc)
    if len(keys) > 1 and keys[-1] == "conversion":
        rest = _indented({k: doc[k] for k in keys[:-1]})
        if rest.endswith("\n}"):
            tail = json.dumps(_finite(doc["conversion"]), indent=2, allow_nan=False)
            return rest[:-2] + ',\n  "conversion": ' + tail.replace("\n", "\n  ") + "\n}\n"
    return json.dumps(_finite(doc), indent=2, allow_nan=False) + "\n"


_LAST_TEXT: dict[str, str] = {}
"""The last document :func:`_indented` wrote, by its compact text (one entry)."""


def _indented(doc: Mapping[str, Any]) -> str:
    """``json.dumps(_finite(doc), indent=2, allow_nan=False)``, kept for the next call with the
    same document (found by its compact text: C-encoded, 20x faster than the indented one)."""
    key = json.dumps(doc, allow_nan=True, default=repr)
    text = _LAST_TEXT.get(key)
    if text is None:
        text = json.dumps(_finite(doc), indent=2, allow_nan=False)
        _LAST_TEXT.clear()
        _LAST_TEXT[key] = text
    return text


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float (at any depth) replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def _depth(value: Any) -> int:
    """The nesting depth of parsed JSON (iterative: no recursion limit)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict | list):
            deepest = max(deepest, d)
            if d <= MAX_DEPTH:
                stack.extend((x, d + 1) for x in (v.values() if isinstance(v, dict) else v))
    return deepest


def parse_calibration(text: str, where: str) -> dict[str, Any]:
    """A calibration document's JSON text as a dict with a ``chain`` list (structure only; see
    :func:`check_calibration` for the entries)."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{where}: not valid JSON: {exc}") from None
    except RecursionError:
        raise CalibrationError(f"{where}: JSON nested deeper than {MAX_DEPTH} levels") from None
    if _depth(doc) > MAX_DEPTH:
        raise CalibrationError(f"{where}: JSON nested deeper than {MAX_DEPTH} levels")
    if not isinstance(doc, dict) or not isinstance(doc.get("chain"), list):
        raise CalibrationError(f"{where}: no 'chain' list (is it a calibration.json?)")
    return doc


def check_calibration(doc: Mapping[str, Any], where: str) -> list[Step]:
    """The steps of a parsed document, every entry checked (see the module docstring)."""
    steps = steps_from_json(doc["chain"], where=where)
    for i, entry in enumerate(doc["chain"]):
        if "fitted_on" in entry and not isinstance(entry["fitted_on"], dict | type(None)):
            raise CalibrationError(f"{where}: chain[{i}].fitted_on: an object expected")
    results = doc.get("results", {})
    if not isinstance(results, dict):
        raise CalibrationError(f"{where}: results: an object expected")
    return steps


def load_calibration(path: str | Path) -> tuple[dict[str, Any], list[Step]]:
    """Read and check a ``calibration.json`` (or a corrected MCAP's attached copy: its
    ``conversion`` record is dropped); returns (document, steps)."""
    path = Path(path)
    where = str(path)
    try:
        info = path.stat()
        if stat.S_ISDIR(info.st_mode):
            raise IsADirectoryError
        if not stat.S_ISREG(info.st_mode):  # opening a FIFO would block
            raise CalibrationError(
                f"{where}: not a regular file (a FIFO, socket or device), not a calibration file"
            )
        size = info.st_size
        if size > MAX_BYTES:
            raise CalibrationError(
                f"{where}: {size} bytes; a calibration file is at most {MAX_BYTES} bytes"
            )
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise CalibrationError(f"{where}: no such file") from None
    except IsADirectoryError:
        raise CalibrationError(f"{where}: a folder, not a calibration file") from None
    except UnicodeDecodeError as exc:
        raise CalibrationError(
            f"{where}: not UTF-8 text ({exc.reason} at byte {exc.start})"
        ) from None
    except OSError as exc:
        raise CalibrationError(f"{where}: cannot read: {exc.strerror or exc}") from None
    doc = parse_calibration(text, where)
    doc.pop("conversion", None)
    return doc, check_calibration(doc, where)
