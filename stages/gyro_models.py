"""Gyroscope scale and misalignment models: static poses (imu_tk), turntable runs (seed 004) and
turns of a known angle (imucal / Ferraris).

Model (raw gyro units, e.g. counts or rad/s, to rad/s)::

    w = T diag(s) (w_raw - b),   T = [[1, -g_yz, g_zy], [g_xz, 1, -g_zx], [-g_xy, g_yx, 1]]

(imu_tk's gyroscope misalignment, six small angles in rad). Exported as ``matrix = T diag(s)``,
``offset = b``.

**static_poses** (Tedaldi et al. 2014): ``b`` is the mean gyro over the initial static period.
Between consecutive static intervals j and j+1 the calibrated gyro is integrated over the motion
(body-frame increments ``exp(w_k dt_k)`` with ``w_k`` the mean of consecutive samples, composed by
a vectorised pairwise quaternion product), and the gravity direction measured in interval j
(mean calibrated accelerometer, normalised) is carried to the end: ``u_pred = R^T u_j``. The nine
parameters minimise ``sum |u_pred - u_{j+1}|^2`` (scipy least squares); the start is a scalar
scale chosen on a log grid from the data (no hand-made guess, e.g. imu_tk's 1/6258).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from imupipe.stages.static_detector import Intervals


def gyro_misalignment(angles: np.ndarray) -> np.ndarray:
    """T from ``(g_yz, g_zy, g_zx, g_xz, g_xy, g_yx)`` (rad)."""
    yz, zy, zx, xz, xy, yx = angles
    return np.array([[1.0, -yz, zy], [xz, 1.0, -zx], [-xy, yx, 1.0]])


def gyro_matrix(scale: np.ndarray, angles: np.ndarray) -> np.ndarray:
    return gyro_misalignment(angles) @ np.diag(scale)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternion arrays (..., 4) stored as (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def rotvec_to_quat(phi: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) of rotation vectors (..., 3) (rad)."""
    angle = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * angle
    sinc = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5)
    return np.concatenate([np.cos(half), phi * sinc], axis=-1)


def compose(q: np.ndarray) -> np.ndarray:
    """Ordered product ``q[:, 0] q[:, 1] ... q[:, L-1]`` of (m, L, 4) quaternions -> (m, 4), by
    pairwise reduction (log2 L vectorised steps)."""
    while q.shape[1] > 1:
        if q.shape[1] % 2:
            ident = np.zeros((q.shape[0], 1, 4))
            ident[..., 0] = 1.0
            q = np.concatenate([q, ident], axis=1)
        q = quat_mul(q[:, 0::2], q[:, 1::2])
    return q[:, 0]


def rotate_inverse(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R(q)^T v`` for (m, 4) quaternions and (m, 3) vectors."""
    w, r = q[:, :1], q[:, 1:]
    t = 2 * np.cross(r, v)
    return v - w * t + np.cross(r, t)


@dataclass
class PoseTransitions:
    """The motions between consecutive static intervals, gathered once (padded per motion)."""

    raw: np.ndarray
    """(m, L + 1, 3) raw gyro from the last sample of interval j to the first of j+1 (padded)."""
    dt: np.ndarray
    """(m, L) time steps (s), 0 in the padding."""
    u_start: np.ndarray
    u_end: np.ndarray
    """(m, 3) measured gravity directions in intervals j and j+1."""

    @classmethod
    def build(
        cls, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, intervals: Intervals
    ) -> PoseTransitions:
        means = intervals.means(accel)
        unit = means / np.linalg.norm(means, axis=1)[:, None]
        first = intervals.stop[:-1] - 1
        last = intervals.start[1:]
        steps = last - first
        width = int(steps.max())
        idx = first[:, None] + np.arange(width + 1)[None, :]
        valid = idx <= last[:, None]
        idx = np.minimum(idx, last[:, None])
        t_s = (t_ns - t_ns[0]) * 1e-9
        dt = np.diff(t_s[idx], axis=1) * valid[:, 1:]
        return cls(gyro[idx], dt, unit[:-1], unit[1:])

    def predict(self, matrix: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """(m, 3) gravity direction at the end of each motion predicted from its start."""
        w = (self.raw - bias) @ matrix.T
        phi = 0.5 * (w[:, 1:] + w[:, :-1]) * self.dt[..., None]
        return rotate_inverse(compose(rotvec_to_quat(phi)), self.u_start)

    def angles_deg(self, matrix: np.ndarray, bias: np.ndarray) -> np.ndarray:
        pred = self.predict(matrix, bias)
        cos = np.einsum("ij,ij->i", pred, self.u_end) / np.linalg.norm(pred, axis=1)
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def scale_start(
    moves: PoseTransitions, bias: np.ndarray, low: float = 1e-7, high: float = 1e3
) -> float:
    """The scalar scale (same on every axis, no misalignment) with the lowest RMS angle residual:
    a log grid (ratio 1.25) from ``low`` to ``high``, refined by a bounded scalar search between
    the best grid point's neighbours."""

    def rms(log_s: float) -> float:
        return float(np.sqrt(np.mean(moves.angles_deg(np.exp(log_s) * np.eye(3), bias) ** 2)))

    step = np.log(1.25)
    grid = np.arange(np.log(low), np.log(high), step)
    best = grid[int(np.argmin([rms(x) for x in grid]))]
    res = minimize_scalar(rms, bounds=(best - step, best + step), method="bounded")
    return float(np.exp(res.x if res.fun < rms(best) else best))


def fit_static_poses(moves: PoseTransitions, bias: np.ndarray) -> dict[str, Any]:
    """Nine gyro parameters (scale, six angles) from the pose transitions; see the module
    docstring. Returns scale, angles, matrix, residuals and solver figures."""
    t0 = time.perf_counter()
    s0 = scale_start(moves, bias)

    def unpack(x: np.ndarray) -> np.ndarray:
        return gyro_matrix(s0 * (1 + x[:3]), x[3:])

    def residual(x: np.ndarray) -> np.ndarray:
        return (moves.predict(unpack(x), bias) - moves.u_end).ravel()

    res = least_squares(residual, np.zeros(9), method="lm", x_scale=1.0)
    matrix = unpack(res.x)
    jac = res.jac
    norms = np.linalg.norm(jac, axis=0)
    norms[norms == 0] = 1
    sv = np.linalg.svd(jac / norms, compute_uv=False)
    before = moves.angles_deg(s0 * np.eye(3), bias)
    after = moves.angles_deg(matrix, bias)
    return {
        "scale": (s0 * (1 + res.x[:3])).tolist(),
        "misalignment_rad": res.x[3:].tolist(),
        "matrix": matrix,
        "start_scale": s0,
        "residual_deg": after,
        "residual_deg_start": before,
        "condition_number": float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf"),
        "function_evaluations": int(res.nfev),
        "time_s": time.perf_counter() - t0,
    }


def turntable_columns(
    runs: list[tuple[int, float, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
    """Seed 004: per run (axis, rate rad/s, mean raw gyro at +rate, at -rate) the scale column
    ``(out(+r) - out(-r)) / 2r``; per axis the least-squares column over its rates. Returns the
    sensitivity matrix M (raw = M w + b; identity columns for axes without runs), the bias b (mean
    of the run midpoints) and a per-run table."""
    m = np.eye(3)
    table = []
    mids = []
    for axis in range(3):
        mine = [r for r in runs if r[0] == axis]
        if not mine:
            continue
        num = sum((plus - minus) * rate for _, rate, plus, minus in mine)
        den = sum(2 * rate**2 for _, rate, _, _ in mine)
        m[:, axis] = num / den
        for _, rate, plus, minus in mine:
            table.append(
                {
                    "axis": "xyz"[axis],
                    "rate_rad_s": rate,
                    "column": ((plus - minus) / (2 * rate)).tolist(),
                    "scale": float((plus[axis] - minus[axis]) / (2 * rate)),
                }
            )
            mids.append((plus + minus) / 2)
    return m, np.mean(mids, axis=0), table
