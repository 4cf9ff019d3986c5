"""Static-interval detection for multi-position calibration (imu_tk, Tedaldi et al. ICRA 2014).

Model: a sample is *static* when the norm of the per-axis variance of the accelerometer over a
centred window of ``window_s`` seconds is below ``k`` times the norm of the per-axis variance of
the initial static period (the first ``init_static_s`` seconds). Runs of static samples at least
``min_interval_s`` long are the static intervals. Samples within half a window of either end of
the log are never static (their window is incomplete).

``k`` is chosen automatically (:func:`choose_threshold`): every candidate is tried and scored by a
caller-given function (the accelerometer stage uses the residual of a 9-parameter fit per degree
of freedom, i.e. the *mean* residual over the intervals, not imu_tk's total cost, which favours
thresholds that find few intervals).

Also here: :func:`segment_mask`, the rows of a labelled or time-bounded segment (``"x_rot"`` or
``[start_s, end_s]``) used by the Ferraris, turntable and rotation methods.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from imupipe.stages.errors import FitError


@dataclass(frozen=True)
class Intervals:
    """Static intervals as sample-index ranges ``[start, stop)`` (each (m,) int64)."""

    start: np.ndarray
    stop: np.ndarray

    def __len__(self) -> int:
        return int(self.start.shape[0])

    @property
    def lengths(self) -> np.ndarray:
        return self.stop - self.start

    def mask(self, n: int) -> np.ndarray:
        """Boolean mask (n,) of the samples inside any interval."""
        edges = np.zeros(n + 1, dtype=np.int64)
        np.add.at(edges, self.start, 1)
        np.add.at(edges, self.stop, -1)
        return np.cumsum(edges[:-1]) > 0

    def labels(self, n: int) -> np.ndarray:
        """(n,) interval index of each sample, -1 outside every interval."""
        out = np.full(n, -1, dtype=np.int64)
        inside = self.mask(n)
        out[inside] = np.repeat(np.arange(len(self)), self.lengths)
        return out

    def means(self, values: np.ndarray) -> np.ndarray:
        """(m, k) mean of ``values`` (n, k) over each interval."""
        values = np.asarray(values, dtype=np.float64)
        csum = np.vstack([np.zeros((1, values.shape[1])), np.cumsum(values, axis=0)])
        return (csum[self.stop] - csum[self.start]) / self.lengths[:, None]


def sample_rate(t_ns: np.ndarray) -> float:
    """Mean sample rate (Hz) from first and last stamp (robust to quantised timestamps)."""
    span = float(t_ns[-1] - t_ns[0]) * 1e-9
    if len(t_ns) < 2 or span <= 0:
        raise FitError("cannot get a sample rate: fewer than 2 distinct timestamps")
    return (len(t_ns) - 1) / span


def moving_variance_norm(values: np.ndarray, window: int) -> np.ndarray:
    """(n,) norm of the per-axis variance over a centred window of ``window`` samples
    (odd; ``inf`` where the window does not fit)."""
    n = values.shape[0]
    half = window // 2
    window = 2 * half + 1
    out = np.full(n, np.inf)
    if n < window:
        return out
    x = values - values.mean(axis=0)
    c1 = np.vstack([np.zeros((1, 3)), np.cumsum(x, axis=0)])
    c2 = np.vstack([np.zeros((1, 3)), np.cumsum(x * x, axis=0)])
    s1 = c1[window:] - c1[:-window]
    s2 = c2[window:] - c2[:-window]
    var = np.maximum(s2 / window - (s1 / window) ** 2, 0.0) * (window / (window - 1))
    out[half : n - half] = np.linalg.norm(var, axis=1)
    return out


def runs(mask: np.ndarray, min_length: int) -> Intervals:
    """The runs of True in ``mask`` at least ``min_length`` long."""
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    start = np.flatnonzero(edges == 1)
    stop = np.flatnonzero(edges == -1)
    keep = (stop - start) >= max(int(min_length), 1)
    return Intervals(start[keep].astype(np.int64), stop[keep].astype(np.int64))


@dataclass(frozen=True)
class Detector:
    """The threshold-independent part of the detection: windowed variance and its reference."""

    variance: np.ndarray
    """(n,) windowed variance norm, (m/s^2)^2 (or counts^2)."""
    reference: float
    """Variance norm of the initial static period."""
    min_samples: int

    def detect(self, k: float) -> Intervals:
        return runs(self.variance < k * self.reference, self.min_samples)


def make_detector(
    t_ns: np.ndarray,
    accel: np.ndarray,
    *,
    window_s: float = 1.0,
    init_static_s: float = 30.0,
    min_interval_s: float = 1.0,
) -> Detector:
    """Prepare the detection on ``accel`` (n, 3) at ``t_ns`` (see the module docstring)."""
    rate = sample_rate(t_ns)
    window = max(int(round(window_s * rate)), 3)
    t_s = (t_ns - t_ns[0]) * 1e-9
    init = t_s <= init_static_s
    if init.sum() < window:
        raise FitError(
            f"the initial static period ({init_static_s} s) holds {int(init.sum())} samples, "
            f"fewer than one {window_s} s window"
        )
    reference = float(np.linalg.norm(accel[init].var(axis=0, ddof=1)))
    if not reference > 0:
        raise FitError("the accelerometer does not vary at all in the initial static period")
    return Detector(
        moving_variance_norm(accel, window), reference, int(round(min_interval_s * rate))
    )


@dataclass(frozen=True)
class ThresholdChoice:
    k: float
    intervals: Intervals
    scores: dict[float, float | None]
    """Every candidate k -> its score (None: too few intervals or the fit failed)."""


def choose_threshold(
    detector: Detector,
    candidates: Sequence[float],
    score: Callable[[Intervals], float | None],
    min_intervals: int,
) -> ThresholdChoice:
    """The candidate ``k`` with the lowest ``score`` among those giving ``min_intervals`` or more
    intervals; ``FitError`` when none does."""
    scores: dict[float, float | None] = {}
    best: tuple[float, float, Intervals] | None = None
    counts = {}
    for k in candidates:
        intervals = detector.detect(k)
        counts[k] = len(intervals)
        value = score(intervals) if len(intervals) >= min_intervals else None
        scores[float(k)] = value
        if value is not None and np.isfinite(value) and (best is None or value < best[1]):
            best = (float(k), float(value), intervals)
    if best is None:
        found = ", ".join(f"k={k:g}: {c}" for k, c in counts.items())
        raise FitError(
            f"too few static intervals: need at least {min_intervals}, found {found} "
            "(hold the IMU still longer in more poses, or lower min_interval_s)"
        )
    return ThresholdChoice(best[0], best[2], scores)


def segment_mask(
    t_s: np.ndarray, labels: pa.ChunkedArray | None, where: str, segment: str | Sequence[float]
) -> np.ndarray:
    """Rows of a segment named by its label (``"x_rot"``, needs a ``label`` column) or by
    ``[start_s, end_s]`` seconds from the first sample. ``FitError`` naming ``where`` when empty."""
    if isinstance(segment, str):
        if labels is None:
            raise FitError(
                f"{where}: segment '{segment}' is a label but the input has no label column "
                "(set csv.label)"
            )
        mask = np.asarray(labels.to_numpy(zero_copy_only=False) == segment, dtype=bool)
    else:
        if len(segment) != 2 or not segment[1] > segment[0]:
            raise FitError(f"{where}: a segment is a label or [start_s, end_s] with end > start")
        mask = (t_s >= segment[0]) & (t_s <= segment[1])
    if not mask.any():
        raise FitError(f"{where}: segment {segment!r} holds no samples")
    return mask
