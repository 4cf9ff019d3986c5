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

5. Issue 27, with ``--ray-nodes N``: the fleet of [2] on a Ray cluster of N one-CPU nodes started
   on this machine (``ray start --head`` and N - 1 ``ray start --address``, all on 127.0.0.1,
   under a folder of their own; stopped and removed at the end, other Rays untouched) against the
   local pool of N workers and of 1: Ray's efficiency (1-worker time / (N x Ray time)) beside the
   pool's.

Usage: ``python benchmarks/bench_convert.py [--messages 1000000] [--logs 20] [--log-messages 200000]
[--ray-nodes 2]``
(prints each ratio; the machine is shared and noisy, so ratios, not absolute times, count).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from imupipe.pipeline.convert.fleet import convert
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap

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
    from imupipe.pipeline.convert.engines import run_tasks

    start = time.perf_counter()
    run_tasks(burn, list(range(n)), lambda _: None, jobs=jobs)
    return time.perf_counter() - start


def timed_convert(logs: list[Path], cal: Path, out: Path, **kw) -> tuple[float, object]:
    shutil.rmtree(out, ignore_errors=True)
    start = time.perf_counter()
    summary = convert(logs, cal, out, **kw)
    seconds = time.perf_counter() - start
    if summary.failed:
        raise SystemExit(f"conversion failed: {summary.failed}")
    return seconds, summary


def timed_cli(logs: list[Path], cal: Path, out: Path, *extra: str) -> tuple[float, list[dict]]:
    """``imupipe convert`` in a fresh process, as a user runs it: (seconds, manifest lines)."""
    from imupipe.pipeline.convert.manifest import read_manifest

    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "imupipe.pipeline.cli", "convert", "-q", "--calibration"]
    start = time.perf_counter()
    subprocess.run([*cmd, str(cal), "--out", str(out), *extra, *map(str, logs)], check=True)
    seconds = time.perf_counter() - start
    return seconds, list(read_manifest(out))


def ray_cluster(nodes: int, root: Path) -> tuple[str, list[subprocess.Popen]]:
    """Start a Ray cluster of ``nodes`` one-CPU nodes on 127.0.0.1 under ``root``; returns (GCS
    address, the ``ray start --block`` processes)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    address = f"127.0.0.1:{port}"
    # `ray start` turns Ray's token authentication on (Ray 2.52+); a driver sends the token
    # (~/.ray/auth_token) only when told to
    os.environ["RAY_AUTH_MODE"] = "token"
    common = ["--num-cpus=1", "--node-ip-address=127.0.0.1", "--block", "--disable-usage-stats"]
    procs = [
        subprocess.Popen(
            ["ray", "start", "--head", f"--port={port}", f"--temp-dir={root}",
             "--include-dashboard=false", *common],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
        )
    ]  # fmt: skip
    import ray

    deadline = time.monotonic() + 120
    while True:  # the head up before the others join
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            if time.monotonic() > deadline:
                raise SystemExit("the Ray head did not start") from None
            time.sleep(0.5)
    for _ in range(nodes - 1):
        procs.append(
            subprocess.Popen(
                ["ray", "start", f"--address={address}", *common],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
            )
        )  # fmt: skip
    try:
        ray.init(address=address, logging_level="ERROR", log_to_driver=False)
        while len([n for n in ray.nodes() if n["Alive"]]) < nodes:
            if time.monotonic() > deadline:
                raise SystemExit(f"only {len(ray.nodes())} of {nodes} Ray nodes joined")
            time.sleep(0.5)
    except BaseException:
        stop_cluster(procs, root)
        raise
    finally:
        ray.shutdown()
    return address, procs


def stop_cluster(procs: list[subprocess.Popen], root: Path) -> None:
    """Stop the nodes started by :func:`ray_cluster` (by their ids) and whatever runs under
    ``root``; remove ``root``."""
    from imupipe.pipeline.convert.ray_reaper import reap

    for proc in procs:
        proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    reap(str(root))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=1_000_000)
    ap.add_argument("--logs", type=int, default=20)
    ap.add_argument("--log-messages", type=int, default=200_000)
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    ap.add_argument("--ray-nodes", type=int, default=0, help="[5]: Ray nodes of one CPU (0: skip)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_convert_"))
    cal = tmp / "calibration.json"
    cal.write_text(json.dumps(CALIBRATION))
    results: dict[str, float] = {}
    try:
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
            worker_ms = min(worker_ms, 1e3 * sum(s.seconds for s in s_tiny.converted) / args.logs)
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
        fleet = tmp / "fleet"
        fleet.mkdir()
        for i in range(args.logs):
            make_log(fleet / f"log{i:02d}.mcap", args.log_messages, seed=10 + i)
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
        if args.ray_nodes:
            # 5. the same fleet on a local multi-node Ray cluster against the local pool
            n = args.ray_nodes
            root = Path(tempfile.mkdtemp(prefix="imupipe-bench-ray-", dir="/tmp"))
            address, procs = ray_cluster(n, root)
            try:
                t_ray = t_pool = float("inf")
                for _ in range(2):
                    t_ray = min(
                        t_ray,
                        timed_convert([fleet], cal, tmp / "out_ray", engine="ray", address=address)[
                            0
                        ],
                    )
                    t_pool = min(t_pool, timed_convert([fleet], cal, tmp / "out_jn", jobs=n)[0])
            finally:
                stop_cluster(procs, root)
            results.update(
                ray_nodes=n,
                ray_fleet_s=t_ray,
                pool_fleet_s=t_pool,
                ray_efficiency=t1 / (n * t_ray),
                pool_efficiency=t1 / (n * t_pool),
                ray_vs_pool=t_pool / t_ray,
            )
            print(
                f"[5] {args.logs} logs x {args.log_messages:,} msgs on a Ray cluster of {n} "
                f"one-CPU nodes on this machine: {t_ray:.2f} s, efficiency "
                f"{t1 / (n * t_ray):.2f} (1 worker {t1:.2f} s); local pool of {n}: {t_pool:.2f} s, "
                f"efficiency {t1 / (n * t_pool):.2f}; Ray at {t_pool / t_ray:.2f}x the pool's speed"
            )
        print(json.dumps({k: round(v, 3) for k, v in results.items()}))
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
