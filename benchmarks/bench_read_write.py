"""Benchmark (issue 3): read and write 1,000,000 sensor_msgs/Imu messages in one MCAP.

Measured in one run, on the same file, against the peers the issue names:

- read to table: ``imupipe.readers.mcap.reader.read_mcap`` vs rosbags ``AnyReader`` +
  ``deserialize`` of every message (goal: >= 10x);
- corrected-MCAP write: ``imupipe.pipeline.writers.mcap.write_mcap`` vs ``mcap_ros2.writer.Writer``
  ``write_message`` per message (goal: >= 5x);
- peak memory growth of a fresh process reading the file, over its size after imports, against
  the size of the decoded table (goal: < 3x);
- with ``--writer-memory N [N ...]`` (issue 17): the peak memory a fresh process adds while
  ``McapTableWriter.write_table`` writes one whole table of N messages, encoded in slices (the
  writer's default) and, for comparison, in one piece (what the writer did before it sliced),
  beside ``mcap_ros2``'s writer in the same run (memory on ``--peer-n`` messages; it holds one
  chunk whatever the count) and the write times.

Prints wall times, the ratios and the memory figures. Not part of the CI test run (minutes of
CPU); ``tests/test_readers_bench.py`` runs a small smoke version.

    python benchmarks/bench_read_write.py [--n 1000000] [--peer-n N] [--keep DIR]
    python benchmarks/bench_read_write.py --writer-memory 1000000 5000000 --peer-n 200000

``--peer-n`` times the peers on the first N messages only and scales linearly (default: all).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from proc_memory import HERE


def make_table(n: int):
    """n Imu messages at 1 kHz with random values, one frame_id (as a real driver publishes)."""
    import pyarrow as pa

    from imupipe.readers.table import make_table as mk

    rng = np.random.default_rng(0)
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 1_000_000
    frames = np.full(n, "imu_link")
    return mk(
        t,
        gyro=rng.normal(0, 0.01, (n, 3)),
        accel=rng.normal(0, 0.1, (n, 3)) + [0, 0, 9.81],
        extra={"frame_id": pa.array(frames)},
        metadata={"topics": {"imu": "/imu/data"}, "frame_id": {"imu": "imu"}},
    )


def timed(fn, *args, **kw):
    start = time.perf_counter()
    out = fn(*args, **kw)
    return time.perf_counter() - start, out


def peer_write(path: Path, table, n: int) -> None:
    """mcap_ros2's writer, one write_message per message."""
    from mcap_ros2.writer import Writer

    from imupipe.pipeline.writers.mcap import msgdef
    from imupipe.readers.table import sensor

    g = sensor(table, "gyro").values[:n]
    a = sensor(table, "accel").values[:n]
    t = table.column("t_ns").to_numpy()[:n]
    frames = table.column("frame_id").to_pylist()[:n]
    with open(path, "wb") as fh:
        writer = Writer(fh)
        schema = writer.register_msgdef("sensor_msgs/msg/Imu", msgdef("sensor_msgs/msg/Imu"))
        for i in range(n):
            ti = int(t[i])
            msg = {
                "header": {
                    "stamp": {"sec": ti // 1_000_000_000, "nanosec": ti % 1_000_000_000},
                    "frame_id": frames[i],
                },
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                "orientation_covariance": [-1.0] + [0.0] * 8,
                "angular_velocity": {"x": g[i, 0], "y": g[i, 1], "z": g[i, 2]},
                "angular_velocity_covariance": [0.0] * 9,
                "linear_acceleration": {"x": a[i, 0], "y": a[i, 1], "z": a[i, 2]},
                "linear_acceleration_covariance": [0.0] * 9,
            }
            writer.write_message("/imu/data", schema, msg, log_time=ti, publish_time=ti)
        writer.finish()


def peer_read(path: Path, n: int) -> int:
    """rosbags AnyReader + deserialize of the first n messages."""
    from rosbags.highlevel import AnyReader

    count = 0
    with AnyReader([path]) as reader:
        for conn, _t, data in reader.messages():
            reader.deserialize(data, conn.msgtype)
            count += 1
            if count >= n:
                break
    return count


MEMORY_PROBE = """
import json, sys
sys.path.insert(0, sys.argv[2])
from proc_memory import status_bytes
from imupipe.readers.mcap.reader import read_mcap
from imupipe.readers.spec import InputSpec
import pyarrow, numpy, zstandard  # noqa
base = status_bytes('VmRSS')
table, _ = read_mcap(InputSpec(path=sys.argv[1]))
peak = status_bytes('VmHWM')
print(json.dumps({"base": base, "peak": peak, "table": table.nbytes, "rows": table.num_rows}))
"""


WRITER_PROBE = """
import json, sys, time
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from proc_memory import status_bytes
from bench_read_write import make_table, peer_write
from imupipe.pipeline.writers.mcap import McapTableWriter
n, how, out = int(sys.argv[2]), sys.argv[3], Path(sys.argv[4])
table = make_table(n)
with open("/proc/self/clear_refs", "w") as fh:  # the high-water mark starts here
    fh.write("5")
base = status_bytes("VmRSS")
start = time.perf_counter()
if how == "mcap_ros2":
    peer_write(out, table, n)
else:
    kw = {"slice_rows": n} if how == "whole" else {}
    with McapTableWriter(out, **kw) as writer:
        writer.write_table(table)
seconds = time.perf_counter() - start
peak = status_bytes("VmHWM")
print(json.dumps({"base": base, "peak": peak, "table": table.nbytes, "seconds": seconds}))
"""


def writer_memory(n: int, how: str, out: Path) -> dict:
    """Peak memory growth of a fresh process writing a table of ``n`` Imu messages: ``sliced``
    (McapTableWriter's default), ``whole`` (one slice) or ``mcap_ros2`` (the peer)."""
    proc = subprocess.run(
        [sys.executable, "-c", WRITER_PROBE, HERE, str(n), how, str(out)],
        capture_output=True,
        text=True,
        check=True,
    )
    out.unlink(missing_ok=True)
    return json.loads(proc.stdout)


def report_writer_memory(sizes: list[int], peer_n: int, work: Path) -> None:
    peer = writer_memory(peer_n, "mcap_ros2", work / "peer.mcap")
    peer_growth = (peer["peak"] - peer["base"]) / 1e6
    per_msg = peer["seconds"] / peer_n
    print(
        f"writer memory, mcap_ros2 write_message on {peer_n} messages: +{peer_growth:.0f} MB, "
        f"{per_msg * 1e6:.1f} us/message"
    )
    for n in sizes:
        row = {how: writer_memory(n, how, work / f"{how}.mcap") for how in ("sliced", "whole")}
        growth = {how: (r["peak"] - r["base"]) / 1e6 for how, r in row.items()}
        print(
            f"writer memory, {n} messages (table {row['sliced']['table'] / 1e6:.0f} MB): "
            f"sliced +{growth['sliced']:.0f} MB in {row['sliced']['seconds']:.2f} s, "
            f"one piece +{growth['whole']:.0f} MB in {row['whole']['seconds']:.2f} s "
            f"({growth['whole'] / growth['sliced']:.1f}x the sliced); mcap_ros2 "
            f"+{peer_growth:.0f} MB ({growth['sliced'] / max(peer_growth, 1):.1f}x ours/peer), "
            f"{per_msg * n:.1f} s scaled -> {per_msg * n / row['sliced']['seconds']:.1f}x faster"
        )


def memory(path: Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", MEMORY_PROBE, str(path), HERE],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--peer-n", type=int, default=None)
    parser.add_argument("--keep", type=Path, default=None)
    parser.add_argument("--repeat", type=int, default=3, help="reads: best of this many, each side")
    parser.add_argument(
        "--writer-memory", type=int, nargs="+", metavar="N", help="only the writer memory probes"
    )
    args = parser.parse_args()
    n = args.n
    peer_n = min(args.peer_n or n, n)
    if args.writer_memory:
        work = args.keep or Path(tempfile.mkdtemp(prefix="imupipe-bench-"))
        work.mkdir(parents=True, exist_ok=True)
        report_writer_memory(args.writer_memory, args.peer_n or 100_000, work)
        return

    from imupipe.pipeline.writers.mcap import write_mcap
    from imupipe.readers.mcap.reader import read_mcap
    from imupipe.readers.spec import InputSpec

    work = args.keep or Path(tempfile.mkdtemp(prefix="imupipe-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    table = make_table(n)
    ours_path = work / "ours.mcap"
    peer_path = work / "peer.mcap"

    t_write, _ = timed(write_mcap, ours_path, table)
    t_peer_write, _ = timed(peer_write, peer_path, table, peer_n)
    t_peer_write *= n / peer_n
    # reads: best of --repeat for each side (the machine is noisy; first-touch page faults vary)
    reads = [timed(read_mcap, InputSpec(path=ours_path)) for _ in range(args.repeat)]
    assert all(r[1][0].num_rows == n for r in reads)
    t_read = min(r[0] for r in reads)
    peer_reads = [timed(peer_read, ours_path, peer_n) for _ in range(args.repeat)]
    t_peer_read = min(t for t, _ in peer_reads) * n / peer_reads[0][1]
    mem = memory(ours_path)
    growth = (mem["peak"] - mem["base"]) / mem["table"]

    scaled = "" if peer_n == n else f" (peer timed on {peer_n} messages, scaled)"
    print(f"messages: {n}; file {ours_path.stat().st_size / 1e6:.1f} MB{scaled}")
    print(
        f"reads, each side (s): imupipe {[round(r[0], 2) for r in reads]}, "
        f"rosbags {[round(t * n / c, 2) for t, c in peer_reads]}"
    )
    print(
        f"read : imupipe {t_read:.2f} s ({n / t_read / 1e6:.2f} M msg/s), "
        f"rosbags AnyReader+deserialize {t_peer_read:.2f} s -> {t_peer_read / t_read:.1f}x"
    )
    print(
        f"write: imupipe {t_write:.2f} s ({n / t_write / 1e6:.2f} M msg/s), "
        f"mcap_ros2 write_message {t_peer_write:.2f} s -> {t_peer_write / t_write:.1f}x"
    )
    print(
        f"memory: table {mem['table'] / 1e6:.0f} MB, peak growth "
        f"{(mem['peak'] - mem['base']) / 1e6:.0f} MB -> {growth:.2f}x the table"
    )


if __name__ == "__main__":
    main()
