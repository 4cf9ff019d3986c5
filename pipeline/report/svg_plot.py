"""A declared plot (:class:`imupipe.pipeline.report.figures.Plot`) as an inline ``<svg>`` element: the
figures of ``report.html``.

Sizes are in px of the viewBox (640 x 340 per plot, 1280 x 340 for a ``3d`` plot), shown at
the width of the page (``width="100%"``); fonts in px, a system sans-serif. The axes are laid out
by :mod:`imupipe.pipeline.report.plot_layout`, as in the recording's 2D plots. What is drawn:

- ``time``: the signals against time since the first sample, in s, min or h by the span, the
  axis ending at the last sample (not rounded up to a tick); the x title says since when (a
  date for a wall-clock log, else the time on the log's own clock);
- ``xy``: curves on linear or log axes; confidence bands (fill, 30 % opaque) beneath, model
  terms (guides) dashed, measured values as dots, fitted curves as lines; log axes labelled in
  plain text (``10\u207b\u00b3``), at 2 and 5 times the powers of ten too on an axis spanning
  less than two decades, else with faint grid lines there;
- ``bars``: one bar per item and column, grouped per x, on integer x ticks;
- ``3d``: the points on the planes x-y, y-z and z-x with the ellipsoids' outlines, at equal
  aspect, and a map of the points' directions from the ellipsoid's centre (azimuth, elevation
  in degrees): their coverage.

Every plot has its title on top, its unit as the y title and, between the title and the plot
area (outside it: it covers no data), a legend in rows. Lines are one ``<polyline>`` per piece
(broken at missing values), dots one ``<path>`` of round-capped zero-length segments per colour;
coordinates are formatted in one operation per element. So that no series hides another: lines
over time are see-through (:data:`LINE_OPACITY`), an input ``under`` its correction is a wide
light halo, a sparse series of dots is drawn last on white edges, a ``highlight`` is shaded spans
beneath everything; ``tests/plot_check.py`` checks every figure of a report for it.
"""

from __future__ import annotations

import datetime as dt
import html
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imupipe.pipeline.report.figures import Plot, Series, is_sparse, is_wall_clock
from imupipe.pipeline.report.plot_layout import Axis, pow10_text, runs, strips

WIDTH, HEIGHT = 640.0, 340.0
"""One plot, in px of the viewBox (a ``3d`` plot is twice as wide)."""
FONT = "system-ui, -apple-system, 'Segoe UI', Roboto, Helvetica, Arial, sans-serif"
TITLE_SIZE, LABEL_SIZE, TICK_SIZE, LEGEND_SIZE = 13.0, 11.0, 10.0, 10.0  # px
CHAR_EM = 0.55
"""Width of a character in em: generous for a sans-serif font (room for labels, legends)."""
TEXT, FRAME, GRID = "#333", "#888", "#999"
LINE_WIDTH = {"line": 1.8, "guide": 1.2, "time": 1.1, "under": 2.6}  # px
LINE_OPACITY = {"time": 0.6, "under": 0.45}
"""Lines over time are slightly see-through, so that x, y and z crossing each other all show;
lines ``under`` others (the input beneath its correction) are wider and lighter, a halo around
the line over them. A ``highlight`` (the still intervals) is shaded spans beneath everything."""
DOT = {"time": 3.0, "xy": 4.0, "cloud": 2.2}  # px, diameter
DASH = "5 3"
BAND_OPACITY = 0.3
MARGIN = 0.02
"""Linear axes of curves reach this fraction of their span past the first and last ticks."""
ORDER = {"band": 0, "guide": 1, "points": 2, "line": 3}
"""Drawing order: bands beneath the model terms, the data over them, the fitted lines on top."""


@dataclass
class Box:
    """A plot area in px of the viewBox: left, top, width, height."""

    x: float
    y: float
    w: float
    h: float


def text_width(text: str, size: float) -> float:
    """The width (px) allowed for ``text`` at font ``size`` (px)."""
    return CHAR_EM * size * len(text)


def caption(plot: Plot) -> str:
    """What a plot shows, in words: its figure's caption and its SVG title."""
    if plot.kind == "time":
        return f"{plot.heading} over time"
    if plot.kind == "bars":
        return f"{plot.heading} per {plot.x_label}"
    if plot.kind == "3d":
        return f"{plot.heading}: projections and directions"
    return f"{plot.heading} against {plot.x_heading}"


def svg(plot: Plot) -> str | None:
    """The plot as an ``<svg>`` element, or None when it has nothing to draw."""
    if plot.kind == "3d":
        body, width = _draw_3d(plot), 2 * WIDTH
    else:
        body, width = _draw_2d(plot), WIDTH
    if body is None:
        return None
    label = html.escape(caption(plot))
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width:g} {HEIGHT:g}" '
        f'width="100%" role="img" aria-label="{label}" font-family="{FONT}" fill="{TEXT}">'
        f"<title>{label}</title>{''.join(body)}</svg>"
    )


# -- pieces --------------------------------------------------------------------------------------
def _hex(color: Sequence[int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*(int(c) for c in color[:3]))


def _text(x: float, y: float, s: str, size: float, anchor: str = "middle", cls: str = "") -> str:
    klass = f' class="{cls}"' if cls else ""
    return (
        f'<text{klass} x="{x:.1f}" y="{y:.1f}" font-size="{size:g}px" text-anchor="{anchor}">'
        f"{html.escape(s)}</text>"
    )


def _coords(pts: np.ndarray, fmt: str = "%.1f,%.1f ") -> str:
    """(n, 2) px as text, in one formatting operation (no Python loop over the points)."""
    return (fmt * len(pts) % tuple(np.asarray(pts).ravel().tolist())).rstrip()


def _polyline(
    pts: np.ndarray, color: str, width: float, dash: bool = False, opacity: float = 1.0
) -> str:
    dashed = f' stroke-dasharray="{DASH}"' if dash else ""
    faded = f' stroke-opacity="{opacity:g}"' if opacity < 1.0 else ""
    return (
        f'<polyline points="{_coords(pts)}" fill="none" stroke="{color}" '
        f'stroke-width="{width:g}" stroke-linejoin="round"{dashed}{faded}/>'
    )


def _dots(pts: np.ndarray, color: str, size: float, edge: bool = False) -> str:
    """Dots of diameter ``size`` px: one path of zero-length segments with round caps (with
    ``edge``, each on a white disc 2 px wider: a few dots over a dense cloud stay apart)."""
    d = _coords(pts, "M%.1f %.1fh0")
    under = (
        f'<path d="{d}" stroke="#fff" stroke-width="{size + 2:g}" stroke-linecap="round" '
        'fill="none"/>'
        if edge
        else ""
    )
    return (
        f'{under}<path class="dots" d="{d}" stroke="{color}" '
        f'stroke-width="{size:g}" stroke-linecap="round" fill="none"/>'
    )


def _px(box: Box, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Axis fractions to px of the viewBox, y pointing down (rows with a NaN dropped)."""
    ok = np.isfinite(fx) & np.isfinite(fy)
    return np.column_stack([box.x + fx[ok] * box.w, box.y + (1.0 - fy[ok]) * box.h])


def _pieces(box: Box, fx: np.ndarray, fy: np.ndarray) -> list[np.ndarray]:
    """The polylines of one curve in px of the viewBox, broken at missing values."""
    return [p + [box.x, box.y] for p in strips(fx, fy, box.w, box.h)]


def _ticks(axis: Axis) -> tuple[np.ndarray, list[str], np.ndarray]:
    """(labelled ticks, their labels, faint grid lines) of an axis. A log axis is labelled in
    plain text at the powers of ten, and at 2 and 5 times them when it spans less than two
    decades; on a wider one those (and decades without a label) get faint grid lines."""
    if not axis.log:
        return axis.ticks, axis.labels, np.zeros(0)
    minor = axis.minor()
    if axis.hi - axis.lo < 2.0:
        ticks = np.sort(np.concatenate([axis.ticks, minor]))
        return ticks, [pow10_text(v) for v in ticks], np.zeros(0)
    decades = 10.0 ** np.arange(math.ceil(axis.lo), math.floor(axis.hi) + 1)
    return (
        axis.ticks,
        [pow10_text(v) for v in axis.ticks],
        np.setdiff1d(np.concatenate([minor, decades]), axis.ticks),
    )


def _y_room(labels: Sequence[str], tick: float, title: float) -> float:
    """Room (px) left of a plot area for the y tick labels and the rotated y title."""
    widest = max((text_width(s, tick) for s in labels), default=0.0)
    return 4.0 + title + 6.0 + widest + 5.0


def _rules(xs: np.ndarray, ys: np.ndarray, box: Box) -> str:
    """Path data of vertical lines at px ``xs`` and horizontal ones at px ``ys`` across a box."""
    v = _coords(np.column_stack([xs, np.full(len(xs), box.y)]), f"M%.1f %.1fv{box.h:.1f} ")
    h = _coords(np.column_stack([np.full(len(ys), box.x), ys]), f"M%.1f %.1fh{box.w:.1f} ")
    return f"{v} {h}".strip()


def _axes(box: Box, xa: Axis, ya: Axis, x_title: str, y_title: str, tick: float) -> list[str]:
    """Grid, frame, tick labels and axis titles (font ``tick`` px, titles 1 px larger)."""
    xt, xl, xf = _ticks(xa)
    yt, yl, yf = _ticks(ya)
    gx, gy = box.x + xa(xt) * box.w, box.y + (1.0 - ya(yt)) * box.h
    fx, fy = box.x + xa(xf) * box.w, box.y + (1.0 - ya(yf)) * box.h
    out = []
    for xs, ys, opacity in ((gx, gy, 0.35), (fx, fy, 0.15)):
        if len(xs) or len(ys):
            out.append(
                f'<path class="grid" d="{_rules(xs, ys, box)}" stroke="{GRID}" '
                f'stroke-opacity="{opacity:g}" stroke-width="0.8" fill="none"/>'
            )
    out.append(
        f'<rect class="frame" x="{box.x:.1f}" y="{box.y:.1f}" width="{box.w:.1f}" '
        f'height="{box.h:.1f}" fill="none" stroke="{FRAME}" stroke-width="1"/>'
    )
    bottom = box.y + box.h
    out += [
        _text(x, bottom + 3.0 + tick, s, tick, cls="xtick") for x, s in zip(gx, xl, strict=True)
    ]
    out += [
        _text(box.x - 5.0, y + 0.35 * tick, s, tick, "end", cls="ytick")
        for y, s in zip(gy, yl, strict=True)
    ]
    out.append(_text(box.x + box.w / 2, bottom + 8.0 + 2.0 * tick, x_title, tick + 1, cls="xtitle"))
    if y_title:
        cx, cy = box.x - _y_room(yl, tick, tick + 1) + 4.0 + tick + 1, box.y + box.h / 2
        out.append(
            f'<text class="ytitle" x="0" y="0" font-size="{tick + 1:g}px" text-anchor="middle" '
            f'transform="translate({cx:.1f},{cy:.1f}) rotate(-90)">{html.escape(y_title)}</text>'
        )
    return out


def _title(text: str, centre: float, y: float, size: float, width: float) -> str:
    """A title centred on ``centre`` px, moved in to stay inside [0, width]."""
    half = text_width(text, size) / 2
    x = min(max(centre, half + 4.0), width - half - 4.0)
    return _text(x, y, text, size, cls="title")


# -- legend --------------------------------------------------------------------------------------
@dataclass
class Entry:
    """One line of a legend: a name, its colour and how its series is drawn."""

    name: str
    color: str
    style: str


LEGEND_GAP = 14.0
"""px between two entries of a legend row."""


def _entry_width(e: Entry, size: float = LEGEND_SIZE) -> float:
    return 24.0 + text_width(e.name, size)


def legend_rows(entries: Sequence[Entry], width: float) -> list[list[Entry]]:
    """The entries in rows no wider than ``width`` px, in order (a row holds at least one)."""
    rows: list[list[Entry]] = []
    used = width + 1.0
    for e in entries:
        w = _entry_width(e)
        if rows and used + LEGEND_GAP + w <= width:
            rows[-1].append(e)
            used += LEGEND_GAP + w
        else:
            rows.append([e])
            used = w
    return rows


def legend_height(entries: Sequence[Entry], width: float) -> float:
    """px a legend of ``entries`` takes above a plot area ``width`` px wide (0: none)."""
    return len(legend_rows(entries, width)) * 1.4 * LEGEND_SIZE + 4.0 if entries else 0.0


def _legend(x0: float, y0: float, width: float, entries: Sequence[Entry]) -> list[str]:
    """The legend in rows from (``x0``, ``y0``) px, above the plot area and outside it: it
    covers no data, whatever the data does."""
    if not entries:
        return []
    rows = legend_rows(entries, width)
    h = len(rows) * 1.4 * LEGEND_SIZE
    out = [
        f'<g class="legend"><rect x="{x0:.1f}" y="{y0:.1f}" width="{width:.1f}" '
        f'height="{h:.1f}" fill="none" stroke="none"/>'
    ]
    for i, row in enumerate(rows):
        y, x = y0 + (i + 0.5) * 1.4 * LEGEND_SIZE, x0
        for e in row:
            out.append(_swatch(x, y, e))
            out.append(_text(x + 24.0, y + 0.35 * LEGEND_SIZE, e.name, LEGEND_SIZE, "start"))
            x += _entry_width(e) + LEGEND_GAP
    out.append("</g>")
    return out


def _entries(series: Sequence[Series], kind: str) -> list[Entry]:
    """One legend entry per drawn line, dot colour, band or bar."""
    out = []
    for s in series:
        if s.style == "band":
            out.append(Entry(s.names[0], _hex(s.colors[0]), "band"))
            continue
        style = "bar" if kind == "bars" else _line_style(s)
        out += [Entry(n, _hex(c), style) for n, c in zip(s.names, s.colors, strict=True)]
    return out


def _line_style(s: Series) -> str:
    """How a series is drawn: its style, or ``under`` / ``highlight`` for such lines."""
    if s.style == "line":
        if s.extra.get("highlight"):
            return "highlight"
        if s.extra.get("under"):
            return "under"
    return s.style


def _swatch(x: float, y: float, e: Entry) -> str:
    if e.style in ("band", "bar"):
        opacity = BAND_OPACITY if e.style == "band" else 1.0
        return (
            f'<rect x="{x:.1f}" y="{y - 4:.1f}" width="18" height="8" fill="{e.color}" '
            f'fill-opacity="{opacity:g}"/>'
        )
    if e.style == "points":
        return _dots(np.array([[x + 9.0, y]]), e.color, DOT["xy"])
    seg = np.array([[x, y], [x + 18.0, y]])
    if e.style == "highlight":
        return (
            f'<rect x="{x:.1f}" y="{y - 5:.1f}" width="18" height="10" fill="{e.color}" '
            f'fill-opacity="{SPAN_OPACITY:g}"/>'
        )
    if e.style == "under":
        return _polyline(seg, e.color, min(LINE_WIDTH[e.style], 6.0), opacity=LINE_OPACITY[e.style])
    return _polyline(seg, e.color, 1.5, dash=e.style == "guide")


# -- 2D plots ------------------------------------------------------------------------------------
def time_axis(plot: Plot) -> tuple[int, float, str] | None:
    """(first time in ns, seconds per unit shown, x title) of a ``time`` plot (None: empty). The
    unit is s, min or h by the span; the title says since when: a date for a wall-clock log,
    else the time on the log's own clock (a CSV from 0, time since boot), never a day in 1970."""
    t0 = min((int(s.x[0]) for s in plot.series if len(s.x)), default=None)
    if t0 is None:
        return None
    if plot.origin is not None and plot.origin <= t0:  # the run's one origin
        t0 = plot.origin
    t1 = max(int(s.x[-1]) for s in plot.series if len(s.x))
    span = (t1 - t0) * 1e-9
    scale, unit = (1.0, "s") if span < 600 else (60.0, "min") if span < 3 * 3600 else (3600.0, "h")
    if is_wall_clock(t0):
        start = dt.datetime.fromtimestamp(t0 * 1e-9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    else:
        start = f"{t0 * 1e-9:.9g} s on the log's clock"
    return t0, scale, f"time since {start} ({unit})"


def _integer_axis(xs: Sequence[np.ndarray]) -> Axis:
    """The x axis of bars: half a bar's slot beyond the first and last item, integer ticks
    (steps of 1, 2, 5, 10... so at most about ten)."""
    data = np.concatenate([np.ravel(x) for x in xs]).astype(np.float64)
    lo, hi = float(data.min()) - 0.6, float(data.max()) + 0.6
    step = next(s for s in (m * 10**k for k in range(12) for m in (1, 2, 5)) if (hi - lo) / s <= 10)
    return Axis.within(lo, hi, step=float(step))


def _draw_2d(plot: Plot) -> list[str] | None:
    """A ``time``, ``xy`` or ``bars`` plot (None: nothing to draw)."""
    series = [s for s in plot.series if len(s.x)]
    if not series:
        return None
    if plot.kind == "time":
        t0, scale, x_title = time_axis(plot)  # type: ignore[misc]
        xs = [(s.x - t0) * (1e-9 / scale) for s in series]
        end = max(float(x[-1]) for x in xs)  # from the first sample to the last, no round-up
        xa = Axis.within(0.0, end) if end > 0 else Axis(xs, False)
    elif plot.kind == "bars":
        xs, x_title = [np.asarray(s.x, dtype=np.float64) for s in series], plot.x_label
        xa = _integer_axis(xs)
    else:
        xs, x_title = [np.asarray(s.x, dtype=np.float64) for s in series], plot.x_heading
        xa = Axis(xs, plot.log_x)
    zero = [np.zeros(1)] if plot.kind == "bars" else []
    ya = Axis([s.values for s in series] + zero, plot.log_y and plot.kind != "bars")
    if plot.kind != "bars":  # lines on a round value stay off the frame
        xa.pad(MARGIN)
        ya.pad(MARGIN)
    bottom = HEIGHT - 7.0 - (LABEL_SIZE + 1) - 6.0 - TICK_SIZE - 4.0
    left = _y_room(_ticks(ya)[1], TICK_SIZE, TICK_SIZE + 1)
    xl = _ticks(xa)[1]
    right = max(10.0, text_width(xl[-1], TICK_SIZE) / 2 + 3.0) if xl else 10.0
    width = WIDTH - left - right
    entries = _entries(series, plot.kind)
    top = 28.0 + legend_height(entries, width)
    box = Box(left, top, width, bottom - top)
    out = [_title(plot.heading, box.x + box.w / 2, 18.0, TITLE_SIZE, WIDTH)]
    out += _legend(box.x, 26.0, box.w, entries)
    out += _axes(box, xa, ya, x_title, plot.unit, TICK_SIZE)
    if plot.kind == "bars":
        drawn = _bars(box, xa, ya, series, xs)
    else:
        drawn = _curves(box, xa, ya, series, xs, plot.kind)
    return out + drawn


def _curves(
    box: Box, xa: Axis, ya: Axis, series: list[Series], xs: list[np.ndarray], kind: str
) -> list[str]:
    """Highlights, bands, lines under others, guides, dots and lines in that order, then the
    dots of a sparse series (:func:`~imupipe.pipeline.report.figures.is_sparse`: the soak
    blocks among heating and cooling) on top, on white edges: a few points over a dense cloud or
    a line stay visible."""
    out: list[str] = []

    def rank(pair: tuple[Series, np.ndarray]) -> float:
        s = pair[0]
        if is_sparse(s, series):
            return 9.0
        return {"highlight": -2.0, "under": -0.5}.get(_line_style(s), ORDER.get(s.style, 3))

    for s, x in sorted(zip(series, xs, strict=True), key=rank):
        fx = xa(x)
        if s.style == "band":
            color = _hex(s.colors[0])
            lo, hi = ya(s.values[:, 0]), ya(s.values[:, 1])
            for r in runs(np.isfinite(fx) & np.isfinite(lo) & np.isfinite(hi)):
                ring = np.vstack([_px(box, fx[r], hi[r]), _px(box, fx[r], lo[r])[::-1]])
                out.append(
                    f'<polygon class="band" points="{_coords(ring)}" fill="{color}" '
                    f'fill-opacity="{BAND_OPACITY:g}" stroke="none"/>'
                )
            if len(fx) <= WHISKERS:
                out += _whiskers(box, fx, lo, hi, color)
            continue
        style = _line_style(s)
        if style == "highlight":  # where it holds: shaded spans across the plot, beneath all
            for j in range(len(s.names)):
                out += _spans(box, fx, s.values[:, j], _hex(s.colors[j]))
            continue
        for j in range(len(s.names)):
            color, fy = _hex(s.colors[j]), ya(s.values[:, j])
            if s.style == "points":
                pts = _px(box, fx, fy)
                size = DOT["time" if kind == "time" else "xy"]
                out.append(_dots(pts, color, size, edge=rank((s, x)) == 9.0))
                continue
            if style == "under":
                width, opacity = LINE_WIDTH[style], LINE_OPACITY[style]
            elif kind == "time":
                width, opacity = LINE_WIDTH["time"], LINE_OPACITY["time"]
            else:
                width, opacity = LINE_WIDTH.get(s.style, LINE_WIDTH["line"]), 1.0
            for piece in _pieces(box, fx, fy):
                out.append(_polyline(piece, color, width, s.style == "guide", opacity))
    return out


SPAN_OPACITY = 0.2


def _spans(box: Box, fx: np.ndarray, values: np.ndarray, color: str) -> list[str]:
    """One shaded rectangle, the plot's full height, per run of finite ``values``."""
    cells = []
    for r in runs(np.isfinite(values) & np.isfinite(fx)):
        x0, x1 = box.x + fx[r.start] * box.w, box.x + fx[r.stop - 1] * box.w
        cells.append(
            f'<rect x="{x0:.1f}" y="{box.y:.1f}" width="{max(x1 - x0, 1.0):.1f}" '
            f'height="{box.h:.1f}"/>'
        )
    if not cells:
        return []
    return [f'<g class="spans" fill="{color}" fill-opacity="{SPAN_OPACITY:g}">{"".join(cells)}</g>']


WHISKERS = 60
"""A band of this many values or fewer (one per log, per flight) also gets an error bar at each
value, capped: an interval thinner than a line still shows where it is."""


def _whiskers(box: Box, fx: np.ndarray, lo: np.ndarray, hi: np.ndarray, color: str) -> list[str]:
    """Error bars from ``lo`` to ``hi`` (axis fractions) at ``fx``, with 6 px caps."""
    ok = np.isfinite(fx) & np.isfinite(lo) & np.isfinite(hi)
    x = box.x + fx[ok] * box.w
    y0, y1 = box.y + (1.0 - lo[ok]) * box.h, box.y + (1.0 - hi[ok]) * box.h
    if not len(x):
        return []
    d = " ".join(
        f"M{a:.1f} {b:.1f}V{c:.1f}M{a - 3:.1f} {b:.1f}h6M{a - 3:.1f} {c:.1f}h6"
        for a, b, c in zip(x.tolist(), y0.tolist(), y1.tolist(), strict=True)
    )
    return [
        f'<path class="whiskers" d="{d}" stroke="{color}" stroke-width="1.2" '
        'stroke-opacity="0.9" fill="none"/>'
    ]


def _bars(box: Box, xa: Axis, ya: Axis, series: list[Series], xs: list[np.ndarray]) -> list[str]:
    """Bars grouped per x (0.8 of a slot shared by a series' columns), from 0."""
    out: list[str] = []
    base = box.y + (1.0 - ya(0.0)) * box.h
    unit = box.w / (xa.hi - xa.lo)
    for s, x in zip(series, xs, strict=True):
        k = s.values.shape[1]
        width = 0.8 / k
        for j in range(len(s.names)):
            color = _hex(s.colors[j])
            top = box.y + (1.0 - ya(s.values[:, j])) * box.h
            left = box.x + xa(x + (j - (k - 1) / 2) * width - width / 2) * box.w
            ok = np.isfinite(top)
            rects = np.column_stack([left[ok], np.minimum(top[ok], base), np.abs(top[ok] - base)])
            cell = f'<rect x="%.1f" y="%.1f" width="{width * unit:.1f}" height="%.1f"/>'
            out.append(
                f'<g class="bars" fill="{color}">{(cell * len(rects)) % tuple(rects.ravel().tolist())}</g>'
            )
    return out


# -- 3D ------------------------------------------------------------------------------------------
PLANES = ((0, 1, "x", "y"), (1, 2, "y", "z"), (2, 0, "z", "x"))
"""The projections of a ``3d`` plot: (axis across, axis up, their names)."""


def ellipse_outline(s: Series, i: int, j: int) -> np.ndarray:
    """The outline (2, 200) of an ellipsoid's projection on the plane of axes i, j: the image of
    the unit circle under the Cholesky factor of P M M^T P^T (M = rotation @ diag(half sizes))."""
    m = s.extra["rotation"] @ np.diag(s.extra["half_sizes"])
    p = m[[i, j], :]
    chol = np.linalg.cholesky(p @ p.T + 1e-30 * np.eye(2))
    t = np.linspace(0, 2 * np.pi, 200)
    return s.values[0, [i, j]][:, None] + chol @ np.vstack([np.cos(t), np.sin(t)])


def _cloud(box: Box, xa: Axis, ya: Axis, s: Series, a: np.ndarray, b: np.ndarray) -> list[str]:
    """A point cloud as dots, one path per colour (the per-point colours of ``extra``)."""
    cols = s.extra.get("colors")
    pts = _px(box, xa(a), ya(b))
    ok = np.isfinite(a) & np.isfinite(b)
    if cols is None or len(cols) != len(s.values):
        return [_dots(pts, _hex(s.colors[0]), DOT["cloud"])]
    shades, which = np.unique(np.asarray(cols)[ok, :3], axis=0, return_inverse=True)
    which = np.ravel(which)
    return [_dots(pts[which == n], _hex(c), DOT["cloud"]) for n, c in enumerate(shades)]


def _equal_axes(a: np.ndarray, b: np.ndarray, w: float, h: float) -> tuple[Axis, Axis]:
    """Axes for values ``a`` across and ``b`` up on a ``w`` x ``h`` px panel, one px per unit
    both ways (the shorter range widened about its middle), 4 % spare."""
    ranges = []
    for v in (a, b):
        v = v[np.isfinite(v)]
        lo, hi = (float(v.min()), float(v.max())) if len(v) else (-1.0, 1.0)
        pad = 0.04 * (hi - lo) or 1.0
        ranges.append((lo - pad, hi + pad))
    scale = min(w / (ranges[0][1] - ranges[0][0]), h / (ranges[1][1] - ranges[1][0]))
    out = []
    for (lo, hi), size, n in zip(ranges, (w, h), (6, 7), strict=True):
        mid, half = (lo + hi) / 2, size / scale / 2
        out.append(Axis.within(mid - half, mid + half, n))
    return out[0], out[1]


def _entries_3d(clouds: Sequence[Series], shells: Sequence[Series]) -> list[Entry]:
    """A cloud's entry per colour it shows (named by ``extra["color_names"]``: blue used in the
    fit, grey thinned out...), then each outline's."""
    out: list[Entry] = []
    for s in clouds:
        names = s.extra.get("color_names") or {}
        cols = s.extra.get("colors")
        shown = (
            [tuple(int(v) for v in c[:3]) for c in np.unique(np.asarray(cols)[:, :3], axis=0)]
            if cols is not None and len(cols) == len(s.values)
            else [tuple(int(v) for v in s.colors[0][:3])]
        )
        for c in sorted(shown, key=lambda c: list(names).index(c) if c in names else 99):
            label = f"{s.names[0]}: {names[c]}" if c in names else s.names[0]
            out.append(Entry(label, _hex(c), "points"))
    out += [Entry(s.names[0], _hex(s.colors[0]), "line") for s in shells]
    return out


def _draw_3d(plot: Plot) -> list[str] | None:
    """Three projections with the ellipsoids' outlines, and the directions' coverage."""
    clouds = [s for s in plot.series if s.style == "cloud" and len(s.values)]
    shells = [s for s in plot.series if s.style == "ellipsoid"]
    if not clouds and not shells:
        return None
    centre = shells[0].values[0] if shells else np.zeros(3)
    width, tick = 2 * WIDTH, 9.0
    entries = _entries_3d(clouds, shells)
    room_left, room_right, bottom = 54.0, 12.0, HEIGHT - 36.0
    top = 42.0 + legend_height(entries, width - 2 * room_left)
    unit = (width - 4 * (room_left + room_right)) / 4.5
    out = [_title(plot.heading, width / 2, 18.0, TITLE_SIZE, width)]
    out += _legend(room_left, 26.0, width - 2 * room_left, entries)
    x = room_left
    for i, j, a, b in PLANES:
        box = Box(x, top, unit, bottom - top)
        outlines = [ellipse_outline(s, i, j) for s in shells]
        along = [s.values[:, i] for s in clouds] + [o[0] for o in outlines]
        up = [s.values[:, j] for s in clouds] + [o[1] for o in outlines]
        xa, ya = _equal_axes(np.concatenate(along), np.concatenate(up), box.w, box.h)
        out += _axes(box, xa, ya, f"{a} ({plot.unit})", f"{b} ({plot.unit})", tick)
        for s in clouds:
            out += _cloud(box, xa, ya, s, s.values[:, i], s.values[:, j])
        for s, o in zip(shells, outlines, strict=True):
            out += [_polyline(p, _hex(s.colors[0]), 1.6) for p in _pieces(box, xa(o[0]), ya(o[1]))]
        x += unit + room_left + room_right
    box = Box(x, top, 1.5 * unit, bottom - top)
    xa, ya = Axis.within(-180.0, 180.0, step=60.0), Axis.within(-90.0, 90.0, step=30.0)
    out += _axes(box, xa, ya, "azimuth (deg)", "elevation (deg)", tick)
    out.append(_title("directions (coverage)", box.x + box.w / 2, top - 6.0, tick + 2, width))
    for s in clouds:
        d = s.values - centre
        r = np.linalg.norm(d, axis=1)
        ok = r > 0
        az = np.degrees(np.arctan2(d[ok, 1], d[ok, 0]))
        el = np.degrees(np.arcsin(np.clip(d[ok, 2] / r[ok], -1, 1)))
        out.append(_dots(_px(box, xa(az), ya(el)), _hex(s.colors[0]), DOT["cloud"]))
    return out
