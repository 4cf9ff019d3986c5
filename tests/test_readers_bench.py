"""Issue 3: a small smoke version of ``benchmarks/bench_read_write.py`` (the 1,000,000-message
run is a script, not part of CI). On 20,000 Imu messages: our read and write must beat the peers
by a clear margin even on a loaded machine, and what is read equals what was written."""

from __future__ import annotations

import sys
import time

import numpy as np

from imupipe.pipeline.writers.mcap import write_mcap
from imupipe.readers.mcap.reader import read_mcap
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import sensor

from conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
from bench_read_write import make_table, peer_read, peer_write  # noqa: E402


def _best(fn, *args, repeat: int = 2) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - start)
    return min(times)


def test_read_write_smoke(tmp_path):
    n, peer_n = 20_000, 2_000
    table = make_table(n)
    ours = tmp_path / "ours.mcap"
    t_write = _best(write_mcap, ours, table)
    t_peer_write = _best(peer_write, tmp_path / "peer.mcap", table, peer_n) * n / peer_n
    t_read = _best(read_mcap, InputSpec(path=ours))
    t_peer_read = _best(peer_read, ours, peer_n) * n / peer_n
    got, _ = read_mcap(InputSpec(path=ours))
    np.testing.assert_array_equal(sensor(got, "gyro").values, sensor(table, "gyro").values)
    print(f"read {t_peer_read / t_read:.1f}x, write {t_peer_write / t_write:.1f}x")
    assert t_peer_read / t_read > 3
    assert t_peer_write / t_write > 2
