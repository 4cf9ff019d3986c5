"""Common tables as ROS 1 bags and ROS 2 bags, with rosbags' writers (for ``imupipe simulate``).

Each stream becomes one topic (the table's topic names, else ``/imu/data``, ``/imu/mag``,
``/imu/temperature``) of ``sensor_msgs/Imu``, ``MagneticField`` or ``Temperature``; the payloads
are encoded with numpy (:func:`imupipe.pipeline.writers.mcap.encode_stream`: CDR for ROS 2, the
ROS 1 wire format for ROS 1 bags; NaN values and absent vectors as in the corrected MCAP), the
header stamp is ``header_stamp_ns`` where kept, else ``t_ns``, and the bag time ``log_time_ns``
(else ``t_ns``); bags have no publish time. Messages are written in bag-time order.

The result appears whole or not at all: the bag is written under a temporary name next to the
target and renamed into place when complete.

- ``write_ros1_bag(path, table, compression="lz4")``: ROS 1 bag v2.0, chunks ``lz4``, ``bz2`` or
  ``none``.
- ``write_ros2_bag(path, table, storage="sqlite3")``: a ROS 2 bag folder (version 9) with sqlite3
  or mcap storage; a ``.db3`` path gets the bare sqlite3 file.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.writers.mcap import (
    DEFAULT_TOPICS,
    STREAM_TYPES,
    encode_stream,
    message_times,
    written_streams,
)
from imupipe.readers.progress import report
from imupipe.readers.table import metadata

REPORT_EVERY = 10_000
"""Messages between two reports of how far the writing is (:mod:`imupipe.readers.progress`)."""


def _messages(table: pa.Table, encoding: str) -> Iterator[tuple[str, int, list[bytes], np.ndarray]]:
    """Per stream present: (stream, topic, payloads in row order, log times)."""
    topics = {**DEFAULT_TOPICS, **metadata(table).get("topics", {})}
    log_all, _ = message_times(table)  # a bag has no publish time
    for stream in written_streams(table):
        rows, groups = encode_stream(table, stream, encoding)
        if not len(rows):
            continue
        payloads: list[bytes] = [b""] * len(rows)
        for sel, enc in groups:
            for i, p in zip(sel.tolist(), enc, strict=True):
                payloads[i] = p.tobytes()
        yield stream, topics[stream], payloads, log_all[rows]


def _ordered(table: pa.Table, encoding: str) -> tuple[dict[str, tuple[str, str]], list]:
    """Streams -> (topic, type), and every message as (log time, stream, payload) in log order."""
    streams: dict[str, tuple[str, str]] = {}
    items: list[tuple[int, int, str, bytes]] = []
    for k, (stream, topic, payloads, log) in enumerate(_messages(table, encoding)):
        streams[stream] = (topic, STREAM_TYPES[stream])
        items += [(int(t), k, stream, p) for t, p in zip(log.tolist(), payloads, strict=True)]
    items.sort(key=lambda x: (x[0], x[1]))
    return streams, items


def _staged(final: Path) -> Path:
    final.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent))


def write_ros1_bag(path: str | Path, table: pa.Table, compression: str = "lz4") -> None:
    """Write ``table`` as a ROS 1 bag at ``path``."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    if compression not in ("lz4", "bz2", "none"):
        raise ConfigError(f"{path}: ROS 1 bag compression '{compression}' (lz4, bz2 or none)")
    final = Path(path)
    tmpdir = _staged(final)
    try:
        tmp = tmpdir / final.name
        store = get_typestore(Stores.ROS1_NOETIC)
        streams, items = _ordered(table, "ros1")
        writer = Writer(tmp)
        if compression != "none":
            writer.set_compression(Writer.CompressionFormat[compression.upper()])
        with writer:
            conns = {
                s: writer.add_connection(topic, typ, typestore=store)
                for s, (topic, typ) in streams.items()
            }
            for i, (t, _, stream, payload) in enumerate(items):
                writer.write(conns[stream], t, payload)
                if not i % REPORT_EVERY:
                    report(i, len(items))
        os.replace(tmp, final)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def write_ros2_bag(path: str | Path, table: pa.Table, storage: str = "sqlite3") -> None:
    """Write ``table`` as a ROS 2 bag folder at ``path`` (or a bare sqlite3 file for ``.db3``)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    if storage not in ("sqlite3", "mcap"):
        raise ConfigError(f"{path}: ROS 2 bag storage '{storage}' (sqlite3 or mcap)")
    final = Path(path)
    bare = final.suffix.lower() == ".db3"
    tmpdir = _staged(final)
    try:
        folder = tmpdir / (final.stem if bare else final.name)
        store = get_typestore(Stores.ROS2_HUMBLE)
        streams, items = _ordered(table, "cdr")
        plugin = StoragePlugin.SQLITE3 if bare or storage == "sqlite3" else StoragePlugin.MCAP
        with Writer(folder, version=9, storage_plugin=plugin) as writer:
            conns = {
                s: writer.add_connection(topic, typ, typestore=store)
                for s, (topic, typ) in streams.items()
            }
            for i, (t, _, stream, payload) in enumerate(items):
                writer.write(conns[stream], t, payload)
                if not i % REPORT_EVERY:
                    report(i, len(items))
        if bare:
            (db,) = folder.glob("*.db3")
            os.replace(db, final)
        else:
            if final.exists():
                if not (final / "metadata.yaml").exists():
                    raise ConfigError(f"{final}: exists and is not a ROS 2 bag; not overwriting")
                shutil.rmtree(final)
            os.replace(folder, final)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
