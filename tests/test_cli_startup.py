"""Issue 17: a command line that starts fast. ``imupipe --help`` and ``imupipe COMMAND --help``
import only what they show: no numpy, no pyarrow, no Rerun, no Ray (measured with ``python -X
importtime``; the times themselves are in ``benchmarks/bench_startup.py``)."""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("numpy", "pyarrow", "rerun", "ray", "scipy", "rosbags", "mcap", "rich")


def imported(*args: str) -> set[str]:
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "imupipe.pipeline.cli", *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [line.split("|")[-1].strip() for line in proc.stderr.splitlines() if "|" in line]
    return {name.split(".")[0] for name in lines}


def test_help_imports_nothing_heavy():
    assert not imported("--help") & set(HEAVY)


def test_convert_help_imports_only_its_parser():
    assert not imported("convert", "--help") & set(HEAVY)


def test_read_does_not_import_convert_or_run():
    """Issue 39: ``imupipe.read`` loads the readers, not the fleet conversion (process pool,
    MCAP writer) nor the run (0.05-0.08 s of CPU a process); ``imupipe.convert`` still works."""
    code = (
        "import sys, imupipe; imupipe.read; imupipe.inspect; imupipe.Calibration; "
        "heavy = [m for m in ('imupipe.pipeline.convert.fleet', 'imupipe.pipeline.run', "
        "'multiprocessing', 'zstandard') if m in sys.modules]; "
        "assert not heavy, heavy; "
        "assert imupipe.convert.__module__ == 'imupipe.pipeline.convert.fleet'; "
        "assert imupipe.ConvertSummary.__name__ == 'ConvertSummary'"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
