"""Exact frequency-stability estimators (NIST SP1065, Riley 2008), all axes at once.

Input is *rate* data ``y`` (n, k): each column a sensor axis sampled every ``tau0 = 1/rate_hz``
seconds (gyro rad/s, accel m/s^2; the deviations come out in the same unit). The mean of each
column is removed first and the "phase" ``x = tau0 * cumsum(y)`` (n + 1 points, x[0] = 0) is
formed; every estimator is then a sum of squared finite differences of ``x`` at lag ``m`` (the
averaging factor, ``tau = m * tau0``), computed in O(n) per tau and in cache-sized row chunks:

| kind | variance at tau = m tau0 (N phase points) | terms (Stable32 ``#``) |
|---|---|---|
| ``oadev`` | sum_i (x[i+2m] - 2x[i+m] + x[i])^2 / (2 tau^2 (N-2m)) | N - 2m |
| ``adev`` | the same over i = 0, m, 2m, ... | (N-1)//m - 1 |
| ``mdev`` | sum_j (sum_{i=j}^{j+m-1} (x[i+2m] - 2x[i+m] + x[i]))^2 / (2 m^2 tau^2 (N-3m+1)) | N - 3m + 1 |
| ``hdev`` | sum over i = 0, m, ... of (x[i+3m] - 3x[i+2m] + 3x[i+m] - x[i])^2 / (6 tau^2 #) | (N-1)//m - 2 |
| ``ohdev`` | the same over every i | N - 3m |
| ``totdev`` | OADEV's sum over i = 1..N-2 of x extended by odd reflection at both ends, / (N-2) | N - 2 |

Confidence: the noise type ``alpha`` (frequency PSD ~ f^alpha) is identified per tau by the lag-1
autocorrelation method (Riley & Greenhall 2004); the equivalent degrees of freedom follow
Greenhall & Riley 2003/2004 (the algorithm Stable32 uses) for the ADEV family and SP1065 Table 7
for TOTDEV; the bounds are the chi-square ones: ``dev * sqrt(edf / chi2.ppf(p, edf))`` with
p = 0.8415 (lower) and 0.1585 (upper), i.e. 68.3 % intervals (the chi-square quantile is
``2 * gammaincinv(edf / 2, p)``: no ``scipy.stats`` import).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal

import numpy as np

from imupipe.stages.cores import usable_cores

Kind = Literal["oadev", "adev", "mdev", "hdev", "ohdev", "totdev"]
KINDS: tuple[str, ...] = ("oadev", "adev", "mdev", "hdev", "ohdev", "totdev")
GRIDS: tuple[str, ...] = ("auto", "octave", "decade", "log", "all")
BEND = 0.125
"""The ``auto`` grid refines an octave where the log-log slope of the curve changes by more
than this (beyond twice its statistical scatter) at either end."""
CHUNK = 1 << 17
"""Phase points processed at once (keeps the temporaries in cache and the memory small)."""
PARALLEL_POINTS = 1 << 20
"""Points per axis from which :func:`each_axis` runs the axes on several threads (each axis then
takes milliseconds or more: below, starting the threads costs more than it saves)."""
DOT = 8192
"""Points per BLAS dot product in :func:`_dot`: OpenBLAS computes a dot of more than 10,000
points on every core, whose threads then spin and wait on one another on a busy machine; below
that it runs on the calling thread, about four times faster than ``einsum``."""


@dataclass(frozen=True)
class Deviation:
    """A deviation curve of every axis: ``taus`` (t,) s, ``m`` (t,) averaging factors,
    ``dev`` (t, k) in the unit of the rate data, ``n`` (t,) number of terms summed."""

    kind: str
    taus: np.ndarray
    m: np.ndarray
    dev: np.ndarray
    n: np.ndarray
    tau0: float
    n_phase: int


@dataclass(frozen=True)
class Confidence:
    """Per tau and axis: identified noise exponent ``alpha`` (int), equivalent degrees of
    freedom ``edf`` and the 68.3 % chi-square bounds ``lo``, ``hi`` of the deviation."""

    alpha: np.ndarray
    edf: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


# -- data -----------------------------------------------------------------------------------------
def rate_to_phase(y: np.ndarray, tau0: float, means: list[float] | None = None) -> np.ndarray:
    """Phase of rate data ``y`` (n,) or (n, k), mean removed first: (k, n + 1), x[:, 0] = 0.

    Axis-major (each axis's phase contiguous) so that the lagged sums below stream through
    memory. ``y`` may also be a sequence of k equal-length 1-D columns (no (n, k) copy needed);
    ``means``: each column's ``mean()``, when the caller has them."""
    if isinstance(y, list | tuple):
        columns = [np.asarray(c, dtype=np.float64) for c in y]
    else:
        y = np.asarray(y, dtype=np.float64)
        columns = list(y.reshape(len(y), -1).T)
    if means is None:
        means = [c.mean() for c in columns]
    x = np.empty((len(columns), len(columns[0]) + 1))
    x[:, 0] = 0.0

    def one_axis(j: int) -> None:
        row = x[j]
        np.subtract(columns[j], means[j], out=row[1:])
        np.cumsum(row[1:], out=row[1:])
        row[1:] *= tau0

    each_axis(one_axis, len(columns), x.shape[1])
    return x


def each_axis(work: Callable[[int], None], k: int, n: int) -> None:
    """``work(j)`` for each axis j < k of series of ``n`` points: on as many threads as the
    process has cores when the series are long (:data:`PARALLEL_POINTS`; numpy's loops and
    BLAS release the GIL), else in turn. ``work`` writes only its own axis's results, so they
    are the same, bit for bit, either way."""
    workers = min(k, usable_cores()) if n >= PARALLEL_POINTS else 1
    if workers < 2:
        for j in range(k):
            work(j)
        return
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(work, range(k)))


def as_phase(x: np.ndarray) -> np.ndarray:
    """Phase data (N,) or (N, k) as the axis-major (k, N) array the estimators use."""
    x = np.asarray(x, dtype=np.float64)
    return np.ascontiguousarray(x.reshape(len(x), -1).T)


def max_af(kind: str, n_phase: int) -> int:
    """The largest averaging factor ``kind`` can use on ``n_phase`` phase points (>= 1 term)."""
    if kind in ("oadev", "adev"):
        return (n_phase - 1) // 2
    if kind in ("mdev", "hdev", "ohdev"):
        return (n_phase - 1) // 3
    if kind == "totdev":
        return n_phase - 1
    raise ValueError(f"unknown deviation kind '{kind}' (known: {', '.join(KINDS)})")


def tau_grid(grid: str, max_m: int, points_per_decade: int = 10) -> np.ndarray:
    """Averaging factors m (sorted, unique, 1 <= m <= max_m) of a grid:
    ``octave`` 1, 2, 4, ...; ``decade`` 1, 2, 4, 10, 20, 40, ...; ``log`` ``points_per_decade``
    log-spaced values per decade (rounded to integers); ``all`` every m. ``auto`` starts from
    ``octave`` and is refined where the curve bends (:func:`curve`)."""
    if max_m < 1:
        return np.zeros(0, dtype=np.int64)
    if grid in ("octave", "auto"):
        m = 2 ** np.arange(int(np.log2(max_m)) + 1)
    elif grid == "decade":
        decades = 10 ** np.arange(int(np.log10(max_m)) + 1)
        m = (np.array([1, 2, 4])[None, :] * decades[:, None]).ravel()
    elif grid == "log":
        if points_per_decade < 1:
            raise ValueError("points_per_decade must be >= 1")
        k = np.arange(int(np.floor(np.log10(max_m) * points_per_decade)) + 1)
        m = np.round(10.0 ** (k / points_per_decade))
    elif grid == "all":
        m = np.arange(1, max_m + 1)
    else:
        raise ValueError(f"unknown tau grid '{grid}' (known: {', '.join(GRIDS)})")
    m = np.unique(m.astype(np.int64))
    return m[(m >= 1) & (m <= max_m)]


# -- sums of squared differences ------------------------------------------------------------------
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum(a * b) of two equal-length contiguous 1-D arrays, in BLAS dots of ``DOT`` points
    summed in order. The whole pieces go to BLAS in one call (``np.vecdot`` over the rows of a
    (pieces, DOT) view: one ``ddot`` per row, on this thread); the same sum as a dot per piece,
    bit for bit, at half the cost of the Python loop."""
    n = len(a)
    if n <= DOT:
        return float(np.dot(a, b))
    whole = n - n % DOT
    if _VECDOT is None or not (a.flags.c_contiguous and b.flags.c_contiguous):
        return float(sum(np.dot(a[i : i + DOT], b[i : i + DOT]) for i in range(0, n, DOT)))
    parts = _VECDOT(a[:whole].reshape(-1, DOT), b[:whole].reshape(-1, DOT)).tolist()
    if whole < n:
        parts.append(float(np.dot(a[whole:], b[whole:])))
    return float(sum(parts))


_VECDOT = getattr(np, "vecdot", None)
"""numpy >= 2.0's row-wise dot (a BLAS ``ddot`` per row); older numpy: a dot per piece."""


def _row_dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`_dot` of each row of ``a`` (k, n) with the same row of ``b`` (k, n), or with
    ``b`` (n,), every row's pieces in one ``np.vecdot`` call: the same sums, bit for bit, with
    one call instead of one per row (the noise identification's series are short)."""
    k, n = a.shape
    if _VECDOT is None or a.strides[1] != 8 or b.strides[-1] != 8:
        return np.array([_dot(x, y) for x, y in zip(a, np.broadcast_to(b, a.shape), strict=True)])
    if n <= DOT:
        return _VECDOT(a, b)
    whole = n - n % DOT
    if b.ndim == 1:
        head, tail = b[:whole].reshape(1, -1, DOT), b[whole:]
    else:
        head, tail = b[:, :whole].reshape(k, -1, DOT), b[:, whole:]
    rows = _VECDOT(a[:, :whole].reshape(k, -1, DOT), head).tolist()
    if whole < n:
        for row, rest in zip(rows, _VECDOT(a[:, whole:], tail).tolist(), strict=True):
            row.append(rest)
    return np.array([float(sum(row)) for row in rows])


def _sumsq_lagged(x: np.ndarray, m: int, hadamard: bool, count: int) -> np.ndarray:
    """Per axis of ``x`` (k, N): sum_{i<count} of the squared second difference
    x[i+2m] - 2x[i+m] + x[i] (or third, ``hadamard``), streamed in cache-sized chunks. For
    lags up to half a chunk the second difference is the lag-m difference of the first
    differences ``D = x[i+m] - x[i]`` over the chunk and m more points: two passes instead of
    three."""
    total = np.zeros(len(x))
    buf = np.empty(min(CHUNK, count))
    first = np.empty(min(CHUNK, count) + m) if m <= CHUNK // 2 and not hadamard else None
    for j, r in enumerate(x):
        acc = 0.0
        for a in range(0, count, CHUNK):
            b = min(a + CHUNK, count)
            d = buf[: b - a]
            if hadamard:
                np.subtract(r[a + m : b + m], r[a + 2 * m : b + 2 * m], out=d)
                d *= 3.0
                d += r[a + 3 * m : b + 3 * m]
                d -= r[a:b]
            elif first is not None:
                f = first[: b - a + m]
                np.subtract(r[a + m : b + 2 * m], r[a : b + m], out=f)
                np.subtract(f[m:], f[: b - a], out=d)
            else:
                np.add(r[a:b], r[a + 2 * m : b + 2 * m], out=d)
                d -= r[a + m : b + m]
                d -= r[a + m : b + m]
            acc += _dot(d, d)
        total[j] = acc
    return total


def _mod_sumsq(x: np.ndarray, m: int) -> tuple[np.ndarray, int]:
    """MDEV's sum of squared m-sums of second differences per axis of ``x`` (k, N); the m-sums
    come from a cumulative sum of the second differences (not of the phase: precision)."""
    total = np.zeros(len(x))
    count = x.shape[1] - 3 * m + 1
    for j, r in enumerate(x):
        d = r[2 * m :] - 2.0 * r[m:-m] + r[: -2 * m]
        c = np.concatenate([[0.0], np.cumsum(d)])
        s = c[m:] - c[:-m]
        total[j] = float(np.einsum("i,i->", s, s))
    return total, count


def _reflect(x: np.ndarray) -> np.ndarray:
    """TOTDEV's extension of x (k, N) by odd reflection at both ends: (k, 3N - 4)."""
    n = x.shape[1]
    inner = x[:, n - 2 : 0 : -1]  # x[N-2] ... x[1]
    left = 2.0 * x[:, :1] - inner
    right = 2.0 * x[:, -1:] - inner
    return np.concatenate([left, x, right], axis=1)


def _variance_at(kind: str, x: np.ndarray, m: int, tau0: float, ext: np.ndarray | None):
    n = x.shape[1]
    tau2 = (m * tau0) ** 2
    if kind == "oadev":
        count = n - 2 * m
        return _sumsq_lagged(x, m, False, count) / (2.0 * tau2 * count), count
    if kind == "ohdev":
        count = n - 3 * m
        return _sumsq_lagged(x, m, True, count) / (6.0 * tau2 * count), count
    if kind == "adev":
        xd = np.ascontiguousarray(x[:, ::m])
        count = xd.shape[1] - 2
        return _sumsq_lagged(xd, 1, False, count) / (2.0 * tau2 * count), count
    if kind == "hdev":
        xd = np.ascontiguousarray(x[:, ::m])
        count = xd.shape[1] - 3
        return _sumsq_lagged(xd, 1, True, count) / (6.0 * tau2 * count), count
    if kind == "mdev":
        s, count = _mod_sumsq(x, m)
        return s / (2.0 * m * m * tau2 * count), count
    if kind == "totdev":
        assert ext is not None
        start = n - 2 + 1 - m  # x*[i - m] for original index i = 1
        s = _sumsq_lagged(ext[:, start:], m, False, n - 2)
        return s / (2.0 * tau2 * (n - 2)), n - 2
    raise ValueError(f"unknown deviation kind '{kind}' (known: {', '.join(KINDS)})")


def deviation_of_phase(
    x: np.ndarray, tau0: float, kind: str = "oadev", m: np.ndarray | None = None
) -> Deviation:
    """Deviation ``kind`` of axis-major phase ``x`` (k, N) (see :func:`as_phase`) at averaging
    factors ``m`` (default octave). Factors beyond :func:`max_af` are dropped.

    Axis by axis, every factor of one axis before the next: one axis's phase (4 MB at 0.5 M
    points) stays in the cache over all its factors, where factor by factor over all axes each
    pass read all of them from memory again (a fifth of the time at 0.5 M points). Each sum is
    the same either way. Long series run their axes on several threads (:func:`each_axis`)."""
    n = x.shape[1]
    top = max_af(kind, n)
    m = tau_grid("octave", top) if m is None else np.asarray(m, dtype=np.int64)
    m = m[(m >= 1) & (m <= top)]
    ext = _reflect(x) if kind == "totdev" else None
    dev = np.empty((len(m), len(x)))
    counts = np.empty(len(m), dtype=np.int64)

    def one_axis(j: int) -> None:
        row = x[j : j + 1]
        row_ext = None if ext is None else ext[j : j + 1]
        for i, mi in enumerate(m):
            var, counts[i] = _variance_at(kind, row, int(mi), tau0, row_ext)
            dev[i, j] = np.sqrt(var[0])

    each_axis(one_axis, len(x), n)
    return Deviation(kind, m * tau0, m, dev, counts, tau0, n)


def deviation(
    y: np.ndarray,
    rate_hz: float,
    kind: str = "oadev",
    grid: str = "octave",
    points_per_decade: int = 10,
    m: np.ndarray | None = None,
) -> Deviation:
    """Deviation ``kind`` of rate data ``y`` (n,) or (n, k) sampled at ``rate_hz`` on ``grid``
    (or at the given averaging factors ``m``), bounded by the data length."""
    tau0 = 1.0 / rate_hz
    x = rate_to_phase(y, tau0)
    if m is None:
        m = tau_grid(grid, max_af(kind, x.shape[1]), points_per_decade)
    return deviation_of_phase(x, tau0, kind, m)


# -- noise identification and confidence ----------------------------------------------------------
def _lag1(z: np.ndarray, scratch: np.ndarray) -> np.ndarray:
    """Lag-1 autocorrelation of each row of ``z`` (k, n) (its mean removed, in ``scratch``, an
    array of at least that shape)."""
    s = scratch[: z.shape[0], : z.shape[1]]
    np.subtract(z, z.mean(axis=1, keepdims=True), out=s)
    return np.array([_dot(r[:-1], r[1:]) / _dot(r, r) for r in s])


def _lag1_sums(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_lag1` of each row of ``z`` (k, n) from sums over the row, without writing a
    mean-removed copy: with mu the mean, sum (z - mu)^2 = sum z^2 - mu sum z and
    sum (z_i - mu)(z_i+1 - mu) = sum z_i z_i+1 - mu (2 sum z - z_0 - z_n-1) + (n - 1) mu^2.
    Also returns how much larger than the result the terms are (n mu^2 / sum (z - mu)^2 + 1):
    the factor by which rounding can grow, small for the detrended and differenced series here
    (their mean is near zero)."""
    n = z.shape[1]
    total = z.sum(axis=1)
    mu = total / n
    square = _row_dots(z, z)
    lagged = _row_dots(z[:, :-1], z[:, 1:])
    var = square - mu * total
    cov = lagged - mu * (2.0 * total - z[:, 0] - z[:, -1]) + (n - 1) * mu * mu
    with np.errstate(divide="ignore", invalid="ignore"):
        return cov / var, n * mu * mu / var + 1.0


DECISION_GUARD = 1e-9
""":func:`noise_alpha` decides on round(2 delta) and on delta < 0.25, i.e. where 2 delta crosses
a half-integer. Where the lag-1 autocorrelation from sums (:func:`_lag1_sums`, rounding a few
units of 1e-16 when its growth factor is small) puts 2 delta within this of one, or the factor
is above 1e4, the row's autocorrelation is taken from the mean-removed copy instead
(:func:`_lag1`): the decision is the one that copy gives."""


@functools.lru_cache(maxsize=64)
def _quadratic_basis(n: int) -> tuple[tuple[np.ndarray, float], ...]:
    """The orthogonal basis t, t^2 - <t^2> of :func:`_detrend2` on ``n`` points (t from -1 to
    1), each with its squared norm."""
    t = np.linspace(-1.0, 1.0, n)
    t2 = t * t
    t2 -= t2.mean()
    t.flags.writeable = t2.flags.writeable = False
    return tuple((p, _dot(p, p)) for p in (t, t2))


def _detrend2(z: np.ndarray, scratch: np.ndarray | None = None) -> np.ndarray:
    """Each row of ``z`` (k, n) minus its least-squares quadratic in time (orthogonal basis 1,
    t, t^2 - <t^2>), in place; ``scratch`` (at least (k, n)) holds the fitted trend of each
    basis vector in turn (a new array when not given)."""
    scratch = np.empty(z.shape) if scratch is None else scratch[: z.shape[0], : z.shape[1]]
    z -= z.mean(axis=1, keepdims=True)
    for p, pp in _quadratic_basis(z.shape[1]):
        coef = _row_dots(z, p) / pp
        np.multiply(coef[:, None], p, out=scratch)
        z -= scratch
    return z


NOISE_ID_MAX_POINTS = 1 << 16
"""The noise identification uses at most this many decimated points (the first ones): the
standard error of the lag-1 autocorrelation is then about 4e-3, far below the 0.25 steps of
the decision."""


@dataclass
class NoiseWork:
    """Working memory of :func:`noise_alpha` on phase ``x`` (k, N), reused over every tau:
    ``buffers`` (2, k, min(N, NOISE_ID_MAX_POINTS)) (the decimated points and their
    differences) and, gathered on first use, ``coarse`` = x[:, ::step], every ``step``-th point
    for the smallest power of two ``step`` that leaves at most NOISE_ID_MAX_POINTS of them:
    the decimated points of every factor that is a multiple of ``step`` are a slice of it (the
    same values, read from a small array instead of strided over the whole phase)."""

    x: np.ndarray
    buffers: np.ndarray
    step: int
    coarse: np.ndarray | None = None

    @classmethod
    def of(cls, x: np.ndarray) -> NoiseWork:
        n = x.shape[1]
        step = 1 << max(0, math.ceil(math.log2(max(n / NOISE_ID_MAX_POINTS, 1.0))))
        while (n + step - 1) // step > NOISE_ID_MAX_POINTS:  # rounding in log2
            step *= 2
        return cls(x, np.empty((2, len(x), min(n, NOISE_ID_MAX_POINTS))), step)

    def decimated(self, m: int) -> np.ndarray:
        """x[:, :m * NOISE_ID_MAX_POINTS : m] (a view)."""
        if m < self.step or m % self.step:
            return self.x[:, : m * NOISE_ID_MAX_POINTS : m]
        if self.coarse is None:
            self.coarse = np.ascontiguousarray(self.x[:, :: self.step])
        return self.coarse[:, :: m // self.step]


def noise_alpha(
    x: np.ndarray, m: int, dmax: int = 2, work: NoiseWork | None = None
) -> np.ndarray | None:
    """Noise exponent alpha (int, per axis) at averaging factor ``m`` from phase ``x`` (k, N)
    by the lag-1 autocorrelation method (Riley & Greenhall 2004): decimate by m, remove a
    quadratic, difference until delta = r1 / (1 + r1) < 0.25 (at most ``dmax`` times),
    alpha = -round(2 delta) - 2 d + 2. None when fewer than 30 decimated points remain.
    Every axis at once (those still undecided are differenced again), in ``work``
    (:class:`NoiseWork` of ``x``, made when not given): the decimated points are gathered once,
    detrended and differenced in place, no array allocated per tau."""
    if (x.shape[1] + m - 1) // m < 30:
        return None
    work = NoiseWork.of(x) if work is None else work
    alpha = np.zeros(len(x), dtype=np.int64)
    todo = np.arange(len(x))
    dec = work.decimated(m)
    buffers = work.buffers
    z, spare = buffers[0, :, : dec.shape[1]], 1  # ``spare``: the buffer not holding z
    other = buffers[spare]
    np.copyto(z, dec)
    _detrend2(z, other)
    for d in range(dmax + 1):
        r1, growth = _lag1_sums(z)
        with np.errstate(divide="ignore", invalid="ignore"):
            delta = r1 / (1.0 + r1)
        twice = 2.0 * delta
        unsure = ~(np.abs(twice - np.floor(twice) - 0.5) >= DECISION_GUARD) | ~(growth <= 1e4)
        if unsure.any():
            rows = np.flatnonzero(unsure)
            r1[rows] = _lag1(z[rows], other)
            delta = r1 / (1.0 + r1)
        done = (delta < 0.25) | (d >= dmax) | (z.shape[1] < 4)
        alpha[todo[done]] = -np.round(2.0 * delta[done]).astype(np.int64) - 2 * d + 2
        todo = todo[~done]
        if not len(todo):
            break
        keep = np.flatnonzero(~done)  # the rows still undecided, differenced into ``other``
        diff = other[: len(keep), : z.shape[1] - 1]
        if len(keep) == len(z):
            np.subtract(z[:, 1:], z[:, :-1], out=diff)
        else:
            for i, j in enumerate(keep):
                np.subtract(z[j, 1:], z[j, :-1], out=diff[i])
        z, spare = diff, 1 - spare
        other = buffers[spare]
    return alpha


def _sw(t: np.ndarray, alpha: int) -> np.ndarray:
    """Greenhall's generalised autocovariance sw(t) for noise exponent alpha (eq. 7):
    -|t| (alpha 2), |t|^(3-alpha) (even alpha <= 0), t^(3-alpha) ln|t| (odd alpha)."""
    t = np.asarray(t, dtype=np.float64)
    p = 3 - alpha
    if alpha % 2 == 0:
        return (-1.0 if alpha == 2 else 1.0) * np.abs(t) ** p
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.abs(t) ** p * np.log(np.abs(t))
    return np.where(t == 0, 0.0, out)


def _sx(t: np.ndarray, f: float, alpha: int) -> np.ndarray:
    if np.isinf(f):
        return _sw(t, alpha + 2)
    return f * f * (2.0 * _sw(t, alpha) - _sw(t - 1.0 / f, alpha) - _sw(t + 1.0 / f, alpha))


def _sz(t: np.ndarray, f: float, alpha: int, d: int) -> np.ndarray:
    c = [math.comb(2 * d, d + j) * (-1) ** j for j in range(d + 1)]
    out = c[0] * _sx(t, f, alpha)
    for j in range(1, d + 1):
        out = out + c[j] * (_sx(t - j, f, alpha) + _sx(t + j, f, alpha))
    return out


def _basic_sum(jj: float, mm: float, s: float, f: float, alpha: int, d: int) -> float:
    j = np.arange(1, int(jj))
    first = _sz(np.array(0.0), f, alpha, d) ** 2
    second = (1 - jj / mm) * _sz(np.array(jj / s), f, alpha, d) ** 2
    third = np.sum(2 * (1 - j / mm) * _sz(j / s, f, alpha, d) ** 2)
    return float(first + second + third)


_TABLE1 = {  # modified variances (F = 1): (a0, a1) by alpha, d
    2: [(2 / 3, 1 / 3), (7 / 9, 1 / 2), (22 / 25, 2 / 3)],
    1: [(0.840, 0.345), (0.997, 0.616), (1.141, 0.843)],
    0: [(1.079, 0.368), (1.033, 0.607), (1.184, 0.848)],
    -1: [None, (1.048, 0.534), (1.180, 0.816)],
    -2: [None, (1.302, 0.535), (1.175, 0.777)],
    -3: [None, None, (1.194, 0.703)],
    -4: [None, None, (1.489, 0.702)],
}
_TABLE2 = {  # unmodified variances (F = m)
    2: [(3 / 2, 1 / 2), (35 / 18, 1.0), (231 / 100, 3 / 2)],
    1: [(78.6, 25.2), (790.0, 410.0), (9950.0, 6520.0)],
    0: [(2 / 3, 1 / 6), (2 / 3, 1 / 3), (7 / 9, 1 / 2)],
    -1: [None, (0.852, 0.375), (0.997, 0.617)],
    -2: [None, (1.079, 0.368), (1.033, 0.607)],
    -3: [None, None, (1.053, 0.553)],
    -4: [None, None, (1.302, 0.535)],
}
_TABLE3 = [(6.0, 4.0), (15.23, 12.0), (47.8, 40.0)]  # alpha = 1, unmodified: b0, b1
_J_MAX = 100


@functools.lru_cache(maxsize=4096)
def edf_greenhall(alpha: int, d: int, m: int, n: int, overlapping: bool, modified: bool) -> float:
    """Equivalent degrees of freedom of a d-th difference variance (d = 2 Allan, 3 Hadamard)
    at averaging factor m on n phase points for power-law noise alpha (Greenhall & Riley,
    "Uncertainty of stability variances based on finite differences", 2003; cases 1-4)."""
    if alpha + 2 * d <= 1:
        raise ValueError(f"alpha {alpha} is not defined for difference order {d}")
    f = 1.0 if modified else float(m)
    s = float(m) if overlapping else 1.0
    length = m / f + m * d
    big_m = 1 + np.floor(s * (n - length) / m)
    jj = min(big_m, (d + 1) * s)
    r = big_m / s
    if modified:
        if jj <= _J_MAX:
            return (
                big_m
                * _sz(np.array(0.0), 1.0, alpha, d) ** 2
                / _basic_sum(jj, big_m, s, 1.0, alpha, d)
            )
        if r > d + 1:
            a0, a1 = _TABLE1[alpha][d - 1]
            return r / (a0 - a1 / r)
        mp = _J_MAX / r
        return (
            _J_MAX
            * _sz(np.array(0.0), 1.0, alpha, d) ** 2
            / _basic_sum(_J_MAX, _J_MAX, mp, 1.0, alpha, d)
        )
    if alpha <= 0:
        if jj <= _J_MAX:
            fp = float(m) if m * (d + 1) <= _J_MAX else np.inf
            return (
                big_m
                * _sz(np.array(0.0), fp, alpha, d) ** 2
                / _basic_sum(jj, big_m, s, fp, alpha, d)
            )
        if r > d + 1:
            a0, a1 = _TABLE2[alpha][d - 1]
            return r / (a0 - a1 / r)
        mp = _J_MAX / r
        return (
            _J_MAX
            * _sz(np.array(0.0), np.inf, alpha, d) ** 2
            / _basic_sum(_J_MAX, _J_MAX, mp, np.inf, alpha, d)
        )
    if alpha == 1:
        if jj <= _J_MAX:
            return (
                big_m
                * _sz(np.array(0.0), float(m), 1, d) ** 2
                / _basic_sum(jj, big_m, s, float(m), 1, d)
            )
        b0, b1 = _TABLE3[d - 1]
        if r > d + 1:
            a0, a1 = _TABLE2[1][d - 1]
            return (b0 + b1 * np.log(m)) ** 2 * r / (a0 - a1 / r)
        mp = _J_MAX / r
        return (b0 + b1 * np.log(m)) ** 2 * _J_MAX / _basic_sum(_J_MAX, _J_MAX, mp, mp, 1, d)
    # alpha = 2, unmodified (white phase noise): case 4
    a0 = math.comb(4 * d, 2 * d) / math.comb(2 * d, d) ** 2
    return big_m / max(a0 - (d / 2.0) / r, 1e-12)


def edf_totdev(n_phase: int, m: int, alpha: int) -> float | None:
    """TOTDEV's EDF, SP1065 Table 7: b (T / tau) - c for alpha 0, -1, -2 (None otherwise)."""
    table = {0: (1.50, 0.0), -1: (1.17, 0.22), -2: (0.93, 0.36)}
    if alpha not in table:
        return None
    b, c = table[alpha]
    return b * (n_phase - 1) / m - c


def _edf(kind: str, alpha: int, m: int, n_phase: int) -> float:
    if kind == "totdev":
        edf = edf_totdev(n_phase, m, alpha)
        if edf is not None:
            return edf
        kind = "oadev"
    d = 3 if kind in ("hdev", "ohdev") else 2
    alpha = min(max(alpha, 2 - 2 * d), 2)
    return edf_greenhall(
        int(alpha), d, int(m), int(n_phase), kind in ("oadev", "ohdev"), kind == "mdev"
    )


def alpha_from_slope(taus: np.ndarray, dev: np.ndarray) -> np.ndarray:
    """Noise exponent per point of a deviation curve (t, k) from its local log-log slope mu:
    sigma ~ tau^mu for S_y ~ f^alpha with mu = -(alpha + 1) / 2 (alpha in -2..0; the ADEV
    slope cannot tell white from flicker phase noise). For curves given without their data."""
    lt = np.log(np.asarray(taus, dtype=np.float64))
    ld = np.log(np.asarray(dev, dtype=np.float64).reshape(len(lt), -1))
    mu = np.gradient(ld, lt, axis=0)
    return np.clip(np.round(-2.0 * mu - 1.0), -2, 0).astype(np.int64)


def edf_of_curve(kind: str, m: np.ndarray, alpha: np.ndarray, n_phase: int) -> np.ndarray:
    """EDF (t, k) of a deviation ``kind`` at factors ``m`` on ``n_phase`` points, noise ``alpha``."""
    return np.array(
        [
            [_edf(kind, int(a), int(mi), n_phase) for a in row]
            for row, mi in zip(alpha.reshape(len(m), -1), m, strict=True)
        ]
    )


def chi2_quantile(p: float, dof: np.ndarray) -> np.ndarray:
    """The chi-square quantile ``chi2.ppf(p, dof)`` as ``2 * gammaincinv(dof / 2, p)``."""
    from imupipe.stages.special import gammaincinv  # scipy: loaded on first use (start-up)

    return 2.0 * gammaincinv(0.5 * np.asarray(dof, dtype=np.float64), p)


def confidence(
    dev: Deviation,
    x: np.ndarray,
    ci: float = 0.683,
    known: dict[int, np.ndarray] | None = None,
    monotone: bool = False,
) -> Confidence:
    """Noise type, EDF and chi-square bounds of ``dev`` computed on phase ``x`` (k, N).
    Where fewer than 30 decimated points remain for the noise identification, the last
    identified alpha is carried on (Stable32 switches to the B1 bias ratio there). ``known``
    maps averaging factors to alphas identified before (kept, not identified again).

    ``monotone``: alpha may only stay or fall as tau grows. Each power law's Allan variance goes
    as tau^(-alpha - 1), so longer taus are dominated by smaller exponents (an IMU: quantisation,
    white, flicker, random walk); with few decimated points (30 to 60) the lag-1 method can
    read a random walk as white phase noise (alpha 2), whose EDF is thousands of times larger,
    and the bounds of every longer tau collapse (a 20 min simulated gyro with K = 2e-6: K's
    68 % upper bound came out 1.7e-7)."""
    k = len(x)
    dmax = 3 if dev.kind in ("hdev", "ohdev") else 2
    alphas = np.zeros((len(dev.m), k), dtype=np.int64)
    last = np.zeros(k, dtype=np.int64)
    work = None
    for i, m in enumerate(dev.m):
        a = (known or {}).get(int(m))
        if a is None:
            work = NoiseWork.of(x) if work is None else work
            a = noise_alpha(x, int(m), dmax, work)
        if a is not None:
            last = np.minimum(a, last) if monotone and i else a
        alphas[i] = last
    edf = edf_of_curve(dev.kind, dev.m, alphas, dev.n_phase)
    edf = np.maximum(edf, 1.0)
    p_lo, p_hi = 0.5 + ci / 2.0, 0.5 - ci / 2.0
    lo = dev.dev * np.sqrt(edf / chi2_quantile(p_lo, edf))
    hi = dev.dev * np.sqrt(edf / chi2_quantile(p_hi, edf))
    return Confidence(alphas, edf, lo, hi)


def bends(dev: Deviation, conf: Confidence, bend: float = BEND) -> np.ndarray:
    """Indices j of the intervals [m_j, m_j+1] of a curve at whose ends the log-log slope of any
    axis changes by more than ``bend`` plus twice the change's statistical scatter (each point's
    ln deviation has variance trigamma(edf / 2) / 4; the points are taken as independent)."""
    if len(dev.m) < 3:
        return np.zeros(0, dtype=np.int64)
    lt = np.log(dev.taus)[:, None]
    ld = np.log(dev.dev)
    from imupipe.stages.special import polygamma

    var = polygamma(1, 0.5 * conf.edf) / 4.0
    slope = np.diff(ld, axis=0) / np.diff(lt, axis=0)
    change = np.abs(np.diff(slope, axis=0))  # at interior points 1 .. t-2
    h1, h2 = np.diff(lt, axis=0)[:-1], np.diff(lt, axis=0)[1:]
    scatter = np.sqrt(var[:-2] / h1**2 + var[1:-1] * (1 / h1 + 1 / h2) ** 2 + var[2:] / h2**2)
    at = np.flatnonzero((change > bend + 2.0 * scatter).any(axis=1)) + 1
    return np.unique(np.concatenate([at - 1, at]))


def _merge(a: Deviation, b: Deviation) -> Deviation:
    order = np.argsort(np.concatenate([a.m, b.m]), kind="stable")

    def cat(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.concatenate([u, v])[order]

    return Deviation(
        a.kind,
        cat(a.taus, b.taus),
        cat(a.m, b.m),
        cat(a.dev, b.dev),
        cat(a.n, b.n),
        a.tau0,
        a.n_phase,
    )


def curve(
    x: np.ndarray,
    tau0: float,
    kind: str = "oadev",
    grid: str = "auto",
    points_per_decade: int = 10,
    m: np.ndarray | None = None,
    top: int | None = None,
) -> tuple[Deviation, Confidence]:
    """Deviation ``kind`` of phase ``x`` (k, N) and its confidence, on ``grid`` up to the
    averaging factor ``top`` (default :func:`max_af`), or at exactly the factors ``m``.

    ``auto``: the octave grid, then, in each octave where the curve bends (:func:`bends`: the
    transitions between noise types, a filter's roll-off), two more factors at a third and two
    thirds of the octave. Straight stretches (white noise, a random walk) keep one point per
    octave, the density at which the fit counts points as independent anyway; the cost of a
    curve is one pass over the data per factor."""
    top = max_af(kind, x.shape[1]) if top is None else min(top, max_af(kind, x.shape[1]))
    refine = m is None and grid == "auto"
    if m is None:
        m = tau_grid(grid, top, points_per_decade)
    dev = deviation_of_phase(x, tau0, kind, m)
    conf = confidence(dev, x, monotone=True)
    if not refine or len(dev.m) < 3:
        return dev, conf
    j = bends(dev, conf)
    extra = np.round(dev.m[j][:, None] * 2.0 ** (np.array([1.0, 2.0]) / 3.0)).astype(np.int64)
    extra = np.setdiff1d(extra.ravel(), dev.m)
    extra = extra[extra <= top]
    if not len(extra):
        return dev, conf
    known = {int(mi): conf.alpha[i] for i, mi in enumerate(dev.m)}
    merged = _merge(dev, deviation_of_phase(x, tau0, kind, extra))
    return merged, confidence(merged, x, known=known, monotone=True)
