"""ROS 2 bags into the common table: a bag folder (sqlite3 or mcap storage) or a bare ``.db3``.

- mcap storage: each ``.mcap`` file is read by :class:`imupipe.readers.mcap_reader.McapSource`.
- sqlite3 storage: ``SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id``,
  fetched in blocks; each block's payloads are joined into one buffer and the sensor messages
  decoded with numpy (:func:`imupipe.readers.cdr.decode`), like an MCAP chunk. The log time is
  the ``timestamp`` column. Other topics are carried over unchanged (CDR) with the schema text
  from the bag's ``message_definitions`` table, else rosbags' ROS 2 Humble definition.

A folder's storage files (``*.db3``, ``*.mcap``) are joined in the order of their first message.
"""

from __future__ import annotations

import contextlib
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa

from imupipe.readers.decoded import Piece, decode_piece
from imupipe.readers.errors import ReadError
from imupipe.readers.mcap_reader import McapSource
from imupipe.readers.sources import LogSource, carry_sources, iter_sources, read_sources
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.readers.topics import normalize_type

BLOCK_ROWS = 50_000
CORRUPT = (sqlite3.DatabaseError, TypeError, ValueError, AttributeError, OverflowError)
"""What a damaged sqlite3 file raises (bad pages, or cells of the wrong type)."""


@contextlib.contextmanager
def _guard(path: Path) -> Iterator[None]:
    """Turn a damaged database's errors into one ReadError line."""
    try:
        yield
    except CORRUPT as exc:
        raise ReadError(
            f"{path}: corrupt ROS 2 sqlite3 bag ({type(exc).__name__}: {exc})"
        ) from None


def _schema_text(msgtype: str) -> bytes:
    from rosbags.typesys import Stores, get_typestore

    try:
        return get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)[0].encode()
    except Exception:  # noqa: BLE001 - a type rosbags does not know: no schema text
        return b""


class Sqlite3Bag:
    """One rosbag2 sqlite3 storage file as a :class:`~imupipe.readers.sources.LogSource`."""

    format = "ros2"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "rb") as fh:
                if not fh.read(16).startswith(b"SQLite format 3"):
                    raise ReadError(f"{self.path}: not a ROS 2 sqlite3 bag (not an SQLite file)")
        except OSError as exc:
            raise ReadError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        with _guard(self.path):
            self._db = sqlite3.connect(f"file:{self.path}?mode=ro&immutable=1", uri=True)
            rows = self._db.execute("SELECT id, name, type, serialization_format FROM topics")
            self.topics = {
                int(tid): (str(name), normalize_type(str(typ)), str(fmt))
                for tid, name, typ, fmt in rows
            }
            self.defs: dict[str, bytes] = {}
            tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master")}
            if "message_definitions" in tables:
                for typ, enc, text in self._db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"
                ):
                    if enc == "ros2msg" and text:
                        self.defs[str(typ)] = str(text).encode()

    def topic_types(self) -> dict[str, str]:
        return {name: typ for name, typ, _ in self.topics.values()}

    def topic_counts(self) -> dict[str, int]:
        with _guard(self.path):
            rows = self._db.execute("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id")
            return {self.topics[t][0]: int(n) for t, n in rows if t in self.topics}

    def first_time(self) -> int:
        with _guard(self.path):
            row = self._db.execute("SELECT MIN(timestamp) FROM messages").fetchone()
            return int(row[0] or 0)

    def topic_times(self) -> dict[str, np.ndarray]:
        with _guard(self.path):
            rows = self._db.execute("SELECT topic_id, timestamp FROM messages").fetchall()
            if not rows:
                return {}
            tid, stamp = (np.asarray(c, np.int64) for c in zip(*rows, strict=True))
        return {
            name: np.sort(stamp[tid == t])
            for t, (name, _, _) in self.topics.items()
            if np.any(tid == t)
        }

    def chunks(
        self, streams: dict[str, str], carry: bool, decode: bool = True
    ) -> Iterator[tuple[dict[str, Piece], list[RawMessage], int]]:
        by_topic = {topic: stream for stream, topic in streams.items()}
        chosen = {tid: by_topic[t[0]] for tid, t in self.topics.items() if t[0] in by_topic}
        for tid, (name, _, fmt) in self.topics.items():
            if tid in chosen and fmt != "cdr":
                raise ReadError(f"{self.path}: topic '{name}': serialization '{fmt}' is not cdr")
        with _guard(self.path):
            cursor = self._db.execute(
                "SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id"
            )
        while True:
            with _guard(self.path):
                rows = cursor.fetchmany(BLOCK_ROWS)
                if not rows:
                    return
                block = self._block(rows, chosen, carry, decode)
            yield block

    def _block(
        self, rows: list, chosen: dict[int, str], carry: bool, decode_: bool
    ) -> tuple[dict[str, Piece], list[RawMessage], int]:
        """Decode a block of rows (ordered by timestamp: later blocks start at its last one)."""
        tids, stamps, datas = zip(*rows, strict=True)
        tid = np.asarray(tids, np.int64)
        log = np.asarray(stamps, np.int64)
        pieces: dict[str, Piece] = {}
        if decode_:
            for t, stream in chosen.items():
                sel = np.flatnonzero(tid == t)
                if len(sel):
                    pieces[stream] = self._decode(
                        [datas[i] for i in sel.tolist()], log[sel], t, stream
                    )
        raw: list[RawMessage] = []
        if carry:
            for i in np.flatnonzero(~np.isin(tid, list(chosen))).tolist():
                t = int(tid[i])
                if t not in self.topics:
                    raise ReadError(
                        f"{self.path}: message of topic id {t}, which the bag never defines"
                    )
                name, typ, fmt = self.topics[t]
                schema = self.defs.get(typ)
                if schema is None:
                    schema = self.defs[typ] = _schema_text(typ)
                lt = int(log[i])
                raw.append(RawMessage(name, typ, "ros2msg", schema, fmt, bytes(datas[i]), lt, lt))
        return pieces, raw, int(log[-1])

    def _decode(self, datas: list[bytes], log: np.ndarray, tid: int, stream: str) -> Piece:
        lengths = np.fromiter(map(len, datas), np.int64, len(datas))
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        buf = np.frombuffer(b"".join(datas), np.uint8)
        where = f"{self.path}: topic '{self.topics[tid][0]}'"
        return decode_piece(buf, starts, lengths, log, stream, "cdr", where)


def bag2_sources(path: Path) -> list[LogSource]:
    """The storage files of a ROS 2 bag folder, or a bare ``.db3`` / ``.mcap``."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.db3")) + sorted(path.glob("*.mcap"))
        if not files:
            raise ReadError(f"{path}: the ROS 2 bag folder holds no .db3 or .mcap file")
    else:
        files = [path]
    sources: list[LogSource] = []
    for f in files:
        if f.suffix == ".mcap":
            src = McapSource(f)
            src.format = "ros2"
            sources.append(src)
        else:
            sources.append(Sqlite3Bag(f))
    return sources


def read_ros2(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a ROS 2 bag (folder or bare .db3) into the common table."""
    return read_sources(spec, bag2_sources(spec.path))


def iter_ros2(spec: InputSpec, batch_rows: int) -> Iterator[tuple[pa.Table, list[RawMessage]]]:
    """Bounded-memory batches (see :func:`imupipe.readers.sources.iter_sources`)."""
    return iter_sources(spec, bag2_sources(spec.path), batch_rows)


def carry_over_ros2(spec: InputSpec) -> list[RawMessage]:
    """Messages of the other topics, unchanged, in log-time order."""
    return carry_sources(spec, bag2_sources(spec.path))
