"""JSON messages that share one shape: their numbers found and parsed without parsing each message.

A JSON writer gives the messages of a channel the same text around their numbers (Foxglove's
SDKs and ``json.dumps`` of one dict per message: ``{"t": 17, "g": [0.01, -0.02, 0.03]}``): only
the numbers differ. :func:`decode_by_template` reads a batch of payloads (one decompressed
chunk) that way:

1. Where every run of number characters (``0-9 . e E + -``) ends is found in the whole chunk in a
   few numpy passes (into work arrays kept per thread: a fresh megabyte temporary costs more in
   page faults than the pass).
2. The first undecoded message is the *template*: parsed once by Python's ``json`` (the
   reference decoder of ``mcap``'s JSON channels), its numbers counted through ``parse_int`` /
   ``parse_float`` in text order. Its runs that start with a digit or ``-`` outside its strings
   (``"imu_1"`` is text) must be exactly its numbers, and every mapped leaf one of them: each leaf
   is then "the j-th number", and the text between numbers is known.
3. For every other message, number j starts where the template's text before it ends and ends
   where its run of number characters does (the runs between two numbers are the template's:
   counted, not searched). The message has the template's shape when its text between the numbers
   is byte for byte the template's (compared 8 bytes at a time) and each number is one whole run;
   it is then valid JSON with the template's structure, provided each number follows the JSON
   grammar (RFC 8259, section 6; checked here: a digit after ``-``, no leading zero, a digit after
   ``.``; Arrow's parser refuses the rest).
4. Messages of another shape (a pretty-printed one, a field that comes and goes) take the next
   template, up to :data:`TEMPLATES` (of at most :data:`MAX_NUMBERS` numbers); the caller reads
   what is left (``rest``: Arrow's JSON reader, and ``json`` for what Arrow refuses).
5. The mapped numbers are parsed for all messages at once: integers digit by digit in numpy
   (exact), other numbers by Arrow's cast of a ``string_view`` array over the chunk (no copy;
   ``fast_float``, correctly rounded): Python's ``int(text)`` / ``float(text)``, which ``json``
   gives, but for ``-0``: the integer 0 to ``json``, so 0.0 here too.

Duplicate keys read as ``json`` reads them (the last one). A number Arrow will not cast: None,
and the caller reads the whole batch its own way, naming the bad message.
"""

from __future__ import annotations

import json
import re
import threading
from collections.abc import Callable, Sequence

import numpy as np

from imupipe.readers.cdr import unaligned

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
    temporary costs more in page faults than the pass that fills it."""

    def __init__(self) -> None:
        self.pad = np.empty(0, np.uint8)
        self.u8 = np.empty(0, np.uint8)
        self.flag = np.empty(0, bool)
        self.e = np.empty(0, bool)
        self.tmp = np.empty(0, bool)

    def get(self, size: int) -> _Scratch:
        if len(self.pad) < size + 16:
            grow = int(size * 1.25) + 16
            self.pad = np.empty(grow + 16, np.uint8)
            self.u8 = np.empty(grow, np.uint8)
            self.flag = np.empty(grow + 1, bool)
            self.e = np.empty(grow, bool)
            self.tmp = np.empty(grow, bool)
        return self


_SCRATCH = _Scratch()


def number_chars(region: np.ndarray, work: _Scratch | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per byte: is it one of ``0-9 . e E + - /`` (one more, False, at the end; ``/`` only to
    save a pass: outside a string it is never next to a number); and is it ``e`` or ``E``."""
    n = len(region)
    work = work or _Scratch().get(n)
    flag, e, u8, tmp = work.flag[: n + 1], work.e[:n], work.u8[:n], work.tmp[:n]
    flag[n] = False
    np.subtract(region, np.uint8(45), out=u8)
    np.less(u8, 13, out=flag[:n])  # - . / 0-9
    np.equal(region, 43, out=tmp)  # +
    np.logical_or(flag[:n], tmp, out=flag[:n])
    np.bitwise_or(region, np.uint8(32), out=u8)
    np.equal(u8, 101, out=e)  # e E
    np.logical_or(flag[:n], e, out=flag[:n])
    return flag, e


def run_ends(flag: np.ndarray, work: _Scratch | None = None) -> np.ndarray:
    """Where each run of number characters ends (exclusive), from :func:`number_chars`."""
    n = len(flag) - 1
    tmp = work.tmp[:n] if work is not None else np.empty(n, bool)
    np.greater(flag[:-1], flag[1:], out=tmp)
    return np.flatnonzero(tmp) + 1


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


def _same_text(words: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per row: the text ``lo[:, j]``..``hi[:, j]`` of every column is row 0's (the sizes are
    row 0's), compared as little-endian 8-byte words."""
    offsets, columns, masks = [], [], []
    for j, size in enumerate((hi[0] - lo[0]).tolist()):
        for w in range(0, size, 8):
            offsets.append(w)
            columns.append(j)
            masks.append(0xFFFF_FFFF_FFFF_FFFF >> (8 * max(8 - (size - w), 0)))
    if not offsets:
        return np.ones(len(lo), bool)
    got = words[lo[:, columns] + np.array(offsets)]
    got ^= got[0]
    got &= np.array(masks, np.uint64)
    return ~got.any(axis=1)


def _grammar(buf: np.ndarray, ts: np.ndarray, te: np.ndarray, bad_ends: np.ndarray) -> np.ndarray:
    """Per row: every number ``buf[ts:te]`` has a digit after its ``-``, no leading zero, a
    digit after its ``.`` (the parts of RFC 8259's grammar Arrow's parser does not hold to):
    ``bad_ends`` are the ends of the runs with ``.e`` or ``.E``; Arrow refuses ``.`` before
    ``+ - .``."""
    p = ts + (buf[ts] == 45)
    lead = buf[p]
    ok = _is_digit(lead)
    ok &= ~((lead == 48) & (p + 1 < te) & _is_digit(buf[p + 1]))
    ok &= buf[te - 1] != 46
    if len(bad_ends):
        ok &= ~np.isin(te, bad_ends)
    return ok.all(axis=1)


_LOW = np.array([(1 << (8 * k)) - 1 for k in range(9)], np.uint64)
"""``_LOW[k]``: the low ``k`` bytes of a little-endian word."""


def _integers(pad: np.ndarray, ts: np.ndarray, te: np.ndarray) -> np.ndarray | None:
    """The integers ``pad[ts:te]`` (an optional ``-``, 1 to 19 digits, within int64) exactly,
    digit by digit; None when one is not such an integer."""
    negative = pad[ts] == 45
    first = ts + negative
    count = te - first
    if not len(ts) or count.min() < 1 or count.max() > 19:
        return None
    width = int(count.max())
    at = te[:, None] - width + np.arange(width)  # right-aligned digits
    digits = pad[np.maximum(at, 0)] - np.uint8(48)
    here = at >= first[:, None]
    if ((digits > 9) & here).any():
        return None
    digits[~here] = 0
    value = digits.astype(np.uint64) @ (
        np.uint64(10) ** np.arange(width - 1, -1, -1, dtype=np.uint64)
    )
    if (value > np.uint64(2**63 - 1) + negative.astype(np.uint64)).any():
        return None
    out = value.astype(np.int64)  # 2**63 (only when negative) wraps to -2**63
    return np.where(negative & (value != np.uint64(2**63)), -out, out)


def _parse(pad: np.ndarray, ts: np.ndarray, te: np.ndarray, integer: bool):  # noqa: ANN202
    """The numbers ``pad[ts:te]`` parsed by Arrow: int64 or float64, or None when Arrow refuses
    one. The text is a ``string_view`` array over ``pad`` (Arrow columnar format: 16 bytes a
    value; its length, then up to 12 bytes inline, or a 4-byte prefix, buffer 0 and the
    offset)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if integer:
        exact = _integers(pad, ts, te)
        if exact is not None:
            return exact
    n = len(ts)
    lengths = (te - ts).astype(np.uint64)
    low = unaligned(pad, "<u8")[ts] & _LOW[np.minimum(lengths, 8)]
    views = np.empty((n, 2), "<u8")
    views[:, 0] = lengths | (low << np.uint64(32))
    views[:, 1] = ts.astype(np.uint64) << np.uint64(32)
    short = np.flatnonzero(lengths <= 12)
    if len(short):
        ss, sl = ts[short], lengths[short]
        high = unaligned(pad, "<u4")[ss + 8].astype(np.uint64) & _LOW[np.clip(sl, 8, 12) - 8]
        views[short, 1] = (low[short] >> np.uint64(32)) | (high << np.uint64(32))
    array = pa.Array.from_buffers(
        pa.string_view(), n, [None, pa.py_buffer(views), pa.py_buffer(pad)]
    )
    try:
        out = pc.cast(array, pa.int64() if integer else pa.float64())
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return None
    values = out.to_numpy(zero_copy_only=False)
    minus_zero = low == np.uint64(0x302D)  # "-0": the integer 0 to json, -0.0 to Arrow
    return np.where(minus_zero, 0.0, values) if not integer and minus_zero.any() else values


def decode_by_template(
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    leaves: Sequence[tuple[str | int, ...]],
    integer: Sequence[bool],
    rest: Callable[[np.ndarray], list[np.ndarray]],
) -> list[np.ndarray] | None:
    """The value of each leaf (a path of keys and list indices) in every payload
    ``buf[starts[i]:starts[i] + lengths[i]]`` (see the module docstring): int64 where
    ``integer``, else float64. ``rest(indices)`` reads the messages no template fits (Arrow's
    JSON reader). None: read the whole batch another way."""
    n = len(starts)
    ends = starts + lengths
    if len(buf) + 16 >= 1 << 31 or not n:  # string_view offsets are int32
        return None
    work = _SCRATCH.get(len(buf))
    pad = work.pad[: len(buf) + 16]
    pad[: len(buf)] = buf
    pad[len(buf) :] = 0
    lo, hi = int(starts.min()), int(ends.max())
    region = pad[lo:hi]
    flag, e = number_chars(region, work)
    run_end = run_ends(flag, work) + lo
    dots = work.tmp[: hi - lo - 1]  # "1.e5": Arrow takes it, JSON does not
    np.equal(region[:-1], 46, out=dots)
    np.logical_and(dots, e[1:], out=dots)
    at = np.flatnonzero(dots) + lo if dots.any() else np.zeros(0, np.int64)
    bad_ends = run_end[np.minimum(np.searchsorted(run_end, at, "right"), len(run_end) - 1)]
    words = unaligned(pad, "<u8")
    found: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (rows, ts, te) of the leaves
    left = np.arange(n)
    for _ in range(TEMPLATES):
        if not len(left):
            break
        t = int(left[0])
        shape = _template(buf[starts[t] : ends[t]].tobytes(), leaves)
        if shape is None:
            break
        rel_s, rel_e, runs, which = shape
        if len(rel_s) > MAX_NUMBERS:
            break
        gaps = np.diff(np.concatenate([[0], np.column_stack([rel_s, rel_e]).ravel()]))[0::2]
        k = len(rel_s)
        ts = np.empty((len(left), k), np.int64)
        te = np.empty((len(left), k), np.int64)
        ok = np.ones(len(left), bool)
        prev = starts[left]
        run = np.searchsorted(run_end, prev + int(gaps[0]), "right")
        for j in range(k):
            # a number is one whole run: the run before it ends before it starts (the same
            # runs between numbers as the template's, once the text there is checked equal)
            if j:
                run += int(runs[j] - runs[j - 1])
            ts[:, j] = prev + int(gaps[j])
            ok &= run < len(run_end)
            np.minimum(run, len(run_end) - 1, out=run)
            te[:, j] = prev = run_end[run]
            ok &= (prev > ts[:, j]) & ((run == 0) | (run_end[np.maximum(run - 1, 0)] <= ts[:, j]))
        stop = ends[left]
        ok &= stop - prev == stop[0] - prev[0]
        rows, ts, te = left[ok], ts[ok], te[ok]
        keep = _same_text(
            words,
            np.column_stack([starts[rows], te]),
            np.column_stack([ts, ends[rows]]),
        )
        keep &= _grammar(pad, ts, te, bad_ends)
        found.append((rows[keep], ts[keep][:, which], te[keep][:, which]))
        left = left[~np.isin(left, rows[keep], assume_unique=True)]
    rows = np.concatenate([f[0] for f in found]) if found else np.zeros(0, np.int64)
    values = [np.empty(n, np.int64 if whole else np.float64) for whole in integer]
    for whole in set(integer) if len(rows) else ():
        # one parse for the float leaves, one for the integer ones
        cols = [j for j, w in enumerate(integer) if w == whole]
        ts = np.concatenate([f[1][:, cols].T.ravel() for f in found])
        te = np.concatenate([f[2][:, cols].T.ravel() for f in found])
        parsed = _parse(pad, ts, te, whole)
        if parsed is None:
            return None
        at = 0
        for f in found:  # per template: its rows, leaf by leaf
            for j in cols:
                values[j][f[0]] = parsed[at : at + len(f[0])]
                at += len(f[0])
    if len(left):
        for column, got in zip(values, rest(left), strict=True):
            column[left] = got
    return values
