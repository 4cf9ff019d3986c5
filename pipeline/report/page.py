"""``report.html``: the calibration in one self-contained file to mail or attach to a ticket.

Per stage: what to look at, the fitted values with their units and uncertainties, the quality
figures and warnings (:mod:`imupipe.pipeline.report.summary`), and the plots the stage declared for the
recording (:mod:`imupipe.pipeline.report.figures`): Allan deviation on log-log axes with the fitted
terms and the confidence band, residual per pose or per transition, the magnetometer samples
against the fitted ellipsoid and the sphere before and after, bias against temperature with the
fit, the raw and corrected signals. The plots are inline SVG (:mod:`imupipe.pipeline.report.svg_plot`),
so the file needs nothing beside it, opens in any browser and stays sharp when zoomed.
"""

from __future__ import annotations

import datetime as dt
import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from imupipe.pipeline.notices import Notice, counted, meaning
from imupipe.pipeline.report.figures import Figures, Plot, split_by_magnitude
from imupipe.pipeline.report.summary import StageSummary, by_input, inputs_warned, reader_items
from imupipe.pipeline.report.svg_plot import caption, svg
from imupipe.pipeline.version import VERSION

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
.notes { background: #fdf8ec; border-left: 4px solid #d8a23a; padding: 0.3em 0.8em; }
.notes li { margin: 0.3em 0; } .means { color: #555; }
.status-ok { color: #1a7f37; } .status-warn { color: #8a5a00; } .status-fail { color: #b00020; }
.plots { display: grid; grid-template-columns: repeat(auto-fill, minmax(560px, 1fr)); gap: 1em; }
figure { margin: 0; } figure.wide { grid-column: 1 / -1; } figure svg { display: block; width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 0.85em; color: #555; }
nav a { margin-right: 1em; }
"""


def write_report(
    path: Path,
    summaries: Sequence[StageSummary],
    figures: Figures,
    cfg: Any,
    notes: Sequence[Notice] = (),
) -> None:
    """Write ``report.html`` to ``path`` (the staged temporary path of the output); ``notes``:
    the run's warnings and notes of no stage (the exports')."""
    title = f"imupipe calibration report: {Path(cfg.path).name}"
    text = render(summaries, figures, title=title, source=str(cfg.path), notes=notes)
    path.write_text(text, encoding="utf-8")


def render(
    summaries: Sequence[StageSummary],
    figures: Figures,
    *,
    title: str,
    source: str = "",
    notes: Sequence[Notice] = (),
) -> str:
    """The report as one HTML string: the summary table, every warning and note with what it
    means, then each stage with its own warnings beside its results."""
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    figures.share_time_origin()
    warned = inputs_warned(summaries)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<p class="meta">config {html.escape(source)} &middot; imupipe {VERSION} &middot; '
        f"written {now}</p>",
        "<nav>"
        + "".join(f'<a href="#{_input_id(n)}">inputs.{html.escape(n)}</a>' for n in warned)
        + "".join(f'<a href="#{_id(s.name)}">{html.escape(s.name)}</a>' for s in summaries)
        + "</nav>",
        "<h2>Summary</h2>",
        overview_html(summaries),
        _notes(summaries, notes),
    ]
    for name, messages in warned.items():
        parts.append(input_html(name, messages))
    for s in summaries:
        parts.append(stage_html(s, [p for p in figures.of_stage(s.name)]))
    parts.append("</body></html>")
    return "\n".join(parts)


def _id(name: str, kind: str = "stage") -> str:
    return f"{kind}-" + "".join(c if c.isalnum() else "-" for c in name)


def _input_id(name: str) -> str:
    return _id(name, "input")


def _status_class(s: StageSummary) -> str:
    if s.failed_checks or s.refused:
        return "status-fail"
    return "status-warn" if s.warnings else "status-ok"


def overview_html(summaries: Sequence[StageSummary]) -> str:
    """The table of the stages (name, type, input, result, status) that opens the report."""
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


def _warning(level: str, message: str, where: str = "", source: str = "stage") -> str:
    """One warning or note with what it means (an ``<li>``); ``where``: the label shown,
    ``source``: where it was raised (``inputs.NAME``, ``stage``: the meaning's fallback)."""
    at = f" [{html.escape(where)}]" if where else ""
    means = meaning(message, where or source)
    return (
        f'<li><b class="warn">{level}</b>{at}: {html.escape(message)}<br>'
        f'<span class="means">What it means: {html.escape(means)}</span></li>'
    )


def _notes(summaries: Sequence[StageSummary], notes: Sequence[Notice]) -> str:
    """Every warning of the inputs' readers and the stages, and note of the run, listed under
    the summary table, each labelled with where it came from."""
    items = [_warning("warning", m, where) for where, m in reader_items(summaries)]
    items += [_warning("warning", w, s.name) for s in summaries for w in s.warnings]
    items += [_warning(n.level, n.message, n.where) for n in notes]
    if not items:
        return ""
    return (
        f'<div class="notes"><b>Warnings and notes ({len(items)})</b><ul>{"".join(items)}</ul>'
        "</div>"
    )


def input_html(name: str, messages: Sequence[str]) -> str:
    """An input's section: what its reader warned about, each with what it means."""
    items = "".join(_warning("warning", m, source=f"inputs.{name}") for m in messages)
    return (
        f'<h2 id="{_input_id(name)}">inputs.{html.escape(name)} '
        f'<small class="status-warn">(its reader: {counted(len(messages), "warning")})'
        "</small></h2>"
        f'<div class="notes"><ul>{items}</ul></div>'
    )


def stage_html(s: StageSummary, plots: Sequence[Plot] = ()) -> str:
    """A stage's section of the report: its summary table, quality figures, warnings and
    ``plots`` (also what a stage result shows in Jupyter: ``imupipe.StageResult``)."""
    out = [
        f'<h2 id="{_id(s.name)}">{html.escape(s.name)} '
        f'<small class="{_status_class(s)}">({html.escape(s.type)} on {html.escape(s.input)}: '
        f"{html.escape(s.status)})</small></h2>"
    ]
    if s.warnings:
        items = "".join(_warning("warning", w) for w in s.warnings)
        out.append(f'<div class="notes"><ul>{items}</ul></div>')
    for name, messages in by_input(s.input_warnings).items():
        out.append(
            f'<p class="notes">The reader of its input {html.escape(name)} warned '
            f'({len(messages)}): listed under <a href="#{_input_id(name)}">inputs.'
            f"{html.escape(name)}</a>.</p>"
        )
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
    for c in s.refused:
        out.append(f'<p class="fail">failed check (refused, not applied): {html.escape(c)}</p>')
    if plots:
        out.append('<div class="plots">')
        # the stage's own figures first, then its signals over time
        # lines of unlike magnitude in plots of their own, as in the recording
        shown = [part for p in plots for part in split_by_magnitude(p)]
        for plot in sorted(shown, key=lambda p: p.kind == "time"):
            drawn = svg(plot)
            if drawn:
                wide = ' class="wide"' if plot.kind == "3d" else ""
                out.append(
                    f"<figure{wide}>{drawn}"
                    f"<figcaption>{html.escape(caption(plot))}</figcaption></figure>"
                )
        out.append("</div>")
    return "\n".join(out)
