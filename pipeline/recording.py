"""The Rerun sink: every stage's signals in one ``recording.rrd``.

Signals are sent in bulk with ``rr.send_columns`` (never one ``rr.log`` per sample) on the
``time`` timeline (the samples' own timestamps). Each signal is one entity with one named series
per axis. Signals longer than ``max_points`` are block-averaged to at most that many points before
they are sent (the full-rate data stays in the MCAP output). A default blueprint has one tab per
stage, holding the views the stage asked for (a time-series view of ``/<stage>`` by default).
Every time-series view opens on the time span of the signals under its origin: the inputs of a
run often lie hours apart, and Rerun would otherwise open each plot on a short window around the
time cursor, which sits at the end of the last input.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from imupipe.stages.blocks import block_means

TIMELINE = "time"
AXIS_COLORS = [(230, 60, 60), (60, 180, 75), (60, 100, 230), (200, 140, 20)]


class Recorder:
    """Writes a Rerun recording to ``path`` (and to a viewer with ``spawn``)."""

    enabled = True

    def __init__(
        self,
        path: Path,
        *,
        spawn: bool = False,
        max_points: int = 200_000,
        application_id: str = "imupipe",
    ) -> None:
        self.max_points = max_points
        self.rec = rr.RecordingStream(application_id)
        if spawn:
            rr.spawn(connect=False)
            self.rec.set_sinks(rr.FileSink(str(path)), rr.GrpcSink())
        else:
            self.rec.save(str(path))
        self._views: dict[str, list[Any]] = {}
        self._styled: set[str] = set()
        self._spans: dict[str, tuple[int, int]] = {}  # entity -> (first, last) t_ns on TIMELINE
        self._curve_spans: dict[str, tuple[int, int]] = {}  # entity -> (first, last) sequence x

    # -- signals -----------------------------------------------------------------------------
    def series(
        self,
        entity: str,
        t_ns: np.ndarray,
        values: np.ndarray,
        names: Sequence[str] = ("x", "y", "z"),
        *,
        colors: Sequence[Any] | None = None,
    ) -> None:
        """One signal: ``values`` (n,) or (n, k) at ``t_ns`` (int64 ns), one named series per column."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        values = np.asarray(values, dtype=np.float64).reshape(len(t_ns), -1)
        if len(t_ns) == 0:
            return
        if len(t_ns) > self.max_points:
            blocks = block_means(t_ns, values, window=math.ceil(len(t_ns) / self.max_points))
            t_ns, values = blocks.t_ns, blocks.means
        self._style(entity, names, colors)
        first, last = self._spans.get(entity, (int(t_ns.min()), int(t_ns.max())))
        self._spans[entity] = (min(first, int(t_ns.min())), max(last, int(t_ns.max())))
        rr.send_columns(
            entity,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=t_ns.astype("datetime64[ns]"))],
            columns=rr.Scalars.columns(scalars=values),
            recording=self.rec,
        )

    def curve(
        self,
        entity: str,
        x: np.ndarray,
        values: np.ndarray,
        names: Sequence[str],
        *,
        timeline: str,
        colors: Sequence[Any] | None = None,
        points: bool = False,
    ) -> None:
        """A curve over something other than time (``x`` becomes a ``sequence`` timeline of ints,
        e.g. round(1000 * log10(tau)) for Allan curves); ``points``: draw markers, not lines
        (for scatter data such as bias against temperature)."""
        x = np.asarray(x, dtype=np.int64)
        values = np.asarray(values, dtype=np.float64).reshape(len(x), -1)
        if len(x) == 0:
            return
        self._style(entity, names, colors, points=points)
        first, last = self._curve_spans.get(entity, (int(x.min()), int(x.max())))
        self._curve_spans[entity] = (min(first, int(x.min())), max(last, int(x.max())))
        rr.send_columns(
            entity,
            indexes=[rr.TimeColumn(timeline, sequence=x)],
            columns=rr.Scalars.columns(scalars=values),
            recording=self.rec,
        )

    def _style(
        self,
        entity: str,
        names: Sequence[str],
        colors: Sequence[Any] | None,
        points: bool = False,
    ) -> None:
        if entity in self._styled:
            return
        self._styled.add(entity)
        colors = list(colors) if colors is not None else AXIS_COLORS[: len(names)]
        if len(colors) < len(names):
            colors = [AXIS_COLORS[i % len(AXIS_COLORS)] for i in range(len(names))]
        style = rr.SeriesPoints if points else rr.SeriesLines
        rr.log(
            entity,
            style(names=list(names), colors=colors),
            static=True,
            recording=self.rec,
        )

    def log(self, entity: str, archetype: Any, *, static: bool = True) -> None:
        """Anything else (3D points, ellipsoids, meshes, text): one ``rr.log`` call."""
        rr.log(entity, archetype, static=static, recording=self.rec)

    # -- blueprint ---------------------------------------------------------------------------
    def add_view(self, stage: str, view: Any) -> None:
        """Add a blueprint view (``rrb.TimeSeriesView``, ``rrb.Spatial3DView``...) to a stage's tab."""
        self._views.setdefault(stage, []).append(view)

    def ensure_stage(self, stage: str) -> None:
        """Give a stage a tab unless it asked for views: one time-series view per signal kind
        under ``/<stage>`` (e.g. ``input/gyro`` and ``output/gyro`` together, ``temperature``
        apart), so that signals of different units do not share an axis."""
        if stage in self._views:
            return
        prefix = f"/{stage}/"
        groups: dict[str, list[str]] = {}
        for entity in self._spans:
            if entity.startswith(prefix):
                groups.setdefault(entity.rsplit("/", 1)[-1], []).append(entity)
        if len(groups) <= 1:
            self._views[stage] = [rrb.TimeSeriesView(origin=f"/{stage}", name=stage)]
            return
        self._views[stage] = [
            _with_span(
                rrb.TimeSeriesView(origin=f"/{stage}", contents=entities, name=f"{stage}: {kind}"),
                [self._spans[e] for e in entities],
            )
            for kind, entities in groups.items()
        ]

    def _fit_time_axis(self, view: Any) -> None:
        """Open a time-series view on the span of the signals under its origin: their ``time``
        span, or, for a view of curves only, their span on the curve's sequence timeline.
        Views that set their own x range are left alone."""
        if getattr(view, "class_identifier", None) != "TimeSeries" or "TimeAxis" in view.properties:
            return
        origin = str(view.origin).rstrip("/")

        def under(spans: dict[str, tuple[int, int]]) -> list[tuple[int, int]]:
            return [v for e, v in spans.items() if e == origin or e.startswith(origin + "/")]

        spans = under(self._spans)
        if spans:
            _with_span(view, spans)
        elif curves := under(self._curve_spans):
            _with_span(view, curves, unit="seq")

    def blueprint(self) -> rrb.Blueprint:
        tabs = []
        for stage, views in self._views.items():
            for view in views:
                self._fit_time_axis(view)
            tabs.append(views[0] if len(views) == 1 else rrb.Vertical(*views, name=stage))
        return rrb.Blueprint(
            rrb.Tabs(*tabs) if tabs else rrb.TimeSeriesView(origin="/"),
            rrb.TimePanel(timeline=TIMELINE),
            collapse_panels=False,
        )

    def close(self) -> None:
        """Send the blueprint and flush everything to the sinks."""
        self.rec.send_blueprint(self.blueprint(), make_active=True, make_default=True)
        self.rec.flush()
        self.rec.disconnect()


def _with_span(view: Any, spans: list[tuple[int, int]], unit: str = "nanos") -> Any:
    """``view`` with its time axis set to cover ``spans`` ((first, last) in ``unit``: ``nanos``
    on the time timeline, ``seq`` on a sequence timeline); unchanged if there are none."""
    if spans:
        view.properties["TimeAxis"] = rrb.TimeAxis(
            view_range=rrb.TimeRange(
                start=rrb.TimeRangeBoundary.absolute(**{unit: min(a for a, _ in spans)}),
                end=rrb.TimeRangeBoundary.absolute(**{unit: max(b for _, b in spans)}),
            )
        )
    return view
