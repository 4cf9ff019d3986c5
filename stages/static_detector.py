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
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.stages.errors import FitError

FLOOR_QUANTILE = 0.1
"""The quantile of the windowed variance taken as the noise floor: a calibration session is at
rest for far more than a tenth of its length, so this quantile falls among still windows."""


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


@dataclass(frozen=True)
class Poses:
    """Static intervals grouped into poses: consecutive intervals whose mean specific force
    points the same way (the IMU was disturbed, not turned) are one pose. ``group`` (m,) is the
    pose index of each interval (non-decreasing, consecutive)."""

    intervals: Intervals
    group: np.ndarray

    def __len__(self) -> int:
        return int(self.group[-1]) + 1 if len(self.group) else 0

    @property
    def start(self) -> np.ndarray:
        """(p,) first sample of each pose."""
        first = np.r_[True, self.group[1:] != self.group[:-1]]
        return self.intervals.start[first]

    @property
    def stop(self) -> np.ndarray:
        """(p,) one past the last sample of each pose."""
        last = np.r_[self.group[1:] != self.group[:-1], True]
        return self.intervals.stop[last]

    @property
    def lengths(self) -> np.ndarray:
        """(p,) static samples of each pose (the gaps between its intervals left out)."""
        return np.bincount(self.group, weights=self.intervals.lengths).astype(np.int64)

    def mask(self, n: int) -> np.ndarray:
        return self.intervals.mask(n)

    def means(self, values: np.ndarray) -> np.ndarray:
        """(p, k) mean of ``values`` (n, k) over the static samples of each pose."""
        sums = self.intervals.means(values) * self.intervals.lengths[:, None]
        out = np.zeros((len(self), sums.shape[1]))
        np.add.at(out, self.group, sums)
        return out / self.lengths[:, None]


def sample_rate(t_ns: np.ndarray) -> float:
    """Mean sample rate (Hz) from first and last stamp (robust to quantised timestamps)."""
    span = float(t_ns[-1] - t_ns[0]) * 1e-9
    if len(t_ns) < 2 or span <= 0:
        raise FitError("cannot get a sample rate: fewer than 2 distinct timestamps")
    return (len(t_ns) - 1) / span


def sample_clock(t_ns: np.ndarray) -> tuple[np.ndarray, str | None]:
    """Seconds since the first sample for integrating between samples, and a note when the
    stamps had to be regularised: stamps that repeat because they were printed coarser than the
    sample period (e.g. to 10 ms at 200 Hz) are replaced by the least-squares line through
    them, provided no step exceeds the quantum (the most common non-zero step: no gap) and
    every stamp lies within one quantum of the line. Otherwise the stamps are used as they are."""
    t_s = (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    steps = np.diff(t_s)
    if len(steps) < 2 or bool(np.all(steps > 0)):
        return t_s, None
    positive = steps[steps > 0]
    if len(positive) == 0:
        return t_s, None
    values, counts = np.unique(np.round(positive, 9), return_counts=True)
    quantum = float(values[np.argmax(counts)])
    index = np.arange(len(t_s), dtype=np.float64)
    slope, intercept = np.polyfit(index, t_s, 1)
    line = intercept + slope * index
    if steps.max() > 1.01 * quantum or np.abs(t_s - line).max() > quantum or not slope > 0:
        return t_s, None
    repeated = int(np.count_nonzero(steps <= 0))
    return line - line[0], (
        f"{repeated} of {len(steps)} time steps are zero (stamps quantised to "
        f"{quantum * 1e3:.3g} ms at {1 / slope:.4g} Hz): integrated on the least-squares line "
        "through the stamps"
    )


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


def dilate(mask: np.ndarray, half: int) -> np.ndarray:
    """``mask`` widened by ``half`` samples on each side of every True run (a sample is True
    when any sample within ``half`` of it is)."""
    count = np.cumsum(np.r_[0, mask.astype(np.int64)])
    n = len(mask)
    idx = np.arange(n)
    hi = np.minimum(idx + half + 1, n)
    lo = np.maximum(idx - half, 0)
    return (count[hi] - count[lo]) > 0


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
    """The variance norm a threshold multiplies: the noise floor, or the initial period's."""
    min_samples: int
    source: str
    """How ``reference`` was obtained (one sentence for the results)."""
    half_window: int = 0
    """Samples each window reaches beyond its centre."""

    def detect(self, k: float, whole_windows: bool = False) -> Intervals:
        """The static intervals at threshold ``k``: the centres of the quiet windows (imu_tk's
        rule), or with ``whole_windows`` every sample of a quiet window (a hold of L s gives an
        interval of L s, not L minus one window: holds of 1 to 2 s survive a 1 s window)."""
        quiet = self.variance < k * self.reference
        if whole_windows and self.half_window > 0:
            quiet = dilate(quiet, self.half_window)
        return runs(quiet, self.min_samples)

    def describe(self, k: float) -> dict[str, Any]:
        """The threshold as the results report it."""
        return {
            "k": float(k),
            "threshold": float(k * self.reference),
            "reference_variance": self.reference,
            "reference": self.source,
        }


def make_detector(
    t_ns: np.ndarray,
    accel: np.ndarray,
    *,
    window_s: float = 1.0,
    init_static_s: float | None = None,
    min_interval_s: float = 1.0,
    floor_quantile: float = FLOOR_QUANTILE,
) -> Detector:
    """Prepare the detection on ``accel`` (n, 3) at ``t_ns`` (see the module docstring): the
    reference is the noise floor of the log itself, or, with ``init_static_s``, the variance of
    that initial period (imu_tk's rule, which needs the log to start at rest)."""
    rate = sample_rate(t_ns)
    window = max(int(round(window_s * rate)), 3)
    variance = moving_variance_norm(accel, window)
    if init_static_s is None:
        finite = variance[np.isfinite(variance)]
        if len(finite) == 0:
            raise FitError(
                f"the log holds {len(accel)} samples, fewer than one {window_s} s window"
            )
        reference = float(np.quantile(finite, floor_quantile))
        source = (
            f"noise floor: the {floor_quantile:.0%} quantile of the {window_s:g} s windowed "
            "accelerometer variance over the whole log"
        )
    else:
        init = (t_ns - t_ns[0]) * 1e-9 <= init_static_s
        if init.sum() < window:
            raise FitError(
                f"the initial static period ({init_static_s} s) holds {int(init.sum())} "
                f"samples, fewer than one {window_s} s window"
            )
        reference = float(np.linalg.norm(accel[init].var(axis=0, ddof=1)))
        source = f"variance of the first init_static_s = {init_static_s:g} s (imu_tk's rule)"
    if not reference > 0:
        raise FitError(
            "the accelerometer does not vary at all where it is still (quantised to a constant?): "
            "no noise floor to set the static threshold"
        )
    return Detector(
        variance,
        reference,
        int(round(min_interval_s * rate)),
        source,
        half_window=window // 2,
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
