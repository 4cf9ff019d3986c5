"""Benchmark (issue 16): reading a PX4 ULog into the common table.

imupipe's ULog reader parses the records itself (``imupipe.readers.ulog.records``: pyulog's
result, the record walk compiled in ``readers/_records.c``), restricted to the topics it reads,
then builds the table. Measured in one run, on the same file, against the peers the issues name:
pyulog's full parse (``ULog(path)``, every topic: what a user of pyulog pays before touching
``sensor_combined``; issue 16) and pyulog reading only the table's topics
(``message_name_filter_list``; issue 39). Also imupipe with the pure-Python walk
(``IMUPIPE_PURE_PYTHON=1``: an install without a C compiler). Prints the best-of-N wall times,
the ratios (imupipe / pyulog: below 1 is faster) and the peak memory growth of a fresh process
reading the file with each.

    python benchmarks/bench_ulog.py [LOG.ulg] [--repeat 5]

Default log: ``../shared/data/logs/px4_ulog/sample.ulg`` (4 MB, 68 s, 17,070 sensor_combined).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from proc_memory import HERE

DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "logs" / "px4_ulog"

PROBE = """
import json, sys
sys.path.insert(0, {here!r})
from proc_memory import status_bytes
import pyulog, numpy, pyarrow
from imupipe.readers.spec import InputSpec
from imupipe.readers.ulog.reader import read_ulog
base = status_bytes("VmRSS")
if {which!r} == "imupipe":
    table, _ = read_ulog(InputSpec(path={path!r}))
else:
    log = pyulog.ULog({path!r})
print(json.dumps({{"growth": status_bytes("VmHWM") - base}}))
"""


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def peak_growth(which: str, path: Path) -> int:
    code = PROBE.format(here=HERE, which=which, path=str(path))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)["growth"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", nargs="?", type=Path, default=DEFAULT / "sample.ulg")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    from pyulog import ULog

    from imupipe.readers.record_walk import PURE_PYTHON_ENV, compiled
    from imupipe.readers.spec import InputSpec
    from imupipe.readers.table import counts, metadata
    from imupipe.readers.ulog.reader import read_ulog

    spec = InputSpec(path=args.log)
    table, _ = read_ulog(spec)
    topics = sorted({t.split("/")[0] for t in metadata(table)["topics"].values()})
    ours = best(lambda: read_ulog(spec), args.repeat)
    peer = best(lambda: ULog(str(args.log)), args.repeat)
    filtered = best(lambda: ULog(str(args.log), message_name_filter_list=topics), args.repeat)
    os.environ[PURE_PYTHON_ENV] = "1"
    read_ulog(spec)
    pure = best(lambda: read_ulog(spec), args.repeat)
    del os.environ[PURE_PYTHON_ENV]
    mib = 1024 * 1024
    print(f"{args.log.name}: {args.log.stat().st_size / mib:.1f} MiB, table {counts(table)}")
    print(f"compiled record walk built: {compiled()}")
    print(f"imupipe read_ulog (table)   {ours * 1e3:8.1f} ms")
    print(f"  pure-Python record walk   {pure * 1e3:8.1f} ms")
    print(f"pyulog ULog (full parse)    {peer * 1e3:8.1f} ms")
    print(f"pyulog ULog {topics}  {filtered * 1e3:8.1f} ms")
    print(
        f"ratio imupipe / pyulog      {ours / peer:8.2f} (full), {ours / filtered:.2f} (filtered)"
    )
    print(
        f"  pure-Python walk          {pure / peer:8.2f} (full), {pure / filtered:.2f} (filtered)"
    )
    print(
        f"peak memory growth: imupipe {peak_growth('imupipe', args.log) / mib:.1f} MiB, "
        f"pyulog {peak_growth('pyulog', args.log) / mib:.1f} MiB"
    )


if __name__ == "__main__":
    main()
