"""Benchmark (issue 16): reading a PX4 ULog into the common table.

imupipe's ULog reader parses with pyulog, restricted to the topics it reads (a filter list), then
builds the table. Measured in one run, on the same file, against the peer the issue names:
pyulog's full parse (``ULog(path)``, every topic), which is what a user of pyulog pays before
touching ``sensor_combined``. Prints the best-of-N wall times, their ratio (imupipe / pyulog:
below 1 is faster) and the peak memory growth of a fresh process reading the file with each.

    python benchmarks/bench_ulog.py [LOG.ulg] [--repeat 5]

Default log: ``../shared/data/logs/px4_ulog/sample.ulg`` (4 MB, 68 s, 17,070 sensor_combined).
"""

from __future__ import annotations

import argparse
import json
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

    from imupipe.readers.spec import InputSpec
    from imupipe.readers.table import counts
    from imupipe.readers.ulog.reader import read_ulog

    spec = InputSpec(path=args.log)
    table, _ = read_ulog(spec)
    ours = best(lambda: read_ulog(spec), args.repeat)
    peer = best(lambda: ULog(str(args.log)), args.repeat)
    mib = 1024 * 1024
    print(f"{args.log.name}: {args.log.stat().st_size / mib:.1f} MiB, table {counts(table)}")
    print(f"imupipe read_ulog (table)   {ours * 1e3:8.1f} ms")
    print(f"pyulog ULog (full parse)    {peer * 1e3:8.1f} ms")
    print(f"ratio imupipe / pyulog      {ours / peer:8.2f}")
    print(
        f"peak memory growth: imupipe {peak_growth('imupipe', args.log) / mib:.1f} MiB, "
        f"pyulog {peak_growth('pyulog', args.log) / mib:.1f} MiB"
    )


if __name__ == "__main__":
    main()
