"""The reaper of a local Ray that imupipe started: no Ray process or session folder outlives the
command, however it ends.

The driver starts Ray with a temporary folder of its own (``ray.init(_temp_dir=ROOT)``, ROOT a
fresh ``/tmp/imupipe-ray-XXXXXXXX``), so every process of that Ray names ROOT on its command line
(GCS, raylet, log monitor: each gets its session folder under ROOT) or holds its log files
there open (the agents and workers, which rename themselves). Before Ray starts, the driver starts ``python -m imupipe.pipeline.convert.ray_reaper
ROOT DRIVER_PID`` in a process session of its own (a Ctrl-C or a process-group kill aimed at the command
does not reach it), which waits for end of file on its standard input, a pipe from the driver.
The pipe closes when the driver is done with Ray (after ``ray.shutdown()``) or when the driver
dies, even by SIGKILL (the kernel closes it). The reaper then ends every process whose command
line names ROOT or that holds a file under it open, SIGTERM first and SIGKILL after :data:`GRACE_S` seconds, and removes ROOT.
Only that Ray is touched: another Ray on the machine (another user's, another command's) names
another folder.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sys
import time
from pathlib import Path

GRACE_S = 3.0
"""How long Ray's processes get to exit on SIGTERM before SIGKILL."""


def session_processes(root: str, spare: int | None = None) -> list[int]:
    """The processes (other than this one and ``spare``, the driver) whose command line names
    ``root`` or that hold a
    file under ``root`` open (Ray's agents and workers rename themselves, ``ray::DashboardAgent``,
    so their command lines no longer name it, but each keeps its log files in its session folder
    open), and every process below those."""
    key = os.fsencode(root)
    prefix = root.rstrip("/") + "/"
    found = []
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) in (os.getpid(), spare):
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            parents[int(entry)] = int(stat[stat.rindex(")") + 2 :].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        try:
            if key in Path(f"/proc/{entry}/cmdline").read_bytes():
                found.append(int(entry))
                continue
            fds = os.listdir(f"/proc/{entry}/fd")
        except OSError:
            continue
        for fd in fds:
            with contextlib.suppress(OSError):
                if os.readlink(f"/proc/{entry}/fd/{fd}").startswith(prefix):
                    found.append(int(entry))
                    break
    # and every process below those (an agent or worker still starting has opened nothing yet)
    frontier = set(found)
    while frontier:
        frontier = {p for p, pp in parents.items() if pp in frontier} - set(found)
        found += sorted(frontier)
    return found


def reap(root: str, spare: int | None = None) -> None:
    """End the processes of the Ray under ``root`` and remove ``root`` (see the module
    docstring), never ``spare`` (the driver, which keeps its own Ray log open). Repeated until
    none is left (a dying raylet may still start a worker)."""
    for _ in range(5):
        pids = session_processes(root, spare)
        if not pids:
            break
        for pid in pids:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + GRACE_S
        while pids and time.monotonic() < deadline:
            time.sleep(0.1)
            pids = [p for p in pids if _alive(p)]
        for pid in pids:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.2)
    for _ in range(3):  # a process that was ending may still have made a folder there
        shutil.rmtree(root, ignore_errors=True)
        time.sleep(0.5)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def main() -> None:
    root, driver = sys.argv[1], int(sys.argv[2])
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        while sys.stdin.buffer.read(1 << 16):
            pass
    reap(root, driver)


if __name__ == "__main__":
    main()
