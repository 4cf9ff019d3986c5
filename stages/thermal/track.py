"""The temperature a thermal correction sees at every IMU sample, computed the same way, bit for
bit, on a whole log and on a log read in batches of any size.

Per IMU sample ``i`` at ``t_i`` (int64 ns):

- ``T_i``: the temperature stream linearly interpolated at ``t_i`` (held before its first and
  after its last sample; NaN/Inf temperature samples are ignored). ``Ta_i`` likewise from the
  ``ambient_temperature`` column when asked for.
- **Blocks** (the block means of the temperature-calibration literature, e.g. the ``ImuDataSum``
  of the MATLAB example in "MEMS 惯性测量组件的温度误差补偿模型研究"): consecutive IMU samples
  are grouped into blocks of ``window`` samples, or of ``window_s`` seconds. A time block is a bin
  of ``window_s`` counted from the first sample of its *segment*, a segment being a run of
  samples without a gap longer than ``window_s``: a burst of a gappy log (5 s every 5 min) never
  shares a block with the next burst. Each block has its sample count, its centre (the mean stamp,
  exact in integer ns) and the mean ``T`` (and ``Ta``) of its samples.
- ``dT_k`` (degC/s): the rate of the block temperatures, the three-point second-order derivative
  over the (unevenly spaced) block centres, one-sided at the log's first and last block.
- ``Ts_k`` (lag model): the sensing element's temperature, a first-order lag of the measured one,
  ``dTs/dt = (T - Ts) / tau``, integrated exactly for ``T`` linear between block centres and
  starting in equilibrium (``Ts_0 = T_0``); its rate ``dTs_k = (T_k - Ts_k) / tau`` (exact).
- Per sample, ``dT_i``, ``Ts_i``, ``dTs_i`` (and ``dTa_i``) are the block values linearly
  interpolated at ``t_i`` over the block centres (held at the ends).

**Streaming** (:class:`Track`): a sample's values are final once the temperature stream has a
sample after it and, when block values are needed, once the blocks around it are complete (the
rate of a block needs the next block): rows wait at most about three blocks plus the time to the
next temperature sample. Memory holds the rows waiting, the temperature samples around them and a
few blocks. Equality with the whole-log computation is exact because every quantity is computed
from the same operands in the same order: interpolation and differences work on integer-ns times
(exact in float64 for spans under 104 days), a block is reduced in one call once complete, and the
lag's recursion is carried across batches (:func:`first_order_lag`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from imupipe.readers.table import interpolate

LAG_CHUNK = 500.0
"""The lag recursion is solved in closed form over chunks of at most this many time constants
(``exp(500)`` stays far from float64 overflow)."""


@dataclass(frozen=True)
class Blocking:
    """Block size: ``window`` samples or ``window_s`` seconds (exactly one)."""

    window: int | None = None
    window_s: float | None = None

    def __post_init__(self) -> None:
        if (self.window is None) == (self.window_s is None):
            raise ValueError("give exactly one of window and window_s")
        if self.window is not None and self.window < 1:
            raise ValueError("window must be >= 1 sample")
        if self.window_s is not None and not self.window_s > 0:
            raise ValueError("window_s must be > 0")

    @property
    def width_ns(self) -> int:
        return max(1, int(round(float(self.window_s) * 1e9)))


# -- blocks ----------------------------------------------------------------------------------


@dataclass
class BlockCarry:
    """Where the block assignment stands after the samples seen so far."""

    count: int = 0
    block: int = -1
    segment: int = -1
    last_t: int = 0
    anchor: int = 0
    bin: int = -1


def assign_blocks(
    t_ns: np.ndarray, blocking: Blocking, carry: BlockCarry
) -> tuple[np.ndarray, np.ndarray, BlockCarry]:
    """Block and segment index (global, increasing) of each stamp, continuing ``carry``."""
    n = len(t_ns)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), carry
    if blocking.window is not None:
        block = (carry.count + np.arange(n, dtype=np.int64)) // int(blocking.window)
        segment = np.zeros(n, np.int64)
        return block, segment, replace(carry, count=carry.count + n, block=int(block[-1]))
    width = blocking.width_ns
    prev = np.r_[carry.last_t, t_ns[:-1]]
    new_segment = (t_ns - prev) > width
    if carry.count == 0:
        new_segment[0] = True
    at = np.maximum.accumulate(np.where(new_segment, np.arange(n), -1))
    anchor = np.where(at >= 0, t_ns[np.maximum(at, 0)], carry.anchor)
    bins = (t_ns - anchor) // width
    new_block = new_segment | (bins != np.r_[carry.bin, bins[:-1]])
    block = carry.block + np.cumsum(new_block)
    segment = carry.segment + np.cumsum(new_segment)
    out = BlockCarry(
        count=carry.count + n,
        block=int(block[-1]),
        segment=int(segment[-1]),
        last_t=int(t_ns[-1]),
        anchor=int(anchor[-1]),
        bin=int(bins[-1]),
    )
    return block, segment, out


@dataclass
class BlockTable:
    """Complete blocks: ``id``, ``segment``, ``count``, ``first``/``last``/``centre`` (ns),
    ``temps`` (m, k) mean temperatures (k channels), and the derived ``rate`` (m, k) degC/s,
    ``lagged`` and ``lag_rate`` (m,) (NaN until known)."""

    id: np.ndarray
    segment: np.ndarray
    count: np.ndarray
    first: np.ndarray
    last: np.ndarray
    centre: np.ndarray
    temps: np.ndarray
    rate: np.ndarray
    lagged: np.ndarray
    lag_rate: np.ndarray

    @classmethod
    def empty(cls, channels: int) -> BlockTable:
        i = np.zeros(0, np.int64)
        f = np.zeros((0, channels))
        return cls(i, i, i, i, i, i, f, f.copy(), np.zeros(0), np.zeros(0))

    def __len__(self) -> int:
        return len(self.id)

    def take(self, index: np.ndarray | slice) -> BlockTable:
        return BlockTable(
            **{k: getattr(self, k)[index] for k in self.__dataclass_fields__}  # type: ignore[arg-type]
        )

    @staticmethod
    def concat(a: BlockTable, b: BlockTable) -> BlockTable:
        return BlockTable(
            **{
                k: np.concatenate([getattr(a, k), getattr(b, k)])
                for k in BlockTable.__dataclass_fields__
            }
        )

    def complete(self, blocking: Blocking) -> np.ndarray:
        """Blocks that span their whole window (``window`` samples; or, for ``window_s``, a
        block followed by another of its segment), or are a whole segment (a burst shorter than
        the window). The last block of a log or of a segment cut short is not complete."""
        if blocking.window is not None:
            return self.count == blocking.window
        same_next = np.r_[self.segment[1:] == self.segment[:-1], False]
        alone = ~same_next & ~np.r_[False, self.segment[1:] == self.segment[:-1]]
        return same_next | alone


def reduce_blocks(
    t_ns: np.ndarray, temps: np.ndarray, block: np.ndarray, segment: np.ndarray
) -> BlockTable:
    """Block values of complete runs of samples (``temps`` (n, k))."""
    n = len(t_ns)
    starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
    count = np.diff(np.r_[starts, n])
    first = t_ns[starts]
    last = t_ns[starts + count - 1]
    rel = t_ns - np.repeat(first, count)
    centre = first + (2 * np.add.reduceat(rel, starts) + count) // (2 * count)
    means = (
        np.column_stack(
            [
                np.add.reduceat(np.ascontiguousarray(temps[:, j]), starts)
                for j in range(temps.shape[1])
            ]
        )
        / count[:, None]
    )
    m = len(starts)
    return BlockTable(
        id=block[starts],
        segment=segment[starts],
        count=count,
        first=first,
        last=last,
        centre=centre,
        temps=means,
        rate=np.full((m, temps.shape[1]), np.nan),
        lagged=np.full(m, np.nan),
        lag_rate=np.full(m, np.nan),
    )


def interior_rate(centre: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The three-point derivative at ``centre[1:-1]`` (second order on uneven spacing), per
    column of ``values`` (m, k); (m - 2, k)."""
    hd = (np.diff(centre[:-1]) * 1e-9)[:, None]
    hs = (np.diff(centre[1:]) * 1e-9)[:, None]
    back = values[1:-1] - values[:-2]
    ahead = values[2:] - values[1:-1]
    return (hs * hs * back + hd * hd * ahead) / (hd * hs * (hd + hs))


def edge_rate(centre: np.ndarray, values: np.ndarray) -> np.ndarray:
    """One-sided derivative between two blocks (1, k)."""
    h = float(centre[1] - centre[0]) * 1e-9
    return (values[1:2] - values[0:1]) / h


# -- the first-order lag ---------------------------------------------------------------------


@dataclass
class LagCarry:
    """The lag recursion's state after the last block: its centre (ns), temperature, lagged
    value, cumulative time in time constants ``e``, and the closed-form chunk it is in."""

    centre: int
    temp: float
    value: float
    e: float
    chunk: int
    e_start: float
    partial: float


def first_order_lag(
    centre: np.ndarray, temp: np.ndarray, tau_s: float, carry: LagCarry | None = None
) -> tuple[np.ndarray, LagCarry | None]:
    """``Ts`` at the block centres for ``dTs/dt = (T - Ts)/tau``, ``T`` linear between centres.

    Step k (``x = dt_k / tau``, ``a = exp(-x)``, ``c = (1 - a)/x``):
    ``Ts_k = a Ts_{k-1} + (1 - c) T_k + (c - a) T_{k-1}`` (exact for a linear input). Solved in
    closed form, ``Ts_k = exp(-(E_k - E_s)) (a_s Ts_{s-1} + sum_{j=s..k} u_j exp(E_j - E_s))``
    with ``E`` the cumulative time in time constants, over chunks of ``LAG_CHUNK`` time
    constants; ``carry`` continues a previous call exactly (sequential sums only)."""
    m = len(centre)
    if m == 0:
        return np.zeros(0), carry
    temp = np.asarray(temp, dtype=np.float64)
    if carry is None:  # equilibrium at the first block
        t0 = float(temp[0])
        carry = LagCarry(int(centre[0]), t0, t0, 0.0, 0, 0.0, t0)
        rest, carry = first_order_lag(centre[1:], temp[1:], tau_s, carry)
        return np.r_[t0, rest], carry
    out = np.empty(m)
    x = np.diff(np.r_[carry.centre, centre]) * 1e-9 / float(tau_s)
    e = np.cumsum(np.r_[carry.e, x])[1:]
    a = np.exp(-x)
    c = np.ones(m)
    pos = x > 0
    c[pos] = -np.expm1(-x[pos]) / x[pos]
    u = (1.0 - c) * temp + (c - a) * np.r_[carry.temp, temp[:-1]]
    chunk = np.floor(e / LAG_CHUNK).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, chunk[1:] != chunk[:-1]])
    value, partial, e_start = carry.value, carry.partial, carry.e_start
    for s, stop in zip(starts, np.r_[starts[1:], m], strict=True):  # chunks, not samples
        if s == 0 and chunk[0] == carry.chunk:
            terms = u[s:stop] * np.exp(e[s:stop] - e_start)
            sums = np.cumsum(np.r_[partial, terms])[1:]
        else:
            e_start = float(e[s])
            first = a[s] * value + u[s]
            terms = u[s + 1 : stop] * np.exp(e[s + 1 : stop] - e_start)
            sums = np.cumsum(np.r_[first, terms])
        out[s:stop] = np.exp(-(e[s:stop] - e_start)) * sums
        value, partial = float(out[stop - 1]), float(sums[-1])
    carry = LagCarry(
        int(centre[-1]), float(temp[-1]), value, float(e[-1]), int(chunk[-1]), e_start, partial
    )
    return out, carry


# -- the streaming track ---------------------------------------------------------------------


@dataclass
class TrackSpec:
    """What a correction needs: ``channels`` (``temperature`` [, ``ambient_temperature``]),
    whether it needs block values (rates or the lag), and the lag's time constant (s)."""

    channels: tuple[str, ...] = ("temperature",)
    blocking: Blocking | None = None
    lag_s: float | None = None
    keep_blocks: bool = False
    """Keep every block (the fit's view of a whole log); a correction keeps only a few."""

    @property
    def needs_blocks(self) -> bool:
        return self.blocking is not None


@dataclass
class Variables:
    """Per-sample values of the samples made final by a push: ``T`` (n, k) temperature per
    channel, ``rate`` (n, k) degC/s, ``lagged`` and ``lag_rate`` (n,), ``block`` (n,) the block
    index of each sample (empty arrays for what was not asked for)."""

    T: np.ndarray
    rate: np.ndarray
    lagged: np.ndarray
    lag_rate: np.ndarray
    block: np.ndarray

    def __len__(self) -> int:
        return len(self.T)

    @staticmethod
    def concat(parts: list[Variables]) -> Variables:
        return Variables(
            *(
                np.concatenate([getattr(p, k) for p in parts])
                for k in Variables.__dataclass_fields__
            )
        )


class Track:
    """Feed IMU stamps and temperature samples in time order (:meth:`push`), then
    :meth:`finish`; each call returns the :class:`Variables` of the IMU samples made final, in
    order. A whole log pushed at once gives the same values as any sequence of pushes.

    Pending samples (pushed, not yet returned) are kept in arrays; the first ``resolved`` of them
    have their temperatures, the first ``reduced`` belong to complete blocks (``blocks``, which
    also keeps the block before them); the rates of the first ``final`` kept blocks are known.
    """

    def __init__(self, spec: TrackSpec) -> None:
        self.spec = spec
        k = len(spec.channels)
        self.temp_t = [np.zeros(0, np.int64) for _ in range(k)]
        self.temp_v = [np.zeros(0) for _ in range(k)]
        self.seen = [False] * k
        self.t = np.zeros(0, np.int64)
        self.block = np.zeros(0, np.int64)
        self.segment = np.zeros(0, np.int64)
        self.temps = np.zeros((0, k))
        self.resolved = 0
        self.reduced = 0
        self.last_t: int | None = None
        self.carry = BlockCarry()
        self.lag: LagCarry | None = None
        self.blocks = BlockTable.empty(k)
        self.final = 0
        self.dropped = 0
        """Blocks dropped from the front of ``blocks`` (memory bound)."""
        self.finished = False

    def missing_channels(self) -> list[str]:
        """Channels that have had no finite sample so far."""
        return [c for c, seen in zip(self.spec.channels, self.seen, strict=True) if not seen]

    def push(self, imu_t: np.ndarray, temps: list[tuple[np.ndarray, np.ndarray]]) -> Variables:
        """IMU stamps (int64 ns) and, per channel, (stamps, values) of new temperature samples."""
        for j, (tt, vv) in enumerate(temps):
            ok = np.isfinite(vv)
            if ok.any():
                self.seen[j] = True
                self.temp_t[j] = np.concatenate([self.temp_t[j], np.asarray(tt, np.int64)[ok]])
                self.temp_v[j] = np.concatenate([self.temp_v[j], np.asarray(vv, np.float64)[ok]])
        imu_t = np.asarray(imu_t, dtype=np.int64)
        if len(imu_t):
            block = segment = np.zeros(len(imu_t), np.int64)
            if self.spec.blocking is not None:
                block, segment, self.carry = assign_blocks(imu_t, self.spec.blocking, self.carry)
            self.t = np.concatenate([self.t, imu_t])
            self.block = np.concatenate([self.block, block])
            self.segment = np.concatenate([self.segment, segment])
            fill = np.full((len(imu_t), self.temps.shape[1]), np.nan)
            self.temps = np.concatenate([self.temps, fill])
            self.last_t = int(imu_t[-1])
        return self._advance()

    def finish(self) -> Variables:
        """End of the log: every remaining sample is made final (unless a channel never had a
        sample: see :meth:`missing_channels`)."""
        self.finished = True
        return self._advance()

    # -- internals ---------------------------------------------------------------------------
    def _advance(self) -> Variables:
        self._resolve()
        if self.spec.blocking is None:
            return self._emit(self.resolved)
        self._reduce()
        self._rates()
        if self.finished and self.reduced == len(self.t):
            ready = len(self.t)
        elif self.final == 0:
            ready = 0
        else:
            horizon = self.blocks.centre[self.final - 1]
            ready = int(np.searchsorted(self.t[: self.reduced], horizon, side="left"))
        return self._emit(ready)

    def _resolve(self) -> None:
        """Temperatures of the pending samples that have a temperature sample after them (of
        every channel), or of all at the end."""
        n = len(self.t)
        if self.missing_channels():
            return
        limit = n
        if not self.finished:
            for tt in self.temp_t:
                limit = min(limit, int(np.searchsorted(self.t, tt[-1], side="left")))
        if limit > self.resolved:
            todo = self.t[self.resolved : limit]
            for j, (tt, vv) in enumerate(zip(self.temp_t, self.temp_v, strict=True)):
                self.temps[self.resolved : limit, j] = interpolate(tt, vv, todo)
            self.resolved = limit
        # keep the temperature samples from the last one at or before the first unresolved
        # sample: the only ones a later interpolation can use
        at = self.t[self.resolved] if self.resolved < n else self.last_t
        if at is None:
            return
        for j, tt in enumerate(self.temp_t):
            cut = max(int(np.searchsorted(tt, at, side="right")) - 1, 0)
            if cut:
                self.temp_t[j], self.temp_v[j] = tt[cut:], self.temp_v[j][cut:]

    def _reduce(self) -> None:
        """Reduce the blocks whose samples are all resolved and that are complete (a later
        block has begun, or the log ended)."""
        stop = self.resolved
        if stop <= self.reduced:
            return
        last = self.block[stop - 1]
        complete = bool(self.block[stop] > last) if stop < len(self.t) else self.finished
        if not complete:
            stop = self.reduced + int(
                np.searchsorted(self.block[self.reduced : stop], last, "left")
            )
        if stop <= self.reduced:
            return
        sl = slice(self.reduced, stop)
        new = reduce_blocks(self.t[sl], self.temps[sl], self.block[sl], self.segment[sl])
        if self.spec.lag_s:
            new.lagged, self.lag = first_order_lag(
                new.centre, new.temps[:, 0], self.spec.lag_s, self.lag
            )
            new.lag_rate = (new.temps[:, 0] - new.lagged) / self.spec.lag_s
        self.blocks = BlockTable.concat(self.blocks, new)
        self.reduced = stop

    def _rates(self) -> None:
        """Rates of the blocks whose neighbours are known (all at the end)."""
        b = self.blocks
        m = len(b)
        lo, hi = self.final, (m if self.finished else m - 1)
        if hi <= lo:
            return
        if lo == 0 and self.dropped == 0:  # the log's first block: one-sided
            b.rate[0] = edge_rate(b.centre[:2], b.temps[:2])[0] if m >= 2 else 0.0
            lo = 1
        at_end = self.finished and hi == m
        inner = hi - 1 if at_end else hi
        if inner > lo:
            b.rate[lo:inner] = interior_rate(
                b.centre[lo - 1 : inner + 1], b.temps[lo - 1 : inner + 1]
            )
        if at_end and m - 1 >= lo:  # the log's last block: one-sided
            b.rate[m - 1] = edge_rate(b.centre[m - 2 :], b.temps[m - 2 :])[0]
        self.final = hi

    def _emit(self, ready: int) -> Variables:
        t = self.t[:ready]
        k = self.temps.shape[1]
        empty = np.zeros(0)
        rate, lagged, lag_rate, block = np.zeros((ready, 0)), empty, empty, empty.astype(np.int64)
        if self.spec.blocking is not None:
            b = self.blocks
            known = slice(0, self.final)
            rate = np.zeros((ready, k))
            if ready:
                rate = interpolate(b.centre[known], b.rate[known], t).reshape(ready, k)
            block = self.block[:ready].copy()
            if self.spec.lag_s:
                lagged = lag_rate = np.zeros(ready)
                if ready:
                    lagged = interpolate(b.centre[known], b.lagged[known], t)
                    lag_rate = interpolate(b.centre[known], b.lag_rate[known], t)
        out = Variables(self.temps[:ready].copy(), rate, lagged, lag_rate, block)
        if ready:
            self.t, self.block = self.t[ready:], self.block[ready:]
            self.segment, self.temps = self.segment[ready:], self.temps[ready:]
            self.resolved -= ready
            self.reduced = max(self.reduced - ready, 0)
            self._trim_blocks()
        return out

    def _trim_blocks(self) -> None:
        """Drop the blocks nothing pending can use: keep from the last block whose centre is
        at or before the first pending sample, and the last block with a known rate (the next
        rate needs it)."""
        if self.spec.keep_blocks or self.final == 0:
            return
        keep = self.final - 1
        if len(self.t):
            at = int(np.searchsorted(self.blocks.centre, self.t[0], side="right")) - 1
            keep = min(keep, max(at, 0))
        if keep > 0:
            self.blocks = self.blocks.take(slice(keep, None))
            self.final -= keep
            self.dropped += keep
