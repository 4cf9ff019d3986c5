"""``report.html``: the calibration in one self-contained file to mail or attach to a ticket.

Per stage: what to look at, the fitted values with their units and uncertainties, the quality
figures and warnings (:mod:`imupipe.pipeline.summary`), and the plots the stage declared for the
recording (:mod:`imupipe.pipeline.figures`): Allan deviation on log-log axes with the fitted
terms and the confidence band, residual per pose or per transition, the magnetometer samples
against the fitted ellipsoid and the sphere before and after, bias against temperature with the
fit, the raw and corrected signals. The plots are drawn with matplotlib (Agg, no display) as
PNG images inlined in base64, so the file needs nothing beside it and opens in any browser.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from imupipe.pipeline.figures import Figures, Plot, Series, is_wall_clock
from imupipe.pipeline.summary import StageSummary
from imupipe.pipeline.version import VERSION

DPI = 100
SIZE = (6.4, 3.4)  # inches: 640 x 340 px per plot

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto;
       max-width: 1400px; padding: 1em 2em; color: #222; background: #fff; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { border-bottom: 2px solid #ddd; padding-bottom: 0.2em; margin-top: 2em; }
.meta { color: #666; font-size: 0.9em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; }
th { background: #f4f4f4; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
.look { background: #f3f7fd; border-left: 4px solid #3a6fd8; padding: 0.5em 0.8em; }
.warn { color: #8a5a00; } .fail { color: #b00020; }
.status-ok { color: #1a7f37; } .status-warn { color: #8a5a00; } .status-fail { color: #b00020; }
.plots { display: grid; grid-template-columns: repeat(auto-fill, minmax(560px, 1fr)); gap: 1em; }
figure { margin: 0; } figure.wide { grid-column: 1 / -1; } figure img { width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 0.85em; color: #555; }
nav a { margin-right: 1em; }
"""


def write_report(path: Path, summaries: Sequence[StageSummary], figures: Figures, cfg: Any) -> None:
    """Write ``report.html`` to ``path`` (the staged temporary path of the output)."""
    title = f"imupipe calibration report: {Path(cfg.path).name}"
    path.write_text(render(summaries, figures, title=title, source=str(cfg.path)), encoding="utf-8")


def render(
    summaries: Sequence[StageSummary], figures: Figures, *, title: str, source: str = ""
) -> str:
    """The report as one HTML string."""
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<p class="meta">config {html.escape(source)} &middot; imupipe {VERSION} &middot; '
        f"written {now}</p>",
        "<nav>"
        + "".join(f'<a href="#{_id(s.name)}">{html.escape(s.name)}</a>' for s in summaries)
        + "</nav>",
        "<h2>Summary</h2>",
        _overview(summaries),
    ]
    for s in summaries:
        parts.append(_stage(s, [p for p in figures.of_stage(s.name)]))
    parts.append("</body></html>")
    return "\n".join(parts)


def _id(name: str) -> str:
    return "stage-" + "".join(c if c.isalnum() else "-" for c in name)


def _status_class(s: StageSummary) -> str:
    return "status-fail" if s.failed_checks else "status-warn" if s.warnings else "status-ok"


def _overview(summaries: Sequence[StageSummary]) -> str:
    rows = "".join(
        f'<tr><td><a href="#{_id(s.name)}">{html.escape(s.name)}</a></td>'
        f"<td>{html.escape(s.type)}</td><td>{html.escape(s.input)}</td>"
        f"<td>{html.escape(s.headline or '-')}</td>"
        f'<td class="{_status_class(s)}">{html.escape(s.status)}</td></tr>'
        for s in summaries
    )
    return (
        "<table><tr><th>stage</th><th>type</th><th>input</th><th>result</th><th>status</th></tr>"
        f"{rows}</table>"
    )


def _stage(s: StageSummary, plots: list[Plot]) -> str:
    out = [
        f'<h2 id="{_id(s.name)}">{html.escape(s.name)} '
        f'<small class="{_status_class(s)}">({html.escape(s.type)} on {html.escape(s.input)}: '
        f"{html.escape(s.status)})</small></h2>"
    ]
    if s.look_at:
        out.append(f'<p class="look"><b>What to look at.</b> {html.escape(s.look_at)}</p>')
    if s.rows:
        rows = "".join(
            f"<tr><td>{html.escape(r.label)}</td>"
            + "".join(
                f'<td class="num">{html.escape(c)}</td>' for c in (r.cells + ["", "", ""])[:3]
            )
            + "</tr>"
            for r in s.rows
        )
        out.append(f"<table><tr><th>quantity</th><th>x</th><th>y</th><th>z</th></tr>{rows}</table>")
    if s.quality:
        out.append(
            "<ul>"
            + "".join(f"<li>{html.escape(k)}: {html.escape(v)}</li>" for k, v in s.quality)
            + "</ul>"
        )
    for c in s.failed_checks:
        out.append(f'<p class="fail">failed check (accepted): {html.escape(c)}</p>')
    for w in s.warnings:
        out.append(f'<p class="warn">warning: {html.escape(w)}</p>')
    if plots:
        out.append('<div class="plots">')
        # the stage's own figures first, then its signals over time
        for plot in sorted(plots, key=lambda p: p.kind == "time"):
            png = _png(plot)
            if png:
                wide = ' class="wide"' if plot.kind == "3d" else ""
                out.append(
                    f'<figure{wide}><img alt="{html.escape(_caption(plot))}" '
                    f'src="data:image/png;base64,{base64.b64encode(png).decode()}">'
                    f"<figcaption>{html.escape(_caption(plot))}</figcaption></figure>"
                )
        out.append("</div>")
    return "\n".join(out)


def _caption(plot: Plot) -> str:
    if plot.kind == "time":
        return f"{plot.heading} over time"
    if plot.kind == "bars":
        return f"{plot.heading} per {plot.x_label}"
    if plot.kind == "3d":
        return f"{plot.heading}: projections and directions"
    return f"{plot.heading} against {plot.x_heading}"


# -- matplotlib ----------------------------------------------------------------------------------
def _rgb(color: Sequence[int]) -> tuple[float, ...]:
    return tuple(c / 255.0 for c in color[:3])


def _png(plot: Plot) -> bytes | None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if plot.kind == "3d":
        fig = Figure(figsize=(2 * SIZE[0], SIZE[1]), dpi=DPI)
        fig.subplots_adjust(left=0.05, right=0.99, top=0.86, bottom=0.15, wspace=0.35)
        _draw_3d(fig, plot)
    else:
        fig = Figure(figsize=SIZE, dpi=DPI)
        fig.subplots_adjust(left=0.12, right=0.98, top=0.91, bottom=0.14)
        ax = fig.add_subplot()
        draw = {"time": _draw_time, "xy": _draw_xy, "bars": _draw_bars}[plot.kind]
        if not draw(ax, plot):
            return None
        # y given: matplotlib then skips its search for top-side tick labels to clear (there
        # are none here; about 5 % of a plot's drawing)
        ax.set_title(plot.heading, fontsize=10, y=1.0)
        ax.grid(True, which="major", alpha=0.35)
        ax.tick_params(labelsize=8)
        handles, _ = ax.get_legend_handles_labels()
        if handles:
            ax.legend(fontsize=7, ncol=2 if len(handles) > 3 else 1, framealpha=0.8)
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _draw_time(ax: Any, plot: Plot) -> bool:
    t0 = min((int(s.x[0]) for s in plot.series if len(s.x)), default=None)
    if t0 is None:
        return False
    t1 = max(int(s.x[-1]) for s in plot.series if len(s.x))
    span = (t1 - t0) * 1e-9
    scale, unit = (1.0, "s") if span < 600 else (60.0, "min") if span < 3 * 3600 else (3600.0, "h")
    for s in plot.series:
        x = (s.x - t0) * 1e-9 / scale
        for j, name in enumerate(s.names):
            kw = (
                {"marker": ".", "linestyle": "none", "markersize": 2}
                if s.style == "points"
                else {"linewidth": 0.8}
            )
            ax.plot(x, s.values[:, j], color=_rgb(s.colors[j]), label=name, **kw)
    if is_wall_clock(t0):
        start = dt.datetime.fromtimestamp(t0 * 1e-9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    else:  # a log's own clock (time since boot, a CSV from 0): no date to give
        start = f"{t0 * 1e-9:.9g} s on the log's clock"
    ax.set_xlabel(f"time since {start} ({unit})", fontsize=8)
    ax.set_ylabel(plot.unit, fontsize=8)
    return True


def _draw_xy(ax: Any, plot: Plot) -> bool:
    for s in plot.series:
        if s.style == "band":
            ax.fill_between(
                s.x,
                s.values[:, 0],
                s.values[:, 1],
                color=_rgb(s.colors[0]),
                alpha=0.3,
                label=s.names[0],
                linewidth=0,
            )
            continue
        for j, name in enumerate(s.names):
            if s.style == "points":
                ax.plot(
                    s.x, s.values[:, j], "o", markersize=2.5, color=_rgb(s.colors[j]), label=name
                )
            elif s.style == "guide":
                ax.plot(
                    s.x, s.values[:, j], "--", color=_rgb(s.colors[j]), linewidth=0.9, label=name
                )
            else:
                ax.plot(s.x, s.values[:, j], color=_rgb(s.colors[j]), linewidth=1.4, label=name)
    for which, log in (("x", plot.log_x), ("y", plot.log_y)):
        if log:
            _log_axis(ax, which)
    ax.set_xlabel(plot.x_heading, fontsize=8)
    ax.set_ylabel(plot.unit, fontsize=8)
    return bool(plot.series)


SUPERSCRIPT = str.maketrans(
    "-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079"
)


def _pow10(value: float, _pos: object = None) -> str:
    """A log axis's tick label as plain text: ``10\u207b\u00b3``, ``2\u00d710\u207b\u00b3``
    (matplotlib's default labels are mathtext, parsed label by label)."""
    if not value > 0:
        return ""
    k = int(np.floor(np.log10(value) + 1e-9))
    mantissa = value / 10.0**k
    power = f"10{str(k).translate(SUPERSCRIPT)}"
    return power if abs(mantissa - 1.0) < 1e-6 else f"{mantissa:.3g}\u00d7{power}"


def _log_axis(ax: Any, which: str) -> None:
    """A logarithmic axis labelled in plain text, at the powers of ten, and at 2 and 5 times
    them when it spans less than two decades; on a wider axis, faint grid lines at 2 and 5
    times the powers drawn as one line collection. (matplotlib's minor ticks are artists of
    their own, a tick mark, a grid line and a label each: they cost most of a plot's drawing.)"""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullLocator

    getattr(ax, f"set_{which}scale")("log")
    axis = getattr(ax, f"{which}axis")
    axis.set_major_formatter(FuncFormatter(_pow10))
    axis.set_minor_locator(NullLocator())
    limits = getattr(ax, f"get_{which}lim")()
    lo, hi = sorted(limits)
    if not (lo > 0 and np.isfinite(hi)):
        return
    if hi / lo < 100.0:
        axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        return
    decades = 10.0 ** np.arange(np.floor(np.log10(lo)), np.ceil(np.log10(hi)) + 1)
    at = (decades[:, None] * [2.0, 5.0]).ravel()
    at = at[(at > lo) & (at < hi)]
    getattr(ax, f"set_{which}lim")(limits)  # the grid lines do not rescale the axis
    lines = ax.vlines if which == "x" else ax.hlines
    trans = ax.get_xaxis_transform() if which == "x" else ax.get_yaxis_transform()
    lines(at, 0.0, 1.0, transform=trans, colors="0.5", alpha=0.12, linewidth=0.6, zorder=0.5)


def _draw_bars(ax: Any, plot: Plot) -> bool:
    for s in plot.series:
        k = s.values.shape[1]
        width = 0.8 / k
        for j, name in enumerate(s.names):
            ax.bar(
                s.x + (j - (k - 1) / 2) * width,
                s.values[:, j],
                width=width,
                color=_rgb(s.colors[j]),
                label=name,
            )
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel(plot.x_label, fontsize=8)
    ax.set_ylabel(plot.unit, fontsize=8)
    return bool(plot.series)


PLANES = ((0, 1, "x", "y"), (1, 2, "y", "z"), (2, 0, "z", "x"))


def _ellipse_outline(s: Series, i: int, j: int) -> np.ndarray:
    """The outline of an ellipsoid's projection on the plane of axes i, j: the image of the unit
    circle under the Cholesky factor of P M M^T P^T (M = rotation @ diag(half sizes))."""
    m = s.extra["rotation"] @ np.diag(s.extra["half_sizes"])
    p = m[[i, j], :]
    chol = np.linalg.cholesky(p @ p.T + 1e-30 * np.eye(2))
    t = np.linspace(0, 2 * np.pi, 200)
    return s.values[0, [i, j]][:, None] + chol @ np.vstack([np.cos(t), np.sin(t)])


def _draw_3d(fig: Any, plot: Plot) -> None:
    """Three projections of the points with the ellipsoids' outlines, and a map of the points'
    directions from the ellipsoid's centre (azimuth, elevation): the coverage."""
    axes = fig.subplots(1, 4, gridspec_kw={"width_ratios": [1, 1, 1, 1.5]})
    clouds = [s for s in plot.series if s.style == "cloud"]
    shells = [s for s in plot.series if s.style == "ellipsoid"]
    centre = shells[0].values[0] if shells else np.zeros(3)
    for ax, (i, j, a, b) in zip(axes[:3], PLANES, strict=True):
        for s in clouds:
            cols = s.extra.get("colors")
            color = (
                cols[:, :3] / 255.0
                if cols is not None and len(cols) == len(s.values)
                else [_rgb(s.colors[0])]
            )
            ax.scatter(s.values[:, i], s.values[:, j], s=1.5, c=color, linewidths=0)
        for s in shells:
            xy = _ellipse_outline(s, i, j)
            ax.plot(xy[0], xy[1], color=_rgb(s.colors[0]), linewidth=1.2, label=s.names[0])
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{a} ({plot.unit})", fontsize=7)
        ax.set_ylabel(f"{b} ({plot.unit})", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.grid(True, alpha=0.3)
    ax = axes[3]
    for s in clouds:
        d = s.values - centre
        r = np.linalg.norm(d, axis=1)
        ok = r > 0
        az = np.degrees(np.arctan2(d[ok, 1], d[ok, 0]))
        el = np.degrees(np.arcsin(np.clip(d[ok, 2] / r[ok], -1, 1)))
        ax.scatter(az, el, s=1.5, c=[_rgb(s.colors[0])], linewidths=0)
    ax.set_xlim(-180, 180)
    ax.set_ylim(-90, 90)
    ax.set_xlabel("azimuth (deg)", fontsize=7)
    ax.set_ylabel("elevation (deg)", fontsize=7)
    ax.set_title("directions (coverage)", fontsize=8)
    ax.tick_params(labelsize=6)
    ax.grid(True, alpha=0.3)
    fig.suptitle(plot.heading, fontsize=9)
