"""Memory of the benchmarks' child processes, read from /proc/self/status (Linux).

``VmHWM`` is the process's own high-water mark. ``ru_maxrss`` is not used: in a child started
by a parent that holds a big table it can carry the parent's RSS at fork time, which inflated
the figures once. Child probes import this file by putting :data:`HERE` on ``sys.path``.
"""

from __future__ import annotations

from pathlib import Path

HERE = str(Path(__file__).resolve().parent)


def status_bytes(key: str) -> int:
    """A ``/proc/self/status`` size in bytes: ``VmRSS`` (now) or ``VmHWM`` (peak)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def run_probe(code: str, *args: str) -> dict:
    """Run ``code`` in a fresh Python with ``args`` and this folder as its last argument (for
    ``sys.path``); returns the JSON object it prints last."""
    import json
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", code, *map(str, args), HERE],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])
