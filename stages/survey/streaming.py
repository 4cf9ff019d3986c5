"""Still periods and their statistics from a log read in batches, with memory bounded by a batch.

The survey's figures (:mod:`imupipe.stages.survey.stats`) depend on the whole log: the noise floor
is a quantile of the log's windowed variance, and a still period may span many batches. Here
they are computed in two passes over consecutive batches of samples (time non-decreasing across
batches), each batch vectorised, with state that does not grow with the log:

**Pass 1** (:class:`FloorPass`): the centred windowed variance norm of the accelerometer and the
gyro (:func:`~imupipe.stages.static_detector.moving_variance_norm` over ``2 half + 1`` samples),
computed continuously across batch boundaries (:class:`Windowed` carries the last ``2 half``
samples), goes into a log-spaced histogram per sensor (:class:`LogHistogram`,
``BINS_PER_DECADE`` bins per decade); the noise floor is the histogram's ``floor_quantile``
quantile (the rank ``q (n - 1)`` of ``numpy.quantile``'s default, located in its bin and
interpolated geometrically inside it: relative error below ``10^(1/BINS_PER_DECADE) - 1``
= 0.23 %). The pass also counts the samples and their first and last stamps: the log's rate.

**Pass 2** (:class:`PeriodPass`): the same windowed variances classify each sample (still where
both lie below ``k`` times their floors); runs of still samples are tracked across boundaries
(an open run carries over) and every run accumulates, in one vectorised step per batch
(:func:`extend`, the same code for a run that starts in the batch and for one carried in):

- the sum of its values (the mean);
- batch-means blocks for the standard error of the mean: the period's length is unknown while
  streaming, so it keeps between ``B`` and ``2 B`` equal blocks (``B`` = :data:`BATCHES`):
  blocks of ``s`` samples, ``s`` the least power of two with ``L // s < 2 B`` (the state a
  scheme reaches that merges adjacent pairs when ``2 B`` blocks are full); the remainder
  ``L - s (L // s)`` is left out. ``se = std(block means, ddof=1) / sqrt(L // s)``;
- the non-overlapping cluster Allan variance at ``m`` samples: the running sum of the squared
  differences of consecutive cluster means (the last complete cluster's mean and the partial
  cluster carried), ``AVAR = sum / (2 pairs)`` (IEEE Std 952-1997 Annex C);
- the temperature samples whose stamps fall inside the period (``[first, last]`` stamp),
  assigned once the classification has passed their stamp (:meth:`PeriodPass.temperature`).

Values are summed centred on the mean of the first batch (precision of the cumulative sums). A
log read as one batch gives the whole-log figures exactly; split into batches it gives the same
periods and the same figures up to the rounding of the sums (and, for the noise floor, of the
variances near a histogram bin edge).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imupipe.stages.errors import FitError
from imupipe.stages.static_detector import moving_variance_norm

BATCHES = 10
"""``B``: a period's mean has between ``B`` and ``2 B - 1`` batch-means blocks (fewer when it
holds fewer samples)."""
BINS_PER_DECADE = 1000
"""Resolution of the noise-floor histogram."""
DECADES = (-30, 10)
"""The histogram's range of variance norms (unit^2); values beyond fall in its end bins."""
MIN_WINDOW_SAMPLES = 10
"""Fewest samples in the variance window: at a low rate the window is ``max(window_s,
MIN_WINDOW_SAMPLES / rate)`` seconds (a variance of 3 samples says nothing of stillness)."""
MIN_PERIOD_SAMPLES = 100
"""Fewest samples in a still period, besides ``min_duration_s`` at the sensor's real rate: a
mean's batch-means error needs ``BATCHES`` blocks of several samples (a 1 Hz topic needs 100 s,
not 5 samples)."""


@dataclass(frozen=True)
class StillOptions:
    """The still-period rule (see :mod:`imupipe.stages.survey.stats`)."""

    min_duration_s: float = 5.0
    window_s: float = 1.0
    k: float = 4.0
    floor_quantile: float = 0.02
    tau_s: float = 0.1
    level_deg: float = 5.0


@dataclass(frozen=True)
class Rule:
    """The rule in samples at the log's rate (Hz): window half-width, shortest period, Allan
    cluster."""

    rate: float
    half: int
    min_samples: int
    m_tau: int

    @classmethod
    def at(cls, opts: StillOptions, rate: float) -> Rule:
        """The rule at ``rate``: the window at least :data:`MIN_WINDOW_SAMPLES`, a period at
        least ``min_duration_s`` and :data:`MIN_PERIOD_SAMPLES`; the Allan cluster ``m_tau`` at
        least one sample."""
        window = max(int(round(opts.window_s * rate)), MIN_WINDOW_SAMPLES)
        return cls(
            rate,
            window // 2,
            max(int(round(opts.min_duration_s * rate)), MIN_PERIOD_SAMPLES),
            max(int(round(opts.tau_s * rate)), 1),
        )

    @property
    def window(self) -> int:
        """The rounded window (the variance uses ``2 half + 1`` samples)."""
        return 2 * self.half + 1


def rate_of(n: int, first_ns: int, last_ns: int) -> float | None:
    """Mean rate (Hz) of ``n`` samples from ``first_ns`` to ``last_ns`` (None: fewer than 3 or
    no time span)."""
    if n < 3 or last_ns <= first_ns:
        return None
    return (n - 1) / ((last_ns - first_ns) * 1e-9)


class LogHistogram:
    """Counts of positive values in log-spaced bins (``BINS_PER_DECADE`` per decade over
    ``DECADES``), zeros counted apart; :meth:`quantile` as ``numpy.quantile`` (linear)."""

    def __init__(self) -> None:
        self.lo, hi = DECADES
        self.counts = np.zeros((hi - self.lo) * BINS_PER_DECADE, np.int64)
        self.zeros = 0
        self.n = 0
        """Values counted (zeros included)."""

    def add(self, values: np.ndarray) -> None:
        v = values[np.isfinite(values)]
        pos = v[v > 0]
        self.zeros += len(v) - len(pos)
        self.n += len(v)
        if not len(pos):
            return
        idx = np.floor((np.log10(pos) - self.lo) * BINS_PER_DECADE).astype(np.int64)
        np.clip(idx, 0, len(self.counts) - 1, out=idx)
        first = int(idx.min())  # count over the span the values cover, not every bin
        counted = np.bincount(idx - first)
        self.counts[first : first + len(counted)] += counted

    def quantile(self, q: float) -> float | None:
        """The ``q`` quantile (None when empty; 0 when it falls among the zeros)."""
        n = self.n
        if n == 0:
            return None
        rank = q * (n - 1)  # 0-based position among the sorted values
        if rank < self.zeros:
            return 0.0
        bins = np.flatnonzero(self.counts)  # the occupied bins, in order
        counts = self.counts[bins]
        cum = np.cumsum(counts) + self.zeros
        i = min(int(np.searchsorted(cum, rank, side="right")), len(bins) - 1)
        b = int(bins[i])
        frac = min(max((rank - (cum[i] - counts[i]) + 0.5) / counts[i], 0.0), 1.0)
        return float(10.0 ** (self.lo + (b + frac) / BINS_PER_DECADE))


class Windowed:
    """The centred windowed variance norms of a stream of rows fed in batches.

    Rows are ``x`` (n, c) with the gyro in columns 0-2 and the accelerometer in 3-5 (other
    columns ride along). :meth:`feed` returns the rows whose variance is final (their whole
    window has arrived) with ``(accel variance, gyro variance)``: the rows lag ``half`` behind
    the input; :meth:`finish` returns the last ``half`` rows (variance ``inf``, as the first
    ``half``: their window does not fit in the log)."""

    def __init__(self, half: int, columns: int) -> None:
        self.half = half
        self.t = np.zeros(0, np.int64)
        self.x = np.zeros((0, columns))
        self.start = 0
        """Global index of the buffer's first row."""
        self.done = 0
        """Rows returned so far."""
        self.n = 0

    def feed(
        self, t: np.ndarray, x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        buf_t = np.concatenate([self.t, t]) if len(self.t) else t
        buf_x = np.concatenate([self.x, x]) if len(self.x) else x
        self.n += len(t)
        end = max(self.n - self.half, self.done)
        j0, j1 = self.done - self.start, end - self.start
        window = 2 * self.half + 1
        va = moving_variance_norm(buf_x[:, 3:6], window)[j0:j1]
        vg = moving_variance_norm(buf_x[:, 0:3], window)[j0:j1]
        out = (buf_t[j0:j1], buf_x[j0:j1], va, vg)
        self.done = end
        keep = max(self.n - 2 * self.half, 0)
        self.t, self.x = buf_t[keep - self.start :], buf_x[keep - self.start :]
        self.start = keep
        return out

    def finish(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        j0 = self.done - self.start
        t, x = self.t[j0:], self.x[j0:]
        self.done = self.n
        inf = np.full(len(t), np.inf)
        return t, x, inf, inf


class FloorPass:
    """Pass 1: the log's noise floors and rate (see the module docstring). ``half``: the
    window's half-width, guessed before the rate is known (the caller checks it against
    :attr:`rate` at the end). ``keep``: hold the rows and their variances for pass 2
    (:meth:`kept`), for a log read as one batch."""

    def __init__(self, half: int, keep: bool = False) -> None:
        self.windowed = Windowed(half, 6)
        self.keep = keep
        self.held: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.accel = LogHistogram()
        self.gyro = LogHistogram()
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.reference: np.ndarray | None = None
        """Mean of the first batch's rows (the centre of the sums)."""

    def feed(self, t: np.ndarray, x: np.ndarray) -> None:
        if not len(t):
            return
        if self.first_ns is None:
            self.first_ns = int(t[0])
            self.reference = x.mean(axis=0)
        self.last_ns = int(t[-1])
        out = self.windowed.feed(t, x)
        self.accel.add(out[2])
        self.gyro.add(out[3])
        if self.keep:
            self.held.append(out)

    def kept(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every row fed, with its (accel, gyro) variance: pass 2's input without a second
        read (``keep``)."""
        parts = [*self.held, self.windowed.finish()]
        self.held = []
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))  # type: ignore[return-value]

    @property
    def n(self) -> int:
        return self.windowed.n

    @property
    def rate(self) -> float | None:
        if self.first_ns is None or self.last_ns is None:
            return None
        return rate_of(self.n, self.first_ns, self.last_ns)

    def floors(self, opts: StillOptions) -> tuple[float, float]:
        """(accel floor, gyro floor), variance norms; ``FitError`` when the accelerometer's is
        not positive (as :func:`~imupipe.stages.static_detector.make_detector`); a gyro floor of
        0 means the gyro is not used."""
        fa = self.accel.quantile(opts.floor_quantile)
        if fa is None:
            raise FitError(
                f"the log holds {self.n} samples, fewer than one {opts.window_s} s window"
            )
        if not fa > 0:
            raise FitError(
                "the accelerometer does not vary at all where it is still (quantised to a "
                "constant?): no noise floor to set the static threshold"
            )
        fg = self.gyro.quantile(opts.floor_quantile)
        return fa, (fg or 0.0)


@dataclass
class Acc:
    """The running sums of ``p`` periods over ``c`` columns (see :func:`extend`)."""

    n: np.ndarray
    """(p,) samples so far."""
    total: np.ndarray
    """(p, c) sum of the centred values."""
    size: np.ndarray
    """(p,) batch-means block size."""
    blocks: np.ndarray
    """(p, 2B, c) sums of the complete blocks (the first ``n // size``)."""
    part: np.ndarray
    """(p, c) sum of the samples after the complete blocks."""
    last: np.ndarray
    """(p, c) mean of the last complete Allan cluster (NaN: none yet)."""
    rest: np.ndarray
    """(p, c) sum of the samples after the complete clusters."""
    sq: np.ndarray
    """(p, c) sum of squared differences of consecutive cluster means."""
    pairs: np.ndarray
    """(p,) count of those differences."""

    @classmethod
    def empty(cls, p: int, c: int, batches: int = BATCHES) -> Acc:
        z = np.zeros((p, c))
        return cls(
            np.zeros(p, np.int64),
            z,
            np.ones(p, np.int64),
            np.zeros((p, 2 * batches, c)),
            z.copy(),
            np.full((p, c), np.nan),
            z.copy(),
            z.copy(),
            np.zeros(p, np.int64),
        )

    def take(self, idx: np.ndarray) -> Acc:
        return Acc(*(getattr(self, f)[idx] for f in _ACC_FIELDS))

    @staticmethod
    def join(parts: list[Acc]) -> Acc:
        return Acc(*(np.concatenate([getattr(a, f) for a in parts]) for f in _ACC_FIELDS))

    def mean(self) -> np.ndarray:
        """(p, c) mean of the centred values."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.total / self.n[:, None]

    def batch_se(self) -> np.ndarray:
        """(p, c) batch-means standard error of the mean (NaN with fewer than 2 blocks)."""
        nb = self.n // self.size
        valid = np.arange(self.blocks.shape[1])[None, :] < nb[:, None]
        means = self.blocks / self.size[:, None, None]
        cnt = np.maximum(nb, 1)[:, None]
        mu = np.where(valid[:, :, None], means, 0.0).sum(axis=1) / cnt
        dev = np.where(valid[:, :, None], means - mu[:, None, :], 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            var = (dev**2).sum(axis=1) / (nb - 1)[:, None]
            se = np.sqrt(var / nb[:, None])
        se[nb < 2] = np.nan
        return se

    def adev(self) -> np.ndarray:
        """(p, c) Allan deviation at the cluster size (NaN with fewer than two clusters)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(self.sq / (2.0 * self.pairs[:, None]))


_ACC_FIELDS = tuple(f for f in Acc.__dataclass_fields__)


def extend(acc: Acc, cs: np.ndarray, lo: np.ndarray, hi: np.ndarray, m: int) -> Acc:
    """``acc`` (p periods) extended by the rows ``[lo, hi)`` (each (p,)) of a batch whose
    cumulative sums of the centred values are ``cs`` (k + 1, c): one vectorised step for every
    period, whether it starts in the batch (``acc`` empty) or carries on from the last one."""
    p, c = acc.total.shape
    two_b = acc.blocks.shape[1]
    k = hi - lo
    n = acc.n
    big = n + k
    total = acc.total + cs[hi] - cs[lo]
    # batch means: the least power-of-two multiple of the block size with fewer than 2B blocks
    size = acc.size.copy()
    while True:
        grow = big // size >= two_b
        if not grow.any():
            break
        size[grow] *= 2
    r = size // acc.size
    nb_old = n // acc.size
    g = n // size
    idx = np.arange(two_b)
    grp = idx[None, :] // r[:, None]  # (p, 2B): the new block each old block merges into
    valid_old = idx[None, :] < nb_old[:, None]
    blocks = np.zeros_like(acc.blocks)
    into = valid_old & (grp < g[:, None])
    pi, bi = np.nonzero(into)
    np.add.at(blocks, (pi, grp[pi, bi]), acc.blocks[pi, bi])
    left = acc.part + np.where((valid_old & ~into)[:, :, None], acc.blocks, 0.0).sum(axis=1)
    nb = big // size
    j = g[:, None] + idx[None, :]  # new blocks g .. nb - 1
    new = j < nb[:, None]
    b_lo = lo[:, None] + np.clip(j * size[:, None] - n[:, None], 0, k[:, None])
    b_hi = lo[:, None] + np.clip((j + 1) * size[:, None] - n[:, None], 0, k[:, None])
    sums = cs[b_hi] - cs[b_lo] + np.where((j == g[:, None])[:, :, None], left[:, None, :], 0.0)
    pn, jn = np.nonzero(new)
    blocks[pn, j[pn, jn]] = sums[pn, jn]
    part = cs[hi] - cs[lo + np.clip(nb * size - n, 0, k)]
    part += np.where((nb == g)[:, None], left, 0.0)
    # Allan: clusters c0 .. c1 - 1 complete in these rows
    c0, c1 = n // m, big // m
    count = c1 - c0
    owner = np.repeat(np.arange(p), count)
    first = np.cumsum(count) - count
    jj = c0[owner] + np.arange(int(count.sum())) - first[owner]
    k_lo = lo[owner] + np.clip(jj * m - n[owner], 0, None)
    k_hi = lo[owner] + (jj + 1) * m - n[owner]
    csum = cs[k_hi] - cs[k_lo]
    csum[first[count > 0]] += acc.rest[count > 0]
    means = csum / m
    sq = acc.sq.copy()
    pairs = acc.pairs.copy()
    same = owner[1:] == owner[:-1]
    np.add.at(sq, owner[1:][same], (means[1:][same] - means[:-1][same]) ** 2)
    pairs += np.bincount(owner[1:][same], minlength=p)
    has = (count > 0) & np.isfinite(acc.last).all(axis=1)
    d0 = means[first[has]] - acc.last[has]
    sq[has] += d0**2
    pairs[has] += 1
    last = acc.last.copy()
    ends = count > 0
    last[ends] = means[(first + count - 1)[ends]]
    rest = np.where(
        ends[:, None],
        cs[hi] - cs[lo + np.clip(c1 * m - n, 0, None)],
        acc.rest + cs[hi] - cs[lo],
    )
    return Acc(big, total, size, blocks, part, last, rest, sq, pairs)


def cumsum0(x: np.ndarray) -> np.ndarray:
    """(n + 1, c) cumulative sums of ``x`` (n, c) starting at 0."""
    out = np.empty((x.shape[0] + 1, x.shape[1]))
    out[0] = 0.0
    np.cumsum(x, axis=0, out=out[1:])
    return out


def assign(
    t: np.ndarray, v: np.ndarray, start_ns: np.ndarray, stop_ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(sum, count) per interval ``[start_ns, stop_ns]`` (sorted, disjoint) of the samples
    ``v`` at ``t`` that fall inside it."""
    p = len(start_ns)
    if p == 0 or not len(t):
        return np.zeros(p), np.zeros(p, np.int64)
    i = np.searchsorted(start_ns, t, side="right") - 1
    inside = i >= 0
    inside[inside] &= t[inside] <= stop_ns[i[inside]]
    return (
        np.bincount(i[inside], weights=v[inside], minlength=p),
        np.bincount(i[inside], minlength=p),
    )


@dataclass
class Periods:
    """The closed still periods of a pass: indices, stamps, sums and temperature sums."""

    start: list[np.ndarray] = field(default_factory=list)
    stop: list[np.ndarray] = field(default_factory=list)
    start_ns: list[np.ndarray] = field(default_factory=list)
    stop_ns: list[np.ndarray] = field(default_factory=list)
    acc: list[Acc] = field(default_factory=list)
    temp_sum: list[np.ndarray] = field(default_factory=list)
    temp_count: list[np.ndarray] = field(default_factory=list)

    def add(
        self,
        start: np.ndarray,
        stop: np.ndarray,
        start_ns: np.ndarray,
        stop_ns: np.ndarray,
        acc: Acc,
        tsum: np.ndarray,
        tcount: np.ndarray,
    ) -> None:
        """Closed periods: row ranges ``[start, stop)``, first and last stamps, sums,
        temperature sums and counts so far."""
        if len(start):
            self.start.append(start)
            self.stop.append(stop)
            self.start_ns.append(start_ns)
            self.stop_ns.append(stop_ns)
            self.acc.append(acc)
            self.temp_sum.append(tsum)
            self.temp_count.append(tcount)

    def flat(self, name: str) -> np.ndarray:
        parts = getattr(self, name)
        if len(parts) > 1:  # keep one array (temperature sums are updated in place)
            parts[:] = [np.concatenate(parts)]
        return parts[0] if parts else np.zeros(0, np.int64)


class PeriodPass:
    """Pass 2: classify, track runs across batches, accumulate each period (see the module
    docstring). ``floors``: (accel, gyro) variance floors from :class:`FloorPass`; rows ``x``
    (n, c): gyro in columns 0-2, accelerometer in 3-5, further columns summarised alike (the
    corrected samples)."""

    def __init__(
        self,
        rule: Rule,
        floors: tuple[float, float],
        opts: StillOptions,
        columns: int,
        reference: np.ndarray | None = None,
    ) -> None:
        self.rule = rule
        self.opts = opts
        self.windowed = Windowed(rule.half, columns)
        self.floors = floors
        self.columns = columns
        self.reference = reference
        self.index = 0
        self.closed = Periods()
        self.open: Acc | None = None
        self.open_start = 0
        self.open_start_ns = 0
        self.open_temp = np.zeros(2)
        self.last_ns = 0
        self.pending_t = np.zeros(0, np.int64)
        self.pending_v = np.zeros(0)

    def feed(self, t: np.ndarray, x: np.ndarray) -> None:
        """Rows ``x`` at ``t`` (continuing the rows fed before)."""
        self.classified(*self.windowed.feed(t, x))

    def temperature(self, t: np.ndarray, v: np.ndarray) -> None:
        """Temperature samples (degC) of the same span of the log (any order); each is added
        to the period it falls in once the classification has passed its stamp."""
        self.pending_t = np.concatenate([self.pending_t, t])
        self.pending_v = np.concatenate([self.pending_v, v])

    def finish(self) -> Periods:
        self.classified(*self.windowed.finish())
        if self.open is not None:
            self._close_open(self.index, self.last_ns)
        self._assign(None)
        return self.closed

    def quiet(self, va: np.ndarray, vg: np.ndarray) -> np.ndarray:
        fa, fg = self.floors
        q = va < self.opts.k * fa
        if fg > 0:
            q &= vg < self.opts.k * fg
        return q

    def classified(self, t: np.ndarray, x: np.ndarray, va: np.ndarray, vg: np.ndarray) -> None:
        """Rows whose windowed variances are known (from :class:`Windowed`, or
        :meth:`FloorPass.kept` for a log held whole)."""
        k = len(t)
        if k == 0:
            return
        if self.reference is None:
            self.reference = x.mean(axis=0)
        elif len(self.reference) < x.shape[1]:  # corrected columns: centred on their own mean
            self.reference = np.r_[self.reference, x[:, len(self.reference) :].mean(axis=0)]
        self.segments(t, x, self.quiet(va, vg))
        self.last_ns = int(t[-1])
        self._assign(self.last_ns)

    def segments(self, t: np.ndarray, x: np.ndarray, quiet: np.ndarray) -> None:
        """Runs of ``quiet`` rows (global indices from ``self.index``) added to the periods."""
        k = len(t)
        i0 = self.index
        edges = np.diff(np.r_[0, quiet.astype(np.int8), 0])
        st = np.flatnonzero(edges == 1)
        sp = np.flatnonzero(edges == -1)
        carried = self.open is not None and len(st) > 0 and st[0] == 0
        if self.open is not None and not carried:
            self._close_open(i0, self.last_ns)
        # runs that start and end here, shorter than a period, need no sums
        keep = (sp - st >= self.rule.min_samples) | (sp == k)
        if carried:
            keep[0] = True
        st, sp = st[keep], sp[keep]
        p = len(st)
        if p == 0:
            self.index += k
            return
        cs = cumsum0(x - self.reference)
        acc = Acc.empty(p, self.columns)
        if carried:
            acc = Acc.join([self.open, acc.take(np.arange(1, p))])  # type: ignore[list-item]
        acc = extend(acc, cs, st, sp, self.rule.m_tau)
        start = i0 + st
        start_ns = t[st].astype(np.int64)
        temp = np.zeros((p, 2))
        if carried:
            start[0], start_ns[0] = self.open_start, self.open_start_ns
            temp[0] = self.open_temp
        stays = sp[-1] == k
        done = np.arange(p - 1 if stays else p)
        long = done[acc.n[done] >= self.rule.min_samples]
        self.closed.add(
            start[long],
            (i0 + sp)[long],
            start_ns[long],
            t[sp[long] - 1].astype(np.int64),
            acc.take(long),
            temp[long, 0],
            temp[long, 1].astype(np.int64),
        )
        self.open = acc.take(np.array([p - 1])) if stays else None
        if stays:
            self.open_start, self.open_start_ns = int(start[-1]), int(start_ns[-1])
            self.open_temp = temp[-1].copy()
        self.index += k

    def _close_open(self, stop: int, stop_ns: int) -> None:
        acc = self.open
        assert acc is not None
        if acc.n[0] >= self.rule.min_samples:
            self.closed.add(
                np.array([self.open_start]),
                np.array([stop]),
                np.array([self.open_start_ns]),
                np.array([stop_ns]),
                acc,
                self.open_temp[:1].copy(),
                self.open_temp[1:].astype(np.int64),
            )
        self.open = None

    def _assign(self, horizon: int | None) -> None:
        ready = np.ones(len(self.pending_t), bool) if horizon is None else self.pending_t <= horizon
        if not ready.any():
            return
        t, v = self.pending_t[ready], self.pending_v[ready]
        self.pending_t, self.pending_v = self.pending_t[~ready], self.pending_v[~ready]
        starts, stops = self.closed.flat("start_ns"), self.closed.flat("stop_ns")
        if self.open is not None and horizon is not None:
            starts = np.r_[starts, self.open_start_ns]
            stops = np.r_[stops, horizon]
        s, c = assign(t, v, starts, stops)
        n = len(self.closed.flat("start_ns"))
        if n:
            self.closed.flat("temp_sum")[:] += s[:n]
            self.closed.flat("temp_count")[:] += c[:n]
        if len(s) > n:
            self.open_temp += (s[n], c[n])
