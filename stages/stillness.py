"""Is the IMU at rest? The motion check shared by the stages that need static data.

Over 1-second blocks: the largest departure of a 1 s gyro mean from the overall gyro mean
(rad/s), and the spread (max - min) of the 1 s means of the accelerometer norm (m/s^2). The data
is called static when the first is at most ``threshold`` and the second at most 0.05 g.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imupipe.stages.blocks import Blocks, block_means, block_starts

G0 = 9.80665
ACCEL_SPREAD_LIMIT = 0.05 * G0
"""m/s^2: the largest spread of 1 s accelerometer-norm means still called static."""


@dataclass(frozen=True)
class Stillness:
    """``gyro_1s``: the 1 s block means of the gyro; ``excursion`` (rad/s) and
    ``accel_spread`` (m/s^2) as in the module docstring."""

    gyro_1s: Blocks
    excursion: float
    accel_spread: float

    def static(self, threshold: float) -> bool:
        return self.excursion <= threshold and self.accel_spread <= ACCEL_SPREAD_LIMIT

    def describe(self, threshold: float) -> str:
        """One sentence for a refusal or a warning: what moved, against which limits."""
        return (
            f"1 s gyro means depart {self.excursion:.3g} rad/s from the mean (motion_threshold "
            f"{threshold:g} rad/s), accelerometer-norm 1 s means spread "
            f"{self.accel_spread:.3g} m/s^2 (limit {ACCEL_SPREAD_LIMIT:.3g} m/s^2)"
        )


def stillness(
    t_ns: np.ndarray,
    gyro: np.ndarray | Sequence[np.ndarray],
    accel: np.ndarray | Sequence[np.ndarray],
    *,
    increasing: bool = False,
    gyro_means: Sequence[float] | None = None,
) -> Stillness:
    """The motion figures of gyro rad/s and accel m/s^2 sampled at ``t_ns``: each (n, 3), or
    three columns (n,) (no copy made either way). ``increasing``: the caller has checked that
    time increases (the blocks are then found by bisection, :func:`block_starts`);
    ``gyro_means``: the three gyro columns' ``mean()``, when the caller has them."""
    gyro = list(gyro.T) if isinstance(gyro, np.ndarray) else list(gyro)
    accel = list(accel.T) if isinstance(accel, np.ndarray) else list(accel)
    starts = block_starts(t_ns, window_s=1.0, increasing=increasing)
    first = block_means(t_ns, gyro[0], starts=starts)
    if not len(first.counts):
        return Stillness(Blocks(first.t_ns, np.zeros((0, 3)), first.counts, starts), 0.0, 0.0)
    counts = first.counts
    means = np.column_stack([first.means] + [np.add.reduceat(c, starts) / counts for c in gyro[1:]])
    overall = [c.mean() for c in gyro] if gyro_means is None else gyro_means
    excursion = max(float(np.abs(means[:, k] - overall[k]).max()) for k in range(len(gyro)))
    with np.errstate(over="ignore"):  # a damaged value's square is inf: not static
        norm = np.multiply(accel[0], accel[0])
        square = np.empty_like(norm)
        for c in accel[1:]:
            np.multiply(c, c, out=square)
            norm += square
    np.sqrt(norm, out=norm)
    spread = float(np.ptp(np.add.reduceat(norm, starts) / counts))
    return Stillness(Blocks(first.t_ns, means, counts, starts), excursion, spread)
