"""ROS 1 bags (v2.0; uncompressed, bz2 or lz4 chunks) into the common table, chunk by chunk.

A bag record is ``uint32 header_len, header (uint32-length-prefixed name=value fields), uint32
data_len, data``. The reader takes the connections and chunk infos from the index section at
``index_pos``, then reads each chunk, decompresses it, and takes the ``IndexData`` records that
follow it: per connection, ``(uint32 sec, uint32 nsec, uint32 offset)`` of every message data
record in the decompressed chunk. The message payloads are then located and decoded with numpy
(:func:`imupipe.readers.cdr.decode` with the ``ros1`` wire format).

A bag without messages (no chunk; its index may end the file) is valid and empty. An unindexed
bag (``index_pos`` 0: a recording that was interrupted before ``rosbag`` wrote its index) is
read by scanning (:meth:`Ros1Bag._scan`, with a warning): the chunk records one after the other
and the ``IndexData`` records that follow each; the connection records, which such a bag holds
only inside its chunks, are found by walking the records between the indexed messages of the
chunks that bring a new connection; a chunk without ``IndexData`` after it is walked record by
record. The chunk an interrupted ``rosbag record`` was writing (its header still has the
place-holder sizes 0, its records run to the end of the file) is decompressed as far as its
bytes go and walked up to its last complete record. A record cut off by the end of the file
ends the scan (with a warning): the messages before it are read.

Messages of every other topic are carried over converted to ROS 2 CDR the way
``rosbags-convert`` does it (:func:`ros2_converter`).
"""

from __future__ import annotations

import bz2
import collections
import io
import struct
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from imupipe.readers.cdr import unaligned
from imupipe.readers.compression import PREFETCH, decompress_chunk, decompress_workers, done
from imupipe.readers.decoded import Piece, concat, decode_piece
from imupipe.readers.errors import READ_TO_CUT, ReadError
from imupipe.readers.mapped import Batch, Definition
from imupipe.readers.progress import report
from imupipe.readers.sources import carry_sources, iter_sources, read_sources
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.readers.topics import normalize_type

VERSION_LINE = b"#ROSBAG V2.0\n"
OP_MSG, OP_BAG_HEADER, OP_INDEX, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 2, 3, 4, 5, 6, 7


def ros2_converter(
    typename: str, msgdef: str, where: str, store: object | None = None
) -> tuple[str, bytes, Callable[[bytes], memoryview]]:
    """(ROS 2 type name, ros2msg schema, ROS 1 -> CDR converter) for a ROS 1 message type, as
    ``rosbags-convert`` builds them: the bag's own definitions with the ROS 2 ``Header``."""
    from rosbags.convert.converter import STATIC_MSGTYPE_RENAMES
    from rosbags.typesys import get_types_from_msg

    try:
        if store is None:
            store = ros2_typestore({typename: msgdef})
        dst = STATIC_MSGTYPE_RENAMES.get(typename, typename)
        if dst not in store.fielddefs:  # type: ignore[attr-defined]
            types = get_types_from_msg(store.generate_msgdef(typename, ros_version=2)[0], dst)  # type: ignore[attr-defined]
            types.pop("std_msgs/msg/Header", None)
            store.register(types)  # type: ignore[attr-defined]
        schema = store.generate_msgdef(dst, ros_version=2)[0]  # type: ignore[attr-defined]
    except Exception as exc:  # noqa: BLE001 - a definition rosbags cannot parse
        raise ReadError(
            f"{where}: cannot use the message definition of {typename} ({exc})"
        ) from None
    return dst, schema.encode(), lambda raw: store.ros1_to_cdr(raw, dst)  # type: ignore[attr-defined]


def ros2_typestore(definitions: dict[str, str]) -> object:
    """A rosbags typestore of ROS 1 definitions (type -> msgdef text) with ROS 2's Header,
    like ``rosbags.convert`` creates for a ROS 1 -> ROS 2 conversion."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    types: dict = {}
    for typename, text in definitions.items():
        types.update(get_types_from_msg(text, typename))
    header = get_typestore(Stores.ROS2_FOXY).fielddefs["std_msgs/msg/Header"]
    store = get_typestore(Stores.EMPTY)
    store.register({**types, "std_msgs/msg/Header": header})
    return store


def _fields(header: bytes, where: str) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    pos = 0
    while pos < len(header):
        if pos + 4 > len(header):
            raise ReadError(f"{where}: corrupt record header")
        (n,) = struct.unpack_from("<I", header, pos)
        field = header[pos + 4 : pos + 4 + n]
        if len(field) != n or b"=" not in field:
            raise ReadError(f"{where}: corrupt record header")
        name, _, value = field.partition(b"=")
        out[name.decode(errors="replace")] = value
        pos += 4 + n
    return out


def _u32(fields: dict[str, bytes], key: str, where: str) -> int:
    value = fields.get(key)
    if value is None or len(value) < 4:
        raise ReadError(f"{where}: record lacks field '{key}'")
    return int.from_bytes(value[:4], "little")


@dataclass
class Connection:
    id: int
    topic: str
    msgtype: str
    msgdef: str


@dataclass
class BagChunk:
    buf: np.ndarray
    index: dict[int, tuple[np.ndarray, np.ndarray]]
    """connection id -> (log time ns, record offsets) in index order."""
    where: str
    bound: int
    """No later chunk has a message with a log time below this (from the chunk infos)."""

    def payloads(self, conn: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(log ns, payload start, payload length) of a connection's messages."""
        log, off = self.index[conn]
        buf = self.buf
        if len(off) == 0:
            return log, off, off
        u4 = unaligned(buf, "<u4")
        if off.max() + 8 > len(buf):
            raise ReadError(f"{self.where}: index points outside its chunk")
        hl = u4[off].astype(np.int64)
        dl_pos = off + 4 + hl
        if np.any(dl_pos + 4 > len(buf)):
            raise ReadError(f"{self.where}: message record header runs past its chunk")
        dl = u4[dl_pos].astype(np.int64)
        start = dl_pos + 4
        if np.any(start + dl > len(buf)):
            raise ReadError(f"{self.where}: message runs past the end of its chunk")
        return log, start, dl


class Ros1Bag:
    """One ROS 1 bag as a :class:`~imupipe.readers.sources.LogSource`."""

    format = "ros1"

    def __init__(self, path: str | Path, salvage: bool = False) -> None:
        """``salvage``: a bag cut off before its index (a copy or recording stopped part-way) is
        read by scanning its chunks up to the cut, with a warning, instead of refused."""
        self.path = Path(path)
        try:
            self.size = self.path.stat().st_size
            with open(self.path, "rb") as fh:
                if fh.read(len(VERSION_LINE)) != VERSION_LINE:
                    raise ReadError(f"{self.path}: not a ROS 1 bag v2.0 (bad version line)")
                op, fields, _ = self._record(fh)
                if op != OP_BAG_HEADER:
                    raise ReadError(f"{self.path}: corrupt bag (no bag header record)")
                encryptor = fields.get("encryptor", b"").decode(errors="replace")
                if encryptor:
                    raise ReadError(f"{self.path}: encrypted bag ({encryptor}) is not supported")
                index_pos = int.from_bytes(fields.get("index_pos", b"\0" * 8)[:8], "little")
                chunk_count = int.from_bytes(fields.get("chunk_count", b"\0" * 4)[:4], "little")
                self.connections: dict[int, Connection] = {}
                self.chunk_infos: list[tuple[int, int, dict[int, int]]] = []
                self.walked: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
                """Chunk position -> its index, for the chunks of an unindexed bag that have no
                ``IndexData`` records (found by walking the chunk)."""
                self.open_buffers: dict[int, np.ndarray] = {}
                """Chunk position -> what decompressed of the chunk an interrupted recording
                left open (an unindexed bag's last)."""
                self.warnings: list[str] = []
                self.indexed = index_pos != 0
                if not self.indexed:
                    self._scan(fh)
                elif index_pos > self.size or (index_pos == self.size and chunk_count):
                    if not salvage:
                        raise ReadError(
                            f"{self.path}: truncated bag (index at byte {index_pos} is past the "
                            "end; --read-truncated reads it up to the cut)"
                        )
                    self.indexed = False
                    self._scan(fh, truncated=(index_pos, chunk_count))
                else:
                    self._read_index(fh, index_pos)
        except OSError as exc:
            raise ReadError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        self.chunk_infos.sort()

    def _read_index(self, fh: io.BufferedReader, index_pos: int) -> None:
        """The connections and chunk infos of the index section at ``index_pos``."""
        fh.seek(index_pos)
        while fh.tell() < self.size:
            op, fields, data = self._record(fh)
            if op == OP_CONNECTION:
                self._connection(fields, data)
            elif op == OP_CHUNK_INFO:
                pos = int.from_bytes(fields.get("chunk_pos", b"")[:8], "little")
                start = fields.get("start_time", b"\0" * 8)
                t0 = int.from_bytes(start[:4], "little") * 10**9 + int.from_bytes(
                    start[4:8], "little"
                )
                pairs = np.frombuffer(data[: len(data) // 8 * 8], "<u4").reshape(-1, 2)
                self.chunk_infos.append((pos, t0, {int(c): int(n) for c, n in pairs}))

    def _connection(self, fields: dict[str, bytes], data: bytes) -> None:
        where = f"{self.path}: connection record"
        conn = _u32(fields, "conn", where)
        info = _fields(data, where)
        self.connections[conn] = Connection(
            conn,
            fields.get("topic", b"").decode(errors="replace"),
            normalize_type(info.get("type", b"").decode(errors="replace")),
            info.get("message_definition", b"").decode(errors="replace"),
        )

    def _scan(self, fh: io.BufferedReader, truncated: tuple[int, int] | None = None) -> None:
        """Chunk infos and connections of an unindexed bag, from its records (see the module
        docstring). Only the chunks that bring a new connection, or have no ``IndexData``, are
        decompressed here. ``truncated``: (index position, chunk count) of the bag header of a
        bag cut off before its index; only the chunks complete before the cut are read."""
        cut = opened = None
        chunks: list[tuple[int, dict[str, bytes], int, int]] = []
        """(position, header fields, data position, data length) of each chunk record."""
        indexes: list[dict[int, tuple[np.ndarray, np.ndarray]]] = []
        while fh.tell() < self.size:
            pos = fh.tell()
            try:
                op, fields, data_pos, data_len = self._head(fh)
            except _CutOff:
                cut = pos
                break
            if op == OP_CHUNK and data_len == 0 and data_pos < self.size:
                opened = (pos, fields, data_pos)  # the chunk rosbag was writing: to the end
                break
            if op == OP_CHUNK:
                chunks.append((pos, fields, data_pos, data_len))
                indexes.append({})
            elif op == OP_INDEX and chunks:
                where = f"{self.path}: index data record at byte {pos}"
                conn, log, off = _index_entries(fields, fh.read(data_len), where)
                indexes[-1][conn] = (log, off)
            elif op == OP_CONNECTION:
                self._connection(fields, fh.read(data_len))
            fh.seek(data_pos + data_len)
        if cut is not None and chunks:
            indexes[-1] = {}  # the file ends in the last chunk's IndexData: walk the chunk
        if truncated is not None:
            index_pos, chunk_count = truncated
            if not chunks:
                raise ReadError(
                    f"{self.path}: truncated bag (cut off at byte {cut}, before its first "
                    "complete chunk: nothing to read)"
                )
            cut = self.size if cut is None else cut
            if opened is not None:  # a cut chunk whose length field says 0: not read
                cut, opened = opened[0], None
            self.warnings.append(
                f"{self.path}: truncated bag: cut off at byte {cut} (the index was at byte "
                f"{index_pos}, the file has {self.size} bytes); {READ_TO_CUT}: "
                f"{len(chunks)} of its {chunk_count} chunks are read, the {self.size - cut} "
                f"bytes from there to the end of the file ({chunk_count - len(chunks)} "
                "chunks) are skipped with the messages in them"
            )
        else:
            self.warnings.append(
                f"{self.path}: the bag is not indexed (an interrupted recording?): read by "
                f"scanning its {len(chunks) + (opened is not None)} chunks"
                + (
                    f"; it is cut off at byte {cut}, the record there is skipped"
                    if cut is not None
                    else ""
                )
            )
        for (pos, fields, data_pos, data_len), index in zip(chunks, indexes, strict=True):
            where = f"{self.path}: chunk at byte {pos}"
            new = [c for c in index if c not in self.connections]
            if index and not new:
                buf = None
            else:
                fh.seek(data_pos)
                buf = self._decompress(fields, fh.read(data_len), where)
            if not index:
                assert buf is not None
                index = self.walked[pos] = self._walk(buf, where)
            elif new:
                assert buf is not None
                self._walk_gaps(buf, index, where)
            self._chunk_info(pos, index)
        if opened is not None:
            self._open_chunk(fh, *opened)

    def _chunk_info(self, pos: int, index: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
        starts = [int(log.min()) for log, _ in index.values() if len(log)]
        counts = {c: len(log) for c, (log, _) in index.items()}
        self.chunk_infos.append((pos, min(starts, default=0), counts))

    def _open_chunk(
        self, fh: io.BufferedReader, pos: int, fields: dict[str, bytes], at: int
    ) -> None:
        """The chunk an interrupted ``rosbag record`` was writing: its header still has the
        place-holder sizes (0) and its records, compressed or not, run to the end of the file.
        What decompresses of it is walked up to its last complete record."""
        where = f"{self.path}: chunk at byte {pos} (not closed)"
        compression = fields.get("compression", b"none").decode(errors="replace")
        fh.seek(at)
        data = fh.read()
        try:
            if compression == "bz2":
                data = bz2.BZ2Decompressor().decompress(data)
            elif compression == "lz4":
                import lz4.frame

                data = lz4.frame.LZ4FrameDecompressor().decompress(data)
            elif compression not in ("none", ""):
                raise ReadError(f"{where}: unsupported chunk compression '{compression}'")
        except (OSError, EOFError, RuntimeError, ValueError) as exc:
            self.warnings.append(f"{where}: cannot be decompressed ({exc}): skipped")
            return
        buf = np.frombuffer(data, np.uint8)
        index = self._walk(buf, where, partial=True)
        n = sum(len(log) for log, _ in index.values())
        self.warnings.append(
            f"{self.path}: the last chunk (at byte {pos}) was not closed (the recording stopped "
            f"while writing it): its {n} complete messages are read"
        )
        self.walked[pos], self.open_buffers[pos] = index, buf
        self._chunk_info(pos, index)

    def _walk(
        self, buf: np.ndarray, where: str, partial: bool = False
    ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Every record of a chunk without ``IndexData``, one by one: the connection records
        are taken, and the index (connection -> log times, record offsets) of the messages
        (``partial``: up to the last complete record)."""
        found: dict[int, tuple[list[int], list[int]]] = {}
        for pos, op, fields, data in _records(buf, 0, where, partial=partial):
            if op == OP_CONNECTION:
                self._connection(fields, data)
            elif op == OP_MSG:
                conn = _u32(fields, "conn", where)
                stamp = fields.get("time", b"")
                if len(stamp) < 8:
                    raise ReadError(f"{where}: message record lacks field 'time'")
                t = int.from_bytes(stamp[:4], "little") * 10**9 + int.from_bytes(
                    stamp[4:8], "little"
                )
                logs, offs = found.setdefault(conn, ([], []))
                logs.append(t)
                offs.append(pos)
        return {
            c: (np.asarray(t, np.int64), np.asarray(o, np.int64)) for c, (t, o) in found.items()
        }

    def _walk_gaps(
        self, buf: np.ndarray, index: dict[int, tuple[np.ndarray, np.ndarray]], where: str
    ) -> None:
        """The connection records of a chunk whose messages are indexed: walked from each place
        that is not an indexed message (the chunk's start, the end of each message) up to the
        next message."""
        off = np.sort(np.concatenate([o for _, o in index.values()]))
        chunk = BagChunk(buf, {0: (np.zeros(len(off), np.int64), off)}, where, 0)
        _, start, length = chunk.payloads(0)
        ends = start + length
        known = set(off.tolist())
        for gap in sorted({0, *ends.tolist()} - known):
            for _, op, fields, data in _records(buf, gap, where, stop=known):
                if op == OP_CONNECTION:
                    self._connection(fields, data)

    def _head(self, fh: io.BufferedReader) -> tuple[int, dict[str, bytes], int, int]:
        """(op, header fields, data position, data length) of the record at the file position,
        leaving the file there; :class:`_CutOff` when the file ends inside it."""
        pos = fh.tell()
        head = fh.read(4)
        if len(head) < 4:
            raise _CutOff
        (hl,) = struct.unpack("<I", head)
        if pos + 8 + hl > self.size:
            raise _CutOff
        fields = _fields(fh.read(hl), f"{self.path}: record at byte {pos}")
        (dl,) = struct.unpack("<I", fh.read(4))
        if fh.tell() + dl > self.size:
            raise _CutOff
        return fields.get("op", b"\xff")[0], fields, fh.tell(), dl

    def _record(self, fh: io.BufferedReader) -> tuple[int, dict[str, bytes], bytes]:
        pos = fh.tell()
        where = f"{self.path}: record at byte {pos}"
        head = fh.read(4)
        if len(head) < 4:
            raise ReadError(f"{self.path}: truncated bag (record at byte {pos} cut off)")
        (hl,) = struct.unpack("<I", head)
        if pos + 8 + hl > self.size:
            raise ReadError(f"{self.path}: truncated bag (record at byte {pos} runs past the end)")
        fields = _fields(fh.read(hl), where)
        (dl,) = struct.unpack("<I", fh.read(4))
        if fh.tell() + dl > self.size:
            raise ReadError(f"{self.path}: truncated bag (record at byte {pos} runs past the end)")
        data = fh.read(dl)
        op = fields.get("op", b"\xff")[0]
        return op, fields, data

    def topic_types(self) -> dict[str, str]:
        return {c.topic: c.msgtype for c in self.connections.values()}

    def topic_counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for _, _, counts in self.chunk_infos:
            for conn, n in counts.items():
                if conn in self.connections:
                    topic = self.connections[conn].topic
                    out[topic] = out.get(topic, 0) + n
        return out

    def first_time(self) -> int:
        return min((t for _, t, _ in self.chunk_infos), default=0)

    def topic_times(self) -> dict[str, np.ndarray]:
        times: dict[str, list[np.ndarray]] = {}
        for chunk in self.bag_chunks():
            for cid, (log, _) in chunk.index.items():
                if cid in self.connections:
                    times.setdefault(self.connections[cid].topic, []).append(log)
        return {t: np.concatenate(v) for t, v in times.items()}

    def bag_chunks(self) -> Iterator[BagChunk]:
        """Every chunk, decompressed, with its index, in file order. Worker threads decompress
        the next chunks while the caller decodes the current one (lz4 and bz2 release the
        GIL)."""
        starts = [t for _, t, _ in self.chunk_infos]
        bounds = list(np.minimum.accumulate(starts[::-1])[::-1][1:]) + [2**63 - 1] if starts else []
        queue: collections.deque[BagChunk] = collections.deque()
        with open(self.path, "rb") as fh, decompress_workers() as worker:
            for (pos, _, counts), bound in zip(self.chunk_infos, bounds, strict=True):
                report(pos, self.size)  # the chunks before this one are read
                fh.seek(pos)
                where = f"{self.path}: chunk at byte {pos}"
                op, fields, data = self._record(fh)
                if op != OP_CHUNK:
                    raise ReadError(f"{where}: the index points at a record that is not a chunk")
                if pos in self.open_buffers:  # decompressed (what could be) by the scan
                    future: Future = Future()
                    future.set_result(self.open_buffers[pos])
                elif len(self.chunk_infos) == 1:  # nothing to overlap: no thread hand-off
                    future = done(self._decompress(fields, data, where))
                else:
                    future = worker.submit(self._decompress, fields, data, where)
                if pos in self.walked:
                    index = self.walked[pos]
                else:
                    index = {}
                    for _ in range(len(counts)):
                        op, fields, data = self._record(fh)
                        if op != OP_INDEX:
                            raise ReadError(f"{where}: index data missing after the chunk")
                        conn, log, off = _index_entries(fields, data, where)
                        index[conn] = (log, off)
                queue.append(BagChunk(future, index, where, int(bound)))  # type: ignore[arg-type]
                if len(queue) > PREFETCH:
                    yield _decompressed(queue.popleft())
            while queue:
                yield _decompressed(queue.popleft())

    def _decompress(self, fields: dict[str, bytes], data: bytes, where: str) -> np.ndarray:
        compression = fields.get("compression", b"none").decode(errors="replace")
        size = _u32(fields, "size", where)
        return decompress_chunk(data, compression, size, where)

    def chunks(
        self, streams: dict[str, str], carry: bool, decode: bool = True, whole: bool = False
    ) -> Iterator[tuple[dict[str, Piece], list[RawMessage], int]]:
        by_topic = {topic: stream for stream, topic in streams.items()}
        chosen = {
            cid: by_topic[c.topic] for cid, c in self.connections.items() if c.topic in by_topic
        }
        converters: dict[int, tuple[str, bytes, Callable]] = {}
        store = None
        for chunk in self.bag_chunks():
            pieces: dict[str, list[Piece]] = {}
            if decode:
                for cid, stream in chosen.items():
                    if cid in chunk.index:
                        pieces.setdefault(stream, []).append(self._decode(chunk, cid, stream))
            raw: list[RawMessage] = []
            if carry:
                for cid in sorted(chunk.index):
                    if cid in chosen:
                        continue
                    conn = self.connections.get(cid)
                    if conn is None:
                        raise ReadError(
                            f"{chunk.where}: messages of connection {cid}, which the bag never defines"
                        )
                    if cid not in converters:
                        if store is None:
                            store = self._typestore()
                        converters[cid] = ros2_converter(
                            conn.msgtype, conn.msgdef, f"{self.path}: topic '{conn.topic}'", store
                        )
                    raw.extend(self._raw(chunk, conn, converters[cid]))
                raw.sort(key=lambda m: m.log_time)
            yield {s: concat(p, s) for s, p in pieces.items()}, raw, chunk.bound

    def _typestore(self) -> object:
        try:
            return ros2_typestore({c.msgtype: c.msgdef for c in self.connections.values()})
        except Exception as exc:  # noqa: BLE001
            raise ReadError(
                f"{self.path}: cannot parse the bag's message definitions ({exc})"
            ) from None

    def definitions(self) -> dict[str, Definition]:
        """Topic -> its type and the connection header's definition text."""
        out: dict[str, Definition] = {}
        for c in self.connections.values():
            out.setdefault(c.topic, Definition(c.msgtype, "ros1", "ros1msg", c.msgdef.encode()))
        return out

    def payloads(self, topics: set[str]) -> Iterator[list[tuple[str, Batch]]]:
        """Per chunk: the messages of ``topics`` (see :mod:`imupipe.readers.mapped`)."""
        conns = {cid: c.topic for cid, c in self.connections.items() if c.topic in topics}
        for chunk in self.bag_chunks():
            out = []
            for cid, topic in conns.items():
                if cid in chunk.index:
                    log, start, length = chunk.payloads(cid)
                    out.append((topic, Batch(chunk.buf, start, length, log)))
            yield out

    def _decode(self, chunk: BagChunk, cid: int, stream: str) -> Piece:
        log, start, length = chunk.payloads(cid)
        where = f"{self.path}: topic '{self.connections[cid].topic}'"
        return decode_piece(chunk.buf, start, length, log, stream, "ros1", where)

    def _raw(self, chunk: BagChunk, conn: Connection, converter: tuple) -> list[RawMessage]:
        name, schema, convert = converter
        log, start, length = chunk.payloads(conn.id)
        out = []
        buf = chunk.buf
        for lt, s, n in zip(log.tolist(), start.tolist(), length.tolist(), strict=True):
            try:
                data = bytes(convert(buf[s : s + n].tobytes()))
            except Exception as exc:  # noqa: BLE001
                raise ReadError(
                    f"{self.path}: topic '{conn.topic}': message at log time {lt} cannot be "
                    f"converted to ROS 2 ({exc})"
                ) from None
            out.append(RawMessage(conn.topic, name, "ros2msg", schema, "cdr", data, lt, lt))
        return out


class _CutOff(Exception):
    """The file ends inside a record (an unindexed bag's last record)."""


def _index_entries(
    fields: dict[str, bytes], data: bytes, where: str
) -> tuple[int, np.ndarray, np.ndarray]:
    """(connection, log times ns, record offsets) of an ``IndexData`` record."""
    conn = _u32(fields, "conn", where)
    count = _u32(fields, "count", where)
    if len(data) < 12 * count:
        raise ReadError(f"{where}: index data of connection {conn} is cut off")
    entries = np.frombuffer(data, "<u4", count=3 * count).reshape(-1, 3)
    log = entries[:, 0].astype(np.int64) * 1_000_000_000 + entries[:, 1]
    return conn, log, entries[:, 2].astype(np.int64)


def _records(
    buf: np.ndarray, pos: int, where: str, stop: set[int] | None = None, partial: bool = False
) -> Iterator[tuple[int, int, dict[str, bytes], bytes]]:
    """(position, op, header fields, data) of the records of a decompressed chunk from ``pos``
    on, up to its end or a position in ``stop`` (``partial``: a record that runs past the end
    ends the walk instead of being an error)."""
    raw = memoryview(buf)
    size = len(buf)
    while pos < size and (stop is None or pos not in stop):
        end = size + 1  # a record whose lengths themselves are cut off runs past the end
        if pos + 4 <= size:
            hl = int.from_bytes(raw[pos : pos + 4], "little")
            if pos + 8 + hl <= size:
                dl = int.from_bytes(raw[pos + 4 + hl : pos + 8 + hl], "little")
                end = pos + 8 + hl + dl
        if end > size:
            if partial:
                return
            raise ReadError(f"{where}: record at byte {pos} of the chunk runs past its end")
        fields = _fields(bytes(raw[pos + 4 : pos + 4 + hl]), where)
        yield pos, fields.get("op", b"\xff")[0], fields, bytes(raw[pos + 8 + hl : end])
        pos = end


def _decompressed(chunk: BagChunk) -> BagChunk:
    """The chunk with its buffer (waiting for the worker that decompresses it)."""
    chunk.buf = chunk.buf.result()  # type: ignore[attr-defined]
    return chunk


def bag_sources(path: Path, salvage: bool = False) -> list[Ros1Bag]:
    """A bag, or every ``*.bag`` of a folder (split bags), as sources (``salvage``: see
    :class:`Ros1Bag`)."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.bag"))
        if not files:
            raise ReadError(f"{path}: no .bag files in the folder")
        return [Ros1Bag(f, salvage) for f in files]
    return [Ros1Bag(path, salvage)]


def read_ros1(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a ROS 1 bag (or a folder of split bags) into the common table."""
    return read_sources(spec, bag_sources(spec.path, spec.read_truncated))


def iter_ros1(
    spec: InputSpec, batch_rows: int, carry: bool = True, warnings: list[str] | None = None
) -> Iterator[tuple[pa.Table, list[RawMessage]]]:
    """Bounded-memory batches (see :func:`imupipe.readers.sources.iter_sources`)."""
    return iter_sources(
        spec, bag_sources(spec.path, spec.read_truncated), batch_rows, carry, warnings
    )


def carry_over_ros1(spec: InputSpec) -> list[RawMessage]:
    """Messages of the other topics, converted to ROS 2 CDR, in log-time order."""
    return carry_sources(spec, bag_sources(spec.path, spec.read_truncated))
