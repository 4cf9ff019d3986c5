"""What an MCAP file holds, from its summary section alone: topics, types, message counts and
each topic's first and last log time, without decompressing a chunk (and without numpy).

The summary (MCAP specification, "Summary Section") holds the channels and schemas, the
``Statistics`` record (message count per channel) and one ``ChunkIndex`` per chunk (its message
start and end times, and the file offset of the ``MessageIndex`` record of every channel in it).
A topic's first log time is the smallest in the message indexes of the chunks holding it, read
in order of chunk start time until a chunk starts after the smallest found (its last log time
likewise, from the chunk end times); usually one message index each.

:func:`topic_summary` returns None when the file cannot answer so: no summary, no statistics,
a summary that does not define every channel with messages (and its schema), messages outside
the indexed chunks (the message indexes list fewer messages than the statistics count), a chunk
without message indexes. The caller then reads the messages' log times
(:mod:`imupipe.readers.mcap.fast`).

Every summary record is optional (MCAP specification, "Summary Section"), and files leave out
what the specification asks for: the ``mcap`` library's own ``Writer(repeat_channels=False)``
writes statistics without repeating the Channel records. :func:`complete` is the one rule, here
and in :mod:`imupipe.readers.mcap.fast`, for when the summary's channels can be taken as the
file's.

The summary's records are read by :func:`imupipe.readers.mcap.records.read_summary`, as
``convert``'s count check reads them (not by the ``mcap`` library: issue 39, its modules cost
``inspect`` about 20 ms to import); a summary it cannot read (a record that does not fit its
layout or has no place in a summary, a footer without the trailing magic) cannot tell either.
"""

from __future__ import annotations

import struct
from collections.abc import Container, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

if TYPE_CHECKING:
    from imupipe.readers.mcap.records import Statistics

OP_MESSAGE_INDEX = 0x07


@dataclass
class TopicSummary:
    """One topic: message type as written, message count, first and last log time (ns; None
    without messages)."""

    type: str
    count: int
    start_ns: int | None
    end_ns: int | None


def _index_times(f: BinaryIO, offset: int, channel: int) -> list[int] | None:
    """The log times of a ``MessageIndex`` record at ``offset`` (None: not one of ``channel``)."""
    f.seek(offset)
    head = f.read(15)
    if len(head) < 15 or head[0] != OP_MESSAGE_INDEX:
        return None
    _, _, cid, size = struct.unpack("<BQHI", head)
    body = f.read(size)
    if cid != channel or len(body) != size or size % 16:
        return None
    return list(struct.unpack(f"<{size // 8}Q", body)[::2])


def complete(
    stats: Statistics | None,
    channels: Mapping[int, int],
    schemas: Container[int],
    indexed: Iterable[Iterable[int]] = (),
) -> bool:
    """Whether the summary's Channel records (``channels``: id -> schema id) can be taken as the
    file's: ``stats`` (the Statistics record, None without) counts no more channels than it
    holds, and every channel the summary holds or says has messages (those ``stats`` counts
    messages on, when its counts add up to its message count; those the chunk indexes list,
    ``indexed``: the channel ids of each) is defined with its schema (:func:`defined`). False
    when the summary names no channel at all (no Channel record, no usable statistics, no
    chunk index listing one): it cannot tell.

    A summary whose Channel records are all it says of the channels (no statistics, chunk
    indexes without message indexes) is taken at its word: writers repeat all their channels
    or none. Should it hold too few, the messages of the others are still read
    (:meth:`imupipe.readers.mcap.fast.McapFile.channel`); only a topic it never names cannot be
    chosen as a stream.

    The specification asks for more ("When using a Statistics record with a non-empty
    channel_message_counts, the Summary Data section MUST contain a copy of all Channel
    records"), but files without it are read by the reference readers (the conformance suite's
    ``TenMessages-st.mcap``), so they are read here too."""
    needed: set[int] = set(channels)
    told = bool(channels)
    if stats is not None:
        counts = stats.channel_message_counts
        if stats.channel_count > len(channels):
            return False
        if sum(counts.values()) == stats.message_count:
            needed.update(cid for cid, n in counts.items() if n)
            told = True
    for ids in indexed:
        needed.update(ids)
        told = told or bool(ids)
    return told and defined(needed, channels, schemas)


def defined(needed: Iterable[int], channels: Mapping[int, int], schemas: Container[int]) -> bool:
    """Whether every channel of ``needed`` is in ``channels`` (id -> schema id) with its schema
    in ``schemas`` (schema id 0: a schemaless channel, complete without)."""
    return all(
        cid in channels and (channels[cid] == 0 or channels[cid] in schemas) for cid in needed
    )


def _indexed_messages(indexes: list) -> int | None:
    """Messages listed by the message indexes of ``indexes`` (chunk indexes), from their lengths
    (15 bytes a record and 16 a message); None when the lengths do not fit (padded records)."""
    total = 0
    for c in indexes:
        body = c.message_index_length - 15 * len(c.message_index_offsets)
        if body < 0 or body % 16:
            return None
        total += body // 16
    return total


class _CannotTell(Exception):
    """The summary does not hold what :func:`topic_summary` needs."""


def _edge(f: BinaryIO, chunks: list, channel: int, last: bool) -> int | None:
    """The first (``last``: the last) log time of ``channel`` over the ``chunks`` (chunk
    indexes) that hold it: their message indexes read in order of chunk start (end) time, until
    a chunk starts after (ends before) the earliest (latest) time found."""
    if last:
        order = sorted(chunks, key=lambda c: -c.message_end_time)
    else:
        order = sorted(chunks, key=lambda c: c.message_start_time)
    best: int | None = None
    for chunk in order:
        if best is not None and (
            chunk.message_end_time <= best if last else chunk.message_start_time >= best
        ):
            break
        times = _index_times(f, chunk.message_index_offsets[channel], channel)
        if times is None:
            raise _CannotTell
        if times:
            edge = max(times) if last else min(times)
            best = edge if best is None else (max(best, edge) if last else min(best, edge))
    return best


def topic_summary(path: Path) -> dict[str, TopicSummary] | None:
    """Topic -> :class:`TopicSummary` from the summary section, or None when the file does not
    hold what it takes (see the module docstring)."""
    from imupipe.readers.mcap.records import RecordError, read_summary

    with open(path, "rb") as f:
        try:  # OSError: a file shorter than the footer, which the read seeks back over
            summary = read_summary(f)
        except (RecordError, OSError):
            return None  # a damaged or odd summary: the caller reads the messages
        if summary is None or summary.statistics is None:
            return None
        stats = summary.statistics
        counts = stats.channel_message_counts
        indexes = summary.chunk_indexes
        channels = {cid: c.schema_id for cid, c in summary.channels.items()}
        if sum(counts.values()) != stats.message_count:
            return None  # per-channel counts that do not add up
        if not complete(stats, channels, summary.schemas):
            return None  # the summary does not define every channel with messages
        if stats.message_count and _indexed_messages(indexes) != stats.message_count:
            return None  # messages outside the indexed chunks, or no chunk indexes
        out: dict[str, TopicSummary] = {}
        for cid, channel in summary.channels.items():
            schema = summary.schemas.get(channel.schema_id)
            count = int(counts.get(cid, 0))
            first = last = None
            if count:
                holding = [c for c in indexes if cid in c.message_index_offsets]
                try:
                    first, last = _edge(f, holding, cid, False), _edge(f, holding, cid, True)
                except _CannotTell:
                    return None
                if first is None or last is None:
                    return None  # no chunk lists a message of it, or its indexes are empty
            prev = out.get(channel.topic)
            if prev is not None:  # several channels on one topic: one entry
                starts = [t for t in (prev.start_ns, first) if t is not None]
                ends = [t for t in (prev.end_ns, last) if t is not None]
                first, last = min(starts, default=None), max(ends, default=None)
                count += prev.count
            out[channel.topic] = TopicSummary(
                schema.name if schema is not None else "", count, first, last
            )
        return out
