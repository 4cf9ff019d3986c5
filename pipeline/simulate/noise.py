"""Noise processes of the IEEE Std 952 / Kalibr IMU model, in continuous-time SI parameters.

Each process's Allan variance is the matching term of
``sigma^2(tau) = 3 Q^2/tau^2 + N^2/tau + B^2 2ln2/pi + K^2 tau/3 + R^2 tau^2/2``
(IEEE 952 Annex C, with the two-sided rate PSD S(f) and ``sigma^2 = 4 int S(f) sin^4(pi f tau) /
(pi f tau)^2 df``):

- white noise of density ``N`` (unit/sqrt(Hz), S = N^2): discrete std ``N * sqrt(fs)``
- random walk of the bias with density ``K`` (unit/s/sqrt(Hz), S = K^2 / (2 pi f)^2): steps of
  std ``K / sqrt(fs)``
- bias instability ``B`` (unit): flicker noise, S = B^2 / (2 pi f), approximated by a sum of
  first-order Gauss-Markov processes whose correlation times are spaced by a factor ``r``
  over ``tc_min`` .. ``tc_max``: a GM process of variance s^2 and time T has S = 2 s^2 T /
  (1 + (2 pi f T)^2); summed over log-spaced T (dT / (T ln r) per process) that is
  s^2 / (2 f ln r), hence ``s^2 = B^2 ln(r) / pi``. Its Allan deviation is flat at
  ``B * sqrt(2 ln 2 / pi)`` (0.664 B) for taus well inside ``tc_min`` .. ``tc_max``.
- quantisation ``Q`` (unit*s, e.g. rad): the integrated signal (angle) carries white noise of
  std ``Q`` (uniform quantisation of step q has Q = q / sqrt(12)); the rate is its difference
  times fs.
- rate ramp ``R`` (unit/s): the deterministic drift ``R * t``.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter


def white(rng: np.random.Generator, n: int, density: float, fs: float) -> np.ndarray:
    """White rate noise of density ``density`` (unit/sqrt(Hz)) at ``fs`` Hz."""
    return rng.standard_normal(n) * (density * np.sqrt(fs))


def random_walk(rng: np.random.Generator, n: int, density: float, fs: float) -> np.ndarray:
    """Random walk of the bias with density ``density`` (unit/s/sqrt(Hz))."""
    if density == 0:
        return np.zeros(n)
    return np.cumsum(rng.standard_normal(n) * (density / np.sqrt(fs)))


def quantization(rng: np.random.Generator, n: int, q: float, fs: float) -> np.ndarray:
    """Quantisation noise ``q`` (unit*s): the difference of white angle noise of std q, * fs."""
    if q == 0:
        return np.zeros(n)
    return np.diff(rng.standard_normal(n + 1) * q) * fs


def rate_ramp(n: int, r: float, fs: float) -> np.ndarray:
    """The ramp ``r * t`` (unit/s * s) over n samples at fs Hz, t from 0."""
    return r * (np.arange(n) / fs)


def flicker(
    rng: np.random.Generator,
    n: int,
    b: float,
    fs: float,
    tc_min: float | None = None,
    tc_max: float | None = None,
    ratio: float = 10 ** (1 / 3),
) -> np.ndarray:
    """Bias instability ``b`` as a sum of Gauss-Markov processes (see the module docstring);
    correlation times from ``tc_min`` (default one sample) to ``tc_max`` (default the length)."""
    if b == 0:
        return np.zeros(n)
    tc_min = tc_min or 1.0 / fs
    tc_max = tc_max or max(n / fs, tc_min * ratio)
    tcs = tc_min * ratio ** np.arange(int(np.ceil(np.log(tc_max / tc_min) / np.log(ratio))) + 1)
    sigma = b * np.sqrt(np.log(ratio) / np.pi)
    out = np.zeros(n)
    for tc in tcs:
        a = np.exp(-1.0 / (fs * tc))
        drive = rng.standard_normal(n) * (sigma * np.sqrt(1 - a * a))
        x0 = rng.standard_normal() * sigma
        out += lfilter([1.0], [1.0, -a], drive, zi=[a * x0])[0]
    return out
