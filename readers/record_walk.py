"""The sequential record walks of the flight-log readers: compiled when built, else Python
(or numpy).

A PX4 ULog's records follow each other without an index (a 3-byte header: uint16 payload size,
little-endian, and uint8 type; then the payload), so where a record starts is known only after
the one before it is read: numpy cannot walk them without a Python step per record. The
compiled helper ``imupipe.readers._records`` (``readers/_records.c``, built by ``setup.py`` as
an optional extension: an install without a C compiler goes on without it) does the walk and the
copy of fixed-size payloads, and the walk of an ArduPilot DataFlash log's records; the ULog
functions here are the same in Python and numpy (no compiled code of imupipe's), and the
DataFlash reader finds the same records with numpy (pointer doubling); they are used when the
helper is not built or ``IMUPIPE_PURE_PYTHON=1`` is set (``tests/test_ulog_records.py`` and
``tests/test_dataflash_reader.py`` check that both ways give the same offsets and bytes).
"""

from __future__ import annotations

import mmap
import os
import struct
from typing import Any, NamedTuple

import numpy as np

Buffer = bytes | bytearray | memoryview | mmap.mmap
"""What the walks read: any object with the buffer protocol."""

GATHER_BYTES = 1 << 20
"""Bytes :func:`py_gather` copies per numpy step (its index array: 8 x that)."""
PURE_PYTHON_ENV = "IMUPIPE_PURE_PYTHON"
"""Set to 1: use the pure-Python walks even when the compiled helper is built."""


def py_ulog_walk(buf: Buffer, start: int, limit: int) -> tuple[bytes, bytes, bytes, bytes, int]:
    """The ULog records lying whole in ``buf[start:limit]`` (``limit`` clipped to the buffer),
    walking from ``start``: a record at ``o`` is taken when ``o + 3 + size <= limit``; the walk
    stops at the first that is not, or with fewer than 3 bytes left. Returns, as bytes, each
    record's offset (int64), payload size (uint16), type (uint8) and payload's first two bytes
    as a little-endian uint16 (a data record's ``msg_id``; 0 for a payload shorter than 2), and
    where the walk stopped (the end of the last record taken)."""
    view = memoryview(buf).cast("B")
    limit = min(limit, len(view))
    size_at = struct.Struct("<H").unpack_from
    offsets: list[int] = []
    o = max(start, 0)
    while o + 3 <= limit:  # the one step per record: where the next one starts
        (size,) = size_at(view, o)
        if o + 3 + size > limit:
            break
        offsets.append(o)
        o += 3 + size
    at = np.asarray(offsets, dtype=np.int64)
    raw = np.frombuffer(view, dtype=np.uint8)
    sizes = (raw[at].astype(np.uint16) | (raw[at + 1].astype(np.uint16) << 8)) if len(at) else at
    ids = np.zeros(len(at), dtype=np.uint16)
    long = np.flatnonzero(sizes >= 2)
    ids[long] = raw[at[long] + 3].astype(np.uint16) | (raw[at[long] + 4].astype(np.uint16) << 8)
    return (
        at.tobytes(),
        np.asarray(sizes, dtype=np.uint16).tobytes(),
        raw[at + 2].tobytes() if len(at) else b"",
        ids.tobytes(),
        o,
    )


def py_gather(buf: Buffer, offsets: Buffer, skip: int, size: int) -> bytearray:
    """``buf[o + skip : o + skip + size]`` for each int64 ``o`` of ``offsets``, concatenated
    (a bytearray: the arrays numpy makes of it are writable), with numpy fancy indexing."""
    view = memoryview(buf).cast("B")
    starts = np.frombuffer(offsets, dtype=np.int64)
    if skip < 0 or size < 0:
        raise ValueError("gather: negative size or skip")
    if len(starts) and (starts.min() < 0 or starts.max() + skip + size > len(view)):
        raise IndexError("gather: offset out of the buffer")
    raw = np.frombuffer(view, dtype=np.uint8)
    out = bytearray(len(starts) * size)
    rows = np.frombuffer(out, dtype=np.uint8).reshape(len(starts), size)
    step = max(1, GATHER_BYTES // max(size, 1))  # records a slice: bounds the index array
    for i in range(0, len(starts), step):  # slices of records, not one step per record
        rows[i : i + step] = raw[starts[i : i + step, None] + skip + np.arange(size)]
    return out


def compiled() -> bool:
    """Whether the compiled helper is used (built, and not turned off by the environment)."""
    return _helper() is not None


def _helper() -> Any:
    """The compiled module, or None (not built, or ``IMUPIPE_PURE_PYTHON`` set)."""
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None
    try:
        from imupipe.readers import _records  # type: ignore[attr-defined]
    except ImportError:
        return None
    return _records


class Walk(NamedTuple):
    """The records a ULog walk took (:func:`py_ulog_walk`), as arrays."""

    offsets: np.ndarray
    """Each record's offset in the file (int64)."""
    sizes: np.ndarray
    """Its payload's size (uint16)."""
    kinds: np.ndarray
    """Its type (uint8: ``ord("D")``...)."""
    ids: np.ndarray
    """Its payload's first two bytes (uint16: a data record's ``msg_id``)."""
    end: int
    """Where the walk stopped."""


def ulog_walk(buf: Buffer, start: int, limit: int) -> Walk:
    """:func:`py_ulog_walk` (compiled when built), as arrays."""
    helper = _helper()
    offsets, sizes, kinds, ids, end = (py_ulog_walk if helper is None else helper.ulog_walk)(
        buf, start, limit
    )
    return Walk(
        np.frombuffer(offsets, dtype=np.int64),
        np.frombuffer(sizes, dtype=np.uint16),
        np.frombuffer(kinds, dtype=np.uint8),
        np.frombuffer(ids, dtype=np.uint16),
        int(end),
    )


def gather(buf: Buffer, offsets: np.ndarray, skip: int, size: int) -> bytearray:
    """:func:`py_gather` (compiled when built)."""
    helper = _helper()
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    return (py_gather if helper is None else helper.gather)(buf, offsets, skip, size)


def ulog_formats(buf: Buffer, offsets: np.ndarray, sizes: np.ndarray) -> list[Any] | None:
    """The ULog format records at ``offsets`` (payload sizes ``sizes``) split in C: per record
    ``(name, [(type, array size or 0, field name), ...])`` as
    :func:`imupipe.readers.ulog.records._format` splits it, or None where the payload is not in
    the plain form the helper takes (ASCII, every entry with a space, array sizes of 1-4
    digits: the caller splits those in Python); None without the compiled helper."""
    helper = _helper()
    if helper is None:
        return None
    return helper.ulog_formats(
        buf,
        np.ascontiguousarray(offsets, dtype=np.int64),
        np.ascontiguousarray(sizes, dtype=np.int64),
    )


def dataflash_walk(
    buf: np.ndarray, lengths: np.ndarray, first_def: np.ndarray
) -> np.ndarray | None:
    """The offsets (int64) of a DataFlash log's records as pymavlink's ``DFReader`` walks them
    (from the start: ``0xA3 0x95 <type>`` of a type with ``lengths[type] > 0``, defined before
    it, ``first_def[type] < offset``, and whole; the next searched from its end; any other byte
    skipped), in C; None without the compiled helper: the DataFlash reader then finds the same
    chain with numpy (:func:`imupipe.readers.dataflash.reader.record_offsets`)."""
    helper = _helper()
    if helper is None:
        return None
    raw = helper.dataflash_walk(
        np.ascontiguousarray(buf, dtype=np.uint8),
        np.ascontiguousarray(lengths, dtype=np.int64),
        np.ascontiguousarray(first_def, dtype=np.int64),
    )
    return np.frombuffer(raw, dtype=np.int64)
