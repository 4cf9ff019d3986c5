"""Binary logs as sources of decoded chunks, and the three ways of reading them.

A :class:`LogSource` (one MCAP file, ROS 1 bag or ROS 2 storage file) knows its topics and
yields, chunk by chunk in file order, the decoded sensor messages of the chosen topics
(:class:`~imupipe.readers.decoded.Piece` per stream) and, when asked, the other topics'
messages as ROS 2 :class:`~imupipe.readers.spec.RawMessage` s. Several sources form one input
(split bags, a folder): they are joined in the order of their first message.

- :func:`read_sources`: the whole input as one table, sorted by time (stable, warned).
- :func:`iter_sources`: bounded-memory batches of about ``batch_rows`` rows, each with the carried
  over messages of the same chunks.
- :func:`carry_sources`: every carried-over message, in log-time order.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import arrow_array
from imupipe.readers.decoded import Piece, concat
from imupipe.readers.errors import ReadError
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.readers.table_buffer import TableBuffer, assemble, order_warnings
from imupipe.readers.topics import select_topics

NEVER = 2**63 - 1


class LogSource(Protocol):
    path: Path
    format: str
    # optional: ``warnings``, a list of lines about how the file was read (an unindexed ROS 1
    # bag read by scanning), reported by read_sources and inspect

    def topic_types(self) -> dict[str, str]:
        """Topic -> message type as written in the file."""

    def topic_counts(self) -> dict[str, int] | None:
        """Topic -> message count, when the file states it without decoding."""

    def first_time(self) -> int:
        """Log time of the first message (ns), for ordering split files."""

    def topic_times(self) -> dict[str, np.ndarray]:
        """Topic -> log times (int64 ns) of its messages, without decoding payloads."""

    def chunks(
        self, streams: dict[str, str], carry: bool, decode: bool = True, whole: bool = False
    ) -> Iterator[tuple[dict[str, Piece], list[RawMessage], int]]:
        """Per chunk: stream -> Piece for the chosen ``streams`` (stream -> topic; none when not
        ``decode``), the messages of every other topic as RawMessage (when ``carry``), and a
        lower bound of the log times of every message that comes later in the file. ``whole``:
        the caller reads the whole log into one table (:func:`read_sources`), so the source
        may hand over several chunks as one (their pieces joined, bound the last one's)."""


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() else path.stat().st_size


def _choose(
    spec: InputSpec, sources: Sequence[LogSource], notes: list[str] | None = None
) -> dict[str, str]:
    types: dict[str, str] = {}
    for src in sources:
        types.update(src.topic_types())
    where = sources[0].path if len(sources) == 1 else Path(spec.path)
    if spec.fields is not None:  # the mapped topics (never carried over)
        from imupipe.readers.mapped import mapped_topics

        return {topic: topic for topic in mapped_topics(spec, list(types))}
    return select_topics(where, spec, types, notes)


OTHER_NAMES = {"gyro": ("linear_acceleration", "accel"), "accel": ("angular_velocity", "gyro")}


def _tally_other(pieces: dict[str, Piece], tally: dict[str, list[int]]) -> None:
    """Add up, per split stream, the messages whose unread vector is not zeros, and all."""
    for stream in OTHER_NAMES:
        piece = pieces.get(stream)
        if piece is not None:
            both = tally.setdefault(stream, [0, 0])
            both[0] += piece.other_nonzero
            both[1] += len(piece)


def other_warnings(where: str, streams: dict[str, str], tally: dict[str, list[int]]) -> list[str]:
    """One line per split topic whose messages carry the other sensor's vector (not zeros): it
    is not read, and the corrected log writes zeros there."""
    out = []
    for stream, (nonzero, total) in tally.items():
        if nonzero:
            field, other = OTHER_NAMES[stream]
            out.append(
                f"{where} topic {streams[stream]} ({stream}_topic): {nonzero} of {total} "
                f"messages carry a {field} that is not zeros; it is not read (the {other} comes "
                "from its own topic) and a corrected log writes zeros there"
            )
    return out


def _ordered(sources: Sequence[LogSource]) -> list[LogSource]:
    return sorted(sources, key=lambda s: s.first_time()) if len(sources) > 1 else list(sources)


def _check_empty(spec: InputSpec, streams: dict[str, str], counts: dict[str, int]) -> None:
    for stream, topic in streams.items():
        if counts.get(stream, 0) == 0:
            raise ReadError(f"{spec.path}: topic '{topic}' has no messages")


def read_sources(spec: InputSpec, sources: Sequence[LogSource]) -> tuple[pa.Table, list[str]]:
    """The whole input as one common table; returns (table, warnings)."""
    if spec.fields is not None:
        from imupipe.readers.mapped import read_mapped

        return read_mapped(spec, sources)  # type: ignore[arg-type]
    notes: list[str] = []
    streams = _choose(spec, sources, notes)
    stated = [src.topic_counts() for src in sources]
    counts = None
    if None not in stated:
        # a damaged file may state absurd counts: never trust more than one message per 16 bytes
        most = sum(_size(src.path) for src in sources) // 16
        counts = {s: min(most, sum(c.get(t, 0) for c in stated)) for s, t in streams.items()}  # type: ignore[union-attr]
    buffer = TableBuffer(list(streams), spec.time, counts)
    total = dict.fromkeys(streams, 0)
    other: dict[str, list[int]] = {}
    for src in _ordered(sources):
        sink = {"sink": buffer} if getattr(src, "prefills", False) else {}
        for pieces, _, _ in src.chunks(streams, carry=False, whole=True, **sink):
            _tally_other(pieces, other)
            buffer.add(pieces)
            for stream, piece in pieces.items():
                total[stream] += len(piece)
    _check_empty(spec, streams, total)
    warnings: list[str] = [w for src in sources for w in getattr(src, "warnings", ())]
    warnings += notes + other_warnings(str(spec.path), streams, other)
    table = buffer.table(
        sort=True,
        source=str(spec.path),
        fmt=sources[0].format,
        topics=streams,
        where=str(spec.path),
        warnings=warnings,
    )
    return table, warnings


def _split(piece: Piece, keep: np.ndarray) -> tuple[Piece, Piece]:
    """(rows where not ``keep``, rows where ``keep``) of a piece."""
    out = []
    for mask in (~keep, keep):
        idx = arrow_array(np.flatnonzero(mask))
        out.append(
            Piece(
                piece.stamp[mask],
                piece.log[mask],
                piece.frame.take(idx),
                {name: col[mask] for name, col in piece.columns.items()},
                None if piece.pub is None else piece.pub[mask],
            )
        )
    return out[0], out[1]


def iter_sources(
    spec: InputSpec,
    sources: Sequence[LogSource],
    batch_rows: int,
    carry: bool = True,
    warnings: list[str] | None = None,
) -> Iterator[tuple[pa.Table, list[RawMessage]]]:
    """Batches of about ``batch_rows`` rows in log-time order, each sorted by the chosen time
    within itself, with the carried-over messages of the same log-time span (none when not
    ``carry``: the other topics are not read).

    ``warnings``: after the last batch, the warnings :func:`read_sources` gives, once per
    topic: the sources' own, then the stamps out of time order or repeated within a batch
    (counts summed over the batches; a pair of stamps across a batch boundary is not
    compared).

    Chunks are read in file order; after each, messages whose log time is below the bound of
    everything still unread (chunk indexes / chunk infos) are final and may be emitted, the
    rest wait. Memory is bounded by ``batch_rows`` plus the overlap of the log's chunks.
    An input read through a field mapping: :func:`imupipe.readers.mapped.iter_mapped`."""
    if spec.fields is not None:
        from imupipe.readers.mapped import iter_mapped

        carried = _carried(spec, sources) if carry else None
        yield from iter_mapped(spec, sources, batch_rows, carried, warnings)  # type: ignore[arg-type]
        return
    notes: list[str] = []
    streams = _choose(spec, sources, notes)
    ordered = _ordered(sources)
    parts: dict[str, list[Piece]] = {s: [] for s in streams}
    raw: list[RawMessage] = []
    rows = 0
    total = {s: 0 for s in streams}
    counts: dict[str, list[int]] = {}
    other: dict[str, list[int]] = {}

    def flush(bound: int) -> tuple[pa.Table, list[RawMessage]]:
        nonlocal raw, rows
        out: dict[str, Piece] = {}
        for s in streams:
            joined = concat(parts[s], s)
            keep = joined.log >= bound
            out[s], rest = _split(joined, keep) if keep.any() else (joined, None)
            parts[s] = [rest] if rest is not None and len(rest) else []
        emit = [m for m in raw if m.log_time < bound]
        raw = [m for m in raw if m.log_time >= bound]
        rows = sum(len(p) for ps in parts.values() for p in ps)
        table = assemble(
            out,
            time=spec.time,
            source=str(spec.path),
            fmt=sources[0].format,
            topics=streams,
            where=str(spec.path),
            warnings=[],
            sort=False,
            counts=None if warnings is None else counts,
        )
        return table, emit

    for src, after in _with_later_first(ordered):
        for pieces, messages, bound in src.chunks(streams, carry=carry):
            _tally_other(pieces, other)
            for stream, piece in pieces.items():
                parts[stream].append(piece)
                rows += len(piece)
                total[stream] += len(piece)
            raw.extend(messages)
            if rows >= batch_rows:
                limit = min(bound, after)
                ready = sum(
                    int(np.count_nonzero(p.log < limit)) for ps in parts.values() for p in ps
                )
                if ready >= batch_rows or (ready and rows >= 4 * batch_rows):
                    yield flush(limit)
    _check_empty(spec, streams, total)
    if rows or raw:
        yield flush(NEVER)
    if warnings is not None:
        warnings += [w for src in sources for w in getattr(src, "warnings", ())]
        warnings += notes + other_warnings(str(spec.path), streams, other)
        warnings += order_warnings(str(spec.path), spec.time, counts)


def _carried(
    spec: InputSpec, sources: Sequence[LogSource]
) -> Iterator[tuple[list[RawMessage], int]]:
    """Per chunk: the messages of the topics the table does not hold, and the log time below
    which every message has been read."""
    streams = _choose(spec, sources)
    for src, after in _with_later_first(_ordered(sources)):
        for _, messages, bound in src.chunks(streams, carry=True, decode=False):
            yield messages, min(bound, after)


def _with_later_first(ordered: list[LogSource]) -> Iterator[tuple[LogSource, int]]:
    """Each source with the first log time of the sources after it (NEVER for the last): no
    message below it is still unread once the source is read."""
    for i, src in enumerate(ordered):
        yield src, min((s.first_time() for s in ordered[i + 1 :]), default=NEVER)


def carry_sources(spec: InputSpec, sources: Sequence[LogSource]) -> list[RawMessage]:
    """Every message of the topics the table does not hold, in log-time order (stable)."""
    out = [m for messages, _ in _carried(spec, sources) for m in messages]
    out.sort(key=lambda m: m.log_time)
    return out
