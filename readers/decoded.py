"""From decoded sensor messages to the common table, shared by the MCAP and bag readers.

A reader decodes each chunk of a log into :class:`Piece` s (one per stream: header stamps, log
times, frame_ids and the message's float fields, see :data:`imupipe.readers.cdr.FIELDS`); this
module decodes them (:func:`decode_piece`; the topics are chosen by
:func:`imupipe.readers.topics.select_topics`).
:mod:`imupipe.readers.table_buffer` joins the pieces into one table in the order the readers
promise: per stream, messages in log order, then sorted stably by the chosen time (out-of-order
and duplicate stamps are counted and warned about, none dropped), then the streams merged in
time order (at equal stamps: imu, mag, temperature).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import string_array
from imupipe.readers.cdr import (
    NotFastPath,
    PayloadError,
    decode,
    decode_with_rosbags,
    even_step,
    field_count,
)
from imupipe.readers.errors import ReadError
from imupipe.readers.topics import COLUMNS, OTHER_VECTOR, PIECE_TYPES


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
    one_frame: str | None = None
    """The frame_id of every message, when the decoder found them all the same (None:
    unknown)."""
    other_nonzero: int = 0
    """A split stream (``gyro``, ``accel``): messages whose other vector, which is not read, is
    not all zeros (see :data:`imupipe.readers.topics.OTHER_VECTOR`)."""

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
    msgtype = PIECE_TYPES[stream]
    slots = [(first, count) for _, first, count in COLUMNS[stream]]
    names = [name for name, _, _ in COLUMNS[stream]]
    other = OTHER_VECTOR.get(stream)
    if other is not None:
        slots.append(other)  # decoded to be checked, then dropped
    piece = None
    if encoding == "cdr":
        uniform = _uniform_cdr(buf, starts, lengths, msgtype, slots)
        if uniform is not None:
            stamp, frame, cols, one = uniform
            piece = Piece(stamp, log, frame, {}, pub, one)
    if piece is None:
        stamp, frame, cols = _decode_general(
            buf, starts, lengths, log, msgtype, encoding, where, slots
        )
        piece = Piece(stamp, log, frame, {}, pub)
    if other is not None:
        vector = cols.pop()
        piece.other_nonzero = int(np.count_nonzero((vector != 0).any(axis=1)))
    piece.columns = dict(zip(names, cols, strict=True))
    return piece


def _decode_general(
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    log: np.ndarray,
    msgtype: str,
    encoding: str,
    where: str,
    slots: list[tuple[int, int]],
) -> tuple[np.ndarray, pa.Array, list[np.ndarray]]:
    """:func:`imupipe.readers.cdr.decode`, or rosbags' deserializer for the layouts it does not
    take; a bad payload is a ReadError naming ``where`` and the message's log time."""
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
    return stamp, frame, cols


def _uniform_cdr(
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    msgtype: str,
    slots: list[tuple[int, int]],
) -> tuple[np.ndarray, pa.Array, list[np.ndarray], str] | None:
    """What :func:`imupipe.readers.cdr.decode` gives (and the one frame_id), in a few numpy
    calls for the common case: little-endian CDR payloads of one length, evenly spaced (one
    channel's records one after the other), all with the same encapsulation header, string
    length and frame_id, so that every field lies at one offset. None for anything else (the
    general decoder then decodes it, or names what is wrong with it)."""
    n = len(starts)
    step = even_step(starts)
    if step is None or not n:
        return None
    size = int(lengths[0])
    if size < 16 or not bool((lengths == size).all()):
        return None
    s0 = int(starts[0])
    head = buf[s0 : s0 + 16].view("<u4")
    encap, strlen = int(head[0]), int(head[3])
    k = field_count(msgtype)
    body = 12 + strlen
    first = 4 + body + (-body) % 8
    if encap != 0x100 or strlen < 1 or first + 8 * k > size:
        return None  # 0x100: bytes 00 01 00 00, little-endian CDR
    if not (_same(buf, s0, step, n, 0, 4) and _same(buf, s0, step, n, 12, 4 + strlen - 1)):
        return None  # the encapsulation header, the string length and the frame_id
    try:
        one = buf[s0 + 16 : s0 + 16 + strlen - 1].tobytes().decode()
    except UnicodeDecodeError:
        return None
    frame = repeat_string(one, n)
    stamp = np.ndarray((n,), "<i4", buffer=buf, offset=s0 + 4, strides=(step,)).astype(np.int64)
    stamp *= 1_000_000_000
    stamp += np.ndarray((n,), "<u4", buffer=buf, offset=s0 + 8, strides=(step,))
    rows = np.ndarray((n, k), "<f8", buffer=buf, offset=s0 + first, strides=(step, 8))
    return stamp, frame, [rows[:, f] if c == 1 else rows[:, f : f + c] for f, c in slots], one


def repeat_string(value: str, n: int) -> pa.Array:
    """An Arrow string array of ``n`` times ``value``."""
    raw = value.encode()
    width = len(raw)
    if (n + 1) * width >= 2**31:
        return pa.concat_arrays([repeat_string(value, n // 2), repeat_string(value, n - n // 2)])
    offsets = (
        np.arange(0, (n + 1) * width, width, dtype=np.int32) if width else np.zeros(n + 1, np.int32)
    )
    return pa.StringArray.from_buffers(n, pa.py_buffer(offsets), pa.py_buffer(raw * n))


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
        return Piece(np.zeros(0, np.int64), np.zeros(0, np.int64), string_array([]), cols)
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
        other_nonzero=sum(p.other_nonzero for p in pieces),
    )
    pieces.clear()
    return joined


def _same(buf: np.ndarray, s0: int, step: int, n: int, lo: int, width: int) -> bool:
    """Bytes ``lo : lo + width`` of the ``n`` records ``step`` apart from ``s0`` are the same in
    every record (compared 8, 4, 2 or 1 bytes at a time)."""
    pos, end = lo, lo + width
    while pos < end:
        size = 8 if end - pos >= 8 else 4 if end - pos >= 4 else 2 if end - pos >= 2 else 1
        if end - pos < 8 and width >= 8:
            pos, size = end - 8, 8  # the last, overlapping word
        dtype = {8: "<u8", 4: "<u4", 2: "<u2", 1: "u1"}[size]
        values = np.ndarray((n,), dtype, buffer=buf, offset=s0 + pos, strides=(step,))
        if not bool((values == values[0]).all()):
            return False
        pos += size
    return True


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
