"""Scenario ``camera``: a depth camera's IMU at rest (an Intel RealSense D435i), whose gyro and
accelerometer are sampled on clocks of their own and published on topics of their own.

realsense-ros publishes ``/camera/gyro/sample`` (``sensor_msgs/Imu``, 200 or 400 Hz, its
linear_acceleration zeros) and ``/camera/accel/sample`` (63 or 250 Hz, its angular_velocity
zeros) unless told to unite them. The table holds each sensor at its own stamps: a gyro row has
a null accelerometer and the other way round (:mod:`imupipe.readers.table`); written as MCAP or
a bag, each goes to its topic (:func:`imupipe.pipeline.writers.mcap.stream_rows`). The noise
model per axis is the ``static`` scenario's (white N, bias instability B, random walk K,
quantisation Q, rate ramp R, continuous-time SI); the defaults are of the order of the Bosch
BMI055 in the D435i (datasheet: gyro 0.014 deg/s/sqrt(Hz), accelerometer 150 ug/sqrt(Hz)).

Truth: as the ``static`` scenario (``gyro``, ``accel``: bias, N, B, K, Q, R; ``gravity``), and
``rates`` (gyro and accel, Hz).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.static import TRUTH_KEYS, _sensor
from imupipe.readers.table import make_table

DEFAULTS: dict[str, Any] = {
    "gyro_rate_hz": 400.0,
    "accel_rate_hz": 250.0,
    "duration_s": 1200.0,
    "t0_s": 1_700_000_000.0,
    "accel_offset_s": 0.0013,
    "gravity": 9.80665,
    "gyro_bias": [0.002, -0.003, 0.001],
    "gyro_N": [2.4e-4, 2.4e-4, 2.4e-4],
    "gyro_B": [0.0, 0.0, 0.0],
    "gyro_K": [1.0e-6, 1.0e-6, 1.0e-6],
    "gyro_Q": [0.0, 0.0, 0.0],
    "gyro_R": [0.0, 0.0, 0.0],
    "accel_bias": [0.08, -0.05, 0.12],
    "accel_N": [1.5e-3, 1.5e-3, 1.5e-3],
    "accel_B": [0.0, 0.0, 0.0],
    "accel_K": [2.0e-5, 2.0e-5, 2.0e-5],
    "accel_Q": [0.0, 0.0, 0.0],
    "accel_R": [0.0, 0.0, 0.0],
    "gyro_topic": "/camera/gyro/sample",
    "accel_topic": "/camera/accel/sample",
}


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    fg, fa = float(p["gyro_rate_hz"]), float(p["accel_rate_hz"])
    duration = float(p["duration_s"])
    ng, na = int(round(duration * fg)), int(round(duration * fa))
    tg = sample_times(p["t0_s"], ng, fg)
    ta = sample_times(float(p["t0_s"]) + float(p["accel_offset_s"]), na, fa)
    gravity = np.array([0.0, 0.0, float(p["gravity"])])
    gyro = _sensor(rng, ng, fg, p, "gyro")
    accel = _sensor(rng, na, fa, p, "accel") + gravity
    t = np.concatenate([tg, ta])
    order = np.argsort(t, kind="stable")  # the gyro first at equal stamps
    is_gyro = (np.arange(ng + na) < ng)[order]
    rows = np.empty(ng + na, np.int64)
    rows[order] = np.arange(ng + na)
    g = np.zeros((ng + na, 3))
    a = np.zeros((ng + na, 3))
    g[rows[:ng]] = gyro
    a[rows[ng:]] = accel
    table = make_table(
        t[order],
        gyro=g,
        accel=a,
        valid={"gyro": is_gyro, "accel": ~is_gyro},
        metadata={
            "source": "imupipe simulate camera",
            "format": "simulated",
            "topics": {"gyro": p["gyro_topic"], "accel": p["accel_topic"]},
            "frame_id": {
                "gyro": "camera_gyro_optical_frame",
                "accel": "camera_accel_optical_frame",
            },
        },
    )
    truth = {
        "gyro": {k: list(p[f"gyro_{k}"]) for k in TRUTH_KEYS},
        "accel": {k: list(p[f"accel_{k}"]) for k in TRUTH_KEYS},
        "gravity": gravity.tolist(),
        "rates": {"gyro": fg, "accel": fa},
    }
    return table, truth
