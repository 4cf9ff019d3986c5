"""Scenario ``poses``: a multi-position calibration session with a known accelerometer and
gyroscope error model.

Timeline: ``init_static_s`` seconds at rest in the first pose (z up), then ``n_poses - 1`` times:
a rotation of ``move_s`` seconds about a fixed body axis (smooth profile ``theta(t) = angle (1 -
cos(pi t / move_s)) / 2``) into the next pose, and ``pose_s`` seconds at rest there. With
``faces = true`` poses 1..5 complete the six faces (+-x, +-y, +-z up); the others are uniformly
random orientations (from the seed), or with ``only_faces = true`` the six faces again and again,
each tilted by a random angle of up to ``face_tilt_deg`` (a six-face session like the T265's). The IMU rotates about its own origin (no linear acceleration).

Error model, the inverse of imupipe's calibration models (so a perfect fit returns the truth)::

    accel_raw = (S K)^-1 f + b           (K: angles a_yz, a_zy, a_zx; see stages/accel_models)
    gyro_raw  = (T diag(s))^-1 w + b_g   (T: six angles yz, zy, zx, xz, xy, yx; stages/gyro_models)

plus white noise of density ``accel_N`` (m/s^2/sqrt(Hz)) and ``gyro_N`` (rad/s/sqrt(Hz)) on the raw
outputs (raw units are SI scaled by the model). Truth: ``accel`` and ``gyro`` each with ``matrix``
and ``offset`` (``corrected = matrix @ (raw - offset)``) and their native parameters, ``gravity``
and ``static_intervals_s`` ([start, end] seconds from the first sample of each rest).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.noise import white
from imupipe.readers.table import make_table
from imupipe.stages.accel_models import misalignment_matrix
from imupipe.stages.gyro_models import gyro_matrix

DEFAULTS: dict[str, Any] = {
    "rate_hz": 100.0,
    "t0_s": 1_700_000_000.0,
    "gravity": 9.80665,
    "n_poses": 18,
    "init_static_s": 40.0,
    "pose_s": 6.0,
    "move_s": 3.0,
    "faces": True,
    "only_faces": False,
    "face_tilt_deg": 2.0,
    "accel_scale": [1.02, 0.985, 1.01],
    "accel_misalignment": [0.004, -0.006, 0.008],
    "accel_bias": [0.15, -0.10, 0.20],
    "accel_N": 5.0e-4,
    "gyro_scale": [1.01, 0.99, 1.005],
    "gyro_misalignment": [0.003, -0.002, 0.004, 0.001, -0.003, 0.002],
    "gyro_bias": [0.01, -0.02, 0.005],
    "gyro_N": 1.0e-4,
    "temperature": 25.0,
}

FACES = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float)


def pose_rotations(p: dict[str, Any], rng: np.random.Generator) -> Rotation:
    """Body-to-world attitudes of the poses (the first with z up)."""
    n = int(p["n_poses"])
    if n < 2:
        raise ValueError("n_poses must be >= 2")
    ups = FACES[: min(n, 6)] if p["faces"] else FACES[:1]
    rots = [Rotation.align_vectors([[0.0, 0.0, 1.0]], [u])[0] for u in ups]
    if p["only_faces"]:
        faces = Rotation.concatenate(
            [Rotation.align_vectors([[0.0, 0.0, 1.0]], [FACES[i % 6]])[0] for i in range(n)]
        )
        tilt = rng.normal(size=(n, 3))
        tilt *= (
            np.radians(p["face_tilt_deg"])
            * rng.uniform(size=(n, 1))
            / np.linalg.norm(tilt, axis=1, keepdims=True)
        )
        return faces * Rotation.from_rotvec(tilt)
    rest = Rotation.random(n - len(rots), random_state=rng)
    return Rotation.concatenate([*rots, rest]) if n > len(rots) else Rotation.concatenate(rots)


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    fs = float(p["rate_hz"])
    poses = pose_rotations(p, rng)
    n_init = int(round(p["init_static_s"] * fs))
    n_pose = int(round(p["pose_s"] * fs))
    n_move = int(round(p["move_s"] * fs))
    attitude = [Rotation.from_quat(np.tile(poses[0].as_quat(), (n_init, 1)))]
    omega = [np.zeros((n_init, 3))]
    intervals = [[0.0, (n_init - 1) / fs]]
    start = n_init
    tau = (np.arange(n_move) + 1) / n_move
    for i in range(1, len(poses)):  # one block per pose, vectorised over its samples
        rel = (poses[i - 1].inv() * poses[i]).as_rotvec()
        angle = float(np.linalg.norm(rel))
        axis = rel / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
        theta = angle * (1 - np.cos(np.pi * tau)) / 2
        rate = angle * np.pi / (2 * p["move_s"]) * np.sin(np.pi * tau)
        attitude.append(poses[i - 1] * Rotation.from_rotvec(theta[:, None] * axis))
        omega.append(rate[:, None] * axis)
        attitude.append(Rotation.from_quat(np.tile(poses[i].as_quat(), (n_pose, 1))))
        omega.append(np.zeros((n_pose, 3)))
        start += n_move
        intervals.append([start / fs, (start + n_pose - 1) / fs])
        start += n_pose
    attitude_all = Rotation.concatenate(attitude)
    w_true = np.vstack(omega)
    g = float(p["gravity"])
    f_true = attitude_all.inv().apply([0.0, 0.0, g])
    n = len(w_true)

    a_matrix = np.diag(p["accel_scale"]) @ misalignment_matrix(np.asarray(p["accel_misalignment"]))
    g_matrix = gyro_matrix(np.asarray(p["gyro_scale"]), np.asarray(p["gyro_misalignment"]))
    noise_a = np.column_stack([white(rng, n, p["accel_N"], fs) for _ in range(3)])
    noise_g = np.column_stack([white(rng, n, p["gyro_N"], fs) for _ in range(3)])
    accel = f_true @ np.linalg.inv(a_matrix).T + np.asarray(p["accel_bias"]) + noise_a
    gyro = w_true @ np.linalg.inv(g_matrix).T + np.asarray(p["gyro_bias"]) + noise_g

    t_ns = sample_times(p["t0_s"], n, fs)
    temperature = None if p["temperature"] is None else np.full(n, float(p["temperature"]))
    table = make_table(
        t_ns,
        gyro=gyro,
        accel=accel,
        temperature=temperature,
        metadata={"source": "imupipe simulate poses", "format": "simulated"},
    )
    truth = {
        "accel": {
            "matrix": a_matrix.tolist(),
            "offset": list(p["accel_bias"]),
            "scale": list(p["accel_scale"]),
            "misalignment": list(p["accel_misalignment"]),
        },
        "gyro": {
            "matrix": g_matrix.tolist(),
            "offset": list(p["gyro_bias"]),
            "scale": list(p["gyro_scale"]),
            "misalignment": list(p["gyro_misalignment"]),
        },
        "gravity": g,
        "static_intervals_s": intervals,
    }
    return table, truth
