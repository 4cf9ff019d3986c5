"""Issue 18: ``--engine ray`` without ``--address`` starts a Ray that listens on loopback only.

Every listening TCP socket of the driver and of the Ray processes it started (GCS, raylet,
workers, agents) is read with ``ss -ltnp`` while the tasks run: each must be bound to 127.0.0.1
(or its IPv6-mapped form), none to every interface or to the machine's address.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_fault_kill import descendants

from imupipe.pipeline.convert.engines import run_tasks
from imupipe.pipeline.convert.manifest import read_manifest

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


# -- issue 27: Ray as an operator expects ---------------------------------------------------------


def _fleet(tmp_path: Path, n: int = 6, messages: int = 40_000) -> tuple[Path, Path]:
    from imupipe.pipeline.simulate import simulate
    from imupipe.pipeline.writers.mcap import write_mcap

    fleet = tmp_path / "fleet"
    fleet.mkdir()
    table, _ = simulate("static", {"duration_s": messages / 1000, "rate_hz": 1000.0}, seed=2)
    write_mcap(fleet / "l0.mcap", table)
    for i in range(1, n):
        (fleet / f"l{i}.mcap").write_bytes((fleet / "l0.mcap").read_bytes())
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"chain": [{"type": "t", "sensor": "gyro", "kind": "linear",
                   "matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "offset": [0.1, 0, 0]}]}))  # fmt: skip
    return fleet, cal


def _ray_roots() -> set[Path]:
    return set(Path("/tmp").glob("imupipe-ray-*"))


def _convert(cal: Path, out: Path, *logs: Path, extra: tuple[str, ...] = ()) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "imupipe.pipeline.cli", "convert", "--engine", "ray", "-j", "1",
         "-q", "--calibration", str(cal), "--out", str(out), *extra, *map(str, logs)],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _left(roots: set[Path]) -> list[str]:
    """What the Ray under each of ``roots`` left: its folder, its processes."""
    from imupipe.pipeline.convert.ray_reaper import session_processes

    left = [str(r) for r in roots if r.exists()]
    for r in roots:
        left += [Path(f"/proc/{p}/cmdline").read_text()[:60] for p in session_processes(str(r))]
    return left


@pytest.mark.slow
def test_a_clean_ray_run_leaves_nothing_and_says_nothing_of_ray(tmp_path):
    pytest.importorskip("ray")
    fleet, cal = _fleet(tmp_path, n=2, messages=2000)
    before = _ray_roots()
    proc = _convert(cal, tmp_path / "out", fleet)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert err == "", err  # Ray's own lines are in DIR/ray.log
    lines = list(read_manifest(tmp_path / "out"))
    assert {rec["engine_log"] for rec in lines} == {str(tmp_path / "out" / "ray.log")}
    time.sleep(1)
    assert _left(_ray_roots() - before) == []


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_a_stopped_ray_driver_leaves_no_process(tmp_path, sig):
    """SIGTERM, SIGINT or SIGKILL of the driver while the tasks run: exit 143 / 130 (one line)
    or -9, and within 15 s no process of the Ray it started and no session folder."""
    pytest.importorskip("ray")
    fleet, cal = _fleet(tmp_path)
    before = _ray_roots()
    proc = _convert(cal, tmp_path / "out", fleet)
    deadline = time.monotonic() + 240
    roots: set[Path] = set()
    while time.monotonic() < deadline and proc.poll() is None:  # until Ray's agents are up
        roots |= _ray_roots() - before
        if roots and any("Agent" in Path(f"/proc/{p}/cmdline").read_text(errors="replace")
                         for p in descendants(proc.pid) if Path(f"/proc/{p}").exists()):  # fmt: skip
            break
        time.sleep(0.3)
    if proc.poll() is not None:
        pytest.skip("the run ended before Ray's agents were seen (machine too fast or too slow)")
    time.sleep(1.0)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    want = {signal.SIGTERM: (143, "imupipe: terminated"), signal.SIGINT: (130, "imupipe: interrupted"),
            signal.SIGKILL: (-9, "")}[sig]  # fmt: skip
    ray_log = tmp_path / "out" / "ray.log"
    assert (proc.returncode, err.strip()) == want, (
        ray_log.read_text()[-3000:] if ray_log.exists() else err
    )
    stop = time.monotonic() + 15
    while _left(roots) and time.monotonic() < stop:
        time.sleep(0.5)
    assert _left(roots) == []


def test_an_unreachable_cluster_is_one_line_within_10_s(tmp_path):
    pytest.importorskip("ray")
    fleet, cal = _fleet(tmp_path, n=1, messages=1000)
    start = time.monotonic()
    proc = _convert(cal, tmp_path / "out", fleet, extra=("--address", "ray://127.0.0.1:1"))
    _, err = proc.communicate(timeout=60)
    assert time.monotonic() - start < 10
    assert proc.returncode == 2 and err.count("\n") == 1 and err.startswith("imupipe: error: ")
    assert "127.0.0.1:1" in err and not (tmp_path / "out").exists()
