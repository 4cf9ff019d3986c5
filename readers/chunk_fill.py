"""One MCAP chunk's sensor messages into the table's columns in one compiled pass, when built.

The numpy path reads a decompressed chunk's messages of one channel in a few dozen numpy calls
(:meth:`imupipe.readers.mcap.fast.ChunkMessages.records`: the record headers;
:func:`imupipe.readers.decoded.decode_piece`: the CDR header and fields as strided views;
:meth:`imupipe.readers.table_buffer.TableBuffer.add`: each column copied into the table after a
check that it still holds zeros). Each call is cheap per message, but a chunk of 2,850 Imu
messages took about as long in them as its decompression did. The compiled helper
``imupipe.readers._chunks`` (``readers/_chunks.c``, built by ``setup.py`` as an optional
extension) does it in two passes over the chunk:

- :func:`walk`: the channel's records checked (opcode, record length, channel id) and found to
  hold one little-endian CDR layout (one payload size, encapsulation header, frame_id length
  and bytes, every field at one offset from its record); their log, publish and header times
  gathered. The result is a :class:`RecordPiece`, whose value columns are not read yet.
- :func:`fill`: the float fields of those messages written straight into the table's columns
  (from :meth:`TableBuffer.add <imupipe.readers.table_buffer.TableBuffer.add>`), a column that
  holds only zeros so far (unknown covariances) left unwritten unless a value is not +0.0 bit
  for bit, and NaN noted where the "no data" marks need it.

Anything :func:`walk` does not take (another layout, a damaged record, big-endian CDR, a split
stream) is read by the numpy path, which names what is wrong. The numpy path is the fallback:
taken when the helper is not built or ``IMUPIPE_PURE_PYTHON=1`` is set
(:data:`~imupipe.readers.record_walk.PURE_PYTHON_ENV`); ``tests/test_chunk_fill.py`` checks that
both give the same tables, byte for byte.
"""

from __future__ import annotations

import os
import sys
import zlib
from array import array
from dataclasses import dataclass
from types import ModuleType

import numpy as np
import pyarrow as pa

from imupipe.readers.cdr import at, even_step, field_count, unaligned
from imupipe.readers.compression import BufferPool
from imupipe.readers.decoded import Piece, repeat_string
from imupipe.readers.record_walk import PURE_PYTHON_ENV
from imupipe.readers.topics import COLUMNS, OTHER_VECTOR, PIECE_TYPES

NAN_COLUMNS = ("gyro_x", "accel_x")
"""The columns whose NaN :func:`imupipe.readers.decoded.absent_sensors` looks for first."""


_found: dict[str, ModuleType | None] = {}
"""The compiled helper (None: not built), once looked for."""


def _module() -> ModuleType | None:
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0") or sys.byteorder != "little":
        return None
    if "module" not in _found:
        try:
            from imupipe.readers import _chunks  # type: ignore[attr-defined]
        except ImportError:
            _found["module"] = None
        else:
            _found["module"] = _chunks
    return _found["module"]


def compiled() -> bool:
    """Whether the compiled pass is used (built, on a little-endian machine, and not turned off
    by ``IMUPIPE_PURE_PYTHON``)."""
    return _module() is not None


@dataclass(frozen=True)
class Records:
    """Where a chunk's messages of one channel hold their float fields: at ``skip`` bytes from
    each record's offset in ``buf`` (a decompressed chunk, uint8), one column per ``slots``
    row (first float, count), named ``names``."""

    buf: np.ndarray
    offsets: np.ndarray
    skip: int
    slots: np.ndarray
    names: tuple[str, ...]
    module: ModuleType
    """The compiled helper that found them."""

    def columns(self) -> dict[str, np.ndarray]:
        """The value columns with the numpy path's values: strided views into ``buf`` when the
        records are evenly spaced, else gathered."""
        n = len(self.offsets)
        step = even_step(self.offsets)
        out = {}
        for name, (first, count) in zip(self.names, self.slots.tolist(), strict=True):
            pos = self.skip + 8 * first
            if step is not None and n:
                shape, strides = ((n,), (step,)) if count == 1 else ((n, count), (step, 8))
                out[name] = np.ndarray(
                    shape,
                    "<f8",
                    buffer=self.buf,
                    offset=int(self.offsets[0]) + pos,
                    strides=strides,
                )
            elif count == 1:
                out[name] = at(self.buf, self.offsets, pos, "<f8", None)
            else:
                f8 = unaligned(self.buf, "<f8")
                out[name] = f8[(self.offsets + pos)[:, None] + 8 * np.arange(count)]
        return out


class RecordPiece(Piece):
    """A :class:`~imupipe.readers.decoded.Piece` whose value columns are still in the chunk
    (:attr:`records`): the table fills its columns from there (:func:`fill`); ``columns`` gives
    them as the numpy path would, made on first use (by a reader of batches, for instance)."""

    def __init__(
        self,
        stamp: np.ndarray,
        log: np.ndarray,
        frame: pa.Array,
        pub: np.ndarray,
        one_frame: str,
        records: Records,
        ordered: int,
    ) -> None:
        self._columns: dict[str, np.ndarray] | None = None
        self.records: Records | None = records
        self.ordered = ((log, bool(ordered & 1)), (stamp, bool(ordered & 2)))
        """(times, whether they never decrease) for the log times and the header stamps, as
        the compiled walk found them."""
        self.filled: tuple[int, int, set[str]] | None = None
        """Set when the table wrote this piece's values right after its chunk's decompression
        (:meth:`imupipe.readers.table_buffer.TableBuffer.prefill`): the first row they took,
        the columns' allocation they went to and the columns holding a NaN."""
        super().__init__(stamp, log, frame, None, pub, one_frame)  # type: ignore[arg-type]

    @property  # type: ignore[override]
    def columns(self) -> dict[str, np.ndarray]:
        if self._columns is None:
            self._columns = self.records.columns() if self.records is not None else {}
        return self._columns

    @columns.setter
    def columns(self, value: dict[str, np.ndarray] | None) -> None:
        self._columns = value
        if value is not None:
            self.records = None


_frames: dict[tuple[str, int], pa.Array] = {}
_SLOTS = {
    stream: (
        tuple(name for name, _, _ in columns),
        np.array([(first, count) for _, first, count in columns], np.int64),
    )
    for stream, columns in COLUMNS.items()
}
"""Per stream: its value columns' names and (first float, count)."""
_BITS = {names: {name: 1 << i for i, name in enumerate(names)} for names, _ in _SLOTS.values()}
"""Per tuple of names: each name's bit (the slot masks of ``_chunks.fill``)."""
_NAN_BITS = {names: sum(bits.get(name, 0) for name in NAN_COLUMNS) for names, bits in _BITS.items()}
"""Per tuple of names: the bits of :data:`NAN_COLUMNS`."""


def repeated_frame(one: str, n: int) -> pa.Array:
    """``repeat_string(one, n)``, the last few kept (most chunks have one size and frame_id)."""
    key = (one, n)
    frame = _frames.get(key)
    if frame is None:
        if len(_frames) > 8:
            _frames.clear()
        frame = _frames[key] = repeat_string(one, n)
    return frame


_TIMES = BufferPool()
"""Buffers :func:`walk` gathers times into, each used again once no piece's times refer to it
(a new one per call cost a fresh mapping of its pages: ~6,000 page faults per million Imu
messages)."""


def walk(buf: np.ndarray, offsets: np.ndarray, channel: int, stream: str) -> RecordPiece | None:
    """The messages of ``channel`` at the record ``offsets`` of the decompressed chunk ``buf``
    as a :class:`RecordPiece` of ``stream``, when the compiled pass takes them (one CDR layout,
    every record whole and of the channel); else None (the numpy path reads them)."""
    module = _module()
    if module is None or stream in OTHER_VECTOR or not len(offsets):
        return None
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    n = len(offsets)
    raw = _TIMES.take(3 * n * 8)
    _TIMES.give(raw)  # taken again only when the views below are gone
    out = raw.view(np.int64)
    found = module.cdr_walk(buf, offsets, channel, field_count(PIECE_TYPES[stream]), out)
    if found is None:
        return None
    _, skip, frame, ordered = found
    try:
        one = frame.decode()
    except UnicodeDecodeError:
        return None
    log, pub, stamp = out[: 3 * n].reshape(3, n)
    names, slots = _SLOTS[stream]
    records = Records(buf, offsets, skip, slots, names, module)
    return RecordPiece(stamp, log, repeated_frame(one, n), pub, one, records, ordered)


def crc32(data: np.ndarray | bytes | memoryview) -> int:
    """``zlib.crc32(data)``, the CRC an MCAP chunk record states over its decompressed bytes:
    by the compiled helper where it is built and the CPU multiplies carry-less (PCLMULQDQ,
    0.03 s for the 355 MB of a million Imu messages against zlib 1.2's 0.12-0.15 s), else by
    zlib (the numpy path, ``IMUPIPE_PURE_PYTHON=1``). The same value either way
    (``tests/test_chunk_fill.py``)."""
    module = _module()
    if module is not None:
        found = module.crc32(data)
        if found is not None:
            return found
    return zlib.crc32(data)


def fill(
    records: Records,
    columns: dict[str, np.ndarray],
    clean: set[str],
    runs: list[tuple[slice, slice]],
) -> tuple[set[str], set[str]]:
    """Write the messages of ``records`` into ``columns`` (the table's, by name), run by run
    (values, rows). A column of ``clean`` (zeros so far) is written only from its first value
    that is not +0.0. Returns the clean columns written, and those of :data:`NAN_COLUMNS` that
    hold a NaN."""
    names = records.names
    bits = _BITS[names]
    clean_bits = sum(bits.get(name, 0) for name in clean)
    nan_bits = _NAN_BITS[names]
    spans = array("q", [x for v, r in runs for x in (v.start, r.start, v.stop - v.start)])
    dirty, nan = records.module.fill(
        records.buf,
        records.offsets,
        records.skip,
        records.slots,
        tuple(columns[name] for name in names),
        clean_bits,
        nan_bits,
        spans,
    )
    if not dirty and not nan:  # most chunks: no column starts holding values, no NaN
        return set(), set()
    return (
        {name for i, name in enumerate(names) if dirty >> i & 1},
        {name for i, name in enumerate(names) if nan >> i & 1},
    )
