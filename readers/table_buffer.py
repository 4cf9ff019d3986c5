"""Decoded messages into the common table, each value copied once into its final column.

The readers promise one order (see :mod:`imupipe.readers.decoded`): per stream, messages in log
order, then sorted stably by the chosen time; the streams merged stably by time (at equal times:
imu, mag, temperature); out-of-order and repeated stamps counted and warned about, none dropped.

:class:`TableBuffer` takes a log chunk by chunk and keeps each stream's messages in the order
they come, in columns allocated once from the message counts the log states (grown by doubling
when it states none). The largest stream (the IMU, typically) is written straight into the
table's own columns, which have room for every stream's rows. At the end, when every stream is
already in order (the common case), the streams are merged without sorting: a message's row is
its index plus the number of the other streams' messages before it (``searchsorted``); the large
stream's columns are then spread to their rows in place, block by block from the end, and the
other streams' values are scattered into theirs. A log with a 1 Hz temperature topic beside
its IMU thus costs about what the IMU alone costs, whether the log interleaves the topics in its
chunks or writes each topic in chunks of its own. A stream out of order is put in order with
one permutation of the whole table.

Columns are allocated zeroed by the kernel, page by page on first write: a value column in
which every message so far carried zeros (unknown covariances, an Imu without orientation) is
not written at all and costs neither a copy nor a page fault, until a message brings a value
that is not zero.

A piece the compiled MCAP pass made (:class:`~imupipe.readers.chunk_fill.RecordPiece`) still
has its values in the decompressed chunk: they are written into the columns by one C call per
piece (:func:`~imupipe.readers.chunk_fill.fill`, the zero check folded in), the same bytes as
the copies of the numpy path. A table of one stream (whose next rows are known before a
piece's times are looked at) takes each chunk's values right after the chunk's decompression,
while its bytes are in the core's cache (:meth:`TableBuffer.prefill`, from
:meth:`imupipe.readers.mcap.reader.McapSource.chunks`); :meth:`_Stream.add` then writes the
piece's times only, or fills its values again where it lands elsewhere.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from imupipe.readers import chunk_fill
from imupipe.readers.arrays import arrow_array, string_array
from imupipe.readers.decoded import Piece, absent_sensors, repeat_string
from imupipe.readers.table import COV, META_KEY, SCHEMA, metadata_bytes, null_floats
from imupipe.readers.topics import COLUMNS, PIECE_TYPES

if TYPE_CHECKING:
    from imupipe.readers.prefault import Prefault

SPREAD_ROWS = 1 << 15
"""Rows moved per step when a column is spread to its rows in place."""
PREFAULT_ROWS = 1 << 16
"""Columns of at least this many rows have their pages mapped by a helper thread."""
ORDER = {s: i for i, s in enumerate(PIECE_TYPES)}
"""At equal times, the streams' rows in this order."""
TIME_COLUMNS = {"log_time_ns": "log", "header_stamp_ns": "stamp", "publish_time_ns": "pub"}
"""The table's int64 per-message columns besides ``t_ns``, in their order: column ->
:class:`Piece` attribute. ``header_stamp_ns`` only with ``time = "log"`` (else it is ``t_ns``);
``publish_time_ns`` only when the log has publish times (MCAP; where a message has none, its log
time stands in)."""


HUGE_BYTES = 1 << 22
"""numpy asks for transparent huge pages on allocations of at least this many bytes
(``_npy_alloc_cache``, numpy/_core/src/multiarray/alloc.c): smaller ones need no
:func:`small_pages`."""
_SCHEMA_FIELDS = list(SCHEMA)
"""The required fields, built once (iterating a schema builds each field: 8-13 us a table)."""
_SCHEMA_NAMES = frozenset(SCHEMA.names)
_FIELDS: dict[str, pa.Field] = {}
"""The optional fields the tables have had, by name (one ``pa.field`` each; hashing a
``pa.DataType`` costs more than the field)."""


def _field(name: str, typ: pa.DataType) -> pa.Field:
    found = _FIELDS.get(name)
    if found is None or not found.type.equals(typ):
        found = _FIELDS[name] = pa.field(name, typ)
    return found


@contextlib.contextmanager
def small_pages() -> Iterator[None]:
    """numpy allocations without its transparent-huge-page hint.

    numpy asks the kernel for huge pages on large arrays. On the 2-core test machine (a VM
    whose free 2 MiB blocks are reported to the host, ``page_reporting_order`` 9) a huge page
    is such a block, whose first touch most likely faults it back in from the host: filling
    364 MB cost 0.29-0.54 s of kernel time with huge pages (once 0.04 s) against 0.13-0.16 s with
    4 KiB pages, with no compaction stall counted (``compact_stall`` 0); a fresh 1M-message read
    once took 0.9 s instead of 0.4 s. Columns that are filled once, sequentially, gain nothing
    from huge pages."""
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


def _zeros(n: int, count: int = 1, dtype: type = np.float64) -> np.ndarray:
    """``np.zeros`` of ``n`` rows (of ``count`` values each) in small pages (see
    :func:`small_pages`, only where numpy would ask for huge ones)."""
    shape = n if count == 1 else (n, count)
    if n * count * np.dtype(dtype).itemsize < HUGE_BYTES:
        return np.zeros(shape, dtype)
    with small_pages():
        return np.zeros(shape, dtype)


class _Stream:
    """One stream's messages in the order they come: times, values, frame_ids."""

    def __init__(self, stream: str, capacity: int, time: str = "header") -> None:
        self.stream = stream
        self.m = 0
        self.capacity = -1
        self.times: dict[str, np.ndarray] = {}
        """``t_ns`` (the chosen time) and :data:`TIME_COLUMNS`, int64; a column of
        :attr:`alias` is the same array as the one it equals."""
        self.time_names = ["t_ns", "log_time_ns"] + (["header_stamp_ns"] if time == "log" else [])
        self.alias = {name: "t_ns" for name in self.time_names[1:]}
        """Time columns equal, row for row, to an earlier one so far (name -> that column, which
        is in no alias itself): one array holds both, written once (an MCAP's log and publish
        times, a writer's header stamps). The first message that differs gives the column an
        array of its own (:meth:`_keep_aliases`); the table's Arrow columns of both then share
        one buffer, the same values. Before any message every time column is taken as
        ``t_ns``'s."""
        self.columns: dict[str, np.ndarray] = {}
        self.flags: dict[str, np.ndarray] = {}
        """Imu only: per sensor (gyro, accel), the messages that mark it "no data" (NaN with
        covariance[0] = -1, see :func:`imupipe.readers.decoded.absent_sensors`): null there."""
        self.seen: set[str] = set()
        """The value columns the messages carried (a ULog has no covariances)."""
        self.clean = {name for name, _, _ in COLUMNS[stream]}
        """The value columns in which every message so far carried zeros, bit for bit (a
        driver's unknown covariances): never written, so that their pages are never touched
        (see :meth:`add`)."""
        self.frames: list[pa.Array] = []
        self.one_frame: str | None = None
        """The frame_id of every message so far, when the decoder said each piece had one and
        they are the same (None: several or unknown)."""
        self.t_sorted = self.log_sorted = True
        self.last_t = self.last_log = -(2**63)
        self.end = 0
        """One past the last row written (rows may have gaps: see :class:`TableBuffer`)."""
        self.prefault: Prefault | None = None
        self.ahead = 0
        """Rows after :attr:`end` whose values :meth:`prefill` wrote, for pieces not added yet."""
        self.generation = 0
        """Counts the column allocations (:meth:`reserve`): a piece filled into older columns
        is filled again."""
        self.reserve(capacity)

    def reserve(self, capacity: int) -> None:
        """Room for ``capacity`` messages (the rows so far kept)."""
        if capacity <= self.capacity:
            return
        end = self.end
        times: dict[str, np.ndarray] = {}
        for name in self.time_names:  # :attr:`alias` targets come first (earlier names)
            src = self.alias.get(name)
            times[name] = times[src] if src is not None else _zeros(capacity, dtype=np.int64)
        columns = {name: _zeros(capacity, count) for name, _, count in COLUMNS[self.stream]}
        flags = {name: np.zeros(capacity, bool) for name in self.flags}
        if end:
            for old, new in ((self.times, times), (self.columns, columns), (self.flags, flags)):
                for name, column in new.items():
                    # a clean column is zeros: so is the new one; an alias is its target
                    if name not in self.clean and name not in self.alias:
                        column[:end] = old[name][:end]
        self.times, self.columns, self.flags = times, columns, flags
        self.capacity = capacity
        self.generation += 1
        self.close()
        if capacity >= PREFAULT_ROWS:
            from imupipe.readers.prefault import Prefault  # large tables only (issue 39)

            self.prefault = Prefault([*_distinct(times.values()), *self._written(columns)])
            self.prefault.advance(end)

    def prefill(self, piece: Piece) -> bool:
        """Write the values of ``piece`` (a piece of the compiled walk, values still in its
        chunk) into the columns now, at the rows it takes if it is the next piece added after
        those already prefilled: while its chunk is in the core's cache (a group of chunks
        walked and filled after four decompressions comes from L3: 0.03-0.04 s more per
        million Imu messages, issue 39). :meth:`add` then writes its times and skips the
        values; a piece added elsewhere (not expected: checked) is filled again there, which
        overwrites these rows as the piece added there writes them. False (nothing written)
        when the piece has no chunk values or does not fit in the columns."""
        records = getattr(piece, "records", None)
        k = len(piece)
        row = self.end + self.ahead
        if records is None or row + k > self.capacity or k == 0:
            return False
        written, nan = chunk_fill.fill(
            records, self.columns, self.clean, [(slice(0, k), slice(row, row + k))]
        )
        self._now_written(written, row)
        piece.filled = (row, self.generation, nan)  # type: ignore[attr-defined]
        self.ahead += k
        return True

    def _now_written(self, names: Iterable[str], row: int) -> None:
        """Columns ``names`` hold a value from ``row`` on: no longer all zeros (:attr:`clean`),
        and their pages mapped ahead from there (:attr:`prefault`)."""
        for name in names:
            self.clean.discard(name)
            if self.prefault is not None:
                self.prefault.add(self.columns[name], row)

    def _written(self, arrays: dict[str, np.ndarray]) -> list[np.ndarray]:
        return [column for name, column in arrays.items() if name not in self.clean]

    def add_time(self, name: str) -> None:
        """Start keeping ``name`` (publish times): the messages so far get their log time (an
        :attr:`alias` of the log times until a message brings other values)."""
        if name not in self.times:
            self.time_names.append(name)
            src = self.alias.get("log_time_ns", "log_time_ns")
            self.alias[name] = src
            self.times[name] = self.times[src]

    def _keep_aliases(self, values: dict[str, np.ndarray]) -> None:
        """Keep the :attr:`alias` of each time column whose ``values`` (of the piece being
        added) equal its target's; the others get an array of their own: the rows so far copied
        from the target (none before the first message, when another equal column is taken
        as the target instead, if any)."""
        for i, name in enumerate(self.time_names):
            src = self.alias.get(name)
            if src is None or _same(values[name], values[src]):
                continue
            del self.alias[name]
            if self.end == 0:
                roots = [s for s in self.time_names[:i] if s not in self.alias]
                src = next((s for s in roots if _same(values[name], values[s])), None)
                if src is not None:
                    self.alias[name] = src
                    self.times[name] = self.times[src]
                    continue
            column = _zeros(self.capacity, dtype=np.int64)
            column[: self.end] = self.times[name][: self.end]
            self.times[name] = column
            if self.prefault is not None:
                self.prefault.add(column, self.end)

    def unalias(self, keep: Callable[[str, str], bool]) -> None:
        """Give each time column of :attr:`alias` for which ``keep(name, target)`` is false an
        array of its own (the same values)."""
        for name, src in list(self.alias.items()):
            if not keep(name, src):
                del self.alias[name]
                self.times[name] = self.times[src].copy()

    @property
    def t(self) -> np.ndarray:
        return self.times["t_ns"]

    @property
    def log(self) -> np.ndarray:
        return self.times["log_time_ns"]

    def close(self) -> None:
        """Stop mapping pages ahead (the columns are complete)."""
        if self.prefault is not None:
            self.prefault.close()
            self.prefault = None

    def arrays(self) -> list[np.ndarray]:
        """Every per-row array that holds values (times, values, flags), each once, for moving
        rows: the clean columns are zeros wherever rows move."""
        return [*_distinct(self.times.values()), *self._written(self.columns), *self.flags.values()]

    def add(self, piece: Piece, t: np.ndarray, at: slice | np.ndarray | Runs | None = None) -> None:
        """Append ``piece`` (``t``: its chosen times) at rows ``at`` (default: the next rows).

        A value column whose values are all zeros (bit for bit) so far is not written: its
        memory came zeroed from the kernel, and pages never written are never mapped (a log
        whose covariances are unknown fills 216 fewer bytes per Imu message)."""
        k = len(piece)
        if k == 0:
            return
        if at is None:
            if self.end + k > self.capacity:
                self.reserve(max(self.end + k, 2 * self.capacity, 1 << 12))
            at = slice(self.end, self.end + k)
        self.t_sorted = self.t_sorted and _follows(self.last_t, t, piece)
        self.log_sorted = self.log_sorted and _follows(self.last_log, piece.log, piece)
        self.last_t, self.last_log = (
            max(self.last_t, int(t[-1])),
            max(self.last_log, int(piece.log[-1])),
        )
        if piece.pub is not None:
            self.add_time("publish_time_ns")
        values = {"t_ns": t}
        for name in self.time_names[1:]:
            value = getattr(piece, TIME_COLUMNS[name])
            values[name] = piece.log if value is None else value
        if self.alias:
            self._keep_aliases(values)
            for name in self.alias:
                del values[name]  # its target's array, written once
        first = _first_row(at)
        records = getattr(piece, "records", None)
        runs = None if records is None else _runs(at)
        filled = getattr(piece, "filled", None)
        if filled is not None:
            self.ahead = max(0, self.ahead - k)
            if filled[:2] != (first, self.generation) or len(runs or ()) != 1:
                filled = None  # filled elsewhere: filled again here
        if filled is not None:  # the values are in their rows already (prefill)
            nan = filled[2]
            self.seen.update(records.names)  # type: ignore[union-attr]
        elif runs is not None and all(isinstance(rows, slice) for _, rows in runs):
            # the compiled pass: the chunk's values straight into the columns (chunk_fill)
            written, nan = chunk_fill.fill(records, self.columns, self.clean, runs)  # type: ignore[arg-type]
            self._now_written(written, first)
            self.seen.update(records.names)  # type: ignore[union-attr]
        else:
            nan = None
            for name, column in piece.columns.items():
                if name in self.clean:
                    if _zeros_only(column):
                        continue
                    self._now_written([name], first)
                values[name] = column
            self.seen.update(piece.columns)
        if self.stream == "imu" and nan != set():  # no NaN in the vectors: nothing marked
            for name, marked in absent_sensors(piece).items():
                if name not in self.flags:
                    self.flags[name] = np.zeros(self.capacity, bool)
                values[f"flag_{name}"] = marked
        targets = {**self.times, **self.columns, **{f"flag_{k}": v for k, v in self.flags.items()}}
        for run, rows in _runs(at):
            for name, column in values.items():
                targets[name][rows] = column[run]
        if self.m == 0 or piece.one_frame != self.one_frame:
            self.one_frame = piece.one_frame if self.m == 0 else None
        self.frames.append(piece.frame)
        self.m += k
        last = at[-1][1] if isinstance(at, list) else at
        self.end = max(self.end, last.stop if isinstance(last, slice) else int(last[-1]) + 1)
        if self.prefault is not None:
            self.prefault.advance(self.end)

    def frame(self) -> pa.Array:
        if not self.frames:
            return string_array([])
        if self.one_frame is not None and len(self.frames) > 1:
            return repeat_string(self.one_frame, self.m)  # the same as joining them
        return self.frames[0] if len(self.frames) == 1 else pa.concat_arrays(self.frames)


Runs = list[tuple[slice, slice]]
"""(values, rows) slice pairs: where runs of consecutive values go."""


def _distinct(arrays: Iterable[np.ndarray]) -> list[np.ndarray]:
    """``arrays`` without repeats of one array (:attr:`_Stream.alias`)."""
    out: list[np.ndarray] = []
    for array in arrays:
        if not any(array is kept for kept in out):
            out.append(array)
    return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the int64 times ``a`` and ``b`` are equal, value for value."""
    return a is b or (len(a) == len(b) and bool((a == b).all()))


def _zeros_only(column: np.ndarray) -> bool:
    """Every value of ``column`` (float64, any strides) is +0.0, bit for bit."""
    bits = column.view(np.uint64)
    return not bits[(0,) * bits.ndim] and not bits.max()  # max: no cast to bool


def _first_row(at: slice | np.ndarray | Runs) -> int:
    """The first row ``at`` writes."""
    if isinstance(at, list):
        at = at[0][1]
    return at.start if isinstance(at, slice) else int(at[0])


RUN_MESSAGES = 256
"""Rows for a piece are passed as runs of consecutive rows (slices; the compiled fill takes
them) while the runs hold this many messages on average, or there are at most 16 of them; else
as one index array. A group of chunks (:meth:`imupipe.readers.mcap.reader.McapSource.chunks`)
of 12,000 Imu messages beside a 1 Hz topic has ~30 gaps."""


def _most_runs(k: int) -> int:
    """The most gaps a piece of ``k`` messages is written in runs with (:data:`RUN_MESSAGES`)."""
    return max(16, k // RUN_MESSAGES)


def _runs(at: slice | np.ndarray | Runs) -> list[tuple[slice, slice | np.ndarray]]:
    """``at`` (rows for consecutive values) as (values, rows) pairs: slices for each run of
    consecutive rows when there are few runs (a slow topic's gaps, :func:`_most_runs`), else
    one index array."""
    if isinstance(at, list):
        return at  # type: ignore[return-value]
    if isinstance(at, slice):
        return [(slice(0, at.stop - at.start), at)]
    breaks = np.flatnonzero(at[1:] - at[:-1] != 1) + 1
    if len(breaks) > _most_runs(len(at)):
        return [(slice(0, len(at)), at)]
    edges = [0, *breaks.tolist(), len(at)]
    return [
        (slice(a, b), slice(int(at[a]), int(at[a]) + b - a))
        for a, b in zip(edges[:-1], edges[1:], strict=True)
    ]


def _follows(last: int, new: np.ndarray, piece: Piece | None = None) -> bool:
    """``new`` is non-decreasing and starts at or after ``last`` (whether ``new``, times of
    ``piece``, never decreases is taken from the piece when it knows: the compiled walk,
    :class:`~imupipe.readers.chunk_fill.RecordPiece`)."""
    if new[0] < last:
        return False
    for times, ordered in getattr(piece, "ordered", ()):
        if times is new:
            return ordered
    return len(new) < 2 or bool(np.all(new[1:] >= new[:-1]))


def _merge_rows(times: list[np.ndarray]) -> list[np.ndarray]:
    """The table row of every message of each stream, for streams each sorted by time, merged
    stably (at equal times the earlier stream first): its index plus the number of the other
    streams' messages before it."""
    rows = []
    for i, t in enumerate(times):
        row = np.arange(len(t), dtype=np.int64)
        for j, other in enumerate(times):
            if j == i or not len(other):
                continue
            if len(other) * 16 < len(t):  # few: where each lands in t, then a running count
                lands = np.searchsorted(t, other, side="left" if j < i else "right")
                row += np.cumsum(np.bincount(lands, minlength=len(t) + 1))[: len(t)]
            else:
                row += np.searchsorted(other, t, side="right" if j < i else "left")
        rows.append(row)
    return rows


def _spread(columns: list[np.ndarray], rows: np.ndarray) -> None:
    """Move ``column[:len(rows)]`` to ``column[rows]`` in place for each column (``rows``
    increasing, each >= its index), from the end so that no value is overwritten before it is
    read: run by run when few runs move (a slow topic beside the IMU), else block by block."""
    m = len(rows)
    moved = np.flatnonzero(rows != np.arange(m))
    if not len(moved):
        return
    first = int(moved[0])
    jumps = np.flatnonzero(rows[first + 1 :] - rows[first:-1] != 1) + first + 1
    if len(jumps) < m // 256:
        starts = [first, *jumps.tolist()]
        ends = [*jumps.tolist(), m]
        targets = rows[starts].tolist()
        for column in columns:
            for a, b, to in zip(starts[::-1], ends[::-1], targets[::-1], strict=True):
                column[to : to + b - a] = column[a:b]
        return
    for column in columns:
        for b in range(m, first, -SPREAD_ROWS):
            a = max(first, b - SPREAD_ROWS)
            column[rows[a:b]] = column[a:b].copy()


def _unclaimed(m: int, rows: np.ndarray) -> np.ndarray:
    """Indices below ``m`` that ``rows`` does not hold: what a spread leaves stale."""
    held = np.zeros(m, bool)
    held[rows[rows < m]] = True
    return np.flatnonzero(~held)


class TableBuffer:
    """The common table of the streams ``streams`` being filled chunk by chunk (see the module
    docstring). ``time`` is ``header`` (t_ns = header stamps) or ``log``; ``counts`` the
    messages per stream the log states (None: unknown)."""

    def __init__(
        self, streams: Sequence[str], time: str, counts: Mapping[str, int] | None = None
    ) -> None:
        self.time = time
        names = [s for s in PIECE_TYPES if s in streams]
        counts = counts or {}
        total = sum(counts.get(s, 0) for s in names)
        self.large = max(names, key=lambda s: counts.get(s, 0)) if counts else None
        self.streams = {
            s: _Stream(s, total if s == self.large else counts.get(s, 0), time) for s in names
        }
        self.gapped = self.large is not None and len(names) > 1
        """The large stream is written at its rows in the table, leaving gaps for the other
        streams' messages (while every stream comes in time order)."""
        self._landed = np.zeros(1024, np.int64)
        self._n_landed = 0
        self.waiting: list[tuple[np.ndarray, bool]] = []
        """Times of the other streams' messages that come after every large-stream message so
        far, and whether they follow a large-stream message of the same time."""
        self.large_t = np.zeros(total if self.gapped else 0, np.int64)
        self.moved = 0
        self.full: dict[str, np.ndarray] = {}
        """The other streams' columns in the table, allocated (and mapped) with the large one."""
        self.full_prefault: Prefault | None = None
        if self.gapped:
            self.full = {
                name: _zeros(total, count)
                for s in names
                if s != self.large
                for name, _, count in COLUMNS[s]
            }
            if total >= PREFAULT_ROWS:  # each column once a message carries a value in it
                from imupipe.readers.prefault import Prefault  # large tables only (issue 39)

                self.full_prefault = Prefault([], rows=total)
        self.full_mapped: set[str] = set()
        """The columns of :attr:`full` given to the prefault thread."""

    def _t(self, piece: Piece) -> np.ndarray:
        return piece.stamp if self.time == "header" else piece.log

    def prefill(self, stream: str, piece: Piece) -> bool:
        """:meth:`_Stream.prefill` for a table of one stream (``stream``), whose next rows are
        known before the piece's times are looked at; False for any other table."""
        st = self.streams.get(stream)
        if st is None or len(self.streams) != 1 or self.gapped:
            return False
        return st.prefill(piece)

    def add(self, pieces: Mapping[str, Piece]) -> None:
        """Append one chunk's pieces (stream -> Piece), each stream in the order given."""
        if not self.gapped:
            for s, piece in pieces.items():
                self.streams[s].add(piece, self._t(piece))
            return
        for s, piece in pieces.items():  # the other streams first: they make room
            if s != self.large and len(piece):
                self._other(s, piece)
        piece = pieces.get(self.large)  # type: ignore[arg-type]
        if piece is not None and len(piece):
            self._large(piece)

    # -- the large stream at its rows, gaps for the others ---------------------------------
    def _other(self, s: str, piece: Piece) -> None:
        st = self.streams[s]
        t = self._t(piece)
        st.add(piece, t)
        if self.full_prefault is not None:  # a clean column (zeros so far) is never mapped
            for name in self.full.keys() - st.clean - self.full_mapped:
                if name in st.columns:
                    self.full_prefault.add(self.full[name], 0)
                    self.full_mapped.add(name)
        if not self.gapped:
            return
        if not st.t_sorted:
            self._ungap()
            return
        big = self.streams[self.large]  # type: ignore[index]
        after = ORDER[s] > ORDER[self.large]  # type: ignore[index]
        land = np.searchsorted(self.large_t[: big.m], t, side="right" if after else "left")
        inside = land < big.m
        if inside.any():
            self._make_room(land[inside])
        if self.gapped and not inside.all():
            self.waiting.append((t[~inside], after))

    def _large(self, piece: Piece) -> None:
        big = self.streams[self.large]  # type: ignore[index]
        t = self._t(piece)
        k, m = len(t), big.m
        if self.gapped and not _follows(big.last_t, t, piece):
            self._ungap()
        if not self.gapped:
            big.add(piece, t)
            return
        before = self._n_landed  # every message landed so far is before message m
        inner = np.zeros(0, np.int64)
        if self.waiting:  # messages waiting for their place among these
            still: list[tuple[np.ndarray, bool]] = []
            lands = []
            for wait, after in self.waiting:
                idx = np.searchsorted(t, wait, side="right" if after else "left")
                lands.append(m + idx[idx < k])
                if not (idx < k).all():
                    still.append((wait[idx >= k], after))
            new = np.sort(np.concatenate(lands))
            self._land(new)
            self.waiting = still
            before += int(np.count_nonzero(new == m))
            inner = new[new > m]
        # message m + j goes to row m + j + (the others' messages landed at or before it)
        if m + k + before + len(inner) > big.capacity:  # the log stated too few messages
            self._ungap()
            big.add(piece, t)
            return
        self.large_t[m : m + k] = t
        if len(inner) > _most_runs(k):
            i = np.arange(m, m + k)
            big.add(piece, t, i + np.searchsorted(self.landed, i, side="right"))
            return
        runs = []
        a, offset = m, before
        for v, c in zip([*inner.tolist(), m + k], [*([1] * len(inner)), 0], strict=True):
            if v > a:
                runs.append((slice(a - m, v - m), slice(a + offset, v + offset)))
            offset += c
            a = v
        big.add(piece, t, runs)
        if self.full_prefault is not None:
            self.full_prefault.advance(big.end)

    def _make_room(self, lands: np.ndarray) -> None:
        """Move the large stream's messages from ``min(lands)`` on to make room for messages
        of the other streams that come before them."""
        big = self.streams[self.large]  # type: ignore[index]
        m = big.m
        i = np.arange(int(lands.min()), m)
        src = i + np.searchsorted(self.landed, i, side="right")
        landed = np.sort(np.concatenate([self.landed, lands]))  # (rare: the others came late)
        dst = i + np.searchsorted(landed, i, side="right")
        self.moved += len(i)
        if dst[-1] >= big.capacity or self.moved > 2 * big.capacity:
            self._ungap()  # too many messages, or too much moving: merge at the end instead
            return
        arrays = big.arrays()
        for b in range(len(i), 0, -SPREAD_ROWS):  # from the end: nothing overwritten unread
            a = max(0, b - SPREAD_ROWS)
            for array in arrays:
                array[dst[a:b]] = array[src[a:b]]
        vacated = np.setdiff1d(np.arange(src[0], dst[-1] + 1), dst, assume_unique=True)
        for array in arrays:
            array[vacated] = 0
        self._n_landed = 0
        self._land(landed)
        big.end = max(big.end, int(dst[-1]) + 1)

    @property
    def landed(self) -> np.ndarray:
        """For each message of the other streams placed among the large stream's: the index of
        the large stream's first message after it (sorted)."""
        return self._landed[: self._n_landed]

    def _land(self, values: np.ndarray) -> None:
        """Append landings (sorted, none below the last)."""
        n = self._n_landed + len(values)
        if n > len(self._landed):
            grown = np.zeros(max(n, 2 * len(self._landed)), np.int64)
            grown[: self._n_landed] = self.landed
            self._landed = grown
        self._landed[self._n_landed : n] = values
        self._n_landed = n

    def _rows(self) -> np.ndarray:
        """The rows the large stream's messages are written at."""
        i = np.arange(self.streams[self.large].m)  # type: ignore[index]
        return i + np.searchsorted(self.landed, i, side="right")

    def _ungap(self) -> None:
        """Close the large stream's gaps: its messages one after the other again."""
        if not self.gapped:
            return
        self.gapped = False
        big = self.streams[self.large]  # type: ignore[index]
        rows = self._rows()
        moved = np.flatnonzero(rows != np.arange(len(rows)))
        if len(moved):
            arrays = big.arrays()
            for a in range(int(moved[0]), len(rows), SPREAD_ROWS):  # from the front
                b = min(len(rows), a + SPREAD_ROWS)
                for array in arrays:
                    array[a:b] = array[rows[a:b]]
            for array in arrays:
                array[big.m : big.end] = 0
        big.end = big.m
        self._n_landed, self.waiting = 0, []

    def _stream_t(self, st: _Stream) -> np.ndarray:
        """A stream's chosen times in the order its messages came."""
        return self.large_t[: st.m] if self.gapped and st.stream == self.large else st.t[: st.m]

    def __len__(self) -> int:
        return sum(st.m for st in self.streams.values())

    # -- order -----------------------------------------------------------------------------
    def _within(self, st: _Stream) -> tuple[np.ndarray, int]:
        """The promised order of one stream's messages (log order, then stably by time) and how
        many messages it moves."""
        order = np.arange(st.m)
        if not st.log_sorted:
            order = np.argsort(st.log[: st.m], kind="stable")
        by_time = np.argsort(st.t[: st.m][order], kind="stable")
        moved = int(np.count_nonzero(by_time != np.arange(st.m)))
        return order[by_time], moved

    def table(
        self,
        *,
        sort: bool,
        source: str,
        fmt: str,
        topics: Mapping[str, str],
        where: str,
        warnings: list[str],
        counts: dict[str, list[int]] | None = None,
    ) -> pa.Table:
        """The common table of what was added (the buffer is emptied).

        ``sort``: the promised order, with warnings; else only a stable merge of the streams
        by time, each stream kept in log order (the batches of the streaming path). ``counts``
        (topic -> [messages out of time order, messages repeating the previous stamp]): where
        the same counts as the warnings' are added up, the warnings left to the caller
        (:func:`order_warnings`), e.g. once per topic over a streamed log's batches."""
        streams = list(self.streams.values())
        for st in streams:
            st.close()
        if self.full_prefault is not None:
            self.full_prefault.close()
        if any("publish_time_ns" in st.times for st in streams):
            for st in streams:  # a stream without publish times: its log times stand in
                st.add_time("publish_time_ns")
        n = len(self)
        in_order = all(st.t_sorted for st in streams)
        if sort or counts is not None:  # counting needs each stream's log order
            in_order = in_order and all(st.log_sorted for st in streams)
        if not in_order:
            self._ungap()
        within: list[np.ndarray | None] = [None] * len(streams)
        if sort or counts is not None:
            tally = {} if counts is None else counts
            for i, st in enumerate(streams):
                order, moved = (None, 0) if in_order else self._within(st)
                if sort:
                    within[i] = order
                t = self._stream_t(st) if order is None else st.t[: st.m][order]
                dups = int(np.count_nonzero(t[1:] == t[:-1])) if st.m > 1 else 0
                both = tally.setdefault(topics[st.stream], [0, 0])
                both[0] += moved
                both[1] += dups
            if counts is None:
                warnings += order_warnings(where, self.time, tally)
        # each stream's frame_id: its first message's (in the table's order; batches: log order)
        frame_ids = {
            st.stream: st.one_frame
            if st.one_frame is not None
            else st.frame()[0 if order is None else int(order[0])].as_py()
            for st, order in zip(streams, within, strict=True)
            if st.m
        }
        if in_order:
            columns, times, frame = self._spread_all(streams, n)
        else:  # the batches of the streaming path: a stable sort by time, streams in order at ties
            frames = [st.frame() for st in streams]
            columns, times, frame = self._gather(streams, within, frames, n, lexsort=not sort)
        self.streams = {}
        arrays: dict[str, pa.Array] = {"t_ns": arrow_array(times.pop("t_ns"), pa.int64())}
        extra: dict[str, pa.Array] = {}
        for name, array in columns.items():
            (arrays if name in _SCHEMA_NAMES else extra)[name] = array
        empty = null_floats(n)
        fields = _SCHEMA_FIELDS + [_field(name, pa.int64()) for name in times]
        fields.append(_field("frame_id", pa.string()))
        values = [arrays.get(f.name, empty) for f in _SCHEMA_FIELDS]
        values += [arrow_array(column, pa.int64()) for column in times.values()] + [frame]
        for name, array in extra.items():
            fields.append(_field(name, COV if array.type == COV else pa.float64()))
            values.append(array)
        names = [st.stream for st in streams]
        meta = {
            "source": source,
            "format": fmt,
            "topics": {s: topics[s] for s in names},
            "types": {s: PIECE_TYPES[s] for s in names},
            "frame_id": frame_ids,
        }
        schema = pa.schema(fields, metadata={META_KEY: metadata_bytes(meta)})
        return pa.Table.from_arrays(values, schema=schema)

    # -- building the columns --------------------------------------------------------------
    def _gap_rows(self, streams: list[_Stream], large: int) -> list[np.ndarray | None] | None:
        """The rows of the other streams' messages when the large stream's gaps are theirs
        (None for the large stream), or None when they are not (cannot happen: checked)."""
        big = streams[large]
        others = [i for i in range(len(streams)) if i != large]
        merged = _merge_rows([streams[i].t[: streams[i].m] for i in others])
        rows: list[np.ndarray | None] = [None] * len(streams)
        for i, among in zip(others, merged, strict=True):
            st = streams[i]
            after = ORDER[st.stream] > ORDER[big.stream]
            land = np.searchsorted(
                self.large_t[: big.m], st.t[: st.m], side="right" if after else "left"
            )
            rows[i] = land + among
        waiting = sum(len(wait) for wait, _ in self.waiting)
        lands = np.concatenate([self.landed, np.full(waiting, big.m, np.int64)])
        gaps = np.sort(lands) + np.arange(len(lands))
        mine = np.sort(np.concatenate([rows[i] for i in others]))  # type: ignore[misc]
        return rows if np.array_equal(gaps, mine) else None

    def _spread_all(
        self, streams: list[_Stream], n: int
    ) -> tuple[dict[str, pa.Array], dict[str, np.ndarray], pa.Array]:
        """Columns of streams already in order, each message at its row of the merged order:
        the large stream's already there (gaps) or spread there in place."""
        names = [st.stream for st in streams]
        rows: list[np.ndarray | None] = []
        if self.gapped:
            large = names.index(self.large)  # type: ignore[arg-type]
            rows = self._gap_rows(streams, large) or []
            if not rows:
                self._ungap()
        if not self.gapped:
            large = max(range(len(streams)), key=lambda i: streams[i].m)
            rows = _merge_rows([st.t[: st.m] for st in streams]) if len(streams) > 1 else []  # type: ignore[assignment]
        big = streams[large]
        big.reserve(n)  # the table's own columns (already this size when the log stated counts)
        if len(streams) > 1 and not self.gapped:
            own = big.arrays()
            _spread(own, rows[large])  # type: ignore[arg-type]
            stale = _unclaimed(big.m, rows[large])  # type: ignore[arg-type]
            for column in own:
                column[stale] = 0
        if len(streams) > 1:  # the others' times go into the large one's: one array, equal
            big.unalias(
                lambda name, src: all(
                    _same(st.times[name][: st.m], st.times[src][: st.m])
                    for st in streams
                    if st is not big
                )
            )
        times = {name: c[:n] for name, c in big.times.items()}
        columns: dict[str, np.ndarray] = {name: c[:n] for name, c in big.columns.items()}
        flags = {name: c[:n] for name, c in big.flags.items()}
        if len(streams) == 1:
            return self._arrays(streams, columns, None, flags), times, streams[0].frame()
        stream_of_row = np.full(n, large, np.uint8)
        for i, (st, at) in enumerate(zip(streams, rows, strict=True)):
            if i == large:
                continue
            m = st.m
            for name, column in times.items():
                column[at] = st.times[name][:m]
            for name, _, count in COLUMNS[st.stream]:
                full = self.full.pop(name, None)
                full = full[:n] if full is not None and len(full) >= n else _zeros(n, count)
                values = st.columns.pop(name)[:m]
                if name not in st.clean:  # else zeros already, its pages never touched
                    full[at] = values
                columns[name] = full
            for name, flag in st.flags.items():
                flags[name] = np.zeros(n, bool)
                flags[name][at] = flag[:m]
            stream_of_row[at] = i
        frame = _frames(streams, rows, large, stream_of_row, self._rows)  # type: ignore[arg-type]
        return self._arrays(streams, columns, stream_of_row, flags), times, frame

    def _gather(
        self,
        streams: list[_Stream],
        within: list[np.ndarray | None],
        frames: list[pa.Array],
        n: int,
        lexsort: bool,
    ) -> tuple[dict[str, pa.Array], dict[str, np.ndarray], pa.Array]:
        """Columns of streams out of order: every row gathered through one permutation of the
        streams' messages one after the other (each in the order ``within`` gives)."""
        start = np.cumsum([0] + [st.m for st in streams])
        index = np.concatenate(
            [
                start[i] + (np.arange(st.m) if order is None else order)
                for i, (st, order) in enumerate(zip(streams, within, strict=True))
            ]
        )
        t_all = np.concatenate([st.t[: st.m] for st in streams])
        sid_all = np.repeat(np.arange(len(streams), dtype=np.uint8), [st.m for st in streams])
        if lexsort:
            perm = index[np.lexsort((sid_all[index], t_all[index]))]
        else:
            perm = index[np.argsort(t_all[index], kind="stable")]
        times = {
            name: np.concatenate([st.times[name][: st.m] for st in streams])[perm]
            for name in streams[0].times
        }
        stream_of_row = sid_all[perm] if len(streams) > 1 else None
        columns: dict[str, np.ndarray] = {}
        flags: dict[str, np.ndarray] = {}
        for i, st in enumerate(streams):
            at = np.flatnonzero(stream_of_row == i) if stream_of_row is not None else None
            for name, _, count in COLUMNS[st.stream]:
                values = st.columns.pop(name)[: st.m]
                if at is None:
                    columns[name] = values[perm]
                else:
                    full = _zeros(n, count)
                    if name not in st.clean:  # else zeros already, its pages never touched
                        full[at] = values[perm[at] - start[i]]
                    columns[name] = full
            for name, flag in st.flags.items():
                flags[name] = np.zeros(n, bool)
                if at is None:
                    flags[name] = flag[: st.m][perm]
                else:
                    flags[name][at] = flag[: st.m][perm[at] - start[i]]
        frame = pa.concat_arrays(frames).take(arrow_array(perm))
        return self._arrays(streams, columns, stream_of_row, flags), times, frame

    @staticmethod
    def _arrays(
        streams: list[_Stream],
        columns: dict[str, np.ndarray],
        stream_of_row: np.ndarray | None,
        flags: dict[str, np.ndarray],
    ) -> dict[str, pa.Array]:
        """Arrow columns of the value columns the messages carried, null where a row holds
        another stream's message (one validity bitmap per stream, shared by its columns) or
        where an Imu message marks the sensor "no data"."""
        out: dict[str, pa.Array] = {}
        for i, st in enumerate(streams):
            mine = None if stream_of_row is None else stream_of_row == i
            valid = None if mine is None else pa.py_buffer(np.packbits(mine, bitorder="little"))
            marked = {}
            for sensor, flag in flags.items():
                keep = ~flag if mine is None else mine & ~flag
                marked[sensor] = pa.py_buffer(np.packbits(keep, bitorder="little"))
            for name, _, _ in COLUMNS[st.stream]:
                values = columns.pop(name)
                if st.seen and name not in st.seen:
                    continue  # a column no message carried (a ULog's covariances)
                sensor = name.split("_")[0]
                own = marked.get(sensor) if name in _SCHEMA_NAMES else None
                out[name] = _array(values, valid if own is None else own)
        return out


def _frames(
    streams: list[_Stream],
    rows: list[np.ndarray | None],
    large: int,
    stream_of_row: np.ndarray,
    large_rows: Callable[[], np.ndarray],
) -> pa.Array:
    """The frame_id column of streams whose messages go to ``rows`` (``large_rows()`` for the
    large stream's where ``rows`` has None): one repeated string when every message has the
    same, a dictionary decode when each stream has one frame_id (a sensor's usual case), else
    one take."""
    ones = [st.one_frame for st in streams]
    if None not in ones and len(set(ones)) == 1:
        return repeat_string(ones[0], len(stream_of_row))  # type: ignore[arg-type]
    import pyarrow.compute as pc  # only here: its import costs 0.06-0.09 s CPU

    frames = [st.frame() for st in streams]
    firsts = [frame[0] if len(frame) else None for frame in frames]
    if all(
        one is not None or first is None or pc.all(pc.equal(frame, first)).as_py()
        for frame, first, one in zip(frames, firsts, ones, strict=True)
    ):
        values = string_array([f.as_py() if f is not None else "" for f in firsts])
        return pa.DictionaryArray.from_arrays(
            arrow_array(stream_of_row.view(np.int8)), values
        ).cast(pa.string())
    if rows[large] is None:
        rows[large] = large_rows()
    source = np.empty(len(stream_of_row), np.int64)  # row -> message of the streams in turn
    start = 0
    for frame, at in zip(frames, rows, strict=True):
        source[at] = np.arange(start, start + len(frame))
        start += len(frame)
    return pa.concat_arrays(frames).take(arrow_array(source))


def _array(values: np.ndarray, valid: pa.Buffer | None) -> pa.Array:
    """A float64 (n,) or fixed-size-list (n, 9) column, null where the bitmap ``valid`` says."""
    n = len(values)
    flat = pa.py_buffer(np.ascontiguousarray(values).reshape(-1))
    if values.ndim == 1:
        return pa.Array.from_buffers(pa.float64(), n, [valid, flat])
    child = pa.Array.from_buffers(pa.float64(), n * values.shape[1], [None, flat])
    typ = COV if values.shape[1] == 9 else pa.list_(pa.float64(), values.shape[1])
    return pa.Array.from_buffers(typ, n, [valid], children=[child])


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
    counts: dict[str, list[int]] | None = None,
) -> pa.Table:
    """The common table of the decoded ``pieces`` (stream -> Piece), all at once (``counts``:
    see :meth:`TableBuffer.table`)."""
    buffer = TableBuffer(list(pieces), time, {s: len(p) for s, p in pieces.items()})
    buffer.add(pieces)
    return buffer.table(
        sort=sort,
        source=source,
        fmt=fmt,
        topics=topics,
        where=where,
        warnings=warnings,
        counts=counts,
    )


def order_warnings(where: str, time: str, counts: Mapping[str, list[int]]) -> list[str]:
    """The readers' warnings about stamps out of order and repeated, from ``counts`` (topic ->
    [messages out of ``time`` order, messages repeating the previous stamp]), per topic."""
    out = []
    for topic, (moved, dups) in counts.items():
        if moved:
            out.append(
                f"{where} topic {topic}: {moved} messages out of {time} time order; "
                "sorted stably (none dropped)"
            )
        if dups:
            out.append(
                f"{where} topic {topic}: {dups} messages repeat the previous {time} stamp (kept)"
            )
    return out
