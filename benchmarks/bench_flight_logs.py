"""Issue 39: reading real PX4 ULog and ArduPilot DataFlash logs, whole process, against the peers
reading only the same topics.

For each log, in pairs (the peer, then imupipe, so that both see the same load), each in a fresh
Python process as a user runs it (interpreter start and imports included):

- imupipe: ``imupipe.read(LOG)`` (the common table; a DataFlash log: ``imu_topic="IMU"``, the
  first IMU, as a log with several asks);
- ULog peer: ``pyulog.ULog(LOG, message_name_filter_list=TOPICS)``;
- DataFlash peer: pymavlink's ``DFReader_binary(LOG)`` and ``recv_match(type=TYPES)`` until the
  end (it indexes the file by type first, then decodes only those records),

where TOPICS / TYPES are the topics the table was read from (its metadata). Prints per log and
pair the wall and CPU times (user + system, ``getrusage``: far less moved by other sessions on a
shared machine than the wall time), both ratios (peer / imupipe: above 1, imupipe is faster) and
both processes' peak RSS (``VmHWM``); then each ratio's min and median over all pairs of a format.
Goal (issue 39): >= 2x. In each pair also the floor (:data:`proc_memory.FLOOR`, as
``bench_fleet.py`` measures it): a fresh Python that only imports numpy and pyarrow, what any
tool that builds Arrow tables pays before it reads a byte; printed with imupipe's CPU beyond it
and the peer's whole process over the floor (``peer / floor``: the most any whole-process ratio
of an Arrow-building reader can reach against that peer, were its read free).

In-process (``--in-process``, after the whole-process pairs; ``--only-in-process`` without
them): one fresh Python per log imports both, reads once with each (not timed: caches, lazy
imports), then runs ``--pairs`` pairs, each ``--reads`` reads of the peer and of imupipe
alternating (default 1: one read each); prints the CPU time (``process_time``) of each side's
reads in a pair, the ratio's min and median over the pairs. This is the read itself, without
interpreter start and imports. A read of a small log takes 10-40 ms, where one descheduling
on a loaded machine moves a single pair by 30 %: ``--reads 5`` sums five reads a side in each
pair, the same work, less noise.

Every child runs with Python's bytecode cache on (``PYTHONDONTWRITEBYTECODE`` dropped, the cache
in a temporary ``PYTHONPYCACHEPREFIX``; warmed by the first, unmeasured, run), as an installed
package runs; the peers are installed packages with their bytecode compiled.

    python benchmarks/bench_flight_logs.py [LOG ...] [--pairs 2] [--in-process | --only-in-process]
        [--reads 1]

Default logs: every ``.ulg`` of ``../shared/data/logs/px4_ulog`` and
``../shared/data/logs/px4_flights_flugdrohne``, every ``.bin`` of
``../shared/data/logs/ardupilot_flights``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from proc_memory import FLOOR, children_cpu, floor_cpu  # noqa: E402

LOGS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "logs"

END = """
with open("/proc/self/status") as fh:
    hwm = next(line.split()[1] for line in fh if line.startswith("VmHWM:"))
with open(sys.argv[1], "w") as fh:
    fh.write(json.dumps({"n": n, "hwm_kb": int(hwm)}))
"""

OURS = (
    """
import json, sys, warnings
import imupipe
from imupipe.readers.table import metadata
warnings.simplefilter("ignore")
table = imupipe.read(sys.argv[2], imu_topic=sys.argv[3] or None)
n = table.num_rows
topics = sorted({t.split("/")[0] for t in metadata(table)["topics"].values()})
with open(sys.argv[1] + ".topics", "w") as fh:
    fh.write(json.dumps(topics))
"""
    + END
)

PYULOG = (
    """
import json, sys
from pyulog import ULog
log = ULog(sys.argv[2], message_name_filter_list=json.loads(sys.argv[3]))
n = sum(len(d.data["timestamp"]) for d in log.data_list)
"""
    + END
)

DFREADER = (
    """
import json, sys
from pymavlink import DFReader
reader = DFReader.DFReader_binary(sys.argv[2], zero_time_base=False)
types = json.loads(sys.argv[3])
n = 0
while reader.recv_match(type=types) is not None:
    n += 1
"""
    + END
)


IN_PROCESS = """
import json, sys, time, warnings
import imupipe
from imupipe.readers.table import metadata
warnings.simplefilter("ignore")
log, imu, pairs, reads = sys.argv[1], sys.argv[2] or None, int(sys.argv[3]), int(sys.argv[4])
if log.lower().endswith(".ulg"):
    from pyulog import ULog

    def peer(topics):
        data = ULog(log, message_name_filter_list=topics)
        return sum(len(d.data["timestamp"]) for d in data.data_list)
else:
    from pymavlink import DFReader

    def peer(topics):
        reader = DFReader.DFReader_binary(log, zero_time_base=False)
        n = 0
        while reader.recv_match(type=topics) is not None:
            n += 1
        return n

table = imupipe.read(log, imu_topic=imu)  # warm
topics = sorted({t.split("/")[0] for t in metadata(table)["topics"].values()})
peer(topics)
ours_s, peer_s = [], []
for _ in range(pairs):
    peer_s.append(0.0)
    ours_s.append(0.0)
    for _ in range(reads):
        t = time.process_time(); peer(topics); peer_s[-1] += time.process_time() - t
        t = time.process_time(); imupipe.read(log, imu_topic=imu); ours_s[-1] += time.process_time() - t
print(json.dumps({"ours": ours_s, "peer": peer_s, "topics": topics, "rows": table.num_rows}))
"""
"""In-process: CPU seconds of each pair's reads (``reads`` a side), imupipe's and the peer's,
alternating."""

ENV: dict[str, str] = {}
"""The children's environment: this one with the bytecode cache on (set by :func:`main`)."""


def run(code: str, note: Path, *args: str) -> tuple[float, float, float]:
    """(wall s, CPU s, peak RSS MB) of ``code`` in a fresh Python."""
    start, cpu = time.perf_counter(), children_cpu()
    subprocess.run([sys.executable, "-c", code, str(note), *args], check=True, env=ENV)
    wall, cpu = time.perf_counter() - start, children_cpu() - cpu
    return wall, cpu, json.loads(note.read_text())["hwm_kb"] / 1024


def default_logs() -> list[Path]:
    found = sorted((LOGS / "px4_ulog").glob("*.ulg"))
    found += sorted((LOGS / "px4_flights_flugdrohne").glob("*.ulg"))
    found += sorted(
        p for p in (LOGS / "ardupilot_flights").rglob("*") if p.suffix.lower() == ".bin"
    )
    return found


def in_process(logs: list[Path], pairs: int, reads: int) -> None:
    """The reads alone, in one process per log (see the module docstring)."""
    ratios: dict[str, list[float]] = {"ULog": [], "DataFlash": []}
    for log in logs:
        fmt = "ULog" if log.suffix.lower() == ".ulg" else "DataFlash"
        imu = "IMU" if fmt == "DataFlash" else ""
        out = subprocess.run(
            [sys.executable, "-c", IN_PROCESS, str(log), imu, str(pairs), str(reads)],
            check=True,
            capture_output=True,
            text=True,
            env=ENV,
        )
        got = json.loads(out.stdout.strip().splitlines()[-1])
        each = [p / o for p, o in zip(got["peer"], got["ours"], strict=True)]
        ratios[fmt].extend(each)
        print(
            f"in-process {log.parent.name}/{log.name} ({got['topics']}, {got['rows']:,} rows): "
            f"peer {min(got['peer']) / reads:.3f} s CPU, imupipe.read {min(got['ours']) / reads:.3f}"
            f" s CPU (a read, best of {pairs} pairs of {reads} a side) -> min {min(each):.2f}x, "
            f"median {statistics.median(each):.2f}x",
            flush=True,
        )
    for fmt, each in ratios.items():
        if each:
            print(
                f"{fmt} in-process: imupipe against the peer over {len(each)} pairs of {reads} "
                f"read(s) a side: CPU min {min(each):.2f}x, median {statistics.median(each):.2f}x "
                "(goal >= 2x)",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--in-process", action="store_true", help="also the reads in one process")
    ap.add_argument("--only-in-process", action="store_true", help="the reads in one process only")
    ap.add_argument("--reads", type=int, default=1, help="in-process reads a side in each pair")
    args = ap.parse_args()
    logs = args.logs or default_logs()
    if not logs:
        raise SystemExit(f"no logs given and none found under {LOGS}")
    ratios: dict[str, list[tuple[float, float]]] = {"ULog": [], "DataFlash": []}
    floors: dict[str, list[tuple[float, float, float]]] = {"ULog": [], "DataFlash": []}
    with tempfile.TemporaryDirectory() as tmp:
        ENV.update({k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"})
        ENV["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pycache")
        note = Path(tmp) / "note.json"
        for log in [] if args.only_in_process else logs:
            fmt = "ULog" if log.suffix.lower() == ".ulg" else "DataFlash"
            imu = "IMU" if fmt == "DataFlash" else ""
            run(OURS, note, str(log), imu)  # the topics the table is read from (and a warm cache)
            topics = Path(str(note) + ".topics").read_text()
            peer_code, peer_name = (
                (PYULOG, "pyulog (filtered)") if fmt == "ULog" else (DFREADER, "DFReader")
            )
            for i in range(args.pairs):
                pw, pc, pm = run(peer_code, note, str(log), topics)
                ow, oc, om = run(OURS, note, str(log), imu)
                cf = floor_cpu(ENV)
                ratios[fmt].append((pw / ow, pc / oc))
                floors[fmt].append((cf, oc - cf, pc))
                print(
                    f"{log.parent.name}/{log.name} ({log.stat().st_size / 1e6:.1f} MB, "
                    f"{json.loads(topics)}) pair {i + 1}: {peer_name} {pw:.2f} s, {pc:.2f} s CPU "
                    f"(peak {pm:.0f} MB); imupipe.read {ow:.2f} s, {oc:.2f} s CPU (peak "
                    f"{om:.0f} MB) -> {pw / ow:.2f}x wall, {pc / oc:.2f}x CPU; floor ({FLOOR}) "
                    f"{cf:.2f} s CPU: imupipe beyond it {oc - cf:.2f} s, {peer_name} / floor "
                    f"{pc / cf:.2f}x",
                    flush=True,
                )
        if args.in_process or args.only_in_process:
            in_process(logs, args.pairs, args.reads)
    for fmt, pairs in ratios.items():
        if pairs:
            wall, cpu = [w for w, _ in pairs], [c for _, c in pairs]
            print(
                f"{fmt}: imupipe against the peer over {len(pairs)} pairs: wall min "
                f"{min(wall):.2f}x, median {statistics.median(wall):.2f}x; CPU min {min(cpu):.2f}x, "
                f"median {statistics.median(cpu):.2f}x (goal >= 2x)"
            )
    for fmt, rows in floors.items():
        if rows:
            cf, beyond, peer = ([r[i] for r in rows] for i in range(3))
            print(
                f"{fmt}: the floor ({FLOOR}) CPU min {min(cf):.2f} s, median "
                f"{statistics.median(cf):.2f} s; imupipe's CPU beyond it min {min(beyond):.2f} s, "
                f"median {statistics.median(beyond):.2f} s; the peer's whole process median "
                f"{statistics.median(peer):.2f} s CPU = {statistics.median(peer) / statistics.median(cf):.2f}x "
                "the floor (the most a whole-process ratio can reach, were the read free; its "
                f"median beyond-floor ratio: {statistics.median(p / b if b > 0 else float('inf') for p, b in zip(peer, beyond, strict=True)):.2f}x)"
            )


if __name__ == "__main__":
    main()
