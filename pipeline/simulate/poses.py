"""Scenario ``poses``: a multi-position calibration session with a known accelerometer and
gyroscope error model.

Timeline: ``max(init_static_s, pose_s)`` seconds at rest in the first pose (z up; ``init_static_s
= 0`` is a session without a long still start, as most are recorded), then ``n_poses - 1`` times:
a rotation of ``move_s`` seconds about a fixed body axis (smooth profile ``theta(t) = angle (1 -
cos(pi t / move_s)) / 2``; each gyro sample is the mean rate over its sample period) into the
next pose, and ``pose_s`` seconds at rest there. With
``faces = true`` poses 1..5 complete the six faces (+-x, +-y, +-z up); the others are uniformly
random orientations (from the seed), or with ``only_faces = true`` the six faces again and again,
each tilted by a random angle of up to ``face_tilt_deg`` (a six-face session like the T265's);
``cluster_deg > 0``: every pose within that angle of z up (clustered poses, a session on a desk).
The IMU rotates about its own origin (no linear acceleration).

Error model, the inverse of imupipe's calibration models (so a perfect fit returns the truth)::

    accel_raw = (S K)^-1 f + b           (K: angles a_yz, a_zy, a_zx; see stages/accel_models)
    gyro_raw  = (T diag(s))^-1 w + b_g   (T: six angles yz, zy, zx, xz, xy, yx; stages/gyro_models)

plus white noise of density ``accel_N`` (m/s^2/sqrt(Hz)) and ``gyro_N`` (rad/s/sqrt(Hz)) on the raw
outputs (raw units are SI scaled by the model). Truths the models do *not* have (all off by
default), to test the fits on data whose form differs from theirs:

- ``accel_nonlinearity`` (3, 1/(m/s^2)): ``accel_raw += c f^2`` per axis (a quadratic scale error);
- ``gyro_g_sensitivity`` (3x3, rad/s per m/s^2): ``gyro_raw += G f`` (g-sensitivity);
- ``accel_bias_rw``, ``gyro_bias_rw``: random walk of the biases (density, unit/s/sqrt(Hz));
- ``tremor_deg``: a hand holding each pose: the attitude wanders by this RMS angle (deg), band
  limited to about ``tremor_hz``, and the gyro sees the matching rates. Truth: ``accel`` and ``gyro`` each with ``matrix``
and ``offset`` (``corrected = matrix @ (raw - offset)``) and their native parameters, ``gravity``
and ``static_intervals_s`` ([start, end] seconds from the first sample of each rest).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.noise import random_walk, white
from imupipe.readers.table import make_table
from imupipe.stages.multiposition.accel_models import misalignment_matrix
from imupipe.stages.multiposition.gyro_models import gyro_matrix

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
    "cluster_deg": 0.0,
    "accel_scale": [1.02, 0.985, 1.01],
    "accel_misalignment": [0.004, -0.006, 0.008],
    "accel_bias": [0.15, -0.10, 0.20],
    "accel_N": 5.0e-4,
    "gyro_scale": [1.01, 0.99, 1.005],
    "gyro_misalignment": [0.003, -0.002, 0.004, 0.001, -0.003, 0.002],
    "gyro_bias": [0.01, -0.02, 0.005],
    "gyro_N": 1.0e-4,
    "accel_nonlinearity": [0.0, 0.0, 0.0],
    "gyro_g_sensitivity": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
    "accel_bias_rw": 0.0,
    "gyro_bias_rw": 0.0,
    "tremor_deg": 0.0,
    "tremor_hz": 3.0,
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
    if p["cluster_deg"] > 0:  # every pose within cluster_deg of z up (a session on a desk)
        tilt = rng.normal(size=(n, 3))
        tilt[:, 2] = 0.0
        tilt *= (
            np.radians(p["cluster_deg"])
            * np.sqrt(rng.uniform(size=(n, 1)))
            / np.linalg.norm(tilt, axis=1, keepdims=True)
        )
        yaw = np.column_stack([np.zeros((n, 2)), rng.uniform(0, 2 * np.pi, n)])
        return Rotation.from_rotvec(tilt) * Rotation.from_rotvec(yaw)
    rest = Rotation.random(n - len(rots), random_state=rng)
    return Rotation.concatenate([*rots, rest]) if n > len(rots) else Rotation.concatenate(rots)


def tremor(
    rng: np.random.Generator, n: int, rms_deg: float, band_hz: float, fs: float
) -> tuple[Rotation, np.ndarray]:
    """A hand's wander about a held pose: small rotations (n,) of RMS angle ``rms_deg`` per axis,
    white noise smoothed by a Gaussian kernel of width ``1 / (2 pi band_hz)`` s, and the body
    rates (n, 3) that produce them (small angles: the rate is the angle's derivative)."""
    if rms_deg <= 0 or n < 2:
        return Rotation.identity(n), np.zeros((n, 3))
    width = max(fs / (2 * np.pi * band_hz), 1.0)
    kernel = np.exp(-0.5 * (np.arange(-4 * width, 4 * width + 1) / width) ** 2)
    noise = rng.standard_normal((n + len(kernel) - 1, 3))
    angle = np.column_stack([np.convolve(noise[:, i], kernel, mode="valid") for i in range(3)])
    angle *= np.radians(rms_deg) / angle.std(axis=0)
    return Rotation.from_rotvec(angle), np.gradient(angle, 1 / fs, axis=0)


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    fs = float(p["rate_hz"])
    poses = pose_rotations(p, rng)
    n_init = int(round(max(p["init_static_s"], p["pose_s"]) * fs))
    n_pose = int(round(p["pose_s"] * fs))
    n_move = int(round(p["move_s"] * fs))
    wander, wander_rate = tremor(rng, n_init, p["tremor_deg"], p["tremor_hz"], fs)
    attitude = [Rotation.from_quat(np.tile(poses[0].as_quat(), (n_init, 1))) * wander]
    omega = [wander_rate]
    intervals = [[0.0, (n_init - 1) / fs]]
    start = n_init
    tau = (np.arange(n_move) + 1) / n_move
    for i in range(1, len(poses)):  # one block per pose, vectorised over its samples
        rel = (poses[i - 1].inv() * poses[i]).as_rotvec()
        angle = float(np.linalg.norm(rel))
        axis = rel / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
        theta = angle * (1 - np.cos(np.pi * tau)) / 2
        # each gyro sample is the mean rate over its sample period (the turn since the previous
        # sample times the rate), as a gyro's anti-alias filter or delta-angle output gives:
        # sampled at instants, the profile's steps of angular acceleration at both ends of a
        # turn made the samples' sum short of the angle by (pi / 2 n)^2 / 3 (n samples per
        # turn: 82 ppm for 1 s turns at 100 Hz), and every scale fitted that much high
        rate = angle * (np.cos(np.pi * (tau - 1 / n_move)) - np.cos(np.pi * tau)) / 2 * fs
        attitude.append(poses[i - 1] * Rotation.from_rotvec(theta[:, None] * axis))
        omega.append(rate[:, None] * axis)
        wander, wander_rate = tremor(rng, n_pose, p["tremor_deg"], p["tremor_hz"], fs)
        attitude.append(Rotation.from_quat(np.tile(poses[i].as_quat(), (n_pose, 1))) * wander)
        omega.append(wander_rate)
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
    accel += np.asarray(p["accel_nonlinearity"], dtype=float) * f_true**2
    gyro += f_true @ np.asarray(p["gyro_g_sensitivity"], dtype=float).reshape(3, 3).T
    accel += np.column_stack([random_walk(rng, n, p["accel_bias_rw"], fs) for _ in range(3)])
    gyro += np.column_stack([random_walk(rng, n, p["gyro_bias_rw"], fs) for _ in range(3)])

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
