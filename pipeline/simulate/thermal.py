"""Scenario ``thermal``: a static IMU in a temperature chamber, cycled between ``t_min`` and
``t_max`` (the ramp method of "MEMS 惯性测量组件的温度误差补偿模型研究"; the full-temperature
cycles of the gyro patent "陀螺仪的温度标定补偿方法、装置、设备及介质").

Chamber (ambient) temperature ``Ta(t)``: piecewise linear. It starts held at ``t_min`` for
``hold_s``; then each cycle ``i`` heats to ``t_max`` at ``heating_rates[i]`` degC/min, holds
``hold_s``, cools to ``t_min`` at ``cooling_rates[i]`` degC/min (default: the heating rates) and
holds ``hold_s``. With ``soak_step`` (degC) the ramps pause for ``hold_s`` every ``soak_step``
degrees (the soak method). The device temperature ``T`` (what the temperature sensor reads)
follows the chamber through a first-order lag, ``dT/dt = (Ta - T) / lag_s``, integrated exactly
for the piecewise-linear ``Ta``. With ``element_lag_s`` > 0 the sensing element's temperature
``Te`` lags ``T`` in turn, ``dTe/dt = (T - Te) / element_lag_s`` (the gyro patent's mechanism:
the sensing core lags the board's temperature sensor); else ``Te = T``.

Sensor error, per axis of gyro (rad/s) and accel (m/s^2), with ``x = Te - poly_tref`` (degC) and
``r = dTe/dt`` (degC/s, its exact rate)::

    bias = c0 + c1 x + c2 x^2 + c3 x^3 + k r

(``<sensor>_poly`` = [[c0, c1, c2, c3] per axis], ``<sensor>_rate_coef`` = [k per axis]: a rate
term makes heating and cooling read differently at the same temperature, the hysteresis the gyro
patent fits with ``k_dt``) plus white noise of density ``<sensor>_N``. The IMU is at rest, z up: true rate 0, true
specific force ``[0, 0, gravity]``. The temperature sensor reads ``T`` plus white noise of std
``temperature_noise`` degC at ``temperature_rate_hz`` (null: every IMU sample); the
``ambient_temperature`` column holds ``Ta`` (when ``ambient`` is true).

Turntable (the gyro patent's scale-factor runs), with ``turntable_rate`` (deg/s): at the end of every ``turntable_period_s``
the table turns about the IMU's z axis at +rate for ``turntable_s`` seconds, then at -rate for
as long (instantaneous switches; the accelerometer, at the centre, feels nothing). The gyro then
reads ``bias + sf * true`` with the scale factor ``sf = 1 + s1 x + s2 x^2`` per axis
(``gyro_scale_poly`` = [[s1, s2] per axis]).

Truth: ``gyro`` and ``accel`` with ``poly`` (coefficients about ``poly_tref``), ``rate_coef``,
``N`` and ``reference`` (the true output when still); gyro ``scale_poly``; ``poly_tref``;
``temperature_range`` (device T); ``element_lag_s``; ``duration_s``; ``turntable_rate`` (rad/s or
null).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
from scipy.signal import lfilter

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.noise import white
from imupipe.readers.table import make_table

DEFAULTS: dict[str, Any] = {
    "rate_hz": 10.0,
    "t0_s": 1_700_000_000.0,
    "t_min": -40.0,
    "t_max": 80.0,
    "heating_rates": [1.0, 0.5],
    "cooling_rates": None,
    "hold_s": 1200.0,
    "soak_step": None,
    "lag_s": 300.0,
    "element_lag_s": 0.0,
    "gravity": 9.80665,
    "poly_tref": 25.0,
    "gyro_poly": [
        [2.0e-3, 1.5e-4, -2.0e-6, -3.0e-8],
        [-1.0e-3, -1.0e-4, 3.0e-6, 2.0e-8],
        [5.0e-4, 8.0e-5, 1.0e-6, -4.0e-8],
    ],
    "gyro_rate_coef": [0.012, -0.008, 0.010],
    "gyro_N": [2.4e-4, 2.4e-4, 2.4e-4],
    "accel_poly": [
        [0.05, 1.0e-3, -1.5e-5, -2.0e-7],
        [-0.03, -8.0e-4, 2.0e-5, 1.0e-7],
        [0.08, 1.2e-3, 1.0e-5, -1.5e-7],
    ],
    "accel_rate_coef": [0.10, -0.08, 0.12],
    "accel_N": [1.5e-3, 1.5e-3, 1.5e-3],
    "temperature_noise": 0.02,
    "temperature_rate_hz": None,
    "ambient": True,
    "turntable_rate": None,
    "turntable_period_s": 900.0,
    "turntable_s": 60.0,
    "gyro_scale_poly": [[2.0e-4, -1.0e-6], [-1.0e-4, 2.0e-6], [3.0e-4, 1.0e-6]],
}


def chamber_keypoints(p: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(time s, chamber degC) corners of the piecewise-linear chamber program."""
    lo, hi = float(p["t_min"]), float(p["t_max"])
    heating = [float(r) for r in p["heating_rates"]]
    cooling = [float(r) for r in (p["cooling_rates"] or heating)]
    if hi <= lo or not heating or len(cooling) != len(heating) or min(heating + cooling) <= 0:
        raise ConfigError(
            "thermal scenario: need t_max > t_min and positive heating_rates/cooling_rates "
            "of equal length (degC/min)"
        )
    hold = float(p["hold_s"])
    step = p["soak_step"]
    times, temps = [0.0, hold], [lo, lo]

    def ramp(target: float, rate_per_min: float) -> None:
        start = temps[-1]
        stops = [target]
        if step:
            direction = np.sign(target - start)
            stops = list(np.arange(start, target, direction * float(step))[1:]) + [target]
        for stop in stops:
            times.append(times[-1] + abs(stop - temps[-1]) / (rate_per_min / 60.0))
            temps.append(float(stop))
            times.append(times[-1] + hold)
            temps.append(float(stop))

    for up, down in zip(heating, cooling, strict=True):
        ramp(hi, up)
        ramp(lo, down)
    return np.array(times), np.array(temps)


def lagged(t_s: np.ndarray, ambient: np.ndarray, lag_s: float) -> np.ndarray:
    """Exact samples of ``dT/dt = (Ta - T)/lag_s`` for ``Ta`` linear between (even) samples,
    starting in equilibrium."""
    if lag_s <= 0:
        return ambient.copy()
    h = float(t_s[1] - t_s[0])
    a = np.exp(-h / lag_s)
    c = lag_s * (1.0 - a) / h
    b = [1.0 - c, c - a]
    zi = np.array([(a + b[1]) * ambient[0]])  # steady state: T = Ta[0] before the first sample
    return lfilter(b, [1.0, -a], ambient, zi=zi)[0]


def _bias(
    poly: list[list[float]], rate_coef: list[float], x: np.ndarray, r: np.ndarray
) -> np.ndarray:
    coefs = np.asarray(poly, dtype=np.float64).reshape(3, 4)
    powers = np.column_stack([np.ones_like(x), x, x * x, x * x * x])
    return powers @ coefs.T + np.outer(r, np.asarray(rate_coef, dtype=np.float64))


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    fs = float(p["rate_hz"])
    key_t, key_temp = chamber_keypoints(p)
    n = int(np.floor(key_t[-1] * fs)) + 1
    t_s = np.arange(n) / fs
    ambient = np.interp(t_s, key_t, key_temp)
    lag = float(p["lag_s"])
    temp = lagged(t_s, ambient, lag)
    rate = (ambient - temp) / lag if lag > 0 else np.gradient(ambient, t_s)
    element_lag = float(p["element_lag_s"])
    element = temp
    if element_lag > 0:
        element = lagged(t_s, temp, element_lag)
        rate = (temp - element) / element_lag
    x = element - float(p["poly_tref"])
    gyro_ref = np.zeros(3)
    accel_ref = np.array([0.0, 0.0, float(p["gravity"])])
    gyro = gyro_ref + _bias(p["gyro_poly"], p["gyro_rate_coef"], x, rate)
    table_rate = None
    if p["turntable_rate"]:
        table_rate = np.deg2rad(float(p["turntable_rate"]))
        period, spin = float(p["turntable_period_s"]), float(p["turntable_s"])
        phase = period - np.mod(t_s, period)  # seconds left in the period
        w = np.where(phase <= spin, -table_rate, np.where(phase <= 2 * spin, table_rate, 0.0))
        sf = 1.0 + np.column_stack([x, x * x]) @ np.asarray(p["gyro_scale_poly"], float).T
        gyro[:, 2] += sf[:, 2] * w
    accel = accel_ref + _bias(p["accel_poly"], p["accel_rate_coef"], x, rate)
    for i in range(3):
        gyro[:, i] += white(rng, n, float(p["gyro_N"][i]), fs)
        accel[:, i] += white(rng, n, float(p["accel_N"][i]), fs)
    measured_t = temp + rng.standard_normal(n) * float(p["temperature_noise"])
    valid = {"imu": np.ones(n, dtype=bool), "temperature": np.ones(n, dtype=bool)}
    if p["temperature_rate_hz"]:
        every = max(1, int(round(fs / float(p["temperature_rate_hz"]))))
        valid["temperature"] = np.arange(n) % every == 0
    t_ns = sample_times(p["t0_s"], n, fs)
    table = make_table(
        t_ns,
        gyro=gyro,
        accel=accel,
        temperature=measured_t,
        valid=valid,
        extra={"ambient_temperature": ambient} if p["ambient"] else None,
        metadata={"source": "imupipe simulate thermal", "format": "simulated"},
    )
    truth = {
        "poly_tref": float(p["poly_tref"]),
        "temperature_range": [float(temp.min()), float(temp.max())],
        "element_lag_s": element_lag,
        "duration_s": float(t_s[-1]),
        "turntable_rate": table_rate,
        "gyro": {
            "poly": p["gyro_poly"],
            "rate_coef": p["gyro_rate_coef"],
            "N": p["gyro_N"],
            "reference": gyro_ref.tolist(),
            "scale_poly": p["gyro_scale_poly"],
        },
        "accel": {
            "poly": p["accel_poly"],
            "rate_coef": p["accel_rate_coef"],
            "N": p["accel_N"],
            "reference": accel_ref.tolist(),
        },
    }
    return table, truth
