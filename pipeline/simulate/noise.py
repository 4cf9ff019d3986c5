"""Noise processes of the IEEE/Kalibr IMU model, in continuous-time SI parameters.

- white noise of density ``N`` (unit/sqrt(Hz)): discrete std ``N * sqrt(fs)``
- random walk of the bias with density ``K`` (unit/s/sqrt(Hz)): steps of std ``K / sqrt(fs)``
- bias instability ``B`` (unit): flicker noise of one-sided PSD ``B^2 / (2 pi f)``, approximated
  by a sum of first-order Gauss-Markov processes with correlation times spaced by a factor ``r``
  (each of variance ``B^2 ln(r) / pi``), spanning ``tc_min`` .. ``tc_max``; its Allan deviation
  is flat at ``B * sqrt(2 ln 2 / pi)`` (0.664 B) between those times.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter


def white(rng: np.random.Generator, n: int, density: float, fs: float) -> np.ndarray:
    return rng.standard_normal(n) * (density * np.sqrt(fs))


def random_walk(rng: np.random.Generator, n: int, density: float, fs: float) -> np.ndarray:
    if density == 0:
        return np.zeros(n)
    return np.cumsum(rng.standard_normal(n) * (density / np.sqrt(fs)))


def flicker(
    rng: np.random.Generator,
    n: int,
    b: float,
    fs: float,
    tc_min: float = 0.1,
    tc_max: float | None = None,
    ratio: float = 10 ** (1 / 3),
) -> np.ndarray:
    """Bias instability ``b`` as a sum of Gauss-Markov processes (see the module docstring)."""
    if b == 0:
        return np.zeros(n)
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
