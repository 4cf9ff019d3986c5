"""Scenario ``thermal_soak``: multi-position sessions at several chamber temperatures (the soak
method of "MEMS 惯性测量组件的温度误差补偿模型研究": calibrate at each held temperature, then fit
each parameter against temperature).

Timeline: for each chamber temperature of ``levels`` (degC) in turn, the chamber moves from the
previous one at ``ramp_rate`` degC/min while the IMU sits still, z up, for ``soak_s`` seconds;
then the IMU is turned through a multi-position session (the ``poses`` scenario's motion:
``n_poses`` poses held ``pose_s`` s, moves of ``move_s`` s; the first six are the faces, the rest
random). The IMU is put back z up (instantly) before the next chamber temperature. The device
temperature ``T`` follows the chamber through a first-order lag of ``lag_s`` seconds, and the
temperature sensor reads it with white noise of ``temperature_noise`` degC.

Error model per sample, with ``x = T - tref`` at that sample (the inverse of imupipe's
calibration models, as in the ``poses`` scenario)::

    accel_raw = (diag(s_a) K(angles_a))^-1 f + b_a
    gyro_raw  = (T(angles_g) diag(s_g))^-1 w + b_g

Every parameter ``p`` (scale, misalignment angles, bias) is ``p(x) = p0 + c1 x + c2 x^2 + c3 x^3``
(``<sensor>_<parameter>`` = p0 per component, ``<sensor>_<parameter>_tc`` = [[c1, c2, c3] per
component]); plus white noise ``accel_N`` (m/s^2/sqrt(Hz)) and ``gyro_N`` (rad/s/sqrt(Hz)).

Truth: ``tref``, ``levels``, ``soaks`` ([start_s, end_s] of each multi-position session, s
from the first sample, and its mean device temperature), and per sensor the parameters'
``p0`` and ``tc`` (as given).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.simulate import poses
from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.noise import white
from imupipe.pipeline.simulate.thermal import lagged
from imupipe.readers.table import make_table, sensor

DEFAULTS: dict[str, Any] = {
    "rate_hz": 20.0,
    "t0_s": 1_700_000_000.0,
    "gravity": 9.80665,
    "levels": [-20.0, -5.0, 10.0, 25.0, 40.0, 55.0, 70.0],
    "ramp_rate": 5.0,
    "soak_s": 900.0,
    "lag_s": 120.0,
    "n_poses": 15,
    "pose_s": 6.0,
    "move_s": 3.0,
    "tref": 25.0,
    "temperature_noise": 0.02,
    "accel_scale": [1.02, 0.985, 1.01],
    "accel_scale_tc": [[1.5e-4, 1.0e-6, 0.0], [-1.0e-4, 2.0e-6, -2.0e-8], [8.0e-5, 0.0, 0.0]],
    "accel_misalignment": [0.004, -0.006, 0.008],
    "accel_misalignment_tc": [[2.0e-5, 0.0, 0.0], [0.0, 0.0, 0.0], [-1.5e-5, 2.0e-7, 0.0]],
    "accel_bias": [0.15, -0.10, 0.20],
    "accel_bias_tc": [[1.0e-3, -2.0e-5, 3.0e-7], [-8.0e-4, 1.0e-5, 0.0], [1.2e-3, 0.0, -2.0e-7]],
    "accel_N": 5.0e-4,
    "gyro_scale": [1.01, 0.99, 1.005],
    "gyro_scale_tc": [[1.0e-4, 0.0, 0.0], [-5.0e-5, 1.0e-6, 0.0], [0.0, 0.0, 0.0]],
    "gyro_misalignment": [0.003, -0.002, 0.004, 0.001, -0.003, 0.002],
    "gyro_misalignment_tc": [[0.0, 0.0, 0.0]] * 6,
    "gyro_bias": [0.01, -0.02, 0.005],
    "gyro_bias_tc": [[2.0e-4, -3.0e-6, 0.0], [-1.0e-4, 0.0, 2.0e-8], [1.5e-4, 2.0e-6, 0.0]],
    "gyro_N": 1.0e-4,
}

PARAMETERS = {"accel": ("scale", "misalignment", "bias"), "gyro": ("scale", "misalignment", "bias")}


def parameter_at(p: dict[str, Any], name: str, x: np.ndarray) -> np.ndarray:
    """(n, k) parameter ``name`` (e.g. ``accel_bias``) at ``x = T - tref`` (n,)."""
    p0 = np.asarray(p[name], dtype=np.float64)
    tc = np.asarray(p[f"{name}_tc"], dtype=np.float64).reshape(len(p0), 3)
    powers = np.column_stack([x, x * x, x * x * x])
    return p0 + powers @ tc.T


def accel_raw(f: np.ndarray, scale: np.ndarray, angles: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """``(diag(s) K)^-1 f + b`` per sample (K as in :mod:`imupipe.stages.multiposition.accel_models`)."""
    yz, zy, zx = angles.T
    u = f / scale
    vz = u[:, 2]
    vy = u[:, 1] + zx * vz
    vx = u[:, 0] + yz * vy - zy * vz
    return np.column_stack([vx, vy, vz]) + bias


def gyro_raw(w: np.ndarray, scale: np.ndarray, angles: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """``(T diag(s))^-1 w + b`` per sample (T as in :mod:`imupipe.stages.multiposition.gyro_models`)."""
    yz, zy, zx, xz, xy, yx = angles.T
    m = np.empty((len(w), 3, 3))
    m[:, 0] = np.column_stack([np.ones(len(w)), -yz, zy])
    m[:, 1] = np.column_stack([xz, np.ones(len(w)), -zx])
    m[:, 2] = np.column_stack([-xy, yx, np.ones(len(w))])
    return np.linalg.solve(m, w[..., None])[..., 0] / scale + bias


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    fs = float(p["rate_hz"])
    levels = [float(v) for v in p["levels"]]
    if len(levels) < 1 or float(p["ramp_rate"]) <= 0 or float(p["soak_s"]) <= 0:
        raise ConfigError("thermal_soak scenario: need levels, ramp_rate > 0 and soak_s > 0")
    motion = {
        **poses.DEFAULTS,
        "rate_hz": fs,
        "gravity": float(p["gravity"]),
        "n_poses": int(p["n_poses"]),
        "init_static_s": float(p["soak_s"]),
        "pose_s": float(p["pose_s"]),
        "move_s": float(p["move_s"]),
        "accel_scale": [1.0] * 3,
        "accel_misalignment": [0.0] * 3,
        "accel_bias": [0.0] * 3,
        "accel_N": 0.0,
        "gyro_scale": [1.0] * 3,
        "gyro_misalignment": [0.0] * 6,
        "gyro_bias": [0.0] * 3,
        "gyro_N": 0.0,
        "temperature": None,
    }
    f_parts, w_parts, chamber_t, chamber_v, sessions = [], [], [0.0], [levels[0]], []
    start = 0
    for level in levels:  # one multi-position session per chamber temperature
        table, truth = poses.simulate(motion, rng)
        f_parts.append(sensor(table, "accel").values)
        w_parts.append(sensor(table, "gyro").values)
        t_level = start / fs
        ramp = abs(level - chamber_v[-1]) / (float(p["ramp_rate"]) / 60.0)
        chamber_t += [t_level, t_level + ramp]
        chamber_v += [chamber_v[-1], level]
        session = truth["static_intervals_s"][1][0] - float(p["move_s"])
        sessions.append(t_level + session)
        start += len(table)
    f = np.vstack(f_parts)
    w = np.vstack(w_parts)
    n = len(f)
    t_s = np.arange(n) / fs
    chamber = np.interp(t_s, chamber_t, chamber_v)
    temp = lagged(t_s, chamber, float(p["lag_s"]))
    x = temp - float(p["tref"])
    accel = accel_raw(
        f,
        parameter_at(p, "accel_scale", x),
        parameter_at(p, "accel_misalignment", x),
        parameter_at(p, "accel_bias", x),
    )
    gyro = gyro_raw(
        w,
        parameter_at(p, "gyro_scale", x),
        parameter_at(p, "gyro_misalignment", x),
        parameter_at(p, "gyro_bias", x),
    )
    accel += np.column_stack([white(rng, n, float(p["accel_N"]), fs) for _ in range(3)])
    gyro += np.column_stack([white(rng, n, float(p["gyro_N"]), fs) for _ in range(3)])
    measured = temp + rng.standard_normal(n) * float(p["temperature_noise"])
    ends = [s / fs for s in np.cumsum([len(part) for part in f_parts])]
    soaks = []
    for begin, end in zip(sessions, ends, strict=True):
        inside = (t_s >= begin) & (t_s < end)
        soaks.append({"session_s": [begin, end], "temperature": float(temp[inside].mean())})
    out = make_table(
        sample_times(p["t0_s"], n, fs),
        gyro=gyro,
        accel=accel,
        temperature=measured,
        metadata={"source": "imupipe simulate thermal_soak", "format": "simulated"},
    )
    truth_out = {
        "tref": float(p["tref"]),
        "levels": levels,
        "soaks": soaks,
        "gravity": float(p["gravity"]),
        **{
            s: {name: {"p0": p[f"{s}_{name}"], "tc": p[f"{s}_{name}_tc"]} for name in names}
            for s, names in PARAMETERS.items()
        },
    }
    return out, truth_out
