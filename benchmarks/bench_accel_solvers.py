"""The accelerometer model solved by Levenberg-Marquardt (scipy, the peer) and by Frank-Wolfe (the
Xiangtan University patent's method), on the same problems in the same run.

Problems: imu_tk's Xsens session (raw counts; pose means, and 100 samples per interval as imu_tk
fits them), a simulated 18-pose session (pose means), and the same session with true scale errors
of +15 % / -10 %, whose optimum lies outside Frank-Wolfe's default +-5 % box (it enlarges the box
and solves again). Both solvers start from the same data-derived guess. For each: iterations,
function evaluations, box enlargements, median wall time of ``--repeat`` runs, the final
| |a| - g | RMS (mg), the largest difference from LM's calibrated |a| over the sphere (mg) and the
time ratio Frank-Wolfe / LM; and the peak memory of the process.

Usage: ``python benchmarks/bench_accel_solvers.py [--repeat 5]`` (ratios, not absolute times: the
machine is shared and noisy).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from imupipe.pipeline.simulate import simulate
from imupipe.readers.csv.reader import read_csv
from imupipe.readers.spec import CsvMapping, InputSpec
from imupipe.readers.table import sensor
from imupipe.stages.multiposition import accel_models as am
from imupipe.stages.multiposition.accel_calibration import AccelCalibrationStage, detect_intervals

sys.path.insert(0, str(Path(__file__).resolve().parent))
from proc_memory import status_bytes  # noqa: E402

XSENS = Path(__file__).resolve().parents[1] / "tests" / "data" / "imu_tk_xsens"


def poses(t_ns: np.ndarray, accel: np.ndarray, g: float):
    """The stage's own detection (default options) and its chosen model's free unknowns."""
    found = detect_intervals(t_ns, accel, AccelCalibrationStage.Options(), g)
    return found.poses, found.fit.problem.free


def xsens_problems() -> dict[str, am.NormProblem]:
    spec = InputSpec(
        path=XSENS / "xsens_acc.mat",
        csv=CsvMapping(time=0, time_unit="s", accel=[1, 2, 3], accel_unit="raw", gyro=None),
    )
    table, _ = read_csv(spec)
    acc = sensor(table, "accel")
    g = 9.81744
    found, free = poses(acc.t_ns, acc.values, g)
    iv = found.intervals
    means = found.means(acc.values)
    take = np.minimum(iv.lengths, 100)
    first = iv.start + (iv.lengths - take) // 2
    idx = np.repeat(first, take) + (np.arange(take.sum()) - np.repeat(np.cumsum(take) - take, take))
    start = am.initial_guess(means, g)
    return {
        f"xsens means ({len(means)})": am.NormProblem(means, g, start, free),
        f"xsens samples ({len(idx)})": am.NormProblem(acc.values[idx], g, start, free),
    }


def simulated_problems() -> dict[str, am.NormProblem]:
    g = 9.80665
    out = {}
    for label, params in (("simulated", {}), ("sim +15/-10 %", {"accel_scale": [1.15, 0.9, 1.0]})):
        table, _ = simulate("poses", params, seed=1)
        acc = sensor(table, "accel")
        found, free = poses(acc.t_ns, acc.values, g)
        means = found.means(acc.values)
        out[f"{label} ({len(means)})"] = am.NormProblem(means, g, am.initial_guess(means, g), free)
    return out


def timed(solve, repeat: int) -> tuple[am.Solution, float]:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        sol = solve()
        times.append(time.perf_counter() - t0)
    return sol, statistics.median(times)


def sphere_difference_mg(a: am.NineParams, b: am.NineParams, g: float) -> float:
    """The largest difference of the calibrated |a| of two calibrations over the sphere, mg."""
    raw = (g * am.SPHERE) @ np.linalg.inv(b.matrix).T + b.bias
    return float(np.abs(np.linalg.norm(a.apply(raw), axis=1) - g).max() / am.MG)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    problems = {**xsens_problems(), **simulated_problems()}
    header = (
        f"{'problem':<26}{'solver':<18}{'iter':>7}{'f-evals':>9}{'boxes':>6}{'time ms':>10}"
        f"{'RMS mg':>10}{'vs LM mg':>10}{'x FW/LM':>9}"
    )
    print(header)
    print("-" * len(header))
    for name, problem in problems.items():
        g = problem.g
        lm, t_lm = timed(lambda p=problem: am.solve_lm(p), args.repeat)
        rows = [("lm (scipy)", lm, t_lm)]
        for label, box in (("frank_wolfe 5%", 0.05), ("frank_wolfe 20%", 0.20)):
            sol, t = timed(
                lambda p=problem, b=box: am.solve_frank_wolfe_enlarging(p, box=np.full(9, b)),
                args.repeat,
            )
            rows.append((label, sol, t))
        for label, sol, t in rows:
            rms = float(np.sqrt(np.mean((problem.residual(sol.x) * g / am.MG) ** 2)))
            is_lm = label.startswith("lm")
            print(
                f"{name:<26}{label:<18}{sol.info['iterations']:>7}"
                f"{sol.info['function_evaluations']:>9}"
                f"{'' if is_lm else sol.info['box_enlargements']:>6}{t * 1e3:>10.2f}{rms:>10.5f}"
                f"{sphere_difference_mg(sol.params, lm.params, g):>10.2g}"
                + ("" if is_lm else f"{t / t_lm:9.1f}")
            )
    print(f"peak memory (VmHWM): {status_bytes('VmHWM') / 1e6:.0f} MB")


if __name__ == "__main__":
    main()
