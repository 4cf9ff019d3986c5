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

Times are noisy on a shared machine: the load average is printed, and the ratios (both sides
measured in the same run, interleaved) are what count.

Usage: ``python benchmarks/bench_allan.py [--sizes 0.5e6 2.88e6 8e6] [--repeats 3]
[--skip-run] [--skip-stage] [--parts]`` (``--parts``: the CPU time of the stage's parts, per call:
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
import sys, time
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
    args = p.parse_args()
    if not args.skip_stage:
        bench_stage(args.sizes, args.repeats, args.parts)
    if not args.skip_run:
        bench_run(args.repeats)


if __name__ == "__main__":
    main()
