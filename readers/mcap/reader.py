"""MCAP logs (ROS 2 CDR or ROS 1 encoded) into the common table, chunk by chunk with numpy.

``sensor_msgs/Imu``, ``MagneticField`` and ``Temperature`` messages are decoded straight from
the decompressed chunks (:mod:`imupipe.readers.mcap.fast`, :func:`imupipe.readers.cdr.decode`;
one compiled pass per chunk when built, :mod:`imupipe.readers.chunk_fill`);
big-endian CDR falls back to rosbags' deserializer. Messages of every other channel are carried
over as they are (ROS 1 encoded ones converted to ROS 2 CDR the way ``rosbags-convert`` does).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from imupipe.readers.chunk_fill import RecordPiece, Records, repeated_frame, walk
from imupipe.readers.decoded import Piece, concat, decode_piece
from imupipe.readers.errors import ReadError
from imupipe.readers.mcap.fast import MESSAGE_HEADER, ChunkMessages, McapFile
from imupipe.readers.sources import carry_sources, iter_sources, read_sources
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.readers.table_buffer import TableBuffer
from imupipe.readers.topics import normalize_type

if TYPE_CHECKING:
    from imupipe.readers.mapped import Batch, Definition

GROUP_BYTES = 4 << 20
"""Chunks read into one table are decompressed back to back into buffers of this size and
decoded as one group (:meth:`McapSource._decode_group`)."""


class McapSource:
    """One MCAP file as a :class:`~imupipe.readers.sources.LogSource`."""

    format = "mcap"

    def __init__(self, path: str | Path, salvage: bool = False) -> None:
        self.path = Path(path)
        self.file = McapFile(self.path, salvage=salvage)
        self.warnings = self.file.warnings
        self._first: int | None = None

    def topic_types(self) -> dict[str, str]:
        return {c.topic: c.schema_name for c in self.file.channels.values()}

    def topic_counts(self) -> dict[str, int] | None:
        if self.file.counts is None:
            return None
        out: dict[str, int] = {}
        for cid, n in self.file.counts.items():
            if cid in self.file.channels:
                topic = self.file.channels[cid].topic
                out[topic] = out.get(topic, 0) + n
        return out

    def first_time(self) -> int:
        if self._first is None:
            self._first = 0
            for chunk in self.file.chunks():
                times = [chunk.records(cid)[0] for cid in chunk.offsets]
                times = [t for t in times if len(t)]
                if times:
                    self._first = int(min(t.min() for t in times))
                    break
        return self._first

    def topic_times(self) -> dict[str, np.ndarray]:
        times: dict[str, list[np.ndarray]] = {}
        for chunk in self.file.chunks():
            for cid in chunk.offsets:
                topic = self.file.channel(cid, chunk).topic
                times.setdefault(topic, []).append(chunk.records(cid)[0])
        return {t: np.concatenate(v) for t, v in times.items()}

    prefills = True
    """:meth:`chunks` takes a ``sink`` (see :func:`imupipe.readers.sources.read_sources`)."""

    def chunks(
        self,
        streams: dict[str, str],
        carry: bool,
        decode: bool = True,
        whole: bool = False,
        sink: TableBuffer | None = None,
    ) -> Iterator[tuple[dict[str, Piece], list[RawMessage], int]]:
        """``sink``: the table the pieces go to, in the order given; a table of one stream
        gets each chunk's values right after the chunk's decompression (:meth:`_prefill`)."""
        by_topic = {topic: stream for stream, topic in streams.items()}
        stream_of: dict[int, str | None] = {}  # channel id -> its stream (None: carried over)
        converters: dict[int, object] = {}
        group = GROUP_BYTES if whole and decode and not carry and self._groups() else 0
        ready = None
        if group and sink is not None and len(streams) == 1:
            on = True  # until the first chunk :meth:`_prefill` does not take

            def ready(chunk: ChunkMessages) -> None:
                nonlocal on
                on = on and self._prefill(by_topic, stream_of, sink, chunk)

        for chunk in self.file.chunks(group, ready):
            if chunk.parts:
                pieces = self._decode_group(chunk, by_topic, stream_of)
                if pieces is not None:
                    yield pieces, [], chunk.bound
                    continue
            for part in chunk.parts or (chunk,):
                self._map_streams(part, by_topic, stream_of)
                yield self._chunk(part, stream_of, converters, carry, decode)

    def _map_streams(
        self, chunk: ChunkMessages, by_topic: dict[str, str], stream_of: dict[int, str | None]
    ) -> None:
        """The stream of each channel of ``chunk`` not yet in ``stream_of`` (None: carried
        over), from its topic; raises :class:`ReadError` for a channel the file never defines."""
        for cid in chunk.offsets:
            if cid not in stream_of:
                stream_of[cid] = by_topic.get(self.file.channel(cid, chunk).topic)

    def _chunk(
        self,
        chunk: ChunkMessages,
        stream_of: dict[int, str | None],
        converters: dict[int, object],
        carry: bool,
        decode: bool,
    ) -> tuple[dict[str, Piece], list[RawMessage], int]:
        """One chunk's pieces, carried-over messages and bound (see :meth:`chunks`)."""
        pieces: dict[str, list[Piece]] = {}
        if decode:
            for cid in chunk.offsets:
                stream = stream_of[cid]
                if stream is not None:
                    pieces.setdefault(stream, []).append(self._decode(chunk, cid, stream))
        raw: list[RawMessage] = []
        if carry:
            for cid in sorted(chunk.offsets):
                if stream_of[cid] is None:
                    raw.extend(self._raw(chunk, cid, converters))
            raw.sort(key=lambda m: m.log_time)
        return {s: concat(p, s) for s, p in pieces.items()}, raw, chunk.bound

    def _prefill(
        self,
        by_topic: dict[str, str],
        stream_of: dict[int, str | None],
        sink: TableBuffer,
        chunk: ChunkMessages,
    ) -> bool:
        """Walk ``chunk`` (just decompressed, in the core's cache) and write its values into
        ``sink`` at the rows they will take (:meth:`TableBuffer.prefill`), keeping the piece in
        ``chunk.filled`` for :meth:`_decode` and :meth:`_decode_group`. False for a chunk this
        does not take (another layout, two channels of the stream, a channel the file does not
        define: read as before, its errors named there): the caller then stops prefilling for
        the rest of the file, so that the prefilled rows stay those the pieces are added at."""
        try:
            self._map_streams(chunk, by_topic, stream_of)
        except ReadError:
            return False
        mine = [cid for cid in chunk.offsets if stream_of[cid] is not None]
        if len(mine) > 1:
            return False
        for cid in mine:
            stream = stream_of[cid]
            piece = None
            if self.file.channels[cid].message_encoding == "cdr" and _inside(chunk, cid):
                piece = walk(chunk.buf, chunk.offsets[cid], cid, stream)  # type: ignore[arg-type]
            if piece is None or not sink.prefill(stream, piece):  # type: ignore[arg-type]
                return False
            chunk.filled[cid] = piece
        return True

    def _groups(self) -> bool:
        """Whether chunks may be decoded as a group (:meth:`_decode_group`)."""
        return True

    def _decode_group(
        self, chunk: ChunkMessages, by_topic: dict[str, str], stream_of: dict[int, str | None]
    ) -> dict[str, Piece] | None:
        """The pieces of chunks handed over as one (:attr:`ChunkMessages.parts`), when the
        compiled pass takes every channel of them in one call each: the same pieces as the
        chunks one by one would give, joined, with a quarter of the Python work per chunk. None
        when it does not (a damaged chunk, another layout, two channels of one stream, whose
        messages would come in another order): the chunks are then read one by one, and their
        errors named as they are, in their order."""
        try:
            for part in chunk.parts:
                self._map_streams(part, by_topic, stream_of)
        except ReadError:  # a channel the file never defines: named when its chunk is reached
            return None
        pieces: dict[str, Piece] = {}
        for cid, offsets in chunk.offsets.items():
            stream = stream_of[cid]
            if stream is None:
                continue
            if stream in pieces or self.file.channels[cid].message_encoding != "cdr":
                return None
            if not all(_inside(part, cid) for part in chunk.parts):
                return None
            piece = _joined([part.filled.get(cid) for part in chunk.parts], chunk, offsets)
            if piece is None:
                piece = walk(chunk.buf, offsets, cid, stream)
            if piece is None:
                return None
            pieces[stream] = piece
        return pieces

    def definitions(self) -> dict[str, Definition]:
        """Topic -> its channel's message definition (the first channel of a topic)."""
        from imupipe.readers.mapped import Definition  # field mappings only (issue 39)

        out: dict[str, Definition] = {}
        for c in sorted(self.file.channels.values(), key=lambda c: c.id):
            out.setdefault(
                c.topic,
                Definition(c.schema_name, c.message_encoding, c.schema_encoding, c.schema_data),
            )
        return out

    def payloads(self, topics: set[str]) -> Iterator[list[tuple[str, Batch]]]:
        """Per chunk: the messages of ``topics`` (field mappings, :mod:`imupipe.readers.mapped`)."""
        from imupipe.readers.mapped import Batch  # field mappings only (issue 39)

        for chunk in self.file.chunks():
            out = []
            for cid in chunk.offsets:
                topic = self.file.channel(cid, chunk).topic
                if topic in topics:
                    view = self._view(chunk, cid)
                    log, pub, starts, lengths = view.records(cid, copy=False)
                    out.append((topic, Batch(view.buf, starts, lengths, log, pub)))
            yield out

    def _view(self, chunk: ChunkMessages, cid: int) -> ChunkMessages:
        """The chunk as a channel's payloads are read from it."""
        return chunk

    def _decode(self, chunk: ChunkMessages, cid: int, stream: str) -> Piece:
        channel = self.file.channels[cid]
        where = f"{self.path}: topic '{channel.topic}'"
        if channel.message_encoding not in ("cdr", "ros1"):
            raise ReadError(
                f"{where}: message encoding '{channel.message_encoding}' is not supported "
                "(cdr or ros1)"
            )
        if channel.message_encoding == "cdr" and isinstance(chunk, ChunkMessages):
            piece = chunk.filled.get(cid)  # type: ignore[assignment]
            if piece is None:
                piece = walk(chunk.buf, chunk.offsets[cid], cid, stream)  # the compiled pass
            if piece is not None:
                return piece
        log, pub, starts, lengths = chunk.records(cid, copy=False)
        return decode_piece(
            chunk.buf, starts, lengths, log, stream, channel.message_encoding, where, pub
        )

    def _raw(
        self, chunk: ChunkMessages, cid: int, converters: dict[int, object]
    ) -> list[RawMessage]:
        channel = self.file.channel(cid, chunk)
        log, pub, starts, lengths = chunk.records(cid)
        schema_name, schema_encoding, schema_data = (
            channel.schema_name,
            channel.schema_encoding,
            channel.schema_data,
        )
        encoding = channel.message_encoding
        convert = None
        if encoding == "ros1":
            from imupipe.readers.ros1.reader import ros2_converter

            if cid not in converters:
                converters[cid] = ros2_converter(
                    normalize_type(schema_name),
                    schema_data.decode(errors="replace"),
                    f"{self.path}: topic '{channel.topic}'",
                )
            schema_name, schema_data, convert = converters[cid]  # type: ignore[misc]
            schema_encoding, encoding = "ros2msg", "cdr"
        buf = chunk.buf
        out = []
        for lt, pt, s, n in zip(
            log.tolist(), pub.tolist(), starts.tolist(), lengths.tolist(), strict=True
        ):
            data = buf[s : s + n].tobytes()
            if convert is not None:
                try:
                    data = bytes(convert(data))
                except Exception as exc:  # noqa: BLE001
                    raise ReadError(
                        f"{self.path}: topic '{channel.topic}': message at log time {lt} cannot "
                        f"be converted to ROS 2 ({exc})"
                    ) from None
            out.append(
                RawMessage(
                    channel.topic, schema_name, schema_encoding, schema_data, encoding, data, lt, pt
                )
            )
        return out


def _joined(
    parts: list[RecordPiece | None], group: ChunkMessages, offsets: np.ndarray
) -> RecordPiece | None:
    """One piece of the group of chunks ``group`` (its channel's record ``offsets``) from the
    pieces its chunks were prefilled with (:meth:`McapSource._prefill`), in rows one after the
    other: the piece a walk of the group gives, its values already in the table. None when a
    chunk was not prefilled or the pieces differ in layout or frame_id (the group is walked)."""
    pieces = [p for p in parts if p is not None and p.records is not None and p.filled]
    if not pieces or len(pieces) != len(parts):
        return None
    first = pieces[0]
    rec, one = first.records, first.one_frame
    row, generation, _ = first.filled  # type: ignore[misc]
    nan: set[str] = set()
    for p in pieces:
        if p.records.skip != rec.skip or p.one_frame != one or p.filled[:2] != (row, generation):  # type: ignore[union-attr,index]
            return None
        nan |= p.filled[2]  # type: ignore[index]
        row += len(p)
    log, pub, stamp = (
        np.concatenate([getattr(p, t) for p in pieces]) for t in ("log", "pub", "stamp")
    )
    ordered = 0
    for bit, which, name in ((1, 0, "log"), (2, 1, "stamp")):
        if all(p.ordered[which][1] for p in pieces) and _edges_ordered(pieces, name):
            ordered |= bit
    records = Records(group.buf, offsets, rec.skip, rec.slots, rec.names, rec.module)  # type: ignore[union-attr]
    piece = RecordPiece(stamp, log, repeated_frame(one, len(log)), pub, one, records, ordered)
    piece.filled = (first.filled[0], generation, nan)  # type: ignore[index]
    return piece


def _edges_ordered(parts: list, name: str) -> bool:
    """Whether the times ``name`` of ``parts`` (each in order) never decrease where one part
    ends and the next starts."""
    last = None
    for p in parts:
        t = getattr(p, name)
        if last is not None and int(t[0]) < last:
            return False
        last = int(t[-1])
    return True


def _inside(chunk: ChunkMessages, cid: int) -> bool:
    """Whether ``chunk``'s records of channel ``cid`` lie inside it, when they all have its
    first record's length (which :func:`~imupipe.readers.chunk_fill.walk` checks): the first
    offset in it, the last record ending in it (the offsets are sorted)."""
    off = chunk.offsets.get(cid)
    if off is None or not len(off):
        return True
    first, last, size = int(off[0]), int(off[-1]), len(chunk.buf)
    if first < 0 or first + MESSAGE_HEADER > size:
        return False
    length = int.from_bytes(chunk.buf[first + 1 : first + 9].tobytes(), "little")
    return last + 9 + length <= size


def read_mcap(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read an MCAP input into the common table; returns (table, warnings)."""
    return read_sources(spec, [McapSource(spec.path, spec.read_truncated)])


def iter_mcap(
    spec: InputSpec, batch_rows: int, carry: bool = True, warnings: list[str] | None = None
) -> Iterator[tuple[pa.Table, list[RawMessage]]]:
    """Bounded-memory batches (see :func:`imupipe.readers.sources.iter_sources`)."""
    return iter_sources(
        spec, [McapSource(spec.path, spec.read_truncated)], batch_rows, carry, warnings
    )


def carry_over_mcap(spec: InputSpec) -> list[RawMessage]:
    """Messages of the topics the table does not hold, in log-time order."""
    return carry_sources(spec, [McapSource(spec.path, spec.read_truncated)])


def mcap_sources(path: Path, salvage: bool = False) -> list[McapSource]:
    """The one source of an MCAP file (the ``log_sources`` entry for MCAP; ``salvage``: read it
    up to a cut, see :class:`~imupipe.readers.mcap.fast.McapFile`)."""
    return [McapSource(path, salvage)]
