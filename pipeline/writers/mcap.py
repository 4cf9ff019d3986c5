"""Corrected logs as MCAP, written chunk by chunk with numpy: every message as it came, only the
corrected fields changed.

Profile ``ros2``, message encoding ``cdr``, schemas ``ros2msg`` (the message definitions rosbags
generates), so the ``mcap`` library's ROS 2 decoder, rosbags, Foxglove and ``ros2 bag`` read it.
The IMU stream is written as ``sensor_msgs/msg/Imu``, the magnetometer as
``sensor_msgs/msg/MagneticField`` (tesla), the temperature as ``sensor_msgs/msg/Temperature``
(degC), each row of the table exactly once (NaN values as NaN), with the message's own times:
header stamp = ``header_stamp_ns`` where the reader kept it (``time = "log"``), else ``t_ns``;
log time = ``log_time_ns``, else ``t_ns``; publish time = ``publish_time_ns`` (MCAP inputs), else
the log time, as the MCAP specification asks of a message without one. The calibration that was
applied travels as the attachment ``calibration.json``. Messages of other topics given as
``carry_over`` are written unchanged, their log and publish times kept.

:class:`McapTableWriter` streams with bounded memory: ``write_table`` queues rows and encodes
:data:`SLICE_ROWS` at a time (counted from the first row written, so the bytes do not depend on
how the rows were batched) with :func:`imupipe.readers.cdr.encode` (one structured array per
frame_id). A slice's message records (``opcode, length, channel, sequence, log_time,
publish_time, payload``) are cut into ~1 MiB chunks planned from the record sizes (fixed per
message type and frame_id), and each chunk's records are built as one numpy array only when
the chunk is written (a slice's 22 MB of Imu records are never held at once; the bytes are
those of encoding the whole slice and cutting it), zstd-compressed, and followed by the
chunk's ``MessageIndex`` records; the summary (schemas, channels, statistics,
chunk and attachment indexes) is written at :meth:`~McapTableWriter.close`. No Python loop runs
per message except for carried-over messages, which arrive as Python objects anyway.
"""

from __future__ import annotations

import bisect
import struct
import time
import zlib
from collections.abc import Iterable, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import zstandard

from imupipe.pipeline.calibration_file import calibration_json
from imupipe.readers import cdr
from imupipe.readers.arrays import arrow_array, arrow_scalar, to_numpy, unique, valid_mask
from imupipe.readers.chunk_fill import crc32
from imupipe.readers.mcap.records import (
    MAGIC,
    OP_ATTACHMENT,
    OP_ATTACHMENT_INDEX,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
    OP_SUMMARY_OFFSET,
    pack,
)
from imupipe.readers.progress import report
from imupipe.readers.spec import RawMessage
from imupipe.readers.table import (
    META_KEY,
    SENSOR_COLUMNS,
    metadata,
    sensor,
    sensor_mask,
    stream_mask,
)

DEFAULT_TOPICS = {
    "imu": "/imu/data",
    "mag": "/imu/mag",
    "temperature": "/imu/temperature",
    "gyro": "/imu/gyro",
    "accel": "/imu/accel",
}
STREAM_TYPES = {
    "imu": "sensor_msgs/msg/Imu",
    "gyro": "sensor_msgs/msg/Imu",
    "accel": "sensor_msgs/msg/Imu",
    "mag": "sensor_msgs/msg/MagneticField",
    "temperature": "sensor_msgs/msg/Temperature",
}
SPLIT = ("gyro", "accel")
"""The streams of an IMU read from a gyro and an accelerometer topic (``gyro_topic``,
``accel_topic``): written back to those topics, one vector each."""
DEFAULT_FRAME = "imu"
CHUNK_BYTES = 1 << 20
RECORD_HEADER = 31
"""Bytes of a message record before its payload (opcode, length, channel, seq, 2 times)."""
SLICE_ROWS = 65_536
"""Table rows encoded as one slice (the writer's memory: the slice's queued rows and their
field arrays, and one chunk of records at a time)."""
RAW_BUFFER_BYTES = 256 << 20
"""Carried-over payload bytes held back, at most, waiting for the table rows to pass them."""


@cache
def msgdef(msgtype: str) -> str:
    """The ros2msg schema text of a message type (as rosbags generates it; the writer's own
    types from :data:`~imupipe.pipeline.writers.msgdefs.MSGDEFS`, without building rosbags'
    typestore)."""
    from imupipe.pipeline.writers.msgdefs import MSGDEFS

    if msgtype in MSGDEFS:
        return MSGDEFS[msgtype]
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)[0]


def _column_or(table: pa.Table, name: str, rows: np.ndarray, default: np.ndarray) -> np.ndarray:
    """Column ``name`` at ``rows`` as numpy, ``default`` (same shape) where it is null or absent."""
    index = table.schema.get_field_index(name)  # -1: absent (or, never here, twice)
    if index < 0:
        if name not in table.schema.names:
            return default
        index = table.schema.names.index(name)
    column = table.column(index)
    if len(rows) != len(column):
        column = column.take(arrow_array(rows))
    # one chunk (a batch as read): that chunk, as combine_chunks gives it, at a third of the cost
    column = column.chunk(0) if column.num_chunks == 1 else column.combine_chunks()
    valid = None if column.null_count == 0 else valid_mask(column)
    if isinstance(column.type, pa.FixedSizeListType):
        if valid is None or pa.types.is_floating(column.type.value_type):
            # the lists' values as (n, k), a null list as zeros: what pc.if_else(valid,
            # column, zeros).flatten() gives, without pyarrow.compute (flatten imports it; see
            # _frame_codes). .values ignores the array's offset: sliced by hand
            k = column.type.list_size
            child = column.values.slice(column.offset * k, len(column) * k)
            values = np.asarray(to_numpy(child)).reshape(len(rows), -1)
            if valid is not None:
                values = np.array(values)
                values[~valid] = 0.0
        else:
            import pyarrow.compute as pc  # integer lists with nulls only

            column = pc.if_else(arrow_array(valid), column, _zero_list(column.type))
            values = np.asarray(to_numpy(column.flatten()))
            values = values.reshape(len(rows), -1)
    else:
        values = to_numpy(column)
    if valid is None:
        return values
    return np.where(valid.reshape((-1,) + (1,) * (values.ndim - 1)), values, default)


def _zero_list(typ: pa.FixedSizeListType) -> pa.Scalar:
    """A fixed-size list of zeros of type ``typ`` (built from buffers: ``pa.scalar`` would
    import pandas)."""
    flat = arrow_array(np.zeros(typ.list_size), typ.value_type)
    return pa.FixedSizeListArray.from_arrays(flat, typ.list_size)[0]


NO_ESTIMATE = np.array([[-1.0] + [0.0] * 8])
"""sensor_msgs/Imu's covariance for "no estimate of this field": element 0 = -1."""

IMU_VECTORS = (
    ("gyro", "angular_velocity", "gyro_cov"),
    ("accel", "linear_acceleration", "accel_cov"),
)
"""sensor_msgs/Imu: (sensor, vector field, covariance column) of the two measured vectors."""


_META: list[tuple[bytes, dict[str, Any]]] = []
"""The last table metadata parsed by :func:`_meta`: (its raw JSON, the parsed dict)."""


def _meta(table: pa.Table) -> dict[str, Any]:
    """:func:`~imupipe.readers.table.metadata` of ``table``, parsed once for the batches that
    share it (the writer asks it about ten times a batch; each parse of the JSON 5-15 us). The
    dict is shared: the writer only reads it."""
    raw = (table.schema.metadata or {}).get(META_KEY)
    if not raw:
        return {}
    entry = _META[0] if _META else None  # one read: another thread may replace it
    if entry is None or entry[0] != raw:
        entry = (raw, metadata(table))
        _META[:] = [entry]
    return entry[1]


def written_streams(table: pa.Table) -> tuple[str, ...]:
    """The streams a writer writes, each to its topic: ``imu``, ``mag``, ``temperature``, and
    for a table read from a gyro and an accelerometer topic (its metadata names ``gyro`` or
    ``accel`` topics) also ``gyro`` and ``accel`` (see :func:`stream_rows`)."""
    topics = _meta(table).get("topics") or {}
    if any(s in topics for s in SPLIT):
        return ("imu", *SPLIT, "mag", "temperature")
    return ("imu", "mag", "temperature")


def stream_rows(table: pa.Table, stream: str) -> np.ndarray:
    """The table rows written as messages of ``stream``. In a table read from split topics
    (:func:`written_streams`) an IMU row with only a gyro sample is a ``gyro`` message, one with
    only an accelerometer sample an ``accel`` message, and only a row with both an ``imu``
    message: every row once, each topic's messages back on their topic."""
    if stream in SPLIT or (stream == "imu" and "gyro" in written_streams(table)):
        gyro, accel = sensor_mask(table, "gyro"), sensor_mask(table, "accel")
        mask = {"imu": gyro & accel, "gyro": gyro & ~accel, "accel": accel & ~gyro}[stream]
        return np.flatnonzero(mask)
    return np.flatnonzero(stream_mask(table, stream))


class StreamRows:
    """The rows of one stream of a table, ready to be encoded, any part at a time (see
    :func:`stream_fields`): ``rows`` (the table rows), ``stamp`` (header stamps, ns),
    ``fields`` (each message field's values, (m, k) or one row (1, k) every message gets) and
    ``frames``: per frame_id, the positions into ``rows`` of its messages (in order)."""

    def __init__(
        self,
        msgtype: str,
        rows: np.ndarray,
        stamp: np.ndarray,
        fields: dict[str, np.ndarray],
        frames: list[tuple[bytes, np.ndarray]],
    ) -> None:
        self.msgtype = msgtype
        self.rows = rows
        self.stamp = stamp
        self.fields = fields
        self.frames = frames

    def record_size(self, frame_id: bytes, encoding: str = "cdr", prefix: int = 0) -> int:
        """Bytes of each encoded message of ``frame_id`` (``prefix`` included)."""
        return cdr.layout(self.msgtype, len(frame_id), encoding, prefix).itemsize

    def encode(
        self, frame_id: bytes, at: np.ndarray | slice, encoding: str = "cdr", prefix: int = 0
    ) -> np.ndarray:
        """The messages at positions ``at`` of :attr:`rows` (all of one frame_id), encoded
        with :func:`cdr.encode`: (len(at), prefix + L) uint8. Each message's bytes depend on
        its own row only, so any cut of the rows gives the same bytes."""
        n = len(self.rows)
        fields = {k: v if len(v) < n else v[at] for k, v in self.fields.items()}
        return cdr.encode(self.msgtype, self.stamp[at], frame_id, fields, encoding, prefix)


def stream_fields(table: pa.Table, stream: str) -> StreamRows:
    """The rows of ``stream`` (:func:`stream_rows`) and every field of their messages, read
    from the table (what :func:`encode_stream` writes; see there)."""
    rows = stream_rows(table, stream)
    n = len(rows)
    if n == 0:
        return StreamRows(STREAM_TYPES[stream], rows, rows, {}, [])
    t_ns = to_numpy(table.column("t_ns"))[rows]
    stamp = _column_or(table, "header_stamp_ns", rows, t_ns)
    meta_frame = _meta(table).get("frame_id", {}).get(stream, DEFAULT_FRAME)
    # defaults are one row, (1, k), broadcast by the encoder: no (n, 9) arrays of zeros
    zeros = np.zeros((1, 9))
    fields: dict[str, np.ndarray] = {}
    if stream in ("imu", *SPLIT):
        for name, vector, cov in IMU_VECTORS:
            covariance = _column_or(table, cov, rows, zeros)
            if stream in SPLIT and name != stream:
                fields[vector] = np.zeros((1, 3))
                fields[f"{vector}_covariance"] = covariance
                continue
            nan = np.full(n, np.nan)  # where the sensor is absent
            columns = SENSOR_COLUMNS[name]
            fields[vector] = np.column_stack([_column_or(table, c, rows, nan) for c in columns])
            absent = ~sensor_mask(table, name)[rows]
            if absent.any():
                covariance = np.array(np.broadcast_to(covariance, (n, 9)))
                covariance[absent, 0] = -1.0
            fields[f"{vector}_covariance"] = covariance
        quat = [f"orientation_{a}" for a in "xyzw"]
        if any(c in table.schema.names for c in quat):
            default_q = (0.0, 0.0, 0.0, 1.0)
            fields["orientation"] = np.column_stack(
                [
                    _column_or(table, c, rows, np.full(n, q))
                    for c, q in zip(quat, default_q, strict=True)
                ]
            )
        else:
            fields["orientation"] = np.array([[0.0, 0.0, 0.0, 1.0]])
        fields["orientation_covariance"] = _column_or(table, "orientation_cov", rows, NO_ESTIMATE)
    elif stream == "mag":
        fields["magnetic_field"] = sensor(table, "mag").values
        fields["magnetic_field_covariance"] = _column_or(table, "mag_cov", rows, zeros)
    else:
        fields["temperature"] = sensor(table, "temperature").values[:, 0]
        fields["variance"] = _column_or(table, "temperature_var", rows, np.zeros(1))
    if "frame_id" in table.schema.names:
        names, codes = _frame_codes(table.column("frame_id"), rows, meta_frame)
    else:
        names, codes = [meta_frame], np.zeros(n, dtype=np.int64)
    frames = []
    for code, name in enumerate(names):
        sel = np.arange(n) if len(names) == 1 else np.flatnonzero(codes == code)
        if len(sel):
            frames.append((name.encode(), sel))
    return StreamRows(STREAM_TYPES[stream], rows, stamp, fields, frames)


def encode_stream(
    table: pa.Table, stream: str, encoding: str = "cdr", prefix: int = 0
) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Encode every row of ``stream`` (:func:`stream_rows`) as CDR (or ROS 1 with
    ``encoding="ros1"``).

    Every field comes from the table: the header stamp is ``header_stamp_ns`` where the reader
    kept it (``time = "log"``), else ``t_ns``; values are written as they are, NaN included. In
    an Imu message whose gyro (or accel) is absent from the row (a CSV without those columns),
    the vector is NaN and element 0 of its covariance is -1, sensor_msgs/Imu's mark for "no
    data". A ``gyro`` (``accel``) message of split topics carries zeros in the vector it does
    not measure, as the cameras that publish such topics do. Optional columns left out take
    ROS defaults: orientation (0, 0, 0, 1) with covariance element 0 = -1 (no orientation
    estimate), other covariances zero.

    Returns ``(rows, groups)``: the table rows of the stream, and per frame_id a pair
    ``(positions into rows, payloads (m, prefix + L) uint8)`` (see :func:`cdr.encode`)."""
    prepared = stream_fields(table, stream)
    n = len(prepared.rows)
    groups = [
        (sel, prepared.encode(name, slice(None) if len(sel) == n else sel, encoding, prefix))
        for name, sel in prepared.frames
    ]
    return prepared.rows, groups


def _one_string(column: pa.Array) -> str | None:
    """The one string every row of ``column`` holds, when it has no null and holds one (a
    sensor's usual frame_id); else None (also for an empty column). Read from Arrow's buffers
    with numpy: a dictionary column by its indices, a string column by its offsets and bytes."""
    n = len(column)
    if n == 0 or column.null_count:
        return None
    if isinstance(column.type, pa.DictionaryType):
        indices = to_numpy(column.indices)
        if not (indices == indices[0]).all():
            return None
        value = column.dictionary[int(indices[0])]
        return None if not value.is_valid else str(value.as_py())
    wide = {pa.string(): np.int32, pa.large_string(): np.int64}.get(column.type)
    if wide is None:
        return None
    _, offsets_buf, data_buf = column.buffers()
    offsets = np.frombuffer(offsets_buf, dtype=wide)[column.offset : column.offset + n + 1]
    length = int(offsets[1] - offsets[0])
    if not (np.diff(offsets) == length).all():
        return None
    if length == 0:
        return ""
    data = np.frombuffer(data_buf, dtype=np.uint8)[offsets[0] : offsets[-1]].reshape(n, length)
    if not (data == data[0]).all():
        return None
    return data[0].tobytes().decode()


def _frame_codes(
    frames: pa.ChunkedArray, rows: np.ndarray, meta_frame: str
) -> tuple[list[str], np.ndarray]:
    """The distinct frame_ids of ``frames`` at ``rows`` (a null: ``meta_frame``) in order of
    first appearance, and each row's index into them: ``pc.dictionary_encode(pc.fill_null(
    frames.take(rows), meta_frame))``. A column that is one frame_id repeated (the usual case)
    is seen without ``pyarrow.compute`` (``take`` imports it too), whose import costs 0.05-0.09 s
    CPU: a tenth of converting a short log (issue 39)."""
    one = _one_string(frames.chunk(0) if frames.num_chunks == 1 else frames.combine_chunks())
    if one is not None:
        return [one], np.zeros(len(rows), dtype=np.int32)
    import pyarrow.compute as pc

    frames = pc.fill_null(frames.take(arrow_array(rows)), arrow_scalar(meta_frame, pa.string()))
    encoded = pc.dictionary_encode(frames.combine_chunks())
    return [str(x) for x in encoded.dictionary.to_pylist()], to_numpy(encoded.indices)


def message_times(table: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """(log time, publish time) of every row as MCAP's **uint64** ns: ``log_time_ns`` where the
    reader kept it, else ``t_ns``; ``publish_time_ns`` where kept, else the log time.

    The table's int64 columns hold a log's uint64 times as their bit pattern (a time past 2^63 - 1
    ns reads as negative); viewed as uint64 they are the log's own times again, so the whole
    uint64 range is written, ordered and indexed as the log had it."""
    t_ns = table.column("t_ns")
    log = table.column("log_time_ns") if "log_time_ns" in table.schema.names else t_ns
    if log.null_count:
        import pyarrow.compute as pc  # nulls only: see _frame_codes

        log = pc.fill_null(log, t_ns)
    log_u = to_numpy(log).view(np.uint64)
    if "publish_time_ns" not in table.schema.names:
        return log_u, log_u
    pub = table.column("publish_time_ns")
    if pub.null_count:
        import pyarrow.compute as pc

        pub = pc.fill_null(pub, log)
    return log_u, to_numpy(pub).view(np.uint64)


def _fill_record_headers(
    records: np.ndarray, channel: int, seq: np.ndarray, log: np.ndarray, pub: np.ndarray
) -> None:
    """Fill the 31-byte message record headers in front of the payloads of ``records`` (m, S)."""
    m, size = records.shape
    dt = np.dtype(
        {
            "names": ["op", "len", "ch", "seq", "log", "pub"],
            "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
            "offsets": [0, 1, 9, 11, 15, 23],
            "itemsize": size,
        }
    )
    head = records.reshape(-1).view(dt)
    head["op"] = OP_MESSAGE
    head["len"] = size - 9
    head["ch"] = channel
    head["seq"] = seq
    head["log"] = log
    head["pub"] = pub


def _conform(table: pa.Table, schema: pa.Schema) -> pa.Table:
    """``table`` with the columns of ``schema`` (a column it lacks: null, so the default)."""
    columns = [
        table.column(f.name).cast(f.type)
        if f.name in table.schema.names
        else pa.nulls(table.num_rows, f.type)
        for f in schema
    ]
    return pa.Table.from_arrays(columns, schema=schema)


def _where_to(table: pa.Table) -> tuple[Any, Any]:
    """The table metadata that the writer uses: topics, and the default frame_ids where rows have
    none of their own."""
    meta = _meta(table)
    column = table.column("frame_id") if "frame_id" in table.schema.names else None
    own = column is not None and column.null_count == 0
    return meta.get("topics"), None if own else meta.get("frame_id")


class McapTableWriter:
    """Stream common-table batches and carried-over messages into one MCAP file.

    ``McapTableWriter(path, calibration=None, topics=None)``; :meth:`write_table` (a batch of the
    common table), :meth:`write_raw` (RawMessage s), :meth:`close` -> messages per topic. As a
    context manager it closes on success and leaves the (unfinished) file for the caller's
    staging to discard on error. ``topics`` overrides stream -> topic names (default: the
    table's metadata, else ``/imu/data``, ``/imu/mag``, ``/imu/temperature``).
    """

    def __init__(
        self,
        path: str | Path,
        calibration: Mapping[str, Any] | None = None,
        topics: Mapping[str, str] | None = None,
        *,
        library: str = "imupipe",
        chunk_bytes: int = CHUNK_BYTES,
        slice_rows: int = SLICE_ROWS,
        raw_buffer_bytes: int = RAW_BUFFER_BYTES,
    ) -> None:
        self.path = Path(path)
        self.calibration = calibration
        self.topics = dict(topics or {})
        self.chunk_bytes = chunk_bytes
        self.slice_rows = slice_rows
        self.raw_buffer_bytes = raw_buffer_bytes
        self._rows: list[pa.Table] = []  # queued table rows, fewer than slice_rows
        self._queued = 0
        self._held: list[RawMessage] = []  # carried-over messages the rows have not passed
        self._held_bytes = 0
        self._passed = -1  # the largest log time of the rows written so far
        self._fh = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._compressor = zstandard.ZstdCompressor(level=1)
        self._schemas: dict[tuple[str, str, bytes], tuple[int, bytes]] = {}
        """Schema -> its id and record, written again in the summary."""
        self._channels: dict[tuple[str, str, int], tuple[int, bytes]] = {}
        """(topic, encoding, schema id) -> the channel's id and record."""
        self._topic_of: dict[int, str] = {}
        self._seq: dict[int, int] = {}
        self._counts: dict[int, int] = {}
        self._chunk_indexes: list[list[Any]] = []
        """The fields of each chunk's ChunkIndex record."""
        self._attachment_indexes: list[bytes] = []
        self._start = -1
        self._end = 0
        self._closed = False
        self._fh.write(MAGIC)
        self._fh.write(pack(OP_HEADER, "ros2", library))

    # -- plumbing --------------------------------------------------------------------------
    def _channel(self, topic: str, encoding: str, schema: tuple[str, str, bytes]) -> int:
        if schema not in self._schemas:
            sid = len(self._schemas) + 1
            self._schemas[schema] = (sid, pack(OP_SCHEMA, sid, *schema))
            self._fh.write(self._schemas[schema][1])
        sid = self._schemas[schema][0]
        key = (topic, encoding, sid)
        if key not in self._channels:
            cid = len(self._channels) + 1
            self._channels[key] = (cid, pack(OP_CHANNEL, cid, sid, topic, encoding, {}))
            self._topic_of[cid] = topic
            self._seq[cid] = 0
            self._counts[cid] = 0
            self._fh.write(self._channels[key][1])
        return self._channels[key][0]

    def _sequence(self, channel: int, m: int) -> np.ndarray:
        start = self._seq[channel]
        self._seq[channel] = start + m
        self._counts[channel] += m
        return (np.arange(start, start + m) & 0xFFFFFFFF).astype(np.uint32)

    def _write_messages(
        self, buf: np.ndarray, starts: np.ndarray, channels: np.ndarray, log: np.ndarray
    ) -> None:
        """Write message records laid end to end in ``buf`` (record i at ``starts[i]``) as
        chunks of about ``chunk_bytes``, each with its message indexes."""
        n = len(starts)
        if n == 0:
            return
        ends = np.append(starts[1:], len(buf))
        cuts = np.searchsorted(ends, np.arange(self.chunk_bytes, int(ends[-1]), self.chunk_bytes))
        bounds = unique(np.concatenate([[0], cuts + 1, [n]]).clip(0, n))
        for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):
            if b > a:
                self._write_chunk(buf, starts[a:b], int(ends[b - 1]), channels[a:b], log[a:b])

    def _write_chunk(
        self, buf: np.ndarray, starts: np.ndarray, stop: int, channels: np.ndarray, log: np.ndarray
    ) -> None:
        base = int(starts[0])
        raw = memoryview(np.ascontiguousarray(buf[base:stop]))  # no copy: zstd and crc32 read it
        compressed = self._compressor.compress(raw)
        start_t, end_t = int(log.min()), int(log.max())
        self._start = start_t if self._start < 0 else min(self._start, start_t)
        self._end = max(self._end, end_t)
        head = struct.pack("<QQQI", start_t, end_t, len(raw), crc32(raw))  # zlib.crc32's value
        head += struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", len(compressed))
        chunk_start = self._fh.tell()
        self._fh.write(struct.pack("<BQ", OP_CHUNK, len(head) + len(compressed)))
        self._fh.write(head)
        self._fh.write(compressed)
        chunk_length = self._fh.tell() - chunk_start
        offsets: dict[int, int] = {}  # the message index of each channel in the chunk
        index_start = self._fh.tell()
        one = len(channels) and channels[0] == channels[-1] and (channels == channels[0]).all()
        for cid in [int(channels[0])] if one else unique(channels).tolist():
            sel = slice(None) if one else channels == cid
            pairs = np.empty((len(channels) if one else int(sel.sum()), 2), dtype="<u8")
            pairs[:, 0] = log[sel]
            pairs[:, 1] = starts[sel] - base
            offsets[cid] = self._fh.tell()
            self._fh.write(
                struct.pack("<BQHI", OP_MESSAGE_INDEX, 6 + pairs.nbytes, cid, pairs.nbytes)
            )
            self._fh.write(pairs.tobytes())
        self._chunk_indexes.append(
            [
                start_t,
                end_t,
                chunk_start,
                chunk_length,
                offsets,
                self._fh.tell() - index_start,
                "zstd",
                len(compressed),
                len(raw),
            ]
        )

    # -- public ----------------------------------------------------------------------------
    def write_table(self, table: pa.Table) -> None:
        """Write every sample of a common-table batch (any size: it is encoded in slices).

        Rows are queued and encoded ``slice_rows`` at a time, counted from the first row ever
        written, so the file does not depend on how the table was cut into batches: one whole
        table or the same rows in any batches give the same bytes. Memory: one slice."""
        if table.num_rows == 0:
            return
        if self._rows and _where_to(table) != _where_to(self._rows[0]):
            self._write_slice(self._queued)  # other topics or frames: not one slice
        if self._rows and table.schema != self._rows[0].schema:
            table = _conform(table, self._rows[0].schema)
        self._rows.append(table)
        self._queued += table.num_rows
        while self._queued >= self.slice_rows:
            self._write_slice(self.slice_rows)

    def write_raw(self, messages: Iterable[RawMessage]) -> None:
        """Write messages of other topics unchanged, log and publish times kept.

        A message is held until the table's rows have passed its log time (or until
        :meth:`close`), then written after the slice that passed it: give a batch's carried-over
        messages *before* its table rows (as :func:`write_mcap` does) and the file is the same
        whatever the batches. Held messages are written at once when they exceed
        ``raw_buffer_bytes`` (memory stays bounded when the sensor topics stop early)."""
        now: list[RawMessage] = []
        for msg in messages:
            if msg.log_time <= self._passed:
                now.append(msg)
            else:
                self._held.append(msg)
                self._held_bytes += len(msg.data)
        if now:
            self._write_raw_now(now)
        if self._held_bytes > self.raw_buffer_bytes:
            self._release(None)

    def _write_slice(self, m: int) -> None:
        """Encode and write the first ``m`` queued rows, then the held messages they passed."""
        parts, taken = [], 0
        while taken < m:
            head = self._rows[0]
            k = min(m - taken, head.num_rows)
            parts.append(head.slice(0, k))
            if k == head.num_rows:
                self._rows.pop(0)
            else:
                self._rows[0] = head.slice(k)
            taken += k
        self._queued -= m
        part = parts[0] if len(parts) == 1 else pa.concat_tables(parts)
        log = self._encode_rows(part)
        self._passed = max(self._passed, int(log.max()))
        self._release(self._passed)

    def _release(self, upto: int | None) -> None:
        """Write the held messages with log time <= ``upto`` (all when None), in log order."""
        if not self._held:
            return
        self._held.sort(key=lambda m: m.log_time)  # stable: arrival order among equal times
        k = len(self._held)
        if upto is not None:
            k = bisect.bisect_right([m.log_time for m in self._held], upto)
        if k:
            out, self._held = self._held[:k], self._held[k:]
            self._held_bytes = sum(len(m.data) for m in self._held)
            self._write_raw_now(out)

    def _encode_rows(self, table: pa.Table) -> np.ndarray:
        """Encode one slice; each (topic, frame_id) group of messages goes into its own chunks,
        in log-time order within the group; chunks are written in the order of their first log
        time (MCAP readers merge overlapping chunks by log time). Returns the log times.

        The chunks are planned from the record sizes (fixed per message type and frame_id)
        and each is encoded only when it is written: the slice's records are never all held
        at once (22 MB for a slice of Imu messages), and the bytes are those of encoding the
        whole slice and cutting it (each message's bytes depend on its own row only)."""
        topics = {**DEFAULT_TOPICS, **_meta(table).get("topics", {}), **self.topics}
        log_all, pub_all = message_times(table)
        pending = []  # (first log time, order, channel, stream rows, frame_id, positions, seq)
        for stream in written_streams(table):
            prepared = stream_fields(table, stream)
            n = len(prepared.rows)
            if not n:
                continue
            msgtype = STREAM_TYPES[stream]
            cid = self._channel(
                topics[stream], "cdr", (msgtype, "ros2msg", msgdef(msgtype).encode())
            )
            seq = self._sequence(cid, n)
            for name, sel in prepared.frames:
                log = log_all[prepared.rows[sel]]
                order = None
                if np.any(log[1:] < log[:-1]):
                    order = np.argsort(log, kind="stable")
                    log = log[order]
                whole = order is None and len(sel) == n  # positions a..b are rows a..b
                size = prepared.record_size(name, "cdr", RECORD_HEADER)
                per_chunk = max(1, self.chunk_bytes // size)
                for a in range(0, len(log), per_chunk):
                    b = min(a + per_chunk, len(log))
                    at = slice(a, b) if whole else sel[a:b] if order is None else sel[order[a:b]]
                    pending.append((int(log[a]), len(pending), cid, prepared, name, at, seq))
        pending.sort(key=lambda p: (p[0], p[1]))
        for _, _, cid, prepared, name, at, seq in pending:
            recs = prepared.encode(name, at, "cdr", RECORD_HEADER)
            rows = prepared.rows[at]
            log = log_all[rows]
            _fill_record_headers(recs, cid, seq[at], log, pub_all[rows])
            m, size = recs.shape
            self._write_chunk(
                recs.reshape(-1),
                np.arange(m, dtype=np.int64) * size,
                m * size,
                np.full(m, cid, dtype=np.int64),
                log,
            )
        return log_all

    def _write_raw_now(self, messages: Iterable[RawMessage]) -> None:
        """Write messages of other topics now, in the order given (one record each)."""
        pieces: list[bytes] = []
        starts: list[int] = []
        channels: list[int] = []
        logs: list[int] = []
        pos = 0
        for msg in messages:
            cid = self._channel(
                msg.topic,
                msg.message_encoding,
                (msg.schema_name, msg.schema_encoding, bytes(msg.schema_data)),
            )
            seq = self._seq[cid] & 0xFFFFFFFF
            self._seq[cid] += 1
            self._counts[cid] += 1
            head = struct.pack(
                "<BQHIQQ",
                OP_MESSAGE,
                22 + len(msg.data),
                cid,
                seq,
                msg.log_time,
                msg.publish_time,
            )
            pieces += [head, msg.data]
            starts.append(pos)
            channels.append(cid)
            logs.append(msg.log_time)
            pos += len(head) + len(msg.data)
            if pos >= self.chunk_bytes:
                self._flush_raw(pieces, starts, channels, logs)
                pieces, starts, channels, logs, pos = [], [], [], [], 0
        self._flush_raw(pieces, starts, channels, logs)

    def _flush_raw(
        self, pieces: list[bytes], starts: list[int], channels: list[int], logs: list[int]
    ) -> None:
        if starts:
            self._write_messages(
                np.frombuffer(b"".join(pieces), np.uint8),
                np.asarray(starts, np.int64),
                np.asarray(channels, np.int64),
                np.asarray(logs, np.uint64),
            )

    def close(self) -> dict[str, int]:
        """Attach the calibration, write the summary and footer; returns messages per topic."""
        if self._closed:
            return self.counts()
        if self._queued:
            self._write_slice(self._queued)
        self._release(None)
        self._closed = True
        if self.calibration is not None:
            now = time.time_ns()
            name, media_type = "calibration.json", "application/json"
            data = calibration_json(self.calibration).encode()
            offset = self._fh.tell()
            record = pack(OP_ATTACHMENT, now, now, name, media_type, data, 0)
            self._fh.write(record)
            self._attachment_indexes.append(
                pack(
                    OP_ATTACHMENT_INDEX, offset, len(record), now, now, len(data), name, media_type
                )
            )
        self._fh.write(pack(OP_DATA_END, 0))
        summary_start = self._fh.tell()
        stats = pack(
            OP_STATISTICS,
            sum(self._counts.values()),
            len(self._schemas),
            len(self._channels),
            len(self._attachment_indexes),
            0,  # metadata records
            len(self._chunk_indexes),
            max(self._start, 0),
            self._end,
            dict(self._counts),
        )
        groups = [
            (OP_SCHEMA, [record for _, record in self._schemas.values()]),
            (OP_CHANNEL, [record for _, record in self._channels.values()]),
            (OP_STATISTICS, [stats]),
            (OP_CHUNK_INDEX, [pack(OP_CHUNK_INDEX, *f) for f in self._chunk_indexes]),
            (OP_ATTACHMENT_INDEX, self._attachment_indexes),
        ]
        parts: list[bytes] = []
        offsets: list[bytes] = []  # a SummaryOffset record per group that has records
        at = summary_start
        for opcode, group in groups:
            size = sum(map(len, group))
            if size:
                offsets.append(pack(OP_SUMMARY_OFFSET, opcode, at, size))
                parts += group
                at += size
        summary = b"".join(parts + offsets)
        offset_start = at
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, offset_start), crc)
        self._fh.write(summary)
        self._fh.write(pack(OP_FOOTER, summary_start, offset_start, crc))
        self._fh.write(MAGIC)
        self._fh.close()
        return self.counts()

    def counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        out: dict[str, int] = {}
        for cid, n in self._counts.items():
            out[self._topic_of[cid]] = out.get(self._topic_of[cid], 0) + n
        return out

    def __enter__(self) -> McapTableWriter:
        return self

    def __exit__(self, exc_type: object, *_: object) -> None:
        if exc_type is None:
            self.close()
        elif not self._fh.closed:
            self._fh.close()


def write_mcap(
    path: str | Path,
    table: pa.Table,
    *,
    calibration: Mapping[str, Any] | None = None,
    topics: Mapping[str, str] | None = None,
    carry_over: Iterable[RawMessage] = (),
    library: str = "imupipe",
    chunk_bytes: int = CHUNK_BYTES,
    slice_rows: int = SLICE_ROWS,
) -> dict[str, int]:
    """Write ``table`` (and ``carry_over`` messages) to ``path``; returns messages per topic.

    The carried-over messages are given to the writer slice by slice, before the rows that pass
    their log times, the way a streamed read hands them over: the file is the same as the one
    written from :func:`~imupipe.readers.dispatch.iter_input` batches of the same log."""
    raw = sorted(carry_over, key=lambda m: m.log_time)
    raw_logs = [m.log_time for m in raw]
    with McapTableWriter(
        path, calibration, topics, library=library, chunk_bytes=chunk_bytes, slice_rows=slice_rows
    ) as writer:
        done = 0
        for start in range(0, table.num_rows, slice_rows):
            part = table.slice(start, slice_rows)
            if raw:
                upto = bisect.bisect_right(raw_logs, int(message_times(part)[0].max()), lo=done)
                writer.write_raw(raw[done:upto])
                done = max(done, upto)
            writer.write_table(part)
            report(start + part.num_rows, table.num_rows)
        writer.write_raw(raw[done:])
    return writer.counts()
