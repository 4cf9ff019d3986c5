"""What the ``temperature`` stage may fit: the still samples, the held-out segments, the
orientations, and the held-out prediction that chooses the model and checks it.

- **Still samples** (:func:`still_samples`): the static-interval detector of the multi-position
  stages (:func:`imupipe.stages.static_detector.make_detector`, the windowed variance against the
  log's own noise floor) run on the accelerometer and on the gyroscope (on means of consecutive
  samples at about 50 Hz for faster logs); a sample is still where both are below ``k`` times
  their floor. Handling, taps and moves between soaks never enter the
  thermal fit: a block's bias is the mean of its still samples.
- **Segments** (:func:`segment_labels`): the runs of still blocks between handling (or between
  excluded blocks), merged in time order to at most :data:`MAX_SEGMENTS` of similar size; a log
  without such breaks is cut into :data:`DEFAULT_SEGMENTS` consecutive stretches of equal block
  count. Consecutive blocks of a slow ramp are not independent, so whole stretches are held out
  (leave-one-segment-out cross-validation), never single blocks.
- **Held-out prediction** (:func:`held_out`): each segment in turn is predicted by the model
  fitted on the others (temperatures clamped to the training range as the correction clamps
  them; rates extrapolated), and by the no-model baseline, the training blocks' weighted mean
  bias (a constant offset, i.e. no temperature compensation). The figure per axis is the
  weighted RMS of the prediction error over the held-out blocks whose temperature lies inside
  the training blocks' range (the final fit covers the whole range and the correction clamps
  beyond it, with a warning), in the sensor's SI unit.
- **What the correction leaves** (:meth:`HeldOut.remaining`): the held-out error is the
  calibration's error plus the noise of the block means; the noise variance of a block mean is
  ``(m1 - m2)^2 / 4`` from its two halves' means (correlated noise included), so the bias the
  correction leaves has the mean square ``D = rms^2 - noise``. Its 95 % interval, for another
  log like this one: the ``K`` segments' ``d_s = ms_s - noise_s`` scatter about ``D``; the
  estimate and a new log each carry ``var(d_s) / K``, so ``D`` lies within ``+- t(K - 1)
  sd(d_s) sqrt(2 / K)`` (Student's t, one degree of freedom per segment since the blocks inside
  a segment are correlated; its quantile ``1 - 0.025 / 3`` so that the three axes hold at once);
  the interval is the square root, ``[sqrt(D - h), sqrt(max(D, 0) + h)]`` (the lower end at
  least 0).

Reference: leave-one-group-out cross-validation for dependent data (Roberts et al., "Cross-
validation strategies for data with temporal, spatial, hierarchical, or phylogenetic structure",
Ecography 40, 2017).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats

from imupipe.stages.errors import FitError
from imupipe.stages.static_detector import make_detector

STILL_K = 10.0
"""A sample is still where the windowed variance is under this many times the noise floor."""
DETECT_HZ = 50.0
"""Logs faster than this are judged on means of consecutive samples at about this rate."""
STILL_WINDOW_SAMPLES = 10
"""The variance window is 1 s, or this many samples when the log is slower (1 Hz tags)."""
MIN_STILL_SHARE = 0.5
"""A block enters the fit when at least this share of its samples is still."""
DEFAULT_SEGMENTS = 5
MAX_SEGMENTS = 8
JOINT_AXES = 3
"""The interval holds on the three axes at once (Bonferroni: 1 - 0.05 / 3 on each)."""
ORIENTATION_DEG = 10.0
"""Still periods whose mean specific force differs in direction by more than this (deg) are
different orientations of the IMU."""


def still_samples(t_ns: np.ndarray, signals: list[np.ndarray], k: float) -> np.ndarray | None:
    """(n,) True where every signal in ``signals`` (each (n, 3), finite rows) is still; None
    when no signal has a noise floor to judge by (quantised to a constant: everything is still).
    Samples within half a window of the log's ends, or of a gap in the stamps, take the verdict of
    the nearest judged one (all of them, when no window is judged)."""
    if len(t_ns) < 3 or t_ns[-1] <= t_ns[0]:
        return None
    full_t = t_ns
    rate = (len(t_ns) - 1) / (float(t_ns[-1] - t_ns[0]) * 1e-9)
    window_s = max(1.0, STILL_WINDOW_SAMPLES / rate)
    # faster logs are judged on means of q samples (at most DETECT_HZ): handling is slow motion
    q = max(1, int(rate // DETECT_HZ))
    n = (len(t_ns) // q) * q
    if q > 1 and n >= 3 * q:
        t_ns = t_ns[:n:q]
        signals = [v[:n].reshape(-1, q, v.shape[1]).mean(axis=1) for v in signals]
    # windows across a gap in the stamps (a logger's bursts) mix two stretches: not judged
    steps = np.diff(t_ns)
    gap = np.r_[False, steps > max(2.0 * float(np.median(steps)), 0.25 * window_s * 1e9)]
    rate_judged = (len(t_ns) - 1) / (float(t_ns[-1] - t_ns[0]) * 1e-9)
    half = max(int(round(window_s * rate_judged)), 3) // 2
    gaps = np.r_[0, np.cumsum(gap)]
    i = np.arange(len(t_ns))
    across = gaps[np.minimum(i + half + 1, len(t_ns))] - gaps[np.maximum(i - half + 1, 0)] > 0
    still: np.ndarray | None = None
    for values in signals:
        try:
            detector = make_detector(t_ns, values, window_s=window_s, min_interval_s=0.0)
        except FitError:
            continue
        judged = np.isfinite(detector.variance) & ~across
        if not judged.any():
            continue
        ok = detector.variance < k * detector.reference
        idx = np.flatnonzero(judged)
        nearest = idx[np.clip(np.searchsorted(idx, np.arange(len(ok))), 0, len(idx) - 1)]
        ok = ok[nearest]
        still = ok if still is None else (still & ok)
    if still is not None and q > 1:
        full = np.repeat(still, q)
        still = np.r_[full, np.full(len(full_t) - len(full), full[-1])]
    return still


def segment_labels(keep: np.ndarray) -> np.ndarray:
    """(m,) segment index of each kept block (``keep``: the kept blocks' indices among every
    block of the log, increasing); see the module docstring."""
    m = len(keep)
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    runs = np.r_[0, np.cumsum(np.diff(keep) > 1)]
    n_runs = int(runs[-1]) + 1
    if n_runs < 3:
        target = min(DEFAULT_SEGMENTS, m)
        return np.minimum((np.arange(m) * target) // m, target - 1).astype(np.int64)
    if n_runs <= MAX_SEGMENTS:
        return runs.astype(np.int64)
    # merge consecutive runs into DEFAULT_SEGMENTS groups of similar block count
    size = np.bincount(runs)
    ends = np.cumsum(size)
    group = np.minimum((ends - size / 2) * DEFAULT_SEGMENTS // m, DEFAULT_SEGMENTS - 1)
    _, group = np.unique(group, return_inverse=True)
    return group[runs].astype(np.int64)


def orientation_spread(directions: np.ndarray) -> float:
    """The largest angle (deg) between the unit vectors ``directions`` (p, 3) and their mean."""
    if len(directions) < 2:
        return 0.0
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    mean = unit.mean(axis=0)
    mean /= np.linalg.norm(mean)
    return float(np.degrees(np.arccos(np.clip(unit @ mean, -1.0, 1.0))).max())


@dataclass
class HeldOut:
    """Per axis (SI): ``rms`` the model's held-out prediction error, ``baseline`` the no-model
    baseline's; ``segments`` the number held out in turn."""

    rms: np.ndarray
    baseline: np.ndarray
    segments: int
    blocks: int = 0
    """The held-out blocks the figures are taken over."""
    segment_ms: np.ndarray | None = None
    """(segments with such blocks, 3) the model's mean square error in each segment."""
    segment_noise: np.ndarray | None = None
    """(segments, 3) the mean noise variance of the block means in each segment."""
    noise: np.ndarray | None = None
    """(3,) the mean noise variance of the held-out block means."""

    def remaining(self, axis: int) -> tuple[float, list[float]]:
        """The RMS of the bias the correction leaves on another log like this one, noise of the
        block means taken out, and its 95 % interval (module docstring); NaN and ``[0, inf]``
        without the noise or from fewer than 2 segments."""
        if self.segment_ms is None or self.segment_noise is None or len(self.segment_ms) < 2:
            return float("nan"), [0.0, float("inf")]
        d = self.segment_ms[:, axis] - self.segment_noise[:, axis]
        if not np.isfinite(d).all():
            return float("nan"), [0.0, float("inf")]
        k = len(d)
        ms = float(self.rms[axis] ** 2 - self.noise[axis])
        q = 1.0 - 0.025 / JOINT_AXES
        half = float(stats.t.ppf(q, k - 1) * np.std(d, ddof=1) * np.sqrt(2.0 / k))
        return float(np.sqrt(max(ms, 0.0))), [
            float(np.sqrt(max(ms - half, 0.0))),
            float(np.sqrt(max(ms, 0.0) + half)),
        ]

    @property
    def ratio(self) -> np.ndarray:
        return self.rms / np.maximum(self.baseline, 1e-300)

    @property
    def score(self) -> float:
        """The geometric mean over axes of ``rms / baseline`` (lower is better)."""
        return float(np.exp(np.mean(np.log(np.maximum(self.ratio, 1e-300)))))


FitPredict = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``(train, test)`` boolean masks over the blocks -> (test blocks, 3) predicted bias."""


def held_out(
    fit_predict: FitPredict,
    bias: np.ndarray,
    w: np.ndarray,
    labels: np.ndarray,
    temp: np.ndarray,
    noise: np.ndarray | None = None,
) -> HeldOut:
    """Leave-one-segment-out prediction of ``bias`` (m, 3) with weights ``w`` (m,). The error
    is taken over the held-out blocks whose temperature ``temp`` (m,) lies inside the range of
    the blocks they were predicted from (the final fit covers the whole range, and the
    correction clamps beyond it and warns); over every held-out block when none does.
    ``noise`` (m, 3): the noise variance of each block mean, for :meth:`HeldOut.remaining`."""
    pred = np.full(bias.shape, np.nan)
    base = np.full(bias.shape, np.nan)
    inside = np.zeros(len(bias), dtype=bool)
    segments = np.unique(labels)
    for s in segments:  # a handful of segments, not samples
        test = labels == s
        train = ~test
        if np.count_nonzero(train) < 3:
            continue
        pred[test] = fit_predict(train, test)
        wt = w[train]
        base[test] = (wt @ bias[train]) / wt.sum()
        lo, hi = temp[train].min(), temp[train].max()
        inside[test] = (temp[test] >= lo) & (temp[test] <= hi)
    done = np.isfinite(pred).all(axis=1)
    if (done & inside).any():
        done &= inside
    if not done.any():
        nan = np.full(bias.shape[1], np.nan)
        return HeldOut(nan, nan.copy(), 0)
    if noise is not None:
        judged = np.isfinite(noise).all(axis=1)
        if (done & judged).any():
            done &= judged
        else:  # blocks of one sample: no noise to take out
            noise = None
    wd = w[done]

    def rms(p: np.ndarray) -> np.ndarray:
        r = bias[done] - p[done]
        return np.sqrt((wd @ (r * r)) / wd.sum())

    def per_segment(x: np.ndarray) -> np.ndarray:
        seg = labels[done]
        return np.array([(wd[seg == s] @ x[seg == s]) / wd[seg == s].sum() for s in np.unique(seg)])

    r2 = (bias[done] - pred[done]) ** 2
    out = HeldOut(rms(pred), rms(base), len(segments), int(np.count_nonzero(done)))
    out.segment_ms = per_segment(r2)
    if noise is not None:
        out.segment_noise = per_segment(noise[done])
        out.noise = (wd @ noise[done]) / wd.sum()
    return out
