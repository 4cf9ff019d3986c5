"""The MCAP conformance suite's files, written from the MCAP specification (test helper).

The MCAP project's conformance suite (foxglove/mcap ``tests/conformance``, MIT) is a set of
small files: a few inputs (:data:`INPUTS`: no data, one message, one schemaless message, ten
messages out of log-time order, one attachment, one metadata record) each written with every
sensible combination of ten features (:data:`FEATURES`), the feature letters joined into the
file name (``TenMessages-ch-chx-mx-st.mcap``):

- ``ch``: Schema, Channel and Message records inside one uncompressed chunk (else in the data
  section itself); ``mx``: the chunk followed by its Message Index records;
- ``st``: a Statistics record; ``rsh`` / ``rch``: the Schema / Channel records repeated in the
  summary; ``chx``, ``ax``, ``mdx``: Chunk, Attachment and Metadata Index records in the summary;
- ``sum``: a Summary Offset record per group of summary records;
- ``pad``: three extra bytes (``01 ff ff``) at the end of every record whose length may grow
  (all but Message, Chunk, Data End and Footer, and none inside the chunk): a reader must skip
  a record's bytes past the fields it knows (MCAP specification, "Records": "Readers should
  ignore any unknown fields").

This module writes them with its own record encoder (:func:`record` and the ``*_body``
functions, field by field as the specification's record tables give them); the sha256 of every
file the suite's own generator wrote is in ``tests/data/mcap_conformance/MANIFEST.txt`` (from
the suite's Git LFS pointers), so that each file written here is checked byte for byte.
:func:`variants` can also write the same feature combinations around other records (the tests
use ROS 2 ``sensor_msgs/msg/Imu`` messages, to read every layout through ``run`` and
``convert``).

Reference: MCAP specification, https://mcap.dev/spec (records, opcodes, summary section).
"""

from __future__ import annotations

import itertools
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

MAGIC = b"\x89MCAP0\r\n"
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX = range(1, 9)
ATTACHMENT, ATTACHMENT_INDEX, STATISTICS, METADATA, METADATA_INDEX, SUMMARY_OFFSET = range(9, 15)
DATA_END = 0x0F
PAD = b"\x01\xff\xff"
"""The extra bytes the ``pad`` feature appends to a record."""

FEATURES = ("ch", "mx", "st", "rsh", "rch", "ax", "mdx", "chx", "sum", "pad")


@dataclass(frozen=True)
class Schema:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class Channel:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class Message:
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


@dataclass(frozen=True)
class Attachment:
    log_time: int
    create_time: int
    name: str
    media_type: str
    data: bytes


@dataclass(frozen=True)
class Metadata:
    name: str
    metadata: tuple[tuple[str, str], ...]


Record = Schema | Channel | Message | Attachment | Metadata


def _string(s: str) -> bytes:
    raw = s.encode()
    return struct.pack("<I", len(raw)) + raw


def _pairs(items: Sequence[tuple[bytes, bytes]]) -> bytes:
    """A map field: uint32 byte length, then its entries."""
    body = b"".join(k + v for k, v in items)
    return struct.pack("<I", len(body)) + body


def _string_map(items: Sequence[tuple[str, str]]) -> bytes:
    return _pairs([(_string(k), _string(v)) for k, v in items])


def record(opcode: int, body: bytes, pad: bool = False) -> bytes:
    """One record: opcode, uint64 length, body (with the ``pad`` bytes when asked)."""
    if pad:
        body += PAD
    return bytes([opcode]) + struct.pack("<Q", len(body)) + body


def schema_body(s: Schema) -> bytes:
    return struct.pack("<H", s.id) + _string(s.name) + _string(s.encoding) + _bytes(s.data)


def _bytes(data: bytes) -> bytes:
    return struct.pack("<I", len(data)) + data


def channel_body(c: Channel) -> bytes:
    return (
        struct.pack("<HH", c.id, c.schema_id)
        + _string(c.topic)
        + _string(c.message_encoding)
        + _string_map(c.metadata)
    )


def message_body(m: Message) -> bytes:
    return struct.pack("<HIQQ", m.channel_id, m.sequence, m.log_time, m.publish_time) + m.data


def attachment_body(a: Attachment) -> bytes:
    fields = (
        struct.pack("<QQ", a.log_time, a.create_time)
        + _string(a.name)
        + _string(a.media_type)
        + struct.pack("<Q", len(a.data))
        + a.data
    )
    return fields + struct.pack("<I", zlib.crc32(fields))


def metadata_body(m: Metadata) -> bytes:
    return _string(m.name) + _string_map(m.metadata)


@dataclass
class _Chunk:
    """The records of one chunk, with the message index of each channel (in the order the
    channels first appear) and the chunk's log-time range."""

    indexed: bool
    buf: bytearray = field(default_factory=bytearray)
    index: dict[int, list[tuple[int, int]]] = field(default_factory=dict)
    start: int = 0
    end: int = 0
    count: int = 0

    def add(self, r: Record) -> None:
        if isinstance(r, Schema):
            self.buf += record(SCHEMA, schema_body(r))
        elif isinstance(r, Channel):
            if self.indexed:
                self.index.setdefault(r.id, [])
            self.buf += record(CHANNEL, channel_body(r))
        else:
            assert isinstance(r, Message)
            if self.count == 0 or r.log_time < self.start:
                self.start = r.log_time
            if self.count == 0 or r.log_time > self.end:
                self.end = r.log_time
            if self.indexed:
                self.index.setdefault(r.channel_id, []).append((r.log_time, len(self.buf)))
            self.count += 1
            self.buf += record(MESSAGE, message_body(r))


def write(records: Sequence[Record], features: set[str] | frozenset[str]) -> bytes:
    """The MCAP file of ``records`` written with ``features`` (see the module docstring)."""
    pad = "pad" in features
    out = bytearray(MAGIC)
    out += record(HEADER, _string("") + _string(""), pad)
    chunk = _Chunk("mx" in features) if "ch" in features else None
    counts: dict[int, int] = {}
    n_schemas = n_channels = n_attachments = n_metadata = 0
    first: int | None = None
    last: int | None = None
    attachment_index: list[bytes] = []
    metadata_index: list[bytes] = []
    chunk_index: list[bytes] = []
    for r in records:
        if isinstance(r, (Schema, Channel, Message)):
            if isinstance(r, Schema):
                n_schemas += 1
            elif isinstance(r, Channel):
                n_channels += 1
            else:
                counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
                first = r.log_time if first is None else min(first, r.log_time)
                last = r.log_time if last is None else max(last, r.log_time)
            if chunk is not None:
                chunk.add(r)
            elif isinstance(r, Schema):
                out += record(SCHEMA, schema_body(r), pad)
            elif isinstance(r, Channel):
                out += record(CHANNEL, channel_body(r), pad)
            else:
                out += record(MESSAGE, message_body(r))
        elif isinstance(r, Attachment):
            n_attachments += 1
            offset = len(out)
            out += record(ATTACHMENT, attachment_body(r), pad)
            if "ax" in features:
                body = struct.pack(
                    "<QQQQQ", offset, len(out) - offset, r.log_time, r.create_time, len(r.data)
                )
                attachment_index.append(body + _string(r.name) + _string(r.media_type))
        else:
            n_metadata += 1
            offset = len(out)
            out += record(METADATA, metadata_body(r), pad)
            if "mdx" in features:
                metadata_index.append(
                    struct.pack("<QQ", offset, len(out) - offset) + _string(r.name)
                )
    if chunk is not None:
        raw = bytes(chunk.buf)
        start = len(out)
        out += record(
            CHUNK,
            struct.pack("<QQQI", chunk.start, chunk.end, len(raw), zlib.crc32(raw))
            + _string("")
            + struct.pack("<Q", len(raw))
            + raw,
        )
        chunk_length = len(out) - start
        offsets: list[tuple[int, int]] = []
        index_start = len(out)
        for cid, entries in chunk.index.items():
            offsets.append((cid, len(out)))
            body = b"".join(struct.pack("<QQ", t, o) for t, o in entries)
            out += record(MESSAGE_INDEX, struct.pack("<HI", cid, len(body)) + body, pad)
        if "chx" in features:
            chunk_index.append(
                struct.pack("<QQQQ", chunk.start, chunk.end, start, chunk_length)
                + _pairs([(struct.pack("<H", c), struct.pack("<Q", o)) for c, o in offsets])
                + struct.pack("<Q", len(out) - index_start)
                + _string("")
                + struct.pack("<QQ", len(raw), len(raw))
            )
    out += record(DATA_END, struct.pack("<I", zlib.crc32(out)))

    summary_start = len(out)
    groups: list[tuple[int, int, int]] = []

    def group(opcode: int, bodies: list[bytes]) -> None:
        begin = len(out)
        for body in bodies:
            out.extend(record(opcode, body, pad))
        if len(out) > begin:
            groups.append((opcode, begin, len(out) - begin))

    if "rsh" in features:
        group(SCHEMA, [schema_body(r) for r in records if isinstance(r, Schema)])
    if "rch" in features:
        group(CHANNEL, [channel_body(r) for r in records if isinstance(r, Channel)])
    if "st" in features:
        stats = struct.pack(
            "<QHIIIIQQ",
            sum(counts.values()),
            n_schemas,
            n_channels,
            n_attachments,
            n_metadata,
            1 if chunk is not None else 0,
            first or 0,
            last or 0,
        ) + _pairs([(struct.pack("<H", c), struct.pack("<Q", n)) for c, n in counts.items()])
        group(STATISTICS, [stats])
    group(METADATA_INDEX, metadata_index)
    group(ATTACHMENT_INDEX, attachment_index)
    group(CHUNK_INDEX, chunk_index)
    has_summary = len(out) != summary_start
    offset_start = 0
    if "sum" in features:
        offset_start = len(out)
        for opcode, begin, length in groups:
            out += record(SUMMARY_OFFSET, struct.pack("<BQQ", opcode, begin, length), pad)
    footer = struct.pack("<QQ", summary_start if has_summary else 0, offset_start)
    head = bytes([FOOTER]) + struct.pack("<Q", 20) + footer
    crc = zlib.crc32(bytes(out[summary_start:]) + head)
    out += head + struct.pack("<I", crc) + MAGIC
    return bytes(out)


_EXAMPLE_SCHEMA = Schema(1, "Example", "c", bytes([4, 5, 6]))
_EXAMPLE_CHANNEL = Channel(1, 1, "example", "a", (("foo", "bar"),))

INPUTS: dict[str, tuple[Record, ...]] = {
    "NoData": (),
    "OneSchemalessMessage": (
        Channel(1, 0, "example", "text"),
        Message(1, 10, 2, 1, bytes([1, 2, 3])),
    ),
    "OneMessage": (_EXAMPLE_SCHEMA, _EXAMPLE_CHANNEL, Message(1, 10, 2, 1, bytes([1, 2, 3]))),
    "OneAttachment": (Attachment(2, 1, "myFile", "application/octet-stream", bytes([1, 2, 3])),),
    "OneMetadata": (Metadata("myMetadata", (("foo", "bar"),)),),
    "TenMessages": (
        _EXAMPLE_SCHEMA,
        _EXAMPLE_CHANNEL,
        *(
            Message(1, seq, t, t, bytes([1, 2, 3]))
            for seq, t in enumerate([0, 2, 1, 3, 3, 5, 4, 7, 8, 9])
        ),
    ),
}
"""The suite's inputs: the records each file holds, in file order (the ten messages' log times
are out of order on purpose)."""


def applies(records: Sequence[Record], features: frozenset[str]) -> bool:
    """Whether the suite writes ``records`` with ``features``: a feature needs what it indexes
    or repeats (``ax`` an attachment, ``rch`` a channel, ...), chunks need Schema, Channel or
    Message records, ``mx``/``chx`` need chunks, ``sum`` needs a summary group it can point at."""
    kinds = {type(r) for r in records}
    needs = {"ax": Attachment, "mdx": Metadata, "rsh": Schema, "rch": Channel}
    if any(f in features and needs[f] not in kinds for f in needs):
        return False
    if not kinds & {Schema, Channel, Message} and features & {"ch", "chx", "mx"}:
        return False
    if "sum" in features and not features & {"chx", "rsh", "rch", "mdx", "ax", "st"}:
        return False
    return not (features & {"chx", "mx"} and "ch" not in features)


def name(base: str, features: frozenset[str]) -> str:
    """The suite's file name: the input's name and the sorted feature letters, ``-``-joined."""
    return "-".join([base, *sorted(features)]) + ".mcap"


def variants(
    inputs: dict[str, Sequence[Record]] | None = None,
) -> Iterator[tuple[str, bytes]]:
    """(file name, bytes) of every applicable feature combination of every input (the suite's
    416 files for the default :data:`INPUTS`)."""
    for base, records in (INPUTS if inputs is None else inputs).items():
        for n in range(len(FEATURES) + 1):
            for combo in itertools.combinations(FEATURES, n):
                features = frozenset(combo)
                if applies(records, features):
                    yield name(base, features), write(records, features)
