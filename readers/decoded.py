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

from imupipe.readers.cdr import NotFastPath, PayloadError, decode, decode_with_rosbags
from imupipe.readers.errors import ReadError
from imupipe.readers.topics import COLUMNS, STREAM_TYPES


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
