"""A plot read the way a person reads it: the check every figure of ``report.html`` must pass.

:func:`problems` takes one inline ``<svg>`` of the report (parsed with ``xml.etree``) and lists,
in words, what would make a reader misread it:

- a legend that covers data: any data (line, dot, band, bar, error bar) drawn inside the box of
  a legend (``<g class="legend">``'s ``<rect>``);
- a legend entry with nothing visible: an entry whose colour no visible data element has;
- a series hidden by another: a data colour none of whose pixels stays visible.

"Visible" is worked out on a 1 px raster in drawing order (SVG paints later elements over
earlier ones): each data element covers the pixels its lines (at their stroke width), dots (at
their diameter), bars and bands touch, and an element with an opacity of at least
:data:`OPAQUE` hides what lies beneath it; a see-through one (a band, an ``under`` halo, lines
over time at 0.6) does not. A series (a colour) is visible when at least 5 % of its pixels (and
4) are not covered by an opaque element drawn after them. White (the edge under a highlighted
dot) hides but is no series.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np

NS = "{http://www.w3.org/2000/svg}"
OPAQUE = 0.75
"""An element at least this opaque hides what it is drawn over."""
NOT_DATA = {"grid", "frame", "legend"}
MIN_VISIBLE, MIN_VISIBLE_PX = 0.05, 4
"""A series shows when at least this share of its pixels (and this many) is not drawn over: a
few specks at the edge of a cloud do not make a series a reader can see."""


def _floats(text: str) -> list[float]:
    return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", text)]


def _path_strokes(d: str) -> list[np.ndarray]:
    """The polylines (m, 2) of a path of M, h, v, V, L commands (what svg_plot writes)."""
    out: list[list[tuple[float, float]]] = []
    x = y = 0.0
    for cmd, args in re.findall(r"([MLhvVH])\s*([^MLhvVH]*)", d):
        vals = _floats(args)
        if cmd == "M":
            x, y = vals[0], vals[1]
            out.append([(x, y)])
            continue
        if cmd == "h":
            x += vals[0]
        elif cmd == "H":
            x = vals[0]
        elif cmd == "v":
            y += vals[0]
        elif cmd == "V":
            y = vals[0]
        elif cmd == "L":
            x, y = vals[0], vals[1]
        out[-1].append((x, y))
    return [np.array(p, dtype=np.float64) for p in out]


class Raster:
    """Pixels (1 px cells) of a ``w`` x ``h`` viewBox."""

    def __init__(self, w: float, h: float) -> None:
        self.w, self.h = int(np.ceil(w)) + 1, int(np.ceil(h)) + 1

    def _cells(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ix = np.clip(np.floor(x).astype(int), 0, self.w - 1)
        iy = np.clip(np.floor(y).astype(int), 0, self.h - 1)
        return np.unique(iy * self.w + ix)

    def stroke(self, pts: np.ndarray, width: float) -> np.ndarray:
        """Cells within ``width / 2`` of a polyline (a lone point: a round dot)."""
        if len(pts) == 1:
            pts = np.vstack([pts, pts])
        a, b = pts[:-1], pts[1:]
        length = np.hypot(*(b - a).T)
        n = np.maximum(1, np.ceil(length / 0.5).astype(int))
        idx = np.repeat(np.arange(len(a)), n + 1)
        t = np.concatenate([np.linspace(0, 1, k + 1) for k in n])
        along = a[idx] + (b[idx] - a[idx]) * t[:, None]
        r = max(width / 2, 0.5)
        offsets = np.arange(-np.floor(r), np.floor(r) + 1)
        dx, dy = np.meshgrid(offsets, offsets)
        keep = np.hypot(dx, dy) <= r + 1e-9
        dx, dy = dx[keep], dy[keep]
        x = (along[:, 0][:, None] + dx[None, :]).ravel()
        y = (along[:, 1][:, None] + dy[None, :]).ravel()
        return self._cells(x, y)

    def box(self, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
        xs, ys = np.arange(np.floor(x0), np.ceil(x1) + 1), np.arange(np.floor(y0), np.ceil(y1) + 1)
        gx, gy = np.meshgrid(xs, ys)
        return self._cells(gx.ravel(), gy.ravel())

    def polygon(self, pts: np.ndarray) -> np.ndarray:
        """Cells of a filled polygon (even-odd rule at the cell centres) and its outline."""
        x0, y0 = np.floor(pts.min(axis=0))
        x1, y1 = np.ceil(pts.max(axis=0))
        gx, gy = np.meshgrid(np.arange(x0, x1 + 1) + 0.5, np.arange(y0, y1 + 1) + 0.5)
        px, py = gx.ravel(), gy.ravel()
        inside = np.zeros(len(px), dtype=bool)
        a, b = pts, np.roll(pts, -1, axis=0)
        for (ax, ay), (bx, by) in zip(a, b, strict=True):
            if ay == by:
                continue
            crosses = (ay > py) != (by > py)
            xc = ax + (py - ay) * (bx - ax) / (by - ay)
            inside ^= crosses & (px < xc)
        filled = self._cells(px[inside], py[inside])
        return np.union1d(filled, self.stroke(np.vstack([pts, pts[:1]]), 1.0))


def _color(el: ET.Element, parent_fill: str | None) -> str | None:
    tag = el.tag.removeprefix(NS)
    if tag in ("polyline", "path"):
        return el.get("stroke")
    return el.get("fill") or parent_fill


def _opacity(el: ET.Element, parent: float) -> float:
    """The element's own opacity times its group's (``parent``)."""
    tag = el.tag.removeprefix(NS)
    key = "stroke-opacity" if tag in ("polyline", "path") else "fill-opacity"
    return parent * float(el.get(key, el.get("opacity", "1")))


def data_elements(svg: ET.Element, raster: Raster) -> list[tuple[str, float, np.ndarray]]:
    """(colour, opacity, cells) of every data element, in drawing order."""
    out: list[tuple[str, float, np.ndarray]] = []

    def walk(el: ET.Element, fill: str | None, opacity: float) -> None:
        for child in el:
            tag = child.tag.removeprefix(NS)
            if child.get("class") in NOT_DATA:
                continue
            if tag == "g":
                group = float(child.get("fill-opacity", child.get("opacity", "1")))
                walk(child, child.get("fill") or fill, opacity * group)
                continue
            color = _color(child, fill)
            if tag == "polyline":
                pts = np.array(_floats(child.get("points", ""))).reshape(-1, 2)
                cells = raster.stroke(pts, float(child.get("stroke-width", "1")))
            elif tag == "path":
                width = float(child.get("stroke-width", "1"))
                strokes = _path_strokes(child.get("d", ""))
                cells = (
                    np.unique(np.concatenate([raster.stroke(p, width) for p in strokes]))
                    if strokes
                    else np.zeros(0, dtype=int)
                )
            elif tag == "polygon":
                pts = np.array(_floats(child.get("points", ""))).reshape(-1, 2)
                cells = raster.polygon(pts) if len(pts) >= 3 else np.zeros(0, dtype=int)
            elif tag == "rect":
                x, y, w, h = (float(child.get(k)) for k in ("x", "y", "width", "height"))
                cells = raster.box(x, y, x + w, y + h)
            else:
                continue
            if color and color != "none" and len(cells):
                out.append((color.lower(), _opacity(child, opacity), cells))

    walk(svg, None, 1.0)
    return out


def legend_boxes(svg: ET.Element) -> list[tuple[float, float, float, float]]:
    out = []
    for g in svg.iter(f"{NS}g"):
        if g.get("class") == "legend":
            r = g.find(f"{NS}rect")
            x, y, w, h = (float(r.get(k)) for k in ("x", "y", "width", "height"))
            out.append((x, y, x + w, y + h))
    return out


def legend_entries(svg: ET.Element) -> list[tuple[str, str]]:
    """(name, swatch colour) of every legend entry."""
    out = []
    for g in svg.iter(f"{NS}g"):
        if g.get("class") != "legend":
            continue
        swatch = None
        for el in list(g)[1:]:
            tag = el.tag.removeprefix(NS)
            if tag == "text":
                out.append((el.text or "", (swatch or "").lower()))
            elif tag in ("polyline", "path") and el.get("stroke") != "#fff":
                swatch = el.get("stroke")
            elif tag == "rect":
                swatch = el.get("fill")
    return out


def problems(svg: ET.Element) -> list[str]:
    """What would make a reader misread this plot (empty: nothing)."""
    _, _, w, h = (float(v) for v in svg.get("viewBox").split())
    raster = Raster(w, h)
    elements = data_elements(svg, raster)
    label = svg.get("aria-label", "?")
    found = []
    covered = np.full(raster.w * raster.h, -1)  # the last opaque element over each cell
    for i, (_, opacity, cells) in enumerate(elements):
        if opacity >= OPAQUE:
            covered[cells] = i
    visible: dict[str, int] = {}
    drawn: dict[str, int] = {}
    for i, (color, _, cells) in enumerate(elements):
        visible[color] = visible.get(color, 0) + int((covered[cells] <= i).sum())
        drawn[color] = drawn.get(color, 0) + len(cells)
    seen = {c for c, n in visible.items() if n >= max(MIN_VISIBLE_PX, MIN_VISIBLE * drawn[c])}
    for color in visible:
        if color not in ("#fff", "#ffffff") and color not in seen:
            found.append(
                f"{label}: the series in {color} is hidden by what is drawn over it "
                f"({visible[color]} of its {drawn[color]} px show)"
            )
    for name, color in legend_entries(svg):
        if color not in seen:
            found.append(f"{label}: legend entry {name!r} ({color}) has nothing visible")
    for box in legend_boxes(svg):
        inside = raster.box(*box)
        for color, _, cells in elements:
            if np.intersect1d(cells, inside).size:
                found.append(f"{label}: the legend {box} covers data in {color}")
                break
    return found


def svgs(html: str) -> list[ET.Element]:
    """Every inline ``<svg>`` of a page."""
    return [ET.fromstring(m) for m in re.findall(r"<svg .*?</svg>", html, flags=re.S)]
