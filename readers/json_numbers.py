"""JSON messages that share one shape: their numbers found and parsed without parsing each message.

A JSON writer gives the messages of a channel the same text around their numbers (Foxglove's
SDKs and ``json.dumps`` of one dict per message: ``{"t": 17, "g": [0.01, -0.02, 0.03]}``): only
the numbers differ. :func:`decode_by_template` reads a batch of payloads (one decompressed
chunk) that way:

1. Where every run of number characters (``0-9 . e E + -``) ends is found in the whole chunk in a
   few numpy passes (into work arrays kept per thread: a fresh megabyte temporary costs more in
   page faults than the pass; the same holds for every large temporary below).
2. A *template* is a message parsed once by Python's ``json`` (the reference decoder of
   ``mcap``'s JSON channels), its numbers counted through ``parse_int`` / ``parse_float`` in text
   order. Its runs that start with a digit or ``-`` outside its strings (``"imu_1"`` is text)
   must be exactly its numbers, and every mapped leaf one of them: each leaf is then "the j-th
   number", and the text between numbers is known (a :class:`Shape`). The shapes of a channel's
   previous chunk are tried first (kept by the caller); then the first message no shape fits.
3. For every message, number j starts where the shape's text before it ends and ends where its
   run of number characters does (the runs between two numbers are the shape's: counted, not
   searched). The message has the shape when its text between the numbers is byte for byte the
   shape's (gathered one byte position at a time over all messages: a gather of unaligned 8-byte
   words costs about ten times one of bytes) and each number is one whole run; it is then valid
   JSON with the template's structure, provided each number follows the JSON grammar (RFC 8259,
   section 6). Checked here: a digit after a leading ``-``, no leading zero, no ``.`` at the end
   or before ``e`` / ``E``; Arrow's parser refuses the rest of what JSON does not allow (``1..2``,
   ``1e``, ``1e5e5``) in the numbers it parses, the mapped ones. An unmapped number is not
   parsed: such a slip in it goes unseen here (the message's mapped values are still
   ``json``'s); the compiled pass below checks every number and sends such a message to
   ``rest``, which names it.
4. Messages of another shape (a pretty-printed one, a field that comes and goes) take the next
   template, up to :data:`TEMPLATES` new ones a chunk (of at most :data:`MAX_NUMBERS` numbers);
   a message no template can be made of (``NaN``, a mapped field absent) is left for the caller,
   which reads what is left (``rest``: Arrow's JSON reader, and ``json`` for what Arrow refuses).
5. The mapped numbers are parsed for all messages at once by Arrow's cast of a ``string_view``
   array over the chunk (no copy; ``fast_float``, correctly rounded; one cast for the integer
   leaves, one for the others): Python's ``int(text)`` / ``float(text)``, which ``json`` gives,
   but for ``-0``: the integer 0 to ``json``, so 0.0 here too.

Duplicate keys read as ``json`` reads them (the last one). A number Arrow will not cast: None,
and the caller reads the whole batch its own way, naming the bad message.

Steps 1, 3 and 5 in one compiled pass, when built: ``imupipe.readers._jsonscan``
(``readers/_jsonscan.c``, an optional extension of ``setup.py``) walks each message once per
template, compares the template's text piece by piece, checks every number (mapped or not)
against the grammar and parses the mapped ones into the columns without the GIL: floats as
``float(text)`` (Clinger's exact case, the Eisel-Lemire algorithm, else ``strtod_l`` in the "C"
locale), integers as ``int(text)`` within int64, ``-0`` as 0.0; a message it does not take goes
to ``rest``. The numpy steps above are the fallback, taken when it is not built or
``IMUPIPE_PURE_PYTHON=1`` is set; ``tests/test_jsonscan.py`` checks both give the same columns,
bit for bit. The numpy path takes about 5 ms a 1 MB chunk of 5,200 messages, the compiled pass 1.3 ms.
"""

from __future__ import annotations

import json
import os
import re
import threading
from collections.abc import Callable, Sequence
from types import ModuleType

import numpy as np

from imupipe.readers.record_walk import PURE_PYTHON_ENV

TEMPLATES = 8
"""Shapes tried per batch before the rest goes to Arrow's JSON reader."""

MAX_NUMBERS = 512
"""A template with more numbers than this (a message holding a long array) is left to Arrow's
JSON reader: the numbers are chained one Python step each."""

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)
"""A JSON string literal (RFC 8259, section 7) in a text ``json`` has accepted."""


class _Number:
    """A number of the template: its position among the template's numbers."""

    __slots__ = ("index",)

    def __init__(self, index: int) -> None:
        self.index = index


def _is_digit(values: np.ndarray) -> np.ndarray:
    return (values - np.uint8(48)) < 10


class _Scratch(threading.local):
    """Work arrays kept from one chunk to the next (per thread): a fresh megabyte-sized numpy
    temporary costs more in page faults than the pass that fills it (the C library hands
    memory over 128 kB back to the system when freed)."""

    def __init__(self) -> None:
        self.named: dict[str, np.ndarray] = {}
        self.u8 = np.empty(0, np.uint8)
        self.flag = np.empty(0, bool)
        self.e = np.empty(0, bool)
        self.tmp = np.empty(0, bool)

    def get(self, size: int) -> _Scratch:
        if len(self.u8) < size:
            grow = int(size * 1.25) + 16
            self.u8 = np.empty(grow, np.uint8)
            self.flag = np.empty(grow + 1, bool)
            self.e = np.empty(grow + 1, bool)
            self.tmp = np.empty(grow, bool)
        return self

    def array(self, name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        """The work array ``name`` (its contents: whatever its last user left)."""
        size = int(np.prod(shape))
        have = self.named.get(name)
        if have is None or len(have) < size or have.dtype != dtype:
            have = self.named[name] = np.empty(int(size * 1.25) + 64, dtype)
        return have[:size].reshape(shape)


_SCRATCH = _Scratch()


def number_chars(region: np.ndarray, work: _Scratch | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per byte: is it one of ``0-9 . e E + - /``; and is it ``e`` or ``E`` (both with one
    more, False, at the end; ``/`` only to save a pass: outside a string it is never next to
    a number)."""
    n = len(region)
    work = work or _Scratch().get(n)
    flag, e, u8, tmp = work.flag[: n + 1], work.e[: n + 1], work.u8[:n], work.tmp[:n]
    flag[n] = e[n] = False
    np.subtract(region, np.uint8(45), out=u8)
    np.less(u8, 13, out=flag[:n])  # - . / 0-9
    np.equal(region, 43, out=tmp)  # +
    np.logical_or(flag[:n], tmp, out=flag[:n])
    np.bitwise_or(region, np.uint8(32), out=u8)
    np.equal(u8, 101, out=e[:n])  # e E
    np.logical_or(flag[:n], e[:n], out=flag[:n])
    return flag, e


def run_ends(flag: np.ndarray, work: _Scratch | None = None) -> np.ndarray:
    """Where each run of number characters ends (exclusive), from :func:`number_chars`."""
    n = len(flag) - 1
    tmp = work.tmp[:n] if work is not None else np.empty(n, bool)
    np.greater(flag[:-1], flag[1:], out=tmp)
    ends = np.flatnonzero(tmp)
    ends += 1
    return ends


def _dot_e(region: np.ndarray, e: np.ndarray, work: _Scratch) -> np.ndarray:
    """Where ``.`` is followed by ``e`` or ``E`` (``1.e5``: Arrow takes it, JSON does not)."""
    dot = work.tmp[: len(region)]
    np.equal(region, 46, out=dot)
    np.logical_and(dot, e[1:], out=dot)
    return np.flatnonzero(dot) if dot.any() else np.zeros(0, np.int64)


def _template(
    text: bytes, leaves: Sequence[tuple[str | int, ...]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]] | None:
    """(starts, ends) of the numbers of the template ``text``, which runs of number characters
    they are (the others are in strings or ``true``), and which number each leaf is;
    None when ``json`` refuses the text, a leaf is not a number in it, or the runs of number
    characters outside its strings are not its numbers."""
    count = [0]

    def number(_: str) -> _Number:
        count[0] += 1
        return _Number(count[0] - 1)

    try:
        doc = json.loads(text, parse_int=number, parse_float=number)
    except (ValueError, RecursionError):
        return None
    which = []
    for path in leaves:
        value: object = doc
        for part in path:
            if (isinstance(part, int) and isinstance(value, list) and part < len(value)) or (
                isinstance(part, str) and isinstance(value, dict) and part in value
            ):
                value = value[part]  # type: ignore[index]
            else:
                return None
        if not isinstance(value, _Number):
            return None
        which.append(value.index)
    region = np.frombuffer(text, np.uint8)
    flag, _ = number_chars(region)
    ends = run_ends(flag)
    starts = np.flatnonzero(np.greater(flag[1:], flag[:-1])) + 1
    starts = np.concatenate([[0], starts]) if flag[0] else starts
    spans = np.array([m.span() for m in _STRING.finditer(text)], np.int64).reshape(-1, 2)
    at = np.searchsorted(spans[:, 0], starts, side="right") - 1
    lead = region[np.minimum(starts, len(region) - 1)]
    number = _is_digit(lead) | (lead == 45)  # not the e of true, not a string's
    runs = np.flatnonzero(number & ~((at >= 0) & (starts < spans[np.maximum(at, 0), 1])))
    if len(runs) != count[0]:
        return None
    return starts[runs], ends[runs], runs, which


class Shape:
    """What every message of one template's shape holds between its numbers: ``gaps[j]``
    bytes before number ``j`` (from the message's start, or from number ``j - 1``'s end),
    ``tail`` bytes after the last, together ``text``; ``steps[j]`` runs of number characters
    from number ``j - 1``'s run to number ``j``'s (runs in strings counted); ``which``: the
    number each leaf is."""

    __slots__ = ("cuts", "gaps", "numbers", "pieces", "span", "steps", "tail", "text", "which")

    def __init__(
        self, text: bytes, starts: np.ndarray, ends: np.ndarray, runs: np.ndarray, which: list
    ) -> None:
        bases = [0, *ends.tolist()]
        self.gaps = [s - b for s, b in zip(starts.tolist(), bases, strict=False)]
        self.tail = len(text) - bases[-1]
        self.steps = [0, *np.diff(runs).tolist()]
        self.span = int(runs[-1] - runs[0])
        self.which = which
        sizes = [*self.gaps, self.tail]
        self.text = np.frombuffer(
            b"".join(text[b : b + n] for b, n in zip(bases, sizes, strict=True)), np.uint8
        )[:, None]
        at = np.cumsum([0, *sizes])
        self.cuts = at.astype(np.int64)
        """Where each piece of ``text`` starts (and the last ends): the compiled pass's."""
        self.numbers = np.asarray(which, np.int64)
        self.pieces = [(j, int(at[j]), int(at[j + 1])) for j in range(len(sizes)) if sizes[j]]
        """(j, first, last): text[first:last] follows the message's start (j = 0) or number
        ``j - 1``'s end."""

    @classmethod
    def of(cls, text: bytes, leaves: Sequence[tuple[str | int, ...]]) -> Shape | None:
        """The shape of the template ``text`` (None: not a template, see :func:`_template`;
        more than :data:`MAX_NUMBERS` numbers; a number at the very start)."""
        got = _template(text, leaves)
        if got is None or len(got[0]) > MAX_NUMBERS or got[0][0] == 0:
            return None
        return cls(text, *got)

    def match(
        self,
        buf: np.ndarray,
        run_end: np.ndarray,
        starts: np.ndarray,
        ends: np.ndarray,
        work: _Scratch,
        keep_in_work: bool,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(which of the messages ``buf[starts:ends]`` have this shape; their numbers'
        starts and ends, one row per number; ``head[i]``: each number's byte ``i``, 0 to 3,
        past the end of ``buf`` its last). ``run_end``: where the runs of number characters
        end. ``keep_in_work``: the arrays returned may be ``work``'s."""
        k, m = len(self.gaps), len(starts)
        mine = {"ts", "te", "head"} if keep_in_work else set()

        def array(name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
            if name in mine or name not in ("ts", "te", "head"):
                return work.array(name, shape, dtype)
            return np.empty(shape, dtype)

        ts = array("ts", (k, m), np.int64)
        te = array("te", (k, m), np.int64)
        np.add(starts, self.gaps[0], out=ts[0])
        run = np.searchsorted(run_end, ts[0], "right")
        np.take(run_end, run, out=te[0], mode="clip")
        ok = te[0] > ts[0]
        for j in range(1, k):
            # number j is the run steps[j] runs on, when the text between is the template's
            run += self.steps[j]
            np.add(te[j - 1], self.gaps[j], out=ts[j])
            np.take(run_end, run, out=te[j], mode="clip")
            ok &= te[j] > ts[j]
        ok &= ends - te[-1] == self.tail
        ok &= run < len(run_end)  # the runs ran out (the takes clipped)
        rows = np.flatnonzero(ok)
        if not len(rows):
            return rows, ts[:, :0], te[:, :0], np.zeros((4, k, 0), np.uint8)
        if len(rows) < m:
            ts, te, starts = ts.take(rows, axis=1), te.take(rows, axis=1), starts[rows]
        # the text between the numbers is the template's, byte for byte (gathered a byte at a
        # time: a gather of unaligned 8-byte words costs ten times as much a word)
        got = work.array("text", (len(self.text), len(rows)), np.uint8)
        for j, first, last in self.pieces:
            base = te[j - 1] if j else starts
            for i in range(first, last):
                np.take(buf[i - first :], base, out=got[i])
        keep = ~(got != self.text).any(axis=0)
        # each number follows the JSON grammar where Arrow does not hold to it: a digit after
        # "-", no leading zero, no "." at the end (the caller's: no ".e", see _dot_e)
        head = array("head", (4, k, len(rows)), np.uint8)
        for i in range(4):  # byte 3 may lie past the message's end (its last bracket)
            np.take(buf[i:], ts, out=head[i], mode="clip")
        minus = head[0] == 45
        lead = np.where(minus, head[1], head[0]) - np.uint8(48)
        after = np.where(minus, head[2], head[1]) - np.uint8(48)
        bad = (lead > 9) | ((lead == 0) & (after < 10))
        bad |= np.take(buf, np.subtract(te, 1, out=work.array("at", te.shape, np.int64))) == 46
        keep &= ~bad.any(axis=0)
        if keep.all():
            return rows, ts, te, head
        kept = np.flatnonzero(keep)
        return rows[kept], ts.take(kept, axis=1), te.take(kept, axis=1), head.take(kept, axis=2)


def _parse(  # noqa: ANN202
    buf: np.ndarray, ts: np.ndarray, te: np.ndarray, head: np.ndarray, integer: bool, work: _Scratch
):
    """The numbers ``buf[ts:te]`` (``head[i]``: their bytes ``i``, 0 to 3) parsed by Arrow: int64 or
    float64, or None when Arrow refuses one. The text is a ``string_view`` array over ``buf``
    (Arrow columnar format: 16 bytes a value: its length, then up to 12 bytes inline,
    zero-padded, or a 4-byte prefix, buffer 0 and the offset)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    n = len(ts)
    lengths = np.subtract(te, ts, out=work.array("lengths", (n,), np.int64))
    views = work.array("views", (n, 4), np.dtype("<u4"))
    views[:, 0] = lengths
    prefix = views[:, 1:2].view(np.uint8)
    for i in range(4):
        prefix[:, i] = head[i]
    views[:, 2] = 0
    views[:, 3] = ts
    short = np.flatnonzero(lengths <= 12)
    minus_zero = None
    if len(short):
        sl = lengths[short, None]
        inline = np.take(buf, ts[short, None] + np.arange(12), mode="clip")
        inline[np.arange(12) >= sl] = 0
        views[short, 1:] = inline.view("<u4")
        if not integer:  # "-0": the integer 0 to json, -0.0 to Arrow
            minus_zero = short[(sl[:, 0] == 2) & (views[short, 1] == 0x302D)]
    array = pa.Array.from_buffers(
        pa.string_view(), n, [None, pa.py_buffer(views), pa.py_buffer(buf)]
    )
    try:
        out = pc.cast(array, pa.int64() if integer else pa.float64())
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return None
    values = out.to_numpy(zero_copy_only=False)
    if minus_zero is not None and len(minus_zero):
        values = values.copy()
        values[minus_zero] = 0.0
    return values


class _Templates:
    """The shapes a batch is tried against, in turn: the caller's (a channel's previous chunk),
    then one made of the first message left that no shape fits, up to :data:`TEMPLATES` new
    ones (a message no template can be made of is skipped)."""

    def __init__(
        self,
        buf: np.ndarray,
        starts: np.ndarray,
        ends: np.ndarray,
        leaves: Sequence[tuple[str | int, ...]],
        known: Sequence[Shape],
    ) -> None:
        self.buf, self.starts, self.ends, self.leaves = buf, starts, ends, leaves
        self.known = [s for s in known if len(s.gaps) <= MAX_NUMBERS]
        self.new = self.refused = 0  # refused: the messages no template can be made of

    def next(self, left: np.ndarray) -> Shape | None:
        """The next shape for the messages ``left`` (None: no more)."""
        while len(left) > self.refused and (self.known or self.new < TEMPLATES):
            if self.known:
                return self.known.pop(0)
            self.new += 1
            t = int(left[self.refused])
            shape = Shape.of(self.buf[self.starts[t] : self.ends[t]].tobytes(), self.leaves)
            if shape is not None:
                return shape
            self.refused += 1  # NaN, a mapped field absent...: the next message's text
        return None


def _module() -> ModuleType | None:
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None
    try:
        from imupipe.readers import _jsonscan  # type: ignore[attr-defined]
    except ImportError:
        return None
    return _jsonscan


def compiled() -> bool:
    """Whether the compiled pass (``imupipe.readers._jsonscan``) is used: built, and not turned
    off by ``IMUPIPE_PURE_PYTHON``."""
    return _module() is not None


def _decode_compiled(
    module: ModuleType,
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    leaves: Sequence[tuple[str | int, ...]],
    integer: Sequence[bool],
    rest: Callable[[np.ndarray], list[np.ndarray]],
    shapes: list[Shape] | None,
) -> list[np.ndarray]:
    """:func:`decode_by_template` by the compiled pass: per shape, one call that checks every
    message left against it (its text byte for byte, every number in JSON's grammar) and
    parses the mapped numbers straight into the columns (``readers/_jsonscan.c``)."""
    n = len(starts)
    starts = np.ascontiguousarray(starts, np.int64)
    lengths = np.ascontiguousarray(lengths, np.int64)
    values = [np.empty(n, np.int64 if whole else np.float64) for whole in integer]
    columns = tuple(values)
    kinds = np.array(integer, np.uint8)
    ok = np.zeros(n, np.uint8)
    picker = _Templates(buf, starts, starts + lengths, leaves, shapes or ())
    used: list[tuple[int, Shape]] = []
    left = np.arange(n, dtype=np.int64)
    while (shape := picker.next(left)) is not None:
        got = module.match(
            buf, starts, lengths, left, shape.text, shape.cuts, shape.numbers, kinds, columns, ok
        )
        if got:
            used.append((got, shape))
            left = left[ok[left] == 0]
    if shapes is not None:
        shapes[:] = [u[1] for u in sorted(used, key=lambda u: -u[0])]
    if len(left):
        for column, got in zip(values, rest(left), strict=True):
            column[left] = got
    return values


def decode_by_template(
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    leaves: Sequence[tuple[str | int, ...]],
    integer: Sequence[bool],
    rest: Callable[[np.ndarray], list[np.ndarray]],
    shapes: list[Shape] | None = None,
) -> list[np.ndarray] | None:
    """The value of each leaf (a path of keys and list indices) in every payload
    ``buf[starts[i]:starts[i] + lengths[i]]`` (see the module docstring): int64 where
    ``integer``, else float64. ``rest(indices)`` reads the messages no template fits (Arrow's
    JSON reader). ``shapes``: the templates of the batches before (of the same ``leaves``),
    tried first; updated to this batch's. None: read the whole batch another way."""
    n = len(starts)
    if not n:
        return None
    module = _module()
    if module is not None and buf.dtype == np.uint8 and buf.flags.c_contiguous:
        return _decode_compiled(module, buf, starts, lengths, leaves, integer, rest, shapes)
    ends = starts + lengths
    if len(buf) >= 1 << 31:  # string_view offsets are int32
        return None
    work = _SCRATCH.get(len(buf))
    lo, hi = int(starts.min()), int(ends.max())
    region = buf[lo:hi]
    flag, e = number_chars(region, work)
    run_end = run_ends(flag, work)
    run_end += lo
    dot_e = _dot_e(region, e, work)
    bad_ends = run_end[np.searchsorted(run_end, dot_e + lo, "right")] if len(dot_e) else None
    picker = _Templates(buf, starts, ends, leaves, shapes or ())
    found: list[tuple[Shape, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    left = np.arange(n)
    while (shape := picker.next(left)) is not None:
        whole = len(left) == n
        rows, ts, te, head = shape.match(
            buf,
            run_end,
            starts if whole else starts[left],
            ends if whole else ends[left],
            work,
            not found,
        )
        fine = ~np.isin(te, bad_ends).any(axis=0) if bad_ends is not None else None
        if fine is not None and not fine.all():
            fine = np.flatnonzero(fine)
            rows, ts, te = rows[fine], ts.take(fine, axis=1), te.take(fine, axis=1)
            head = head.take(fine, axis=2)
        if not len(rows):
            continue
        rows = rows if whole else left[rows]
        found.append((shape, rows, ts, te, head))
        left = np.delete(left, np.searchsorted(left, rows)) if len(rows) < len(left) else left[:0]
    if shapes is not None:
        shapes[:] = [f[0] for f in sorted(found, key=lambda f: -len(f[1]))]
    values = [np.empty(n, np.int64 if whole else np.float64) for whole in integer]
    for whole in set(integer) if found else ():
        # one parse for the float leaves, one for the integer ones
        cols = [j for j, w in enumerate(integer) if w == whole]
        size = sum(len(cols) * len(f[1]) for f in found)
        ts = work.array("pick ts", (size,), np.int64)
        te = work.array("pick te", (size,), np.int64)
        head = work.array("pick head", (4, size), np.uint8)
        at = 0
        for f in found:
            pick, m = [f[0].which[j] for j in cols], len(cols) * len(f[1])
            np.take(f[2], pick, axis=0, out=ts[at : at + m].reshape(len(cols), -1))
            np.take(f[3], pick, axis=0, out=te[at : at + m].reshape(len(cols), -1))
            np.take(f[4], pick, axis=1, out=head[:, at : at + m].reshape(4, len(cols), -1))
            at += m
        parsed = _parse(buf, ts, te, head, whole, work)
        if parsed is None:
            return None
        at = 0
        for f in found:  # per template: its rows, leaf by leaf
            rows = f[1]
            every = len(rows) == n
            for j in cols:
                if every:
                    values[j][:] = parsed[at : at + n]
                else:
                    values[j][rows] = parsed[at : at + len(rows)]
                at += len(rows)
    if len(left):
        for column, got in zip(values, rest(left), strict=True):
            column[left] = got
    return values
