"""Pick the reader for a path by its suffix (or folder layout) and read it into the common table."""

from __future__ import annotations

import errno
import importlib
import os
import stat
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from imupipe.readers.errors import ReadError
from imupipe.readers.spec import InputSpec, RawMessage

if TYPE_CHECKING:  # pyarrow is loaded by the reader a read imports, not by choosing one
    import pyarrow as pa

    from imupipe.readers.sources import LogSource

_NOT_THERE = {errno.ENOENT, errno.ENOTDIR, errno.EBADF, errno.ELOOP}
"""The errors of ``stat`` that ``Path.exists`` takes for a path that is not there (and the
Windows errors 21, 123, 1921: ``pathlib._ignore_error``)."""
CSV_SUFFIXES = {".csv", ".txt", ".tsv", ".mat", ".dat"}

READERS: dict[str, str] = {
    "csv": "imupipe.readers.csv.reader:read_csv",
    "mcap": "imupipe.readers.mcap.reader:read_mcap",
    "ros1": "imupipe.readers.ros1.reader:read_ros1",
    "ros2": "imupipe.readers.ros2.reader:read_ros2",
    "ulog": "imupipe.readers.ulog.reader:read_ulog",
    "dataflash": "imupipe.readers.dataflash.reader:read_dataflash",
}
"""Format -> "module:function(spec) -> (table, warnings)"."""

CARRY_OVER: dict[str, str] = {
    "mcap": "imupipe.readers.mcap.reader:carry_over_mcap",
    "ros1": "imupipe.readers.ros1.reader:carry_over_ros1",
    "ros2": "imupipe.readers.ros2.reader:carry_over_ros2",
}
"""Format -> "module:function(spec) -> Iterable[RawMessage]": the messages of every topic the
table does not hold, in log-time order (formats without other topics are absent; a ULog's other
topics have no ROS type and are listed in one warning by its reader instead)."""

ITERATORS: dict[str, str] = {
    "mcap": "imupipe.readers.mcap.reader:iter_mcap",
    "ros1": "imupipe.readers.ros1.reader:iter_ros1",
    "ros2": "imupipe.readers.ros2.reader:iter_ros2",
}
"""Format -> "module:function(spec, batch_rows, carry, warnings) -> Iterator[(table, [RawMessage])]": bounded
memory batches (formats absent here are read whole and yielded as one batch: CSV, ULog, which
pyulog reads whole, and DataFlash)."""

SOURCES: dict[str, str] = {
    "mcap": "imupipe.readers.mcap.reader:mcap_sources",
    "ros1": "imupipe.readers.ros1.reader:bag_sources",
    "ros2": "imupipe.readers.ros2.reader:bag2_sources",
    "ulog": "imupipe.readers.ulog.reader:ulog_sources",
    "dataflash": "imupipe.readers.dataflash.reader:dataflash_sources",
}
"""Format -> "module:function(path) -> [LogSource]": the files of a binary log, for ``inspect``."""

READ_TRUNCATED = {"mcap", "ros1", "ros2"}
"""The formats whose ``SOURCES`` function reads a cut-off file up to the cut when asked
(``(path, salvage)``: :attr:`~imupipe.readers.spec.InputSpec.read_truncated`)."""

INSTANCES: dict[str, str] = {
    "ulog": "imupipe.readers.ulog.reader:raw_instances",
    "dataflash": "imupipe.readers.dataflash.reader:raw_instances",
}
"""Format -> "module:function(path) -> {kind: [instance key]}": the raw sensor instances of a
log with several (``imu``, ``mag``, ``baro``), named as the topic keys take them."""


def raw_instances(spec: InputSpec) -> dict[str, list[str]]:
    """The raw sensor instances of ``spec``'s log by kind (``imu``, ``mag``, ``baro``);
    ReadError for a format without instances (CSV, ROS)."""
    fmt = detect_format(Path(spec.path))
    if fmt not in INSTANCES:
        raise ReadError(
            f"{spec.path}: a {fmt} input has no sensor instances to list (ULog and DataFlash "
            "logs have)"
        )
    return _load(spec, fmt, INSTANCES[fmt])(Path(spec.path))


def detect_format(path: Path) -> str:
    """``csv``, ``mcap``, ``ros1``, ``ros2``, ``ulog`` or ``dataflash`` (ArduPilot ``.bin``) for
    a path; ReadError when unknown or missing."""
    try:  # one stat (what exists, is_dir and is_file each ask)
        mode = os.stat(path).st_mode
    except ValueError:  # an embedded null byte: no such file, as Path.exists says
        mode = None
    except OSError as exc:
        if exc.errno not in _NOT_THERE and getattr(exc, "winerror", None) not in (21, 123, 1921):
            raise
        mode = None
    if mode is None:
        raise ReadError(f"{path}: no such file or folder")
    if not stat.S_ISDIR(mode) and not stat.S_ISREG(mode):  # stat only: opening a FIFO would block
        raise ReadError(
            f"{path}: not a regular file (a FIFO, socket or device); imupipe reads log files"
        )
    if stat.S_ISDIR(mode):
        if (path / "metadata.yaml").exists() or any(
            any(path.glob(p)) for p in ("*.db3", "*.mcap", "*.db3.zstd", "*.mcap.zstd")
        ):
            return "ros2"
        if any(path.glob("*.bag")):
            return "ros1"
        raise ReadError(
            f"{path}: a folder, but not a ROS 2 bag or a folder of ROS 1 bags "
            "(no metadata.yaml, .db3, .mcap or .bag)"
        )
    suffix = path.suffix.lower()
    if suffix in CSV_SUFFIXES:
        return "csv"
    if suffix == ".mcap":
        return "mcap"
    if suffix == ".bag":
        return "ros1"
    if suffix == ".db3" or path.name.lower().endswith((".db3.zstd", ".mcap.zstd")):
        return "ros2"  # a bare ROS 2 storage file, or one that rosbag2 compressed whole
    if suffix == ".ulg":
        return "ulog"
    if suffix == ".bin":
        return "dataflash"
    raise ReadError(
        f"{path}: unknown log format '{suffix}' (expected .csv, .mcap, .bag, .db3, .db3.zstd, .ulg, "
        ".bin or a ROS 2 bag folder)"
    )


def _load(spec: InputSpec, fmt: str, target: str) -> Callable:
    module, name = target.split(":")
    try:
        return getattr(importlib.import_module(module), name)
    except ModuleNotFoundError as exc:
        if exc.name != module:
            raise
        raise ReadError(f"{spec.path}: reading {fmt} logs is not supported yet") from None


def reader_for(spec: InputSpec) -> Callable[[InputSpec], tuple[pa.Table, list[str]]]:
    """The reader of ``spec``'s format, its module imported (ReadError when the file is missing
    or its format unknown)."""
    fmt = detect_format(Path(spec.path))
    return _load(spec, fmt, READERS[fmt])


def read_input(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read one input into the common table; returns (table, warnings)."""
    return reader_for(spec)(spec)


def iter_input(
    spec: InputSpec,
    batch_rows: int = 200_000,
    carry: bool = True,
    warnings: list[str] | None = None,
) -> Iterator[tuple[pa.Table, list[RawMessage]]]:
    """The input as ``(table batch, carried-over messages)`` pairs in log order, with memory
    bounded by ``batch_rows`` rows (plus one chunk) for MCAP and ROS bags.

    Each batch holds the sensor messages of a run of consecutive chunks (about ``batch_rows``
    rows, sorted by time within the batch; batches are not sorted against each other, so a
    stamp that goes back across a batch boundary stays where the log put it) and the other
    topics' messages of the same chunks, in log-time order. ``warnings``: the reader's
    warnings are appended to it once the last batch was yielded (for MCAP and bags, those of
    :func:`read_input` once per topic, the counts of stamps out of order or repeated summed
    over the batches). Other formats (CSV) are read whole and yielded as one batch. ``carry=False``: the other topics are not read
    (every batch comes with an empty list; for a reader of the table only, as the survey).
    """
    fmt = detect_format(Path(spec.path))
    if fmt in ITERATORS:
        yield from _load(spec, fmt, ITERATORS[fmt])(spec, batch_rows, carry, warnings)
        return
    table, warned = read_input(spec)
    yield table, list(carry_over(spec)) if carry else []
    if warnings is not None:
        warnings += warned


def carry_over(spec: InputSpec) -> Iterable[RawMessage]:
    """The input's messages on topics the pipeline does not correct (empty for CSV)."""
    fmt = detect_format(Path(spec.path))
    if fmt not in CARRY_OVER:
        return ()
    return _load(spec, fmt, CARRY_OVER[fmt])(spec)


def log_sources(spec: InputSpec) -> list[LogSource]:
    """The sources of a binary input (MCAP, ROS 1 bag(s), ROS 2 bag, ULog)."""
    fmt = detect_format(Path(spec.path))
    if fmt not in SOURCES:
        raise ReadError(f"{spec.path}: not a binary log (MCAP, ROS bag, ULog or DataFlash)")
    load = _load(spec, fmt, SOURCES[fmt])
    if fmt in READ_TRUNCATED:
        return list(load(Path(spec.path), spec.read_truncated))
    return list(load(Path(spec.path)))
