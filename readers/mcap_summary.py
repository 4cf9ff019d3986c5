"""What an MCAP file holds, from its summary section alone: topics, types, message counts and
each topic's first and last log time, without decompressing a chunk (and without numpy).

The summary (MCAP specification, "Summary Section") holds the channels and schemas, the
``Statistics`` record (message count per channel) and one ``ChunkIndex`` per chunk (its message
start and end times, and the file offset of the ``MessageIndex`` record of every channel in it).
A topic's first log time is the smallest in the message indexes of the chunks holding it, read
in order of chunk start time until a chunk starts after the smallest found (its last log time
likewise, from the chunk end times); usually one message index each.

:func:`topic_summary` returns None when the file cannot answer so: no summary, no statistics,
messages outside chunks, a chunk without message indexes. The caller then reads the messages'
log times (:mod:`imupipe.readers.fast_mcap`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

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
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        try:  # OSError: a file shorter than the footer, which the reader seeks back over
            summary = make_reader(f).get_summary()
        except (McapError, struct.error, ValueError, EOFError, KeyError, OSError):
            return None
        if summary is None or summary.statistics is None:
            return None
        counts = summary.statistics.channel_message_counts
        indexes = summary.chunk_indexes
        if sum(counts.values()) and not indexes:
            return None  # messages outside chunks, or no chunk indexes
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
