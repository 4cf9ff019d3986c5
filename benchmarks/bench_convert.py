"""Issue 8 performance goals for ``imupipe convert``, measured against peers in the same run.

1. One MCAP of N (default 1,000,000) ``sensor_msgs/msg/Imu`` messages: ``imupipe convert``
   (read + correct + write + verify) against a rosbags ``AnyReader`` loop that only reads and
   deserialises the same file. Goal: >= 5x faster for the work itself; issue 27: >= 6x for the
   whole command as a user runs it (``imupipe convert`` in a fresh process, interpreter start,
   imports and planning included; one log is converted in-process, no pool is started).
2. 20 logs with 2 workers against 1 worker. Goal: >= 1.6x faster.
3. Peak memory of a worker (max RSS) converting the big log streamed in batches, a log a quarter
   of its size, and the big log in one batch: streamed peak must not grow with the log.
4. The per-log fixed cost (issue 17): 20 tiny logs (1,000 messages) against one, one worker, in
   the same run as the rest; beside it the cost per message of the fleet's logs and of the big
   log, so that what the fixed cost adds to a fleet of short logs is seen.

5. Issue 27, with ``--ray-nodes 2,3``: for each N, a Ray cluster of N one-CPU nodes started on
   this machine (``benchmarks/local_ray.py``; stopped and removed at the end, other Rays
   untouched) and the fleet of [2] converted by the whole command in-process (``--jobs 1``), on
   the local pool of N and on Ray (``--engine ray --address``), interleaved, on the same logs:
   speed-up over in-process, efficiency (speed-up / N), the CPUs each got, peak memory of each
   process and the cluster's own. ``--ray-only`` runs this section alone.

Usage: ``python benchmarks/bench_convert.py [--messages 1000000] [--logs 20] [--log-messages 200000]
[--ray-nodes 2,3] [--ray-only]``
(prints each ratio; the machine is shared and noisy, so ratios, not absolute times, count).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from imupipe.pipeline.convert.fleet import convert
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap

sys.path.insert(0, str(Path(__file__).resolve().parent))
from local_ray import cluster_rss_mb, ray_cluster, stop_cluster  # noqa: E402
from proc_memory import run_measured  # noqa: E402

CALIBRATION = {
    "imupipe_version": "bench",
    "chain": [
        {
            "type": "accel_calibration",
            "sensor": "accel",
            "kind": "linear",
            "matrix": [[1.01, 0.002, -0.001], [0.0, 0.99, 0.003], [0.001, 0.0, 1.02]],
            "offset": [0.05, -0.03, 0.08],
        },
        {
            "type": "gyro_calibration",
            "sensor": "gyro",
            "kind": "linear",
            "matrix": [[1.0, 0.001, 0.0], [0.0, 1.0, 0.0], [0.0, 0.002, 0.998]],
            "offset": [0.01, -0.02, 0.005],
        },
    ],
    "results": {},
}


def make_log(path: Path, messages: int, seed: int = 0) -> None:
    """An MCAP of ``messages`` Imu messages at 1 kHz (no other topic)."""
    table, _ = simulate(
        "static", {"rate_hz": 1000.0, "duration_s": messages / 1000.0, "temperature": None}, seed
    )
    write_mcap(path, table)


def rosbags_read(path: Path) -> tuple[float, int]:
    """The peer: read and deserialise every message with rosbags' AnyReader."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    start = time.perf_counter()
    n = 0
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for conn, _, raw in reader.messages(connections=reader.connections):
            reader.deserialize(raw, conn.msgtype)
            n += 1
    return time.perf_counter() - start, n


def burn(_: int) -> int:
    """A pure-CPU task of about 0.1 s (no I/O, no numpy)."""
    return sum(i * i for i in range(1_500_000))


def timed_burn(n: int, jobs: int) -> float:
    """``n`` pure-CPU tasks on a local pool of ``jobs`` workers (a pool for 1 too: ``run_tasks``
    would run them in-process, without the pool's start-up)."""
    from imupipe.pipeline.convert.engines import run_local

    start = time.perf_counter()
    run_local(burn, list(range(n)), lambda _: None, jobs=jobs)
    return time.perf_counter() - start


def timed_convert(logs: list[Path], cal: Path, out: Path, **kw) -> tuple[float, object]:
    shutil.rmtree(out, ignore_errors=True)
    start = time.perf_counter()
    summary = convert(logs, cal, out, **kw)
    seconds = time.perf_counter() - start
    if summary.failed:
        raise SystemExit(f"conversion failed: {summary.failed}")
    return seconds, summary


def measured_cli(
    logs: list[Path], cal: Path, out: Path, *extra: str
) -> tuple[float, float, list[dict]]:
    """``imupipe convert`` in a fresh process, as a user runs it: (seconds, the command's own
    process's peak RSS in MB, manifest lines). A local pool's workers and a Ray cluster's
    processes are not in that peak: their ``peak_rss_mb`` is in the manifest lines."""
    from imupipe.pipeline.convert.manifest import read_manifest

    shutil.rmtree(out, ignore_errors=True)
    cli = ["convert", "-q", "--calibration", str(cal), "--out", str(out), *extra]
    seconds, peak_mb = run_measured([*cli, *map(str, logs)], out.with_name(out.name + ".peak"))
    return seconds, peak_mb, list(read_manifest(out))


def timed_cli(logs: list[Path], cal: Path, out: Path, *extra: str) -> tuple[float, list[dict]]:
    """``imupipe convert`` in a fresh process, as a user runs it: (seconds, manifest lines)."""
    seconds, _, lines = measured_cli(logs, cal, out, *extra)
    return seconds, lines


def ray_section(n: int, fleet: Path, cal: Path, tmp: Path, args: argparse.Namespace) -> dict:
    """[5] The fleet converted by the whole command (a fresh process each, as a user runs it) in
    three ways, interleaved, best of 2: in-process (``--jobs 1``), the local pool of ``n``
    workers, and a Ray cluster of ``n`` one-CPU nodes started here (``--engine ray --address``);
    efficiency = speed-up over in-process / ``n``. Beside it the machine's own ceiling now (the
    pool's pure-CPU speed-up, ``n`` workers against 1), the CPUs each way got (its workers' CPU
    seconds over its wall time) and the peak memory of each."""
    root = Path(tempfile.mkdtemp(prefix="imupipe-bench-ray-", dir="/tmp"))
    t0 = time.perf_counter()
    address, procs = ray_cluster(n, root)
    try:
        started = time.perf_counter() - t0
        idle_mb = cluster_rss_mb(root)
        ways = {
            "inline": ("--jobs", "1"),
            "pool": ("--jobs", str(n)),
            "ray": ("--engine", "ray", "--address", address),
        }
        best = {way: (float("inf"), 0.0, 0.0, 0.0) for way in ways}
        c1 = cn = float("inf")
        for _ in range(2):
            for way, extra in ways.items():
                seconds, peak, lines = measured_cli([fleet], cal, tmp / f"out5_{way}", *extra)
                done = [x for x in lines if x.get("status") == "converted"]
                if len(done) != args.logs:
                    raise SystemExit(f"[5] {way}: {len(done)} of {args.logs} logs converted")
                if seconds < best[way][0]:
                    cpus = sum(x["cpu_seconds"] for x in done) / seconds
                    best[way] = (seconds, peak, max(x["peak_rss_mb"] for x in done), cpus)
            c1 = min(c1, timed_burn(args.logs, jobs=1))
            cn = min(cn, timed_burn(args.logs, jobs=n))
        busy_mb = cluster_rss_mb(root)
    finally:
        stop_cluster(procs, root)
    from imupipe.pipeline.convert.ray_reaper import session_processes

    left = session_processes(str(root))
    if left or root.exists():
        print(f"[5] warning: the Ray cluster left {left} / {root}", file=sys.stderr)
    (t1, p1, _, u1), (tp, pp, wp, up), (tr, pr, wr, ur) = (best[w] for w in ways)
    print(
        f"[5] {args.logs} logs x {args.log_messages:,} msgs, whole command, best of 2 "
        f"(Ray cluster of {n} one-CPU nodes started in {started:.1f} s): in-process {t1:.2f} s "
        f"(peak {p1:.0f} MB, {u1:.2f} CPUs); local pool of {n}: {tp:.2f} s -> {t1 / tp:.2f}x, "
        f"efficiency {t1 / (n * tp):.2f} ({up:.2f} CPUs; worker peak {wp:.0f} MB, command "
        f"{pp:.0f} MB); Ray on {n} nodes: {tr:.2f} s -> {t1 / tr:.2f}x, efficiency "
        f"{t1 / (n * tr):.2f} ({ur:.2f} CPUs; Ray worker peak {wr:.0f} MB, driver {pr:.0f} MB, "
        f"the cluster itself {idle_mb:.0f} MB idle, {busy_mb:.0f} MB after the runs); Ray at "
        f"{tp / tr:.2f}x the pool's speed; the machine's ceiling now (pure-CPU tasks, pool of "
        f"{n} against 1): {c1 / cn:.2f}x"
    )
    return {
        f"ray{n}_inline_s": t1,
        f"ray{n}_pool_s": tp,
        f"ray{n}_ray_s": tr,
        f"ray{n}_pool_speedup": t1 / tp,
        f"ray{n}_ray_speedup": t1 / tr,
        f"ray{n}_pool_efficiency": t1 / (n * tp),
        f"ray{n}_ray_efficiency": t1 / (n * tr),
        f"ray{n}_ray_vs_pool": tp / tr,
        f"ray{n}_machine_ceiling": c1 / cn,
        f"ray{n}_inline_peak_mb": p1,
        f"ray{n}_pool_worker_peak_mb": wp,
        f"ray{n}_pool_command_peak_mb": pp,
        f"ray{n}_ray_worker_peak_mb": wr,
        f"ray{n}_ray_driver_peak_mb": pr,
        f"ray{n}_cluster_idle_mb": idle_mb,
        f"ray{n}_cluster_after_mb": busy_mb,
        f"ray{n}_cluster_start_s": started,
        f"ray{n}_inline_cpus": u1,
        f"ray{n}_pool_cpus": up,
        f"ray{n}_ray_cpus": ur,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=1_000_000)
    ap.add_argument("--logs", type=int, default=20)
    ap.add_argument("--log-messages", type=int, default=200_000)
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    ap.add_argument(
        "--ray-nodes",
        type=lambda v: [int(n) for n in v.split(",")],
        default=[],
        help="[5]: Ray clusters of N one-CPU nodes, one after the other (e.g. 2,3; default: skip)",
    )
    ap.add_argument("--ray-only", action="store_true", help="run [5] only (with its own peers)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_convert_"))
    cal = tmp / "calibration.json"
    cal.write_text(json.dumps(CALIBRATION))
    results: dict[str, float] = {}
    try:
        fleet = tmp / "fleet"
        fleet.mkdir()
        for i in range(args.logs):
            make_log(fleet / f"log{i:02d}.mcap", args.log_messages, seed=10 + i)
        if not args.ray_only:
            big = tmp / "big" / "imu.mcap"
            big.parent.mkdir()
            make_log(big, args.messages)
            quarter = tmp / "quarter" / "imu.mcap"
            quarter.parent.mkdir()
            make_log(quarter, args.messages // 4, seed=1)

            # 1. one big log against the rosbags read-and-deserialise loop, interleaved, best of 2:
            # the work itself (read + correct + write + verify, like the peer's loop), convert() called
            # from Python, and the whole command in a fresh process (interpreter start, imports and
            # planning included; one log runs in-process: no pool)
            t_peer = t_ours = t_worker = t_cli = float("inf")
            for _ in range(2):
                seconds, n_peer = rosbags_read(big)
                t_peer = min(t_peer, seconds)
                seconds, summary = timed_convert([big], cal, tmp / "out_big", jobs=1)
                (stats,) = summary.converted
                assert stats.messages == n_peer == args.messages, (stats.messages, n_peer)
                t_ours, t_worker = min(t_ours, seconds), min(t_worker, stats.seconds)
                seconds, lines = timed_cli([big], cal, tmp / "out_cli")
                assert lines[-1]["messages"] == args.messages, lines[-1]
                t_cli = min(t_cli, seconds)
            results.update(
                convert_1log_worker_s=t_worker,
                convert_1log_call_s=t_ours,
                convert_1log_command_s=t_cli,
                rosbags_read_deserialize_s=t_peer,
                speedup_vs_rosbags=t_peer / t_worker,
                speedup_vs_rosbags_call=t_peer / t_ours,
                speedup_vs_rosbags_command=t_peer / t_cli,
            )
            print(
                f"[1] {args.messages:,} Imu messages: rosbags AnyReader read+deserialise {t_peer:.2f} s; "
                f"imupipe convert read+correct+write+verify {t_worker:.2f} s "
                f"({args.messages / t_worker / 1e6:.2f} M msg/s) -> {t_peer / t_worker:.1f}x faster "
                f"(goal >= 5x); convert() call {t_ours:.2f} s -> {t_peer / t_ours:.1f}x; whole command "
                f"in a fresh process {t_cli:.2f} s -> {t_peer / t_cli:.1f}x (goal >= 6x)"
            )

            # 3. peak memory of the process converting (a fresh one each: its peak is its own):
            # streamed big, streamed quarter, big read whole
            _, lines = timed_cli([big], cal, tmp / "out_big_mem")
            results["peak_rss_streamed_mb"] = lines[-1]["peak_rss_mb"]
            _, lines = timed_cli([quarter], cal, tmp / "out_quarter")
            results["peak_rss_streamed_quarter_mb"] = lines[-1]["peak_rss_mb"]
            _, lines = timed_cli([big], cal, tmp / "out_whole", "--batch-rows", str(10**12))
            results["peak_rss_one_batch_mb"] = lines[-1]["peak_rss_mb"]
            print(
                f"[3] peak RSS of the converting process: streamed {args.messages:,} msgs "
                f"{results['peak_rss_streamed_mb']:.0f} MB, streamed {args.messages // 4:,} msgs "
                f"{results['peak_rss_streamed_quarter_mb']:.0f} MB, the big log in one batch "
                f"{results['peak_rss_one_batch_mb']:.0f} MB"
            )

            # 4. the per-log fixed cost: n tiny logs against one, one worker, best of 3
            tiny = tmp / "tiny"
            tiny.mkdir()
            for i in range(args.logs):
                make_log(tiny / f"t{i:02d}.mcap", 1000, seed=100 + i)
            one = all_ = float("inf")
            worker_ms = float("inf")
            for _ in range(3):
                one = min(one, timed_convert([tiny / "t00.mcap"], cal, tmp / "out_t1", jobs=1)[0])
                seconds, s_tiny = timed_convert([tiny], cal, tmp / "out_tn", jobs=1)
                all_ = min(all_, seconds)
                worker_ms = min(
                    worker_ms, 1e3 * sum(s.seconds for s in s_tiny.converted) / args.logs
                )
            fixed = (all_ - one) / (args.logs - 1)
            results.update(fixed_cost_per_log_ms=1e3 * fixed, worker_time_per_tiny_log_ms=worker_ms)
            print(
                f"[4] per-log fixed cost: {1e3 * fixed:.1f} ms per log ({args.logs} logs of 1,000 "
                f"msgs {all_:.2f} s against one {one:.2f} s, one worker; the worker's own time per "
                f"tiny log {worker_ms:.1f} ms) = {1e6 * fixed / args.log_messages:.2f} us per message "
                f"on logs of {args.log_messages:,}; the big log alone: "
                f"{1e6 * t_ours / args.messages:.2f} us per message (whole command)"
            )

            # 2. 20 logs, 1 worker against 2; and what this (shared) machine gives two processes now:
            # the same pool running a pure-CPU task, 1 against 2 workers, interleaved, best of 3
            t1 = t2 = c1 = c2 = float("inf")
            busy = 0.0
            for _ in range(3):
                t1 = min(t1, timed_convert([fleet], cal, tmp / "out_j1", jobs=1)[0])
                seconds, s2 = timed_convert([fleet], cal, tmp / "out_j2", jobs=2)
                if seconds < t2:
                    t2, busy = seconds, sum(s.cpu_seconds for s in s2.converted) / seconds
                c1 = min(c1, timed_burn(args.logs, jobs=1))
                c2 = min(c2, timed_burn(args.logs, jobs=2))
            per_msg = 1e6 * t1 / (args.logs * args.log_messages)
            results.update(
                fleet_us_per_message_1_worker=per_msg,
                fleet_1_worker_s=t1,
                fleet_2_workers_s=t2,
                fleet_speedup=t1 / t2,
                machine_speedup=c1 / c2,
                cpus_busy_2_workers=busy,
            )
            print(
                f"[2] {args.logs} logs x {args.log_messages:,} msgs: 1 worker {t1:.2f} s, "
                f"2 workers {t2:.2f} s -> {t1 / t2:.2f}x (goal >= 1.6x); the machine's own ceiling "
                f"now (pure-CPU tasks, same pool): {c1 / c2:.2f}x; CPUs the 2 workers got: {busy:.2f}; "
                f"{per_msg:.2f} us per message with 1 worker"
            )
        for n in args.ray_nodes:
            results.update(ray_section(n, fleet, cal, tmp, args))
        print(json.dumps({k: round(v, 3) for k, v in results.items()}))
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
