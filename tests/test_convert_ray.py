"""Issue 18: ``--engine ray`` without ``--address`` starts a Ray that listens on loopback only.

Every listening TCP socket of the driver and of the Ray processes it started (GCS, raylet,
workers, agents) is read with ``ss -ltnp`` while the tasks run: each must be bound to 127.0.0.1
(or its IPv6-mapped form), none to every interface or to the machine's address.
"""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest
from test_fault_kill import descendants

from imupipe.pipeline.engines import run_tasks

LOOPBACK = ("127.0.0.1:", "[::ffff:127.0.0.1]:", "[::1]:")


def listening(pids: set[int]) -> list[tuple[str, str]]:
    """(local address, process) of every listening TCP socket of ``pids``."""
    out = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True).stdout
    found = []
    for line in out.splitlines():
        cols = line.split()
        if any(f"pid={p}," in cols[-1] for p in pids):
            found.append((cols[3], cols[-1]))
    return found


def test_local_ray_listens_on_loopback_only():
    ray = pytest.importorskip("ray")
    if shutil.which("ss") is None:
        pytest.skip("no ss command (iproute2) to list the listening sockets")
    assert not ray.is_initialized()
    seen: list[tuple[str, str]] = []

    def on_done(outcome) -> None:
        assert outcome.error is None, outcome.error
        seen.extend(listening(descendants(os.getpid()) | {os.getpid()}))

    run_tasks(abs, [-3], on_done, engine="ray", jobs=1)
    assert not ray.is_initialized()  # the Ray started here is shut down at the end
    assert len(seen) >= 5, seen  # GCS, raylet, a worker, the agents
    exposed = [(addr, proc) for addr, proc in seen if not addr.startswith(LOOPBACK)]
    assert not exposed, exposed
