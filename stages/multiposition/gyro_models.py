"""Gyroscope scale and misalignment models: static poses (Tedaldi, Pretto and Menegatti, ICRA
2014, as imu_tk implements it), turntable runs at +rate and -rate (the scale-factor formula of the
gyroscope temperature-calibration patent) and turns of a known angle (imucal / Ferraris).

Model (raw gyro units, e.g. counts or rad/s, to rad/s)::

    w = T diag(s) (w_raw - b),   T = [[1, -g_yz, g_zy], [g_xz, 1, -g_zx], [-g_xy, g_yx, 1]]

(imu_tk's gyroscope misalignment, six small angles in rad). Exported as ``matrix = T diag(s)``,
``offset = b``.

**static_poses** (Tedaldi et al. 2014): ``b`` is the mean gyro over the static intervals (or
over an initial rest, as imu_tk). Between consecutive static intervals j and j+1 the calibrated
gyro is integrated over the motion (body-frame increments ``exp(w_k dt_k)`` with ``w_k`` the mean
of consecutive samples -- the trapezoidal rule, second order like imu_tk's RK4 on linearly
interpolated rates -- composed by a vectorised pairwise quaternion product), and the gravity
direction measured in interval j (mean calibrated accelerometer, normalised) is carried to the
end: ``u_pred = R^T u_j``. The parameters minimise ``sum |u_pred - u_{j+1}|^2`` (scipy
Levenberg-Marquardt); the start is a scalar scale chosen on a log grid from the data (no
hand-made guess, e.g. imu_tk's 1/6258). Two models are fitted -- the nine parameters, and the
three scales alone -- and the one with the lower corrected Akaike information criterion (two
observations per motion: a direction on the sphere) is kept: with few motions, or motions that do
not turn about every axis, the six angles are not supported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from imupipe.stages.errors import FitError
from imupipe.stages.multiposition.accel_models import aicc, fmt_criterion
from imupipe.stages.static_detector import Intervals, Poses


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
        cls, t_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray, intervals: Intervals | Poses
    ) -> PoseTransitions:
        """From sample times ``t_s`` (s, e.g. :func:`imupipe.stages.static_detector.sample_clock`),
        raw gyro and accelerometer (n, 3) and the static intervals or poses (a motion runs from
        the last static sample of one to the first of the next)."""
        means = intervals.means(accel)
        unit = means / np.linalg.norm(means, axis=1)[:, None]
        first = intervals.stop[:-1] - 1
        last = intervals.start[1:]
        steps = last - first
        width = int(steps.max())
        idx = first[:, None] + np.arange(width + 1)[None, :]
        valid = idx <= last[:, None]
        idx = np.minimum(idx, last[:, None])
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


def scale_guess(moves: PoseTransitions, bias: np.ndarray) -> float | None:
    """A ballpark scalar scale: the median over the motions of the angle between the measured
    gravity directions over the magnitude of the integrated bias-free raw gyro (the turn about
    gravity is invisible to the first, so this is low by up to a few times). None when no motion
    turned the gravity direction by at least 10 deg."""
    turned = np.arccos(np.clip(np.einsum("ij,ij->i", moves.u_start, moves.u_end), -1.0, 1.0))
    raw = moves.raw - bias
    integral = np.linalg.norm(
        (0.5 * (raw[:, 1:] + raw[:, :-1]) * moves.dt[..., None]).sum(1), axis=1
    )
    ok = (turned > np.radians(10)) & (integral > 0)
    return float(np.median(turned[ok] / integral[ok])) if ok.any() else None


def scale_start(
    moves: PoseTransitions, bias: np.ndarray, low: float = 1e-7, high: float = 1e3
) -> float:
    """The scalar scale (same on every axis, no misalignment) with the lowest RMS angle residual:
    a log grid (ratio 1.25) over a factor 30 either side of :func:`scale_guess` (from ``low`` to
    ``high`` without a guess, or when the best point lies on the window's edge), refined by a
    bounded scalar search between the best grid point's neighbours."""

    def rms(log_s: float) -> float:
        return float(np.sqrt(np.mean(moves.angles_deg(np.exp(log_s) * np.eye(3), bias) ** 2)))

    step = np.log(1.25)
    guess = scale_guess(moves, bias)
    grid = np.arange(np.log(low), np.log(high), step)
    if guess is not None:
        window = np.log(guess) + np.arange(-15, 16) * step
        scores = [rms(x) for x in window]
        best_i = int(np.argmin(scores))
        if 0 < best_i < len(window) - 1:
            grid, best = window, window[best_i]
        else:
            best = grid[int(np.argmin([rms(x) for x in grid]))]
    else:
        best = grid[int(np.argmin([rms(x) for x in grid]))]
    res = minimize_scalar(rms, bounds=(best - step, best + step), method="bounded")
    return float(np.exp(res.x if res.fun < rms(best) else best))


GYRO_MODELS: dict[str, np.ndarray] = {
    "9-parameter": np.ones(9, dtype=bool),
    "scale-only": np.r_[np.ones(3, dtype=bool), np.zeros(6, dtype=bool)],
}
"""The gyroscope models: three scales and six misalignment angles, or the three scales alone."""


@dataclass
class GyroFit:
    """One gyroscope model fitted on the pose transitions, with its statistics."""

    name: str
    free: np.ndarray
    start_scale: float
    x: np.ndarray
    """(9,) relative scale corrections and the six angles (zeros where not fitted)."""
    residual: np.ndarray
    """(3 m,) predicted minus measured gravity directions at the fit."""
    jacobian: np.ndarray
    function_evaluations: int

    @property
    def scale(self) -> np.ndarray:
        return self.start_scale * (1 + self.x[:3])

    @property
    def matrix(self) -> np.ndarray:
        return gyro_matrix(self.scale, self.x[3:])

    @property
    def n_params(self) -> int:
        return int(self.free.sum())

    @property
    def n_obs(self) -> int:
        """Independent observations: two per transition (a direction on the sphere)."""
        return 2 * (len(self.residual) // 3)

    @property
    def rss(self) -> float:
        return float(self.residual @ self.residual)

    @property
    def aicc(self) -> float:
        """Corrected Akaike information criterion over the direction residuals."""
        return aicc(self.n_obs, self.n_params, self.rss)

    def standard_errors(self) -> np.ndarray:
        """(9,) standard errors of ``x`` (relative scale, rad), 0 where not fitted, NaN without
        degrees of freedom."""
        out = np.zeros(9)
        dof = self.n_obs - self.n_params
        if dof <= 0:
            out[self.free] = np.nan
            return out
        cov = np.linalg.pinv(self.jacobian.T @ self.jacobian) * (self.rss / dof)
        out[self.free] = np.sqrt(np.maximum(np.diag(cov), 0))
        return out

    def condition_number(self) -> float:
        norms = np.linalg.norm(self.jacobian, axis=0)
        norms[norms == 0] = 1
        sv = np.linalg.svd(self.jacobian / norms, compute_uv=False)
        return float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")


def fit_gyro_model(
    moves: PoseTransitions, bias: np.ndarray, name: str, start_scale: float
) -> GyroFit:
    """Fit the model ``name`` (a key of :data:`GYRO_MODELS`) by LM from ``start_scale``."""
    free = GYRO_MODELS[name]

    def unpack(z: np.ndarray) -> np.ndarray:
        x = np.zeros(9)
        x[free] = z
        return x

    def residual(z: np.ndarray) -> np.ndarray:
        x = unpack(z)
        return (
            moves.predict(gyro_matrix(start_scale * (1 + x[:3]), x[3:]), bias) - moves.u_end
        ).ravel()

    res = least_squares(residual, np.zeros(int(free.sum())), method="lm", x_scale=1.0)
    return GyroFit(name, free, start_scale, unpack(res.x), res.fun, res.jac, int(res.nfev))


def fit_static_poses(
    moves: PoseTransitions, bias: np.ndarray, models: list[str] | None = None
) -> dict[str, Any]:
    """The gyro model (default: the 9-parameter or the scale-only one, whichever has the lower
    AICc) fitted on the pose transitions; see the module docstring. Returns the chosen fit, the
    reason, every candidate's figures, residuals before and after, and solver figures."""
    t0 = time.perf_counter()
    models = models or list(GYRO_MODELS)
    if len(moves.u_end) < 2:
        raise FitError(
            f"{len(moves.u_end)} motion(s) between static intervals: the gyro fit needs at least 2"
        )
    s0 = scale_start(moves, bias)
    fits = [
        fit_gyro_model(moves, bias, m, s0)
        for m in models
        if 3 * len(moves.u_end) >= GYRO_MODELS[m].sum()
    ]
    best = min(fits, key=lambda f: (f.aicc, f.n_params))
    short = [
        f"the {m} model needs at least {-(-int(GYRO_MODELS[m].sum()) // 3)}"
        for m in models
        if m not in {f.name for f in fits}
    ]
    if len(fits) == 1 and short:
        reason = f"{len(moves.u_end)} motions: " + "; ".join(short)
    elif len(fits) == 1:
        reason = f"the {best.name} model was asked for"
    else:
        reason = (
            "lowest AICc ("
            + "; ".join(
                f"{f.name}: AICc {fmt_criterion(f.aicc)}, direction residual "
                f"{np.degrees(np.sqrt(f.rss / len(moves.u_end))):.3g} deg"
                for f in sorted(fits, key=lambda f: f is not best)
            )
            + ")"
        )
    return {
        "fit": best,
        "reason": reason,
        "candidates": {
            f.name: {
                "parameters": f.n_params,
                "aicc": float(f.aicc) if np.isfinite(f.aicc) else None,
                "residual_deg_rms": float(np.sqrt(np.mean(moves.angles_deg(f.matrix, bias) ** 2))),
            }
            for f in fits
        },
        "start_scale": s0,
        "residual_deg": moves.angles_deg(best.matrix, bias),
        "residual_deg_start": moves.angles_deg(s0 * np.eye(3), bias),
        "time_s": time.perf_counter() - t0,
    }


def turntable_columns(
    runs: list[tuple[int, float, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
    """Per run (axis, rate rad/s, mean raw gyro at +rate, at -rate) the scale column
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
