"""Arrow arrays from numpy and back, built on their buffers, so that pandas is never imported.

pyarrow's ``pa.array(...)`` and ``pa.scalar(...)`` (and so ``Table.take``/``pc.*`` called
with a numpy array or a Python number) ask its pandas shim whether the input is a pandas object, and ``Array.to_numpy`` goes through
``ConvertArrayToPandas``, whose static data imports pandas: in a process where pandas is
installed, the first of either imports it (0.5 s and 32 MB on the machine of issue 39, for a
package imupipe never uses). The functions here give the same arrays (same type, values, NaN
kept as a value, validity) from the Arrow columnar format's buffers directly
(https://arrow.apache.org/docs/format/Columnar.html: a validity bitmap, least significant bit
first, and a values buffer); types they do not cover fall back to pyarrow's own conversion.
``tests/test_arrays.py`` checks them equal to pyarrow's, and ``tests/test_no_pandas.py`` that a
read and a convert never import pandas.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pyarrow as pa

_NUMERIC = {
    pa.int8(): np.int8,
    pa.int16(): np.int16,
    pa.int32(): np.int32,
    pa.int64(): np.int64,
    pa.uint8(): np.uint8,
    pa.uint16(): np.uint16,
    pa.uint32(): np.uint32,
    pa.uint64(): np.uint64,
    pa.float32(): np.float32,
    pa.float64(): np.float64,
}
"""Arrow fixed-width numeric types and their numpy dtypes (same bytes, little-endian)."""


def bitmap(mask: np.ndarray) -> pa.Buffer:
    """An Arrow bitmap (least significant bit first) of the boolean ``mask``."""
    return pa.py_buffer(np.packbits(np.asarray(mask, dtype=bool), bitorder="little"))


def arrow_array(
    values: np.ndarray, typ: pa.DataType | None = None, mask: np.ndarray | None = None
) -> pa.Array:
    """``pa.array(values, typ, mask=mask)`` for a 1-D numpy array: null where ``mask`` is true.

    Numeric and boolean types are built on the array's buffer (no copy when it is contiguous and
    of ``typ``'s own dtype; a safe numpy cast otherwise); other types and unsafe casts go to
    ``pa.array``."""
    values = np.asarray(values)
    if typ is None:
        typ = pa.bool_() if values.dtype == np.bool_ else pa.from_numpy_dtype(values.dtype)
    n = len(values)
    validity = None if mask is None else bitmap(~np.asarray(mask, dtype=bool))
    if typ == pa.bool_() and values.dtype == np.bool_:
        return pa.Array.from_buffers(typ, n, [validity, bitmap(values)])
    dtype = _NUMERIC.get(typ)
    if dtype is None or values.ndim != 1 or not np.can_cast(values.dtype, dtype, "safe"):
        return pa.array(values, typ, mask=mask)
    data = np.ascontiguousarray(values, dtype=dtype)
    return pa.Array.from_buffers(typ, n, [validity, pa.py_buffer(data)])


def string_array(strings: Sequence[str]) -> pa.Array:
    """``pa.array(strings, pa.string())`` for a sequence of ``str`` (no nulls)."""
    encoded = [s.encode() for s in strings]
    offsets = np.zeros(len(encoded) + 1, np.int64)
    np.cumsum([len(b) for b in encoded], out=offsets[1:])
    if offsets[-1] >= 2**31:
        return pa.array(list(strings), pa.string())
    return pa.StringArray.from_buffers(
        len(encoded), pa.py_buffer(offsets.astype(np.int32)), pa.py_buffer(b"".join(encoded))
    )


def arrow_scalar(value: float | int | str, typ: pa.DataType) -> pa.Scalar:
    """``pa.scalar(value, typ)`` for a number or a string (a Python scalar given to a pyarrow
    compute function is converted by ``pa.scalar``, which imports pandas)."""
    if typ == pa.string():
        return string_array([str(value)])[0]
    return arrow_array(np.array([value], dtype=_NUMERIC[typ]), typ)[0]


def valid_mask(column: pa.Array | pa.ChunkedArray) -> np.ndarray:
    """``pc.is_valid(column).to_numpy(zero_copy_only=False)``: true where a row is not null."""
    if isinstance(column, pa.ChunkedArray):
        if column.num_chunks == 1:
            return valid_mask(column.chunk(0))
        return np.concatenate([valid_mask(c) for c in column.chunks] or [np.zeros(0, bool)])
    n = len(column)
    if column.null_count == 0:
        return np.ones(n, dtype=bool)
    if column.null_count == n:
        return np.zeros(n, dtype=bool)
    bits = column.buffers()[0]
    if bits is None or isinstance(column.type, pa.UnionType | pa.DictionaryType):
        return _to_numpy(column.is_valid())
    return _unpack(bits, column.offset, n)


def to_numpy(column: pa.Array | pa.ChunkedArray) -> np.ndarray:
    """``column.to_numpy(zero_copy_only=False)`` for numeric and boolean columns: a read-only
    view of the buffer when there is no null; with nulls, a copy with NaN at the nulls (float,
    and integers as float64, as pyarrow gives them). Other types go to pyarrow's own."""
    if isinstance(column, pa.ChunkedArray):
        if column.num_chunks == 1:
            return to_numpy(column.chunk(0))
        plain = column.type in _NUMERIC or (column.type == pa.bool_() and not column.null_count)
        if column.num_chunks == 0 or not plain:
            return column.to_numpy()
        return np.concatenate([_to_numpy(c) for c in column.chunks])
    return _to_numpy(column)


def _to_numpy(column: pa.Array) -> np.ndarray:
    typ, n = column.type, len(column)
    dtype = _NUMERIC.get(typ)
    if typ == pa.bool_() and column.null_count == 0:
        return _unpack(column.buffers()[1], column.offset, n)
    if dtype is None or (column.null_count and typ == pa.bool_()):
        return column.to_numpy(zero_copy_only=False)
    data = column.buffers()[1]
    size = np.dtype(dtype).itemsize
    values = (
        np.frombuffer(data, dtype, count=n, offset=column.offset * size)
        if n
        else np.zeros(0, dtype)
    )
    if column.null_count == 0:
        return values
    out = values.astype(np.float64 if dtype not in (np.float32, np.float64) else dtype)
    out[~valid_mask(column)] = np.nan
    return out


def _unpack(bits: pa.Buffer, offset: int, n: int) -> np.ndarray:
    """Booleans ``offset .. offset + n`` of an Arrow bitmap."""
    if n == 0:
        return np.zeros(0, dtype=bool)
    raw = np.frombuffer(bits, np.uint8, count=(offset + n + 7) // 8)
    return np.unpackbits(raw, bitorder="little", count=offset + n)[offset:].view(bool)


def unique(values: np.ndarray, axis: int | None = None) -> np.ndarray:
    """``np.unique(values, axis=axis)``: the sorted distinct values (rows with ``axis=0``). Plain
    ``np.unique`` asks ``np.ma.is_masked``, which imports ``numpy.ma`` (25-70 ms) in a process
    that has not; with ``return_index`` it does not, and the values are the same. The rows of
    an integer matrix are sorted by one ``lexsort`` of its columns (first column first), the
    order ``np.unique`` gives; its own row sort goes through a structured view, about 100x
    slower (issue 39)."""
    values = np.asarray(values)
    if axis == 0 and values.ndim == 2 and values.dtype.kind in "iu" and len(values):
        rows = values[np.lexsort(values.T[::-1])]
        first = np.ones(len(rows), dtype=bool)
        first[1:] = (rows[1:] != rows[:-1]).any(axis=1)
        return rows[first]
    return np.unique(values, axis=axis, return_index=True)[0]


def take(data: pa.Array | pa.ChunkedArray | pa.Table, index: np.ndarray) -> Any:
    """``data.take(index)`` (``index``: int64, -1 for a null row, as a null index gives):
    pyarrow's own take kernel, called through ``pyarrow._compute.call_function`` as
    ``pyarrow.compute.take`` calls it (the same options, result and bytes), without importing
    ``pyarrow.compute``, whose Python wrappers of every kernel cost 0.05-0.1 s CPU in a fresh
    process that a flight-log read otherwise never pays (``Table.take`` imports it)."""
    index = np.asarray(index, dtype=np.int64)
    missing = index < 0
    indices = arrow_array(
        np.where(missing, 0, index), pa.int64(), mask=missing if missing.any() else None
    )
    return _call_function()("take", [data, indices])


def _call_function() -> Any:
    """pyarrow's ``call_function`` of its compute kernels (``pyarrow._compute``: the compiled
    module ``pyarrow.compute`` wraps); ``pyarrow.compute``'s where a pyarrow lacks it."""
    try:
        from pyarrow._compute import call_function
    except ImportError:  # pragma: no cover - every pyarrow imupipe supports has it
        from pyarrow.compute import call_function
    return call_function
