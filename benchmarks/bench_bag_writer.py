"""Benchmark (issue 39): ``write_ros1_bag`` (numpy, a chunk at a time) against rosbags'
``rosbag1.Writer`` fed one message at a time (the writer ``imupipe simulate`` used before).

Each writer runs in a fresh Python on the same simulated table (the ``static`` scenario: Imu and
Temperature, ``--rate`` Hz for ``--duration`` s; the README's bag is ``--rate 100 --duration
7200``, 1.44 M messages). Prints per writer the CPU time of the write alone (best of
``--repeat``), the process's peak RSS (``VmHWM``) and its rise over the RSS before the write, and
the ratio of CPU times; checks the two bags are the same byte for byte.

    python benchmarks/bench_bag_writer.py [--rate 100] [--duration 7200] [--compression lz4]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from proc_memory import run_probe

PROBE = """
import json, sys, time
sys.path.insert(0, sys.argv[-1])
from pathlib import Path
from proc_memory import status_bytes
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers import bag

which, out, rate, duration, compression = sys.argv[1:6]
table, _ = simulate("static", {"rate_hz": float(rate), "duration_s": float(duration)}, seed=1)
rss = status_bytes("VmRSS")


def rosbags_writer(path, table, compression):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    streams, items = bag._ordered(table, "ros1")
    writer = Writer(path)
    if compression != "none":
        writer.set_compression(Writer.CompressionFormat[compression.upper()])
    with writer:
        conns = {s: writer.add_connection(tp, ty, typestore=store) for s, (tp, ty) in streams.items()}
        for t, _, stream, payload in items:
            writer.write(conns[stream], t, payload)


write = bag.write_ros1_bag if which == "imupipe" else rosbags_writer
Path(out).unlink(missing_ok=True)
cpu = time.process_time()
write(Path(out), table, compression)
cpu = time.process_time() - cpu
print(json.dumps({"cpu": cpu, "peak": status_bytes("VmHWM"), "rss": rss, "n": table.num_rows}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--duration", type=float, default=7200.0)
    ap.add_argument("--compression", default="lz4", choices=("lz4", "bz2", "none"))
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    mb = 1 << 20
    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for which in ("imupipe", "rosbags"):
            out = Path(tmp) / f"{which}.bag"
            res = [
                run_probe(PROBE, which, out, args.rate, args.duration, args.compression)
                for _ in range(args.repeat)
            ]
            runs[which] = min(res, key=lambda r: r["cpu"])
            r = runs[which]
            print(
                f"{which:8s} write {r['cpu']:6.2f} s CPU  peak {r['peak'] / mb:6.0f} MB "
                f"(+{(r['peak'] - r['rss']) / mb:.0f} MB over the table)  "
                f"{out.stat().st_size / mb:.0f} MB bag"
            )
        same = (Path(tmp) / "imupipe.bag").read_bytes() == (Path(tmp) / "rosbags.bag").read_bytes()
        ratio = runs["rosbags"]["cpu"] / runs["imupipe"]["cpu"]
        print(
            f"{runs['imupipe']['n']} rows, {args.compression}: imupipe {ratio:.1f}x less CPU than "
            f"rosbags' Writer; bags identical byte for byte: {same}"
        )


if __name__ == "__main__":
    main()
