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


PEAK_WRAPPER = """
import atexit, sys

def peak(path=sys.argv[1]):
    with open('/proc/self/status') as fh:
        hwm = next(line.split()[1] for line in fh if line.startswith('VmHWM:'))
    with open(path, 'w') as fh:
        fh.write(hwm)

atexit.register(peak)
sys.argv = ['imupipe', *sys.argv[2:]]
try:
    from imupipe.pipeline.cli import console
except ImportError:  # a checkout before the console entry (a --baseline)
    from imupipe.pipeline.cli import main
    sys.exit(main())
console()
"""
"""An ``imupipe`` command run as the ``imupipe`` program runs it (:func:`imupipe.pipeline.cli.
console`) that writes its process's own peak RSS (``VmHWM``, kB) to ``argv[1]`` at exit."""


def run_measured(
    argv: list[str], peak_file: Path, env: dict[str, str] | None = None
) -> tuple[float, float]:
    """Run ``imupipe ARGV`` in a fresh Python, as a user runs it: (seconds, the command's own
    process's peak RSS in MB, from its ``VmHWM``; a pool's workers and a Ray cluster's processes
    are not in it). ``env``: the process's environment (default: this one's). A failing command
    raises ``CalledProcessError``."""
    import subprocess
    import sys
    import time

    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", PEAK_WRAPPER, str(peak_file), *argv], check=True, env=env)
    seconds = time.perf_counter() - start
    return seconds, int(peak_file.read_text()) / 1024


def children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished children so far (``getrusage``:
    far less moved by the other sessions of a shared machine than wall time)."""
    import resource

    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


FLOOR = "import numpy, pyarrow"
"""What the library floor's process runs: the imports of any tool that builds Arrow tables."""


FLOOR_FROZEN = "import gc, numpy, pyarrow; gc.freeze()"
"""The floor ending as the ``imupipe`` program ends (:func:`imupipe.pipeline.cli.console`: the
objects alive frozen before the interpreter exits, whose last collection then skips them): the
floor against which imupipe's own cost is counted without the part of that saving that falls on
numpy's and pyarrow's objects."""


def floor_cpu(env: dict[str, str] | None = None, code: str = FLOOR) -> float:
    """CPU seconds of a fresh Python (environment ``env``, default this one's) that imports
    numpy and pyarrow (:data:`FLOOR`, or ``code``) and stops: what any Python tool that builds
    Arrow tables pays before it reads a byte."""
    import subprocess
    import sys

    cpu = children_cpu()
    subprocess.run([sys.executable, "-c", code], check=True, env=env)
    return children_cpu() - cpu
