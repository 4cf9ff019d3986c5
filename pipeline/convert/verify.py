"""Verification of a converted log: the written file holds the input's messages, topic for topic.

The reference is the input's own index, read without reading the messages (MCAP summary
statistics, the ROS 1 bag index, ROS 2 ``metadata.yaml``, each read as ``inspect`` and ``run``
read it); for CSV and unindexed logs, the messages read. The written file's counts come from its
own summary.
"""

from __future__ import annotations

import collections
import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa

from imupipe.pipeline.errors import ImupipeError, ReadError
from imupipe.pipeline.writers.mcap import DEFAULT_TOPICS, stream_rows, written_streams
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import counts, metadata
from imupipe.readers.topics import NOT_CARRIED, some_of


class VerifyError(ImupipeError):
    """The written output does not hold the input's messages, topic for topic."""


def mcap_summary(
    path: Path, attachments: bool = True
) -> tuple[dict[str, int], dict[str, Any] | None] | None:
    """(messages per topic, the attached calibration.json) of a finished MCAP; None when the file
    has no summary (unfinished, or written without one) or one that does not name the topic of
    every channel it counts messages on (:func:`imupipe.readers.mcap.summary.complete`: every
    summary record is optional). ``attachments=False``: the attachments are not read (None in
    their place; half the time of a short log's summary)."""
    with open(path, "rb") as fh:
        return summary_of(fh, attachments)


def summary_of(
    fh: Any, attachments: bool = True
) -> tuple[dict[str, int], dict[str, Any] | None] | None:
    """:func:`mcap_summary` of an open, seekable binary file (a local file, or an object opened
    for ranged reads by :mod:`imupipe.pipeline.convert.remote`). Read by
    :func:`imupipe.readers.mcap.records.read_summary`; a file it cannot read so (a record that
    does not fit its layout, or has no place in a summary) by the ``mcap`` library, as before
    (issue 39: its modules cost a one-log ``convert`` about 5 ms to import)."""
    from imupipe.readers.mcap import records

    try:
        summary = records.read_summary(fh)
        if summary is None:
            return None
        topics = {cid: c.topic for cid, c in summary.channels.items()}
        counts = _per_topic(summary.statistics, topics)
        if counts is None or not attachments:
            return None if counts is None else (counts, None)
        found = [records.read_attachment(fh, offset) for offset in summary.attachments]
        return counts, _calibration(found)
    except records.RecordError:
        return _library_summary(fh, attachments)


def _library_summary(
    fh: Any, attachments: bool
) -> tuple[dict[str, int], dict[str, Any] | None] | None:
    """:func:`summary_of` by the ``mcap`` library's reader (from the start of ``fh``)."""
    from mcap.reader import make_reader

    fh.seek(0)
    reader = make_reader(fh)
    summary = reader.get_summary()
    if summary is None:
        return None
    counts = _per_topic(summary.statistics, {cid: c.topic for cid, c in summary.channels.items()})
    if counts is None or not attachments:
        return None if counts is None else (counts, None)
    return counts, _calibration((att.name, att.data) for att in reader.iter_attachments())


def _per_topic(stats: Any, topics: Mapping[int, str]) -> dict[str, int] | None:
    """Messages per topic of a summary's Statistics record (``topics``: its channels' topics by
    id); None without one, or when it counts messages on a channel the summary does not name
    (:func:`imupipe.readers.mcap.summary.complete`: no schema needed here)."""
    from imupipe.readers.mcap.summary import complete

    if stats is None or not complete(stats, dict.fromkeys(topics, 0), ()):
        return None
    per_topic: collections.Counter[str] = collections.Counter()
    for cid, n in stats.channel_message_counts.items():
        per_topic[topics[cid]] += n
    return dict(per_topic)


def _calibration(attached: Iterable[tuple[str, bytes]]) -> dict[str, Any] | None:
    """The (last) ``calibration.json`` of a file's (name, data) attachments; None without."""
    found = None
    for name, data in attached:
        if name == "calibration.json":
            found = json.loads(data)
    return found


def mcap_counts(path: Path) -> dict[str, int] | None:
    """Messages per topic from an MCAP's summary statistics (None when it has none)."""
    summary = mcap_summary(path, attachments=False)
    return None if summary is None else summary[0]


def input_counts(
    path: Path, fmt: str, warnings: list[str] | None = None, salvage: bool = False
) -> dict[str, int] | None:
    """Messages per topic from the log's own index, without reading the messages; None for CSV and
    for logs that have no index (then the counts read are the reference). ROS bags are opened by
    imupipe's own readers, so that ``convert`` accepts exactly what ``inspect`` and ``run`` do:
    a ROS 2 bag's ``metadata.yaml`` (:func:`imupipe.readers.ros2.reader.bag2_counts`), a ROS 1
    bag's index (None for an unindexed bag, whose scanning warning is appended to
    ``warnings``). ``salvage`` (``--read-truncated``): a cut-off MCAP or ROS 1 bag has no index
    to count by (None: the counts read, up to the cut, are the reference)."""
    try:
        if fmt == "mcap":
            try:
                return mcap_counts(path)
            except Exception:  # noqa: BLE001 - its reader reads it up to the cut, or refuses
                if salvage:
                    return None
                raise
        if fmt == "ros2":
            from imupipe.readers.ros2.reader import bag2_counts, bag2_sources

            if salvage and any(  # metadata.yaml counts what the cut-off files no longer hold
                getattr(getattr(src, "file", None), "cut", None) is not None
                for src in bag2_sources(path, salvage)
            ):
                return None
            return bag2_counts(path)
        if fmt == "ros1":
            from imupipe.readers.ros1.reader import bag_sources

            per_topic: collections.Counter[str] = collections.Counter()
            bags = bag_sources(path, salvage)
            for bag in bags:
                if warnings is not None and not salvage:  # the reader's warnings say it then
                    warnings += [w.removeprefix(f"{path}: ") for w in bag.warnings]
                per_topic.update(bag.topic_counts())
            return dict(per_topic) if all(bag.indexed for bag in bags) else None
    except ImupipeError:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure to open the index is a bad log
        what = "truncated or corrupt" if fmt == "mcap" else "unreadable"
        hint = "; --read-truncated reads a cut-off log up to the cut" if fmt == "mcap" else ""
        raise ReadError(
            f"{path}: {what} {fmt} log (its index cannot be read: "
            f"{' '.join(str(exc).split())}{hint})"
        ) from None
    return None


FORMAT_NAMES = {"ulog": "ULog", "mcap": "MCAP", "ros1": "ROS 1 bag", "ros2": "ROS 2 bag"}
"""How messages name a format."""


def source_counts(path: Path, fmt: str) -> dict[str, int] | None:
    """Messages per topic of a log whose other topics are not carried over (ULog: no ROS type),
    from its own sources (:func:`~imupipe.readers.dispatch.log_sources`); None for the formats
    that carry every topic over (MCAP, ROS bags: their counts are verified) and CSV."""
    from imupipe.readers import dispatch

    if fmt in dispatch.CARRY_OVER or fmt == "csv":
        return None
    counts: collections.Counter[str] = collections.Counter()
    for source in dispatch.log_sources(InputSpec(path=path)):
        counts.update(source.topic_counts() or {})
    return dict(counts)


def lost_topics(counts: Mapping[str, int] | None, written: Mapping[str, int]) -> dict[str, int]:
    """Every input topic (of ``counts``: topic -> messages) with no messages in the output."""
    return {
        t: n
        for t, n in sorted((counts or {}).items())
        if n and t not in written and not any(w.startswith(t + "/") for w in written)
    }


def not_carried(
    fmt: str, counts: Mapping[str, int] | None, written: Mapping[str, int]
) -> list[str]:
    """One warning counting the input topics with no messages in the output (a topic is written
    as itself or as ``topic/...``) and naming the largest few with their message counts (every
    one is in the manifest record: :func:`lost_topics`); none when all are written."""
    if not counts:
        return []
    lost = lost_topics(counts, written)
    if not lost:
        return []
    total, dropped = sum(counts.values()), sum(lost.values())
    largest = sorted(lost, key=lambda t: (-lost[t], t))  # the most messages first
    names = some_of([f"{t} ({lost[t]:,})" for t in largest])
    return [
        f"{len(lost)} of {len(counts)} {FORMAT_NAMES.get(fmt, fmt)} topics are {NOT_CARRIED} (they "
        f"have no ROS message type; {dropped:,} of {total:,} messages; imupipe inspect lists "
        f"them all): {names}"
    ]


def counts_by_topic(table: pa.Table) -> collections.Counter[str]:
    """Messages per topic that ``table`` will be written as."""
    topics = {**DEFAULT_TOPICS, **metadata(table).get("topics", {})}
    if "gyro" in written_streams(table):  # split topics: each row to the topic it came from
        per = {s: len(stream_rows(table, s)) for s in written_streams(table)}
        return collections.Counter({topics[s]: n for s, n in per.items() if n})
    return collections.Counter({topics[s]: n for s, n in counts(table).items() if n})


def verify_counts(where: Path, expected: Mapping[str, int], written: Mapping[str, int]) -> None:
    """Raise :class:`VerifyError` naming the first topic whose count differs."""
    for topic in sorted(set(expected) | set(written)):
        want, got = expected.get(topic, 0), written.get(topic, 0)
        if want != got:
            raise VerifyError(
                f"{where}: topic {topic}: the input has {want} messages but the output {got}"
            )
