"""Issue 39: a fleet of many short logs, whole commands, against a plain rosbags read loop.

A fleet is often thousands of short logs (one per flight or per boot); there the fixed cost per
command and per log decides. Measured, each as a user runs it (a fresh process: interpreter
start, imports, planning, writing and verifying included), imupipe and the peer alternating in
pairs so that both see the same load:

[1] one log of ``--log-messages`` (default 1,000) ``sensor_msgs/msg/Imu`` messages: ``imupipe
    convert`` against ``python peer.py LOG`` (rosbags' ``AnyReader`` reading and deserialising
    every message; the typestore built once).
    In the same pairs, the floor any Python tool that writes Arrow pays before it reads a
    message: ``python -c "import numpy, pyarrow"``; imupipe's fixed cost per command is the
    convert's CPU less this floor (issue 39's aim: below 0.1 s). The ``imupipe`` program freezes
    its objects before the interpreter exits (:func:`imupipe.pipeline.cli.console`), which also
    spares the exit's walk over numpy's and pyarrow's objects; so the cost is also given against
    the floor ending the same way (``import gc, numpy, pyarrow; gc.freeze()``): imupipe's own
    cost, with none of the floor's share of that saving.
[2] ``--logs`` (default 1,000) such logs in one run: ``imupipe convert --jobs 1 FOLDER`` against
    the same rosbags loop over all of them in one process, ``--fleet-pairs`` times (default 1;
    the peer first in odd pairs, imupipe first in even ones). Goal (issue 39): >= 5x faster.
    1,000 logs take about 1.5 minutes on a 2-core machine at load 3 (the loop's 50 s CPU).

Each pair prints both wall times, the ratio (peer / imupipe), both CPU times (user + system of
the process and its children, from ``getrusage``: far less moved by the other sessions on a
shared machine than the wall time) and their ratio, and both processes' peak RSS (their own
``VmHWM``); the summary gives each ratio's min and median over the pairs. Only ratios measured in
the same pair count. Then each side's CPU a log (the fleet's CPU less the one log's median, over
the other logs) and, with fewer than 1,000 logs, the 1,000-log ratio that those give, printed as
a **projection** (not measured).

Every child runs with Python's bytecode cache on (``PYTHONDONTWRITEBYTECODE`` dropped, the
cache in a temporary ``PYTHONPYCACHEPREFIX``, warmed by a first unmeasured run), as an installed
package runs: a source checkout run with ``PYTHONDONTWRITEBYTECODE=1`` compiles every imupipe
module on each start (0.25-0.3 s CPU of a 1k-message convert, measured), which the peer, an
installed package, never pays. With ``--baseline DIR`` (a checkout of the code before a change,
with its ``.shim``) its convert runs in each pair too: before/after in the same pairs.

Usage: ``python benchmarks/bench_fleet.py [--logs 1000] [--log-messages 1000] [--pairs 3]
[--fleet-pairs 1] [--baseline DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_convert import CALIBRATION, make_log  # noqa: E402
from proc_memory import FLOOR, FLOOR_FROZEN, children_cpu, floor_cpu, run_measured  # noqa: E402

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


def floor() -> tuple[float, float]:
    """CPU seconds of a fresh process that imports numpy and pyarrow and stops: as is, and
    ending as the ``imupipe`` program ends (:data:`proc_memory.FLOOR_FROZEN`)."""
    return floor_cpu(ENV), floor_cpu(ENV, FLOOR_FROZEN)


def pairs(
    label: str,
    n: int,
    run_peer,
    run_ours,
    run_base=None,
    alternate: bool = False,
    run_floor=None,
) -> dict[str, float]:
    """``n`` pairs (peer first, then imupipe, then the baseline's imupipe when given, then the
    library floor when given; with ``alternate``, imupipe first in the even pairs); prints each
    and the ratios' min and median, and imupipe's CPU beyond the floor."""
    ratios, cpu_ratios, best_peer, best_ours = [], [], float("inf"), float("inf")
    base_ratios, base_cpu_ratios = [], []
    peer_cpu, ours_cpu, beyond, beyond_frozen = [], [], [], []
    for i in range(n):
        if alternate and i % 2:
            to, co, mo, no = run_ours()
            tp, cp, mp, np_ = run_peer()
        else:
            tp, cp, mp, np_ = run_peer()
            to, co, mo, no = run_ours()
        peer_cpu.append(cp)
        ours_cpu.append(co)
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
        if run_floor is not None:
            cf, cff = run_floor()
            beyond.append(co - cf)
            beyond_frozen.append(co - cff)
            print(
                f"{label} pair {i + 1}: floor ({FLOOR}) {cf:.2f} s CPU; imupipe beyond it "
                f"{co - cf:.3f} s CPU; beyond the floor ending as imupipe does ({FLOOR_FROZEN}: "
                f"{cff:.2f} s) {co - cff:.3f} s CPU",
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
        f"{label}_peer_cpu_median_s": statistics.median(peer_cpu),
        f"{label}_imupipe_cpu_median_s": statistics.median(ours_cpu),
    }
    for key, what, values in (
        ("beyond_floor", "(CPU beyond the floor)", beyond),
        ("beyond_frozen_floor", "against the floor ending as imupipe does", beyond_frozen),
    ):
        if values:
            print(
                f"{label}: imupipe's own fixed cost {what}: min {min(values):.3f} s, "
                f"median {statistics.median(values):.3f} s",
                flush=True,
            )
            out[f"{label}_{key}_min_s"] = min(values)
            out[f"{label}_{key}_median_s"] = statistics.median(values)
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


def per_log(results: dict[str, float], n: int, target: int = 1000) -> dict[str, float]:
    """Each side's CPU a log beyond the first (the fleet's median CPU less the one log's, over
    ``n - 1`` logs), printed; with ``n < target``, the ratio at ``target`` logs those give,
    printed as a projection (measured only when ``n >= target``)."""
    out: dict[str, float] = {}
    if n < 2:
        return out
    for side in ("peer", "imupipe"):
        one, many = results[f"one_log_{side}_cpu_median_s"], results[f"fleet_{side}_cpu_median_s"]
        out[f"{side}_cpu_per_log_ms"] = 1000 * (many - one) / (n - 1)
    print(
        f"CPU a log beyond the first ({n - 1} logs): rosbags loop "
        f"{out['peer_cpu_per_log_ms']:.1f} ms, imupipe convert "
        f"{out['imupipe_cpu_per_log_ms']:.1f} ms",
        flush=True,
    )
    if min(out.values()) <= 0:  # a few logs: within the noise of one log's start
        print("too few logs to project from (a log's CPU is within the noise)", flush=True)
    elif n < target:
        at = {
            side: results[f"one_log_{side}_cpu_median_s"]
            + (target - 1) * out[f"{side}_cpu_per_log_ms"] / 1000
            for side in ("peer", "imupipe")
        }
        out["projected_cpu_ratio"] = at["peer"] / at["imupipe"]
        print(
            f"PROJECTION (not measured): {target:,} logs from these figures: rosbags loop "
            f"{at['peer']:.1f} s CPU, imupipe {at['imupipe']:.1f} s CPU -> "
            f"{out['projected_cpu_ratio']:.2f}x; run --logs {target} to measure it",
            flush=True,
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=1000)
    ap.add_argument("--log-messages", type=int, default=1000)
    ap.add_argument("--pairs", type=int, default=3, help="pairs of one log")
    ap.add_argument("--fleet-pairs", type=int, default=1, help="pairs of the whole fleet")
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
        one, five, _ = os.getloadavg()
        print(
            f"{args.logs:,} logs written; load average {one:.2f} (1 min), {five:.2f} (5 min) "
            f"on {os.cpu_count()} cores",
            flush=True,
        )
        note = tmp / "peer.txt"
        # warm the bytecode caches (not measured)
        peer(logs[:1], note)
        ours(logs[0], cal, tmp / "out1", 1)
        if base_env is not None:
            ours(logs[0], cal, tmp / "out1", 1, base_env)
        results = pairs(
            "one_log",
            args.pairs,
            lambda: peer(logs[:1], note),
            lambda: ours(logs[0], cal, tmp / "out1", 1),
            None if base_env is None else lambda: ours(logs[0], cal, tmp / "out1", 1, base_env),
            run_floor=floor,
        )
        if args.fleet_pairs < 1:  # the one log only
            return
        results |= pairs(
            "fleet",
            args.fleet_pairs,
            lambda: peer(logs, note),
            lambda: ours(fleet, cal, tmp / "outn", args.logs),
            None
            if base_env is None
            else lambda: ours(fleet, cal, tmp / "outn", args.logs, base_env),
            alternate=True,
        )
        results |= per_log(results, args.logs)
        one, five, _ = os.getloadavg()
        print(f"load average at the end: {one:.2f} (1 min), {five:.2f} (5 min)", flush=True)
        print(json.dumps({k: round(v, 3) for k, v in results.items()}))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
