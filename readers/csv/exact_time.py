"""Time stamps written as text into int64 nanoseconds, exactly.

A value ``v`` in a unit worth ``10**exponent`` nanoseconds (ns: 0, us: 3, ms: 6, s: 9) is
``v * 10**exponent`` ns. Parsing the text as a float64 first loses that: a float64 holds 15-17
significant digits, so ``1700000000.0025`` s becomes 1700000000002500096 ns
(the float64 grid is 256 ns wide near 1.7e18), and a column of
integer nanoseconds with one cell written ``1.7e18`` turns into floats that shift every stamp by
up to 128 ns. Here the text is cast to an Arrow decimal with ``exponent`` fractional digits, whose
stored integer *is* the count of nanoseconds: exact for every stamp with at most nanosecond
digits. Digits below the nanosecond are rounded half to even for s, ms and us; for a column in
ns a fractional value is an error, as is anything outside |t| < 2**63 ns.
"""

from __future__ import annotations

import re

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import valid_mask

INT64_MAX = 2**63 - 1


class TimeCellError(ValueError):
    """Cell ``row`` of a time column cannot be a time: ``reason`` says why (one line)."""

    def __init__(self, row: int, reason: str) -> None:
        super().__init__(reason)
        self.row = row
        self.reason = reason


def _low_words(array: pa.Array) -> tuple[np.ndarray, np.ndarray]:
    """(low int64 word, high int64 word) of each value of a decimal128 array."""
    words = np.frombuffer(array.buffers()[1], dtype=np.int64).reshape(-1, 2)
    words = words[array.offset : array.offset + len(array)]
    return words[:, 0], words[:, 1]


HUGE_EXPONENT = r"[eE][+-]?0*[1-9][0-9]{4,}"
"""An exponent of five digits or more: no time has one, and pyarrow's decimal cast crashes on
some (``1e-9999999``); such cells are refused one by one."""


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _as_decimal(cells: pa.Array, exponent: int) -> pa.Array:
    """The cells as decimal128 with ``exponent`` fractional digits (rounded below that)."""
    import pyarrow.compute as pc  # text times only: its import costs 0.06-0.09 s CPU

    target = pa.decimal128(38, exponent)
    try:
        return pc.cast(cells, target)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        pass
    wide = pc.cast(cells, pa.decimal256(76, 40))  # raises for text that is no number
    if exponent == 0:
        whole = pc.equal(pc.round(wide, ndigits=0), wide).to_numpy(zero_copy_only=False)
        if not whole.all():
            raise TimeCellError(_first(~whole), "is not a whole number of nanoseconds")
    return pc.cast(pc.round(wide, ndigits=exponent, round_mode="half_to_even"), target)


def _locate(cells: pa.Array, exponent: int) -> TimeCellError:
    """The first cell that does not parse, with the reason (slow: errors only)."""
    from decimal import Decimal, InvalidOperation

    for row, cell in enumerate(cells.to_pylist()):
        if isinstance(cell, str) and re.search(HUGE_EXPONENT, cell):
            return TimeCellError(row, "has an exponent of five digits or more")
        try:
            value = Decimal(cell.strip()) * (10**exponent)
        except (InvalidOperation, AttributeError):
            return TimeCellError(row, "is not a number")
        if not value.is_finite():
            return TimeCellError(row, "is not a finite time")
        if exponent == 0 and value != value.to_integral_value():
            return TimeCellError(row, "is not a whole number of nanoseconds")
        if not -INT64_MAX <= value <= INT64_MAX:
            return TimeCellError(row, "is out of range (|t| >= 2^63 ns, past the year 2262)")
    return TimeCellError(0, "cannot be read as a time")


def text_to_ns(cells: pa.Array, exponent: int) -> np.ndarray:
    """int64 ns of a string array of times in a unit of ``10**exponent`` ns (no nulls).

    Raises :class:`TimeCellError` naming the first cell that is no number, not a whole number
    of ns (``exponent`` 0) or out of int64 range."""
    if len(cells) == 0:
        return np.zeros(0, np.int64)
    import pyarrow.compute as pc  # text times only: its import costs 0.06-0.09 s CPU

    if pc.any(pc.match_substring_regex(cells, HUGE_EXPONENT)).as_py():
        raise _locate(cells, exponent)  # pyarrow 26's decimal cast crashes on "1e-9999999"
    try:
        try:
            dec = _as_decimal(cells, exponent)
        except pa.ArrowInvalid:
            cells = pc.utf8_trim_whitespace(cells)
            dec = _as_decimal(cells, exponent)
    except pa.ArrowInvalid:
        raise _locate(cells, exponent) from None
    if dec.null_count:
        raise TimeCellError(_first(~valid_mask(dec)), "is empty")
    low, high = _low_words(dec)
    fits = high == (low >> 63)
    if not fits.all():
        raise TimeCellError(_first(~fits), "is out of range (|t| >= 2^63 ns, past the year 2262)")
    return low.copy()


def scaled_ns(values: np.ndarray, exponent: int) -> np.ndarray:
    """int64 ns of integer times in a unit of ``10**exponent`` ns, with an overflow check.

    Raises :class:`TimeCellError` for the first value out of int64 range."""
    values = np.asarray(values, dtype=np.int64)
    if exponent == 0:
        return values
    factor = 10**exponent
    bad = np.abs(values) > INT64_MAX // factor
    if bad.any():
        raise TimeCellError(_first(bad), "is out of range (|t| >= 2^63 ns, past the year 2262)")
    return values * factor
