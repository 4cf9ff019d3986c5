"""ArduPilot DataFlash logs (``.bin``) into the common table, decoded with numpy.

A DataFlash log (ArduPilot's on-board log, ``libraries/AP_Logger``) is a sequence of records,
each ``0xA3 0x95 <type>`` followed by a payload of fixed size. ``FMT`` records (type 128) define
each type: its name, record length, field formats (one character per field: ``f`` float32,
``Q`` uint64, ``h`` int16, ``c`` int16 x 0.01, ...) and column names. pymavlink's
``DFReader`` (the reference reader) parses the records one by one in Python; this module finds
the record starts and decodes each type's records at once with ``np.frombuffer`` on a
structured dtype built from its ``FMT``, and gives the same values as ``DFReader`` (tested value
for value on every field of every record of the real logs).

**Finding the records** (:func:`record_offsets`): every ``0xA3 0x95 <known type>`` is a
candidate; each candidate's successor is the first candidate at or after its end (so garbage
between records is skipped as ``DFReader`` skips it, byte by byte to the next header of a known
type); the records are the candidates reachable from the first, walked in C when the compiled
helper is built (:func:`imupipe.readers.record_walk.dataflash_walk`: one pass over the bytes),
else found by pointer doubling (log2(n) vectorised steps; the same records, tested equal). A
record cut by the end of the file ends the log, as in ``DFReader``.

**Damaged ``FMT`` records** (:func:`_fit_lengths`, :meth:`DataFlashLog.undecodable`): a
type whose ``FMT`` length disagrees with the sizes of its field formats is walked with the
length its records show (the one after which more of its records are followed by another
record's header) and the warning says so; a type whose records still cannot be decoded (its
formats do not add up, name an unknown character, repeat a column) is skipped with a warning
giving its record count and its ``FMT``'s offset, so no stream vanishes unsaid; bytes between
records are counted with the first offset and the record headers found among them. A file
without an ``FMT`` record in its first MiB is refused before it is read whole.

**Instances.** ArduPilot logs a sensor kind either as one message per instance (``IMU``,
``IMU2``, ``IMU3``; ``MAG``, ``MAG2``; ``BARO``, ``BAR2``: older firmware) or as one message with
an instance field ``I`` (``IMU`` with ``I`` = 0, 1, 2: ArduPilot 4.1 and later). imupipe names
an instance as pyulog names PX4's: the message for instance 0, ``<message>_<I>`` for the others
(``IMU``, ``IMU_1``, ``MAG_2``); an old-style message keeps its own name (``IMU2`` is instance
1).

**What fills the streams** (units from ``LogStructure.h``'s units and multipliers, converted to
SI):

| stream | messages | fields |
|---|---|---|
| ``imu`` | ``IMU[_N]``, ``IMU2``, ``IMU3`` | ``GyrX..Z`` rad/s, ``AccX..Z`` m/s^2 |
| ``mag`` | ``MAG[_N]``, ``MAG2``, ``MAG3`` | ``MagX..Z`` milligauss (x 1e-7 to tesla) |
| ``temperature`` | the IMU's own ``T``/``Temp`` (degC), or a ``BARO[_N]``/``BAR2``/``BAR3`` ``Temp`` | degC |

A barometer read as the temperature stream also fills the optional ``pressure`` column (its
``Press``, Pa) on the same rows.

Both ArduPilot's ``IMU`` and ``MAG`` values are *already corrected* by its own calibration
(``INS_*OFFS``/``INS_*SCAL``, ``COMPASS_OFS*``...; the board orientation applied): the table's
metadata says so (``ardupilot.calibrated``), as for PX4's ``sensor_combined``.

**Time**: ``TimeUS`` (microseconds since boot) or, in older logs, ``TimeMS`` (milliseconds),
kept as nanoseconds since boot; a DataFlash record has one time, so ``time = "header"`` and
``time = "log"`` read the same.

**Metadata** (besides the common keys): ``instance`` (stream -> instance number),
``device_id`` (stream or sensor -> the device id the log's parameters give its instance,
:func:`device_ids`) and
``ardupilot``: ``calibrated`` (stream -> true), ``parameters`` (the log's ``PARM`` values at
start, the first of each name, of the calibration-related ones: :data:`CALIBRATION_PREFIXES`;
:meth:`DataFlashLog.parameters` gives them all) and ``firmware`` (the first ``MSG`` text that
names a vehicle, e.g. ``ArduCopter V3.3-dev``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import unique
from imupipe.readers.decoded import Piece, repeat_string
from imupipe.readers.errors import ReadError
from imupipe.readers.record_walk import dataflash_walk
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import (
    metadata,
    with_flight_streams,
    with_metadata,
    with_stream_column,
)
from imupipe.readers.table_buffer import assemble
from imupipe.readers.topics import NOT_CARRIED, asked_topics, some_of

HEAD = (0xA3, 0x95)
"""The two bytes that start every record."""
FMT_TYPE = 128
"""The type of ``FMT`` records (``LOG_FORMAT_MSG``), defined by no record."""
FMT_DTYPE = np.dtype(
    [("type", "u1"), ("length", "u1"), ("name", "S4"), ("format", "S16"), ("columns", "S64")]
)
"""An ``FMT`` record's payload (``struct log_Format``, format ``BBnNZ``)."""
FIELD_DTYPES: dict[str, Any] = {
    "a": ("<i2", (32,)),
    "b": "i1",
    "B": "u1",
    "g": "<f2",
    "h": "<i2",
    "H": "<u2",
    "i": "<i4",
    "I": "<u4",
    "f": "<f4",
    "d": "<f8",
    "n": "S4",
    "N": "S16",
    "Z": "S64",
    "c": "<i2",
    "C": "<u2",
    "e": "<i4",
    "E": "<u4",
    "L": "<i4",
    "M": "i1",
    "q": "<i8",
    "Q": "<u8",
}
"""DataFlash field format character -> numpy dtype (little-endian, as ``AP_Logger`` writes and
``DFReader.FORMAT_TO_STRUCT`` reads them)."""
FIELD_SIZES = {c: np.dtype(v).itemsize for c, v in FIELD_DTYPES.items()}
"""Bytes of each field format character."""
FIELD_SCALES = {"c": 0.01, "C": 0.01, "e": 0.01, "E": 0.01, "L": 1e-7}
"""Format characters whose integer is scaled on reading: divided by ``1 / scale`` (100, or 1e7
for degrees of latitude), as ``DFReader.DFMessage`` does, to the same float64."""
MILLIGAUSS = 1e-7
"""Tesla per milligauss (``MAG`` fields are int16 milligauss: units ``G``, multiplier ``C``)."""
IMU_NAMES = ("IMU", "IMU2", "IMU3")
MAG_NAMES = ("MAG", "MAG2", "MAG3")
BARO_NAMES = ("BARO", "BAR2", "BAR3")
OLD_STYLE_INSTANCE = {"IMU2": 1, "IMU3": 2, "MAG2": 1, "MAG3": 2, "BAR2": 1, "BAR3": 2}
"""Older firmware's one message per instance."""
GYRO = ("GyrX", "GyrY", "GyrZ")
ACCEL = ("AccX", "AccY", "AccZ")
MAG = ("MagX", "MagY", "MagZ")
NUMERIC = "bBghHiIfdcCeELMqQ"
"""Format characters of one number (what a stream's fields and an instance field must be)."""
TEMPERATURE_FIELDS = ("T", "Temp")
"""An ``IMU`` message's temperature (``T`` since 3.5, ``Temp`` before); a ``BARO``'s ``Temp``."""


@dataclass(frozen=True)
class Format:
    """One message type's ``FMT``: name, record length (with the 3 header bytes), field
    formats and column names."""

    type: int
    name: str
    length: int
    format: str
    columns: tuple[str, ...]
    at: int = field(default=-1, compare=False)
    """The offset of the ``FMT`` record that defined it (-1: ``FMT`` itself)."""
    said: int = field(default=0, compare=False)
    """The length its ``FMT`` record gave, when :func:`_fit_lengths` took another."""

    def numeric(self, *columns: str) -> bool:
        """Whether every one of ``columns`` is a field holding one number."""
        return all(
            c in self.columns and self.format[self.columns.index(c)] in NUMERIC for c in columns
        )

    def dtype(self) -> np.dtype | None:
        """The payload's structured dtype; None when the format is unknown or does not add up
        to the record length (``DFReader`` cannot unpack such records either)."""
        return _payload_dtype(self.format, self.columns, self.length)


@functools.lru_cache(maxsize=4096)
def _payload_dtype(format: str, columns: tuple[str, ...], length: int) -> np.dtype | None:
    """:meth:`Format.dtype`, made once per (field formats, columns, length): a read asks for
    each type's dtype about 100 times."""
    if len(format) != len(columns) or any(c not in FIELD_DTYPES for c in format):
        return None
    names = [c if c else f"field{i}" for i, c in enumerate(columns)]
    if len(set(names)) != len(names):
        return None
    dtype = np.dtype([(n, FIELD_DTYPES[c]) for n, c in zip(names, format, strict=True)])
    return dtype if dtype.itemsize == length - 3 else None


def _text(raw: bytes) -> str:
    """A DataFlash string field: up to the first NUL (as ``DFReader.null_term``)."""
    return raw.split(b"\0", 1)[0].decode("ascii", "replace")


def _payloads(buf: np.ndarray, offsets: np.ndarray, size: int, dtype: np.dtype) -> np.ndarray:
    """The ``size``-byte payloads of the records at ``offsets`` as a structured array: a
    sliding-window view of the file, fancy-indexed by record (copies the payload bytes only)."""
    windows = np.lib.stride_tricks.sliding_window_view(buf, size) if size else None
    if windows is None or not len(offsets):
        return np.zeros(len(offsets), dtype=dtype)
    return np.ascontiguousarray(windows[offsets + 3]).view(dtype).reshape(-1)


HEAD_BYTES = 1 << 20
"""A DataFlash log starts with its ``FMT`` records: a file without one in its first MiB is not
read further (a 2 GiB file of zeros named ``.bin`` is refused at once)."""
SCAN_BLOCK = 1 << 24
"""Bytes scanned for headers at a time (bounds the scan's temporary masks to a few x 16 MiB)."""


def _candidates(buf: np.ndarray) -> np.ndarray:
    """Offsets of every ``0xA3 0x95`` pair that leaves room for a type byte."""
    n = len(buf) - 2
    found = [np.zeros(0, dtype=np.int64)]
    for start in range(0, max(n, 0), SCAN_BLOCK):  # blocks of the file, not records
        stop = min(start + SCAN_BLOCK, n)
        hit = np.flatnonzero(buf[start:stop] == HEAD[0]) + start  # then its next byte
        found.append(hit[buf[hit + 1] == HEAD[1]].astype(np.int64))
    return np.concatenate(found)


def _formats_at(buf: np.ndarray, offsets: np.ndarray) -> dict[int, Format]:
    """The message types the ``FMT`` records at ``offsets`` define (the first definition of a
    type wins: ArduPilot writes each once; ``FMT`` itself is fixed by the format)."""
    formats = {
        FMT_TYPE: Format(
            FMT_TYPE,
            "FMT",
            3 + FMT_DTYPE.itemsize,
            "BBnNZ",
            ("Type", "Length", "Name", "Format", "Columns"),
        )
    }
    end = len(buf) - 3 - FMT_DTYPE.itemsize
    offsets = offsets[offsets <= end]
    if not len(offsets):
        return formats
    recs = _payloads(buf, offsets, FMT_DTYPE.itemsize, FMT_DTYPE)
    fields = zip(
        offsets.tolist(),
        *(recs[k].tolist() for k in ("type", "length", "name", "format", "columns")),
        strict=True,
    )
    for at, t, length, name, form, cols in fields:  # one per message type: tens
        if t in formats or length < 3:
            continue
        columns = tuple(_text(cols).split(",")) if cols else ()
        formats[t] = Format(
            t, _text(name), length, _text(form), columns if columns != ("",) else (), at
        )
    return formats


def _reachable(nxt: np.ndarray) -> np.ndarray:
    """Which nodes lie on the chain from node 0, where ``nxt[i] > i`` is node i's successor
    (``len(nxt)``: none). Pointer doubling: after step k the set holds every node fewer than
    2**(k+1) links from node 0."""
    n = len(nxt)
    jump = np.append(nxt, n)  # the sentinel n leads to itself
    on = np.zeros(n + 1, dtype=bool)
    on[0] = n > 0
    while True:
        on[jump[on]] = True
        if bool(np.all(jump == n)):
            break
        jump = jump[jump]
    return on[:n]


def _format_size(fmt: Format) -> int | None:
    """The record length (header included) ``fmt``'s field formats add up to; None when a
    format character is unknown."""
    if not set(fmt.format) <= FIELD_SIZES.keys():
        return None
    return 3 + sum(map(FIELD_SIZES.__getitem__, fmt.format))


def _fit_lengths(
    cand: np.ndarray, types: np.ndarray, formats: dict[int, Format]
) -> dict[int, Format]:
    """``formats`` with the length of each type whose ``FMT`` length and field formats
    disagree (a damaged ``FMT``) taken from its records: of the two lengths, the one after
    which more of its records are followed by another record's header (ties: the ``FMT``'s
    length). The records of a type whose format still does not add up are skipped and counted
    (:meth:`DataFlashLog.undecodable`)."""
    out = dict(formats)
    for t, fmt in formats.items():
        size = _format_size(fmt)
        if t == FMT_TYPE or size is None or size == fmt.length or not 3 < size < 256:
            continue
        at = cand[types == t]
        if not len(at):
            continue

        def followed(length: int, at: np.ndarray = at) -> int:
            ends = at + length
            i = np.minimum(np.searchsorted(cand, ends), len(cand) - 1)
            return int(np.count_nonzero(cand[i] == ends))

        if followed(size) > followed(fmt.length):
            out[t] = replace(fmt, length=size, said=fmt.length)
    return out


def _chain(
    buf: np.ndarray,
    cand: np.ndarray,
    types: np.ndarray,
    lengths: np.ndarray,
    first_def: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(offsets, types) of the records ``DFReader`` walks: from the first candidate that is a
    record (a known type, defined before it, and whole), each next the first such candidate at
    or after its end. In C when the compiled helper is built
    (:func:`imupipe.readers.record_walk.dataflash_walk`: one pass over the bytes), else with
    numpy (each candidate's successor, then the chain from the first by pointer doubling,
    :func:`_reachable`); both give the same records (``tests/test_dataflash_reader.py``)."""
    walked = dataflash_walk(buf, lengths, first_def)
    if walked is not None:
        return walked, buf[walked + 2].astype(np.int64)
    ok = (lengths[types] > 0) & (first_def[types] < cand) & (cand + lengths[types] <= len(buf))
    pos, typ = cand[ok], types[ok]
    on = _reachable(np.searchsorted(pos, pos + lengths[typ]))
    return pos[on], typ[on]


def record_offsets(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[int, Format], int]:
    """(offsets, types, formats, end) of the log's records, in file order, as ``DFReader`` walks
    them; ``end`` is the offset after the last whole record (bytes after it: a cut record or
    trailing garbage). A damaged ``FMT`` length is corrected from the records
    (:func:`_fit_lengths`)."""
    cand = _candidates(buf)
    types = buf[cand + 2].astype(np.int64) if len(cand) else np.zeros(0, np.int64)
    fmt_at = cand[types == FMT_TYPE]
    formats = _fit_lengths(cand, types, _formats_at(buf, fmt_at))
    for _ in range(2):  # again when a false FMT candidate off the chain defined a type
        lengths = np.zeros(256, dtype=np.int64)
        first_def = np.full(256, len(buf), dtype=np.int64)
        first_def[FMT_TYPE] = -1
        for t, f in formats.items():
            lengths[t] = f.length
        defined = fmt_at[fmt_at <= len(buf) - 3 - FMT_DTYPE.itemsize]
        if len(defined):
            def_types = buf[defined + 3].astype(np.int64)
            np.minimum.at(first_def, def_types, defined)
        pos, typ = _chain(buf, cand, types, lengths, first_def)
        walked = _fit_lengths(cand, types, _formats_at(buf, pos[typ == FMT_TYPE]))
        if walked == formats or fmt_at.size == 0:
            break
        formats, fmt_at = walked, pos[typ == FMT_TYPE]
    end = int(pos[-1] + lengths[typ[-1]]) if len(pos) else 0
    return pos, typ, formats, end


class DataFlashLog:
    """A DataFlash log: its records found and each type decodable on demand (:meth:`records`);
    also the :class:`~imupipe.readers.sources.LogSource` view ``inspect`` uses."""

    format = "dataflash"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise ReadError(f"{self.path}: no such file")
        try:
            with open(self.path, "rb") as fh:  # judged by its head before it is read whole
                head = fh.read(HEAD_BYTES)
            if bytes((*HEAD, FMT_TYPE)) not in head:
                raise ReadError(
                    f"{self.path}: not an ArduPilot DataFlash log (no FMT record in its first "
                    f"{len(head):,} bytes)"
                )
            self.buf = np.fromfile(self.path, dtype=np.uint8)
        except OSError as exc:
            raise ReadError(f"{self.path}: cannot be read ({exc.strerror})") from None
        self.offsets, self.types, self.formats, self.end = record_offsets(self.buf)
        if not len(self.offsets) or len(self.formats) < 2:
            raise ReadError(
                f"{self.path}: not an ArduPilot DataFlash log, or cut before its first whole "
                "record (no FMT record found)"
            )
        self.by_name: dict[str, Format] = {}
        """Message name -> its format (a name defined twice: the first type)."""
        for fmt in self.formats.values():
            self.by_name.setdefault(fmt.name, fmt)
        self._records: dict[str, np.ndarray] = {}
        self.instances = self._instances()

    @property
    def trailing(self) -> int:
        """Bytes after the last whole record (a cut record or padding)."""
        return int(len(self.buf) - self.end)

    def skipped(self) -> int:
        """Bytes before the last whole record that belong to no record (corruption
        ``DFReader`` skips)."""
        lengths = np.zeros(256, dtype=np.int64)
        for t, f in self.formats.items():
            lengths[t] = f.length
        return int(self.end - lengths[self.types].sum())

    def undecodable(self) -> list[str]:
        """One line per message type whose records were found but cannot be decoded (its
        ``FMT``'s fields do not add up to its length, name an unknown format or repeat a
        column), and per ``FMT`` length corrected from the records (:func:`_fit_lengths`)."""
        out = []
        present, n = np.unique(self.types, return_counts=True)
        for t, count in zip(present.tolist(), n.tolist(), strict=True):
            fmt = self.formats[t]
            if t == FMT_TYPE:
                continue
            where = f"its FMT at byte {fmt.at}" if fmt.at >= 0 else "its FMT"
            if fmt.said:
                out.append(
                    f"message {fmt.name}: {where} says {fmt.said} bytes a record, its fields "
                    f"and its {count} records {fmt.length}: read as {fmt.length}"
                )
            if fmt.dtype() is None:
                size = _format_size(fmt)
                why = (
                    f"fields '{fmt.format}' ({size} bytes) in records of {fmt.length}"
                    if size is not None and size != fmt.length
                    else f"fields '{fmt.format}' for columns '{','.join(fmt.columns)}'"
                )
                out.append(
                    f"{count} records of message {fmt.name} (type {t}) skipped: {where} "
                    f"gives {why}, which cannot be decoded"
                )
            elif self.by_name.get(fmt.name) is not fmt:
                out.append(
                    f"{count} records of message {fmt.name} (type {t}) skipped: another FMT "
                    f"defines {fmt.name} first"
                )
        return out

    def off_chain(self) -> tuple[int, dict[str, int]]:
        """(offset of the first byte between records that belongs to no record, or -1;
        message name -> record headers found among such bytes): what the skipped bytes
        held."""
        lengths = np.zeros(256, dtype=np.int64)
        for t, f in self.formats.items():
            lengths[t] = f.length
        if not len(self.offsets):
            return -1, {}
        ends = self.offsets + lengths[self.types]
        gaps = np.flatnonzero(ends[:-1] < self.offsets[1:])
        first = int(ends[gaps[0]]) if len(gaps) else -1
        cand = _candidates(self.buf[: self.end])
        if not len(cand):
            return first, {}
        types = self.buf[cand + 2].astype(np.int64)
        known = lengths[types] > 0
        cand, types = cand[known], types[known]
        off = ~np.isin(cand, self.offsets)
        names, counts = np.unique(types[off], return_counts=True)
        return first, {
            self.formats[int(t)].name: int(c) for t, c in zip(names, counts, strict=True)
        }

    def records(self, name: str) -> np.ndarray:
        """Every record of message ``name`` as a structured array (raw field values; see
        :meth:`field` for the scaled ones). ReadError when its FMT cannot be decoded."""
        if name not in self._records:
            fmt = self.by_name.get(name)
            dtype = None if fmt is None else fmt.dtype()
            if fmt is None or dtype is None:
                raise ReadError(f"{self.path}: message {name} has no decodable FMT definition")
            at = self.offsets[self.types == fmt.type]
            self._records[name] = _payloads(self.buf, at, fmt.length - 3, dtype)
        return self._records[name]

    def field(self, name: str, column: str, rows: np.ndarray | None = None) -> np.ndarray:
        """One field of message ``name`` with ``DFReader``'s scaling (``c``: x 0.01, ``L``:
        x 1e-7...): float64 for numbers, the raw array for strings and arrays."""
        fmt = self.by_name[name]
        values = self.records(name)[column]
        if rows is not None:
            values = values[rows]
        code = fmt.format[fmt.columns.index(column)]
        if code in FIELD_SCALES:
            return values.astype(np.float64) / (1 / FIELD_SCALES[code])
        if values.dtype.kind in "iuf" and values.ndim == 1:
            with np.errstate(invalid="ignore"):  # a float16 NaN of a damaged record
                return values.astype(np.float64)
        return values

    def time_ns(self, name: str, rows: np.ndarray | None = None) -> np.ndarray | None:
        """``TimeUS`` (or old ``TimeMS``) of message ``name`` as int64 ns; None without one."""
        fmt = self.by_name[name]
        for column, scale in (("TimeUS", 1000), ("TimeMS", 1_000_000)):
            if fmt.numeric(column):
                t = self.records(name)[column].astype(np.int64) * scale
                return t if rows is None else t[rows]
        return None

    def _instances(self) -> dict[str, Instance]:
        """Every instance of every message type present: key -> Instance."""
        out: dict[str, Instance] = {}
        present = unique(self.types)
        for t in present.tolist():
            fmt = self.formats[t]
            if fmt.dtype() is None or self.by_name[fmt.name] is not fmt:
                continue
            if fmt.numeric("I") and fmt.name != "FMT":
                ids = self.records(fmt.name)["I"].astype(np.int64)
                for i in unique(ids).tolist():
                    inst = Instance(fmt.name, int(i), np.flatnonzero(ids == i))
                    out[inst.key] = inst
            else:
                n = int(np.count_nonzero(self.types == t))
                inst = Instance(fmt.name, OLD_STYLE_INSTANCE.get(fmt.name, 0), np.arange(n))
                out[inst.key if fmt.name not in OLD_STYLE_INSTANCE else fmt.name] = inst
        return dict(sorted(out.items()))

    # -- LogSource view, for inspect -----------------------------------------------------------
    def topic_types(self) -> dict[str, str]:
        """Instance key -> its DataFlash message name."""
        return {k: v.name for k, v in self.instances.items()}

    def topic_counts(self) -> dict[str, int]:
        return {k: len(v) for k, v in self.instances.items()}

    def first_time(self) -> int:
        firsts = [t[0] for t in self.topic_times().values() if len(t)]
        return int(min(firsts)) if firsts else 0

    def topic_times(self) -> dict[str, np.ndarray]:
        """Instance key -> its records' times (ns; message types without a time are left
        out)."""
        out = {}
        for key, inst in self.instances.items():
            t = self.time_ns(inst.name, inst.rows)
            if t is not None:
                out[key] = t
        return out

    # -- what the log says about itself --------------------------------------------------------
    def parameters(self) -> dict[str, float]:
        """Every ``PARM`` name with its first value in the log (the value at start)."""
        fmt = self.by_name.get("PARM")
        if fmt is None or "PARM" not in self.topic_types().values():
            return {}
        if not fmt.numeric("Value") or "Name" not in fmt.columns:
            return {}
        if fmt.format[fmt.columns.index("Name")] not in "nNZ":
            return {}
        names = self.records("PARM")["Name"]
        values = self.field("PARM", "Value")
        _, first = np.unique(names, return_index=True)  # in the names' order
        return {
            _text(n): v for n, v in zip(names[first].tolist(), values[first].tolist(), strict=True)
        }

    def firmware(self) -> str | None:
        """The first ``MSG`` text naming the vehicle firmware (``ArduCopter V3.3-dev``)."""
        fmt = self.by_name.get("MSG")
        if fmt is None or "MSG" not in self.topic_types().values() or "Message" not in fmt.columns:
            return None
        if fmt.format[fmt.columns.index("Message")] not in "nNZ":
            return None
        for raw in self.records("MSG")["Message"][:20]:
            text = _text(raw)
            if text.startswith(("Ardu", "APM", "Copter", "Plane", "Rover", "Sub", "Blimp")):
                return text
        return None


@dataclass(frozen=True)
class Instance:
    """One instance of a DataFlash message: its name, instance number and record rows."""

    name: str
    instance: int
    rows: np.ndarray

    @property
    def key(self) -> str:
        return self.name if self.instance == 0 else f"{self.name}_{self.instance}"

    def __len__(self) -> int:
        return int(len(self.rows))


# -- choosing the instances ----------------------------------------------------------------------


def _has(f: DataFlashLog, inst: Instance, *columns: str) -> bool:
    """Whether the instance's message has the numeric ``columns`` and a time."""
    fmt = f.by_name[inst.name]
    return fmt.numeric(*columns) and (fmt.numeric("TimeUS") or fmt.numeric("TimeMS"))


def _temperature_field(f: DataFlashLog, inst: Instance) -> str | None:
    return next((c for c in TEMPERATURE_FIELDS if _has(f, inst, c)), None)


def candidates(f: DataFlashLog) -> dict[str, list[str]]:
    """Stream -> the instances that can fill it (instance order)."""
    by_kind = {
        kind: [k for k, v in f.instances.items() if v.name in names]
        for kind, names in (("imu", IMU_NAMES), ("mag", MAG_NAMES), ("baro", BARO_NAMES))
    }
    imu = [k for k in by_kind["imu"] if _has(f, f.instances[k], *GYRO, *ACCEL)]
    mag = [k for k in by_kind["mag"] if _has(f, f.instances[k], *MAG)]
    temperature = [
        k
        for k in by_kind["imu"] + by_kind["baro"]
        if _temperature_field(f, f.instances[k]) is not None
    ]
    return {"imu": imu, "mag": mag, "temperature": temperature}


def choose_topics(spec: InputSpec, f: DataFlashLog) -> tuple[dict[str, str], list[str]]:
    """Stream -> instance key, from the spec's topic settings and the log; returns (choice,
    warnings). Defaults: the only IMU instance (several: an error naming them), the only
    magnetometer (several: left out with a warning), the chosen IMU's own temperature. A key set
    to ``""`` leaves its stream out."""
    cands = candidates(f)
    chosen, off = asked_topics(spec, cands, f.instances, f.path, "DataFlash messages")
    warnings: list[str] = []
    if "imu" not in chosen and cands["imu"] and "imu" not in off:
        if len(cands["imu"]) > 1:
            raise ReadError(
                f"{f.path}: several IMU instances ({', '.join(cands['imu'])}); set imu_topic in "
                f"{spec.settings_place}"
            )
        chosen["imu"] = cands["imu"][0]
    if "mag" not in chosen and cands["mag"] and "mag" not in off:
        if len(cands["mag"]) == 1:
            chosen["mag"] = cands["mag"][0]
        else:
            warnings.append(
                f"magnetometer not read: several instances ({', '.join(cands['mag'])}); set "
                f"mag_topic in {spec.settings_place}"
            )
    if "temperature" not in chosen and chosen.get("imu") in cands["temperature"]:
        chosen["temperature"] = chosen["imu"]
    if not chosen:
        raise ReadError(
            f"{f.path}: no IMU, MAG or BARO message; messages: {', '.join(f.instances) or 'none'}"
        )
    return chosen, warnings


# -- decoding ------------------------------------------------------------------------------------


def _piece(f: DataFlashLog, inst: Instance, columns: dict[str, np.ndarray]) -> Piece:
    t = f.time_ns(inst.name, inst.rows)
    if t is None:
        raise ReadError(f"{f.path}: message {inst.name} has no TimeUS or TimeMS field")
    return Piece(t, t, repeat_string("", len(t)), columns, one_frame="")


def _xyz(
    f: DataFlashLog, inst: Instance, prefix: str, fields: tuple[str, ...], scale: float
) -> dict[str, np.ndarray]:
    return {
        f"{prefix}_{a}": f.field(inst.name, c, inst.rows) * scale
        for a, c in zip("xyz", fields, strict=True)
    }


def stream_piece(f: DataFlashLog, stream: str, key: str) -> Piece:
    """The decoded samples of ``stream`` from instance ``key`` (SI units)."""
    inst = f.instances[key]
    if stream == "imu":
        cols = {**_xyz(f, inst, "gyro", GYRO, 1.0), **_xyz(f, inst, "accel", ACCEL, 1.0)}
    elif stream == "mag":
        cols = _xyz(f, inst, "mag", MAG, MILLIGAUSS)
    else:
        field = _temperature_field(f, inst)
        assert field is not None  # a candidate has one
        cols = {"temperature": f.field(inst.name, field, inst.rows)}
    return _piece(f, inst, cols)


def output_topic(stream: str, key: str) -> str:
    """The table's (and the corrected MCAP's) topic of a stream: the instance key, with
    ``/temperature`` appended for the temperature (a ROS topic has one message type)."""
    return f"{key}/temperature" if stream == "temperature" else key


def _warnings(f: DataFlashLog) -> list[str]:
    out = f.undecodable()
    skipped = f.skipped()
    if skipped:
        first, headers = f.off_chain()
        held = ", ".join(f"{n} x {c}" for n, c in sorted(headers.items(), key=lambda x: -x[1]))
        out.append(
            f"{skipped} bytes between records belong to no record (corrupt in places, the "
            f"first at byte {first}; skipped as pymavlink's DFReader skips them"
            + (f"; record headers among them: {held}" if held else "")
            + ")"
        )
    if f.trailing:
        out.append(
            f"the last {f.trailing} bytes are no whole record (a cut record or padding: "
            "the log is read up to them)"
        )
    return out


def read_dataflash(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a DataFlash input into the common table; returns (table, warnings)."""
    f = DataFlashLog(spec.path)
    chosen, warnings = choose_topics(spec, f)
    warnings += _warnings(f)
    pieces = {stream: stream_piece(f, stream, key) for stream, key in chosen.items()}
    for stream, piece in pieces.items():
        if len(piece) == 0:
            raise ReadError(f"{spec.path}: message '{chosen[stream]}' has no records")
    table = assemble(
        pieces,
        time=spec.time,
        source=str(spec.path),
        fmt="dataflash",
        topics={s: output_topic(s, k) for s, k in chosen.items()},
        where=str(spec.path),
        warnings=warnings,
    )
    baro = chosen.get("temperature")
    if (
        baro is not None
        and f.instances[baro].name in BARO_NAMES
        and _has(f, f.instances[baro], "Press")
    ):
        inst = f.instances[baro]
        table = with_stream_column(
            table,
            "temperature",
            "pressure",
            pieces["temperature"].stamp,
            f.field(inst.name, "Press", inst.rows),  # Pa (LogStructure.h units: P)
        )
    table = with_flight_streams(table, flight_streams(f))
    meta = metadata(table)
    meta.pop("frame_id", None)  # a DataFlash log names no frames
    year = gps_year(f)
    if year is not None:
        meta["gps_year"] = year
    unread = candidates(f)["mag"]
    if "mag" not in chosen and unread:  # named by a stage that needs a compass
        meta["mag_candidates"] = unread
    meta["instance"] = {s: f.instances[k].instance for s, k in chosen.items()}
    params = calibration_parameters(f)
    devices = device_ids(f, chosen, params)
    if devices:
        meta["device_id"] = devices
    meta["ardupilot"] = {
        "calibrated": {s: True for s in chosen if s != "temperature"},
        "parameters": params,
        "firmware": f.firmware(),
    }
    others = sorted(set(f.instances) - set(chosen.values()))
    if others:
        shown = some_of(others)
        warnings.append(
            f"{len(others)} other DataFlash messages are {NOT_CARRIED} "
            f"(they have no ROS message type; imupipe inspect lists them): {shown}"
        )
    return with_metadata(table, meta), warnings


def _suffix(instance: int) -> str:
    """ArduPilot's parameter names' instance part: ``""`` for the first, ``"2"``, ``"3"``."""
    return "" if instance == 0 else str(instance + 1)


def device_ids(f: DataFlashLog, chosen: dict[str, str], params: dict[str, float]) -> dict[str, int]:
    """Stream (or sensor) -> device id, from the log's own parameters: IMU instance ``n`` is
    the IMU of ``INS_GYR{n}_ID`` (``imu``, ``gyro``) and ``INS_ACC{n}_ID`` (``accel``), compass
    ``n`` of ``COMPASS_DEV_ID{n}``, barometer ``n`` of ``BARO{n+1}_DEVID`` (ArduPilot numbers
    its sensors' parameter slots by instance); a temperature read from an IMU or barometer is
    that device's. Ids that are zero or not logged are left out."""
    found: dict[str, int] = {}

    def put(key: str, name: str) -> None:
        value = params.get(name)
        if value:
            found[key] = int(value)

    for stream, key in chosen.items():
        inst = f.instances[key]
        s = _suffix(inst.instance)
        if inst.name in IMU_NAMES:
            targets = {"imu": f"INS_GYR{s}_ID", "accel": f"INS_ACC{s}_ID"}
            if stream == "temperature":
                targets = {"temperature": f"INS_GYR{s}_ID"}
            elif "temperature" not in chosen or chosen["temperature"] == key:
                targets["temperature"] = f"INS_GYR{s}_ID"
            for k, name in targets.items():
                put(k, name)
        elif inst.name in MAG_NAMES:
            put(stream, f"COMPASS_DEV_ID{s}")
        elif inst.name in BARO_NAMES:
            put(stream, f"BARO{inst.instance + 1}_DEVID")
    return found


def euler_quaternion(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (w, x, y, z) of Z-Y-X Euler angles (rad): the rotation body ->
    NED of an aerospace roll, pitch, yaw (``q = q_z(yaw) q_y(pitch) q_x(roll)``)."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.column_stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def _first_instance(f: DataFlashLog, name: str) -> np.ndarray | None:
    """Rows of instance 0 of message ``name`` (all rows when it has no instance field)."""
    fmt = f.by_name.get(name)
    if fmt is None or fmt.dtype() is None or len(f.records(name)) == 0:
        return None
    for column in ("I", "Instance", "Inst"):
        if fmt.numeric(column):
            return np.flatnonzero(f.records(name)[column] == 0)
    return np.arange(len(f.records(name)))


def flight_streams(f: DataFlashLog) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The flight streams the log holds (see :data:`~imupipe.readers.table.FLIGHT_COLUMNS`),
    stream -> (t_ns, values), in SI units and degrees of latitude/longitude:

    - ``attitude`` from ``ATT`` ``Roll``/``Pitch``/``Yaw`` (degrees, or centidegrees of format
      ``c``/``C`` that :meth:`DataFlashLog.field` scales to degrees), as quaternions;
    - ``position`` from ``GPS`` instance 0 ``Lat``/``Lng`` (1e-7 deg, format ``L``) and ``Alt``
      (cm of format ``e`` in older firmware, m of format ``f``), the records with a 3D fix
      (``Status`` >= 3) only, stamped by ``TimeUS`` (or, in 3.3 and older whose ``TimeMS`` is
      the GPS time of week, by the boot time ``T``, ms);
    - ``current`` from ``BAT`` instance 0 ``Curr`` (A) or, in older logs, ``CURR`` ``Curr``
      (A as a float; centiamperes as an int16 ``h``, ArduCopter 3.2-3.3);
    - ``throttle`` from a copter's ``CTUN`` ``ThO`` (0..1, ``motors->get_throttle()``, the value
      ``Copter::update_batt_compass`` hands to ``Compass::set_throttle`` for the throttle-based
      motor compensation, ``COMPASS_MOTCT = 1``) or, in ArduCopter 3.2-3.3, ``ThrOut`` (an int16
      0..1000, ``rc_3.servo_out``, which that firmware divides by 1000). Only a copter's
      ``CTUN`` (the one with ``ThI``/``ThrIn`` beside it): a plane's ``CTUN.ThO`` is a percentage
      of another output and its compass takes no throttle.
    """
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    rows = _first_instance(f, "ATT")
    if rows is not None and f.by_name["ATT"].numeric("Roll", "Pitch", "Yaw"):
        t = f.time_ns("ATT", rows)
        if t is not None:
            roll, pitch, yaw = (
                np.radians(f.field("ATT", c, rows)) for c in ("Roll", "Pitch", "Yaw")
            )
            out["attitude"] = (t, euler_quaternion(roll, pitch, yaw))
    rows = _first_instance(f, "GPS")
    if rows is not None and f.by_name["GPS"].numeric("Lat", "Lng", "Alt"):
        if f.by_name["GPS"].numeric("Status"):
            rows = rows[f.records("GPS")["Status"][rows] >= 3]
        t = f.time_ns("GPS", rows)
        if f.by_name["GPS"].numeric("Week", "T"):  # 3.3 and older: TimeMS is GPS time of week
            t = f.records("GPS")["T"][rows].astype(np.int64) * 1_000_000
        if t is not None and len(rows):
            lla = np.column_stack([f.field("GPS", c, rows) for c in ("Lat", "Lng", "Alt")])
            out["position"] = (t, lla)
    for name in ("BAT", "CURR"):
        rows = _first_instance(f, name)
        if rows is None or not f.by_name[name].numeric("Curr"):
            continue
        t = f.time_ns(name, rows)
        if t is None:
            continue
        fmt = f.by_name[name]
        amps = f.field(name, "Curr", rows)
        if fmt.format[fmt.columns.index("Curr")] in "hHiI":
            amps = amps * 0.01  # centiamperes (AP_Battery's old CURR: current_amps * 100)
        out["current"] = (t, amps)
        break
    throttle = _copter_throttle(f)
    if throttle is not None:
        out["throttle"] = throttle
    return out


def _copter_throttle(f: DataFlashLog) -> tuple[np.ndarray, np.ndarray] | None:
    """(t_ns, throttle 0..1) of a copter's ``CTUN`` (see :func:`flight_streams`); None without."""
    fmt = f.by_name.get("CTUN")
    if fmt is None:
        return None
    if fmt.numeric("ThO", "ThI"):
        column, scale = "ThO", 1.0
    elif fmt.numeric("ThrOut", "ThrIn"):
        column, scale = "ThrOut", 1e-3
    else:
        return None
    rows = np.arange(len(f.records("CTUN")))
    t = f.time_ns("CTUN", rows)
    if t is None or not len(rows):
        return None
    if fmt.format[fmt.columns.index(column)] not in "hHiI":
        scale = 1.0  # a float ThrOut: already 0..1
    return t, f.field("CTUN", column, rows) * scale


GPS_EPOCH_UNIX_S = 315_964_800
"""1980-01-06 00:00:00 UTC, the start of GPS week 0, in Unix seconds."""


def gps_year(f: DataFlashLog) -> float | None:
    """The decimal year (UTC, leap seconds ignored) of the first ``GPS`` record with a 3D fix,
    from its week (``GWk``, old ``Week``) and time of week (``GMS``, old ``TimeMS``, ms); None
    without one."""
    rows = _first_instance(f, "GPS")
    if rows is None:
        return None
    fmt = f.by_name["GPS"]
    week = next((c for c in ("GWk", "Week") if fmt.numeric(c)), None)
    ms = "GMS" if fmt.numeric("GMS") else "TimeMS"
    if week is None or not fmt.numeric(ms):
        return None
    rec = f.records("GPS")[rows]
    ok = rec[week] > 0
    if fmt.numeric("Status"):
        ok &= rec["Status"] >= 3
    if not ok.any():
        return None
    i = int(np.flatnonzero(ok)[0])
    unix = GPS_EPOCH_UNIX_S + int(rec[week][i]) * 604_800 + int(rec[ms][i]) / 1000.0
    return 1970.0 + unix / (365.2425 * 86400.0)


def dataflash_sources(path: Path) -> list[DataFlashLog]:
    """The one source of a DataFlash log (the ``log_sources`` entry)."""
    return [DataFlashLog(path)]


CALIBRATION_PREFIXES = ("INS_", "COMPASS_", "AHRS_ORIENTATION", "AHRS_TRIM", "BARO", "TCAL")
"""The parameters kept in the table's metadata and shown by ``inspect``: IMU and compass
calibration, board orientation and trim, barometer, temperature calibration."""


def raw_instances(path: Path) -> dict[str, list[str]]:
    """Kind -> the log's sensor instances (instance order): ``imu`` the ``IMU`` instances with
    gyro and accel, ``mag`` the ``MAG`` ones, ``baro`` the ``BARO`` ones with a temperature and
    a pressure, ``temperature`` those with a temperature; the names the topic keys take."""
    f = DataFlashLog(path)
    cands = candidates(f)
    baro = [
        k
        for k in cands["temperature"]
        if f.instances[k].name in BARO_NAMES and _has(f, f.instances[k], "Press")
    ]
    return {
        "imu": cands["imu"],
        "mag": cands["mag"],
        "baro": baro,
        "temperature": cands["temperature"],
    }


def calibration_parameters(f: DataFlashLog) -> dict[str, float]:
    """The log's calibration-related parameters at start (:data:`CALIBRATION_PREFIXES`)."""
    return {k: v for k, v in f.parameters().items() if k.startswith(CALIBRATION_PREFIXES)}


def describe(spec: InputSpec) -> dict[str, Any]:
    """What ``inspect`` shows beyond the messages: the instance of every message instance, the
    streams a read would fill and why not, and the calibration parameters (the shape of
    :func:`imupipe.readers.ulog.reader.describe`)."""
    f = DataFlashLog(spec.path)
    try:
        chosen, warnings = choose_topics(spec, f)
        error = None
    except ReadError as exc:
        chosen, warnings, error = {}, [], str(exc)
    return {
        "instances": {
            k: {"topic": v.name, "instance": v.instance, "device_id": None}
            for k, v in f.instances.items()
        },
        "chosen": chosen,
        "device_id": {s: None for s in chosen},
        "samples": {s: len(f.instances[k]) for s, k in chosen.items()},
        "warnings": warnings + _warnings(f),
        "selection_error": error,
        "calibrated": {s: True for s in chosen if s != "temperature"},
        "parameters": calibration_parameters(f),
        "parameters_of": "ArduPilot",
    }
