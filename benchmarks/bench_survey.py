"""Issue 30 scale figures for ``imupipe survey`` on a simulated fleet (``imupipe simulate fleet``).

1. Throughput: ``--logs`` logs (default 1,000: ``--logs / 20`` vehicles of 20 logs, 2 IMUs each,
   ``--log-s`` seconds at 100 Hz) surveyed with ``--jobs`` workers on the local engine: logs per
   second and still periods per second, wall clock, fleet view and report included.
2. Per-log fixed cost: the manifest's per-log worker seconds of the fleet's logs against those of
   20 logs a tenth as long, surveyed alike; the straight line through the two means, extrapolated
   to a log of length zero, is the fixed cost of a log (read setup, topic listing, part written).
3. Peak memory of a worker (``peak_rss_mb`` of the manifest: the worker's max RSS) and of the
   driver (its ``VmHWM``: the fleet view holds the whole dataset).

Usage: ``python benchmarks/bench_survey.py [--logs 1000] [--log-s 150] [--jobs 2]``. Not run in
CI (minutes); the machine is shared, so the figures are indicative.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.pipeline.survey.scan import survey

sys.path.insert(0, str(Path(__file__).resolve().parent))
from proc_memory import status_bytes  # noqa: E402


def make_fleet(root: Path, logs: int, log_s: float, seed: int) -> Path:
    vehicles = max(logs // 20, 1)
    per = max(logs // vehicles, 1)
    fleet, _ = simulate(
        "fleet", {"vehicles": vehicles, "imus": 2, "logs": per, "log_s": log_s}, seed=seed
    )
    write_log(root, fleet)
    return root


def per_log_seconds(out: Path) -> list[float]:
    return [r["seconds"] for r in read_manifest(out) if r.get("status") == "surveyed"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--logs", type=int, default=1000)
    ap.add_argument("--log-s", type=float, default=150.0)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_survey_"))
    try:
        t = time.perf_counter()
        logs = make_fleet(tmp / "fleet", args.logs, args.log_s, 1)
        made = time.perf_counter() - t
        n = sum(1 for _ in logs.rglob("*.mcap"))
        size = sum(p.stat().st_size for p in logs.rglob("*.mcap"))
        print(f"simulated {n} logs ({size / 1e9:.2f} GB) in {made:.0f} s")
        t = time.perf_counter()
        result = survey([logs], tmp / "out", jobs=args.jobs)
        wall = time.perf_counter() - t
        long = per_log_seconds(tmp / "out")
        rss = [r["peak_rss_mb"] for r in read_manifest(tmp / "out") if r.get("peak_rss_mb")]
        small = make_fleet(tmp / "small", 20, args.log_s / 10, 2)
        survey([small], tmp / "out_small", jobs=args.jobs)
        short = per_log_seconds(tmp / "out_small")
        mean_long, mean_short = sum(long) / len(long), sum(short) / len(short)
        slope = (mean_long - mean_short) / (args.log_s - args.log_s / 10)
        fixed = mean_short - slope * args.log_s / 10
        figures = {
            "logs": n,
            "jobs": args.jobs,
            "wall_s": round(wall, 1),
            "logs_per_s": round(n / wall, 2),
            "periods_per_s": round(result["rows"] / wall, 1),
            "worker_s_per_log": round(mean_long, 3),
            "worker_s_per_log_short": round(mean_short, 3),
            "fixed_cost_s_per_log": round(fixed, 3),
            "worker_peak_rss_mb": max(rss),
            "driver_peak_rss_mb": round(status_bytes("VmHWM") / 2**20, 1),
            "failed": len(result["failed"]),
        }
        print(json.dumps(figures, indent=2))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
