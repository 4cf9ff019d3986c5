"""Scenario ``mag``: an IMU with a magnetometer tumbled by hand through all orientations (or,
with ``motion = "planar"``, turned about its z axis only, flat on a table).

Orientation ``R(t)`` (body to world, world z up) is ``Rz(yaw) Ry(pitch) Rx(roll)``, each angle a
sum of three slow sinusoids of random frequency (``tumble_hz`` range) and phase with amplitude
``pi`` (planar: yaw only). The body turns about the sensor, so there is no linear acceleration.

- magnetometer (T): ``raw = A @ (R^T field) + hard_iron + noise``, with the soft iron
  ``A = Q diag(soft_iron_scale) Q^T`` symmetric, its axes rotated by ``Q`` (xyz Euler angles
  ``soft_iron_euler_deg``; zeros give an axis-aligned soft iron), white noise ``mag_noise`` (T per
  axis and sample).
- gyroscope (rad/s): the body rate between samples, plus white noise of density ``gyro_N``.
- accelerometer (m/s^2): ``R^T [0, 0, gravity]`` plus white noise of density ``accel_N``.

Truth: ``mag`` with ``hard_iron`` (T), ``soft_iron`` (A), ``field`` (world vector, T),
``field_norm`` (T), and the ideal correction ``matrix = A^-1``, ``offset = hard_iron`` (corrected
norm = ``field_norm`` for every sample).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.noise import white
from imupipe.readers.table import make_table

DEFAULTS: dict[str, Any] = {
    "rate_hz": 100.0,
    "duration_s": 60.0,
    "t0_s": 1_700_000_000.0,
    "motion": "tumble",
    "tumble_hz": [0.02, 0.12],
    "field": [2.0e-5, 1.5e-6, -4.4e-5],
    "hard_iron": [1.2e-5, -8.0e-6, 2.1e-5],
    "soft_iron_scale": [1.12, 0.9, 1.03],
    "soft_iron_euler_deg": [30.0, -25.0, 50.0],
    "mag_noise": 1.0e-7,
    "gravity": 9.80665,
    "gyro_N": 1.7e-4,
    "accel_N": 2.0e-3,
}


def soft_iron_matrix(scale: list[float], euler_deg: list[float]) -> np.ndarray:
    """``Q diag(scale) Q^T`` with ``Q`` from xyz Euler angles in degrees (symmetric)."""
    q = Rotation.from_euler("xyz", euler_deg, degrees=True).as_matrix()
    return q @ np.diag(np.asarray(scale, dtype=np.float64)) @ q.T


def tumbling(
    rng: np.random.Generator, t_s: np.ndarray, motion: str, band_hz: list[float]
) -> Rotation:
    """The orientation path (see the module docstring)."""
    if motion not in ("tumble", "planar"):
        raise ConfigError(f"simulate mag: motion '{motion}' is not one of tumble, planar")
    n_angles = 3 if motion == "tumble" else 1
    freqs = rng.uniform(band_hz[0], band_hz[1], size=(n_angles, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(n_angles, 3))
    arg = 2 * np.pi * freqs[None, :, :] * t_s[:, None, None] + phases[None, :, :]
    angles = np.pi * np.sin(arg).sum(axis=2)
    if motion == "planar":
        return Rotation.from_euler("z", angles[:, :1])
    return Rotation.from_euler("ZYX", angles)


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    fs = float(p["rate_hz"])
    n = int(round(float(p["duration_s"]) * fs))
    t_s = np.arange(n) / fs
    t_ns = sample_times(p["t0_s"], n, fs)
    attitude = tumbling(rng, t_s, p["motion"], p["tumble_hz"])
    field = np.asarray(p["field"], dtype=np.float64)
    soft = soft_iron_matrix(p["soft_iron_scale"], p["soft_iron_euler_deg"])
    hard = np.asarray(p["hard_iron"], dtype=np.float64)
    body_field = attitude.inv().apply(field)
    mag = body_field @ soft.T + hard + rng.standard_normal((n, 3)) * float(p["mag_noise"])

    step = (attitude[:-1].inv() * attitude[1:]).as_rotvec() * fs
    gyro = np.vstack([step, step[-1:]]) + np.column_stack(
        [white(rng, n, p["gyro_N"], fs) for _ in range(3)]
    )
    gravity = np.array([0.0, 0.0, float(p["gravity"])])
    accel = attitude.inv().apply(gravity) + np.column_stack(
        [white(rng, n, p["accel_N"], fs) for _ in range(3)]
    )
    table = make_table(
        t_ns,
        gyro=gyro,
        accel=accel,
        mag=mag,
        metadata={"source": "imupipe simulate mag", "format": "simulated"},
    )
    truth = {
        "mag": {
            "hard_iron": hard.tolist(),
            "soft_iron": soft.tolist(),
            "field": field.tolist(),
            "field_norm": float(np.linalg.norm(field)),
            "matrix": np.linalg.inv(soft).tolist(),
            "offset": hard.tolist(),
        }
    }
    return table, truth
