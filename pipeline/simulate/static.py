"""Scenario ``static``: an IMU at rest, z axis up, with constant biases and the noise model of
:mod:`imupipe.pipeline.simulate.noise` per axis: white N, bias instability B, random walk K,
quantisation Q and rate ramp R (continuous-time SI, the Allan ``allan`` stage's units).

Truth: ``gyro`` and ``accel`` each with ``bias``, ``N``, ``B``, ``K``, ``Q``, ``R`` (3 values
each, SI), and ``gravity`` (the true specific force at rest, m/s^2).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.noise import flicker, quantization, random_walk, rate_ramp, white
from imupipe.readers.table import make_table

DEFAULTS: dict[str, Any] = {
    "rate_hz": 200.0,
    "duration_s": 60.0,
    "t0_s": 1_700_000_000.0,
    "gravity": 9.80665,
    "gyro_bias": [0.01, -0.02, 0.005],
    "gyro_N": [1.7e-4, 1.7e-4, 1.7e-4],
    "gyro_B": [0.0, 0.0, 0.0],
    "gyro_K": [2.0e-6, 2.0e-6, 2.0e-6],
    "gyro_Q": [0.0, 0.0, 0.0],
    "gyro_R": [0.0, 0.0, 0.0],
    "accel_bias": [0.05, -0.03, 0.08],
    "accel_N": [2.0e-3, 2.0e-3, 2.0e-3],
    "accel_B": [0.0, 0.0, 0.0],
    "accel_K": [3.0e-5, 3.0e-5, 3.0e-5],
    "accel_Q": [0.0, 0.0, 0.0],
    "accel_R": [0.0, 0.0, 0.0],
    "temperature": 25.0,
}


TRUTH_KEYS = ("bias", "N", "B", "K", "Q", "R")


def _sensor(
    rng: np.random.Generator, n: int, fs: float, p: dict[str, Any], name: str
) -> np.ndarray:
    cols = []
    for i in range(3):
        cols.append(
            p[f"{name}_bias"][i]
            + white(rng, n, p[f"{name}_N"][i], fs)
            + flicker(rng, n, p[f"{name}_B"][i], fs)
            + random_walk(rng, n, p[f"{name}_K"][i], fs)
            + quantization(rng, n, p[f"{name}_Q"][i], fs)
            + rate_ramp(n, p[f"{name}_R"][i], fs)
        )
    return np.column_stack(cols)


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    fs = float(p["rate_hz"])
    n = int(round(float(p["duration_s"]) * fs))
    t_ns = sample_times(p["t0_s"], n, fs)
    gravity = np.array([0.0, 0.0, float(p["gravity"])])
    gyro = _sensor(rng, n, fs, p, "gyro")
    accel = _sensor(rng, n, fs, p, "accel") + gravity
    temperature = None if p["temperature"] is None else np.full(n, float(p["temperature"]))
    table = make_table(
        t_ns,
        gyro=gyro,
        accel=accel,
        temperature=temperature,
        metadata={"source": "imupipe simulate static", "format": "simulated"},
    )
    truth = {
        "gyro": {k: list(p[f"gyro_{k}"]) for k in TRUTH_KEYS},
        "accel": {k: list(p[f"accel_{k}"]) for k in TRUTH_KEYS},
        "gravity": gravity.tolist(),
    }
    return table, truth
