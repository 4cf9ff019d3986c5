"""Issue 17, item 2: what keeps an Allan run fast without changing its results. The deviations'
sums of squares go through BLAS dots of at most ``DOT`` points (single-threaded in OpenBLAS);
a quiet run that writes no corrected MCAP imports neither rich (the progress bar) nor the MCAP
writer. The times themselves: ``benchmarks/bench_allan.py``."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.stages import allan_estimators as est


@pytest.mark.parametrize("n", [1, 7, est.DOT - 1, est.DOT, est.DOT + 1, 3 * est.DOT + 5])
def test_dot_in_pieces_is_the_sum_of_products(n):
    rng = np.random.default_rng(n)
    a, b = rng.standard_normal(n), rng.standard_normal(n)
    assert est._dot(a, b) == pytest.approx(float(np.sum(a * b)), rel=1e-12, abs=1e-12)


def test_sumsq_lagged_matches_the_direct_second_difference():
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.standard_normal((2, 3 * est.CHUNK + 17)), axis=1)
    for m in (1, 3, 64, est.CHUNK // 2, est.CHUNK // 2 + 1, est.CHUNK + 5):
        count = x.shape[1] - 2 * m
        d = x[:, 2 * m :] - 2.0 * x[:, m:-m] + x[:, : -2 * m]
        np.testing.assert_allclose(
            est._sumsq_lagged(x, m, False, count), np.sum(d * d, axis=1), rtol=1e-11
        )


def test_quiet_allan_run_imports_no_progress_bar_nor_mcap_writer(tmp_path):
    table, _ = simulate("static", {"duration_s": 60.0, "rate_hz": 100.0, "temperature": None}, 2)
    write_log(tmp_path / "static.csv", table)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\n\n'
        '[output]\ndir = "out"\nreport = false\n'
    )
    code = (
        "import sys\n"
        "from imupipe.pipeline.run import run\n"
        f"run({str(cfg)!r}, quiet=True)\n"
        "print(sorted(m for m in ('rich', 'imupipe.pipeline.mcap_writer') if m in sys.modules))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().splitlines()[-1] == "[]"
    assert (tmp_path / "out" / "imu.yaml").exists()
