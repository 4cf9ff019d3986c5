"""Issue 39: a fleet of many short logs, whole commands, against a plain rosbags read loop.

A fleet is often thousands of short logs (one per flight or per boot); there the fixed cost per
command and per log decides. Measured, each as a user runs it (a fresh process: interpreter
start, imports, planning, writing and verifying included), imupipe and the peer alternating in
pairs so that both see the same load:

[1] one log of ``--log-messages`` (default 1,000) ``sensor_msgs/msg/Imu`` messages: ``imupipe
    convert`` against ``python peer.py LOG`` (rosbags' ``AnyReader`` reading and deserialising
    every message; the typestore built once).
[2] ``--logs`` (default 100) such logs in one run: ``imupipe convert --jobs 1 FOLDER`` against the
    same rosbags loop over all of them in one process. Goal (issue 39): >= 5x faster.

Each pair prints both wall times, the ratio (peer / imupipe), both CPU times (user + system of
the process and its children, from ``getrusage``: far less moved by the other sessions on a
shared machine than the wall time) and their ratio, and both processes' peak RSS (their own
``VmHWM``); the summary gives each ratio's min and median over the pairs. Only ratios measured in
the same pair count.

Usage: ``python benchmarks/bench_fleet.py [--logs 100] [--log-messages 1000] [--pairs 2]``
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_convert import CALIBRATION, make_log  # noqa: E402
from proc_memory import run_measured  # noqa: E402

PEER = """
import sys
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

store = get_typestore(Stores.ROS2_HUMBLE)
n = 0
for path in sys.argv[2:]:
    with AnyReader([Path(path)], default_typestore=store) as reader:
        for conn, _, raw in reader.messages(connections=reader.connections):
            reader.deserialize(raw, conn.msgtype)
            n += 1
with open("/proc/self/status") as fh:
    hwm = next(line.split()[1] for line in fh if line.startswith("VmHWM:"))
with open(sys.argv[1], "w") as fh:
    fh.write(f"{n} {hwm}")
"""
"""The peer: rosbags' read-and-deserialise loop over the logs given; writes ``messages VmHWM``."""


def children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished children so far."""
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def peer(logs: list[Path], note: Path) -> tuple[float, float, float, int]:
    """(seconds, CPU seconds, peak RSS MB, messages) of the rosbags loop in a fresh process."""
    start, cpu = time.perf_counter(), children_cpu()
    subprocess.run([sys.executable, "-c", PEER, str(note), *map(str, logs)], check=True)
    seconds, cpu = time.perf_counter() - start, children_cpu() - cpu
    n, hwm = note.read_text().split()
    return seconds, cpu, int(hwm) / 1024, int(n)


def ours(target: Path, cal: Path, out: Path, n_logs: int) -> tuple[float, float, float, int]:
    """(seconds, CPU seconds, the command's peak RSS MB, messages) of ``imupipe convert --jobs
    1``."""
    from imupipe.pipeline.convert.manifest import read_manifest

    shutil.rmtree(out, ignore_errors=True)
    argv = ["convert", "-q", "--jobs", "1", "--calibration", str(cal), "--out", str(out)]
    cpu = children_cpu()
    seconds, peak = run_measured([*argv, str(target)], out.with_name(out.name + ".peak"))
    cpu = children_cpu() - cpu
    lines = [x for x in read_manifest(out) if x.get("status") == "converted"]
    if len(lines) != n_logs:
        raise SystemExit(f"{len(lines)} of {n_logs} logs converted")
    return seconds, cpu, peak, sum(x["messages"] for x in lines)


def pairs(label: str, n: int, run_peer, run_ours) -> dict[str, float]:
    """``n`` pairs (peer first, then imupipe); prints each and the ratio's min and median."""
    ratios, cpu_ratios, best_peer, best_ours = [], [], float("inf"), float("inf")
    for i in range(n):
        tp, cp, mp, np_ = run_peer()
        to, co, mo, no = run_ours()
        assert np_ == no, (np_, no)
        ratios.append(tp / to)
        cpu_ratios.append(cp / co)
        best_peer, best_ours = min(best_peer, tp), min(best_ours, to)
        print(
            f"{label} pair {i + 1}: rosbags loop {tp:.2f} s, {cp:.2f} s CPU (peak {mp:.0f} MB); "
            f"imupipe convert {to:.2f} s, {co:.2f} s CPU (peak {mo:.0f} MB) -> {tp / to:.2f}x "
            f"wall, {cp / co:.2f}x CPU ({no:,} messages)",
            flush=True,
        )
    print(
        f"{label}: imupipe against the rosbags loop: wall min {min(ratios):.2f}x, median "
        f"{statistics.median(ratios):.2f}x; CPU min {min(cpu_ratios):.2f}x, median "
        f"{statistics.median(cpu_ratios):.2f}x over {n} pairs (best wall times: rosbags "
        f"{best_peer:.2f} s, imupipe {best_ours:.2f} s)",
        flush=True,
    )
    return {
        f"{label}_ratio_min": min(ratios),
        f"{label}_ratio_median": statistics.median(ratios),
        f"{label}_cpu_ratio_min": min(cpu_ratios),
        f"{label}_cpu_ratio_median": statistics.median(cpu_ratios),
        f"{label}_peer_best_s": best_peer,
        f"{label}_imupipe_best_s": best_ours,
        f"{label}_imupipe_peak_mb": mo,
        f"{label}_peer_peak_mb": mp,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=100)
    ap.add_argument("--log-messages", type=int, default=1000)
    ap.add_argument("--pairs", type=int, default=2)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_fleet_"))
    try:
        cal = tmp / "calibration.json"
        cal.write_text(json.dumps(CALIBRATION))
        fleet = tmp / "fleet"
        fleet.mkdir()
        for i in range(args.logs):
            make_log(fleet / f"log{i:04d}.mcap", args.log_messages, seed=i)
        logs = sorted(fleet.iterdir())
        note = tmp / "peer.txt"
        results = pairs(
            "one_log",
            args.pairs + 1,
            lambda: peer(logs[:1], note),
            lambda: ours(logs[0], cal, tmp / "out1", 1),
        )
        results |= pairs(
            "fleet",
            args.pairs,
            lambda: peer(logs, note),
            lambda: ours(fleet, cal, tmp / "outn", args.logs),
        )
        print(json.dumps({k: round(v, 3) for k, v in results.items()}))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
