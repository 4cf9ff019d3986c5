"""ROS 2 bags into the common table: a bag folder (sqlite3 or mcap storage) or a bare ``.db3``.

- mcap storage: each ``.mcap`` file is read by :class:`imupipe.readers.mcap.reader.McapSource`.
- sqlite3 storage: ``SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id``,
  fetched in blocks; each block's payloads are joined into one buffer and the sensor messages
  decoded with numpy (:func:`imupipe.readers.cdr.decode`), like an MCAP chunk. The log time is
  the ``timestamp`` column. Other topics are carried over unchanged (CDR) with the schema text
  from the bag's ``message_definitions`` table, else rosbags' ROS 2 Humble definition.

A bag folder is read as its ``metadata.yaml`` describes it (:func:`read_metadata`: every
metadata version rosbag2 writes, 1 to 9, and later ones by the same fields, as rosbag2 itself
reads them): its storage files (``relative_file_paths``, split bags joined in the order of their
first message), sqlite3 or mcap storage, and rosbag2's compression (zstd, the only format
rosbag2 offers): ``compression_mode: file`` (each storage file one zstd stream, ``*.db3.zstd``,
``*.mcap.zstd``) is decompressed, streaming, to a temporary file that lives as long as the
source; ``compression_mode: message`` (each payload one zstd frame) is decompressed chunk by
chunk (:func:`imupipe.readers.compression.inflate_messages`). A folder without
``metadata.yaml`` is read from its ``*.db3`` / ``*.mcap`` files, uncompressed.
"""

from __future__ import annotations

import contextlib
import sqlite3
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.readers.compression import inflate_file, inflate_messages
from imupipe.readers.decoded import Piece, decode_piece
from imupipe.readers.errors import ReadError
from imupipe.readers.mapped import Batch, Definition
from imupipe.readers.mcap.fast import ChunkMessages
from imupipe.readers.mcap.reader import McapSource
from imupipe.readers.sources import LogSource, carry_sources, iter_sources, read_sources
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.readers.topics import normalize_type

BLOCK_ROWS = 50_000
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
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

    def __init__(
        self, path: str | Path, *, shown: Path | None = None, zstd_messages: bool = False
    ) -> None:
        """``path``: the sqlite3 file; ``shown``: the file named in errors (the bag's own
        ``.db3.zstd`` when ``path`` is its decompressed copy); ``zstd_messages``: each payload
        is one zstd frame (``compression_mode: message``)."""
        self.path = Path(shown or path)
        self.zstd_messages = zstd_messages
        try:
            with open(path, "rb") as fh:
                if not fh.read(16).startswith(b"SQLite format 3"):
                    raise ReadError(f"{self.path}: not a ROS 2 sqlite3 bag (not an SQLite file)")
        except OSError as exc:
            raise ReadError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        with _guard(self.path):
            self._db = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)
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

    def sniff_zstd(self) -> bool:
        """Whether the first message's payload is a zstd frame (magic ``28 b5 2f fd``), for a
        file without ``metadata.yaml`` to say so; a CDR payload starts with a zero byte."""
        with _guard(self.path):
            row = self._db.execute("SELECT data FROM messages LIMIT 1").fetchone()
        return row is not None and bytes(row[0][:4]) == ZSTD_MAGIC

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
        self, streams: dict[str, str], carry: bool, decode: bool = True, whole: bool = False
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
                data = bytes(datas[i])
                if self.zstd_messages:
                    where = f"{self.path}: topic '{name}' at log time {lt}"
                    data = inflate_messages(data, [0], [len(data)], where)[0].tobytes()
                raw.append(RawMessage(name, typ, "ros2msg", schema, fmt, data, lt, lt))
        return pieces, raw, int(log[-1])

    def definitions(self) -> dict[str, Definition]:
        """Topic -> its type, with the bag's ``message_definitions`` text (rosbag2 Iron and
        later write it; else rosbags' Humble definitions know the standard types)."""
        return {
            name: Definition(
                typ, fmt, "ros2msg" if typ in self.defs else "", self.defs.get(typ, b"")
            )
            for name, typ, fmt in self.topics.values()
        }

    def payloads(self, topics: set[str]) -> Iterator[list[tuple[str, Batch]]]:
        """Per block of rows: the messages of ``topics`` (see :mod:`imupipe.readers.mapped`)."""
        chosen = {tid: t[0] for tid, t in self.topics.items() if t[0] in topics}
        if not chosen:
            return
        marks = ",".join("?" * len(chosen))
        with _guard(self.path):
            cursor = self._db.execute(
                f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({marks}) "
                "ORDER BY timestamp, id",
                list(chosen),
            )
        while True:
            with _guard(self.path):
                rows = cursor.fetchmany(BLOCK_ROWS)
            if not rows:
                return
            tids, stamps, datas = zip(*rows, strict=True)
            tid = np.asarray(tids, np.int64)
            log = np.asarray(stamps, np.int64)
            out = []
            for t, name in chosen.items():
                sel = np.flatnonzero(tid == t)
                if len(sel):
                    picked = [datas[i] for i in sel.tolist()]
                    buf, starts, lengths = self._joined(picked, f"{self.path}: topic '{name}'")
                    out.append((name, Batch(buf, starts, lengths, log[sel])))
            yield out

    def _joined(self, datas: list[bytes], where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Payloads joined into one buffer: (buf, starts, lengths), decompressed when each is
        a zstd frame."""
        lengths = np.fromiter(map(len, datas), np.int64, len(datas))
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        buf = np.frombuffer(b"".join(datas), np.uint8)
        if self.zstd_messages:
            buf, starts, lengths = inflate_messages(buf, starts, lengths, where)
        return buf, starts, lengths

    def _decode(self, datas: list[bytes], log: np.ndarray, tid: int, stream: str) -> Piece:
        where = f"{self.path}: topic '{self.topics[tid][0]}'"
        buf, starts, lengths = self._joined(datas, where)
        return decode_piece(buf, starts, lengths, log, stream, "cdr", where)


class _Inflated:
    """A chunk of an MCAP storage file whose payloads are zstd frames, seen with its payloads
    decompressed (``records`` and ``buf`` as :class:`~imupipe.readers.mcap.fast.ChunkMessages`
    has them), one channel at a time."""

    def __init__(self, chunk: ChunkMessages, where: str) -> None:
        self.chunk, self.where, self.offsets = chunk, where, chunk.offsets
        self.buf = chunk.buf
        self._cid: int | None = None
        self._records: tuple[np.ndarray, ...] = ()

    def records(
        self, channel_id: int, copy: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if channel_id != self._cid:
            log, pub, starts, lengths = self.chunk.records(channel_id)
            self.buf, starts, lengths = inflate_messages(
                self.chunk.buf, starts, lengths, self.where
            )
            self._cid, self._records = channel_id, (log, pub, starts, lengths)
        return self._records  # type: ignore[return-value]


class Bag2Mcap(McapSource):
    """One MCAP storage file of a ROS 2 bag: an :class:`McapSource` whose errors name the bag's
    own file (``shown``: its ``.mcap.zstd`` when this is the decompressed copy) and whose
    payloads may each be one zstd frame (``compression_mode: message``)."""

    format = "ros2"

    def __init__(
        self,
        path: Path,
        *,
        shown: Path | None = None,
        zstd_messages: bool = False,
        salvage: bool = False,
    ):
        self._real, self._shown = Path(path), Path(shown or path)
        with self._named():
            super().__init__(path, salvage)
        self.path = self._shown
        self.zstd_messages = zstd_messages

    @contextlib.contextmanager
    def _named(self) -> Iterator[None]:
        """Errors of the decompressed copy name the bag's own file."""
        try:
            yield
        except ReadError as exc:
            if self._shown == self._real:
                raise
            raise ReadError(str(exc).replace(str(self._real), str(self._shown))) from None

    def first_time(self) -> int:
        with self._named():
            return super().first_time()

    def topic_times(self) -> dict[str, np.ndarray]:
        with self._named():
            return super().topic_times()

    def chunks(  # type: ignore[override]
        self, *args: Any, **kwargs: Any
    ) -> Iterator[tuple[dict[str, Piece], list[RawMessage], int]]:
        """:meth:`McapSource.chunks`, its errors naming the bag's own file."""
        with self._named():
            yield from super().chunks(*args, **kwargs)

    def _groups(self) -> bool:
        return not self.zstd_messages  # each payload is inflated on its own

    def _view(self, chunk: ChunkMessages, cid: int) -> ChunkMessages:
        if self.zstd_messages:
            chunk = _Inflated(chunk, f"{self.path}: topic '{self.file.channels[cid].topic}'")  # type: ignore[assignment]
        return chunk

    def payloads(self, topics: set[str]) -> Iterator[list[tuple[str, Batch]]]:
        with self._named():
            yield from super().payloads(topics)

    def _decode(self, chunk: ChunkMessages, cid: int, stream: str) -> Piece:
        if self.zstd_messages:
            where = f"{self.path}: topic '{self.file.channels[cid].topic}'"
            chunk = _Inflated(chunk, where)  # type: ignore[assignment]
        return super()._decode(chunk, cid, stream)

    def _raw(self, chunk: ChunkMessages, cid: int, converters: dict[int, object]) -> list:
        if self.zstd_messages:
            channel = self.file.channels.get(cid)
            where = f"{self.path}: topic '{channel.topic if channel else cid}'"
            chunk = _Inflated(chunk, where)  # type: ignore[assignment]
        return super()._raw(chunk, cid, converters)


STORAGES = ("sqlite3", "mcap")
"""The storage plugins whose files are read (rosbag2's two)."""
COMPRESSION_MODES = ("", "none", "file", "message")
"""rosbag2's compression modes (``storage``, MCAP's own chunk compression, is written as none)."""


@dataclass
class Bag2Metadata:
    """What a rosbag2 ``metadata.yaml`` says about reading the bag (:func:`read_metadata`)."""

    folder: Path
    version: int
    storage: str
    """``sqlite3`` or ``mcap``."""
    files: list[Path]
    """The storage files, in the order listed (split bags)."""
    compression: str
    """``""``, ``file`` or ``message`` (always zstd)."""
    counts: dict[str, int] = field(default_factory=dict)
    """Topic -> message count (``topics_with_message_count``)."""


def read_metadata(folder: Path) -> Bag2Metadata:
    """The bag folder's ``metadata.yaml``: the one rule by which ``inspect``, ``run`` and
    ``convert`` accept a ROS 2 bag.

    Every version rosbag2 writes (1 to 9; rosbag2 reads a version by the fields it has, with no
    upper limit, and so does this): ``relative_file_paths`` (only the file name is used: before
    version 4 the paths included the bag folder), ``storage_identifier`` (sqlite3 or mcap),
    ``compression_mode`` / ``compression_format`` (from version 3; zstd) and
    ``topics_with_message_count``. A ReadError names what is missing or not supported."""
    import yaml

    where = folder / "metadata.yaml"
    try:
        doc = yaml.safe_load(where.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ReadError(f"{where}: cannot read: {exc.strerror or exc}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        what = " ".join(str(exc).split())
        raise ReadError(f"{where}: not a rosbag2 metadata file ({what})") from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise ReadError(f"{where}: not a rosbag2 metadata file (no rosbag2_bagfile_information)")
    try:
        version = int(info["version"])
        storage = str(info["storage_identifier"])
        names = [str(PurePath(str(p)).name) for p in info["relative_file_paths"]]
        topics = info.get("topics_with_message_count") or []
        counts: dict[str, int] = {}
        for entry in topics:
            name = str(entry["topic_metadata"]["name"])
            counts[name] = counts.get(name, 0) + int(entry.get("message_count", 0))
    except KeyError as exc:
        raise ReadError(f"{where}: the rosbag2 metadata lacks {exc}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise ReadError(f"{where}: invalid rosbag2 metadata ({exc})") from None
    if version < 1:
        raise ReadError(f"{where}: invalid rosbag2 metadata version {version}")
    if storage not in STORAGES:
        raise ReadError(f"{where}: storage '{storage}' is not supported (sqlite3 or mcap)")
    mode = str(info.get("compression_mode") or "").lower() if version >= 3 else ""
    fmt = str(info.get("compression_format") or "").lower() if version >= 3 else ""
    if mode not in COMPRESSION_MODES:
        raise ReadError(f"{where}: unknown compression mode '{mode}' (file or message)")
    mode = "" if mode == "none" else mode
    if mode and fmt != "zstd":
        raise ReadError(
            f"{where}: compression format '{fmt}' is not supported (rosbag2 compresses with zstd)"
        )
    files = [folder / n for n in names]
    if not files:
        raise ReadError(f"{where}: the bag lists no storage file")
    for f in files:
        if not f.is_file():
            raise ReadError(f"{folder}: the bag's storage file {f.name} is missing")
    return Bag2Metadata(folder, version, storage, files, mode, counts)


def bag2_counts(path: Path) -> dict[str, int] | None:
    """Messages per topic as the bag's ``metadata.yaml`` states them (None without one): the
    reference ``convert`` checks its output against."""
    path = Path(path)
    if not (path.is_dir() and (path / "metadata.yaml").exists()):
        return None
    return read_metadata(path).counts


def _storage_source(
    path: Path,
    storage: str,
    shown: Path | None,
    zstd_messages: bool | None,
    salvage: bool = False,
) -> LogSource:
    """The source of one storage file; ``zstd_messages`` None: not known (no
    ``metadata.yaml``), told by the payloads for sqlite3 (:meth:`Sqlite3Bag.sniff_zstd`);
    ``salvage``: an mcap storage file cut off is read up to the cut
    (:class:`~imupipe.readers.mcap.fast.McapFile`)."""
    if storage == "mcap":
        return Bag2Mcap(path, shown=shown, zstd_messages=bool(zstd_messages), salvage=salvage)
    bag = Sqlite3Bag(path, shown=shown, zstd_messages=bool(zstd_messages))
    if zstd_messages is None:
        bag.zstd_messages = bag.sniff_zstd()
    return bag


def _inflated_source(path: Path, storage: str, zstd_messages: bool | None) -> LogSource:
    """A file-compressed storage file (``x.db3.zstd``) decompressed to a temporary folder that
    is removed when the source is (or at exit)."""
    tmp = tempfile.TemporaryDirectory(prefix="imupipe-bag-")
    plain = Path(tmp.name) / (path.name[: -len(".zstd")] if path.suffix == ".zstd" else path.name)
    try:
        inflate_file(path, plain)
    except OSError as exc:
        tmp.cleanup()
        raise ReadError(f"{path}: cannot decompress to {tmp.name}: {exc.strerror or exc}") from None
    except ReadError:
        tmp.cleanup()
        raise
    src = _storage_source(plain, storage, path, zstd_messages)
    src._tmp = tmp  # type: ignore[attr-defined] - the folder lives as long as the source
    return src


PATTERNS = ("*.db3", "*.mcap", "*.db3.zstd", "*.mcap.zstd")
"""The storage files of a bag folder without ``metadata.yaml``."""


def bag2_sources(path: Path, salvage: bool = False) -> list[LogSource]:
    """The storage files of a ROS 2 bag folder (as its ``metadata.yaml`` lists them, else
    :data:`PATTERNS`), or a bare ``.db3`` / ``.mcap`` / ``.db3.zstd`` / ``.mcap.zstd``. Without
    ``metadata.yaml`` a ``.zstd`` file is decompressed whole (rosbag2's file compression) and a
    sqlite3 file's payloads are taken as zstd frames when they start with zstd's magic number
    (rosbag2's message compression; a CDR payload starts with a zero byte). ``salvage``: its
    mcap storage files cut off are read up to the cut (``--read-truncated``)."""
    path = Path(path)
    if path.is_dir() and (path / "metadata.yaml").exists():
        meta = read_metadata(path)
        if meta.compression == "file":
            return [_inflated_source(f, meta.storage, False) for f in meta.files]
        zstd = meta.compression == "message"
        return [_storage_source(f, meta.storage, None, zstd, salvage) for f in meta.files]
    if path.is_dir():
        files = [f for pattern in PATTERNS for f in sorted(path.glob(pattern))]
        if not files:
            raise ReadError(f"{path}: the ROS 2 bag folder holds no .db3 or .mcap file")
    else:
        files = [path]
    sources = []
    for f in files:
        storage = "mcap" if f.name.endswith((".mcap", ".mcap.zstd")) else "sqlite3"
        if f.suffix == ".zstd":
            sources.append(_inflated_source(f, storage, None))
        else:
            sources.append(_storage_source(f, storage, None, None, salvage))
    return sources


def read_ros2(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a ROS 2 bag (folder or bare .db3) into the common table."""
    return read_sources(spec, bag2_sources(spec.path, spec.read_truncated))


def iter_ros2(
    spec: InputSpec, batch_rows: int, carry: bool = True, warnings: list[str] | None = None
) -> Iterator[tuple[pa.Table, list[RawMessage]]]:
    """Bounded-memory batches (see :func:`imupipe.readers.sources.iter_sources`)."""
    return iter_sources(
        spec, bag2_sources(spec.path, spec.read_truncated), batch_rows, carry, warnings
    )


def carry_over_ros2(spec: InputSpec) -> list[RawMessage]:
    """Messages of the other topics, unchanged, in log-time order."""
    return carry_sources(spec, bag2_sources(spec.path, spec.read_truncated))
