"""Fault injection: hostile CSVs through ``imupipe run`` and ``imupipe convert`` (issue 18).

Hypothesis damages a good CSV (cells replaced by text, empty, NaN, huge or negative numbers;
lines dropped, duplicated or cut; the header changed); each run keeps the contract of
:mod:`faults`, and when it succeeds the corrected MCAP holds one Imu message per row that had one.
The CSV reader's own cases (duplicate column names, negative or overflowing times, float stamps,
endless files) are one line naming the file, line and column.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from faults import check, cli, snapshot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_fault_config import good_csv

from helpers import decode_mcap

CFG = (
    '[inputs.a]\npath = "a.csv"\n\n[[stages]]\ntype = "gyro_bias"\n\n'
    '[output]\ndir = "out"\nrerun = false\n'
)
CSV = good_csv(200, seed=3)


def run_csv(root: Path, text: str | bytes, case: str, cfg: str = CFG) -> tuple[int, str]:
    path = root / "a.csv"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    (root / "cfg.toml").write_text(cfg)
    before = snapshot(root)
    code, err = cli("run", root / "cfg.toml", "--quiet")
    check(case, code, err, root, before, [root / "out"])
    return code, err


cells = st.one_of(
    st.sampled_from(["", "nan", "NaN", "inf", "-inf", "abc", "1e308", "-1e308", "1e400", " ", '"']),
    st.integers(min_value=-(2**70), max_value=2**70).map(str),
    st.floats(allow_nan=True).map(repr),
    st.text(max_size=4).filter(lambda s: "\n" not in s and "\r" not in s),
)


@st.composite
def damaged(draw, kinds=("cell", "cell", "drop", "dup", "cut", "header")) -> str:
    lines = CSV.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        what = draw(st.sampled_from(kinds))
        i = draw(st.integers(0 if what in ("cut", "header", "dup") else 1, len(lines) - 1))
        if what in ("cell", "value"):  # "value": not the time column (see test_times_*)
            cols = lines[i].split(",")
            cols[draw(st.integers(0 if what == "cell" else 1, len(cols) - 1))] = draw(cells)
            lines[i] = ",".join(cols)
        elif what == "drop":
            del lines[i]
        elif what == "dup":
            lines.insert(i, lines[i])
        elif what == "cut":
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
        else:
            cols = lines[0].split(",")
            # (two columns of one name: test_two_columns_of_one_name, until the readers fix)
            cols[draw(st.integers(0, len(cols) - 1))] = draw(cells)
            lines[0] = ",".join(cols)
        if not lines:
            break
    return "\n".join(lines) + "\n"


def _contract(text: str) -> None:
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        code, err = run_csv(root, text, text[:300])
        if code == 0:
            rows = text.splitlines()[1:]
            imu = decode_mcap(root / "out" / "a.mcap").get("/imu/data", [])
            assert len(imu) <= len(rows), "more Imu messages than rows"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(damaged(kinds=("value", "drop", "dup")))
def test_damaged_rows_keep_the_contract(text):
    """Data rows damaged: value cells replaced, rows dropped or repeated."""
    _contract(text)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(damaged())
def test_damaged_csvs_keep_the_contract(text):
    """Anything damaged: also the header, and lines cut anywhere."""
    _contract(text)


def lines_of(n: int = 100) -> list[str]:
    return good_csv(n, seed=4).splitlines()


def test_a_nan_cell_travels_as_nan(tmp_path):
    lines = lines_of()
    cols = lines[10].split(",")
    cols[5] = "nan"  # accel_y of row 10
    lines[10] = ",".join(cols)
    code, err = run_csv(tmp_path, "\n".join(lines) + "\n", "nan accel cell")
    assert code == 0, err
    assert len(decode_mcap(tmp_path / "out" / "a.mcap")["/imu/data"]) == 100


def test_no_gyro_columns_invents_no_gyro(tmp_path):
    """A CSV without gyro columns: one Imu message per row (its accelerometer), the gyro written
    as NaN with element 0 of its covariance -1 ("no data", sensor_msgs/Imu), never zeros."""
    lines = [",".join(line.split(",")[:1] + line.split(",")[4:]) for line in lines_of()]
    cfg = CFG.replace('type = "gyro_bias"', 'type = "average"') + 'apply_to = ["a"]\n'
    code, err = run_csv(tmp_path, "\n".join(lines) + "\n", "no gyro columns", cfg)
    assert code == 0, err
    imu = decode_mcap(tmp_path / "out" / "a.mcap")["/imu/data"]
    assert len(imu) == len(lines) - 1
    for _, msg in imu:
        assert np.isnan(msg.angular_velocity.x) and msg.angular_velocity_covariance[0] == -1.0
        assert np.isfinite(msg.linear_acceleration.z)


def test_two_columns_of_one_name(tmp_path):
    lines = lines_of()
    lines[0] = lines[0].replace("accel_z", "accel_y")
    code, err = run_csv(tmp_path, "\n".join(lines) + "\n", "duplicate column")
    assert code == 2 and "accel_y" in err


@pytest.mark.parametrize("stamp", ["-5000000", "99999999999999999999"], ids=["negative", "int64+"])
def test_times_out_of_range(tmp_path, stamp):
    lines = lines_of()
    lines[5] = stamp + lines[5][lines[5].index(",") :]
    code, err = run_csv(tmp_path, "\n".join(lines) + "\n", f"t_ns {stamp}")
    assert code == 2 and "line 6" in err and "t_ns" in err, err


def test_one_float_stamp_shifts_no_other_stamp(tmp_path):
    """Stamps near 1.7e18 ns with one cell written ``1.7e18``: every other stamp must come out
    exactly (a column read as float64 moves them by up to 128 ns)."""
    from helpers import stamps_ns

    lines = lines_of()
    stamps = [1_700_000_000_000_000_000 + 10_000_000 * i + 7 for i in range(len(lines) - 1)]
    for i, t in enumerate(stamps, start=1):
        lines[i] = f"{t}" + lines[i][lines[i].index(",") :]
    lines[1] = "1.7e18" + lines[1][lines[1].index(",") :]
    code, err = run_csv(tmp_path, "\n".join(lines) + "\n", "1.7e18")
    assert code == 0, err
    got = stamps_ns(decode_mcap(tmp_path / "out" / "a.mcap")["/imu/data"]).tolist()
    assert got == [1_700_000_000_000_000_000] + stamps[1:]


def test_dev_zero_is_refused(tmp_path):
    """An endless input (a ``.csv`` link to /dev/zero) is refused, not read until memory runs
    out (run in a child process with 3 GB of address space, so that it cannot take the
    machine's memory)."""
    import subprocess
    import sys

    (tmp_path / "z.csv").symlink_to("/dev/zero")
    (tmp_path / "cfg.toml").write_text(CFG.replace("a.csv", "z.csv"))
    limit = "import resource; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30)); "
    proc = subprocess.run(
        [sys.executable, "-c", limit + "from imupipe.pipeline.cli import main; "
         f"raise SystemExit(main(['run', {str(tmp_path / 'cfg.toml')!r}, '-q']))"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2 and "z.csv" in proc.stderr, proc.stderr
