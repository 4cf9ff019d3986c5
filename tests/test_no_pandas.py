"""Issue 39: a read or a convert never imports pandas (imupipe does not use it; where it is
installed, pyarrow's ``pa.array``/``pa.scalar``/``to_numpy`` import it on first use, +0.5 s and
+32 MB per process). Each command runs in a fresh process whose path starts with a stand-in
``pandas`` package that records being imported (and then fails, as an absent pandas does), so the
test holds whether the real pandas is installed or not."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap

DATA = Path(__file__).resolve().parent / "data"

STAND_IN = """
import os, traceback
with open(os.environ["PANDAS_MARK"], "a") as fh:
    fh.write("".join(traceback.format_stack()[:-1]) + "\\n----\\n")
raise ImportError("pandas stand-in: imported by imupipe")
"""

CALIBRATION = {
    "imupipe_version": "test",
    "chain": [
        {
            "type": "gyro_calibration",
            "sensor": "gyro",
            "kind": "linear",
            "matrix": [[1.0, 0.001, 0.0], [0.0, 1.0, 0.0], [0.0, 0.002, 0.998]],
            "offset": [0.01, -0.02, 0.005],
        }
    ],
    "results": {},
}


def run_without_pandas(tmp_path: Path, *argv: str) -> str:
    """Run ``python ARGV`` with the stand-in first on the path; what imported it ('' if none)."""
    (tmp_path / "stand_in" / "pandas").mkdir(parents=True)
    (tmp_path / "stand_in" / "pandas" / "__init__.py").write_text(STAND_IN)
    mark = tmp_path / "pandas_imported.txt"
    env = dict(os.environ, PANDAS_MARK=str(mark))
    env["PYTHONPATH"] = os.pathsep.join(
        [str(tmp_path / "stand_in"), *filter(None, [os.environ.get("PYTHONPATH")])]
    )
    proc = subprocess.run(
        [sys.executable, *argv], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return mark.read_text() if mark.exists() else ""


def test_stand_in_is_seen(tmp_path: Path) -> None:
    """The check itself: pyarrow's own conversion does import the stand-in."""
    code = "import numpy, pyarrow; pyarrow.array(numpy.arange(3))"
    assert run_without_pandas(tmp_path, "-c", code) != ""


def test_convert_of_a_small_log_imports_no_pandas(tmp_path: Path) -> None:
    table, _ = simulate(
        "static", {"rate_hz": 200.0, "duration_s": 5.0, "temperature": None}, seed=3
    )
    log = tmp_path / "small.mcap"
    write_mcap(log, table)
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps(CALIBRATION))
    out = tmp_path / "out"
    argv = ["-m", "imupipe.pipeline.cli", "convert", "-q", "--calibration", str(cal)]
    assert run_without_pandas(tmp_path, *argv, "--out", str(out), str(log)) == ""
    assert (out / "small.mcap").exists()


@pytest.mark.parametrize(
    "log", [DATA / "px4_ulog" / "pixhawk6c_bmi055.ulg", DATA / "px4_ulog" / "sample_log_small.ulg"]
)
def test_read_imports_no_pandas(tmp_path: Path, log: Path) -> None:
    code = "import sys, imupipe; t = imupipe.read(sys.argv[1]); assert t.num_rows > 0"
    assert run_without_pandas(tmp_path, "-c", code, str(log)) == ""


@pytest.mark.parametrize(
    "log", [DATA / "px4_ulog" / "pixhawk6c_bmi055.ulg", DATA / "px4_ulog" / "sample_log_small.ulg"]
)
def test_read_of_a_flight_log_imports_no_pyarrow_compute(log: Path) -> None:
    """A ULog read, both row layouts, never imports ``pyarrow.compute`` (0.06-0.09 s CPU in a
    fresh process; ``Table.take`` imports it: the reader's takes are
    :func:`imupipe.readers.arrays.take`)."""
    code = (
        "import sys, imupipe\n"
        "for rows in ('samples', 'messages'):\n"
        "    assert imupipe.read(sys.argv[1], rows=rows).num_rows > 0\n"
        "assert 'pyarrow.compute' not in sys.modules, 'pyarrow.compute imported'\n"
    )
    proc = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", code, str(log)], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
