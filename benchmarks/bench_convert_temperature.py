"""Issue 17 item 1: ``imupipe convert`` of a long log with a temperature step, streamed.

One MCAP of N (default 10,000,000) messages: ``sensor_msgs/msg/Imu`` at 200 Hz and a
``sensor_msgs/msg/Temperature`` every 200th message (1 Hz), a slow temperature cycle; written batch
by batch (never held whole). Two calibrations are applied to it with ``imupipe convert`` (one
worker, the command's own process pool):

- the peer: a linear chain (a gyro bias step), which streams sample by sample;
- the temperature chain: the gyro's ``temperature`` step with the lag model (the temperature
  stream's rate and the sensing element's lagged temperature at every IMU stamp, so rows are
  held back until their context has arrived) and the same bias step.

Prints the worker's peak memory (``peak_rss_mb`` of the manifest: the worker process's maximum
resident set; with ``--jobs 1`` the worker is the command's own process, so this is its
``VmHWM``) for both, their ratio, and the time ratio, measured in the same run. Goals: the
temperature chain's worker under 0.5 GB for 10 M messages, near the linear chain's (issue 17);
both chains' workers under 250 MB, flat in the log's length (issue 39: 500,000 and 2,000,000
messages in the benchmarks page).

Usage: ``python benchmarks/bench_convert_temperature.py [--messages 10000000] [--keep]``
(the machine is shared and noisy: the ratios, not absolute times, count).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

IMU_HZ, TEMP_EVERY, ROWS = 200, 200, 500_000
BIAS = {
    "type": "gyro_bias",
    "sensor": "gyro",
    "kind": "linear",
    "matrix": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    "offset": [0.01, -0.02, 0.005],
}
TERMS = ["1", "Ts", "Ts^2", "Ts^3", "dTs", "dT"]
TEMPERATURE = {
    "type": "temperature",
    "sensor": "gyro",
    "kind": "temperature",
    "model": "lag",
    "tref": 25.0,
    "window": None,
    "window_s": 10.0,
    "lag_s": 200.0,
    "ranges": {"Ts": [5.0, 45.0], "dTs": [-0.01, 0.01], "dT": [-0.01, 0.01], "T": [5.0, 45.0]},
    "knots": None,
    "scale": None,
    "axes": [{"terms": TERMS, "coefficients": [1e-4, 2e-5, 1e-7, 1e-9, 0.1, 0.05]}] * 3,
    "reference": [0.0, 0.0, 0.0],
}


def write_log(path: Path, messages: int) -> None:
    """The log, written ``ROWS`` rows at a time."""
    from imupipe.pipeline.writers.mcap import McapTableWriter
    from imupipe.readers.table import make_table

    rng = np.random.default_rng(0)
    with McapTableWriter(path) as writer:
        for start in range(0, messages, ROWS):
            i = np.arange(start, min(start + ROWS, messages))
            is_temp = i % TEMP_EVERY == TEMP_EVERY - 1
            t = i / IMU_HZ
            writer.write_table(
                make_table(
                    1_700_000_000_000_000_000 + np.round(t * 1e9).astype(np.int64),
                    gyro=rng.normal(0, 1e-3, (len(i), 3)),
                    accel=rng.normal(0, 1e-2, (len(i), 3)) + [0, 0, 9.8],
                    temperature=25 + 20 * np.sin(t / 3000.0),
                    valid={"imu": ~is_temp, "temperature": is_temp},
                )
            )


def convert(log: Path, chain: list[dict], out: Path) -> dict:
    """``imupipe convert`` of ``log`` with ``chain``; the manifest line (seconds, peak RSS)."""
    cal = out.with_suffix(".json")
    cal.write_text(json.dumps({"imupipe_version": "bench", "chain": chain, "results": {}}))
    cmd = [sys.executable, "-m", "imupipe.pipeline.cli", "convert", "--calibration", str(cal)]
    cmd += ["--out", str(out), "--jobs", "1", "--quiet", str(log)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"convert failed: {done.stderr.strip()}")
    (line,) = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    return {**line, "wall": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=10_000_000)
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_convert_temperature_"))
    try:
        log = tmp / "long.mcap"
        t0 = time.perf_counter()
        write_log(log, args.messages)
        print(
            f"log: {args.messages:,} messages, {log.stat().st_size / 2**30:.2f} GiB, "
            f"written in {time.perf_counter() - t0:.1f} s"
        )
        linear = convert(log, [BIAS], tmp / "linear")
        thermal = convert(log, [TEMPERATURE, BIAS], tmp / "thermal")
        for name, line in (("linear chain (peer)", linear), ("temperature chain", thermal)):
            print(
                f"{name:22s} worker {line['seconds']:.1f} s, command {line['wall']:.1f} s, "
                f"peak RSS {line['peak_rss_mb']:.0f} MB, mode {line['mode']}"
            )
        print(
            f"temperature / linear: memory {thermal['peak_rss_mb'] / linear['peak_rss_mb']:.2f}x, "
            f"time {thermal['seconds'] / linear['seconds']:.2f}x; "
            f"temperature chain peak {thermal['peak_rss_mb'] / 1024:.2f} GB (goal < 0.5 GB)"
        )
        worst = max(linear["peak_rss_mb"], thermal["peak_rss_mb"])
        print(f"larger worker peak {worst:.0f} MB (issue 39 goal: < 250 MB for both chains)")
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
