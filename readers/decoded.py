"""From decoded sensor messages to the common table, shared by the MCAP and bag readers.

A reader decodes each chunk of a log into :class:`Piece` s (one per stream: header stamps, log
times, frame_ids and the message's float fields, see :data:`imupipe.readers.cdr.FIELDS`), and
this module chooses the topics (:func:`select_topics`) and joins pieces into one table
(:func:`assemble`): per stream, messages in log order, then sorted stably by the chosen time
(out-of-order and duplicate stamps are counted and warned about, none dropped), then the streams
merged in time order (at equal stamps: imu, mag, temperature).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from imupipe.readers.cdr import NotFastPath, PayloadError, decode, decode_with_rosbags
from imupipe.readers.errors import ReadError
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import COV, SCHEMA, with_metadata

STREAM_TYPES: dict[str, str] = {
    "imu": "sensor_msgs/msg/Imu",
    "mag": "sensor_msgs/msg/MagneticField",
    "temperature": "sensor_msgs/msg/Temperature",
}
TYPE_STREAMS = {v: k for k, v in STREAM_TYPES.items()}
TOPIC_KEYS = {"imu": "imu_topic", "mag": "mag_topic", "temperature": "temperature_topic"}

COLUMNS: dict[str, list[tuple[str, int, int]]] = {
    "imu": [
        ("orientation_x", 0, 1),
        ("orientation_y", 1, 1),
        ("orientation_z", 2, 1),
        ("orientation_w", 3, 1),
        ("orientation_cov", 4, 9),
        ("gyro_x", 13, 1),
        ("gyro_y", 14, 1),
        ("gyro_z", 15, 1),
        ("gyro_cov", 16, 9),
        ("accel_x", 25, 1),
        ("accel_y", 26, 1),
        ("accel_z", 27, 1),
        ("accel_cov", 28, 9),
    ],
    "mag": [("mag_x", 0, 1), ("mag_y", 1, 1), ("mag_z", 2, 1), ("mag_cov", 3, 9)],
    "temperature": [("temperature", 0, 1), ("temperature_var", 1, 1)],
}
"""Per stream: the table columns its message fills, as (column, first float field, count) over
the float fields of :data:`imupipe.readers.cdr.FIELDS`."""


def normalize_type(name: str) -> str:
    """``sensor_msgs/Imu`` (ROS 1, MCAP ros1msg) -> ``sensor_msgs/msg/Imu``."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name


@dataclass
class Piece:
    """Decoded messages of one stream: header ``stamp`` and ``log`` time (int64 ns), ``frame``
    (Arrow strings), ``columns`` (table column -> (n,) or (n, 9) float64, see
    :data:`COLUMNS`) and ``pub``, the publish time (int64 ns; None where the format has none:
    ROS bags)."""

    stamp: np.ndarray
    log: np.ndarray
    frame: pa.Array
    columns: dict[str, np.ndarray]
    pub: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.stamp.shape[0])


def decode_piece(
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    log: np.ndarray,
    stream: str,
    encoding: str,
    where: str,
    pub: np.ndarray | None = None,
) -> Piece:
    """Decode one chunk's messages of ``stream`` (payloads in ``buf``) into a :class:`Piece`;
    numpy path first, rosbags' deserializer for layouts it does not take. A bad payload is a
    ReadError prefixed with ``where`` (file and topic)."""
    msgtype = STREAM_TYPES[stream]
    slots = [(first, count) for _, first, count in COLUMNS[stream]]
    try:
        try:
            stamp, frame, cols = decode(buf, starts, lengths, msgtype, encoding, slots)
        except NotFastPath:
            payloads = [buf[s : s + n].tobytes() for s, n in zip(starts, lengths, strict=True)]
            stamp, frame, values = decode_with_rosbags(payloads, msgtype, encoding)
            cols = [
                values[:, f].copy() if c == 1 else np.ascontiguousarray(values[:, f : f + c])
                for f, c in slots
            ]
    except PayloadError as exc:
        raise ReadError(
            f"{where}: message at log time {int(log[exc.index])} is not a valid {msgtype}: "
            f"{exc.reason}"
        ) from None
    names = [name for name, _, _ in COLUMNS[stream]]
    return Piece(stamp, log, frame, dict(zip(names, cols, strict=True)), pub)


def select_topics(path: Path | str, spec: InputSpec, types: Mapping[str, str]) -> dict[str, str]:
    """Stream -> topic, from the spec's topic settings and the log's ``topic -> type``.

    A setting that names a missing topic or one of another type is an error; an omitted setting
    takes the only topic of the stream's type (several: an error listing them; none: the stream
    is absent). At least one stream must be found.
    """
    chosen: dict[str, str] = {}
    for stream, msgtype in STREAM_TYPES.items():
        key = TOPIC_KEYS[stream]
        wanted = getattr(spec, key)
        candidates = sorted(t for t, ty in types.items() if normalize_type(ty) == msgtype)
        if wanted is not None:
            if wanted not in types:
                have = ", ".join(f"{t} ({normalize_type(ty)})" for t, ty in sorted(types.items()))
                raise ReadError(f"{path}: {key} '{wanted}' is not in the log; topics: {have}")
            if normalize_type(types[wanted]) != msgtype:
                raise ReadError(
                    f"{path}: topic '{wanted}' ({key}) has type {normalize_type(types[wanted])}, "
                    f"expected {msgtype}"
                )
            chosen[stream] = wanted
        elif len(candidates) == 1:
            chosen[stream] = candidates[0]
        elif len(candidates) > 1:
            raise ReadError(
                f"{path}: several {msgtype} topics ({', '.join(candidates)}); "
                f"set {key} in [inputs.{spec.name}]"
            )
    if not chosen:
        have = ", ".join(f"{t} ({normalize_type(ty)})" for t, ty in sorted(types.items()))
        raise ReadError(
            f"{path}: no sensor_msgs/Imu, MagneticField or Temperature topic; topics: "
            f"{have or 'none'}"
        )
    return chosen


def _order_stream(
    piece: Piece, time: str, where: str, warnings: list[str]
) -> tuple[np.ndarray, Piece]:
    """Log order, then a stable sort by the chosen time; returns (t_ns, reordered piece)."""
    if len(piece) > 1 and np.any(piece.log[1:] < piece.log[:-1]):
        order = np.argsort(piece.log, kind="stable")
        piece = _take(piece, order)
    t = piece.stamp if time == "header" else piece.log
    if len(t) > 1:
        step = t[1:] - t[:-1]
        if np.any(step < 0):
            order = np.argsort(t, kind="stable")
            moved = int(np.count_nonzero(order != np.arange(len(t))))
            piece = _take(piece, order)
            t = t[order]
            warnings.append(
                f"{where}: {moved} messages out of {time} time order; sorted stably (none dropped)"
            )
            step = t[1:] - t[:-1]
        dups = int(np.count_nonzero(step == 0))
        if dups:
            warnings.append(f"{where}: {dups} messages repeat the previous {time} stamp (kept)")
    return t, piece


def _take(piece: Piece, order: np.ndarray) -> Piece:
    """``piece`` reordered; its columns are replaced one at a time (memory: one column extra)."""
    for name in list(piece.columns):
        piece.columns[name] = piece.columns.pop(name)[order]
    pub = None if piece.pub is None else piece.pub[order]
    return Piece(
        piece.stamp[order], piece.log[order], piece.frame.take(pa.array(order)), piece.columns, pub
    )


def concat(pieces: list[Piece], stream: str) -> Piece:
    """Join pieces of one stream in the order given, emptying ``pieces`` as it goes (so the
    memory peak is one column above the decoded size)."""
    if len(pieces) == 1:
        return pieces.pop()
    if not pieces:
        cols = {
            name: np.zeros(0) if count == 1 else np.zeros((0, count))
            for name, _, count in COLUMNS[stream]
        }
        return Piece(np.zeros(0, np.int64), np.zeros(0, np.int64), pa.array([], pa.string()), cols)
    columns = {}
    for name, _, _ in COLUMNS[stream]:
        columns[name] = np.concatenate([p.columns.pop(name) for p in pieces])
    pubs = None
    if any(p.pub is not None for p in pieces):  # the log time stands in where there is none
        pubs = np.concatenate([p.log if p.pub is None else p.pub for p in pieces])
    joined = Piece(
        np.concatenate([p.stamp for p in pieces]),
        np.concatenate([p.log for p in pieces]),
        pa.concat_arrays([p.frame for p in pieces]),
        columns,
        pubs,
    )
    pieces.clear()
    return joined


@contextlib.contextmanager
def small_pages() -> Iterator[None]:
    """numpy allocations without its transparent-huge-page hint.

    numpy asks the kernel for huge pages on large arrays; with the common THP setting
    (``defrag = madvise``) the first touch of such an array can stall on memory compaction: a
    fresh 1M-message read took 0.9 s instead of 0.4 s in a process that had already used a lot
    of memory. Columns that are filled once, sequentially, gain nothing from huge pages."""
    setter = getattr(getattr(np, "_core", None), "multiarray", None)
    setter = getattr(setter, "_set_madvise_hugepage", None)
    if setter is None:
        yield
        return
    previous = setter(False)
    try:
        yield
    finally:
        setter(previous)


class StreamBuffer:
    """Collects one stream's pieces. With ``capacity`` (the message count the log states) the
    columns are allocated once and each chunk's piece is copied in and dropped, so reading
    costs the table's size once; without it (or when the count was wrong) pieces are kept and
    joined at the end."""

    def __init__(self, stream: str, capacity: int | None) -> None:
        self.stream = stream
        self.filled = 0
        self.frames: list[pa.Array] = []
        self.spill: list[Piece] = []
        self.full: Piece | None = None
        if capacity:
            with small_pages():
                self.full = self._allocate(capacity)

    def _allocate(self, capacity: int) -> Piece:
        return Piece(
            np.empty(capacity, np.int64),
            np.empty(capacity, np.int64),
            pa.array([], pa.string()),
            {
                name: np.empty(capacity) if count == 1 else np.empty((capacity, count))
                for name, _, count in COLUMNS[self.stream]
            },
        )

    def add(self, piece: Piece) -> None:
        full, a, m = self.full, self.filled, len(piece)
        if full is None or self.spill or a + m > len(full.stamp):
            # own copies: the piece's columns may be views into its chunk's buffer
            columns = {name: np.array(col) for name, col in piece.columns.items()}
            self.spill.append(Piece(piece.stamp, piece.log, piece.frame, columns, piece.pub))
            return
        full.stamp[a : a + m] = piece.stamp
        full.log[a : a + m] = piece.log
        if piece.pub is not None and full.pub is None:
            full.pub = np.empty_like(full.log)
            full.pub[:a] = full.log[:a]
        if full.pub is not None:
            full.pub[a : a + m] = piece.log if piece.pub is None else piece.pub
        for name, col in piece.columns.items():
            full.columns[name][a : a + m] = col
        self.frames.append(piece.frame)
        self.filled += m

    def result(self) -> Piece:
        """The joined stream (the buffer is emptied)."""
        parts: list[Piece] = []
        if self.full is not None and self.filled:
            n = self.filled
            full = self.full
            frame = pa.concat_arrays(self.frames) if len(self.frames) > 1 else self.frames[0]
            parts.append(
                Piece(
                    full.stamp[:n],
                    full.log[:n],
                    frame,
                    {k: v[:n] for k, v in full.columns.items()},
                    None if full.pub is None else full.pub[:n],
                )
            )
        self.full, self.frames = None, []
        parts += self.spill
        self.spill = []
        return concat(parts, self.stream)


def _column(
    n: int, rows: np.ndarray | None, values: np.ndarray, absent: np.ndarray | None = None
) -> pa.Array:
    """A float64 (n,) or fixed-size-list (n, 9) column holding ``values`` at ``rows``, null elsewhere
    (and null where ``absent``, a mask over ``values``)."""
    if absent is not None:
        mask = np.ones(n, dtype=bool) if rows is not None else np.zeros(n, dtype=bool)
        if rows is not None:
            mask[rows] = False
        mask[absent if rows is None else rows[absent]] = True
        full = values if rows is None else np.zeros(n, dtype=np.float64)
        if rows is not None:
            full[rows] = values
        return pa.array(full, pa.float64(), mask=mask)
    if rows is None:
        if values.ndim == 1:
            return pa.array(values, pa.float64())
        flat = pa.array(np.ascontiguousarray(values).reshape(-1), pa.float64())
        return pa.FixedSizeListArray.from_arrays(flat, values.shape[1])
    mask = np.ones(n, dtype=bool)
    mask[rows] = False
    full = np.zeros((n,) + values.shape[1:], dtype=np.float64)
    full[rows] = values
    if values.ndim == 1:
        return pa.array(full, pa.float64(), mask=mask)
    flat = pa.array(full.reshape(-1), pa.float64())
    return pa.FixedSizeListArray.from_arrays(flat, values.shape[1], mask=pa.array(mask))


def absent_sensors(piece: Piece) -> dict[str, np.ndarray]:
    """Imu messages that mark gyro or accel as "no data" (sensor_msgs/Imu: element 0 of the
    covariance is -1) *and* carry NaN in that vector: what the corrected MCAP writes for a CSV
    without that sensor. The sensor is read back as absent (null) there, unless both are marked
    (the message then stays a sample, its NaN values kept)."""
    out: dict[str, np.ndarray] = {}
    for name in ("gyro", "accel"):
        cov = piece.columns.get(f"{name}_cov")  # a format without covariances marks nothing
        if cov is None or f"{name}_x" not in piece.columns:
            continue
        marked = np.isnan(piece.columns[f"{name}_x"])
        if marked.any():
            for axis in "yz":
                marked &= np.isnan(piece.columns[f"{name}_{axis}"])
            marked &= cov[:, 0] == -1.0
            if marked.any():
                out[name] = marked
    if len(out) == 2:
        both = out["gyro"] & out["accel"]
        out = {k: v & ~both for k, v in out.items() if np.any(v & ~both)}
    return out


def assemble(
    pieces: Mapping[str, Piece],
    *,
    time: str,
    source: str,
    fmt: str,
    topics: Mapping[str, str],
    where: str,
    warnings: list[str],
    sort: bool = True,
) -> pa.Table:
    """The common table of the decoded ``pieces`` (stream -> Piece).

    ``time`` is ``header`` or ``log``; ``where`` prefixes warnings (file); ``sort=False`` keeps
    each stream in log order without the stamp sort (the streaming path, which sorts per batch
    and reports nothing)."""
    ordered: dict[str, tuple[np.ndarray, Piece]] = {}
    for stream, piece in pieces.items():
        if sort:
            ordered[stream] = _order_stream(
                piece, time, f"{where} topic {topics[stream]}", warnings
            )
        else:
            ordered[stream] = (piece.stamp if time == "header" else piece.log, piece)
    streams = [s for s in STREAM_TYPES if s in ordered and len(ordered[s][1])]
    t_all = np.concatenate([ordered[s][0] for s in streams]) if streams else np.zeros(0, np.int64)
    n = len(t_all)
    merge = None
    if len(streams) > 1 or (not sort and n > 1 and np.any(t_all[1:] < t_all[:-1])):
        merge = np.argsort(t_all, kind="stable")
        t_all = t_all[merge]
    rank = None if merge is None else np.argsort(merge)  # position of each input row
    rows: dict[str, np.ndarray | None] = {}
    start = 0
    for s in streams:
        m = len(ordered[s][1])
        rows[s] = None if rank is None else rank[start : start + m]
        start += m

    columns: dict[str, pa.Array] = {"t_ns": pa.array(t_all, pa.int64())}
    extra: dict[str, pa.Array] = {}
    nulls = pa.nulls(n, pa.float64())

    for name in ("gyro", "accel", "mag"):
        for axis in "xyz":
            columns[f"{name}_{axis}"] = nulls
    columns["temperature"] = nulls
    for s in (s for s in STREAM_TYPES if s in ordered):  # every chosen stream: one schema per input
        piece = ordered[s][1]
        where_rows = rows.get(s, np.zeros(0, np.int64))
        absent = absent_sensors(piece) if s == "imu" else {}
        for name in (c for c, _, _ in COLUMNS[s] if c in piece.columns):  # ULog: no covariances
            target = columns if name in columns else extra
            marked = absent.get(name.split("_")[0]) if name in columns else None
            target[name] = _column(n, where_rows, piece.columns.pop(name), marked)

    def merged(times: list[np.ndarray]) -> pa.Array:
        joined = np.concatenate(times) if times else np.zeros(0, np.int64)
        return pa.array(joined if merge is None else joined[merge], pa.int64())

    frames = [ordered[s][1].frame for s in streams]
    frame_all = pa.concat_arrays(frames) if frames else pa.array([], pa.string())
    if merge is not None:
        frame_all = frame_all.take(pa.array(merge))
    fields = list(SCHEMA) + [pa.field("log_time_ns", pa.int64())]
    arrays = [columns[f.name] for f in SCHEMA] + [merged([ordered[s][1].log for s in streams])]
    # what the writer needs to give every message back its own times (see readers.table)
    if time == "log":
        fields.append(pa.field("header_stamp_ns", pa.int64()))
        arrays.append(merged([ordered[s][1].stamp for s in streams]))
    if any(p.pub is not None for _, p in ordered.values()):
        fields.append(pa.field("publish_time_ns", pa.int64()))
        pieces_ = [ordered[s][1] for s in streams]
        arrays.append(merged([p.log if p.pub is None else p.pub for p in pieces_]))
    fields.append(pa.field("frame_id", pa.string()))
    arrays.append(frame_all)
    for name, array in extra.items():
        fields.append(
            pa.field(name, COV if isinstance(array.type, pa.FixedSizeListType) else pa.float64())
        )
        arrays.append(array)
    table = pa.Table.from_arrays(arrays, schema=pa.schema(fields))
    meta = {
        "source": source,
        "format": fmt,
        "topics": {s: topics[s] for s in STREAM_TYPES if s in ordered},
        "types": {s: STREAM_TYPES[s] for s in STREAM_TYPES if s in ordered},
        "frame_id": {
            s: ordered[s][1].frame[0].as_py() for s in streams if len(ordered[s][1].frame)
        },
    }
    return with_metadata(table, meta)
