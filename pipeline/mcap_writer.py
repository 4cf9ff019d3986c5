"""Corrected logs as MCAP (SPEC "Corrected MCAP"), written chunk by chunk with numpy.

Profile ``ros2``, message encoding ``cdr``, schemas ``ros2msg`` (the message definitions rosbags
generates), so the ``mcap`` library's ROS 2 decoder, rosbags, Foxglove and ``ros2 bag`` read it.
The IMU stream is written as ``sensor_msgs/msg/Imu``, the magnetometer as
``sensor_msgs/msg/MagneticField`` (tesla), the temperature as ``sensor_msgs/msg/Temperature``
(degC), each row of the table exactly once, with the table's timestamps (header stamp = ``t_ns``,
log and publish time = ``log_time_ns`` when the reader kept it, else ``t_ns``). The calibration
that was applied travels as the attachment ``calibration.json``. Messages of other topics given
as ``carry_over`` are written unchanged.

:class:`McapTableWriter` streams: each ``write_table`` batch is encoded with
:func:`imupipe.readers.cdr.encode` (one structured array per frame_id), its message records
are built as one numpy array (``opcode, length, channel, sequence, log_time, publish_time,
payload``), cut into ~1 MiB chunks, zstd-compressed, and each chunk is followed by its
``MessageIndex`` records; the summary (schemas, channels, statistics, chunk and attachment
indexes) is written at :meth:`~McapTableWriter.close`. No Python loop runs per message except
for carried-over messages, which arrive as Python objects anyway.
"""

from __future__ import annotations

import bisect
import json
import struct
import time
import zlib
from collections.abc import Iterable, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Schema,
    Statistics,
    SummaryOffset,
)

from imupipe.readers import cdr
from imupipe.readers.spec import RawMessage
from imupipe.readers.table import metadata, sensor, stream_mask

DEFAULT_TOPICS = {"imu": "/imu/data", "mag": "/imu/mag", "temperature": "/imu/temperature"}
STREAM_TYPES = {
    "imu": "sensor_msgs/msg/Imu",
    "mag": "sensor_msgs/msg/MagneticField",
    "temperature": "sensor_msgs/msg/Temperature",
}
DEFAULT_FRAME = "imu"
MAGIC = b"\x89MCAP0\r\n"
CHUNK_BYTES = 1 << 20
RECORD_HEADER = 31
"""Bytes of a message record before its payload (opcode, length, channel, seq, 2 times)."""


@cache
def msgdef(msgtype: str) -> str:
    """The ros2msg schema text of a message type (as rosbags generates it)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)[0]


def _column_or(table: pa.Table, name: str, rows: np.ndarray, default: np.ndarray) -> np.ndarray:
    if name not in table.column_names:
        return default
    column = table.column(name).take(pa.array(rows))
    if isinstance(column.type, pa.FixedSizeListType):
        filled = column.combine_chunks()
        if filled.null_count:
            filled = pc.if_else(
                pc.is_valid(filled), filled, pa.scalar(default[0].tolist(), column.type)
            )
        return np.asarray(filled.flatten().to_numpy(zero_copy_only=False)).reshape(len(rows), -1)
    values = column.to_numpy(zero_copy_only=False)
    if values.dtype == object or np.issubdtype(values.dtype, np.floating):
        values = np.where(pc.is_valid(column).to_numpy(zero_copy_only=False), values, default)
    return values


def encode_stream(
    table: pa.Table, stream: str, encoding: str = "cdr", prefix: int = 0
) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Encode every row of ``stream`` as CDR (or ROS 1 with ``encoding="ros1"``).

    Returns ``(rows, groups)``: the table rows of the stream, and per frame_id a pair
    ``(positions into rows, payloads (m, prefix + L) uint8)`` (see :func:`cdr.encode`)."""
    rows = np.flatnonzero(stream_mask(table, stream))
    n = len(rows)
    t_ns = table.column("t_ns").to_numpy()[rows]
    meta_frame = metadata(table).get("frame_id", {}).get(stream, DEFAULT_FRAME)
    fields: dict[str, np.ndarray] = {}
    if stream == "imu":
        fields["angular_velocity"] = sensor(table, "gyro").values
        fields["linear_acceleration"] = sensor(table, "accel").values
        default_q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        quat = [
            _column_or(table, f"orientation_{a}", rows, default_q[:, i])
            for i, a in enumerate("xyzw")
        ]
        fields["orientation"] = np.column_stack(quat) if n else default_q
        no_orientation = np.zeros((n, 9))
        no_orientation[:, 0] = -1.0
        fields["orientation_covariance"] = _column_or(
            table, "orientation_cov", rows, no_orientation
        )
        zeros = np.zeros((n, 9))
        fields["angular_velocity_covariance"] = _column_or(table, "gyro_cov", rows, zeros)
        fields["linear_acceleration_covariance"] = _column_or(table, "accel_cov", rows, zeros)
    elif stream == "mag":
        fields["magnetic_field"] = sensor(table, "mag").values
        fields["magnetic_field_covariance"] = _column_or(table, "mag_cov", rows, np.zeros((n, 9)))
    else:
        fields["temperature"] = sensor(table, "temperature").values[:, 0]
        fields["variance"] = _column_or(table, "temperature_var", rows, np.zeros(n))
    if n == 0:
        return rows, []
    if "frame_id" in table.column_names:
        frames = pc.fill_null(table.column("frame_id").take(pa.array(rows)), meta_frame)
        encoded = pc.dictionary_encode(frames.combine_chunks())
        names = [str(x) for x in encoded.dictionary.to_pylist()]
        codes = encoded.indices.to_numpy(zero_copy_only=False)
    else:
        names, codes = [meta_frame], np.zeros(n, dtype=np.int64)
    groups = []
    for code, name in enumerate(names):
        sel = np.arange(n) if len(names) == 1 else np.flatnonzero(codes == code)
        if len(sel) == 0:
            continue
        whole = len(sel) == n
        payloads = cdr.encode(
            STREAM_TYPES[stream],
            t_ns if whole else t_ns[sel],
            name.encode(),
            fields if whole else {k: v[sel] for k, v in fields.items()},
            encoding,
            prefix,
        )
        groups.append((sel, payloads))
    return rows, groups


def _fill_record_headers(
    records: np.ndarray, channel: int, seq: np.ndarray, log: np.ndarray
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
    head["op"] = Opcode.MESSAGE
    head["len"] = size - 9
    head["ch"] = channel
    head["seq"] = seq
    head["log"] = log
    head["pub"] = log


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
    ) -> None:
        self.path = Path(path)
        self.calibration = calibration
        self.topics = dict(topics or {})
        self.chunk_bytes = chunk_bytes
        self._fh = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._compressor = zstandard.ZstdCompressor(level=1)
        self._schemas: dict[tuple[str, str, bytes], Schema] = {}
        self._channels: dict[tuple[str, str, int], Channel] = {}
        self._topic_of: dict[int, str] = {}
        self._seq: dict[int, int] = {}
        self._counts: dict[int, int] = {}
        self._chunk_indexes: list[ChunkIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._start = -1
        self._end = 0
        self._closed = False
        self._fh.write(MAGIC)
        self._write_record(Header(profile="ros2", library=library))

    # -- plumbing --------------------------------------------------------------------------
    def _write_record(self, record: Any) -> int:
        builder = RecordBuilder()
        record.write(builder)
        data = builder.end()
        self._fh.write(data)
        return len(data)

    def _channel(self, topic: str, encoding: str, schema: tuple[str, str, bytes]) -> int:
        if schema not in self._schemas:
            s = Schema(
                id=len(self._schemas) + 1, name=schema[0], encoding=schema[1], data=schema[2]
            )
            self._schemas[schema] = s
            self._write_record(s)
        sid = self._schemas[schema].id
        key = (topic, encoding, sid)
        if key not in self._channels:
            c = Channel(
                id=len(self._channels) + 1,
                topic=topic,
                message_encoding=encoding,
                schema_id=sid,
                metadata={},
            )
            self._channels[key] = c
            self._topic_of[c.id] = topic
            self._seq[c.id] = 0
            self._counts[c.id] = 0
            self._write_record(c)
        return self._channels[key].id

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
        bounds = np.unique(np.concatenate([[0], cuts + 1, [n]]).clip(0, n))
        for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):
            if b > a:
                self._write_chunk(buf, starts[a:b], int(ends[b - 1]), channels[a:b], log[a:b])

    def _write_chunk(
        self, buf: np.ndarray, starts: np.ndarray, stop: int, channels: np.ndarray, log: np.ndarray
    ) -> None:
        base = int(starts[0])
        raw = buf[base:stop].tobytes()
        compressed = self._compressor.compress(raw)
        start_t, end_t = int(log.min()), int(log.max())
        self._start = start_t if self._start < 0 else min(self._start, start_t)
        self._end = max(self._end, end_t)
        head = struct.pack("<QQQI", start_t, end_t, len(raw), zlib.crc32(raw))
        head += struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", len(compressed))
        chunk_start = self._fh.tell()
        self._fh.write(struct.pack("<BQ", Opcode.CHUNK, len(head) + len(compressed)))
        self._fh.write(head)
        self._fh.write(compressed)
        chunk_length = self._fh.tell() - chunk_start
        index = ChunkIndex(
            message_start_time=start_t,
            message_end_time=end_t,
            chunk_start_offset=chunk_start,
            chunk_length=chunk_length,
            message_index_offsets={},
            message_index_length=0,
            compression="zstd",
            compressed_size=len(compressed),
            uncompressed_size=len(raw),
        )
        index_start = self._fh.tell()
        for cid in np.unique(channels).tolist():
            sel = channels == cid
            pairs = np.empty((int(sel.sum()), 2), dtype="<u8")
            pairs[:, 0] = log[sel]
            pairs[:, 1] = starts[sel] - base
            index.message_index_offsets[cid] = self._fh.tell()
            self._fh.write(
                struct.pack("<BQHI", Opcode.MESSAGE_INDEX, 6 + pairs.nbytes, cid, pairs.nbytes)
            )
            self._fh.write(pairs.tobytes())
        index.message_index_length = self._fh.tell() - index_start
        self._chunk_indexes.append(index)

    # -- public ----------------------------------------------------------------------------
    def write_table(self, table: pa.Table) -> None:
        """Write every sample of a common-table batch.

        Each (topic, frame_id) group of messages goes into its own chunks, in log-time order
        within the group; chunks are written in the order of their first log time (MCAP
        readers merge overlapping chunks by log time)."""
        if table.num_rows == 0:
            return
        topics = {**DEFAULT_TOPICS, **metadata(table).get("topics", {}), **self.topics}
        if "log_time_ns" in table.column_names:
            log_all = pc.fill_null(table.column("log_time_ns"), table.column("t_ns")).to_numpy()
        else:
            log_all = table.column("t_ns").to_numpy()
        pending = []  # (first log time, order, channel, records, log times)
        for stream in ("imu", "mag", "temperature"):
            rows, groups = encode_stream(table, stream, prefix=RECORD_HEADER)
            if not len(rows):
                continue
            msgtype = STREAM_TYPES[stream]
            cid = self._channel(
                topics[stream], "cdr", (msgtype, "ros2msg", msgdef(msgtype).encode())
            )
            seq = self._sequence(cid, len(rows))
            for sel, recs in groups:
                log = log_all[rows[sel]]
                _fill_record_headers(recs, cid, seq[sel], log)
                if np.any(log[1:] < log[:-1]):
                    order = np.argsort(log, kind="stable")
                    recs, log = recs[order], log[order]
                per_chunk = max(1, self.chunk_bytes // recs.shape[1])
                for a in range(0, len(log), per_chunk):
                    b = min(a + per_chunk, len(log))
                    pending.append((int(log[a]), len(pending), cid, recs[a:b], log[a:b]))
        pending.sort(key=lambda p: (p[0], p[1]))
        for _, _, cid, recs, log in pending:
            m, size = recs.shape
            self._write_chunk(
                recs.reshape(-1),
                np.arange(m, dtype=np.int64) * size,
                m * size,
                np.full(m, cid, dtype=np.int64),
                log,
            )

    def write_raw(self, messages: Iterable[RawMessage]) -> None:
        """Write messages of other topics unchanged (one record each)."""
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
                Opcode.MESSAGE,
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
                np.asarray(logs, np.int64),
            )

    def close(self) -> dict[str, int]:
        """Attach the calibration, write the summary and footer; returns messages per topic."""
        if self._closed:
            return self.counts()
        self._closed = True
        if self.calibration is not None:
            now = time.time_ns()
            att = Attachment(
                create_time=now,
                log_time=now,
                name="calibration.json",
                media_type="application/json",
                data=json.dumps(self.calibration, indent=2).encode(),
            )
            offset = self._fh.tell()
            length = self._write_record(att)
            self._attachment_indexes.append(
                AttachmentIndex(
                    offset=offset,
                    length=length,
                    create_time=now,
                    log_time=now,
                    data_size=len(att.data),
                    name=att.name,
                    media_type=att.media_type,
                )
            )
        self._write_record(DataEnd(0))
        summary_start = self._fh.tell()
        builder = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records: Iterable[Any]) -> None:
            begin = builder.count
            for r in records:
                r.write(builder)
            if builder.count > begin:
                offsets.append(SummaryOffset(opcode, summary_start + begin, builder.count - begin))

        stats = Statistics(
            message_count=sum(self._counts.values()),
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=len(self._attachment_indexes),
            metadata_count=0,
            chunk_count=len(self._chunk_indexes),
            message_start_time=max(self._start, 0),
            message_end_time=self._end,
            channel_message_counts=dict(self._counts),
        )
        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, self._attachment_indexes)
        offset_start = summary_start + builder.count
        for o in offsets:
            o.write(builder)
        summary = builder.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
        self._fh.write(summary)
        self._write_record(Footer(summary_start, offset_start, crc))
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
    slice_rows: int = 100_000,
) -> dict[str, int]:
    """Write ``table`` (and ``carry_over`` messages) to ``path``; returns messages per topic.

    The table is written in slices of ``slice_rows`` rows, each followed by the carried-over
    messages up to its last log time, so the file stays in (nearly) log-time order."""
    raw = sorted(carry_over, key=lambda m: m.log_time)
    raw_logs = [m.log_time for m in raw]
    with McapTableWriter(
        path, calibration, topics, library=library, chunk_bytes=chunk_bytes
    ) as writer:
        done = 0
        for start in range(0, table.num_rows, slice_rows):
            part = table.slice(start, slice_rows)
            writer.write_table(part)
            if raw:
                log = "log_time_ns" if "log_time_ns" in part.column_names else "t_ns"
                last = pc.max(pc.fill_null(part.column(log), part.column("t_ns"))).as_py()
                upto = bisect.bisect_right(raw_logs, last, lo=done)
                writer.write_raw(raw[done:upto])
                done = upto
        writer.write_raw(raw[done:])
    return writer.counts()
