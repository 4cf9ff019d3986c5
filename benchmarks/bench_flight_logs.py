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
Goal (issue 39): >= 2x.

In-process (``--in-process``, after the whole-process pairs): one fresh Python per log imports
both, reads once with each (not timed: caches, lazy imports), then alternates imupipe and the
peer ``--pairs`` times; prints the CPU time (``process_time``) of each read, the ratio's min and
median. This is the read itself, without interpreter start and imports.

Every child runs with Python's bytecode cache on (``PYTHONDONTWRITEBYTECODE`` dropped, the cache
in a temporary ``PYTHONPYCACHEPREFIX``; warmed by the first, unmeasured, run), as an installed
package runs; the peers are installed packages with their bytecode compiled.

    python benchmarks/bench_flight_logs.py [LOG ...] [--pairs 2] [--in-process]

Default logs: every ``.ulg`` of ``../shared/data/logs/px4_ulog`` and
``../shared/data/logs/px4_flights_flugdrohne``, every ``.bin`` of
``../shared/data/logs/ardupilot_flights``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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
log, imu, pairs = sys.argv[1], sys.argv[2] or None, int(sys.argv[3])
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
    t = time.process_time(); peer(topics); peer_s.append(time.process_time() - t)
    t = time.process_time(); imupipe.read(log, imu_topic=imu); ours_s.append(time.process_time() - t)
print(json.dumps({"ours": ours_s, "peer": peer_s, "topics": topics, "rows": table.num_rows}))
"""
"""In-process: CPU seconds of each read, imupipe's and the peer's, alternating."""

ENV: dict[str, str] = {}
"""The children's environment: this one with the bytecode cache on (set by :func:`main`)."""


def children_cpu() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


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


def in_process(logs: list[Path], pairs: int) -> None:
    """The reads alone, in one process per log (see the module docstring)."""
    ratios: dict[str, list[float]] = {"ULog": [], "DataFlash": []}
    for log in logs:
        fmt = "ULog" if log.suffix.lower() == ".ulg" else "DataFlash"
        imu = "IMU" if fmt == "DataFlash" else ""
        out = subprocess.run(
            [sys.executable, "-c", IN_PROCESS, str(log), imu, str(pairs)],
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
            f"peer {min(got['peer']):.3f} s CPU, imupipe.read {min(got['ours']):.3f} s CPU (best "
            f"of {pairs}) -> min {min(each):.2f}x, median {statistics.median(each):.2f}x",
            flush=True,
        )
    for fmt, each in ratios.items():
        if each:
            print(
                f"{fmt} in-process: imupipe against the peer over {len(each)} pairs: CPU min "
                f"{min(each):.2f}x, median {statistics.median(each):.2f}x (goal >= 2x)",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--in-process", action="store_true", help="also the reads in one process")
    args = ap.parse_args()
    logs = args.logs or default_logs()
    if not logs:
        raise SystemExit(f"no logs given and none found under {LOGS}")
    ratios: dict[str, list[tuple[float, float]]] = {"ULog": [], "DataFlash": []}
    with tempfile.TemporaryDirectory() as tmp:
        ENV.update({k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"})
        ENV["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pycache")
        note = Path(tmp) / "note.json"
        for log in logs:
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
                ratios[fmt].append((pw / ow, pc / oc))
                print(
                    f"{log.parent.name}/{log.name} ({log.stat().st_size / 1e6:.1f} MB, "
                    f"{json.loads(topics)}) pair {i + 1}: {peer_name} {pw:.2f} s, {pc:.2f} s CPU "
                    f"(peak {pm:.0f} MB); imupipe.read {ow:.2f} s, {oc:.2f} s CPU (peak "
                    f"{om:.0f} MB) -> {pw / ow:.2f}x wall, {pc / oc:.2f}x CPU",
                    flush=True,
                )
        if args.in_process:
            in_process(logs, args.pairs)
    for fmt, pairs in ratios.items():
        if pairs:
            wall, cpu = [w for w, _ in pairs], [c for _, c in pairs]
            print(
                f"{fmt}: imupipe against the peer over {len(pairs)} pairs: wall min "
                f"{min(wall):.2f}x, median {statistics.median(wall):.2f}x; CPU min {min(cpu):.2f}x, "
                f"median {statistics.median(cpu):.2f}x (goal >= 2x)"
            )


if __name__ == "__main__":
    main()
