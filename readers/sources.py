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

from imupipe.pipeline.errors import ReadError
from imupipe.readers.decoded import Piece, assemble, concat, select_topics
from imupipe.readers.spec import InputSpec, RawMessage


class LogSource(Protocol):
    path: Path
    format: str

    def topic_types(self) -> dict[str, str]:
        """Topic -> message type as written in the file."""

    def topic_counts(self) -> dict[str, int] | None:
        """Topic -> message count, when the file states it without decoding."""

    def first_time(self) -> int:
        """Log time of the first message (ns), for ordering split files."""

    def topic_times(self) -> dict[str, np.ndarray]:
        """Topic -> log times (int64 ns) of its messages, without decoding payloads."""

    def chunks(
        self, streams: dict[str, str], carry: bool, decode: bool = True
    ) -> Iterator[tuple[dict[str, Piece], list[RawMessage]]]:
        """Per chunk: stream -> Piece for the chosen ``streams`` (stream -> topic; none when not
        ``decode``), and the messages of every other topic as RawMessage (when ``carry``)."""


def _choose(spec: InputSpec, sources: Sequence[LogSource]) -> dict[str, str]:
    types: dict[str, str] = {}
    for src in sources:
        types.update(src.topic_types())
    where = sources[0].path if len(sources) == 1 else Path(spec.path)
    return select_topics(where, spec, types)


def _ordered(sources: Sequence[LogSource]) -> list[LogSource]:
    return sorted(sources, key=lambda s: s.first_time()) if len(sources) > 1 else list(sources)


def _check_empty(spec: InputSpec, streams: dict[str, str], counts: dict[str, int]) -> None:
    for stream, topic in streams.items():
        if counts.get(stream, 0) == 0:
            raise ReadError(f"{spec.path}: topic '{topic}' has no messages")


def read_sources(spec: InputSpec, sources: Sequence[LogSource]) -> tuple[pa.Table, list[str]]:
    """The whole input as one common table; returns (table, warnings)."""
    streams = _choose(spec, sources)
    parts: dict[str, list[Piece]] = {s: [] for s in streams}
    for src in _ordered(sources):
        for pieces, _ in src.chunks(streams, carry=False):
            for stream, piece in pieces.items():
                parts[stream].append(piece)
    joined = {s: concat(p, s) for s, p in parts.items()}
    _check_empty(spec, streams, {s: len(p) for s, p in joined.items()})
    parts.clear()
    warnings: list[str] = []
    table = assemble(
        joined,
        time=spec.time,
        source=str(spec.path),
        fmt=sources[0].format,
        topics=streams,
        where=str(spec.path),
        warnings=warnings,
    )
    return table, warnings


def iter_sources(
    spec: InputSpec, sources: Sequence[LogSource], batch_rows: int
) -> Iterator[tuple[pa.Table, list[RawMessage]]]:
    """Batches of about ``batch_rows`` rows in file (log) order, each sorted by time within
    itself, with the carried-over messages of the same chunks."""
    streams = _choose(spec, sources)
    parts: dict[str, list[Piece]] = {s: [] for s in streams}
    raw: list[RawMessage] = []
    rows = 0
    total = {s: 0 for s in streams}

    def flush() -> tuple[pa.Table, list[RawMessage]]:
        joined = {s: concat(p, s) for s, p in parts.items()}
        table = assemble(
            joined,
            time=spec.time,
            source=str(spec.path),
            fmt=sources[0].format,
            topics=streams,
            where=str(spec.path),
            warnings=[],
            sort=False,
        )
        return table, raw

    for src in _ordered(sources):
        for pieces, messages in src.chunks(streams, carry=True):
            for stream, piece in pieces.items():
                parts[stream].append(piece)
                rows += len(piece)
                total[stream] += len(piece)
            raw.extend(messages)
            if rows >= batch_rows:
                yield flush()
                parts = {s: [] for s in streams}
                raw, rows = [], 0
    _check_empty(spec, streams, total)
    if rows or raw:
        yield flush()


def carry_sources(spec: InputSpec, sources: Sequence[LogSource]) -> list[RawMessage]:
    """Every message of the topics the table does not hold, in log-time order (stable)."""
    streams = _choose(spec, sources)
    out: list[RawMessage] = []
    for src in _ordered(sources):
        for _, messages in src.chunks(streams, carry=True, decode=False):
            out.extend(messages)
    out.sort(key=lambda m: m.log_time)
    return out


def log_sources(spec: InputSpec) -> list[LogSource]:
    """The sources of a binary input (MCAP, ROS 1 bag(s), ROS 2 bag)."""
    from imupipe.readers.dispatch import detect_format

    fmt = detect_format(Path(spec.path))
    if fmt == "mcap":
        from imupipe.readers.mcap_reader import McapSource

        return [McapSource(spec.path)]
    if fmt == "ros1":
        from imupipe.readers.ros1_reader import bag_sources

        return list(bag_sources(Path(spec.path)))
    if fmt == "ros2":
        from imupipe.readers.ros2_reader import bag2_sources

        return bag2_sources(Path(spec.path))
    raise ReadError(f"{spec.path}: not a binary log (MCAP or ROS bag)")
