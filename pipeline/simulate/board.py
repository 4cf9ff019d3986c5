"""Scenario ``board``: a PX4 flight controller with several IMUs (and a barometer) warming up
at rest, logged as PX4 v1.11 logs its raw sensor topics (written only as ``.ulg``).

This is the log of PX4's thermal calibration procedure (PX4-Autopilot
``Tools/process_sensor_caldata.py``: cold-soaked board, powered and left still while it warms):
IMU ``i`` (``sensor_gyro`` and ``sensor_accel`` instance ``i``, both with device id
``device_ids[i]``) has its own temperature, a first-order warm-up from ``t_start`` to
``t_end[i]`` with time constant ``tau_s[i]``::

    T_i(t) = t_end[i] - (t_end[i] - t_start) exp(-t / tau_s[i])

and its own thermal bias, per axis, with ``x = T_i - tref`` (degC)::

    gyro_i  = gyro_poly[i] (x) + white noise of density gyro_N                     rad/s
    accel_i = [0, 0, -gravity] + accel_poly[i] (x) + white noise of density accel_N   m/s^2

(``<sensor>_poly[i]`` = [[c0, c1, c2, c3] per axis]; PX4's body frame is forward-right-down,
so a level board reads ``-gravity`` on z.) The barometer (``sensor_baro`` instance 0, with
``baro``) reads ``pressure + baro_poly(T_b - tref)`` Pa (``baro_poly`` [c0 .. c5], the known
thermal pressure error that PX4's ``TC_B*`` compensate) plus white noise of std ``baro_noise``
Pa, at its own temperature ``T_b`` (the first IMU's warm-up plus ``baro_offset`` degC), written
in hPa (mbar) as PX4 v1.11 does. Magnetometer ``j`` (``sensor_mag`` instance ``j``, one per
``mag_device_ids``; none by default), held in one orientation as in a thermal chamber, reads
``mag_field + mag_poly[j](T_m - tref)`` tesla (``mag_field`` the Earth's field in its frame,
``mag_poly[j]`` its known thermal offset, cubic per axis as ``gyro_poly``) plus white noise of
std ``mag_noise`` T, at ``mag_rate_hz``, at its own temperature ``T_m`` (the first IMU's warm-up
plus ``mag_offset[j]`` degC), written in gauss as PX4 does. Every temperature carries white
noise of std ``temperature_noise``. Stamps are
microseconds since boot from ``boot_s``; gyro and accel of one IMU share their
``timestamp_sample`` (PX4's FIFO drivers stamp both alike).

The log's parameters at start are ``CAL_ACCn_ID``/``CAL_GYROn_ID`` = ``device_ids[n]`` (in
``cal_order``: ``cal_order[n]`` is the IMU in slot ``n``), ``CAL_ACCn_*SCALE`` =
``accel_scale[n]`` (a previous accelerometer calibration that an export must not erase),
``CAL_MAGj_ID`` = ``mag_device_ids[j]``, ``TC_*_ENABLE = 0``, ``SENS_BOARD_ROT = 0``, plus
``parameters``.

Truth: per IMU (``imus``): ``device_id``, ``instance``, ``gyro_poly``, ``accel_poly``,
``temperature_range``; ``tref``; ``baro`` (``device_id``, ``poly``, ``temperature_range``) when
written; ``mags`` (per magnetometer ``device_id``, ``instance``, ``poly``, ``field``,
``temperature_range``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.simulate.noise import white
from imupipe.pipeline.writers.ulog import Topic, UlogData

WRITES = (".ulg",)
"""The only format a board is written in (several devices: a ULog's topic instances)."""

DEFAULTS: dict[str, Any] = {
    "rate_hz": 20.0,
    "duration_s": 2700.0,
    "boot_s": 5.0,
    "device_ids": [2424842, 3670050],
    "cal_order": None,
    "t_start": 5.0,
    "t_end": [48.0, 52.0],
    "tau_s": [700.0, 900.0],
    "tref": 25.0,
    "gravity": 9.80665,
    "gyro_poly": [
        [
            [2.0e-3, 1.5e-4, -2.0e-6, -3.0e-8],
            [-1.0e-3, -1.0e-4, 3.0e-6, 2.0e-8],
            [5.0e-4, 8.0e-5, 1.0e-6, -4.0e-8],
        ],
        [
            [-4.0e-3, -6.0e-5, 1.0e-6, 1.0e-8],
            [3.0e-3, 1.2e-4, -1.5e-6, -2.0e-8],
            [1.0e-3, -9.0e-5, 2.0e-6, 3.0e-8],
        ],
    ],
    "accel_poly": [
        [
            [0.05, 1.0e-3, -1.5e-5, -2.0e-7],
            [-0.03, -8.0e-4, 2.0e-5, 1.0e-7],
            [0.08, 1.2e-3, 1.0e-5, -1.5e-7],
        ],
        [
            [-0.06, 6.0e-4, 1.0e-5, 1.0e-7],
            [0.04, -1.0e-3, -1.0e-5, 2.0e-7],
            [-0.02, 9.0e-4, -2.0e-5, -1.0e-7],
        ],
    ],
    "gyro_N": 7.0e-5,
    "accel_N": 1.0e-3,
    "temperature_noise": 0.02,
    "accel_scale": [[1.0, 1.0, 0.975], [0.998, 0.987, 0.9795]],
    "baro": True,
    "baro_device_id": 6620441,
    "baro_rate_hz": 10.0,
    "baro_offset": -3.0,
    "pressure": 101325.0,
    "baro_poly": [0.0, 4.0, -0.05, 1.0e-3, 0.0, 0.0],
    "baro_noise": 1.0,
    "mag_device_ids": [],
    "mag_rate_hz": 10.0,
    "mag_field": [2.0e-5, 3.0e-6, 4.5e-5],
    "mag_poly": [
        [
            [0.0, 3.0e-8, 4.0e-10, -1.0e-11],
            [0.0, -2.0e-8, 2.0e-10, 0.0],
            [0.0, 5.0e-8, -3.0e-10, 0.0],
        ],
        [[0.0, -4.0e-8, 0.0, 1.0e-11], [0.0, 1.0e-8, 3.0e-10, 0.0], [0.0, 2.0e-8, 0.0, -1.0e-11]],
    ],
    "mag_noise": 1.0e-7,
    "mag_offset": [1.0, -2.0],
    "parameters": {},
}


def warm_up(t_s: np.ndarray, t_start: float, t_end: float, tau_s: float) -> np.ndarray:
    """The board temperature, degC, of a first-order warm-up (module docstring)."""
    return t_end - (t_end - t_start) * np.exp(-t_s / tau_s)


def _poly3(coefs: Any, x: np.ndarray) -> np.ndarray:
    c = np.asarray(coefs, dtype=np.float64).reshape(3, 4)
    return (x[:, None] ** np.arange(4)) @ c.T


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[UlogData, dict[str, Any]]:
    ids = [int(i) for i in p["device_ids"]]
    k = len(ids)
    per_imu = ("t_end", "tau_s", "gyro_poly", "accel_poly", "accel_scale")
    if not 1 <= k <= 4 or any(len(p[key]) != k for key in per_imu):
        raise ConfigError(
            f"board scenario: 1 to 4 device_ids, and one entry each in {', '.join(per_imu)}"
        )
    order = list(range(k)) if p["cal_order"] is None else [int(i) for i in p["cal_order"]]
    if sorted(order) != list(range(k)):
        raise ConfigError("board scenario: cal_order must list every IMU once")
    fs, duration = float(p["rate_hz"]), float(p["duration_s"])
    t_s = np.arange(int(duration * fs) + 1) / fs
    n = len(t_s)
    boot_us = int(round(float(p["boot_s"]) * 1e6))
    stamp = boot_us + np.round(t_s * 1e6).astype(np.int64)
    tref = float(p["tref"])
    topics: list[Topic] = []
    truth_imus = []
    for i, dev in enumerate(ids):
        temp = warm_up(t_s, float(p["t_start"]), float(p["t_end"][i]), float(p["tau_s"][i]))
        measured = temp + rng.standard_normal(n) * float(p["temperature_noise"])
        x = temp - tref
        gyro = _poly3(p["gyro_poly"][i], x)
        accel = _poly3(p["accel_poly"][i], x) + [0.0, 0.0, -float(p["gravity"])]
        gyro += np.column_stack([white(rng, n, float(p["gyro_N"]), fs) for _ in range(3)])
        accel += np.column_stack([white(rng, n, float(p["accel_N"]), fs) for _ in range(3)])
        sample = stamp + 200 * i  # the instances' drivers run at different instants
        for name, values in (("sensor_gyro", gyro), ("sensor_accel", accel)):
            data = {"timestamp": sample + 50, "timestamp_sample": sample}
            data |= {"device_id": np.full(n, dev), "temperature": measured}
            data |= {a: values[:, j] for j, a in enumerate("xyz")}
            topics.append(Topic(name, i, data))
        truth_imus.append(
            {
                "instance": i,
                "device_id": dev,
                "gyro_poly": p["gyro_poly"][i],
                "accel_poly": p["accel_poly"][i],
                "temperature_range": [float(measured.min()), float(measured.max())],
            }
        )
    params: dict[str, float | int] = {"SENS_BOARD_ROT": 0}
    for slot, i in enumerate(order):
        params[f"CAL_ACC{slot}_ID"] = params[f"CAL_GYRO{slot}_ID"] = ids[i]
        for a, s in zip("XYZ", p["accel_scale"][i], strict=True):
            params[f"CAL_ACC{slot}_{a}SCALE"] = float(s)
    params |= {"TC_A_ENABLE": 0, "TC_G_ENABLE": 0, "TC_B_ENABLE": 0}
    truth: dict[str, Any] = {"tref": tref, "imus": truth_imus, "duration_s": float(t_s[-1])}
    if p["baro"]:
        bfs = float(p["baro_rate_hz"])
        tb = np.arange(int(duration * bfs) + 1) / bfs
        nb = len(tb)
        temp = warm_up(tb, float(p["t_start"]), float(p["t_end"][0]), float(p["tau_s"][0]))
        temp = temp + float(p["baro_offset"])
        poly = np.asarray(p["baro_poly"], dtype=np.float64)
        pa_ = float(p["pressure"]) + np.polynomial.polynomial.polyval(temp - tref, poly)
        pa_ = pa_ + rng.standard_normal(nb) * float(p["baro_noise"])
        bstamp = boot_us + np.round(tb * 1e6).astype(np.int64) + 300
        measured = temp + rng.standard_normal(nb) * float(p["temperature_noise"])
        data = {"timestamp": bstamp + 50, "timestamp_sample": bstamp}
        data |= {"device_id": np.full(nb, int(p["baro_device_id"])), "temperature": measured}
        data |= {"pressure": pa_ / 100.0}  # hPa, as PX4 v1.11 publishes
        topics.append(Topic("sensor_baro", 0, data))
        params["CAL_BARO0_ID"] = int(p["baro_device_id"])
        truth["baro"] = {
            "device_id": int(p["baro_device_id"]),
            "poly": p["baro_poly"],
            "temperature_range": [float(measured.min()), float(measured.max())],
        }
    mag_ids = [int(i) for i in p["mag_device_ids"]]
    if len(mag_ids) > min(len(p["mag_poly"]), len(p["mag_offset"]), 4):
        raise ConfigError(
            "board scenario: at most 4 mag_device_ids, each with its mag_poly and mag_offset"
        )
    truth["mags"] = []
    for j, dev in enumerate(mag_ids):
        mfs = float(p["mag_rate_hz"])
        tm_s = np.arange(int(duration * mfs) + 1) / mfs
        nm = len(tm_s)
        temp = warm_up(tm_s, float(p["t_start"]), float(p["t_end"][0]), float(p["tau_s"][0]))
        temp = temp + float(p["mag_offset"][j])
        field_t = np.asarray(p["mag_field"], dtype=np.float64) + _poly3(
            p["mag_poly"][j], temp - tref
        )
        field_t = field_t + rng.standard_normal((nm, 3)) * float(p["mag_noise"])
        measured = temp + rng.standard_normal(nm) * float(p["temperature_noise"])
        mstamp = boot_us + np.round(tm_s * 1e6).astype(np.int64) + 400 + 50 * j
        data = {"timestamp": mstamp + 50, "timestamp_sample": mstamp}
        data |= {"device_id": np.full(nm, dev), "temperature": measured}
        data |= {a: field_t[:, i] * 1e4 for i, a in enumerate("xyz")}  # gauss
        topics.append(Topic("sensor_mag", j, data))
        params[f"CAL_MAG{j}_ID"] = dev
        params["TC_M_ENABLE"] = 0
        truth["mags"].append(
            {
                "instance": j,
                "device_id": dev,
                "poly": p["mag_poly"][j],
                "field": list(p["mag_field"]),
                "temperature_range": [float(measured.min()), float(measured.max())],
            }
        )
    params |= dict(p["parameters"])
    info = {"sys_name": "PX4", "ver_hw": "IMUPIPE_SIMULATED_BOARD", "ver_sw_branch": "v1.11.2"}
    return UlogData(topics, params, info), truth
