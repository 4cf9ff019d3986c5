"""Issue 17 item 1 for the thermal corrections: applied batch by batch, time and memory.

A bag-like log (IMU at 200 Hz in rows of its own, the temperature at 1 Hz beside it, a slow
temperature cycle) is generated batch by batch (``--batch-rows``), never held whole, and streamed
through ``apply_chain_stream``:

1. Time of the temperature step (the lag model: rates and the sensing element's lag, rows held
   for their context) against the peer, a linear step (``LinearStep``: each batch on its own), on
   the same ``--time-messages`` in one process, alternating, best of 3. Prints the ratio.
2. Peak memory (``VmHWM``, in a fresh child process each) streaming N messages and N/4: the
   streamed peak must not grow with the log (ratio about 1).

Usage: ``python benchmarks/bench_temperature_stream.py [--messages 10000000] [--time-messages
2000000] [--batch-rows 100000]``
(the machine is shared and noisy: ratios, not absolute times, count).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from collections.abc import Iterator

import numpy as np
import pyarrow as pa

IMU_HZ, TEMP_EVERY = 200, 200


def batches(messages: int, rows: int) -> Iterator[pa.Table]:
    """``messages`` rows (IMU rows and, every ``TEMP_EVERY``-th row, a temperature row)."""
    from imupipe.readers.table import make_table

    rng = np.random.default_rng(0)
    for start in range(0, messages, rows):
        i = np.arange(start, min(start + rows, messages))
        is_temp = i % TEMP_EVERY == TEMP_EVERY - 1
        t = i / IMU_HZ
        yield make_table(
            1_700_000_000_000_000_000 + np.round(t * 1e9).astype(np.int64),
            gyro=rng.normal(0, 1e-3, (len(i), 3)),
            accel=rng.normal(0, 1e-2, (len(i), 3)) + [0, 0, 9.8],
            temperature=25 + 20 * np.sin(t / 3000.0),
            valid={"imu": ~is_temp, "temperature": is_temp},
        )


def steps(kind: str) -> list:
    from imupipe.stages.steps import LinearStep
    from imupipe.stages.thermal.step import TemperatureStep

    if kind == "linear":
        return [LinearStep("gyro_bias", "gyro", np.eye(3), np.array([0.01, -0.02, 0.005]))]
    terms = ["1", "Ts", "Ts^2", "Ts^3", "dTs", "dT"]
    return [
        TemperatureStep(
            type="temperature", sensor="gyro", model="lag", tref=25.0, window=None,
            window_s=10.0, lag_s=200.0,
            axes=[{"terms": terms, "coefficients": np.full(len(terms), 1e-4)}] * 3,
            ranges={"Ts": [5.0, 45.0], "dTs": [-0.01, 0.01], "dT": [-0.01, 0.01], "T": [5.0, 45.0]},
            quiet=True,
        )
    ]  # fmt: skip


def run(kind: str, messages: int, rows: int) -> tuple[float, int]:
    """Seconds to stream the log through ``kind``'s chain (generation excluded), rows out."""
    from imupipe.stages.steps import apply_chain_stream

    spent = 0.0
    out = 0
    source = batches(messages, rows)

    def timed() -> Iterator[pa.Table]:
        nonlocal spent
        for b in source:
            spent -= time.perf_counter()  # generation is not the step's time
            yield b
            spent += time.perf_counter()

    t0 = time.perf_counter()
    for part in apply_chain_stream(timed(), steps(kind)):
        out += len(part)
    return time.perf_counter() - t0 + spent, out


def child(kind: str, messages: int, rows: int, queue: mp.Queue) -> None:
    """In a fresh process: stream once (``kind``), or time both kinds (``kind = "time"``)."""
    sys.path.insert(0, __import__("os").path.dirname(__file__))
    from proc_memory import status_bytes

    if kind == "time":
        best = {"linear": float("inf"), "temperature": float("inf")}
        for _ in range(3):
            for k in best:
                best[k] = min(best[k], run(k, messages, rows)[0])
        queue.put((best["linear"], best["temperature"], 0))
        return
    seconds, out = run(kind, messages, rows)
    queue.put((seconds, out, status_bytes("VmHWM")))


def measure(kind: str, messages: int, rows: int) -> tuple[float, int, int]:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=child, args=(kind, messages, rows, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=10_000_000)
    parser.add_argument("--time-messages", type=int, default=2_000_000)
    parser.add_argument("--batch-rows", type=int, default=100_000)
    args = parser.parse_args()
    n, rows = args.messages, args.batch_rows
    lin_s, tmp_s, _ = measure("time", args.time_messages, rows)
    m = args.time_messages
    print(f"time, {m:,} messages in batches of {rows:,} rows, best of 3:")
    print(f"  linear step (peer):     {lin_s:7.2f} s  {m / lin_s / 1e6:6.2f} M msg/s")
    print(f"  temperature step (lag): {tmp_s:7.2f} s  {m / tmp_s / 1e6:6.2f} M msg/s")
    print(f"  ratio temperature / linear: {tmp_s / lin_s:.2f}")
    _, lin_out, lin_mem = measure("linear", n, rows)
    _, tmp_out, tmp_mem = measure("temperature", n, rows)
    _, q_out, q_mem = measure("temperature", n // 4, rows)
    assert lin_out == tmp_out == n and q_out == n // 4
    print(f"peak memory (VmHWM), {n:,} messages streamed:")
    print(f"  linear step {lin_mem / 2**20:.0f} MiB, temperature step {tmp_mem / 2**20:.0f} MiB")
    print(
        f"  temperature step, N / (N/4) messages: {tmp_mem / q_mem:.2f} ({q_mem / 2**20:.0f} MiB)"
    )


if __name__ == "__main__":
    main()
