"""Benchmark: the ``allan`` stage and a whole ``imupipe run`` against allantools, in one run.

1. Stage alone: ``AllanStage.fit`` with default options (sample clock, motion check, the
   ``auto`` tau grid, noise identification + Greenhall EDF + chi-square bounds, the five-term
   fit with K's profile interval, on six axes) on a common table in memory, against
   ``allantools.oadev(taus="octave")`` on the same six arrays, at 0.5 M, 2.88 M (2 h at
   400 Hz) and 8 M samples. Each size runs in a fresh process; the two sides alternate, best
   of ``--repeats`` each. Goal: ratio <= 1.0 at every size.
2. ``imupipe run`` of a 2 h, 400 Hz static CSV with one ``allan`` stage and default options
   (read + fit + ``imu.yaml`` + Rerun recording), as a user runs it: a fresh Python process,
   imports included; against allantools ``oadev(taus="octave")`` on the same six arrays in
   memory. Goal: ratio <= 2.0. Peak RSS (``VmHWM``) of the run's process beside the size of
   the input's common table; the best run in parts (imports, read, stage, ``report.html``, the
   rest); and the floor no run avoids (a fresh process importing what a run imports, import by
   import, then ``pyarrow.csv.read_csv`` of the file) against the same peer.

3. ``--script``: the whole ``imupipe run`` (one ``allan`` stage, defaults, every output)
   against what a user writes without imupipe, each a whole process on the same CSV: the
   user's script (``pandas.read_csv``, then ``allantools.oadev(taus="octave")`` per axis;
   :data:`USER_SCRIPT`). The two alternate in pairs; each pair gives the ratio of wall times
   and of CPU times (``os.wait4``'s rusage of that child: user + system, every thread), and the
   children's peak RSS (``ru_maxrss``; the parent holds no data: the CSV is written by a child).
   ``--minutes`` sets the log's length (120: the issue's 2 h at 400 Hz); ``--peer-path`` a
   folder put on the script's ``PYTHONPATH`` only (pandas, when it is not installed: imupipe
   never imports it). Goal (issue 39): ratio <= 0.5. Beside them, in each pair, the floor: a
   process that imports what every such run needs (numpy, pyarrow, Rerun for the recording,
   scipy.special's three functions for the confidence bounds and the fit, loaded as the run
   loads them) and reads the file with
   ``pyarrow.csv.read_csv`` (:data:`SCRIPT_FLOOR`). Every child runs with Python's bytecode
   cache on (:func:`bytecode_env`), warmed by an untimed run of each side. ``--baseline DIR``:
   the ``imupipe run`` of another checkout (the code before a change, with its ``.shim``) in
   each pair too, with its ratio to the script and the new code's to it.

Times are noisy on a shared machine: the load average is printed, and the ratios (both sides
measured in the same run, interleaved) are what count.

Usage: ``python benchmarks/bench_allan.py [--sizes 0.5e6 2.88e6 8e6] [--repeats 3]
[--skip-run] [--skip-stage] [--parts] [--script [--minutes 120] [--pairs 2] [--peer-path DIR]
[--baseline DIR]]`` (``--parts``: the CPU time of the stage's parts, per call:
sample clock, motion check, phase, deviations, noise identification + EDF + bounds, fit).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from proc_memory import HERE

RATE = 400.0

STAGE_CHILD = """
import json, sys, time
sys.path.insert(0, sys.argv[3])
import allantools
import numpy as np
from proc_memory import status_bytes
from imupipe.readers.table import make_table
from imupipe.stages.allan.stage import AllanStage
from imupipe.stages.base import StageContext

n, repeats, rate = int(float(sys.argv[1])), int(sys.argv[2]), 400.0
parts = {}
if sys.argv[4:] == ["parts"]:  # CPU time of the stage's parts, per call
    import imupipe.stages.allan.stage as A
    import imupipe.stages.allan.estimators as E

    def timed(owner, name, label):
        f = getattr(owner, name)

        def g(*a, **k):
            t = time.process_time()
            try:
                return f(*a, **k)
            finally:
                parts.setdefault(label, [0.0] * repeats)[r] += time.process_time() - t

        setattr(owner, name, g)

    for owner, name, label in (
        (A, "sample_clock", "sample clock"), (A, "stillness", "motion check"),
        (E, "rate_to_phase", "phase"), (E, "deviation_of_phase", "deviations"),
        (E, "confidence", "noise id + EDF + bounds"), (A, "fit_allan", "fit"),
    ):
        timed(owner, name, label)
rng = np.random.default_rng(0)
t_ns = 1_700_000_000_000_000_000 + np.round(np.arange(n) * (1e9 / rate)).astype(np.int64)
gyro = rng.standard_normal((n, 3)) * 0.01 + np.cumsum(rng.standard_normal((n, 3)), axis=0) * 1e-6
accel = rng.standard_normal((n, 3)) * 0.02 + np.cumsum(rng.standard_normal((n, 3)), axis=0) * 1e-5
accel += [0.0, 0.0, 9.81]
table = make_table(t_ns, gyro=gyro, accel=accel)
columns = [np.ascontiguousarray(a[:, i]) for a in (gyro, accel) for i in range(3)]
del gyro, accel
base = status_bytes("VmHWM")
ours, peer, taus = [], [], 0
for r in range(repeats):
    ctx = StageContext(name="allan", input_name="bench", quiet=True)
    t, cpu = time.perf_counter(), time.process_time()
    out = AllanStage(AllanStage.Options()).fit(table, ctx)
    ours.append(time.perf_counter() - t)
    if parts:
        parts.setdefault("whole stage", [0.0] * repeats)[r] = time.process_time() - cpu
    if r == 0:
        peak = status_bytes("VmHWM")
        taus = out.results["metrics"]["taus"]
    del out
    t = time.perf_counter()
    for c in columns:
        allantools.oadev(c, rate=rate, data_type="freq", taus="octave")
    peer.append(time.perf_counter() - t)
    if parts:
        cpu = time.process_time()
        for c in columns:
            allantools.oadev(c, rate=rate, data_type="freq", taus="octave")
        parts.setdefault("allantools", [0.0] * repeats)[r] = time.process_time() - cpu
print(json.dumps({"ours": ours, "peer": peer, "taus": taus, "table": table.nbytes,
                  "growth": peak - base, "parts": parts}))
"""

FLOOR_CHILD = """
import os, sys, time
os.environ.setdefault("MIMALLOC_ARENA_EAGER_COMMIT", "0")  # as imupipe's command line starts
t0 = time.perf_counter()
import numpy, pyarrow
t1 = time.perf_counter()
import imupipe.pipeline.run, imupipe.pipeline.report.page, imupipe.stages.allan.stage
t2 = time.perf_counter()
import rerun, imupipe.pipeline.report.recording
t3 = time.perf_counter()
import scipy.special
t4 = time.perf_counter()
import pyarrow.csv
pyarrow.csv.read_csv(sys.argv[1])
t5 = time.perf_counter()
print(t4 - t0, t5 - t4, t1 - t0, t2 - t1, t3 - t2, t4 - t3)
"""
"""What no run can avoid: the imports of a run (pyarrow, numpy, Rerun, scipy) and
``pyarrow.csv.read_csv`` of the whole file, in a fresh process; then the imports one by one
(numpy + pyarrow, imupipe's run, report and stage, Rerun, scipy)."""
FLOOR_PARTS = ("numpy+pyarrow", "imupipe", "rerun", "scipy")

RUN_CHILD = """
import sys, time
t0 = time.perf_counter()
sys.path.insert(0, sys.argv[2])
from proc_memory import status_bytes
import imupipe.pipeline.cli as C
import os
os.environ.setdefault("MIMALLOC_ARENA_EAGER_COMMIT", C.EAGER_COMMIT)  # as main() does, first
import imupipe.pipeline.run as R
from imupipe.stages.allan.stage import AllanStage
parts = {"imports": time.perf_counter() - t0}

def timed(owner, name, label):
    f = getattr(owner, name)

    def g(*a, **k):
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            parts[label] = parts.get(label, 0.0) + time.perf_counter() - t

    setattr(owner, name, g)

timed(R, "read_input", "read")
timed(AllanStage, "fit", "stage")
timed(R, "publish", "report")
C.main(["run", sys.argv[1], "--quiet"])  # as on the command line (one run per process)
total = time.perf_counter() - t0
parts["rest"] = total - sum(parts.values())
print(total)
print(" ".join(f"{k}={v:.3f}" for k, v in parts.items()))
print(status_bytes("VmHWM"))
"""
"""A run as a user runs it, timed in parts: imports (of the run and the stage), the read, the
stage (with the imports it makes on first use: scipy), ``report.html``
and the rest (the Rerun import and recording, the exports, the outputs)."""


USER_SCRIPT = """
import sys
import allantools
import pandas as pd

df = pd.read_csv(sys.argv[1])
rate = 1e9 / df["t_ns"].diff().median()
for c in ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"):
    allantools.oadev(df[c].to_numpy(), rate=rate, data_type="freq", taus="octave")
"""
"""The user's script: the CSV into a DataFrame, then allantools on each axis (octave taus)."""

SCRIPT_FLOOR = """
import os, sys
os.environ.setdefault("MIMALLOC_ARENA_EAGER_COMMIT", "0")  # as imupipe's command line starts
import numpy, pyarrow, pyarrow.csv, rerun, rerun.blueprint
import imupipe.stages.special  # scipy.special's three functions, without its __init__
pyarrow.csv.read_csv(sys.argv[1])
"""
"""What no Allan run with a recording avoids: its imports (numpy, pyarrow, Rerun for the
recording, the three scipy.special functions of the bounds and the fit, as the run loads them:
:mod:`imupipe.stages.special`; ``import scipy.special`` whole cost 0.3 s more before issue 39's
last pass) and pyarrow's parse of the file, with the allocator setting imupipe's command line
starts with (:data:`imupipe.pipeline.cli.EAGER_COMMIT`)."""

WRITE_CHILD = """
import sys
from pathlib import Path
from imupipe.pipeline.simulate import simulate, write_log
table, _ = simulate("static", {"rate_hz": 400.0, "duration_s": float(sys.argv[2]),
                               "temperature": None}, 1)
write_log(Path(sys.argv[1]), table)
"""


def timed_child(argv: list[str], env: dict[str, str] | None = None) -> tuple[float, float, int]:
    """(wall s, CPU s: user + system of every thread, peak RSS bytes) of one child process."""
    t = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if proc.returncode != 0:
        raise SystemExit(f"{argv[:3]} failed ({proc.returncode}): {err[-2000:]}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024


def bytecode_env(pycache: Path) -> dict[str, str]:
    """This environment with Python's bytecode cache on, in ``pycache`` (``PYTHONPYCACHEPREFIX``;
    ``PYTHONDONTWRITEBYTECODE`` dropped), as an installed package runs: a source checkout run
    with ``PYTHONDONTWRITEBYTECODE=1`` compiles every imupipe module it imports on each start
    (64 modules: 0.20-0.26 s of CPU of an Allan run, measured), which pandas and allantools,
    installed with their bytecode, never pay. The cache is warmed by a first, untimed, run."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = str(pycache)
    return env


def bench_script(
    minutes: float, pairs: int, peer_path: str | None, baseline: str | None = None
) -> None:
    import statistics

    d = Path(tempfile.mkdtemp(prefix="bench_allan_script_"))
    csv = d / "static.csv"
    subprocess.run([sys.executable, "-c", WRITE_CHILD, str(csv), str(minutes * 60.0)], check=True)
    (d / "cfg.toml").write_text(
        '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\n\n'
        '[output]\ndir = "out"\n'
    )
    ours_cmd = [sys.executable, "-m", "imupipe.pipeline.cli", "run", str(d / "cfg.toml"), "--quiet"]
    peer_cmd = [sys.executable, "-c", USER_SCRIPT, str(csv)]
    env = bytecode_env(d / "pycache")
    peer_env = dict(env)
    if peer_path:
        peer_env["PYTHONPATH"] = os.pathsep.join(p for p in (peer_path, env.get("PYTHONPATH")) if p)
    floor_cmd = [sys.executable, "-c", SCRIPT_FLOOR, str(csv)]
    sides = [("ours", ours_cmd, env), ("peer", peer_cmd, peer_env), ("floor", floor_cmd, env)]
    if baseline:  # the code before a change (a checkout with its .shim), in the same pairs
        base_env = {**env, "PYTHONPATH": str(Path(baseline).resolve() / ".shim")}
        base_cmd = [*ours_cmd[:-2], str(d / "cfg_base.toml"), "--quiet"]
        (d / "cfg_base.toml").write_text(
            (d / "cfg.toml").read_text().replace('"out"', '"out_base"')
        )
        sides.insert(1, ("base", base_cmd, base_env))
    for _, cmd, side_env in sides:  # not timed: the bytecode caches, the file in the page cache
        timed_child(cmd, side_env)
    rows = []
    for i in range(pairs):  # alternate which side goes first
        got = {
            name: timed_child(cmd, side_env)
            for name, cmd, side_env in (sides if i % 2 == 0 else sides[::-1])
        }
        rows.append(got)
    print(
        f"3. whole imupipe run (allan, defaults) vs the user's script (pandas.read_csv + "
        f"allantools oadev octave per axis), {minutes:g} min at 400 Hz "
        f"({csv.stat().st_size / 1e6:.0f} MB CSV), {pairs} pairs; {load()}"
    )
    for label, k in (("wall", 0), ("CPU", 1)):
        ratios = [r["ours"][k] / r["peer"][k] for r in rows]
        each = ", ".join(f"{r['ours'][k]:.2f}/{r['peer'][k]:.2f}" for r in rows)
        print(
            f"   {label}: ratio imupipe/script min {min(ratios):.2f}, median "
            f"{statistics.median(ratios):.2f} (goal <= 0.5); pairs imupipe/script s: {each}"
        )
        floor = [r["floor"][k] / r["peer"][k] for r in rows]
        print(
            f"     floor (imports + pyarrow.csv.read_csv)/script min {min(floor):.2f}, median "
            f"{statistics.median(floor):.2f}; imupipe/floor median "
            f"{statistics.median(r['ours'][k] / r['floor'][k] for r in rows):.2f}"
        )
        if baseline:
            base = [r["base"][k] / r["peer"][k] for r in rows]
            each = ", ".join(f"{r['base'][k]:.2f}" for r in rows)
            print(
                f"     baseline/script min {min(base):.2f}, median {statistics.median(base):.2f} "
                f"(baseline s: {each}); imupipe/baseline median "
                f"{statistics.median(r['ours'][k] / r['base'][k] for r in rows):.3f}"
            )
    peak = max(r["ours"][2] for r in rows), max(r["peer"][2] for r in rows)
    print(f"   peak RSS: imupipe {peak[0] / 1e6:.0f} MB, script {peak[1] / 1e6:.0f} MB")


def load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} cores"


def bench_stage(sizes: list[float], repeats: int, parts: bool = False) -> None:
    print(f"1. allan stage alone vs allantools oadev(taus='octave'), 6 axes; {load()}")
    for n in sizes:
        proc = subprocess.run(
            [sys.executable, "-c", STAGE_CHILD, str(n), str(repeats), HERE]
            + (["parts"] if parts else []),
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            raise SystemExit(proc.stderr)
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        ours, peer = min(r["ours"]), min(r["peer"])
        runs = ", ".join(f"{a:.2f}/{b:.2f}" for a, b in zip(r["ours"], r["peer"], strict=True))
        print(
            f"   {int(n):>9,d} samples: imupipe {ours:.2f} s ({r['taus']} taus), allantools "
            f"{peer:.2f} s (octave), ratio {ours / peer:.2f} (goal <= 1.0); repeats "
            f"imupipe/allantools s: {runs}; stage peak RSS growth {r['growth'] / 1e6:.0f} MB "
            f"= {r['growth'] / r['table']:.2f} x the {r['table'] / 1e6:.0f} MB table"
        )
        if r["parts"]:  # the fastest of the repeats (after the first: page faults, imports)
            best = min(range(1, repeats) or [0], key=lambda i: r["parts"]["whole stage"][i])
            each = ", ".join(f"{k} {v[best] * 1e3:.1f}" for k, v in r["parts"].items())
            print(f"     CPU ms in the fastest repeat: {each}")


def bench_run(repeats: int) -> None:
    import allantools
    import numpy as np

    from imupipe.pipeline.simulate import simulate, write_log
    from imupipe.readers.table import sensor

    d = Path(tempfile.mkdtemp(prefix="bench_allan_"))
    table, _ = simulate("static", {"rate_hz": RATE, "duration_s": 7200.0, "temperature": None}, 1)
    write_log(d / "static.csv", table)
    columns = [
        np.ascontiguousarray(sensor(table, s).values[:, i])
        for s in ("gyro", "accel")
        for i in range(3)
    ]
    table_bytes = table.nbytes
    del table
    cfg = d / "cfg.toml"
    cfg.write_text(
        '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\n\n'
        '[output]\ndir = "out"\n'
    )
    walls, peers, floors, parts, peak = [], [], [], [], 0
    for _ in range(repeats):
        proc = subprocess.run(
            [sys.executable, "-c", FLOOR_CHILD, str(d / "static.csv")],
            capture_output=True,
            text=True,
            check=True,
        )
        floors.append(tuple(float(v) for v in proc.stdout.split()))
        t = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-c", RUN_CHILD, str(cfg), HERE], capture_output=True, text=True
        )
        walls.append(time.perf_counter() - t)
        if proc.returncode != 0:
            raise SystemExit(proc.stderr)
        lines = proc.stdout.strip().splitlines()
        peak = max(peak, int(lines[-1]))
        parts.append(lines[-2])
        t = time.perf_counter()
        for c in columns:
            allantools.oadev(c, rate=RATE, data_type="freq", taus="octave")
        peers.append(time.perf_counter() - t)
    outputs = sorted(p.name for p in (d / "out").iterdir())
    wall, peer = min(walls), min(peers)
    print(f"2. imupipe run, 2 h at 400 Hz static CSV, defaults; {load()}")
    print(
        f"   imupipe run {wall:.2f} s (process start to exit; repeats "
        f"{', '.join(f'{w:.2f}' for w in walls)}), allantools oadev octave on the same arrays "
        f"in memory {peer:.2f} s: ratio {wall / peer:.2f} (goal <= 2.0)"
    )
    print(f"   best run in parts (s, process start to exit): {parts[walls.index(wall)]}")
    imports, read = min(f[0] for f in floors), min(f[1] for f in floors)
    each = ", ".join(
        f"{name} {min(f[2 + i] for f in floors):.2f}" for i, name in enumerate(FLOOR_PARTS)
    )
    print(
        f"   floor: the run's imports {imports:.2f} s ({each}) + pyarrow.csv.read_csv "
        f"{read:.2f} s = {(imports + read) / peer:.2f} x allantools before any fitting"
    )
    print(
        f"   peak RSS {peak / 1e6:.0f} MB = {peak / table_bytes:.2f} x the common table "
        f"({table_bytes / 1e6:.0f} MB); outputs: {', '.join(outputs)} (files in {d})"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=float, nargs="+", default=[0.5e6, 2.88e6, 8e6])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--skip-run", action="store_true", help="only the stage benchmark")
    p.add_argument("--skip-stage", action="store_true", help="only the run benchmark")
    p.add_argument(
        "--parts", action="store_true", help="also the CPU time of the stage's parts, per call"
    )
    p.add_argument("--script", action="store_true", help="only the run vs the user's script")
    p.add_argument("--minutes", type=float, default=120.0, help="--script: the log's length")
    p.add_argument("--pairs", type=int, default=2, help="--script: pairs of runs")
    p.add_argument("--peer-path", help="--script: a folder on the script's PYTHONPATH (pandas)")
    p.add_argument(
        "--baseline", help="--script: a checkout of the code before a change (with its .shim)"
    )
    args = p.parse_args()
    if args.script:
        bench_script(args.minutes, args.pairs, args.peer_path, args.baseline)
        return
    if not args.skip_stage:
        bench_stage(args.sizes, args.repeats, args.parts)
    if not args.skip_run:
        bench_run(args.repeats)


if __name__ == "__main__":
    main()
