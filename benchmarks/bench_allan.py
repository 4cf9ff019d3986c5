"""Benchmark of issue 4: the Allan stage against allantools, and a full ``imupipe run``.

1. Estimator + fit: 2 h at 400 Hz, 6 axes (2.88 M samples each). imupipe: phase, overlapping
   Allan deviation on octave taus, noise identification + Greenhall EDF + chi-square bounds and
   the five-term fit of all six axes; peer: ``allantools.oadev(taus="octave")`` on the same six
   arrays, in the same run. Prints each repeat and the median ratio (goal: <= 1.0).
2. ``imupipe run`` on the same duration as a simulated CSV (the allan stage, writing the corrected
   MCAP, and with ``apply_to = []``): wall time (goal: < 15 s on the 2-core machine) and peak RSS
   against the size of the input's common table (goal: < 3x).

Usage: ``python benchmarks/bench_allan.py [--hours 2] [--repeats 3] [--skip-run]``.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import allantools
import numpy as np
from proc_memory import HERE

from imupipe.stages import allan_estimators as est
from imupipe.stages.allan_fit import fit_allan

RATE = 400.0


def ours(columns: list[np.ndarray]) -> float:
    t = time.perf_counter()
    x = est.rate_to_phase(columns, 1.0 / RATE)
    dev = est.deviation_of_phase(
        x, 1.0 / RATE, "oadev", est.tau_grid("octave", est.max_af("oadev", x.shape[1]))
    )
    conf = est.confidence(dev, x)
    for i in range(len(columns)):
        fit_allan(dev.taus, dev.dev[:, i], conf.edf[:, i])
    return time.perf_counter() - t


def peer(columns: list[np.ndarray]) -> float:
    t = time.perf_counter()
    for c in columns:
        allantools.oadev(c, rate=RATE, data_type="freq", taus="octave")
    return time.perf_counter() - t


def bench_estimators(hours: float, repeats: int) -> None:
    n = int(hours * 3600 * RATE)
    rng = np.random.default_rng(0)
    columns = [
        rng.standard_normal(n) * 0.01 + np.cumsum(rng.standard_normal(n)) * 1e-6 for _ in range(6)
    ]
    check = est.deviation(columns[0], RATE, "oadev", "octave")
    ref = allantools.oadev(columns[0], rate=RATE, data_type="freq", taus="octave")[1]
    assert np.allclose(check.dev[: len(ref), 0], ref, rtol=1e-9), "results differ from allantools"
    ratios = []
    for r in range(repeats):
        a, b = ours(columns), peer(columns)
        ratios.append(a / b)
        print(f"  repeat {r}: imupipe {a:.2f} s, allantools {b:.2f} s, ratio {a / b:.2f}")
    print(
        f"oadev octave + fit, 6 x {n} samples: imupipe / allantools = "
        f"{statistics.median(ratios):.2f} (median of {repeats}; goal <= 1.0)"
    )


def bench_run(hours: float) -> None:
    from imupipe.pipeline.simulate import simulate, write_log

    d = Path(tempfile.mkdtemp(prefix="bench_allan_"))
    table, _ = simulate(
        "static", {"rate_hz": RATE, "duration_s": hours * 3600, "temperature": None}, seed=1
    )
    write_log(d / "static.csv", table)
    from imupipe.pipeline.config import load_config
    from imupipe.readers.dispatch import read_input  # the table as the run reads it

    for label, apply_to in (("with corrected MCAP", None), ("apply_to = []", "[]")):
        cfg = d / f"cfg_{'mcap' if apply_to is None else 'none'}.toml"
        out = f"out_{cfg.stem}"
        text = f'[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\n\n[output]\ndir = "{out}"\n'
        if apply_to is not None:
            text += f"apply_to = {apply_to}\n"
        cfg.write_text(text)
        table_bytes = read_input(load_config(cfg).inputs["static"])[0].nbytes
        cmd = [sys.executable, "-c", RUN_AND_REPORT, str(cfg), HERE]
        t = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t
        if proc.returncode != 0:
            print(proc.stderr)
            raise SystemExit(1)
        base, peak = (int(v) for v in proc.stdout.strip().splitlines()[-2:])
        print(
            f"imupipe run ({label}): {wall:.1f} s wall (goal < 15 s), peak RSS {peak / 1e6:.0f} MB "
            f"= {peak / table_bytes:.2f} x the common table ({table_bytes / 1e6:.0f} MB); growth "
            f"over the {base / 1e6:.0f} MB after imports {(peak - base) / 1e6:.0f} MB = "
            f"{(peak - base) / table_bytes:.2f} x the table (goal < 3x)"
        )
    print(f"(files in {d})")


RUN_AND_REPORT = """
import sys
sys.path.insert(0, sys.argv[2])
from proc_memory import status_bytes
from imupipe.pipeline.run import run
import imupipe.pipeline.recording, imupipe.stages.allan, imupipe.readers.csv_reader
print(status_bytes('VmHWM'))  # after imports
run(sys.argv[1], quiet=True)
print(status_bytes('VmHWM'))
"""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hours", type=float, default=2.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--skip-run", action="store_true", help="only the estimator benchmark")
    args = p.parse_args()
    bench_estimators(args.hours, args.repeats)
    if not args.skip_run:
        bench_run(args.hours)


if __name__ == "__main__":
    main()
