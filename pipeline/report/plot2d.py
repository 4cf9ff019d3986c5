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

from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from imupipe.pipeline.report.figures import Plot, is_sparse
from imupipe.pipeline.report.plot_layout import Axis, strips

W, H = 160.0, 100.0
"""The plot area, in scene units."""
MARGIN_LEFT, MARGIN_TOP, MARGIN_BOTTOM = 34.0, 6.0, 27.0
CHAR_WIDTH = 4.2  # scene units per character of a label in a view of ~500 px (for the legend)
LABEL_DROP = 5.0
"""How far (scene units, in a view of ~250 px) the viewer draws a point's label below the point:
a y tick's label is placed this much higher, so it reads level with its grid line (it sat a
third of a decade low on a log axis, the bottom one under the frame)."""
FRAME_COLOR = (128, 128, 128)
GRID_COLOR = (150, 150, 150)
TEXT_COLOR = (110, 110, 110)
LINE_RADIUS = -1.0  # negative radii are UI points
BAND_RADIUS = -1.0
POINT_RADIUS = -2.5
"""A fitted line (2 px) over markers 5 px across: the markers show on both sides of the line
that follows them (the Allan deviation's measured points lay hidden under a 3 px fit, 4 px
markers), as in ``report.html`` (:data:`~imupipe.pipeline.report.svg_plot.DOT`)."""
GUIDE_RADIUS = -1.0
# bands and guide lines (model terms) beneath the data, fitted lines over it, and a few points
# amid many (the soak blocks among heating and cooling: figures.is_sparse) over everything
BAND_ORDER, GUIDE_ORDER, POINT_ORDER, LINE_ORDER, SPARSE_ORDER = 10.0, 15.0, 20.0, 30.0, 40.0


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
            edges = strips(x, ya(s.values[:, 0]), W, H) + strips(x, ya(s.values[:, 1]), W, H)
            band = rr.LineStrips2D(
                edges,
                colors=[s.colors[0]],
                radii=BAND_RADIUS,
                labels=[s.names[0]],
                show_labels=False,
                draw_order=BAND_ORDER,
            )
            out.append((s.entity, band))
            legend.append((s.names[0], s.colors[0]))
        elif s.style == "points":
            pts, cols, labels = [], [], []
            for j, name in enumerate(s.names):
                y = ya(s.values[:, j])
                ok = np.isfinite(x) & np.isfinite(y)
                if not ok.any():  # no legend entry without data
                    continue
                pts.append(np.column_stack([x[ok] * W, (1.0 - y[ok]) * H]))
                cols += [s.colors[j]] * int(ok.sum())
                labels += [name] * int(ok.sum())  # hovering a marker names it
                legend.append((name, s.colors[j]))
            if not pts:
                continue
            points = rr.Points2D(
                np.concatenate(pts),
                colors=cols,
                radii=POINT_RADIUS,
                labels=labels,
                show_labels=False,
                draw_order=SPARSE_ORDER if is_sparse(s, plot.series) else POINT_ORDER,
            )
            out.append((s.entity, points))
        else:
            pieces, cols, labels = [], [], []
            for j, name in enumerate(s.names):
                parts = strips(x, ya(s.values[:, j]), W, H)
                if not parts:  # no legend entry without a line
                    continue
                pieces += parts
                cols += [s.colors[j]] * len(parts)
                labels += [name] * len(parts)
                legend.append((name, s.colors[j]))
            guide = s.style == "guide"
            lines = rr.LineStrips2D(
                pieces,
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
    y_ticks = [[-MARGIN_LEFT / 2, (1 - ya(t)) * H - LABEL_DROP] for t in ya.ticks]
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
