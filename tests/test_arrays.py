"""The buffer-built conversions of :mod:`imupipe.readers.arrays` give what pyarrow's own give."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from imupipe.readers.arrays import arrow_array, string_array, take, to_numpy, valid_mask

RNG = np.random.default_rng(7)
VALUES = {
    pa.int64(): RNG.integers(-(2**62), 2**62, 37),
    pa.int32(): RNG.integers(-1000, 1000, 37).astype(np.int32),
    pa.uint64(): RNG.integers(0, 2**63, 37).astype(np.uint64),
    pa.float64(): np.r_[RNG.normal(size=34), np.nan, np.inf, -0.0],
    pa.float32(): RNG.normal(size=37).astype(np.float32),
    pa.bool_(): RNG.random(37) < 0.5,
}


@pytest.mark.parametrize("typ", list(VALUES), ids=str)
@pytest.mark.parametrize("masked", [False, True])
def test_arrow_array_equals_pa_array(typ: pa.DataType, masked: bool) -> None:
    values = VALUES[typ]
    mask = RNG.random(len(values)) < 0.3 if masked else None
    ours, theirs = arrow_array(values, typ, mask=mask), pa.array(values, typ, mask=mask)
    assert ours.type == theirs.type and ours.null_count == theirs.null_count
    # NaN is a value, not a null, in both (Array.equals says NaN != NaN)
    assert ours.is_null().equals(theirs.is_null())
    np.testing.assert_array_equal(
        ours.to_numpy(zero_copy_only=False), theirs.to_numpy(zero_copy_only=False)
    )


def test_arrow_array_strided_and_cast() -> None:
    wide = RNG.normal(size=(20, 3))
    assert arrow_array(wide[:, 1], pa.float64()).equals(pa.array(wide[:, 1], pa.float64()))
    small = np.arange(9, dtype=np.int32)
    assert arrow_array(small, pa.int64()).equals(pa.array(small, pa.int64()))
    assert arrow_array(np.arange(0, dtype=np.int64)).equals(pa.array(np.arange(0)))


@pytest.mark.parametrize("strings", [[], [""], ["imu_link", "", "ä/b"], ["x"] * 5])
def test_string_array(strings: list[str]) -> None:
    assert string_array(strings).equals(pa.array(strings, pa.string()))


@pytest.mark.parametrize("typ", list(VALUES), ids=str)
def test_to_numpy_and_valid_mask_equal_pyarrow(typ: pa.DataType) -> None:
    values = VALUES[typ]
    mask = RNG.random(len(values)) < 0.3
    for array in (
        pa.array(values, typ),
        pa.array(values, typ, mask=mask),
        pa.array(values, typ, mask=mask).slice(3, 20),  # an offset into the bitmaps
        pa.chunked_array([pa.array(values[:10], typ), pa.array(values[10:], typ)]),
        pa.chunked_array([pa.array(values, typ, mask=mask).slice(5)]),
    ):
        want = array.to_numpy(zero_copy_only=False)
        got = to_numpy(array)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(
            valid_mask(array), pc.is_valid(array).to_numpy(zero_copy_only=False)
        )


def test_unique_equals_numpy_and_imports_no_numpy_ma() -> None:
    import subprocess
    import sys

    from imupipe.readers.arrays import unique

    values = RNG.integers(0, 9, 50)
    np.testing.assert_array_equal(unique(values), np.unique(values))
    rows = RNG.integers(0, 3, (40, 2))
    np.testing.assert_array_equal(unique(rows, axis=0), np.unique(rows, axis=0))
    for wide in (RNG.integers(-5, 5, (300, 3)), RNG.integers(0, 2**40, (20, 2), dtype=np.uint64)):
        np.testing.assert_array_equal(unique(wide, axis=0), np.unique(wide, axis=0))
    assert unique(np.zeros((0, 2), np.int64), axis=0).shape == (0, 2)
    code = (
        "import sys, numpy as np; from imupipe.readers.arrays import unique; "
        "unique(np.arange(5)); unique(np.zeros((3, 2)), axis=0); print('numpy.ma' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _ipc(array: pa.Array) -> bytes:
    sink = pa.BufferOutputStream()
    table = pa.table({"x": array})
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()


TAKEN = [
    pa.array([1.0, None, 3.0, float("nan"), 5.0]),
    pa.array([1, 2, None, 4], pa.int64()),
    pa.array(np.arange(10, dtype=np.float32)),
    pa.array(["a", None, "ccc", "", "dd"]),
    pa.array(["", "", ""]),
    pa.chunked_array([pa.array([1.0, 2.0]), pa.array([None, 4.0])]),
    pa.array([1.0, 2.0, 3.0, 4.0, 5.0]).slice(1, 3),
    pa.array(["a", None, "ccc", "", "dd"]).slice(1, 3),
    pa.array([True, None, False]),  # pyarrow's own take
]


@pytest.mark.parametrize("column", TAKEN, ids=lambda c: f"{c.type}-{len(c)}")
def test_take_is_pyarrows_take(column: pa.Array) -> None:
    """:func:`take` gives pyarrow's take, byte for byte (values under a null, a null index)."""
    n = len(column)
    whole = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    for index in (
        np.arange(n),
        RNG.integers(0, n, 7),
        np.array([-1, 0, -1, n - 1]),
        np.zeros(0, np.int64),
        np.full(3, -1),
    ):
        ref = whole.take(pa.array(np.where(index < 0, 0, index), mask=index < 0))
        got = take(column, index)
        assert got.type == ref.type and got.null_count == ref.null_count
        assert _ipc(got) == _ipc(ref), (column, index)
