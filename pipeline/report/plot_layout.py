"""The layout of a plot's axes, shared by the Rerun 2D plots and the report's SVG figures.

Pure numpy, no drawing: round tick values and their labels for linear axes, powers of ten (and
2 and 5 times them) for logarithmic ones, the mapping of data values to fractions [0, 1] of an
axis (:class:`Axis`; fraction 0 at the low end), and a curve cut into polylines where a value
is missing (:func:`strips`). Values are in the unit a plot shows (see
:mod:`imupipe.pipeline.report.figures`); positions are fractions of the axis, or, in :func:`strips`,
the caller's units (Rerun scene units, SVG pixels).
"""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """Round tick values (steps of 1, 2, 2.5 or 5 x 10^k) covering [lo, hi]: of the steps
    giving 3 to n + 2 intervals, the one that pads the range least (then the larger step)."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return np.array([0.0, 1.0])
    if hi <= lo:
        pad = abs(lo) * 0.1 or 1.0
        lo, hi = lo - pad, hi + pad
    if not np.isfinite(hi - lo):  # a span past float64's range (cells of 1e308): the ends
        return np.array([lo, hi])
    mag = 10.0 ** math.floor(math.log10((hi - lo) / n))
    best = None
    for step in (m * mag for m in (0.5, 1, 2, 2.5, 5, 10, 20)):
        # data a hair past a round value (-40.006 degC) does not add a whole step
        first = math.floor(lo / step + 0.02) * step
        last = math.ceil(hi / step - 0.02) * step
        if not math.isfinite(last - first):  # near float64's largest values
            continue
        count = round((last - first) / step)
        if 3 <= count <= n + 2 and (best is None or (last - first, -step) < best[0]):
            best = ((last - first, -step), first, step, count)
    if best is None:
        return np.array([lo, hi])
    _, first, step, count = best
    return first + step * np.arange(count + 1)


def _fmt_sci(v: float, digits: int) -> str:
    if v == 0:
        return "0"
    mantissa, exponent = f"{v:.{digits - 1}e}".split("e")
    if "." in mantissa:
        mantissa = mantissa.rstrip("0").rstrip(".")
    return f"{mantissa}e{int(exponent)}"


def tick_labels(ticks: np.ndarray) -> list[str]:
    """Labels of linear ticks: as many decimals as the step needs (scientific notation for very
    small or large values, with as many digits as keep the labels distinct)."""
    with np.errstate(over="ignore"):  # ends near float64's limit: an infinite step
        step = float(np.min(np.diff(ticks))) if len(ticks) > 1 else 1.0
    if float(np.max(np.abs(ticks))) >= 1e5 or step < 1e-4:
        for digits in range(1, 6):
            labels = [_fmt_sci(v, digits) for v in ticks]
            if len(set(labels)) == len(labels):
                break
        return labels
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if abs(step * 10**decimals - round(step * 10**decimals)) > 1e-6:
        decimals += 1
    return [
        f"{v:.{decimals}f}".replace("-0." + "0" * decimals, "0." + "0" * decimals) for v in ticks
    ]


def pow10_label(k: int) -> str:
    """10^k as a short decimal (``0.001``, ``100``) or ``1e-5``: Rerun's log tick labels."""
    if 0 <= k <= 4:
        return f"{10**k}"
    if -3 <= k < 0:
        return f"{10.0**k:.{-k}f}"
    return f"1e{k}"


SUPERSCRIPT = str.maketrans(
    "-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079"
)


def pow10_text(value: float) -> str:
    """A log tick label as plain text with superscripts: ``10\u207b\u00b3``,
    ``2\u00d710\u207b\u00b3`` ("" for a value that is not positive): the report's labels."""
    if not value > 0:
        return ""
    k = int(np.floor(np.log10(value) + 1e-9))
    mantissa = value / 10.0**k
    power = f"10{str(k).translate(SUPERSCRIPT)}"
    return power if abs(mantissa - 1.0) < 1e-6 else f"{mantissa:.3g}\u00d7{power}"


SPAN_LIMIT = float(np.finfo(np.float64).max) / 4
"""Data drawn on a linear axis is clipped to +-this, so that the axis's span, padded, stays a
finite float64 (a CSV cell of 1e308 is a number)."""


class Axis:
    """Maps data values to [0, 1] along one axis (linear, or log10), with its ticks.

    ``lo`` and ``hi`` are the ends (log10 of them on a log axis); a linear axis made from data
    ends on round ticks, a log axis on whole decades."""

    def __init__(self, values: list[np.ndarray], log: bool) -> None:
        data = np.concatenate([np.ravel(v) for v in values]) if values else np.zeros(0)
        data = np.clip(data[np.isfinite(data)], -SPAN_LIMIT, SPAN_LIMIT)
        self.log = log
        if log:
            data = data[data > 0]
            if len(data) == 0:
                data = np.array([1.0, 10.0])
            a = math.floor(math.log10(data.min()))
            b = max(math.ceil(math.log10(data.max())), a + 1)
            self.lo, self.hi = float(a), float(b)
            ks = np.arange(a, b + 1, 1 if b - a <= 7 else 2)
            self.ticks = 10.0**ks
            self.labels = [pow10_label(int(k)) for k in ks]
        else:
            if len(data) == 0:
                data = np.array([0.0, 1.0])
            self.ticks = nice_ticks(float(data.min()), float(data.max()))
            self.lo, self.hi = float(self.ticks[0]), float(self.ticks[-1])
            self.labels = tick_labels(self.ticks)

    @classmethod
    def within(cls, lo: float, hi: float, n: int = 5, step: float | None = None) -> Axis:
        """A linear axis from exactly ``lo`` to ``hi`` (an equal-aspect panel, a map in
        degrees), with the round ticks (:func:`nice_ticks`, or the multiples of ``step``) that
        fall inside."""
        axis = cls([], log=False)
        if step is None:
            ticks = nice_ticks(lo, hi, n)
            eps = 1e-9 * (hi - lo)
            axis.ticks = ticks[(ticks >= lo - eps) & (ticks <= hi + eps)]
        else:
            axis.ticks = np.arange(math.ceil(lo / step), math.floor(hi / step) + 1) * step
        axis.labels = tick_labels(axis.ticks)
        axis.lo, axis.hi = float(lo), float(hi)
        return axis

    def pad(self, fraction: float) -> None:
        """Widen a linear axis by ``fraction`` of its span at both ends, past its first and last
        ticks: data on a round value then does not lie on the frame."""
        if not self.log:
            extra = fraction * (self.hi - self.lo)
            self.lo, self.hi = self.lo - extra, self.hi + extra

    def minor(self) -> np.ndarray:
        """On a log axis, 2 and 5 times the powers of ten strictly inside it; else none."""
        if not self.log:
            return np.zeros(0)
        decades = 10.0 ** np.arange(math.floor(self.lo), math.ceil(self.hi) + 1)
        at = (decades[:, None] * [2.0, 5.0]).ravel()
        return at[(at > 10.0**self.lo) & (at < 10.0**self.hi)]

    def __call__(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=np.float64)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan)
        with np.errstate(over="ignore"):  # past float64's range (a 1e308 cell): inf, not drawn
            return (v - self.lo) / (self.hi - self.lo)


def runs(ok: np.ndarray) -> list[slice]:
    """The index ranges where ``ok`` holds at two or more consecutive places: the pieces of a
    curve between its missing values."""
    breaks = np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1
    edges = [0, *breaks.tolist(), len(ok)]
    return [slice(a, b) for a, b in pairwise(edges) if b - a > 1 and ok[a]]


def strips(x: np.ndarray, y: np.ndarray, width: float, height: float) -> list[np.ndarray]:
    """The polylines of one curve given as axis fractions ``x``, ``y`` (NaN: missing), in a
    plot area of ``width`` x ``height`` with y pointing down: (m, 2) arrays, one per run of
    :func:`runs`."""
    pts = np.column_stack([x * width, (1.0 - y) * height])
    return [pts[r] for r in runs(np.isfinite(x) & np.isfinite(y))]
