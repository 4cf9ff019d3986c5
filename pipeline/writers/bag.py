"""Common tables as ROS 1 bags and ROS 2 bags (for ``imupipe simulate``).

Each stream becomes one topic (the table's topic names, else ``/imu/data``, ``/imu/mag``,
``/imu/temperature``) of ``sensor_msgs/Imu``, ``MagneticField`` or ``Temperature``; the payloads
are encoded with numpy (:func:`imupipe.pipeline.writers.mcap.encode_stream`: CDR for ROS 2, the
ROS 1 wire format for ROS 1 bags; NaN values and absent vectors as in the corrected MCAP), the
header stamp is ``header_stamp_ns`` where kept, else ``t_ns``, and the bag time ``log_time_ns``
(else ``t_ns``); bags have no publish time. Messages are written in bag-time order.

The result appears whole or not at all: the bag is written under a temporary name next to the
target and renamed into place when complete.

- ``write_ros1_bag(path, table, compression="lz4")``: ROS 1 bag v2.0, chunks ``lz4``, ``bz2`` or
  ``none``, built with numpy a chunk at a time (the same bytes as rosbags' ``rosbag1.Writer``).
- ``write_ros2_bag(path, table, storage="sqlite3")``: a ROS 2 bag folder (version 9) with sqlite3
  or mcap storage, with rosbags' writer; a ``.db3`` path gets the bare sqlite3 file.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

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
from imupipe.readers.ros1.reader import (
    OP_BAG_HEADER,
    OP_CHUNK,
    OP_CHUNK_INFO,
    OP_CONNECTION,
    OP_INDEX,
    OP_MSG,
    VERSION_LINE,
)
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


CHUNK_THRESHOLD = 1 << 20
"""Bytes of messages after which a ROS 1 chunk is closed (rosbags' writer's default, 1 MiB)."""
_MSG_PREFIX = 46
"""Bytes of a ROS 1 message data record before its payload: header length, the fields ``op``,
``conn`` and ``time``, and the data length."""
_IDX_ROW = np.dtype([("sec", "<u4"), ("nsec", "<u4"), ("offset", "<u4")])


def _u32(value: int) -> bytes:
    return int(value).to_bytes(4, "little")


def _time(ns: int) -> bytes:
    return _u32(ns // 1_000_000_000) + _u32(ns % 1_000_000_000)


def _header(op: int | None, fields: list[tuple[str, bytes]]) -> bytes:
    """A ROS 1 record header: its length, then each ``name=value`` after its own length."""
    items = ([("op", bytes([op]))] if op is not None else []) + fields
    data = b"".join(_u32(len(k) + 1 + len(v)) + k.encode() + b"=" + v for k, v in items)
    return _u32(len(data)) + data


def _connection_record(conn: int, topic: str, typ: str, msgdef: str, md5: str) -> bytes:
    """Connection record (op 0x07): ``conn`` and ``topic`` in the header, the connection's own
    header (topic, type, md5sum, message_definition) as its data, as rosbags writes it."""
    data = _header(
        None,
        [
            ("topic", topic.encode()),
            ("type", typ.encode()),
            ("md5sum", md5.encode()),
            ("message_definition", msgdef.encode()),
        ],
    )
    return _header(OP_CONNECTION, [("conn", _u32(conn)), ("topic", topic.encode())]) + data


def _bag_header(index_pos: int, conn_count: int, chunk_count: int) -> bytes:
    """Bag header record (op 0x03) padded with spaces to 4096 bytes."""
    head = _header(
        OP_BAG_HEADER,
        [
            ("index_pos", index_pos.to_bytes(8, "little")),
            ("conn_count", _u32(conn_count)),
            ("chunk_count", _u32(chunk_count)),
        ],
    )
    pad = 4096 - 4 - len(head)
    return head + _u32(pad) + b" " * pad


@dataclass
class _Ros1Messages:
    """Every message of a table as ROS 1 message data records, in bag-time order.

    ``segments``: ``(conn, payloads (m, L) uint8)``, one per stream and frame_id. Per message in
    log-time order (ties: stream order, then row order): its segment ``seg``, its row ``pos`` in
    that segment's payloads, its uint64 log time ``times`` (``sec``, ``nsec`` as uint32) and the
    end of its record in the concatenation of all records (``ends``)."""

    streams: dict[str, str]
    """Stream -> topic, in connection order."""
    segments: list[tuple[int, np.ndarray]]
    seg: np.ndarray
    pos: np.ndarray
    times: np.ndarray
    sec: np.ndarray
    nsec: np.ndarray
    ends: np.ndarray
    templates: np.ndarray
    """Per segment, the 46 bytes before a payload (time zero, set per message: bytes 34..42)."""

    @classmethod
    def of(cls, table: pa.Table, path: str | Path) -> _Ros1Messages:
        log_all, _ = message_times(table)  # a bag has no publish time
        topics = {**DEFAULT_TOPICS, **metadata(table).get("topics", {})}
        streams: dict[str, str] = {}
        segments: list[tuple[int, np.ndarray]] = []
        seg_parts, pos_parts, time_parts = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], []
        for stream in written_streams(table):
            rows, groups = encode_stream(table, stream, "ros1")
            if not len(rows):
                continue
            seg = np.empty(len(rows), dtype=np.int64)
            pos = np.empty(len(rows), dtype=np.int64)
            for sel, enc in groups:
                seg[sel] = len(segments)
                pos[sel] = np.arange(len(sel))
                segments.append((len(streams), enc))
            streams[stream] = topics[stream]
            seg_parts.append(seg)
            pos_parts.append(pos)
            time_parts.append(log_all[rows])
        times = np.concatenate([np.zeros(0, np.uint64), *time_parts])
        order = np.argsort(times, kind="stable")  # stream order, then row order, among ties
        times = times[order]
        sec = times // np.uint64(1_000_000_000)
        if len(sec) and sec.max() > np.iinfo(np.uint32).max:
            raise ConfigError(
                f"{path}: a log time past 2106 does not fit a ROS 1 bag's uint32 seconds"
            )
        seg = np.concatenate(seg_parts)[order]
        templates = np.zeros((len(segments), _MSG_PREFIX), dtype=np.uint8)
        for s, (conn, enc) in enumerate(segments):
            head = _header(OP_MSG, [("conn", _u32(conn)), ("time", bytes(8))])
            templates[s] = np.frombuffer(head + _u32(enc.shape[1]), dtype=np.uint8)
        seg_len = np.array([enc.shape[1] for _, enc in segments] or [0], dtype=np.int64)
        return cls(
            streams,
            segments,
            seg,
            np.concatenate(pos_parts)[order],
            times,
            sec.astype("<u4"),
            (times % np.uint64(1_000_000_000)).astype("<u4"),
            np.cumsum(_MSG_PREFIX + seg_len[seg]),
            templates,
        )

    def chunk_end(self, a: int, before: int) -> int:
        """End of the chunk whose first message is ``a``, after ``before`` bytes of other
        records: the first message that takes the chunk past ``CHUNK_THRESHOLD`` closes it."""
        done = int(self.ends[a - 1]) if a else 0
        b = int(np.searchsorted(self.ends, done - before + CHUNK_THRESHOLD, side="right"))
        return min(b + 1, len(self.seg))

    def records(self, a: int, b: int, pre: bytes) -> tuple[np.ndarray, np.ndarray]:
        """The uncompressed data of a chunk: ``pre`` then the records of messages ``a:b``;
        and each record's offset in it."""
        done = int(self.ends[a - 1]) if a else 0
        m = b - a
        offsets = len(pre) + np.concatenate(([0], self.ends[a : b - 1] - done)).astype(np.int64)
        out = np.empty(len(pre) + (int(self.ends[b - 1]) - done if m else 0), dtype=np.uint8)
        out[: len(pre)] = np.frombuffer(pre, dtype=np.uint8)
        if not m:
            return out, offsets[:0]
        sg, ps = self.seg[a:b], self.pos[a:b]
        prefix = self.templates[sg]
        prefix[:, 34:38] = self.sec[a:b, None].view(np.uint8).reshape(m, 4)
        prefix[:, 38:42] = self.nsec[a:b, None].view(np.uint8).reshape(m, 4)
        _rows_at(out, _MSG_PREFIX)[offsets] = prefix
        for s in np.unique(sg):
            sel = sg == s
            enc = self.segments[s][1]
            _rows_at(out[_MSG_PREFIX:], enc.shape[1])[offsets[sel]] = enc[ps[sel]]
        return out, offsets


def _rows_at(buf: np.ndarray, width: int) -> np.ndarray:
    """``buf`` as overlapping rows of ``width`` bytes, row ``i`` starting at byte ``i``: writing
    rows at chosen offsets copies whole records, not one indexed byte at a time."""
    return np.lib.stride_tricks.as_strided(buf, (len(buf) - width + 1, width), (1, 1))


def _compressor(compression: str) -> Callable[[bytes], bytes]:
    """rosbags' chunk compression: lz4 frames at level 0, bz2 at level 9, or none."""
    if compression == "lz4":
        from lz4.frame import compress

        return lambda data: compress(data, 0)
    if compression == "bz2":
        import bz2

        return lambda data: bz2.compress(data, 9)
    return lambda data: data


def _write_chunk(
    f: BinaryIO, msgs: _Ros1Messages, a: int, b: int, pre: bytes, compression: str
) -> bytes:
    """Write a chunk record (``pre``, then messages ``a:b``) and its index data records (op
    0x04, version 1), one per connection in the order of its first message in the chunk;
    returns the chunk's chunk info record (op 0x06)."""
    chunk_pos = f.tell()
    out, offsets = msgs.records(a, b, pre)
    data = _compressor(compression)(out.tobytes())
    f.write(_header(OP_CHUNK, [("compression", compression.encode()), ("size", _u32(len(out)))]))
    f.write(_u32(len(data)) + data)
    conns = np.array([c for c, _ in msgs.segments] or [0], dtype=np.int64)[msgs.seg[a:b]]
    present, first = np.unique(conns, return_index=True)
    counts = b""
    for c in present[np.argsort(first)].tolist():
        sel = conns == c
        idx = np.empty(int(sel.sum()), dtype=_IDX_ROW)
        idx["sec"], idx["nsec"] = msgs.sec[a:b][sel], msgs.nsec[a:b][sel]
        idx["offset"] = offsets[sel]
        fields = [("ver", _u32(1)), ("conn", _u32(c)), ("count", _u32(len(idx)))]
        f.write(_header(OP_INDEX, fields) + _u32(idx.nbytes) + idx.tobytes())
        counts += _u32(c) + _u32(len(idx))
    t0, t1 = (int(msgs.times[a]), int(msgs.times[b - 1])) if b > a else (0, 0)
    fields = [
        ("ver", _u32(1)),
        ("chunk_pos", chunk_pos.to_bytes(8, "little")),
        ("start_time", _time(t0)),
        ("end_time", _time(t1)),
        ("count", _u32(len(present))),
    ]
    return _header(OP_CHUNK_INFO, fields) + _u32(len(counts)) + counts


def write_ros1_bag(path: str | Path, table: pa.Table, compression: str = "lz4") -> None:
    """Write ``table`` as a ROS 1 bag (format 2.0) at ``path``.

    The records are those of rosbags' ``rosbag1.Writer`` byte for byte (ROS wiki,
    Bags/Format/2.0), built with numpy a chunk at a time instead of a call per message: the bag
    header (padded to 4096 bytes); chunks closed once their records pass 1 MiB, the first
    holding the connection records, each followed by one index data record (version 1: time,
    offset) per connection; then the connection records and one chunk info record per chunk,
    whose position the bag header gives (``index_pos``). Times are uint32 seconds and
    nanoseconds: a log time past 2106 is refused."""
    from rosbags.typesys import Stores, get_typestore
    from rosbags.typesys.msg import denormalize_msgtype

    if compression not in ("lz4", "bz2", "none"):
        raise ConfigError(f"{path}: ROS 1 bag compression '{compression}' (lz4, bz2 or none)")
    final = Path(path)
    msgs = _Ros1Messages.of(table, path)
    store = get_typestore(Stores.ROS1_NOETIC)
    conn_records = b""
    for conn, (stream, topic) in enumerate(msgs.streams.items()):
        msgdef, md5 = store.generate_msgdef(STREAM_TYPES[stream])
        typ = denormalize_msgtype(STREAM_TYPES[stream])
        conn_records += _connection_record(conn, topic, typ, msgdef, md5)
    n = len(msgs.seg)
    tmpdir = _staged(final)
    try:
        tmp = tmpdir / final.name
        chunk_infos: list[bytes] = []
        with tmp.open("xb") as f:
            f.write(VERSION_LINE + _bag_header(0, 0, 0))
            a, pre = 0, conn_records
            while a < n or pre:
                b = msgs.chunk_end(a, len(pre))
                chunk_infos.append(_write_chunk(f, msgs, a, b, pre, compression))
                report(a, n)
                a, pre = b, b""
            index_pos = f.tell()
            f.write(conn_records + b"".join(chunk_infos))
            f.seek(len(VERSION_LINE))
            f.write(_bag_header(index_pos, len(msgs.streams), len(chunk_infos)))
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
