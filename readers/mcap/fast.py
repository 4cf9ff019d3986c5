"""MCAP at the chunk level: records, channels, and each chunk's messages as numpy offsets.

The file is read sequentially, one top-level record at a time (a few per chunk, never one per
message). A chunk is decompressed (zstd, lz4 or none; its CRC checked when set) and the
``MessageIndex`` records that follow it give, per channel, the offset of every message record in
the decompressed chunk; a message record is ``opcode 0x05, uint64 length, uint16 channel,
uint32 sequence, uint64 log_time, uint64 publish_time, payload`` so the payload of message ``i``
starts at ``offset + 31`` and is ``length - 22`` bytes long. All of that is gathered with numpy.
A small file (:data:`SMALL_FILE`, a fleet's short log) is read whole in one read instead, and
its chunks decompressed in the reading thread; the Schema and Channel records, which a fleet's
logs repeat, are parsed once per process (issue 39: the fixed cost of a file).

Which messages exist is decided by the data section alone: every Message record in it, inside
chunks or not, is read. The summary section (every record of it optional) gives what it has:
the channels and schemas when it defines every channel it says has messages
(:func:`imupipe.readers.mcap.summary.complete`), the chunk start times (chunk indexes) and the
message counts (statistics, used to size the table). When it does not, the Schema and Channel
records are gathered from the data section first (top-level or inside chunks; the pass stops
once the channels the summary names are all found, and reads the whole data section when the
summary names none). A message on a channel still unknown when it is read (a summary that
named too few) has its Channel record looked for in its chunk, then in the whole data section.

Fallbacks: a chunk without message indexes (writers that omit them; foxglove/mcap#1735) is
scanned record by record; messages outside chunks are gathered into pseudo-chunks. Bytes past
the fields a record is known to have (the specification lets records grow) are skipped.

Every inconsistency (bad magic, a record running past the end of the file, a failed
decompression or CRC, an index pointing outside its chunk) is a :class:`ReadError` naming the
file and the byte offset.
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import functools
import io
import os
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imupipe.readers.cdr import at, even_step
from imupipe.readers.chunk_fill import crc32
from imupipe.readers.compression import (
    DECOMPRESSORS,
    PREFETCH,
    BufferPool,
    decompress_chunk,
    decompress_into,
    decompress_workers,
    no_spare_cpu,
)
from imupipe.readers.errors import READ_TO_CUT, ReadError
from imupipe.readers.mcap import records
from imupipe.readers.mcap.records import (
    MAGIC,
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
    Channel,
    Schema,
    Statistics,
)
from imupipe.readers.mcap.summary import complete, defined
from imupipe.readers.progress import report

NEVER = 2**63 - 1
MESSAGE_HEADER = 31
"""Bytes from a message record's opcode to its payload."""
PSEUDO_CHUNK_BYTES = 1 << 20
CHUNK_HEAD = 64
"""Bytes of a chunk record the reading thread reads (the fields before the records, for
compression names of up to 20 characters)."""
POOLED_BYTES = 64 << 20
"""Chunks up to this size are decompressed into buffers used again (:class:`BufferPool`)."""
SMALL_FILE = 1 << 20
"""A file up to this size is read whole, in one read, each time it is walked (its summary at
opening, its chunks when they are read), its chunks decompressed in the reading thread: a
fleet's short logs cost one system call each instead of a seek and a read per record, and no
hand-off to a decompression thread (issue 39)."""
SUMMARY_BYTES = 16 << 20
"""A summary section up to this size is read in one read (a larger one, or a footer pointing
far back into a damaged file, record by record: memory bounded by its largest record)."""
PARSED_BYTES = 4 << 20
"""Schema and Channel records parsed so far are kept (by their bytes) up to this many bytes:
a fleet's logs repeat the same records, parsed once per process."""


_PARSED: dict[tuple[int, bytes], Schema | Channel] = {}
"""(opcode, record body) -> the record, for :meth:`McapFile._parsed`."""
_parsed_bytes = 0
"""Bytes of the record bodies :data:`_PARSED` holds."""


@dataclass(frozen=True)
class ChannelInfo:
    """A channel with its schema: topic, message encoding, schema name/encoding/data."""

    id: int
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes


_INFOS: dict[tuple[int, int], tuple[Channel, Schema | None, ChannelInfo]] = {}
"""The :class:`ChannelInfo` of a Channel and Schema record (:data:`_PARSED`'s, shared by the
files that hold the same records), by their ids; each entry holds the records it was made of."""


def _channel_info(c: Channel, s: Schema | None) -> ChannelInfo:
    """The channel ``c`` with its schema ``s`` (None: none), made once for the same records."""
    key = (id(c), id(s))
    hit = _INFOS.get(key)
    if hit is not None and hit[0] is c and hit[1] is s:
        return hit[2]
    info = ChannelInfo(
        c.id,
        c.topic,
        c.message_encoding,
        s.name if s else "",
        s.encoding if s else "",
        bytes(s.data) if s else b"",
    )
    if len(_INFOS) >= 1024:
        _INFOS.clear()
    _INFOS[key] = (c, s, info)
    return info


@dataclass
class ChunkMessages:
    """One decompressed chunk: ``buf`` (uint8) and, per channel id, the sorted byte offsets of
    its message records in ``buf``."""

    buf: np.ndarray
    offsets: dict[int, np.ndarray]
    where: str
    bound: int = NEVER
    """No message after this chunk (in file order) has a log time below ``bound``: from the
    summary's chunk indexes, else assumed to be this chunk's start time (a log written in time
    order)."""
    start: int = -1
    """Where ``buf`` starts in the arena it was carved from (``buf.base``, see
    :class:`~imupipe.readers.compression.BufferPool`); -1: a buffer of its own."""
    parts: list[ChunkMessages] = field(default_factory=list)
    """Chunks that lay back to back in memory, handed over as this one (:meth:`McapFile.chunks`
    with ``group``): each as it would have been alone, its ``buf`` a view into this ``buf``;
    empty for a single chunk."""
    filled: dict[int, object] = field(default_factory=dict)
    """Per channel id: the piece whose values the reader wrote into its table right after this
    chunk's decompression (``ready`` of :meth:`McapFile.chunks`), if any."""

    def records(
        self, channel_id: int, copy: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(log_time, publish_time, payload start, payload length) of a channel's messages,
        validated against the buffer. ``copy=False``: the times may be read-only views into the
        chunk's buffer (for a caller that copies them at once)."""
        off = self.offsets.get(channel_id)
        if off is None or len(off) == 0:
            z = np.zeros(0, np.int64)
            return z, z, z, z
        buf = self.buf
        if off[0] < 0 or off[-1] + MESSAGE_HEADER > len(buf):
            raise ReadError(f"{self.where}: message index points outside its chunk")
        step = even_step(off)  # records of one size, one after the other: strided views
        n = len(off)
        if step is not None and n > 1:
            # one record header (opcode, length, channel: 11 bytes) for all, checked once
            first = buf[int(off[0]) : int(off[0]) + 11].tobytes()
            reclen = int.from_bytes(first[1:9], "little")
            if (
                first[0] == OP_MESSAGE
                and int.from_bytes(first[9:11], "little") == channel_id
                and reclen >= MESSAGE_HEADER - 9
                and int(off[-1]) + 9 + reclen <= len(buf)
                and bool(
                    (at(buf, off, 0, "<u8", step) == int.from_bytes(first[:8], "little")).all()
                )
                and bool(
                    (at(buf, off, 7, "<u4", step) == int.from_bytes(first[7:], "little")).all()
                )
            ):
                log = at(buf, off, 15, "<i8", step)  # uint64 read as int64, as astype would
                pub = at(buf, off, 23, "<i8", step)
                if copy:
                    log, pub = log.copy(), pub.copy()
                return log, pub, off + MESSAGE_HEADER, np.full(n, reclen - (MESSAGE_HEADER - 9))
        reclen = at(buf, off, 1, "<u8", step).astype(np.int64)
        bad = (at(buf, off, 0, "u1", step) != OP_MESSAGE) | (
            at(buf, off, 9, "<u2", step) != channel_id
        )
        bad |= (reclen < MESSAGE_HEADER - 9) | (off + 9 + reclen > len(buf))
        if np.any(bad):
            raise ReadError(
                f"{self.where}: message index does not point at channel {channel_id}'s messages"
            )
        log = at(buf, off, 15, "<u8", step).astype(np.int64)
        pub = at(buf, off, 23, "<u8", step).astype(np.int64)
        return log, pub, off + MESSAGE_HEADER, reclen - (MESSAGE_HEADER - 9)


@dataclass
class McapFile:
    """An MCAP file opened for chunk-level reading."""

    path: Path
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    counts: dict[int, int] | None = None
    """Messages per channel id: from the Statistics record, or counted by a pass over the data
    section (None when neither)."""
    profile: str = ""
    chunk_starts: list[tuple[int, int]] = field(default_factory=list)
    """(file offset, message start time) of every chunk, from the summary's chunk indexes."""
    salvage: bool = False
    """Read a file that is cut off up to the cut (the last complete record before it), with a
    warning, instead of refusing it (:attr:`~imupipe.readers.spec.InputSpec.read_truncated`)."""
    warnings: list[str] = field(default_factory=list)
    cut: int | None = None
    """Byte where a cut-off file's damage starts (``salvage``), once a pass has reached it."""

    def __post_init__(self) -> None:
        self.path = Path(self.path)
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._scanned = False
        """Whether the whole data section has been read for Schema and Channel records."""
        self._whole: bytes | None = None
        """The file's bytes while it is opened, when it is small (:data:`SMALL_FILE`)."""
        self._bounds_cache: tuple[list[int], list[int]] | None = None
        try:
            with open(self.path, "rb") as fh:
                self.size = os.fstat(fh.fileno()).st_size
                if self.size <= SMALL_FILE:
                    self._whole = fh.read()
                    self.size = len(self._whole)
                    head = self._whole[:8]
                else:
                    head = fh.read(8)
                if head == MAGIC:
                    needed = self._read_summary(fh)
        except OSError as exc:
            raise ReadError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        if head != MAGIC:
            raise ReadError(f"{self.path}: not an MCAP file (bad magic bytes)")
        try:
            if needed is not None:
                self._first_pass(needed)
        finally:
            self._whole = None
        if self.cut is not None and not any((self.counts or {}).values()):
            raise ReadError(
                f"{self.path}: truncated MCAP (cut off at byte {self.cut}, before its first "
                "complete message: nothing to read)"
            )
        self._join()

    # -- records ---------------------------------------------------------------------------
    def _records(
        self, fh: io.BufferedIOBase, start: int, end: int, lazy: bool = False, base: int = 0
    ) -> Iterator[tuple[int, int, bytes]]:
        """Top-level records between ``start`` and ``end``: (opcode, offset, body). ``lazy``:
        a chunk's body is left unread but for its first :data:`CHUNK_HEAD` bytes (its start
        time, sizes, CRC and compression); a worker reads the rest (:meth:`_load_chunk`).
        ``base``: the file offset of ``fh``'s first byte (a part of the file read into
        memory, up to its end)."""
        pos = start
        fh.seek(pos - base)
        while pos < end:
            head = fh.read(9)
            if len(head) < 9:
                if pos + len(head) >= self.size and pos >= end - 8:
                    return  # the trailing magic
                self._cut_off(pos, "record header at byte {pos} cut off")
                return
            opcode, length = head[0], int.from_bytes(head[1:9], "little")
            if pos + 9 + length > self.size:
                if head[:8] == MAGIC[:8] and pos + 8 == self.size:
                    return
                self._cut_off(pos, "record at byte {pos} runs past the end of the file")
                return
            if lazy and opcode == OP_CHUNK:
                body = fh.read(min(length, CHUNK_HEAD))
                fh.seek(pos + 9 + length - base)
            else:
                body = fh.read(length)
            yield opcode, pos, body
            pos += 9 + length

    def _cut_off(self, pos: int, what: str) -> None:
        """The file ends inside the record at ``pos``: ReadError, or (``salvage``) the records
        before it are kept and one warning says where the damage starts and what is skipped."""
        if not self.salvage:
            raise ReadError(
                f"{self.path}: truncated MCAP ({what.format(pos=pos)}; --read-truncated reads "
                "it up to the cut)"
            )
        if self.cut is None:
            self.cut = pos
            self.warnings.append(
                f"{self.path}: truncated MCAP: cut off at byte {pos} ({what.format(pos=pos)}); "
                f"{READ_TO_CUT}: the {self.size - pos} bytes from there to the end of the file "
                f"({self.size} bytes) are skipped with the messages in them"
            )

    def _open(self) -> io.BufferedIOBase:
        """The file, to read records from: its bytes in memory while :meth:`__post_init__`
        holds them (a small file), else opened."""
        if self._whole is not None:
            return io.BytesIO(self._whole)
        return open(self.path, "rb")  # noqa: SIM115 - closed by the caller's ``with``

    def _read_summary(self, fh: io.BufferedIOBase) -> set[int] | None:
        """Channels, schemas, statistics and chunk indexes from the summary section (``fh``:
        the open file). Returns None when its channels are the file's
        (:func:`~imupipe.readers.mcap.summary.complete`), else the ids of the channels it says
        have messages (empty: it names none), which the data section must then define
        (:meth:`_first_pass`)."""
        if self.size < 8 + 9 + 20 + 8:
            raise ReadError(f"{self.path}: truncated MCAP ({self.size} bytes)")
        stats: list[Statistics] = []
        indexed: list[list[int]] = []
        if self._whole is not None:
            tail = self._whole[self.size - 37 :]
        else:
            fh.seek(self.size - 37)
            tail = fh.read(37)
        if tail[-8:] != MAGIC or tail[0] != OP_FOOTER:
            return set()
        summary_start = int.from_bytes(tail[9:17], "little")
        if summary_start == 0 or summary_start > self.size - 37:
            return set()
        if self._whole is not None:
            section, base = io.BytesIO(self._whole), 0
        elif self.size - summary_start > SUMMARY_BYTES:  # (a damaged footer's) record by record
            section, base = fh, 0
        else:  # the summary section and the footer in one read
            fh.seek(summary_start)
            rest = fh.read(self.size - summary_start)
            section, base = (
                (io.BytesIO(rest), summary_start)
                if len(rest) == self.size - summary_start
                else (fh, 0)
            )
        records = self._records(section, summary_start, self.size - 37, base=base)
        for opcode, _pos, body in records:
            if opcode == OP_STATISTICS:
                stats.append(self._read_record(OP_STATISTICS, body))
            elif opcode == OP_CHUNK_INDEX:
                indexed.append(self._chunk_index(body))
            else:
                self._collect(opcode, body)
        if stats:
            self.counts = dict(stats[0].channel_message_counts)
        schema_of = {cid: c.schema_id for cid, c in self._channels.items()}
        if complete(stats[0] if stats else None, schema_of, self._schemas, indexed):
            return None
        needed = set(self.counts or ()) | {cid for ids in indexed for cid in ids}
        needed |= {
            cid for cid, c in self._channels.items() if c.schema_id not in (0, *self._schemas)
        }
        return {cid for cid in needed if (self.counts or {}).get(cid, 1)}

    def _chunk_index(self, body: bytes) -> list[int]:
        """Record a chunk index's chunk (offset, start time); returns the channel ids it lists."""
        try:
            start, _end, offset, _length, size = struct.unpack_from("<QQQQI", body, 0)
            if size % 10 or 36 + size > len(body):
                raise struct.error("message index offsets past the record")
            ids = np.frombuffer(body, "<u2", count=size // 2, offset=36)[::5]
        except (struct.error, ValueError) as exc:
            raise ReadError(
                f"{self.path}: corrupt MCAP record (opcode {OP_CHUNK_INDEX:#x}): {exc}"
            ) from None
        self.chunk_starts.append((offset, start))
        return ids.tolist()

    def _read_record(self, opcode: int, body: bytes):  # noqa: ANN202
        """A Schema, Channel or Statistics record's body (:mod:`imupipe.readers.mcap.records`:
        the fields the specification lists, the rest left); one whose fields do not fit it as
        their lengths say is read by the mcap library's record class, which reads it its own
        way or fails (imported then only: issue 39); ReadError naming the file when it
        cannot be read."""
        read = {
            OP_SCHEMA: records.read_schema,
            OP_CHANNEL: records.read_channel,
            OP_STATISTICS: records.read_statistics,
        }[opcode]
        try:
            return read(body)
        except records.RecordError:
            pass
        from mcap import records as library
        from mcap.data_stream import ReadDataStream

        kind = {OP_SCHEMA: library.Schema, OP_CHANNEL: library.Channel}.get(
            opcode, library.Statistics
        )
        try:
            return kind.read(ReadDataStream(io.BytesIO(body)))
        except Exception as exc:  # noqa: BLE001 - any failure to parse is a corrupt record
            raise ReadError(
                f"{self.path}: corrupt MCAP record (opcode {opcode:#x}): {exc}"
            ) from None

    def _parsed(self, opcode: int, body: bytes):  # noqa: ANN202
        """:meth:`_read_record` of a Schema or Channel record, parsed once per process for the
        same bytes (:data:`PARSED_BYTES`; the records are never changed once read)."""
        key = (opcode, body)
        found = _PARSED.get(key)
        if found is None:
            found = self._read_record(opcode, body)
            global _parsed_bytes
            _parsed_bytes += len(body)
            if _parsed_bytes > PARSED_BYTES:
                _PARSED.clear()
                _parsed_bytes = len(body)
            _PARSED[key] = found
        return found

    def _collect(self, opcode: int, body: bytes) -> bool:
        """Keep a Schema or Channel record (a schema of id 0 is invalid and ignored, as the
        specification says); True when it was one of them."""
        if opcode == OP_SCHEMA:
            s = self._parsed(opcode, body)
            if s.id:
                self._schemas[s.id] = s
        elif opcode == OP_CHANNEL:
            c = self._parsed(opcode, body)
            self._channels[c.id] = c
        elif opcode == OP_HEADER:
            try:
                self.profile = records.unpack(OP_HEADER, body)[0]
            except records.RecordError:  # the profile is informative only
                self.profile = ""
            return False
        else:
            return False
        return True

    def _join(self) -> None:
        """:attr:`channels` from the Schema and Channel records gathered so far."""
        out = {}
        for c in self._channels.values():
            out[c.id] = _channel_info(c, self._schemas.get(c.schema_id))
        self.channels = out

    def _defined(self, needed: set[int]) -> bool:
        """Whether the records gathered so far define every channel of ``needed``."""
        schema_of = {cid: c.schema_id for cid, c in self._channels.items()}
        return defined(needed, schema_of, self._schemas)

    def _first_pass(self, needed: set[int]) -> None:
        """Schema and Channel records from the data section (top-level and inside chunks),
        until every channel of ``needed`` is defined with its schema; with ``needed`` empty,
        from the whole data section, counting the messages of each channel too."""
        counts: dict[int, int] = {}
        with self._open() as fh:
            for opcode, pos, body in self._records(fh, 8, self.size):
                if opcode == OP_CHUNK:
                    buf = self._decompress(body, pos)
                    for op, start, end in scan_records(buf, f"{self.path}: chunk at byte {pos}"):
                        if op == OP_MESSAGE:
                            cid = int.from_bytes(bytes(buf[start : start + 2]), "little")
                            counts[cid] = counts.get(cid, 0) + 1
                        else:
                            self._collect(op, bytes(buf[start:end]))
                elif opcode == OP_MESSAGE and len(body) >= 2:
                    cid = int.from_bytes(body[:2], "little")
                    counts[cid] = counts.get(cid, 0) + 1
                elif opcode == OP_DATA_END:
                    self._scanned = True
                    break
                else:
                    self._collect(opcode, body)
                if needed and self._defined(needed):
                    return
            else:
                self._scanned = True
        if not needed:
            self.counts = counts

    def channel(self, cid: int, chunk: ChunkMessages) -> ChannelInfo:
        """The channel of id ``cid``, on which ``chunk`` holds messages: looked for in the
        chunk's own records, then in the whole data section, when not known yet; ReadError
        when the file never defines it."""
        found = self.channels.get(cid)
        if found is not None:
            return found
        if len(chunk.buf):
            for op, start, end in scan_records(chunk.buf, chunk.where):
                if op in (OP_SCHEMA, OP_CHANNEL):
                    self._collect(op, chunk.buf[start:end].tobytes())
        if cid not in self._channels and not self._scanned:
            self._first_pass({cid})
        self._join()
        if cid not in self.channels:
            raise ReadError(
                f"{chunk.where}: message on channel {cid}, which the file never defines"
            )
        return self.channels[cid]

    def _load_chunk(
        self, pread: Callable[[int, int], bytes], pos: int, head: bytes, out: np.ndarray | None
    ) -> np.ndarray:
        """Read the chunk record at ``pos`` and decompress it (thread-safe: ``pread(length,
        offset)`` reads the file, see :func:`_pread`); into ``out`` (of the chunk's uncompressed
        size, see :func:`_chunk_buffer`) when given."""
        try:
            length = int.from_bytes(pread(9, pos)[1:9], "little")
            if out is None:
                return self._decompress(pread(length, pos + 9), pos)
            where = f"{self.path}: chunk at byte {pos}"
            f = ChunkFields.of(head, where)
            if f.data_start + f.data_length > length:
                raise ReadError(f"{where}: {f.past_the_record}")
            if f.compression not in DECOMPRESSORS:
                raise ReadError(f"{where}: unsupported chunk compression '{f.compression}'")
            data = pread(f.data_length, pos + 9 + f.data_start)
        except OSError as exc:
            raise ReadError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        if len(data) != f.data_length:
            raise ReadError(f"{where}: {f.past_the_record}")
        return f.checked(decompress_into(data, f.compression, out, where), where)

    def _decompress(self, body: bytes, pos: int) -> np.ndarray:
        where = f"{self.path}: chunk at byte {pos}"
        f = ChunkFields.of(body, where)
        data = memoryview(body)[f.data_start : f.data_start + f.data_length]
        if len(data) != f.data_length:
            raise ReadError(f"{where}: {f.past_the_record}")
        return f.checked(decompress_chunk(data, f.compression, f.size, where), where)

    # -- chunks ----------------------------------------------------------------------------
    def _bounds(self) -> tuple[list[int], list[int]]:
        """Chunk offsets (sorted) and the minimum start time of the chunks from each on."""
        if self._bounds_cache is None:
            pairs = sorted(self.chunk_starts)
            suffix, low = [], NEVER
            for _, start in reversed(pairs):
                low = min(low, start)
                suffix.append(low)
            self._bounds_cache = [offset for offset, _ in pairs], suffix[::-1]
        return self._bounds_cache

    def chunks(
        self, group: int = 0, ready: Callable[[ChunkMessages], None] | None = None
    ) -> Iterator[ChunkMessages]:
        """Every chunk (and every run of un-chunked messages) in file order.

        ``group`` (bytes, 0: none): chunks are decompressed back to back into buffers of that
        size, and those that lie back to back are handed over as one :class:`ChunkMessages`
        (its :attr:`~ChunkMessages.parts` the chunks as they would have come one by one), for
        a caller whose work per chunk costs more than its work per message (issue 39).
        ``ready``: called with each chunk (not a group) once it is decompressed and indexed,
        in the reading thread, before it is handed over: work on its bytes while they are in
        the core's cache.

        Worker threads decompress (and CRC-check) the next :data:`PREFETCH` chunks while the
        caller decodes the current one (zstd, lz4 and zlib release the GIL). A file of one
        chunk, or a small one (:data:`SMALL_FILE`, read whole), has its chunks decompressed in
        the reading thread, each when it is reached: nothing to overlap worth a hand-off; so
        has every file when no CPU is free for a decompression thread (:func:`no_spare_cpu`:
        one CPU allowed, or a busy machine)."""
        offsets, suffix_min = self._bounds()
        pool = BufferPool(group)
        merge = _Merge() if group else None
        pending: ChunkMessages | None = None
        queue: collections.deque[ChunkMessages] = collections.deque()
        loose = bytearray()
        loose_off: dict[int, list[int]] = {}
        whole = None
        if self.size <= SMALL_FILE:
            with open(self.path, "rb") as fh:
                whole = fh.read()
            if len(whole) != self.size:  # changed since it was opened: read it as a large one
                whole = None
        inline = whole is not None or len(offsets) == 1 or no_spare_cpu()
        with (
            open(self.path, "rb") if whole is None else io.BytesIO(whole) as fh,
            contextlib.nullcontext() if inline else decompress_workers() as worker,
        ):
            pread = _pread(fh.fileno()) if whole is None else _pread(whole)
            for opcode, pos, body in self._records(fh, 8, self.size, lazy=True):
                if opcode == OP_MESSAGE_INDEX and pending is not None:
                    if len(body) < 6:
                        raise ReadError(f"{pending.where}: corrupt message index")
                    cid, rlen = struct.unpack_from("<HI", body, 0)
                    if 6 + rlen > len(body) or rlen % 16:
                        raise ReadError(f"{pending.where}: corrupt message index")
                    pairs = np.frombuffer(body, "<u8", count=rlen // 8, offset=6).reshape(-1, 2)
                    found = pairs[:, 1].astype(np.int64)
                    if len(found) > 1 and (found[1:] < found[:-1]).any():
                        found.sort()
                    pending.offsets[cid] = found
                    continue
                if pending is not None:
                    queue.append(pending)
                    pending = None
                while len(queue) > PREFETCH or (queue and opcode != OP_CHUNK):
                    yield from _handed(_finished(queue.popleft(), pool, ready), merge)
                if opcode == OP_MESSAGE:
                    if len(body) < 22:
                        raise ReadError(f"{self.path}: corrupt message record at byte {pos}")
                    cid = int.from_bytes(body[:2], "little")
                    loose_off.setdefault(cid, []).append(len(loose))
                    loose += bytes([OP_MESSAGE]) + len(body).to_bytes(8, "little") + body
                    if len(loose) >= PSEUDO_CHUNK_BYTES:
                        report(pos, self.size)
                        yield from _handed(None, merge)
                        yield _loose_chunk(
                            loose, loose_off, f"{self.path}: messages before byte {pos}"
                        )
                        loose, loose_off = bytearray(), {}
                    continue
                if loose:
                    yield from _handed(None, merge)
                    yield _loose_chunk(loose, loose_off, f"{self.path}: messages before byte {pos}")
                    loose, loose_off = bytearray(), {}
                if opcode in (OP_SCHEMA, OP_CHANNEL):
                    if self._collect(opcode, body):
                        self._join()
                elif opcode == OP_CHUNK:
                    report(pos, self.size)  # the chunks before this one are read
                    k = bisect.bisect_right(offsets, pos)
                    if offsets:
                        bound = suffix_min[k] if k < len(offsets) else NEVER
                    else:
                        bound = int.from_bytes(body[:8], "little") if len(body) >= 8 else 0
                    out = _chunk_buffer(body, pool)
                    if inline:  # no thread hand-off
                        future = _Later(self._load_chunk, pread, pos, body, out)
                    else:
                        future = worker.submit(self._load_chunk, pread, pos, body, out)
                    pending = ChunkMessages(
                        future,  # type: ignore[arg-type]
                        {},
                        f"{self.path}: chunk at byte {pos}",
                        bound,
                        -1 if out is None else pool.start,
                    )
                elif opcode == OP_DATA_END:
                    break
            if pending is not None:
                queue.append(pending)
            while queue:
                yield from _handed(_finished(queue.popleft(), pool, ready), merge)
            yield from _handed(None, merge)
            if loose:
                yield _loose_chunk(loose, loose_off, f"{self.path}: messages at the end")


def _pread(source: int | bytes) -> Callable[[int, int], bytes | memoryview]:
    """``read(length, offset)`` of a file: ``os.pread`` of the descriptor ``source``, or a
    view of the file's bytes ``source`` (as short as ``pread`` past the end)."""
    if isinstance(source, int):
        return functools.partial(os.pread, source)
    view = memoryview(source)
    return lambda length, offset: view[offset : offset + length]


class _Later:
    """Work done in the reading thread when its result is asked for: what a worker's future
    gives (``result()``), at the same point of the read (an error included)."""

    __slots__ = ("args", "fn")

    def __init__(self, fn: Callable[..., np.ndarray], *args: object) -> None:
        self.fn, self.args = fn, args

    def result(self) -> np.ndarray:
        return self.fn(*self.args)


@dataclass(frozen=True)
class ChunkFields:
    """The fields of a chunk record's body before its data: uncompressed ``size``, ``crc``
    (0: none), ``compression``, and where the compressed data lies in the body."""

    size: int
    crc: int
    compression: str
    data_start: int
    data_length: int

    @classmethod
    def of(cls, body: bytes, where: str) -> ChunkFields:
        """The fields of ``body`` (the record's body, or at least its first bytes up to the
        data); ReadError naming ``where`` when they cannot be read."""
        try:
            size, crc = struct.unpack_from("<QI", body, 16)
            (clen,) = struct.unpack_from("<I", body, 28)
            compression = str(body[32 : 32 + clen], "utf-8")  # bytes or a memoryview
            (dlen,) = struct.unpack_from("<Q", body, 32 + clen)
        except (struct.error, UnicodeDecodeError):
            raise ReadError(f"{where}: corrupt chunk header") from None
        return cls(size, crc, compression, 40 + clen, dlen)

    @property
    def past_the_record(self) -> str:
        return f"corrupt chunk (data length {self.data_length} past the record)"

    def checked(self, raw: np.ndarray, where: str) -> np.ndarray:
        """``raw`` (the decompressed data), once its CRC is checked."""
        if self.crc and crc32(raw) != self.crc:
            raise ReadError(f"{where}: chunk CRC mismatch (corrupt data)")
        return raw


def _chunk_buffer(head: bytes, pool: BufferPool) -> np.ndarray | None:
    """A buffer of ``pool`` for the chunk record whose body starts with ``head``; None when
    its fields are not all in ``head`` or its sizes are implausible (a damaged file: the
    chunk is then read as a whole and its errors named as they are)."""
    try:
        f = ChunkFields.of(head, "")
    except ReadError:
        return None
    if f.compression != "zstd" or f.size > min(POOLED_BYTES, 64 * f.data_length + 4096):
        return None
    return pool.take(f.size)


def _finished(
    chunk: ChunkMessages, pool: BufferPool, ready: Callable[[ChunkMessages], None] | None
) -> ChunkMessages:
    """The chunk with its decompressed buffer (waiting for the worker) and its offsets, given
    to ``ready`` (if any); the buffer goes back to ``pool`` (used again once nothing refers to
    it)."""
    chunk.buf = chunk.buf.result()  # type: ignore[attr-defined]
    pool.give(chunk.buf)
    chunk = _indexed_or_scanned(chunk)
    if ready is not None:
        ready(chunk)
    return chunk


class _Merge:
    """Chunks that lie back to back in one arena of a
    :class:`~imupipe.readers.compression.BufferPool`, gathered to be handed over as one."""

    def __init__(self) -> None:
        self.parts: list[ChunkMessages] = []

    def push(self, chunk: ChunkMessages | None) -> list[ChunkMessages]:
        """Take ``chunk`` (None: no more to come here); returns what is ready to hand over."""
        parts = self.parts
        if chunk is not None and parts:
            last = parts[-1]
            if (
                last.start >= 0
                and chunk.start == BufferPool.after(last.start, len(last.buf))
                and chunk.buf.base is last.buf.base
            ):
                parts.append(chunk)
                return []
        self.parts = [] if chunk is None else [chunk]
        if len(parts) < 2:
            return parts
        first = parts[0]
        by_channel: dict[int, list[np.ndarray]] = {}
        for part in parts:
            shift = part.start - first.start
            for cid, off in part.offsets.items():
                by_channel.setdefault(cid, []).append(off + shift if shift else off)
        offsets = {
            cid: found[0] if len(found) == 1 else np.concatenate(found)
            for cid, found in by_channel.items()
        }
        buf = first.buf.base[first.start : parts[-1].start + len(parts[-1].buf)]
        return [ChunkMessages(buf, offsets, first.where, parts[-1].bound, first.start, parts)]


def _handed(chunk: ChunkMessages | None, merge: _Merge | None) -> list[ChunkMessages]:
    """The chunks to hand over once ``chunk`` is done (None: flush what ``merge`` holds)."""
    if merge is None:
        return [] if chunk is None else [chunk]
    return merge.push(chunk)


def _loose_chunk(buf: bytearray, offsets: dict[int, list[int]], where: str) -> ChunkMessages:
    """Messages outside chunks as a pseudo-chunk (bound: its first message's log time)."""
    first = min(o[0] for o in offsets.values())
    return ChunkMessages(
        np.frombuffer(bytes(buf), np.uint8),
        {cid: np.asarray(o, np.int64) for cid, o in offsets.items()},
        where,
        int.from_bytes(bytes(buf[first + 15 : first + 23]), "little"),
    )


def _indexed_or_scanned(chunk: ChunkMessages) -> ChunkMessages:
    """The chunk with per-channel offsets, scanning its records when it came without indexes."""
    if chunk.offsets or len(chunk.buf) == 0:
        return chunk
    found: dict[int, list[int]] = {}
    for opcode, start, _end in scan_records(chunk.buf, chunk.where):
        if opcode == OP_MESSAGE and _end - start >= 22:
            cid = int(chunk.buf[start]) | (int(chunk.buf[start + 1]) << 8)
            found.setdefault(cid, []).append(start - 9)
    chunk.offsets = {cid: np.asarray(o, np.int64) for cid, o in found.items()}
    return chunk


def scan_records(buf: np.ndarray, where: str) -> Iterator[tuple[int, int, int]]:
    """Records inside a decompressed chunk: (opcode, body start, body end). One Python step per
    record: the fallback for chunks without message indexes."""
    raw = buf.tobytes() if isinstance(buf, np.ndarray) else bytes(buf)
    pos, n = 0, len(raw)
    while pos < n:
        if pos + 9 > n:
            raise ReadError(f"{where}: record header cut off inside the chunk")
        length = int.from_bytes(raw[pos + 1 : pos + 9], "little")
        end = pos + 9 + length
        if end > n:
            raise ReadError(f"{where}: record runs past the end of its chunk")
        yield raw[pos], pos + 9, end
        pos = end
