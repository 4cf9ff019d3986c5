"""Issue 5: the 9-parameter accelerometer model solved by Levenberg-Marquardt (scipy, the peer)
and by Frank-Wolfe (seed 003), on the same problems in the same run.

Problems: imu_tk's Xsens session (raw counts; interval means, and 100 samples per interval as
imu_tk fits them), and a simulated 18-pose session (interval means). Both solvers start from the
same data-derived guess. For each: iterations, function evaluations, median wall time of
``--repeat`` runs, the final | |a| - g | RMS (mg) and the time ratio Frank-Wolfe / LM. Frank-Wolfe
is also run with a wider box (+-20 %) to show how its speed depends on the box.

Usage: ``python benchmarks/bench_accel_solvers.py [--repeat 5]`` (ratios, not absolute times: the
machine is shared and noisy).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from imupipe.pipeline.simulate import simulate
from imupipe.readers.csv_reader import read_csv
from imupipe.readers.spec import CsvMapping, InputSpec
from imupipe.readers.table import sensor
from imupipe.stages import accel_models as am
from imupipe.stages.static_detector import make_detector

XSENS = Path(__file__).resolve().parents[1] / "tests" / "data" / "imu_tk_xsens"


def xsens_problems() -> dict[str, am.NormProblem]:
    spec = InputSpec(
        path=XSENS / "xsens_acc.mat",
        csv=CsvMapping(time=0, time_unit="s", accel=[1, 2, 3], accel_unit="raw", gyro=None),
    )
    table, _ = read_csv(spec)
    acc = sensor(table, "accel")
    g = 9.81744
    iv = make_detector(acc.t_ns, acc.values, init_static_s=50.0).detect(3.0)
    means = iv.means(acc.values)
    take = np.minimum(iv.lengths, 100)
    first = iv.start + (iv.lengths - take) // 2
    idx = np.repeat(first, take) + (np.arange(take.sum()) - np.repeat(np.cumsum(take) - take, take))
    start = am.initial_guess(means, g)
    return {
        f"xsens means ({len(means)})": am.NormProblem(means, g, start),
        f"xsens samples ({len(idx)})": am.NormProblem(acc.values[idx], g, start),
    }


def simulated_problem() -> dict[str, am.NormProblem]:
    table, _ = simulate("poses", seed=1)
    acc = sensor(table, "accel")
    means = make_detector(acc.t_ns, acc.values).detect(3.0).means(acc.values)
    g = 9.80665
    return {f"simulated means ({len(means)})": am.NormProblem(means, g, am.initial_guess(means, g))}


def timed(solve, repeat: int) -> tuple[am.Solution, float]:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        sol = solve()
        times.append(time.perf_counter() - t0)
    return sol, statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    problems = {**xsens_problems(), **simulated_problem()}
    header = f"{'problem':<26}{'solver':<18}{'iter':>7}{'f-evals':>9}{'time ms':>10}{'RMS mg':>10}{'x FW/LM':>9}"
    print(header)
    print("-" * len(header))
    for name, problem in problems.items():
        g = problem.g
        lm, t_lm = timed(lambda p=problem: am.solve_lm(p), args.repeat)
        rows = [("lm (scipy)", lm, t_lm)]
        for label, box in (("frank_wolfe 5%", 0.05), ("frank_wolfe 20%", 0.20)):
            sol, t = timed(
                lambda p=problem, b=box: am.solve_frank_wolfe(p, box=np.full(9, b)), args.repeat
            )
            rows.append((label, sol, t))
        for label, sol, t in rows:
            rms = float(np.sqrt(np.mean((problem.residual(sol.x) * g / am.MG) ** 2)))
            ratio = "" if label.startswith("lm") else f"{t / t_lm:9.1f}"
            print(
                f"{name:<26}{label:<18}{sol.info['iterations']:>7}"
                f"{sol.info['function_evaluations']:>9}{t * 1e3:>10.2f}{rms:>10.5f}{ratio}"
            )
            if not label.startswith("lm"):
                print(f"{'':<26}  stop: {sol.info['stop']}")


if __name__ == "__main__":
    main()
