"""Issue 17, item 3: the pages a read never needs are never mapped. A column whose every value
is +0.0 (a driver's unknown covariance or variance) is left as the kernel's untouched zeros, in
the large stream's columns and in the full-length columns of a slow topic beside it; a column
with values is mapped whole. Checked with ``mincore`` (Linux), on an MCAP large enough for the
page-mapping thread to run, in a process of its own: glibc serves a large ``calloc`` from fresh
(unmapped) pages only above its mmap threshold, which grows with a process's frees up to 32 MiB;
the check fixes it at 128 KiB (``mallopt``), so that this small log's columns come from fresh
pages as a long log's do, without changing the test session's allocator."""

from __future__ import annotations

import ctypes
import ctypes.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import resident

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mincore: Linux")


def resident_column(column) -> float:
    """The share of the whole pages under an Arrow column's values that are mapped."""
    assert column.num_chunks == 1
    chunk = column.chunk(0)
    buffer = (chunk.values if hasattr(chunk, "values") else chunk).buffers()[1]  # no copy
    return resident(buffer.address, buffer.size)


def check(path: Path) -> None:
    """Write and read an Imu + 1 Hz Temperature log; assert what is mapped (the child)."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    assert libc.mallopt(-3, 128 * 1024), "mallopt(M_MMAP_THRESHOLD)"
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_read_limits import make_table

    from imupipe.pipeline.writers.mcap import write_mcap
    from imupipe.readers.mcap.reader import read_mcap
    from imupipe.readers.spec import InputSpec
    from imupipe.readers.table_buffer import PREFAULT_ROWS

    n = 3 * PREFAULT_ROWS
    write_mcap(path, make_table(n, temperature_hz=1.0))
    table, _ = read_mcap(InputSpec(path=path))
    assert table.num_rows > n  # the temperature rows among the Imu ones
    assert resident_column(table.column("temperature")) > 0.9  # a value every 401 rows: every page
    assert resident_column(table.column("gyro_x")) > 0.9
    for name in ("temperature_var", "orientation_x", "gyro_cov"):
        assert resident_column(table.column(name)) < 0.05, name  # before anything reads them
        chunk = table.column(name).chunk(0)
        values = chunk.values if hasattr(chunk, "values") else chunk
        assert not np.any(values.fill_null(0.0).to_numpy(zero_copy_only=False)), name


def test_zero_columns_of_both_streams_stay_unmapped(tmp_path):
    proc = subprocess.run(
        [sys.executable, __file__, str(tmp_path / "imu_temp.mcap")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]


if __name__ == "__main__":
    check(Path(sys.argv[1]))
