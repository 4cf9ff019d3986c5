"""Start-up time of the command line (issue 17: under 0.15 s for ``imupipe --help`` and
``imupipe inspect small.mcap``).

Prints, best of N runs each (wall time of the whole process): a bare ``python -c pass`` (the
floor), ``import imupipe`` (the Python API: issue 29), ``imupipe --help``, ``imupipe convert --help`` and ``imupipe inspect`` on a 2 s MCAP;
inspect's topic figures from the MCAP summary against the same from every message's log time
(what a file without a summary takes), each a fresh process; the peak RSS of the ``inspect``
process; then the slowest imports of the ``inspect`` run (``python -X importtime``), cumulative.

Usage: ``python benchmarks/bench_startup.py [--runs 7]``
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = [sys.executable, "-m", "imupipe.pipeline.cli"]
HERE = str(Path(__file__).resolve().parent)
SUMMARY_CHILD = """
import sys
from pathlib import Path
from imupipe.pipeline.inspect_log import _from_summary
assert _from_summary(Path(sys.argv[1])) is not None
"""
MESSAGES_CHILD = """
import sys
from imupipe.pipeline.inspect_log import _from_messages
from imupipe.readers.spec import InputSpec
_from_messages(InputSpec(path=sys.argv[1]))
"""
PEAK_CHILD = """
import contextlib, io, sys
sys.path.insert(0, sys.argv[2])
from proc_memory import status_bytes
from imupipe.pipeline.cli import main
with contextlib.redirect_stdout(io.StringIO()):
    main(["inspect", sys.argv[1]])
print(status_bytes("VmHWM"))
"""


def best(cmd: list[str], runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        times.append(time.perf_counter() - start)
    return min(times)


def slowest_imports(cmd: list[str], n: int = 8) -> list[tuple[float, str]]:
    err = subprocess.run([sys.executable, "-X", "importtime", *cmd[1:]], capture_output=True,
                         text=True).stderr  # fmt: skip
    rows = []
    for line in err.splitlines():
        if line.startswith("import time:") and "|" in line and "cumulative" not in line:
            _, cumulative, name = line.split("|")
            if not name.startswith("  "):  # top-level imports only (cumulative of their tree)
                rows.append((int(cumulative) / 1e6, name.strip()))
    return sorted(rows, reverse=True)[:n]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        log = Path(d) / "small.mcap"
        subprocess.run([*CLI, "simulate", "static", "--out", str(log), "--duration", "2"],
                       check=True, capture_output=True)  # fmt: skip
        floor = best([sys.executable, "-c", "pass"], args.runs)
        print(f"python -c pass              {floor:6.3f} s (the floor)")
        for label, cmd in [
            ("import imupipe", [sys.executable, "-c", "import imupipe"]),
            ("imupipe --help", [*CLI, "--help"]),
            ("imupipe convert --help", [*CLI, "convert", "--help"]),
            ("imupipe inspect small.mcap", [*CLI, "inspect", str(log)]),
        ]:
            t = best(cmd, args.runs)
            verdict = "meets" if t < 0.15 else "misses"
            print(f"{label:<27} {t:6.3f} s ({t - floor:5.3f} s over python; {verdict} 0.15 s)")
        t = best([sys.executable, "-c", MESSAGES_CHILD, str(log)], args.runs)
        fast = best([sys.executable, "-c", SUMMARY_CHILD, str(log)], args.runs)
        print(
            f"inspect's topics from the MCAP summary {fast:.3f} s against every message's log "
            f"time (the path without a summary) {t:.3f} s, whole process: ratio {fast / t:.2f}"
        )
        peak = int(
            subprocess.run(
                [sys.executable, "-c", PEAK_CHILD, str(log), HERE],
                check=True,
                capture_output=True,
                text=True,
            ).stdout.split()[-1]
        )
        print(f"peak RSS of imupipe inspect small.mcap: {peak / 1e6:.0f} MB")
        print("slowest top-level imports of inspect (cumulative s):")
        for seconds, name in slowest_imports([*CLI, "inspect", str(log)]):
            print(f"  {seconds:6.3f}  {name}")


if __name__ == "__main__":
    main()
