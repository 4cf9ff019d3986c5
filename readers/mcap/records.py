"""The MCAP records imupipe reads and writes itself, field by field from one table of layouts.

Each record's body is its fields in the order of the MCAP specification ("Records"):
little-endian unsigned integers, strings (UTF-8) and byte arrays prefixed with their ``uint32``
length (an Attachment's data with a ``uint64`` one), and the maps and arrays of a Channel
(metadata), a Statistics record (messages per channel) and a ChunkIndex (message index offsets
per channel), each prefixed with its length in bytes. :func:`pack` writes the bytes the ``mcap``
library's ``write`` methods write; :func:`unpack` reads what its ``read`` methods read from a
body whose fields fill it exactly as their lengths say (bytes after the last field, which the
specification lets a record grow, are left), and raises :class:`RecordError` for any other
(the caller may then ask the library, which reads damaged records its own way).

Issue 39: the library's 16 record dataclasses take 8 to 15 ms to import, a tenth of what a
one-log ``imupipe convert`` costs beyond numpy and pyarrow; its reader, lz4 and their modules
a few ms more.
"""

from __future__ import annotations

import struct
import zlib
from typing import Any, BinaryIO

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_ATTACHMENT = 0x06, 0x07, 0x08, 0x09
OP_ATTACHMENT_INDEX, OP_STATISTICS, OP_METADATA_INDEX = 0x0A, 0x0B, 0x0D
OP_SUMMARY_OFFSET, OP_DATA_END = 0x0E, 0x0F

LAYOUTS = {
    OP_HEADER: "ss",  # profile, library
    OP_FOOTER: "QQI",  # summary start, summary offset start, summary CRC
    OP_SCHEMA: "Hssb",  # id, name, encoding, data
    OP_CHANNEL: "HHssM",  # id, schema id, topic, message encoding, metadata
    OP_CHUNK_INDEX: "QQQQCQsQQ",  # start, end, chunk offset, chunk length, message index
    # offsets, message index length, compression, compressed size, uncompressed size
    OP_ATTACHMENT: "QQssDI",  # log time, create time, name, media type, data, CRC
    OP_ATTACHMENT_INDEX: "QQQQQss",  # offset, length, log time, create time, size, name, type
    OP_STATISTICS: "QHIIIIQQC",  # messages, schemas, channels, attachments, metadata, chunks,
    # message start time, message end time, messages per channel
    OP_METADATA_INDEX: "QQs",  # offset, length, name
    OP_SUMMARY_OFFSET: "BQQ",  # group opcode, group start, group length
    OP_DATA_END: "I",  # data section CRC
}
"""Each record's fields: ``B H I Q`` integers; ``s`` a string; ``b`` bytes (``uint32`` length),
``D`` bytes (``uint64`` length); ``M`` a string -> string map and ``C`` a ``uint16`` ->
``uint64`` map, each prefixed with its ``uint32`` length in bytes."""

_INT = {code: struct.Struct("<" + code) for code in "BHIQ"}
_ENTRY = struct.Struct("<HQ")


class RecordError(ValueError):
    """A record body that does not hold its fields as their lengths say."""


class Schema:
    """A Schema record."""

    __slots__ = ("id", "name", "encoding", "data")

    def __init__(self, id: int, name: str, encoding: str, data: bytes) -> None:  # noqa: A002
        self.id, self.name, self.encoding, self.data = id, name, encoding, data


class Channel:
    """A Channel record."""

    __slots__ = ("id", "schema_id", "topic", "message_encoding", "metadata")

    def __init__(
        self, id: int, schema_id: int, topic: str, message_encoding: str, metadata: dict[str, str]
    ) -> None:  # noqa: A002
        self.id, self.schema_id, self.topic = id, schema_id, topic
        self.message_encoding, self.metadata = message_encoding, metadata


class _Fields:
    """A record whose fields are set, in the order of its ``__slots__``, from its layout's."""

    __slots__ = ()

    def __init__(self, *fields: Any) -> None:
        for name, value in zip(self.__slots__, fields, strict=True):
            setattr(self, name, value)


class Statistics(_Fields):
    """A Statistics record (the names of the ``mcap`` library's)."""

    __slots__ = (
        "message_count",
        "schema_count",
        "channel_count",
        "attachment_count",
        "metadata_count",
        "chunk_count",
        "message_start_time",
        "message_end_time",
        "channel_message_counts",
    )


class ChunkIndex(_Fields):
    """A ChunkIndex record (the names of the ``mcap`` library's)."""

    __slots__ = (
        "message_start_time",
        "message_end_time",
        "chunk_start_offset",
        "chunk_length",
        "message_index_offsets",
        "message_index_length",
        "compression",
        "compressed_size",
        "uncompressed_size",
    )


def _string(body: bytes, pos: int) -> tuple[str, int]:
    data, pos = _bytes(body, pos, _INT["I"])
    try:
        return data.decode(), pos
    except UnicodeDecodeError as exc:
        raise RecordError(f"a string at byte {pos - len(data)} is not UTF-8: {exc}") from None


def _bytes(body: bytes, pos: int, size: struct.Struct) -> tuple[bytes, int]:
    (n,) = _int(body, pos, size)
    start = pos + size.size
    if start + n > len(body):
        raise RecordError(f"a field of {n} bytes at byte {start} runs past the record")
    return bytes(body[start : start + n]), start + n


def _int(body: bytes, pos: int, size: struct.Struct) -> tuple[int]:
    if pos + size.size > len(body):
        raise RecordError(f"the record ends at byte {len(body)}, inside a field at byte {pos}")
    return size.unpack_from(body, pos)


def _map(body: bytes, pos: int, code: str) -> tuple[dict, int]:
    (n,) = _int(body, pos, _INT["I"])
    pos += 4
    end = pos + n
    if end > len(body):
        raise RecordError(f"a map of {n} bytes at byte {pos} runs past the record")
    out: dict = {}
    if code == "C":
        if n % _ENTRY.size:
            raise RecordError(f"a map of {n} bytes at byte {pos} is not whole entries")
        out.update(_ENTRY.iter_unpack(body[pos:end]))
        return out, end
    while pos < end:
        key, pos = _string(body, pos)
        out[key], pos = _string(body, pos)
    if pos != end:
        raise RecordError(f"a map at byte {end - n} runs past its {n} bytes")
    return out, end


def unpack(opcode: int, body: bytes) -> list[Any]:
    """The fields of a record's body (``opcode``: one of :data:`LAYOUTS`); :class:`RecordError`
    when they do not fit in it."""
    pos, out = 0, []
    for code in LAYOUTS[opcode]:
        if code in _INT:
            value = _int(body, pos, _INT[code])[0]
            pos += _INT[code].size
        elif code == "s":
            value, pos = _string(body, pos)
        elif code in "bD":
            value, pos = _bytes(body, pos, _INT["I" if code == "b" else "Q"])
        else:
            value, pos = _map(body, pos, code)
        out.append(value)
    return out


def pack(opcode: int, *fields: Any) -> bytes:
    """A whole record (opcode, length, body) of ``fields`` (an Attachment's CRC is computed:
    give 0)."""
    parts: list[bytes] = []
    for code, value in zip(LAYOUTS[opcode], fields, strict=True):
        if code in _INT:
            parts.append(_INT[code].pack(value))
        elif code == "s":
            parts.append(_prefixed(value.encode(), "I"))
        elif code in "bD":
            parts.append(_prefixed(bytes(value), "I" if code == "b" else "Q"))
        elif code == "C":
            parts.append(_INT["I"].pack(len(value) * _ENTRY.size))
            parts += [_ENTRY.pack(k, v) for k, v in value.items()]
        else:
            entries = [_prefixed(x.encode(), "I") for kv in value.items() for x in kv]
            parts.append(_prefixed(b"".join(entries), "I"))
    if opcode == OP_ATTACHMENT:  # its CRC covers the fields before it
        parts[-1] = _INT["I"].pack(zlib.crc32(b"".join(parts[:-1])))
    body = b"".join(parts)
    return struct.pack("<BQ", opcode, len(body)) + body


def _prefixed(data: bytes, size: str) -> bytes:
    return _INT[size].pack(len(data)) + data


def read_schema(body: bytes) -> Schema:
    """A Schema record's body."""
    sid, name, encoding, data = unpack(OP_SCHEMA, body)
    return Schema(sid, name, encoding, data)


def read_channel(body: bytes) -> Channel:
    """A Channel record's body."""
    return Channel(*unpack(OP_CHANNEL, body))


def read_statistics(body: bytes) -> Statistics:
    """A Statistics record's body."""
    return Statistics(*unpack(OP_STATISTICS, body))


class Summary:
    """What :func:`read_summary` finds: the summary's schemas and channels (by id), its
    Statistics record (the last; None without), its chunk indexes and the offsets of its
    attachments."""

    __slots__ = ("schemas", "channels", "statistics", "chunk_indexes", "attachments")

    def __init__(self) -> None:
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.statistics: Statistics | None = None
        self.chunk_indexes: list[ChunkIndex] = []
        self.attachments: list[int] = []


SUMMARY_RECORDS = frozenset(
    (
        OP_SCHEMA,
        OP_CHANNEL,
        OP_STATISTICS,
        OP_CHUNK_INDEX,
        OP_ATTACHMENT_INDEX,
        OP_METADATA_INDEX,
        OP_SUMMARY_OFFSET,
    )
)
"""The records :func:`read_summary` reads in a summary section."""


def read_summary(fh: BinaryIO) -> Summary | None:
    """The summary section of an MCAP (``fh``: open, seekable), as the ``mcap`` library's
    ``get_summary`` reads it: after the magic at the start, the footer 37 bytes before the end
    and the records from its summary start to it; None when the footer says there is none.
    Every record of the section must fit its layout, the section must end at the footer and
    hold no other record than those of :data:`SUMMARY_RECORDS`: else :class:`RecordError` (the
    caller asks the library, which reads such a file its own way)."""
    fh.seek(0)
    if fh.read(8) != MAGIC:
        raise RecordError("no MCAP magic at the start")
    fh.seek(-(9 + 20 + 8), 2)
    footer_at = fh.tell()
    tail = fh.read(9 + 20 + 8)
    if len(tail) != 37 or tail[:9] != struct.pack("<BQ", OP_FOOTER, 20) or tail[-8:] != MAGIC:
        raise RecordError("no footer record at the end")
    start = unpack(OP_FOOTER, tail[9:29])[0]
    if start == 0:
        return None
    if start > footer_at:
        raise RecordError(f"the summary starts at byte {start}, after the footer")
    fh.seek(start)
    section = fh.read(footer_at - start)
    if len(section) != footer_at - start:
        raise RecordError("the summary section is cut off")
    summary, pos = Summary(), 0
    while pos < len(section):
        if pos + 9 > len(section):
            raise RecordError(f"a record header at byte {start + pos} runs into the footer")
        opcode, length = section[pos], int.from_bytes(section[pos + 1 : pos + 9], "little")
        body = section[pos + 9 : pos + 9 + length]
        if len(body) != length:
            raise RecordError(f"the record at byte {start + pos} runs into the footer")
        if opcode not in SUMMARY_RECORDS:
            raise RecordError(f"a record of opcode {opcode:#x} at byte {start + pos}")
        fields = unpack(opcode, body)
        if opcode == OP_CHANNEL:
            summary.channels[fields[0]] = Channel(*fields)
        elif opcode == OP_SCHEMA:
            summary.schemas[fields[0]] = Schema(*fields)
        elif opcode == OP_CHUNK_INDEX:
            summary.chunk_indexes.append(ChunkIndex(*fields))
        elif opcode == OP_STATISTICS:
            summary.statistics = Statistics(*fields)
        elif opcode == OP_ATTACHMENT_INDEX:
            summary.attachments.append(fields[0])
        pos += 9 + length
    return summary


def read_attachment(fh: BinaryIO, offset: int) -> tuple[str, bytes]:
    """(name, data) of the Attachment record at ``offset``; :class:`RecordError` when there is
    none that fits its layout."""
    fh.seek(offset)
    head = fh.read(9)
    if len(head) != 9 or head[0] != OP_ATTACHMENT:
        raise RecordError(f"no attachment record at byte {offset}")
    length = int.from_bytes(head[1:9], "little")
    body = fh.read(length)
    if len(body) != length:
        raise RecordError(f"the attachment record at byte {offset} is cut off")
    _, _, name, _, data, _ = unpack(OP_ATTACHMENT, body)
    return name, data
