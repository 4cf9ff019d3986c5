"""The TOML config (see ``docs/reference/config.md``), parsed and validated into dataclasses.

Every problem is a :class:`ConfigError` naming the file and the key: broken TOML, unknown keys
(never ignored), wrong types, missing files, unknown inputs or stage types. Paths are relative to
the config file's folder.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.exports import EXPORTERS
from imupipe.readers.spec import (
    ACCEL_UNITS,
    GYRO_UNITS,
    MAG_UNITS,
    TIME_UNITS,
    CsvMapping,
    FieldMapping,
    InputSpec,
)
from imupipe.stages.registry import STAGE_TYPES, stage_class

SPLIT_KEYS = ("gyro_topic", "accel_topic")
"""An input's keys for a gyro and an accelerometer on topics of their own (see InputSpec)."""
INPUT_KEYS = {
    "path",
    "imu_topic",
    "mag_topic",
    "temperature_topic",
    "time",
    "csv",
    "fields",
    "instances",
}
INPUT_KEYS |= set(SPLIT_KEYS)
CSV_KEYS = {f.name for f in dataclasses.fields(CsvMapping)} - {"required"}
OUTPUT_KEYS = {"dir", "apply_to", "rerun", "rerun_max_points", "report", "exports", "params"}
TOP_KEYS = {"inputs", "stages", "output"}

INPUT_NAME = re.compile(r"^\w[\w.-]*$")
"""An input's name becomes a file name (``<name>.mcap``, ``<stage>_<name>_<sensor>.csv``): letters,
digits, ``_``, ``-`` and ``.``, not starting with ``.`` or ``-`` (no path separator, no ``..``)."""

INT64 = (-(2**63), 2**63 - 1)


@dataclass
class StageConfig:
    type: str
    name: str
    input: str
    options: Any
    index: int
    accept_failed_checks: bool | list[str] = False
    """Keep a fit that fails its own quality check (with a warning) instead of stopping; on an
    input with ``instances``, a list keeps those instances' fits only (``["sensor_mag_1"]``)."""
    instance_of: str | None = None
    """The configured stage this one was expanded from, one per instance of its input's log
    (:mod:`imupipe.pipeline.instances`); None: a stage as written."""
    instance: str | None = None
    """The instance (topic key: ``sensor_mag_1``) of an expanded stage."""


@dataclass
class OutputConfig:
    dir: Path
    apply_to: list[str]
    rerun: bool = True
    rerun_max_points: int = 20_000
    """Signals longer than this are block-averaged before they go to Rerun (the file stays small)."""
    report: bool = True
    """Write ``report.html`` (plots and numbers of every stage, one self-contained file)."""
    exports: list[str] | None = None
    """The files for other tools to write (names of :data:`EXPORTERS`); None: the ROS and VIO
    ones (Kalibr, imu_utils, VINS, OpenVINS), plus PX4's when a step was fitted on a PX4 log.
    Kalibr's ``imu.yaml`` is written whenever an ``allan`` stage ran."""
    params: str = "estimated"
    """The autopilot parameter files (PX4, ArduPilot): ``"estimated"`` holds only what the stages
    fitted; ``"complete"`` merges it over the log's own calibration parameters."""


@dataclass
class Config:
    path: Path
    inputs: dict[str, InputSpec]
    stages: list[StageConfig]
    output: OutputConfig
    raw: dict[str, Any] = field(default_factory=dict)
    instances: dict[str, str | list[str]] = field(default_factory=dict)
    """Input name -> its ``instances`` key (``"all"`` or topic keys): the stages on that input
    run once per raw sensor instance of the log (:mod:`imupipe.pipeline.instances`)."""


def _check_keys(where: str, table: dict[str, Any], allowed: set[str]) -> None:
    for key in table:
        if key not in allowed:
            raise ConfigError(
                f"{where}: unknown key '{key}' (allowed: {', '.join(sorted(allowed))})"
            )


def _type_ok(value: Any, hint: Any) -> bool:
    """Whether a TOML value fits a type hint (int accepted for float)."""
    if hint is Any:
        return True
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, h) for h in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if origin is list:
        (inner,) = typing.get_args(hint) or (Any,)
        return isinstance(value, list) and all(_type_ok(v, inner) for v in value)
    if origin is dict:
        return isinstance(value, dict)
    if origin is typing.Literal:
        return value in typing.get_args(hint)
    if hint is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(hint, type):
        return isinstance(value, hint)
    return True


def _describe(hint: Any) -> str:
    origin = typing.get_origin(hint)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in typing.get_args(hint))
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _check_range(where: str, value: Any, meta: typing.Mapping[str, Any]) -> None:
    """Numbers (also inside lists) must be finite (unless the field's metadata says
    ``finite=False``), fit in int64, and lie within the field's ``min``/``max`` metadata."""
    if isinstance(value, list):
        for i, v in enumerate(value):
            _check_range(f"{where}[{i}]", v, meta)
        return
    if isinstance(value, bool) or not isinstance(value, int | float):
        return
    if isinstance(value, float) and not math.isfinite(value) and meta.get("finite", True):
        raise ConfigError(f"{where}: {value} is not a finite number")
    if isinstance(value, int) and not INT64[0] <= value <= INT64[1]:
        raise ConfigError(f"{where}: {value} does not fit in a 64-bit integer")
    low, high = meta.get("min"), meta.get("max")
    if (low is not None and value < low) or (high is not None and value > high):
        bounds = f"[{'' if low is None else low}, {'' if high is None else high}]"
        raise ConfigError(f"{where}: {value} is out of range {bounds}")


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    """``typing.get_type_hints`` of an options dataclass, evaluated once per class (about 1 ms
    a call: a read's ``input_spec`` builds two)."""
    return typing.get_type_hints(cls)


def build_options(cls: type, values: dict[str, Any], where: str) -> Any:
    """Instantiate the options dataclass ``cls`` from TOML values, checking names, types and
    ranges: a number must be finite unless its field says ``metadata={"finite": False}``, and
    within ``metadata={"min": ..., "max": ...}`` where the field gives them."""
    hints = _type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    _check_keys(where, values, set(fields))
    for key, value in values.items():
        if not _type_ok(value, hints[key]):
            raise ConfigError(f"{where}.{key}: {value!r} is not of type {_describe(hints[key])}")
        _check_range(f"{where}.{key}", value, fields[key].metadata)
        if typing.get_origin(hints[key]) is float or hints[key] is float:
            values[key] = float(value)
    return cls(**values)


def _check_units(where: str, mapping: CsvMapping | FieldMapping) -> None:
    """The ``*_unit`` keys of a CSV or field mapping: each one of the units the readers convert."""
    for key, units in (
        ("time_unit", TIME_UNITS),
        ("gyro_unit", GYRO_UNITS),
        ("accel_unit", ACCEL_UNITS),
        ("mag_unit", MAG_UNITS),
    ):
        if getattr(mapping, key) not in units:
            raise ConfigError(
                f"{where}.{key}: '{getattr(mapping, key)}' is not one of {', '.join(units)}"
            )


def _csv_mapping(where: str, raw: dict[str, Any]) -> CsvMapping:
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: must be a table")
    mapping = build_options(CsvMapping, dict(raw), where)
    _check_units(where, mapping)
    for key in ("gyro", "accel", "mag"):
        value = getattr(mapping, key)
        if value is not None and len(value) != 3:
            raise ConfigError(f"{where}.{key}: must name 3 columns, got {len(value)}")
    for key in ("scale", "offset"):
        for col, value in (getattr(mapping, key) or {}).items():
            if not (isinstance(value, int | float) and not isinstance(value, bool)) or not (
                math.isfinite(value)
            ):
                raise ConfigError(f"{where}.{key}.{col}: {value!r} is not a finite number")
            if key == "scale" and value == 0:
                raise ConfigError(f"{where}.scale.{col}: must not be 0")
        if getattr(mapping, key) is not None:
            setattr(mapping, key, {str(c): float(v) for c, v in getattr(mapping, key).items()})
    mapping.required = tuple(
        k
        for k in ("time", "gyro", "accel", "mag", "temperature", "ambient_temperature")
        if k in raw
    )
    if "time" not in raw and "rate_hz" in raw:
        mapping.time = None
    return mapping


def _field_mapping(where: str, raw: Any) -> FieldMapping | None:
    """``[inputs.NAME.fields]`` into a :class:`FieldMapping` (None when absent); the paths are
    checked against the log when it is read."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: must be a table")
    mapping = build_options(FieldMapping, dict(raw), where)
    _check_units(where, mapping)
    for key in ("gyro", "accel", "mag"):
        value = getattr(mapping, key)
        if isinstance(value, list) and len(value) != 3:
            raise ConfigError(f"{where}.{key}: must name 3 fields (x, y, z), got {len(value)}")
        for path in [value] if isinstance(value, str) else value or []:
            if "." not in path.strip("."):
                raise ConfigError(f"{where}.{key}: '{path}' is not TOPIC.FIELD")
    if all(getattr(mapping, k) is None for k in ("gyro", "accel", "mag", "temperature")):
        raise ConfigError(f"{where}: maps no sensor (gyro, accel, mag or temperature)")
    if mapping.time not in ("header", "log") and "." not in mapping.time.strip("."):
        raise ConfigError(f"{where}.time: '{mapping.time}' is not header, log or TOPIC.FIELD")
    return mapping


def parse_input(name: str, raw: Any, base: Path, where: str) -> InputSpec:
    """One ``[inputs.NAME]`` table into an :class:`InputSpec`."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: must be a table")
    _check_keys(where, raw, INPUT_KEYS)
    if "path" not in raw:
        raise ConfigError(f"{where}: missing key 'path'")
    for key in ("path", "imu_topic", "mag_topic", "temperature_topic", "time", *SPLIT_KEYS):
        if key in raw and not isinstance(raw[key], str):
            raise ConfigError(f"{where}.{key}: must be a string")
    path = Path(raw["path"])
    if not path.is_absolute():
        path = base / path
    if not path.exists():
        raise ConfigError(f"{where}.path: no such file or folder: {path}")
    time = raw.get("time", "header")
    if time not in ("header", "log"):
        raise ConfigError(f"{where}.time: '{time}' is not one of header, log")
    csv = _csv_mapping(f"{where}.csv", raw.get("csv", {}))
    if csv.gyro_file is not None:
        gyro_file = Path(csv.gyro_file)
        gyro_file = gyro_file if gyro_file.is_absolute() else base / gyro_file
        if not gyro_file.is_file():
            raise ConfigError(f"{where}.csv.gyro_file: no such file: {gyro_file}")
        csv.gyro_file = str(gyro_file)
    return InputSpec(
        path=path,
        name=name,
        imu_topic=raw.get("imu_topic"),
        gyro_topic=raw.get("gyro_topic"),
        accel_topic=raw.get("accel_topic"),
        mag_topic=raw.get("mag_topic"),
        temperature_topic=raw.get("temperature_topic"),
        time=time,
        csv=csv,
        fields=_fields_of(raw, where),
    )


def _fields_of(raw: dict[str, Any], where: str) -> FieldMapping | None:
    """The input's field mapping: its ``time`` defaults to the input's; the topic keys, which
    it replaces, are an error beside it."""
    mapping = _field_mapping(f"{where}.fields", raw.get("fields"))
    if mapping is None:
        return None
    for key in ("imu_topic", "mag_topic", "temperature_topic", *SPLIT_KEYS):
        if key in raw:
            raise ConfigError(
                f"{where}.{key}: not used with [fields], which names every sensor's topic "
                f'(map the Imu\'s fields there: gyro = "TOPIC.angular_velocity")'
            )
    if "time" not in raw["fields"]:
        mapping.time = raw.get("time", "header")
    return mapping


def _name_part(key: str, value: Any) -> str | None:
    """A value as part of a stage name (``gyro``, ``order3``); None for unset values, lists and
    tables."""
    if value is None or isinstance(value, list | dict):
        return None
    text = value if isinstance(value, str) else f"{key}{value}"
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in str(text))


def default_names(stages: list[StageConfig], taken: set[str], path: Path) -> None:
    """Name the stages written without ``name``: the type alone when the type appears once
    among them, else the type followed by what tells the stages of that type apart, their
    input and then their options in declaration order (``temperature_gyro`` and
    ``temperature_accel``). Two stages of one type on one input with the same options need a
    ``name``; so does a default name that another stage took."""
    groups: dict[str, list[StageConfig]] = {}
    for st in stages:
        if not st.name:
            groups.setdefault(st.type, []).append(st)
    for type_name, group in groups.items():
        rows = [{"input": st.input, **dataclasses.asdict(st.options)} for st in group]
        keys = [k for k in rows[0] if len({repr(r[k]) for r in rows}) > 1]
        for st, row in zip(group, rows, strict=True):
            parts = [_name_part(k, row[k]) for k in keys]
            st.name = "_".join([type_name, *(p for p in parts if p)])
        names = [st.name for st in group]
        for st in group:
            if names.count(st.name) > 1 or st.name in taken:
                clash = "another stage's name" if st.name in taken else "another stage"
                raise ConfigError(
                    f"{path}: stages[{st.index}] ({type_name} on input '{st.input}') would be "
                    f"named '{st.name}' like {clash}; give it a distinct 'name'"
                )
        taken.update(names)


LOG_SUFFIXES = (".bag", ".mcap", ".ulg", ".db3", ".csv", ".rrd")
"""Files ``imupipe run`` is sometimes given instead of its config."""


LOG_MAGIC = (b"#ROSBAG", b"\x89MCAP", b"ULog", b"SQLite format")
"""How the logs imupipe reads begin (ROS 1 bag, MCAP, PX4 ULog, ROS 2 .db3)."""


def looks_like_a_log(path: Path) -> bool:
    """Whether ``path`` begins as a log does (or holds a NUL byte early: binary, not text)."""
    with path.open("rb") as fh:
        head = fh.read(512)
    return head.startswith(LOG_MAGIC) or b"\x00" in head


def not_a_config(path: Path) -> str:
    """The one line for a log (or a folder) passed where the TOML config is expected."""
    return (
        f"{path}: expected a TOML config file, got a log or a folder: write a config that names "
        f'the log (`[inputs.static]` `path = "{path.name}"`, then `[[stages]]`), see '
        'README\'s "Calibrate the IMU in your bag" or docs/reference/config.md'
    )


def load_config(path: str | Path) -> Config:
    """Read and validate a config file."""
    path = Path(path)
    if path.suffix.lower() in LOG_SUFFIXES or path.is_dir():
        raise ConfigError(not_a_config(path))
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except UnicodeDecodeError as exc:
        if looks_like_a_log(path):
            raise ConfigError(not_a_config(path)) from None
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); TOML is UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return parse_config(raw, path, path.resolve().parent)


def parse_config(raw: dict[str, Any], path: Path, base: Path) -> Config:
    """Validate a config already parsed (a TOML file's tables, or the dict given to
    ``imupipe.run``): ``path`` names it in messages, relative paths are taken from ``base``."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: a config is a table of tables (inputs, stages, output)")
    _check_keys(str(path), raw, TOP_KEYS)

    inputs_raw = raw.get("inputs")
    if not isinstance(inputs_raw, dict) or not inputs_raw:
        raise ConfigError(f"{path}: no [inputs.NAME] table")
    for name in inputs_raw:
        if not INPUT_NAME.match(name):
            raise ConfigError(
                f"{path}: [inputs.{name!r}]: an input's name becomes a file name: use letters, "
                "digits, _, - and . (not first)"
            )
    inputs = {
        name: parse_input(name, value, base, f"{path}: [inputs.{name}]")
        for name, value in inputs_raw.items()
    }
    instances: dict[str, str | list[str]] = {}
    for name, value in inputs_raw.items():
        each = value.get("instances") if isinstance(value, dict) else None
        if each is None:
            continue
        if not (
            each == "all"
            or (isinstance(each, list) and each and all(isinstance(k, str) for k in each))
        ):
            raise ConfigError(
                f'{path}: [inputs.{name}].instances: "all" or a list of topic instances '
                '(["sensor_gyro", "sensor_gyro_1"])'
            )
        instances[name] = each

    stages_raw = raw.get("stages", [])
    if not isinstance(stages_raw, list):
        raise ConfigError(f"{path}: 'stages' must be an array of tables ([[stages]])")
    stages: list[StageConfig] = []
    seen: set[str] = set()
    for i, entry in enumerate(stages_raw):
        where = f"{path}: stages[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: must be a table")
        entry = dict(entry)
        type_name = entry.pop("type", None)
        if type_name is None:
            raise ConfigError(f"{where}: missing key 'type'")
        if not isinstance(type_name, str):
            raise ConfigError(f"{where}.type: must be a string (a stage type)")
        if type_name not in STAGE_TYPES:
            raise ConfigError(
                f"{where}.type: unknown stage type '{type_name}' (known: {', '.join(STAGE_TYPES)})"
            )
        name = entry.pop("name", None)
        if name is not None:
            if not isinstance(name, str) or not name.replace("_", "").replace("-", "").isalnum():
                raise ConfigError(f"{where}.name: must be a word (letters, digits, _ or -)")
            if name in seen:
                raise ConfigError(
                    f"{where}: a second stage named '{name}'; give each a distinct 'name'"
                )
            seen.add(name)
        input_name = entry.pop("input", None)
        if input_name is not None and not isinstance(input_name, str):
            raise ConfigError(f"{where}.input: must be a string (an input's name)")
        if input_name is None:
            if len(inputs) != 1:
                raise ConfigError(
                    f"{where}: missing key 'input' (there are {len(inputs)} inputs: {', '.join(inputs)})"
                )
            input_name = next(iter(inputs))
        if input_name not in inputs:
            raise ConfigError(
                f"{where}.input: unknown input '{input_name}' (inputs: {', '.join(inputs)})"
            )
        accept = entry.pop("accept_failed_checks", False)
        listed = isinstance(accept, list) and all(isinstance(k, str) for k in accept)
        if not isinstance(accept, bool) and not (listed and input_name in instances):
            raise ConfigError(
                f"{where}.accept_failed_checks: must be true or false"
                + (
                    ', or a list of the input\'s instances (["sensor_mag_1"])'
                    if input_name in instances
                    else ""
                )
            )
        cls = stage_class(type_name)
        options = build_options(cls.Options, entry, f"{where} ({type_name})")
        stages.append(StageConfig(type_name, name or "", input_name, options, i, accept))

    default_names(stages, seen, path)

    out_raw = raw.get("output", {})
    if not isinstance(out_raw, dict):
        raise ConfigError(f"{path}: [output] must be a table")
    _check_keys(f"{path}: [output]", out_raw, OUTPUT_KEYS)
    if not isinstance(out_raw.get("dir", "out"), str):
        raise ConfigError(f"{path}: [output].dir must be a string (a folder)")
    out_dir = Path(out_raw.get("dir", "out"))
    if not out_dir.is_absolute():
        out_dir = base / out_dir
    # default: every input when a stage corrects (a calibration), none for analyses alone (an
    # Allan run of a static recording needs no corrected copy of it)
    corrects = any(stage_class(st.type).corrects for st in stages)
    apply_to = out_raw.get("apply_to", list(inputs) if corrects else [])
    if not isinstance(apply_to, list) or not all(isinstance(a, str) for a in apply_to):
        raise ConfigError(f"{path}: [output].apply_to must be a list of input names")
    for name in apply_to:
        if name not in inputs:
            raise ConfigError(f"{path}: [output].apply_to: unknown input '{name}'")
    rerun = out_raw.get("rerun", True)
    if not isinstance(rerun, bool):
        raise ConfigError(f"{path}: [output].rerun must be true or false")
    max_points = out_raw.get("rerun_max_points", OutputConfig.rerun_max_points)
    if not isinstance(max_points, int) or isinstance(max_points, bool) or max_points < 100:
        raise ConfigError(f"{path}: [output].rerun_max_points must be an integer >= 100")
    _check_range(f"{path}: [output].rerun_max_points", max_points, {"min": 100})
    report = out_raw.get("report", True)
    if not isinstance(report, bool):
        raise ConfigError(f"{path}: [output].report must be true or false")
    exports = out_raw.get("exports")
    if exports is not None and (
        not isinstance(exports, list) or not all(e in EXPORTERS for e in exports)
    ):
        raise ConfigError(f"{path}: [output].exports must be a list of: {', '.join(EXPORTERS)}")
    params = out_raw.get("params", "estimated")
    if params not in ("estimated", "complete"):
        raise ConfigError(f'{path}: [output].params must be "estimated" or "complete"')
    output = OutputConfig(
        dir=out_dir,
        apply_to=apply_to,
        rerun=rerun,
        rerun_max_points=max_points,
        report=report,
        exports=exports,
        params=params,
    )
    return Config(
        path=path, inputs=inputs, stages=stages, output=output, raw=raw, instances=instances
    )
