"""Pick the reader for a path by its suffix (or folder layout) and read it into the common table."""

from __future__ import annotations

import importlib
from collections.abc import Iterable
from pathlib import Path

import pyarrow as pa

from imupipe.pipeline.errors import ReadError
from imupipe.readers.spec import InputSpec, RawMessage

CSV_SUFFIXES = {".csv", ".txt", ".tsv", ".mat", ".dat"}

READERS: dict[str, str] = {
    "csv": "imupipe.readers.csv_reader:read_csv",
    "mcap": "imupipe.readers.mcap_reader:read_mcap",
    "ros1": "imupipe.readers.ros1_reader:read_ros1",
    "ros2": "imupipe.readers.ros2_reader:read_ros2",
}
"""Format -> "module:function(spec) -> (table, warnings)"."""

CARRY_OVER: dict[str, str] = {}
"""Format -> "module:function(spec) -> Iterable[RawMessage]": the messages of every topic the
table does not hold, in log-time order (formats without other topics are absent)."""


def detect_format(path: Path) -> str:
    """``csv``, ``mcap``, ``ros1`` or ``ros2`` for a path; ReadError when unknown or missing."""
    if not path.exists():
        raise ReadError(f"{path}: no such file or folder")
    if path.is_dir():
        if (path / "metadata.yaml").exists() or any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return "ros2"
        raise ReadError(f"{path}: a folder, but not a ROS 2 bag (no metadata.yaml, .db3 or .mcap)")
    suffix = path.suffix.lower()
    if suffix in CSV_SUFFIXES:
        return "csv"
    if suffix == ".mcap":
        return "mcap"
    if suffix == ".bag":
        return "ros1"
    if suffix == ".db3":
        return "ros2"
    raise ReadError(
        f"{path}: unknown log format '{suffix}' (expected .csv, .mcap, .bag, .db3 or a ROS 2 bag folder)"
    )


def read_input(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read one input into the common table; returns (table, warnings)."""
    fmt = detect_format(Path(spec.path))
    module, name = READERS[fmt].split(":")
    try:
        reader = getattr(importlib.import_module(module), name)
    except ModuleNotFoundError:
        raise ReadError(f"{spec.path}: reading {fmt} logs is not supported yet") from None
    return reader(spec)


def carry_over(spec: InputSpec) -> Iterable[RawMessage]:
    """The input's messages on topics the pipeline does not correct (empty for CSV)."""
    fmt = detect_format(Path(spec.path))
    if fmt not in CARRY_OVER:
        return ()
    module, name = CARRY_OVER[fmt].split(":")
    return getattr(importlib.import_module(module), name)(spec)
