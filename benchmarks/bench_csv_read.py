"""Benchmark (issue 17 item 2, the CSV lever): a 2 h, 400 Hz static CSV into the common table.

Measured in one run, on the same file (imupipe's own layout, as ``imupipe simulate`` writes it:
``t_ns`` and six IMU columns, 2.88 M rows, 412 MB):

- **peer**: ``pyarrow.csv.read_csv(path)`` with its defaults (multithreaded, every column, types
  inferred): the parse alone, no table of ours;
- **ours**: ``imupipe.readers.csv.reader.read_csv``, the whole read into the common table (layout
  sniffing, the exact int64 time column, SI columns, validity); goal: about the peer's time;
- **peak memory** of a fresh process doing each, as VmHWM growth over the process after imports,
  against the size of the common table.

Wall and CPU (all threads) times are the best of ``--repeat`` interleaved runs of each side; the
2-core machine is shared, so the ratios are what count.

    python benchmarks/bench_csv_read.py [--hours 2] [--repeat 5] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from proc_memory import run_probe


def make_csv(path: Path, hours: float) -> None:
    from imupipe.pipeline.simulate import simulate, write_log

    table, _ = simulate(
        "static", {"rate_hz": 400.0, "duration_s": hours * 3600, "temperature": None}, seed=1
    )
    write_log(path, table)


def peer(path: Path) -> int:
    import pyarrow.csv as pacsv

    return pacsv.read_csv(path).num_rows


def ours(path: Path) -> int:
    from imupipe.readers.csv.reader import read_csv
    from imupipe.readers.spec import InputSpec

    return read_csv(InputSpec(path=path))[0].num_rows


def timed(fn, path: Path) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    fn(path)
    return time.perf_counter() - wall, time.process_time() - cpu


MEMORY_PROBE = """
import json, sys
sys.path.insert(0, sys.argv[-1])
from proc_memory import status_bytes
import pyarrow, pyarrow.csv, numpy
from imupipe.readers.csv.reader import read_csv
from imupipe.readers.spec import InputSpec
base = status_bytes('VmRSS')
if sys.argv[2] == "ours":
    table = read_csv(InputSpec(path=sys.argv[1]))[0]
else:
    table = pyarrow.csv.read_csv(sys.argv[1])
print(json.dumps({"base": base, "peak": status_bytes('VmHWM'), "table": table.nbytes}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=2.0)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--keep", type=Path, default=None)
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="imupipe-csv-"))
    work.mkdir(parents=True, exist_ok=True)
    path = work / f"static_{args.hours:g}h.csv"
    if not path.exists():
        make_csv(path, args.hours)
    assert ours(path) == peer(path)
    print(f"load average before: {os.getloadavg()[0]:.2f}; file {path.stat().st_size / 1e6:.0f} MB")
    runs: dict[str, list[tuple[float, float]]] = {"peer": [], "ours": []}
    for _ in range(args.repeat):
        runs["peer"].append(timed(peer, path))
        runs["ours"].append(timed(ours, path))
    best = {k: (min(w for w, _ in v), min(c for _, c in v)) for k, v in runs.items()}
    for k, v in runs.items():
        print(f"  {k}: wall {[round(w, 2) for w, _ in v]} s, cpu {[round(c, 2) for _, c in v]} s")
    (pw, pc), (ow, oc) = best["peer"], best["ours"]
    print(
        f"read: imupipe {ow:.2f} s wall ({oc:.2f} s cpu), pyarrow.csv.read_csv {pw:.2f} s wall "
        f"({pc:.2f} s cpu) -> ratio {ow / pw:.2f} wall, {oc / pc:.2f} cpu (goal: about 1)"
    )
    for side in ("peer", "ours"):
        mem = run_probe(MEMORY_PROBE, path, side)
        growth = mem["peak"] - mem["base"]
        print(
            f"memory ({side}): peak growth {growth / 1e6:.0f} MB, its table "
            f"{mem['table'] / 1e6:.0f} MB -> {growth / mem['table']:.2f}x"
        )
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
