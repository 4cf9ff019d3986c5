"""A stream's sample clock: timestamp jitter told apart from lost samples and gaps.

Real logs stamp samples on arrival: a stamp may come late and the next one early (steps of
1.66 and 0.34 periods in the Phidgets bag of imu_tools), while a lost sample leaves a step of
two periods between steps of one. Judged step by step against ``max_gap * period`` the first
reads as a gap; judged by how many sample *slots* of the nominal clock a stretch spans, it does
not.

Model. The nominal period ``T`` is the median step. The samples lost in step ``i`` (from stamp
``i`` to ``i + 1``) are the fewest that any window of one or two steps containing it implies:

    lost_i = max(0, min(round(dt_i / T) - 1,
                        round((t[i+1] - t[i-1]) / T) - 2,
                        round((t[i+2] - t[i]) / T) - 2))

so a stamp displaced by less than half a period (whose two steps sum to whole periods) loses
nothing, a step of about two periods between steps of one loses one sample, and a long gap
loses what it spans. Each sample's slot on the nominal clock is ``sum(1 + lost)`` of the steps
before it. The jitter figure is the RMS of ``dt / T - 1`` over the steps that lost nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SampleClock:
    """``period_ns`` the nominal period (median step), ``lost`` (n - 1,) the samples lost in
    each step, ``jitter`` the RMS step deviation of the steps that lost nothing, in periods."""

    period_ns: float
    lost: np.ndarray
    jitter: float
    n_lost: int

    @property
    def n_slots(self) -> int:
        """Slots of the nominal clock from the first sample to the last, both included."""
        return len(self.lost) + 1 + self.n_lost

    @property
    def slots(self) -> np.ndarray:
        """(n,) int64: each sample's slot on the nominal clock (the first at 0)."""
        slots = np.zeros(len(self.lost) + 1, dtype=np.int64)
        np.cumsum(self.lost + 1, out=slots[1:])
        return slots

    @property
    def n_gaps(self) -> int:
        """Steps that lost one sample or more."""
        return int(np.count_nonzero(self.lost)) if self.n_lost else 0


def sample_clock(t_ns: np.ndarray, dt: np.ndarray | None = None) -> SampleClock:
    """The sample clock of increasing stamps ``t_ns`` (int64 ns, at least 2); see the module
    docstring. The caller checks that time increases (``dt``: its ``np.diff(t_ns)``, if it
    has it)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    dt = np.diff(t_ns) if dt is None else dt
    lo, hi = int(dt.min()), int(dt.max())
    if lo == hi:  # a perfectly regular clock: the median is every step, no jitter, none lost
        return SampleClock(float(lo), np.zeros(len(dt), dtype=np.int64), 0.0, 0)
    period = float(np.median(dt))
    if hi < 1.5 * period:  # no step reaches a second slot: nothing lost (the common case)
        off = dt - period
        jitter = float(np.sqrt(np.einsum("i,i->", off, off) / len(off))) / period
        return SampleClock(period, np.zeros(len(dt), dtype=np.int64), jitter, 0)
    ratio = dt / period
    lost = np.round(ratio) - 1.0
    if len(dt) >= 2:
        two = np.round((t_ns[2:] - t_ns[:-2]) / period) - 2.0  # steps (i, i + 1)
        lost = np.minimum(lost, np.r_[two, np.inf])  # the window starting at step i
        lost = np.minimum(lost, np.r_[np.inf, two])  # the window ending at step i
    lost = np.maximum(lost, 0.0).astype(np.int64)
    clean = ratio[lost == 0] - 1.0
    jitter = float(np.sqrt(np.mean(clean * clean))) if len(clean) else 0.0
    return SampleClock(period, lost, jitter, int(lost.sum()))


def fill_lost(clock: SampleClock, values: np.ndarray) -> np.ndarray:
    """``values`` (n,) sampled on ``clock`` put on every one of its slots, the lost ones
    linearly interpolated between their neighbours."""
    if not clock.n_lost:
        return np.asarray(values, dtype=np.float64)
    return np.interp(np.arange(clock.n_slots, dtype=np.float64), clock.slots, values)


def longest_run(breaks: np.ndarray, n: int) -> tuple[int, int]:
    """``(start, stop)`` sample indices of the longest run of ``n`` samples that no break
    crosses; ``breaks`` holds the indices of the steps that break (step i is between samples
    i and i + 1)."""
    edges = np.r_[0, np.asarray(breaks, dtype=np.int64) + 1, n]
    k = int(np.argmax(np.diff(edges)))
    return int(edges[k]), int(edges[k + 1])
