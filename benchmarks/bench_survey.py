"""Issue 30 scale figures for ``imupipe survey`` on a simulated fleet (``imupipe simulate fleet``).

1. Throughput: ``--logs`` logs (default 1,000: ``--logs / 20`` vehicles of 20 logs, 2 IMUs each,
   ``--log-s`` seconds at 100 Hz) surveyed by the whole command in a fresh process (``imupipe
   survey``, as a user runs it) on the local engine with ``--jobs`` workers: logs per second and
   still periods per second, wall clock, fleet view, report and recording included.
2. Per-log fixed cost: the manifest's per-log worker seconds of the fleet's logs against those of
   20 logs a tenth as long, surveyed alike; the straight line through the two means, extrapolated
   to a log of length zero, is the fixed cost of a log (read setup, topic listing, part written).
3. Peak memory of a worker (``peak_rss_mb`` of the manifest: the worker's max RSS) and of the
   command's own process (the driver: its ``VmHWM``; the fleet view holds the whole dataset).
4. With ``--ray-nodes N``: 1. to 3. again in the same run on the same logs, on a Ray cluster of N
   one-CPU nodes started on this machine (``benchmarks/local_ray.py``; stopped and removed at the
   end) with ``--engine ray --address``, beside the cluster's own resident memory.

   Against a plain read of the same logs in the same run (:func:`measure_plain`: every IMU topic
   the survey reads, read once by the readers' batches in a fresh process, on ``--jobs``
   processes): logs per second and CPU seconds per log of each, and their ratios; ``--runs``
   runs (default 2) of both, alternated, printed as the min and the median.
5. With ``--long-s S``: peak memory (``peak_rss_mb`` of the manifest) and worker seconds of one
   worker surveying one log of ``S`` seconds at ``--long-hz`` (default 400) with 1 IMU, read in
   batches (the default ``batch_rows``) against read as one batch (``batch_rows`` beyond the
   log: the whole topic in memory, as before the survey streamed), and the ratio of the two.

6. With ``--scaling P`` (issue 39): ``P`` rounds over the same fleet, each in a fresh process as a
   user runs it: a plain read of every log (rosbags' ``AnyReader`` reading and deserialising every
   message; the typestore built once per process) in one process, and the same logs split in two
   halves read by two such processes at once; then ``imupipe survey --jobs 1`` and ``--jobs 2``.
   Printed per round and as min and median: the survey's speed-up with 2 jobs against the plain
   read's with 2 processes (what this machine gives two processes at that moment), each survey
   against the plain read (wall and CPU of the process tree), and peak memory. With ``--baseline
   DIR`` (a checkout of the code before a change, with its ``.shim``), its two surveys too, in
   the same rounds (``base_`` figures).

Usage: ``python benchmarks/bench_survey.py [--logs 1000] [--log-s 150] [--jobs 2]
[--ray-nodes 2] [--long-s 7200] [--scaling 2]`` (``--logs 0``: only 5.). Not run in CI (minutes); the machine is shared, so the figures are indicative.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.simulate import simulate, write_log

sys.path.insert(0, str(Path(__file__).resolve().parent))
from local_ray import cluster_rss_mb, ray_cluster, stop_cluster  # noqa: E402
from proc_memory import run_measured  # noqa: E402


def make_fleet(root: Path, logs: int, log_s: float, seed: int) -> Path:
    vehicles = max(logs // 20, 1)
    per = max(logs // vehicles, 1)
    fleet, _ = simulate(
        "fleet", {"vehicles": vehicles, "imus": 2, "logs": per, "log_s": log_s}, seed=seed
    )
    write_log(root, fleet)
    return root


def measure(
    logs: Path, small: Path, out: Path, log_s: float, engine: list[str]
) -> dict[str, float]:
    """Survey ``logs`` then ``small`` (the same fleet shape, logs a tenth as long) with the
    engine options ``engine``, each by the whole command in a fresh process."""
    import pyarrow.parquet as pq

    shutil.rmtree(out, ignore_errors=True)
    cmd = ["survey", "--quiet", *engine, "--out"]
    wall, driver_mb = run_measured([*cmd, str(out), str(logs)], out.with_suffix(".peak"))
    lines = [r for r in read_manifest(out) if r.get("status") == "surveyed"]
    n = sum(1 for _ in logs.rglob("*.mcap"))
    if len(lines) != n:
        raise SystemExit(f"{' '.join(engine)}: {len(lines)} of {n} logs surveyed")
    rows = pq.read_metadata(out / "survey.parquet").num_rows
    small_out = out.with_name(out.name + "_small")
    shutil.rmtree(small_out, ignore_errors=True)
    run_measured([*cmd, str(small_out), str(small)], small_out.with_suffix(".peak"))
    short = [r["seconds"] for r in read_manifest(small_out) if r.get("status") == "surveyed"]
    mean_long = sum(r["seconds"] for r in lines) / len(lines)
    mean_short = sum(short) / len(short)
    slope = (mean_long - mean_short) / (log_s - log_s / 10)
    return {
        "wall_s": round(wall, 1),
        "logs_per_s": round(n / wall, 2),
        "periods_per_s": round(rows / wall, 1),
        "worker_s_per_log": round(mean_long, 3),
        "worker_s_per_log_short": round(mean_short, 3),
        "worker_cpu_s_per_log": round(sum(r["cpu_seconds"] for r in lines) / len(lines), 3),
        "fixed_cost_s_per_log": round(mean_short - slope * log_s / 10, 3),
        "worker_peak_rss_mb": max(r["peak_rss_mb"] for r in lines),
        "driver_peak_rss_mb": round(driver_mb, 1),
    }


PLAIN = """
import dataclasses, json, resource, sys, time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

def read(path):
    from imupipe.pipeline.survey.scan import imu_topics, split_topics
    from imupipe.pipeline.survey.stream import DEFAULT_BATCH_ROWS
    from imupipe.readers import dispatch
    from imupipe.readers.spec import InputSpec

    cpu = time.process_time()
    spec = InputSpec(path=Path(path), name="plain")
    rows = 0
    for imu, temp, mag in imu_topics(spec):
        one = dataclasses.replace(spec, **split_topics(imu), temperature_topic=temp, mag_topic=mag)
        for table, _ in dispatch.iter_input(one, batch_rows=DEFAULT_BATCH_ROWS, carry=False):
            rows += table.num_rows
    return rows, time.process_time() - cpu

if __name__ == "__main__":
    logs = sorted(str(p) for p in Path(sys.argv[1]).rglob("*.mcap"))
    t = time.perf_counter()
    with ProcessPoolExecutor(int(sys.argv[2])) as pool:
        done = list(pool.map(read, logs, chunksize=8))
    wall = time.perf_counter() - t
    print(json.dumps({"logs": len(logs), "wall_s": wall, "rows": sum(r for r, _ in done),
                      "cpu_s_per_log": sum(c for _, c in done) / len(logs)}))
"""
"""A plain read of every log under a folder (what the survey reads, once), on a process pool;
prints its wall clock, rows and the workers' CPU seconds per log."""


def measure_plain(logs: Path, jobs: int) -> dict[str, float]:
    """The plain read of ``logs`` (:data:`PLAIN`) in a fresh process: logs per second (wall
    clock, process start included as for the survey's command) and CPU seconds per log."""
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", PLAIN, str(logs), str(jobs)],
        capture_output=True,
        text=True,
        check=True,
    )
    wall = time.perf_counter() - t
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    return {
        "wall_s": round(wall, 1),
        "logs_per_s": round(got["logs"] / wall, 2),
        "cpu_s_per_log": round(got["cpu_s_per_log"], 4),
    }


def min_median(runs: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Per figure: its min and median over ``runs``."""
    return {
        key: {
            "min": min(r[key] for r in runs),
            "median": round(statistics.median(r[key] for r in runs), 4),
        }
        for key in runs[0]
    }


def measure_long(root: Path, seconds: float, rate_hz: float) -> dict[str, float]:
    """5.: one long log surveyed whole (one batch) and streamed, each by a fresh worker."""
    # simulated in a process of its own: a process's peak RSS passes to its children (fork and
    # exec keep it), so the workers below must not descend from one that held the simulation
    sim = (
        "import sys; from pathlib import Path; from imupipe.pipeline.simulate import simulate,"
        " write_log; f, _ = simulate('fleet', {'vehicles': 1, 'imus': 1, 'logs': 1, 'log_s':"
        " float(sys.argv[2]), 'rate_hz': float(sys.argv[3]), 'events': False}, seed=3);"
        " write_log(Path(sys.argv[1]), f)"
    )
    subprocess.run(
        [sys.executable, "-c", sim, str(root / "long"), str(seconds), str(rate_hz)], check=True
    )
    figures: dict[str, float] = {"long_log_s": seconds, "long_rate_hz": rate_hz}
    rows = {}
    for name, batch in (("whole", 1 << 40), ("streamed", None)):
        out = root / f"long_{name}"
        shutil.rmtree(out, ignore_errors=True)
        # a fresh process each: a worker's peak is measured from its own start
        code = (
            "import sys; from pathlib import Path; from imupipe.pipeline.survey.scan import survey;"
            "r = survey([Path(sys.argv[1])], Path(sys.argv[2]), jobs=1, rerun=False, quiet=True,"
            " batch_rows=None if sys.argv[3] == 'None' else int(sys.argv[3])); print(r['rows'])"
        )
        proc = subprocess.run(
            [sys.executable, "-c", code, str(root / "long"), str(out), str(batch)],
            capture_output=True,
            text=True,
            check=True,
        )
        (line,) = [r for r in read_manifest(out) if r.get("status") == "surveyed"]
        figures[f"{name}_worker_peak_rss_mb"] = line["peak_rss_mb"]
        figures[f"{name}_worker_s"] = line["seconds"]
        rows[name] = int(proc.stdout.split()[-1])
    if rows["whole"] != rows["streamed"]:
        raise SystemExit(f"whole and streamed found different periods: {rows}")
    figures["still_periods"] = rows["whole"]
    figures["memory_whole_vs_streamed"] = round(
        figures["whole_worker_peak_rss_mb"] / figures["streamed_worker_peak_rss_mb"], 2
    )
    figures["speed_streamed_vs_whole"] = round(
        figures["whole_worker_s"] / figures["streamed_worker_s"], 2
    )
    return figures


PLAIN_READ = """
import sys
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

store = get_typestore(Stores.ROS2_HUMBLE)
n = 0
for path in sys.argv[1:]:
    with AnyReader([Path(path)], default_typestore=store) as reader:
        for conn, _, raw in reader.messages(connections=reader.connections):
            reader.deserialize(raw, conn.msgtype)
            n += 1
print(n)
"""
"""6.'s plain read: every message of the logs given, read and deserialised by rosbags."""


def children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished children so far."""
    import resource

    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def plain_read(logs: list[Path], parts: int) -> tuple[float, float, int]:
    """(wall s, CPU s, messages) of the plain read of ``logs`` split over ``parts`` processes
    running at once."""
    start, cpu = time.perf_counter(), children_cpu()
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", PLAIN_READ, *map(str, logs[i::parts])],
            stdout=subprocess.PIPE,
            text=True,
        )
        for i in range(parts)
    ]
    n = sum(int(p.communicate()[0]) for p in procs)
    if any(p.returncode for p in procs):
        raise SystemExit("the plain read failed")
    return time.perf_counter() - start, children_cpu() - cpu, n


def scaling(logs: Path, out: Path, rounds: int, baseline: Path | None) -> dict[str, float]:
    """6.: survey with 1 and 2 jobs against the plain read in 1 and 2 processes."""
    import os
    import statistics

    variants: list[tuple[str, dict[str, str] | None]] = [("", None)]
    if baseline is not None:
        base_env = {**os.environ, "PYTHONPATH": str(baseline / ".shim")}
        variants.append(("base_", base_env))

    files = sorted(logs.rglob("*.mcap"))
    rows: dict[str, list[float]] = {}
    for r in range(rounds):
        fig: dict[str, float] = {}
        for parts in (1, 2):
            wall, cpu, _ = plain_read(files, parts)
            fig[f"read_{parts}_s"], fig[f"read_{parts}_cpu_s"] = wall, cpu
        for pre, env in variants:
            for jobs in (1, 2):
                shutil.rmtree(out, ignore_errors=True)
                cpu = children_cpu()
                wall, peak = run_measured(
                    ["survey", "--quiet", "--jobs", str(jobs), "--out", str(out), str(logs)],
                    out.with_suffix(".peak"),
                    env,
                )
                name = f"{pre}survey_{jobs}"
                fig[f"{name}_s"], fig[f"{name}_cpu_s"] = wall, children_cpu() - cpu
                fig[f"{name}_driver_peak_mb"] = peak
                lines = [x for x in read_manifest(out) if x.get("status") == "surveyed"]
                if len(lines) != len(files):
                    raise SystemExit(f"{name}: {len(lines)} of {len(files)} logs surveyed")
                fig[f"{name}_worker_peak_mb"] = max(x["peak_rss_mb"] for x in lines)
                fig[f"{name}_worker_s_per_log"] = sum(x["seconds"] for x in lines) / len(lines)
            if pre:
                fig[f"{pre}survey_speedup_vs_read_speedup"] = (
                    fig[f"{pre}survey_1_s"]
                    / fig[f"{pre}survey_2_s"]
                    / (fig["read_1_s"] / fig["read_2_s"])
                )
        fig["read_speedup_2"] = fig["read_1_s"] / fig["read_2_s"]
        fig["survey_speedup_2"] = fig["survey_1_s"] / fig["survey_2_s"]
        fig["survey_speedup_vs_read_speedup"] = fig["survey_speedup_2"] / fig["read_speedup_2"]
        fig["survey_1_vs_read_1"] = fig["survey_1_s"] / fig["read_1_s"]
        fig["survey_2_vs_read_2"] = fig["survey_2_s"] / fig["read_2_s"]
        fig["survey_1_cpu_vs_read_1_cpu"] = fig["survey_1_cpu_s"] / fig["read_1_cpu_s"]
        print(
            f"round {r + 1}: plain read 1 process {fig['read_1_s']:.2f} s, 2 processes "
            f"{fig['read_2_s']:.2f} s ({fig['read_speedup_2']:.2f}x); survey --jobs 1 "
            f"{fig['survey_1_s']:.2f} s, --jobs 2 {fig['survey_2_s']:.2f} s "
            f"({fig['survey_speedup_2']:.2f}x, {fig['survey_speedup_vs_read_speedup']:.2f} of the read's "
            f"speed-up); survey/read: {fig['survey_1_vs_read_1']:.2f}x (1), "
            f"{fig['survey_2_vs_read_2']:.2f}x (2); CPU 1 job/1 read "
            f"{fig['survey_1_cpu_vs_read_1_cpu']:.2f}x; worker s/log {fig['survey_1_worker_s_per_log']:.3f}"
            f" (1) {fig['survey_2_worker_s_per_log']:.3f} (2); peak driver "
            f"{fig['survey_2_driver_peak_mb']:.0f} MB, worker {fig['survey_2_worker_peak_mb']:.0f} MB",
            flush=True,
        )
        if baseline is not None:
            print(
                f"round {r + 1} baseline: survey --jobs 1 {fig['base_survey_1_s']:.2f} s, --jobs 2 "
                f"{fig['base_survey_2_s']:.2f} s ({fig['base_survey_speedup_vs_read_speedup']:.2f}"
                f" of the read's speed-up); worker s/log {fig['base_survey_1_worker_s_per_log']:.3f}"
                f" (1) {fig['base_survey_2_worker_s_per_log']:.3f} (2); worker peak "
                f"{fig['base_survey_2_worker_peak_mb']:.0f} MB",
                flush=True,
            )
        for k, v in fig.items():
            rows.setdefault(k, []).append(v)
    summary = {}
    for k, v in rows.items():
        summary[f"{k}_min"] = round(min(v), 3)
        summary[f"{k}_median"] = round(statistics.median(v), 3)
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--logs", type=int, default=1000)
    ap.add_argument("--log-s", type=float, default=150.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--ray-nodes", type=int, default=0, help="4.: Ray nodes of one CPU (0: skip)")
    ap.add_argument("--long-s", type=float, default=0.0, help="5.: one log this long (0: skip)")
    ap.add_argument("--long-hz", type=float, default=400.0)
    ap.add_argument("--scaling", type=int, default=0, help="6.: rounds of 1 vs 2 jobs (0: skip)")
    ap.add_argument("--baseline", type=Path, help="6.: a checkout of the code before, to compare")
    ap.add_argument("--runs", type=int, default=2, help="runs of the survey and the plain read")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_survey_"))
    try:
        if args.long_s:
            print(json.dumps(measure_long(tmp, args.long_s, args.long_hz), indent=2), flush=True)
        if not args.logs:
            return
        t = time.perf_counter()
        logs = make_fleet(tmp / "fleet", args.logs, args.log_s, 1)
        made = time.perf_counter() - t
        n = sum(1 for _ in logs.rglob("*.mcap"))
        size = sum(p.stat().st_size for p in logs.rglob("*.mcap"))
        print(f"simulated {n} logs ({size / 1e9:.2f} GB) in {made:.0f} s", flush=True)
        if args.scaling:
            print(
                json.dumps(scaling(logs, tmp / "scaling", args.scaling, args.baseline), indent=2),
                flush=True,
            )
            return
        small = make_fleet(tmp / "small", 20, args.log_s / 10, 2)
        figures: dict[str, object] = {"logs": n, "log_s": args.log_s}
        local = ["--jobs", str(args.jobs)]
        surveyed, plain = [], []
        for _ in range(args.runs):  # alternated: the machine's load falls on both alike
            surveyed.append(measure(logs, small, tmp / "out", args.log_s, local))
            plain.append(measure_plain(logs, args.jobs))
        figures[f"local_{args.jobs}_workers"] = min_median(surveyed)
        figures["plain_read"] = min_median(plain)
        figures["survey_vs_plain_read"] = {
            "cpu_s_per_log": round(
                statistics.median(r["worker_cpu_s_per_log"] for r in surveyed)
                / statistics.median(r["cpu_s_per_log"] for r in plain),
                2,
            ),
            "logs_per_s": round(
                statistics.median(r["logs_per_s"] for r in surveyed)
                / statistics.median(r["logs_per_s"] for r in plain),
                2,
            ),
        }
        print(json.dumps(figures, indent=2), flush=True)
        if args.ray_nodes:
            root = Path(tempfile.mkdtemp(prefix="imupipe-bench-ray-", dir="/tmp"))
            address, procs = ray_cluster(args.ray_nodes, root)
            try:
                idle = cluster_rss_mb(root)
                ray = ["--engine", "ray", "--address", address]
                on_ray = measure(logs, small, tmp / "out_ray", args.log_s, ray)
                on_ray["cluster_idle_rss_mb"] = round(idle, 1)
                on_ray["cluster_after_rss_mb"] = round(cluster_rss_mb(root), 1)
            finally:
                stop_cluster(procs, root)
            figures[f"ray_{args.ray_nodes}_nodes"] = on_ray
            local_wall = figures[f"local_{args.jobs}_workers"]["wall_s"]["median"]  # type: ignore[index]
            figures["ray_vs_local_speed"] = round(local_wall / on_ray["wall_s"], 2)
        print(json.dumps(figures, indent=2))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
