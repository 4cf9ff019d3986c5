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

Every child runs with Python's bytecode cache on (``PYTHONDONTWRITEBYTECODE`` dropped, the
cache in a temporary ``PYTHONPYCACHEPREFIX``, warmed by a first unmeasured run), as an installed
package runs: a source checkout run with ``PYTHONDONTWRITEBYTECODE=1`` compiles every imupipe
module on each start (0.25-0.3 s CPU of a 1k-message convert, measured), which the peer, an
installed package, never pays. With ``--baseline DIR`` (a checkout of the code before a change,
with its ``.shim``) its convert runs in each pair too: before/after in the same pairs.

Usage: ``python benchmarks/bench_fleet.py [--logs 100] [--log-messages 1000] [--pairs 2]
[--baseline DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
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


def child_env(pycache: Path, shim: Path | None = None) -> dict[str, str]:
    """This environment with the bytecode cache on (in ``pycache``) and, given ``shim``, the
    imupipe of that checkout first on the path."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = str(pycache)
    if shim is not None:
        env["PYTHONPATH"] = str(shim)
    return env


ENV: dict[str, str] | None = None
"""The children's environment (:func:`child_env`), set by :func:`main`."""


def peer(logs: list[Path], note: Path) -> tuple[float, float, float, int]:
    """(seconds, CPU seconds, peak RSS MB, messages) of the rosbags loop in a fresh process."""
    start, cpu = time.perf_counter(), children_cpu()
    subprocess.run([sys.executable, "-c", PEER, str(note), *map(str, logs)], check=True, env=ENV)
    seconds, cpu = time.perf_counter() - start, children_cpu() - cpu
    n, hwm = note.read_text().split()
    return seconds, cpu, int(hwm) / 1024, int(n)


def ours(
    target: Path, cal: Path, out: Path, n_logs: int, env: dict[str, str] | None = None
) -> tuple[float, float, float, int]:
    """(seconds, CPU seconds, the command's peak RSS MB, messages) of ``imupipe convert --jobs
    1`` (``env``: default :data:`ENV`)."""
    from imupipe.pipeline.convert.manifest import read_manifest

    shutil.rmtree(out, ignore_errors=True)
    argv = ["convert", "-q", "--jobs", "1", "--calibration", str(cal), "--out", str(out)]
    cpu = children_cpu()
    seconds, peak = run_measured(
        [*argv, str(target)], out.with_name(out.name + ".peak"), env or ENV
    )
    cpu = children_cpu() - cpu
    lines = [x for x in read_manifest(out) if x.get("status") == "converted"]
    if len(lines) != n_logs:
        raise SystemExit(f"{len(lines)} of {n_logs} logs converted")
    return seconds, cpu, peak, sum(x["messages"] for x in lines)


def pairs(label: str, n: int, run_peer, run_ours, run_base=None) -> dict[str, float]:
    """``n`` pairs (peer first, then imupipe, then the baseline's imupipe when given); prints
    each and the ratios' min and median."""
    ratios, cpu_ratios, best_peer, best_ours = [], [], float("inf"), float("inf")
    base_ratios, base_cpu_ratios = [], []
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
        if run_base is not None:
            tb, cb, mb, nb = run_base()
            assert nb == no, (nb, no)
            base_ratios.append(tp / tb)
            base_cpu_ratios.append(cp / cb)
            print(
                f"{label} pair {i + 1}: baseline convert {tb:.2f} s, {cb:.2f} s CPU (peak "
                f"{mb:.0f} MB) -> {tp / tb:.2f}x wall, {cp / cb:.2f}x CPU against the rosbags "
                f"loop; this code against the baseline: {cb / co:.2f}x CPU",
                flush=True,
            )
    print(
        f"{label}: imupipe against the rosbags loop: wall min {min(ratios):.2f}x, median "
        f"{statistics.median(ratios):.2f}x; CPU min {min(cpu_ratios):.2f}x, median "
        f"{statistics.median(cpu_ratios):.2f}x over {n} pairs (best wall times: rosbags "
        f"{best_peer:.2f} s, imupipe {best_ours:.2f} s)",
        flush=True,
    )
    out = {
        f"{label}_ratio_min": min(ratios),
        f"{label}_ratio_median": statistics.median(ratios),
        f"{label}_cpu_ratio_min": min(cpu_ratios),
        f"{label}_cpu_ratio_median": statistics.median(cpu_ratios),
        f"{label}_peer_best_s": best_peer,
        f"{label}_imupipe_best_s": best_ours,
        f"{label}_imupipe_peak_mb": mo,
        f"{label}_peer_peak_mb": mp,
    }
    if base_ratios:
        print(
            f"{label}: the baseline against the rosbags loop: wall min {min(base_ratios):.2f}x, "
            f"median {statistics.median(base_ratios):.2f}x; CPU min {min(base_cpu_ratios):.2f}x, "
            f"median {statistics.median(base_cpu_ratios):.2f}x",
            flush=True,
        )
        out[f"{label}_base_ratio_min"] = min(base_ratios)
        out[f"{label}_base_ratio_median"] = statistics.median(base_ratios)
        out[f"{label}_base_cpu_ratio_min"] = min(base_cpu_ratios)
        out[f"{label}_base_cpu_ratio_median"] = statistics.median(base_cpu_ratios)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=100)
    ap.add_argument("--log-messages", type=int, default=1000)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--baseline", type=Path, help="a checkout of the code before, to compare")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_fleet_"))
    global ENV
    ENV = child_env(tmp / "pycache")
    base_env = (
        None if args.baseline is None else child_env(tmp / "pycache_base", args.baseline / ".shim")
    )
    try:
        cal = tmp / "calibration.json"
        cal.write_text(json.dumps(CALIBRATION))
        fleet = tmp / "fleet"
        fleet.mkdir()
        for i in range(args.logs):
            make_log(fleet / f"log{i:04d}.mcap", args.log_messages, seed=i)
        logs = sorted(fleet.iterdir())
        note = tmp / "peer.txt"
        # warm the bytecode caches (not measured)
        peer(logs[:1], note)
        ours(logs[0], cal, tmp / "out1", 1)
        if base_env is not None:
            ours(logs[0], cal, tmp / "out1", 1, base_env)
        results = pairs(
            "one_log",
            args.pairs + 1,
            lambda: peer(logs[:1], note),
            lambda: ours(logs[0], cal, tmp / "out1", 1),
            None if base_env is None else lambda: ours(logs[0], cal, tmp / "out1", 1, base_env),
        )
        results |= pairs(
            "fleet",
            args.pairs,
            lambda: peer(logs, note),
            lambda: ours(fleet, cal, tmp / "outn", args.logs),
            None
            if base_env is None
            else lambda: ours(fleet, cal, tmp / "outn", args.logs, base_env),
        )
        print(json.dumps({k: round(v, 3) for k, v in results.items()}))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
