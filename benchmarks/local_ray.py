"""A local multi-node Ray cluster for the benchmarks (issue 27 [5] of ``bench_convert.py``,
issue 30 of ``bench_survey.py``): N one-CPU nodes on 127.0.0.1 (``ray start --head`` and N - 1
``ray start --address``), every process of it under a temporary folder of its own, stopped and
the folder removed at the end; another Ray on the machine is not touched.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path


def ray_cluster(nodes: int, root: Path) -> tuple[str, list[subprocess.Popen]]:
    """Start a Ray cluster of ``nodes`` one-CPU nodes on 127.0.0.1 under ``root``; returns (GCS
    address, the ``ray start --block`` processes).

    The nodes stay in this process's session: with the kernel's autogroup scheduling (Linux's
    default on desktops and on this machine), each session gets a fair share of a busy machine,
    so nodes in sessions of their own got up to twice the CPU the local pool got in the
    benchmark's session, which measured the machine's scheduler, not the engines."""
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
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=False,
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
    try:
        ray.init(address=address, logging_level="ERROR", log_to_driver=False)
        for k in range(2, nodes + 1):  # one node at a time (started together, one did not join)
            log = open(root / f"node-{k}.out", "wb")  # noqa: SIM115 - the node's, closed with it
            procs.append(
                subprocess.Popen(
                    ["ray", "start", f"--address={address}", *common],
                    stdout=log, stderr=subprocess.STDOUT, start_new_session=False,
                )
            )  # fmt: skip
            log.close()
            deadline = time.monotonic() + 120
            while len([n for n in ray.nodes() if n["Alive"]]) < k:
                if time.monotonic() > deadline or procs[-1].poll() is not None:
                    said = (root / f"node-{k}.out").read_text(errors="replace")[-2000:]
                    raise SystemExit(f"Ray node {k} of {nodes} did not join; it said:\n{said}")
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


def cluster_rss_mb(root: Path) -> float:
    """Resident memory of a Ray cluster started by :func:`ray_cluster` (every process under
    ``root``: GCS, raylets, agents, idle workers), MB."""
    from imupipe.pipeline.convert.ray_reaper import session_processes

    total = 0
    for pid in session_processes(str(root)):
        try:
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except OSError:
            continue
    return total / 1024
