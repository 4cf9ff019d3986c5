"""Curves that are not over time, drawn as Rerun 2D plots.

Rerun's time-series view plots against the timeline the time panel shows, on linear axes. A
curve over tau or temperature logged on a timeline of its own therefore opens empty (the time
panel starts on ``time``) and cannot be read on log-log axes. So such a plot is drawn in a
``Spatial2DView``: its curves as line strips (or points) mapped into a plot area of W x H scene
units (log10 for logarithmic axes, y pointing up), and around them the frame, the grid, the tick
labels, the x-axis title and a legend, all logged as static 2D primitives. It opens showing all
of it, on any timeline; hovering a line names it. Line widths and marker sizes are in UI points
(negative radii), so they stay thin when zooming. Confidence bands and guide lines (the terms of
a model) lie beneath the data points, fitted curves over them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from imupipe.pipeline.figures import Plot

W, H = 160.0, 100.0
"""The plot area, in scene units."""
MARGIN_LEFT, MARGIN_TOP, MARGIN_BOTTOM = 34.0, 6.0, 27.0
CHAR_WIDTH = 4.2  # scene units per character of a label in a view of ~500 px (for the legend)
FRAME_COLOR = (128, 128, 128)
GRID_COLOR = (150, 150, 150)
TEXT_COLOR = (110, 110, 110)
LINE_RADIUS = -1.5  # negative radii are UI points
BAND_RADIUS = -1.0
POINT_RADIUS = -2.0
GUIDE_RADIUS = -1.0
# bands and guide lines (model terms) beneath the data, fitted lines over it
BAND_ORDER, GUIDE_ORDER, POINT_ORDER, LINE_ORDER = 10.0, 15.0, 20.0, 30.0


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """Round tick values (steps of 1, 2, 2.5 or 5 x 10^k) covering [lo, hi]: of the steps
    giving 3 to n + 2 intervals, the one that pads the range least (then the larger step)."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return np.array([0.0, 1.0])
    if hi <= lo:
        pad = abs(lo) * 0.1 or 1.0
        lo, hi = lo - pad, hi + pad
    mag = 10.0 ** math.floor(math.log10((hi - lo) / n))
    best = None
    for step in (m * mag for m in (0.5, 1, 2, 2.5, 5, 10, 20)):
        # data a hair past a round value (-40.006 degC) does not add a whole step
        first = math.floor(lo / step + 0.02) * step
        last = math.ceil(hi / step - 0.02) * step
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
    if 0 <= k <= 4:
        return f"{10**k}"
    if -3 <= k < 0:
        return f"{10.0**k:.{-k}f}"
    return f"1e{k}"


class Axis:
    """Maps data values to [0, 1] along one axis (linear, or log10), with its ticks."""

    def __init__(self, values: list[np.ndarray], log: bool) -> None:
        data = np.concatenate([np.ravel(v) for v in values]) if values else np.zeros(0)
        data = data[np.isfinite(data)]
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

    def __call__(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=np.float64)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan)
        return (v - self.lo) / (self.hi - self.lo)


def _strips(x: np.ndarray, y: np.ndarray) -> list[np.ndarray]:
    """Plot-coordinate polylines of one curve, broken where a value is missing."""
    ok = np.isfinite(x) & np.isfinite(y)
    pts = np.column_stack([x * W, (1.0 - y) * H])
    breaks = np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1
    pieces = zip(np.split(pts, breaks), np.split(ok, breaks), strict=True)
    return [seg for seg, good in pieces if len(seg) > 1 and good[0]]


def right_margin(plot: Plot) -> float:
    """Room right of the plot area for the legend (centred labels): its longest name."""
    longest = max((len(n) for s in plot.series for n in s.names), default=0)
    return min(max(12.0 + CHAR_WIDTH * longest, 40.0), 140.0)


def axes_root(plot: Plot) -> str:
    """Where a plot's frame, ticks and legend are logged."""
    return f"/{plot.stage}/{plot.key}/axes"


def _series(plot: Plot, xa: Axis, ya: Axis) -> tuple[list, list[tuple[str, tuple]]]:
    """The curves in plot coordinates, and the legend entries (name, colour)."""
    out: list[tuple[str, Any]] = []
    legend: list[tuple[str, tuple]] = []
    for s in plot.series:
        x = xa(s.x)
        if s.style == "band":
            strips = _strips(x, ya(s.values[:, 0])) + _strips(x, ya(s.values[:, 1]))
            band = rr.LineStrips2D(
                strips,
                colors=[s.colors[0]],
                radii=BAND_RADIUS,
                labels=[s.names[0]],
                show_labels=False,
                draw_order=BAND_ORDER,
            )
            out.append((s.entity, band))
            legend.append((s.names[0], s.colors[0]))
        elif s.style == "points":
            pts, cols = [], []
            for j, name in enumerate(s.names):
                y = ya(s.values[:, j])
                ok = np.isfinite(x) & np.isfinite(y)
                pts.append(np.column_stack([x[ok] * W, (1.0 - y[ok]) * H]))
                cols += [s.colors[j]] * int(ok.sum())
                legend.append((name, s.colors[j]))
            points = rr.Points2D(
                np.concatenate(pts), colors=cols, radii=POINT_RADIUS, draw_order=POINT_ORDER
            )
            out.append((s.entity, points))
        else:
            strips, cols, labels = [], [], []
            for j, name in enumerate(s.names):
                parts = _strips(x, ya(s.values[:, j]))
                strips += parts
                cols += [s.colors[j]] * len(parts)
                labels += [name] * len(parts)
                legend.append((name, s.colors[j]))
            guide = s.style == "guide"
            lines = rr.LineStrips2D(
                strips,
                colors=cols,
                radii=GUIDE_RADIUS if guide else LINE_RADIUS,
                labels=labels,
                show_labels=False,
                draw_order=GUIDE_ORDER if guide else LINE_ORDER,
            )
            out.append((s.entity, lines))
    return out, legend


def draw(plot: Plot) -> list[tuple[str, Any]]:
    """(entity, archetype) pairs of one plot: its curves in plot coordinates, then the frame,
    grid, tick labels, x-axis title and legend under :func:`axes_root`."""
    xa = Axis([s.x for s in plot.series], plot.log_x)
    ya = Axis([s.values for s in plot.series], plot.log_y)
    out, legend = _series(plot, xa, ya)
    root = axes_root(plot)
    frame = np.array([[0, 0], [W, 0], [W, H], [0, H], [0, 0]], dtype=np.float64)
    grid = [np.array([[xa(t) * W, 0], [xa(t) * W, H]]) for t in xa.ticks[1:-1]]
    grid += [np.array([[0, (1 - ya(t)) * H], [W, (1 - ya(t)) * H]]) for t in ya.ticks[1:-1]]
    out.append((f"{root}/grid", rr.LineStrips2D(grid, colors=[GRID_COLOR], radii=-0.5)))
    out.append((f"{root}/frame", rr.LineStrips2D([frame], colors=[FRAME_COLOR], radii=-1.0)))

    def text(where: str, xy: list[list[float]], labels: list[str], colors: list[Any]) -> None:
        points = rr.Points2D(xy, labels=labels, colors=colors, radii=0.0, show_labels=True)
        out.append((f"{root}/{where}", points))

    text("x_ticks", [[xa(t) * W, H + 8.0] for t in xa.ticks], xa.labels, [TEXT_COLOR])
    y_ticks = [[-MARGIN_LEFT / 2, (1 - ya(t)) * H] for t in ya.ticks]
    text("y_ticks", y_ticks, ya.labels, [TEXT_COLOR])
    text("x_title", [[W / 2, H + 20.0]], [plot.x_heading], [TEXT_COLOR])
    if legend:
        text(
            "legend",
            [[W + right_margin(plot) / 2, 6.0 + 9.0 * i] for i in range(len(legend))],
            [name for name, _ in legend],
            [c for _, c in legend],
        )
    return out


def view(plot: Plot) -> Any:
    """The ``Spatial2DView`` of a plot, framed on the plot area and its margins."""
    return rrb.Spatial2DView(
        origin="/",
        contents=[*dict.fromkeys(plot.entities), f"{axes_root(plot)}/**"],
        name=f"{plot.heading} vs {plot.x_heading}",
        visual_bounds=rrb.VisualBounds2D(
            x_range=[-MARGIN_LEFT, W + right_margin(plot)],
            y_range=[-MARGIN_TOP, H + MARGIN_BOTTOM],
        ),
    )
