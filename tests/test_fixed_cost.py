"""Issue 39: the fixed cost of a command on a short log. ``imupipe convert`` of an MCAP whose
messages carry one frame_id imports neither ``pyarrow.compute`` (0.05-0.09 s CPU: a tenth of
converting a 1k-message log) nor anything the format does not need; the writer's own frame_id
grouping (:func:`imupipe.pipeline.writers.mcap._frame_codes`) gives what pyarrow's
``dictionary_encode`` gives."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import _frame_codes, write_mcap

CASES = {
    "one string": pa.chunked_array([pa.array(["imu"] * 5)]),
    "one string, two chunks": pa.chunked_array([pa.array(["imu"] * 3), pa.array(["imu"] * 2)]),
    "sliced": pa.chunked_array([pa.array(["x", "imu", "imu", "imu"]).slice(1)]),
    "empty strings": pa.chunked_array([pa.array([""] * 4)]),
    "large string": pa.chunked_array([pa.array(["imu"] * 4, pa.large_string())]),
    "same length, differ": pa.chunked_array([pa.array(["aa", "ab", "aa", "ba"])]),
    "lengths differ": pa.chunked_array([pa.array(["a", "aa", "a"])]),
    "nulls": pa.chunked_array([pa.array(["a", None, "a"])]),
    "all null": pa.chunked_array([pa.array([None, None], pa.string())]),
    "unicode": pa.chunked_array([pa.array(["größe"] * 3)]),
    "dictionary one": pa.chunked_array(
        [pa.DictionaryArray.from_arrays(pa.array([1, 1, 1], pa.int8()), ["a", "imu"])]
    ),
    "dictionary two": pa.chunked_array(
        [pa.DictionaryArray.from_arrays(pa.array([1, 0, 1], pa.int8()), ["a", "imu"])]
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_frame_codes_are_dictionary_encodes(name: str) -> None:
    frames = CASES[name]
    filled = pc.fill_null(frames, pa.scalar("meta", pa.string()))
    encoded = pc.dictionary_encode(filled.combine_chunks())
    want = [str(x) for x in encoded.dictionary.to_pylist()]
    want_codes = np.asarray(encoded.indices)
    names, codes = _frame_codes(frames, np.arange(len(frames)), "meta")
    # the rows of each frame_id that is used (the writer skips unused dictionary entries)
    got = {n: np.flatnonzero(codes == i).tolist() for i, n in enumerate(names)}
    expected = {n: np.flatnonzero(want_codes == i).tolist() for i, n in enumerate(want)}
    assert {k: v for k, v in got.items() if v} == {k: v for k, v in expected.items() if v}
    rows = np.arange(len(frames))[::2]  # some rows only, as a stream of a mixed table
    taken = pc.fill_null(frames.take(pa.array(rows)), pa.scalar("meta", pa.string()))
    encoded = pc.dictionary_encode(taken.combine_chunks())
    want = [str(x) for x in encoded.dictionary.to_pylist()]
    names, codes = _frame_codes(frames, rows, "meta")
    got = {n: np.flatnonzero(codes == i).tolist() for i, n in enumerate(names)}
    expected = {
        n: np.flatnonzero(np.asarray(encoded.indices) == i).tolist() for i, n in enumerate(want)
    }
    assert {k: v for k, v in got.items() if v} == {k: v for k, v in expected.items() if v}


PROBE = """
import sys
from imupipe.pipeline.cli import main
code = main(sys.argv[1:])
heavy = ("pyarrow.compute", "pyarrow.parquet", "pandas", "scipy", "rerun", "rosbags", "pyulog",
         "pymavlink")
print(sorted(m for m in sys.modules if m.split(".")[0] in heavy or m in heavy))
sys.exit(code)
"""


def test_convert_of_a_short_mcap_imports_only_what_it_needs(tmp_path: Path) -> None:
    table, _ = simulate("static", {"rate_hz": 200.0, "duration_s": 5.0, "temperature": None}, 3)
    log = tmp_path / "short.mcap"
    write_mcap(log, table)
    cal = tmp_path / "calibration.json"
    cal.write_text(
        json.dumps(
            {
                "imupipe_version": "test",
                "chain": [
                    {
                        "type": "gyro_calibration",
                        "sensor": "gyro",
                        "kind": "linear",
                        "matrix": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                        "offset": [0.01, -0.02, 0.005],
                    }
                ],
                "results": {},
            }
        )
    )
    out = tmp_path / "out"
    argv = ["convert", "-q", "--calibration", str(cal), "--out", str(out), str(log)]
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "[]"
    assert (out / "short.mcap").exists()


@pytest.mark.parametrize("offset", [0, 1])
@pytest.mark.parametrize("nulls", [False, True])
def test_list_columns_read_without_compute_as_with_it(offset: int, nulls: bool) -> None:
    """A covariance column's values as :func:`_column_or` reads them (null lists: zeros) equal
    ``pc.if_else(valid, column, zeros).flatten()``, on a sliced array too."""
    from imupipe.pipeline.writers.mcap import _column_or

    rng = np.random.default_rng(1)
    flat = pa.array(rng.standard_normal(6 * 9))
    mask = pa.array([False, True, False, False, True, False]) if nulls else None
    lists = pa.FixedSizeListArray.from_arrays(flat, 9, mask=mask).slice(offset)
    table = pa.table({"gyro_cov": lists})
    rows = np.arange(len(lists))
    got = _column_or(table, "gyro_cov", rows, np.zeros((1, 9)))
    zeros = pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(9)), 9)[0]
    filled = pc.if_else(pc.is_valid(lists), lists, zeros) if nulls else lists
    want = np.asarray(filled.flatten()).reshape(len(rows), 9)
    assert np.array_equal(got, want)
