"""The Rerun sink: every stage's signals in one ``recording.rrd``, laid out so that every view
shows its data when the recording opens.

A stage declares *what* it shows through the recorder (``ctx.recorder``): a signal over time
(:meth:`Recorder.series`), a curve over something else (:meth:`Recorder.curve`), one value per
item (:meth:`Recorder.bars`), points and ellipsoids in 3D (:meth:`Recorder.points3d`,
:meth:`Recorder.ellipsoid`), each with its SI unit, the names of its lines and the plot it goes
in. The recorder keeps these as :class:`~imupipe.pipeline.report.figures.Figures` (which ``report.html``
draws too) and decides *how* they look in Rerun:

- signals over time: a ``TimeSeriesView`` per plot, on the ``time`` timeline (the one the time
  panel opens on: time elapsed since the start of the recording, a duration, so the viewer
  labels ``+10m``, ``+1h`` and not the hour of the day; the samples' own times are the ``log
  time`` timeline), opened on the span of its own data, titled with its unit. Signals are sent in
  bulk with ``rr.send_columns``; one longer than ``max_points`` is averaged over consecutive
  blocks down to that many points (the MCAP output keeps every sample);
- curves over something else (Allan deviation over tau, bias against temperature): a
  ``Spatial2DView`` of line strips in plot coordinates, with the axes, grid, tick labels, axis
  titles and a legend drawn as 2D primitives, logged as static data. A time-series view cannot
  do it: its x axis is the time panel's timeline, so a curve on a timeline of its own opens empty
  until one switches timelines by hand, and Rerun's plots have no logarithmic axes;
- one value per item (residual per pose or per transition): a ``BarChartView`` (static);
- 3D points and ellipsoids: a ``Spatial3DView``;
- per stage a markdown ``TextDocument`` with the results (:mod:`imupipe.pipeline.report.summary`), and
  a first tab, "Summary", with all of them.

The default blueprint has the Summary tab, then one tab per stage (:func:`plan_tab`: the
signals of a session of many hours get inner tabs at full width, where Rerun labels every hour;
each legend's corner is kept free of data, :func:`legend_room`; lines ``under`` others are
see-through where they share a view, since Rerun draws a view's lines in entity-path order). With a viewer (``--spawn``)
everything also streams live to it over gRPC (a second stream with the same recording id, so a
failing viewer never touches the file).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from imupipe.pipeline.report import plot2d
from imupipe.pipeline.report.figures import (
    AXIS_COLORS,
    NAMED_COLORS,
    PALETTE,
    Figures,
    Plot,
    Series,
    colors_for,
    column_ranges,
    decimate,
    decimate_columns,
    display_unit,
    is_wall_clock,
    lighter,
    split_by_magnitude,
    stage_of,
)
from imupipe.pipeline.report.plot_layout import nice_ticks
from imupipe.pipeline.report.summary import raw_count_sensors
from imupipe.readers.table import (
    SENSOR_COLUMNS,
    SENSOR_UNITS,
    STREAM_OF_SENSOR,
    has_stream,
    sensor_columns,
)
from imupipe.stages.base import NullRecorder

TIMELINE = "time"
"""The timeline the recording opens on: time elapsed since the start of the recording (a
duration: the viewer labels it ``+10m``, ``+1h``, as the report's "min since start"), from
:meth:`Recorder.start_at` (default: the first sample sent)."""

LOG_TIMELINE = "log time"
"""The samples' own times, a second timeline to switch to: dates for a wall-clock log (a ROS or
MCAP stamp), else a duration on the log's own clock (a CSV from 0, a ULog's time since boot)."""


class Recorder:
    """Collects what the stages show and writes it to ``path`` (a Rerun recording; None: keep
    the figures only, for the report) and, with ``viewer`` (a gRPC URL), streams it live."""

    enabled = True

    def __init__(
        self,
        path: Path | None,
        *,
        viewer: str | None = None,
        max_points: int = 20_000,
        keep_points: int = 2_000,
        application_id: str = "imupipe",
        warn: Callable[[str], None] | None = None,
        elapsed: bool = True,
    ) -> None:
        """``elapsed``: the :data:`TIMELINE` counts from the start of the recording (a run's
        session); False: it is the samples' own time, the only timeline (the fleet survey's
        calendar, over months of flights)."""
        self.max_points = max_points
        self._elapsed = elapsed
        self.figures = Figures(keep_points)
        self.raw_counts: dict[str, set[str]] = {}
        """input -> the sensors it holds in raw counts (not SI): plotted apart, in counts"""
        self._warn = warn or (lambda message: None)
        self._streams: list[rr.RecordingStream] = []
        self._live: rr.RecordingStream | None = None
        self._path = path
        if path is not None:
            self.rec = rr.RecordingStream(application_id)
            self.rec.save(str(path))
            self._streams.append(self.rec)
            if viewer is not None:
                self._live = rr.RecordingStream(
                    application_id, recording_id=self.rec.get_recording_id()
                )
                self._live.set_sinks(rr.GrpcSink(viewer))
                self._streams.append(self._live)
        self._views: dict[str, list[Any]] = {}  # stage -> views added with add_view
        self._documents: dict[str, str] = {}  # stage ("" for the run) -> markdown
        self._styled: set[str] = set()
        self._spans: dict[str, tuple[int, int]] = {}  # entity -> (first, last) t_ns
        self._wall_clock: bool | None = None  # the log time line: dates, or durations
        self._origin: int | None = None  # ns: 0 on the time line (start_at, or the first sample)
        self._still_counts: set[tuple[str, str]] = set()  # (input, sensor) corrected, in counts
        self._input_units: dict[tuple[str, str], str] = {}  # (stage, sensor) -> unit of its input
        self._reused: dict[Any, Series] = {}  # (input, sensor, steps applied) -> series sent

    # -- sending -------------------------------------------------------------------------------
    def _send(self, fn: Callable[[rr.RecordingStream], None]) -> None:
        """``fn(stream)`` for the file and, while it works, the live viewer."""
        for stream in list(self._streams):
            if stream is self._live:
                try:
                    fn(stream)
                except Exception as exc:  # noqa: BLE001 - a viewer failure never stops the run
                    self._drop_live(exc)
            else:
                fn(stream)

    def _drop_live(self, exc: BaseException) -> None:
        if self._live is not None:
            self._streams.remove(self._live)
            with contextlib.suppress(Exception):
                self._live.disconnect()
            self._live = None
            self._warn(f"the Rerun viewer stopped receiving ({' '.join(str(exc).split())})")

    def start_at(self, t_ns: int | None) -> None:
        """The start of the recording (ns on the samples' clock): 0 on the :data:`TIMELINE`
        (elapsed time); before any signal is sent (later: unchanged). None: the first sample
        sent."""
        if self._elapsed and self._origin is None and t_ns is not None and not self._spans:
            self._origin = int(t_ns)

    def log(self, entity: str, archetype: Any, *, static: bool = True) -> None:
        """Anything else (a mesh, arrows...): one ``rr.log`` call, shown in a view the stage adds
        with :meth:`add_view`."""
        self.figures.stage(stage_of(entity))
        self._send(lambda s: rr.log(entity, archetype, static=static, recording=s))

    def _style(
        self,
        entity: str,
        names: Sequence[str],
        colors: Sequence[Any],
        points: bool,
        highlight: bool = False,
    ) -> None:
        if entity in self._styled:
            return
        self._styled.add(entity)
        if points:
            self.log(entity, rr.SeriesPoints(names=list(names), colors=list(colors)))
        elif highlight:  # a wide see-through stroke: the lines over it show through
            self.log(
                entity,
                rr.SeriesLines(
                    names=list(names),
                    colors=[see_through(c, HIGHLIGHT_ALPHA) for c in colors],
                    widths=[HIGHLIGHT_PX] * len(names),
                ),
            )
        else:  # zoomed out, the viewer draws each pixel column's min and max, never a mean
            policy = rr.components.AggregationPolicy.MinMax
            self.log(
                entity,
                rr.SeriesLines(names=list(names), colors=list(colors), aggregation_policy=policy),
            )

    # -- what a stage shows ------------------------------------------------------------------
    def series(
        self,
        entity: str,
        t_ns: np.ndarray,
        values: np.ndarray,
        names: Sequence[str] = ("x", "y", "z"),
        *,
        unit: str | None = None,
        plot: str | None = None,
        title: str | None = None,
        colors: Sequence[Any] | None = None,
        points: bool = False,
        under: bool = False,
        highlight: bool = False,
    ) -> None:
        """A signal over time: ``values`` (n,) or (n, k) in the SI ``unit`` at ``t_ns`` (int64
        ns), one named line per column. ``plot`` (default: the entity's last path part) groups
        signals of one stage into one plot; ``title`` names it (the unit is appended). With
        ``under``, the lines lie beneath the others of their plot (the signal before a
        correction, the raw samples under their block means): in a view with other lines they
        are drawn see-through (:data:`UNDER_ALPHA`), whatever order the viewer draws them in.
        With ``highlight``, a line marks where something holds (the still intervals, at g) as
        a wide see-through stroke (:data:`HIGHLIGHT_PX`) that the line it marks shows over."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        values = np.asarray(values, dtype=np.float64).reshape(len(t_ns), -1)
        names, colors, values = _with_data(names, colors_for(names, colors), values)
        if len(t_ns) == 0 or not names:  # no legend entry without data
            return
        shown, factor = display_unit(unit)
        key = plot or entity.rstrip("/").rsplit("/", 1)[-1]
        fig = self.figures.plot(stage_of(entity), key, "time", title=title, unit=shown)
        t_ns, values = decimate(t_ns, values, self.max_points)  # then scaled: fewer points
        if factor != 1.0:
            with np.errstate(over="ignore"):  # a damaged 1e308 cell: inf, not drawn
                values = values * factor
        kept_t, kept = decimate(t_ns, values, self.figures.keep_points)
        fig.series.append(
            Series(
                entity,
                list(names),
                colors,
                kept_t,
                kept,
                "points" if points else "line",
                {"under": True} if under else {"highlight": True} if highlight else {},
            )
        )
        for name, color in zip(names, colors, strict=True):
            self._style(line_path(entity, name), [name], [color], points, highlight)
        if self._wall_clock is None:  # one kind per timeline: the first signal decides
            self._wall_clock = is_wall_clock(int(t_ns.min()))
        if self._origin is None:
            self._origin = int(t_ns.min()) if self._elapsed else 0
        elapsed = t_ns - self._origin
        lo, hi = int(elapsed.min()), int(elapsed.max())  # spans on the time line
        first, last = self._spans.get(entity, (lo, hi))
        self._spans[entity] = (min(first, lo), max(last, hi))
        if self._streams:
            own = LOG_TIMELINE if self._elapsed else TIMELINE
            indexes = [
                rr.TimeColumn(own, timestamp=t_ns.astype("datetime64[ns]"))
                if self._wall_clock
                else rr.TimeColumn(own, duration=t_ns.astype("timedelta64[ns]"))
            ]
            if self._elapsed:
                indexes.insert(
                    0, rr.TimeColumn(TIMELINE, duration=elapsed.astype("timedelta64[ns]"))
                )
            for j, name in enumerate(names):  # one entity per line: views pick lines
                path, columns = line_path(entity, name), rr.Scalars.columns(scalars=values[:, j])
                self._send(
                    lambda s, p=path, c=columns: rr.send_columns(
                        p, indexes=indexes, columns=c, recording=s
                    )
                )

    def curve(
        self,
        entity: str,
        x: np.ndarray,
        values: np.ndarray,
        names: Sequence[str],
        *,
        x_label: str | None = None,
        x_unit: str = "",
        unit: str | None = None,
        plot: str | None = None,
        title: str | None = None,
        log_x: bool = False,
        log_y: bool = False,
        points: bool = False,
        band: bool = False,
        guide: bool = False,
        colors: Sequence[Any] | None = None,
        timeline: str | None = None,
    ) -> None:
        """A curve over something other than time: ``values`` (n,) or (n, k) in the SI ``unit``
        against ``x`` (in ``x_unit``), one named line per column, drawn as markers with
        ``points``, as thin guide lines beneath the data with ``guide`` (the terms of a model).
        With ``band``, ``values`` is (n, 2), the lower and upper edge of a confidence band, and
        ``names`` has its one name. Curves with the same ``plot`` (default:
        the entity, relative to its stage) share a plot and its axes, logarithmic with
        ``log_x``/``log_y``. (``timeline``: the older form, kept working: a label for ``x``.)"""
        x = np.asarray(x, dtype=np.float64)
        values = np.asarray(values, dtype=np.float64).reshape(len(x), -1)
        if not band:
            given = None if colors is None else colors_for(names, colors)
            names, kept_colors, values = _with_data(
                names, given or [(0, 0, 0)] * len(names), values, x
            )
            colors = kept_colors if given is not None else None
        if len(x) == 0 or not names:  # no legend entry without data
            return
        shown, factor = display_unit(unit)
        stage = stage_of(entity)
        key = plot or entity.strip("/").split("/", 1)[-1]
        fig = self.figures.plot(
            stage,
            key,
            "xy",
            title=title,
            unit=shown,
            x_label=x_label or timeline or "x",
            x_unit=x_unit,
            log_x=log_x,
            log_y=log_y,
        )
        if band:
            color = colors_for(names, colors)[0] if colors is not None else (150, 150, 150)
            fig.series.append(Series(entity, list(names[:1]), [color], x, values * factor, "band"))
            return
        style = "points" if points else "guide" if guide else "line"
        x, kept = decimate(x, values * factor, 5 * self.figures.keep_points)
        if colors is None:
            used = sum(len(s.names) for s in fig.series if s.style != "band")
            colors = [PALETTE[(used + i) % len(PALETTE)] for i in range(len(names))]
        fig.series.append(Series(entity, list(names), colors_for(names, colors), x, kept, style))

    def bars(
        self,
        entity: str,
        values: np.ndarray,
        names: Sequence[str],
        *,
        x_label: str,
        unit: str | None = None,
        plot: str | None = None,
        title: str | None = None,
        colors: Sequence[Any] | None = None,
    ) -> None:
        """One value per item (``values`` (n,) or (n, k), item i at x = i), e.g. the residual
        per pose; ``k`` columns are drawn side by side (before/after)."""
        values = np.asarray(values, dtype=np.float64)
        values = values.reshape(len(values), -1)
        shown, factor = display_unit(unit)
        key = plot or entity.strip("/").split("/", 1)[-1]
        fig = self.figures.plot(
            stage_of(entity), key, "bars", title=title, unit=shown, x_label=x_label
        )
        if colors is None:
            named = list(NAMED_COLORS.values())
            colors = named[1:2] if len(names) == 1 else named[: len(names)]
        colors = colors_for(names, colors)
        x = np.arange(len(values), dtype=np.float64)
        fig.series.append(Series(entity, list(names), colors, x, values * factor, "line"))
        k = values.shape[1]
        width = 0.8 / k
        for j, name in enumerate(names):
            offset = (j - (k - 1) / 2) * width
            chart = rr.BarChart(
                values[:, j] * factor,
                color=colors[j],
                abscissa=x + offset,
                widths=np.full(len(x), width),
            )
            self._send(
                lambda s, c=chart, n=name: rr.log(
                    f"{entity}/{_part(n)}", c, static=True, recording=s
                )
            )

    def points3d(
        self,
        entity: str,
        xyz: np.ndarray,
        *,
        unit: str | None,
        name: str,
        plot: str | None = None,
        title: str | None = None,
        colors: np.ndarray | Sequence[Any] | None = None,
        radius: float | None = None,
        color_names: dict[tuple[int, int, int], str] | None = None,
    ) -> None:
        """A cloud of 3D points (n, 3) in the SI ``unit`` (``colors``: one, or one per point;
        ``color_names``: what each colour means, RGB -> words, for the legend)."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        shown, factor = display_unit(unit)
        key = plot or entity.strip("/").split("/", 1)[-1]
        fig = self.figures.plot(stage_of(entity), key, "3d", title=title, unit=shown)
        pts = xyz * factor
        cols = np.asarray(colors if colors is not None else [(40, 100, 230)], dtype=np.uint8)
        cols = cols.reshape(-1, cols.shape[-1])
        stride = max(1, math.ceil(len(pts) / (2 * self.figures.keep_points)))
        kept_cols = cols[::stride] if len(cols) == len(pts) else cols
        fig.series.append(
            Series(
                entity,
                [name],
                [tuple(int(c) for c in cols[0][:3])],
                np.arange(len(pts))[::stride],
                pts[::stride],
                "cloud",
                {"colors": kept_cols, "color_names": dict(color_names or {})},
            )
        )
        radius = cloud_radius(pts) if radius is None else radius
        self.log(entity, rr.Points3D(pts, colors=cols, radii=radius))

    def ellipsoid(
        self,
        entity: str,
        centre: Sequence[float],
        half_sizes: Sequence[float],
        rotation: np.ndarray | None = None,
        *,
        unit: str | None,
        name: str,
        plot: str | None = None,
        title: str | None = None,
        color: Sequence[int] = (50, 50, 50),
    ) -> None:
        """An ellipsoid (``rotation``: 3x3 matrix whose columns are its axes) in the SI ``unit``."""
        from scipy.spatial.transform import Rotation

        shown, factor = display_unit(unit)
        key = plot or entity.strip("/").split("/", 1)[-1]
        fig = self.figures.plot(stage_of(entity), key, "3d", title=title, unit=shown)
        rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        centre_s = np.asarray(centre, dtype=np.float64) * factor
        half = np.asarray(half_sizes, dtype=np.float64) * factor
        fig.series.append(
            Series(
                entity,
                [name],
                [tuple(color)],
                np.zeros(1),
                centre_s[None, :],
                "ellipsoid",
                {"half_sizes": half, "rotation": rot},
            )
        )
        quat = Rotation.from_matrix(rot).as_quat()
        self.log(
            entity,
            rr.Ellipsoids3D(
                centers=[centre_s],
                half_sizes=[half],
                quaternions=[rr.Quaternion(xyzw=quat)],
                colors=[color],
                labels=[name],
            ),
        )

    # -- what the pipeline shows -------------------------------------------------------------
    def sensors(
        self,
        stage: str,
        table: Any,
        sensors: Sequence[str],
        *,
        input_name: str,
        chain: Sequence[Any] = (),
        corrected: bool = False,
        counts: Sequence[str] = (),
    ) -> None:
        """A stage's ``sensors`` in ``table``, one plot per sensor: before the stage (``gyro x
        raw``, or ``gyro x input`` when earlier steps of the ``chain`` corrected it; lighter
        colours) or, with ``corrected``, after it (``gyro x corrected``; ``counts``: the sensors
        the correction left in raw counts). A sensor of an input already sent at the same point
        of the chain (an earlier stage on the same input) is not sent again: the stage's plot
        shows the earlier signal."""
        for name in sensors:
            if not has_stream(table, STREAM_OF_SENSOR[name]):
                continue
            applied = sum(getattr(step, "sensor", None) == name for step in chain)
            label = "corrected" if corrected else "input" if applied else "raw"
            # raw counts (a CSV read with <sensor>_unit = "raw", until a correction makes them
            # SI) are not SI: a plot of their own
            read_in_counts = name in self.raw_counts.get(input_name, ())
            if corrected and read_in_counts and name in counts:
                self._still_counts.add((input_name, name))
            elif corrected:
                self._still_counts.discard((input_name, name))
            in_counts = read_in_counts and (
                label == "raw" or (input_name, name) in self._still_counts
            )
            unit = "raw counts" if in_counts else SENSOR_UNITS[name]
            key, title = name, name
            if not corrected:
                self._input_units[(stage, name)] = unit
            reuse = None if corrected else (input_name, name, applied)
            if reuse is not None and reuse in self._reused:
                shown = display_unit(unit)[0]
                plot = self.figures.plot(stage, key, "time", title=title, unit=shown)
                plot.series.append(self._reused[reuse])
                continue
            # averaged down column by column first: no (n, 3) copy of the input
            t_ns, values = decimate_columns(*sensor_columns(table, name), self.max_points)
            axes = [c.split("_")[-1] for c in SENSOR_COLUMNS[name]]
            names = [f"{name} {a} {label}" if len(axes) > 1 else f"{name} {label}" for a in axes]
            colors = AXIS_COLORS[: len(axes)]
            if not corrected:
                colors = [lighter(c) for c in colors]
            entity = f"/{stage}/{label}/{name}"
            self.series(
                entity,
                t_ns,
                values,
                names,
                unit=unit,
                plot=key,
                title=title,
                colors=colors,
                under=not corrected,
            )
            shown_series = next(
                (
                    p.series[-1]
                    for p in self.figures.of_stage(stage)
                    if p.series and p.series[-1].entity == entity
                ),
                None,  # nothing drawn: every value of the stream is NaN (a CSV without gyro)
            )
            if reuse is not None and shown_series is not None:
                self._reused[reuse] = shown_series

    def input_unit(self, stage: str, sensor: str) -> str:
        """The unit of ``sensor`` in the table ``stage`` fits on: SI, or ``raw counts`` for a
        CSV read with ``<sensor>_unit = "raw"`` that no earlier stage corrected."""
        return self._input_units.get((stage, sensor), SENSOR_UNITS[sensor])

    def document(self, stage: str | None, markdown: str) -> None:
        """A stage's results (``stage`` None: the run's summary) as a markdown ``TextDocument``."""
        path = "/summary" if stage is None else f"/{stage}/summary"
        self._documents[stage or ""] = path
        if stage is not None:
            self.figures.stage(stage)
        self._send(
            lambda s: rr.log(
                path,
                rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN),
                static=True,
                recording=s,
            )
        )

    # -- blueprint ---------------------------------------------------------------------------
    def add_view(self, stage: str, view: Any) -> None:
        """Add a view of your own (``rrb.Spatial3DView`` of what :meth:`log` sent...) to a
        stage's tab, after the plots the recorder lays out."""
        self.figures.stage(stage)
        self._views.setdefault(stage, []).append(view)

    def ensure_stage(self, stage: str) -> None:
        """Give a stage a tab (even one that showed nothing: its results document)."""
        self.figures.stage(stage)

    def _time_views(self, plot: Plot, plot_px: float = 0.0, width_px: float = 0.0) -> list[Any]:
        """The views of a plot over time: one per group of lines of like magnitude
        (:func:`~imupipe.pipeline.report.figures.split_by_magnitude`, as in the report: accel z at
        9.8 m/s^2 apart from x and y near 0), each with its legend in the top right corner above
        the data (the y range leaves it room in a plot ``plot_px`` high; 0: a lone view's)."""
        return [self._time_view(part, plot_px, width_px) for part in split_by_magnitude(plot)]

    def _time_view(self, part: Plot, plot_px: float, width_px: float = 0.0) -> Any:
        """One view of :meth:`_time_views`. Rerun draws a view's lines in the order of their
        entity paths, not of its contents: the lines ``under`` the others (raw samples beneath
        block means, the input beneath the corrected signal) are made see-through in this view
        (a blueprint override of their colour) so that the lines over them show wherever they
        are drawn; alone in a view they keep their own colour."""
        paths = list(dict.fromkeys(line_path(s.entity, n) for s in part.series for n in s.names))
        under = {
            line_path(s.entity, n): c
            for s in part.series
            if s.extra.get("under")
            for n, c in zip(s.names, s.colors, strict=True)
        }
        policy = rr.components.AggregationPolicy.MinMax
        overrides = {}
        if under and len(under) < len(paths):  # beneath lines of another kind: see-through
            overrides = {
                path: rr.SeriesLines(
                    colors=[see_through(color)], widths=[UNDER_PX], aggregation_policy=policy
                ).visualizer()
                for path, color in under.items()
            }
        for path, color in crossing(part).items():  # x, y, z over each other: all show
            overrides[path] = rr.SeriesLines(
                colors=[see_through(color, CROSSING_ALPHA)], aggregation_policy=policy
            ).visualizer()
        # the legend's corner kept free of data: above the data (a y range with room) or, where
        # that costs less of the view (a wide view), beside it (a time range that runs on)
        rows, wide = len(paths), legend_width(paths_names(part)) / max(width_px or PLOT_PX, 1.0)
        tall = legend_share(rows, plot_px or PLOT_PX)
        beside = width_px > 0 and wide < tall  # a view whose width is known
        view = rrb.TimeSeriesView(
            origin="/",
            contents=paths,
            name=part.heading,
            plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True),
            axis_y=rrb.ScalarAxis(
                range=legend_room(part, 0 if beside else rows, plot_px or PLOT_PX)
            ),
            overrides=overrides or None,
        )
        return _with_span(view, self._spans_of(part), run_on=wide if beside else 0.0)

    def _spans_of(self, plot: Plot) -> list[tuple[int, int]]:
        """(first, last) ns of each signal of a plot."""
        return [self._spans[e] for e in dict.fromkeys(plot.entities) if e in self._spans]

    def _view(self, plot: Plot) -> Any:
        if plot.kind == "bars":
            # the legend of a bar chart shows entity paths: the colours are named in the title
            named = {c: n for n, c in NAMED_COLORS.items()}
            key = [
                f"{named.get(tuple(c), str(tuple(c)))} {n}"
                for s in plot.series
                for n, c in zip(s.names, s.colors, strict=True)
            ]
            title = f"{plot.heading} per {plot.x_label}"
            return rrb.BarChartView(
                origin="/",
                contents=[f"{e}/**" for e in dict.fromkeys(plot.entities)],
                name=title + (f": {', '.join(key)}" if len(key) > 1 else ""),
                plot_legend=rrb.PlotLegend(visible=False),
            )
        if plot.kind == "3d":
            return rrb.Spatial3DView(
                origin="/",
                contents=[*dict.fromkeys(plot.entities), f"{axes3d_path(plot)}/**"],
                name=f"{plot.heading}; axes {scale3d(plot)[1]:g} {plot.unit}".rstrip(),
            )
        return plot2d.view(plot)

    def _fit_time_axis(self, view: Any) -> None:
        """A time-series view added by a stage opens on the span of the signals under its origin."""
        if getattr(view, "class_identifier", None) != "TimeSeries" or "TimeAxis" in view.properties:
            return
        origin = str(view.origin).rstrip("/")
        _with_span(
            view,
            [v for e, v in self._spans.items() if e == origin or e.startswith(origin + "/")],
        )

    def blueprint(self) -> rrb.Blueprint:
        tabs: list[Any] = []
        if "" in self._documents:
            tabs.append(rrb.TextDocumentView(origin=self._documents[""], name="Summary"))
        for stage in self.figures.stages:
            plots = self.figures.of_stage(stage)
            parts = [part for p in plots if p.kind == "time" for part in split_by_magnitude(p)]
            others = [self._view(p) for p in plots if p.kind != "time"]
            added = []
            for view in self._views.get(stage, []):
                self._fit_time_axis(view)
                (added if view.class_identifier == "TimeSeries" else others).append(view)
            spans = [sp for part in parts for sp in self._spans_of(part)]
            spans += [_span_of(v) for v in added if _span_of(v) is not None]  # type: ignore[misc]
            hours = max(((b - a) / 3.6e12 for a, b in spans), default=0.0)
            text = (
                rrb.TextDocumentView(origin=self._documents[stage], name=f"{stage}: results")
                if stage in self._documents
                else None
            )
            plan = plan_tab(text is not None, len(others), len(parts) + len(added), hours)
            signals = [self._time_view(p, plan.plot_px, plan.width_px) for p in parts] + added
            tabs.append(_stage_layout(stage, text, others, signals, plan))
        return rrb.Blueprint(
            rrb.Tabs(*tabs) if tabs else rrb.TimeSeriesView(origin="/"),
            # paused: a recording that plays moves its time cursor (and redraws) for its whole
            # span after it opens
            rrb.TimePanel(timeline=TIMELINE, state="collapsed", play_state="paused"),
            rrb.BlueprintPanel(state="collapsed"),
            rrb.SelectionPanel(state="collapsed"),
        )

    def _draw_plots(self) -> None:
        for plot in self.figures.plots.values():
            if plot.kind == "3d":
                centre, length = scale3d(plot)
                arrows = rr.Arrows3D(
                    origins=[centre] * 3, vectors=np.eye(3) * length, colors=AXIS_COLORS
                )
                # each name past its arrow's tip (the arrows' own labels, from one origin,
                # overlapped); the length is in the view's name
                tips = rr.Points3D(
                    np.asarray(centre) + np.eye(3) * length * 1.12,
                    colors=AXIS_COLORS,
                    labels=list("xyz"),
                    radii=length * 0.01,
                    show_labels=True,
                )
                path = axes3d_path(plot)
                self._send(lambda s, p=path, a=arrows: rr.log(p, a, static=True, recording=s))
                self._send(
                    lambda s, p=path, a=tips: rr.log(f"{p}/names", a, static=True, recording=s)
                )
            if plot.kind == "xy":
                for entity, archetype in plot2d.draw(plot):
                    self._send(
                        lambda s, e=entity, a=archetype: rr.log(e, a, static=True, recording=s)
                    )

    def close(self) -> None:
        """Draw the 2D plots, send the blueprint and flush everything to the sinks."""
        if not self._streams:
            return
        self._draw_plots()
        blueprint = self.blueprint()
        if self._live is not None:
            try:
                self._live.send_blueprint(blueprint, make_active=True, make_default=True)
                self._live.flush(timeout_sec=10.0)
            except Exception as exc:  # noqa: BLE001 - the file is complete; only the viewer failed
                self._drop_live(exc)
        self.rec.flush()
        for stream in self._streams:
            stream.disconnect()
        if self._path is not None:
            blueprint_first(self._path, blueprint)


def blueprint_first(path: Path, blueprint: rrb.Blueprint) -> None:
    """Rewrite the recording at ``path`` with ``blueprint`` (active and default) as its first
    messages, then its data chunks as they were.

    A viewer that streams the file (``rerun --web-viewer``, a web viewer opened with
    ``?url=.../recording.rrd``) lays out what it has received so far: with the blueprint at the
    end, as the recorder can only send it once every stage has shown its plots, it has no
    blueprint of imupipe's until the last byte (issue #38: Rerun's automatic layout, without
    the tabs); first, the tabs come with the first bytes. Rerun's own
    ``save(default_blueprint=...)`` puts it first the same way, but needs it before the data.
    Re-encoding the demo's 325 chunks takes about 0.8 s."""
    import rerun.chunk as rc

    reader = rc.RrdReader(str(path))
    stores = reader.recordings()
    app_id = stores[0].application_id if stores else "imupipe"
    tmp = path.with_name(path.name + ".blueprint-first")
    try:
        out = rr.RecordingStream(app_id, recording_id=stores[0].recording_id if stores else None)
        out.save(str(tmp))
        out.send_blueprint(blueprint, make_active=True, make_default=True)
        for store in stores:
            for chunk in reader.stream(store=store).to_chunks():
                out.send_chunks(chunk)
        out.flush()
        out.disconnect()
        del reader
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _with_data(
    names: Sequence[str],
    colors: Sequence[Any],
    values: np.ndarray,
    x: np.ndarray | None = None,
) -> tuple[list[str], list[Any], np.ndarray]:
    """The columns of ``values`` (n, k) that have a finite value (at a finite ``x``), with their
    names and colours: a line without data never gets a legend entry."""
    ok = np.isfinite(values)
    if x is not None:
        ok &= np.isfinite(x)[:, None]
    keep = ok.any(axis=0) if len(values) else np.zeros(values.shape[1], dtype=bool)
    if keep.all():
        return list(names), list(colors), values
    idx = np.flatnonzero(keep)
    return [names[i] for i in idx], [colors[i] for i in idx], values[:, idx]


def line_path(entity: str, name: str) -> str:
    """The entity of one line of a signal: ``/gyro_bias/corrected/gyro/gyro_x_corrected``."""
    return f"{entity}/{_part(name)}"


def axes3d_path(plot: Plot) -> str:
    """Where a 3D plot's axes (three arrows with their length) are logged."""
    return f"/{plot.stage}/{plot.key}/axes3d"


def scale3d(plot: Plot) -> tuple[list[float], float]:
    """(where, length) of a 3D plot's axes: at the low corner of the points' bounding box (out
    of the cloud, not hidden in it), a round length about half the points' largest distance
    from their median along an axis (the scale of the view)."""
    pts = [s.values.reshape(-1, 3) for s in plot.series if s.values.size]
    data = np.concatenate(pts) if pts else np.zeros((1, 3))
    data = data[np.isfinite(data).all(axis=1)]
    if not len(data):
        return [0.0, 0.0, 0.0], 1.0
    reach = float(np.abs(data - np.median(data, axis=0)).max()) or 1.0
    ticks = nice_ticks(0.0, 0.6 * reach, 3)
    inside = ticks[(ticks > 0) & (ticks <= 0.6 * reach)]
    length = float(inside[-1] if len(inside) else ticks[1])
    return [float(c) for c in data.min(axis=0)], length


SCREEN = (1600.0, 1000.0)
"""The window the tabs are laid out for (px): docs/screenshots/make_screenshots.py's default."""
TAB_PX = 906.0
"""Height of a stage tab's content at :data:`SCREEN` (below the viewer's top bar and the
stages' tab bar, above the collapsed time panel); an inner tab bar takes :data:`INNER_TAB_PX`."""
INNER_TAB_PX = 27.0
VIEW_CHROME_PX = (46.0, 70.0)
"""What a time-series view spends outside its plot (px): height (title bar, time labels) and
width (value labels, margins)."""
TEXT_SHARE = 2 / 5
"""The width share of a stage's results document beside its plots."""
LEGEND_ROW_PX, LEGEND_PAD_PX = 23.0, 12.0
"""Height of a legend row and the legend's margins, as the viewer draws them."""
PLOT_PX = 250.0
"""The plot height assumed for a view laid out on its own (a stage's added view)."""
HOUR_PX = 72.0
"""Pixels per hour a time axis needs to label every hour: Rerun's time axis steps from 1 h
marks to 12 h ones (re_format's ``next_grid_tick_magnitude_nanos``) and writes a mark's label
only when marks are 60 px apart or more (egui_plot's ``label_spacing``, faded up to 80 px): a
13.7 h session in a 280 px wide view showed one label, its day."""
SIGNALS_PER_TAB = 4
"""The most views of a long session stacked in one inner tab (each keeps ~200 px of height)."""
HIGHLIGHT_PX, HIGHLIGHT_ALPHA = 6.0, 0.4
"""Width (px) and opacity of a ``highlight`` line (:meth:`Recorder.series`)."""
UNDER_ALPHA, UNDER_PX = 0.4, 3.0
"""Opacity and width (px) of a line ``under`` the others of its view (:meth:`Recorder.series`):
a light halo around the line over it, which a line of the same values (a temperature of little
noise beneath its block means) showed nothing of at the viewer's width (0.75 px)."""


CROSSING_ALPHA = 0.6
"""Opacity of lines over time that share their values' range with another line of their view
(x, y and z corrected, all about 0): as ``report.html``'s lines over time
(:data:`~imupipe.pipeline.report.svg_plot.LINE_OPACITY`), so the one drawn last hides none."""


def crossing(plot: Plot) -> dict[str, tuple[int, ...]]:
    """Line entity -> colour of the lines of ``plot`` (neither ``under`` nor ``highlight``) whose
    range of values overlaps another such line's: drawn in one view, one would hide the other."""
    kept = {
        (s.entity, n): c
        for s in plot.series
        if not s.extra.get("under") and not s.extra.get("highlight") and s.style != "points"
        for n, c in zip(s.names, s.colors, strict=True)
    }
    ranges = [(e, n, lo, hi) for e, n, lo, hi in column_ranges(plot) if (e, n) in kept]
    out = {}
    for i, (e, n, lo, hi) in enumerate(ranges):
        if any(lo <= b and a <= hi for k, (_, _, a, b) in enumerate(ranges) if k != i):
            out[line_path(e, n)] = tuple(kept[(e, n)])
    return out


def see_through(color: Sequence[int], alpha: float = UNDER_ALPHA) -> tuple[int, int, int, int]:
    """``color`` (RGB) with the opacity ``alpha`` (RGBA, 0..255)."""
    return (int(color[0]), int(color[1]), int(color[2]), int(round(255 * alpha)))


class TabPlan:
    """How a stage's tab is laid out at :data:`SCREEN` (:func:`plan_tab`): ``long`` (its signals
    stacked at full width, :data:`SIGNALS_PER_TAB` to an inner tab), the signals' grid columns,
    the height of their plots (px) and the width of their plots (px)."""

    def __init__(self, long: bool, columns: int, plot_px: float, width_px: float) -> None:
        self.long, self.columns, self.plot_px, self.width_px = long, columns, plot_px, width_px

    def __repr__(self) -> str:
        return (
            f"TabPlan(long={self.long}, columns={self.columns}, "
            f"plot_px={self.plot_px:.0f}, width_px={self.width_px:.0f})"
        )


def plan_tab(text: bool, plots: int, signals: int, hours: float) -> TabPlan:
    """The layout of a stage's tab with a results document (``text``), ``plots`` views of its fit
    and ``signals`` time-series views whose longest signal lasts ``hours``.

    A time axis is readable when it labels several times. Rerun chooses the marks itself (1 h,
    then 12 h apart) and labels those :data:`HOUR_PX` apart, so a session of many hours needs
    a wide view: when the signals' grid, beside the document, leaves them less than
    :data:`HOUR_PX` per hour, the tab gives the signals inner tabs of their own at the full
    width of the window, one view under another (:data:`SIGNALS_PER_TAB` to a tab), as long as
    that width labels every hour (up to about 21 h). Shorter sessions keep the grid (as before);
    longer ones too (Rerun labels their 12 h marks in the grid)."""
    width, _ = SCREEN
    beside = width * (1 - TEXT_SHARE) if text else width
    inner = plots + signals > 4 and plots > 0 and signals > 0
    n = signals if inner else plots + signals
    columns = max(1, math.ceil(math.sqrt(n)))
    plot_w = beside / columns - VIEW_CHROME_PX[1]
    if signals and plot_w < hours * HOUR_PX <= width - VIEW_CHROME_PX[1]:
        # stacked at full width, where every hour gets its label (a longer session gets 12 h
        # marks, labelled in the grid too); one view per row, SIGNALS_PER_TAB to an inner tab
        per_tab = math.ceil(signals / math.ceil(signals / SIGNALS_PER_TAB))
        height = TAB_PX - INNER_TAB_PX
        return TabPlan(True, 1, height / per_tab - VIEW_CHROME_PX[0], width - VIEW_CHROME_PX[1])
    rows = math.ceil(n / columns) if n else 1
    height = TAB_PX - (INNER_TAB_PX if inner else 0.0)
    return TabPlan(False, columns, height / rows - VIEW_CHROME_PX[0], plot_w)


def legend_share(rows: int, plot_px: float) -> float:
    """The share of a plot ``plot_px`` high that a legend of ``rows`` covers (at most 0.7)."""
    return min(0.7, (LEGEND_ROW_PX * rows + LEGEND_PAD_PX) / max(plot_px, 1.0)) if rows else 0.0


def legend_width(names: Sequence[str]) -> float:
    """The width (px) of a legend of ``names`` as the viewer draws it (its marker, its margins
    and about 7.2 px a character)."""
    return 7.2 * max((len(n) for n in names), default=0) + 40.0


def paths_names(plot: Plot) -> list[str]:
    """The names of a plot's lines (what its legend lists)."""
    return [n for s in plot.series for n in s.names]


def legend_room(plot: Plot, rows: int, plot_px: float = PLOT_PX) -> tuple[float, float]:
    """The y range of a view of ``plot``'s lines: their data with 5 % to spare below, and above
    it room for the legend's ``rows`` in the top right corner of a plot ``plot_px`` high, so the
    legend covers no data."""
    spans = [(lo, hi) for _, _, lo, hi in column_ranges(plot)]
    if not spans:
        return (0.0, 1.0)
    lo, hi = min(a for a, _ in spans), max(b for _, b in spans)
    span = (hi - lo) or (abs(hi) * 0.1 or 1.0)
    top = legend_share(rows, plot_px)  # of the height
    return (lo - 0.05 * span, hi + span * (0.05 + top) / (1.0 - top))


def _part(name: str) -> str:
    """A name as one entity path part (``|a| - g`` -> ``a_g``)."""
    return re.sub(r"[^0-9A-Za-z]+", "_", name).strip("_") or "value"


def _stage_layout(
    stage: str, text: Any, plots: list[Any], signals: list[Any], plan: TabPlan | None = None
) -> Any:
    """A stage's tab (:func:`plan_tab`): its results document beside its plots; when it has both
    plots of its fit and signals over time, and more than four views in all, those sit in two
    inner tabs; the signals of a long session sit in inner tabs of their own, at full width."""
    plan = plan or plan_tab(text is not None, len(plots), len(signals), 0.0)
    if plan.long and signals:
        first = []
        if plots or text is not None:
            front = rrb.Grid(*plots, name=f"{stage}: fit") if plots else None
            if text is not None and front is not None:
                front = rrb.Horizontal(text, front, column_shares=[2, 3], name=f"{stage}: fit")
            elif text is not None:
                front = rrb.TextDocumentView(origin=text.origin, name=f"{stage}: results")
            first.append(front)
        tabs = math.ceil(len(signals) / SIGNALS_PER_TAB)
        per_tab = math.ceil(len(signals) / tabs)
        chunks = [signals[i : i + per_tab] for i in range(0, len(signals), per_tab)]
        named = (
            [f"{stage}: signals"]
            if len(chunks) == 1
            else [f"{stage}: signals {i + 1}/{len(chunks)}" for i in range(len(chunks))]
        )
        stacks = [rrb.Vertical(*c, name=n) for c, n in zip(chunks, named, strict=True)]
        return rrb.Tabs(*first, *stacks, name=stage)
    if len(plots) + len(signals) > 4 and plots and signals:
        right: Any = rrb.Tabs(
            rrb.Grid(*plots, name=f"{stage}: fit"),
            rrb.Grid(*signals, name=f"{stage}: signals", grid_columns=plan.columns),
        )
    else:
        right = rrb.Grid(*plots, *signals, name=f"{stage}: plots", grid_columns=plan.columns)
    if text is None:
        return rrb.Horizontal(right, name=stage) if plots or signals else rrb.Grid(name=stage)
    if not plots and not signals:
        return rrb.TextDocumentView(origin=text.origin, name=stage)
    return rrb.Horizontal(text, right, column_shares=[2, 3], name=stage)


def _span_of(view: Any) -> tuple[int, int] | None:
    """(first, last) ns of a time-series view's time axis, when it has one."""
    axis = view.properties.get("TimeAxis")
    if axis is None or axis.view_range is None:
        return None
    rng = axis.view_range.as_arrow_array()[0].as_py()
    start, end = rng.get("start"), rng.get("end")
    return (int(start), int(end)) if isinstance(start, int) and isinstance(end, int) else None


def _with_span(view: Any, spans: list[tuple[int, int]], run_on: float = 0.0) -> Any:
    """``view`` with its time axis set to cover ``spans`` ((first, last) ns); unchanged if none.
    With ``run_on`` (a share of the view's width) the axis runs on past the last sample so that
    much of the view's right side is free of data (the legend's corner)."""
    if spans:
        first, last = min(a for a, _ in spans), max(b for _, b in spans)
        if 0.0 < run_on < 1.0:
            last += int((last - first) * run_on / (1.0 - run_on))
        view.properties["TimeAxis"] = rrb.TimeAxis(
            view_range=rrb.TimeRange(
                start=rrb.TimeRangeBoundary.absolute(nanos=first),
                end=rrb.TimeRangeBoundary.absolute(nanos=last),
            )
        )
    return view


def open_recorder(
    cfg: Any, out: Any, *, spawn: bool = False, quiet: bool = False
) -> tuple[Any, list[Path]]:
    """The recorder of a run and the files it writes: a :class:`Recorder` writing
    ``recording.rrd`` (staged in ``out``) when ``[output] rerun``, keeping the figures for
    ``report.html`` when ``[output] report``, streaming to a viewer with ``spawn``; a
    :class:`NullRecorder` when neither is wanted. A viewer that cannot start is one warning:
    the run and its files go on without it."""

    def warn(message: str) -> None:
        if not quiet:
            print(f"imupipe: warning: {message}", file=sys.stderr)

    if spawn and not cfg.output.rerun:
        warn("--spawn: [output] rerun = false: there is no recording to show")
    if not (cfg.output.rerun or cfg.output.report):
        return NullRecorder(), []
    rrd = cfg.output.dir / "recording.rrd"
    viewer = None
    if spawn and cfg.output.rerun:
        viewer, why = start_viewer()
        if viewer is None:
            warn(
                f"--spawn: {why}; the recording is written to {rrd}: without a display, "
                f"open it with `rerun --web-viewer {rrd}`, or see report.html"
            )
    recorder = Recorder(
        out.path(rrd) if cfg.output.rerun else None,
        viewer=viewer,
        max_points=cfg.output.rerun_max_points,
        warn=warn,
    )
    recorder.raw_counts = raw_count_sensors(cfg.inputs)
    return recorder, [rrd] if cfg.output.rerun else []


# -- the viewer (--spawn) --------------------------------------------------------------------------
def start_viewer(timeout: float = 20.0) -> tuple[str | None, str]:
    """Start the Rerun viewer (the ``rerun`` command on PATH, which rerun-sdk installs) on a free
    port, detached, and wait until it accepts data. Returns (its gRPC URL, "") or (None, why it
    cannot be used)."""
    exe = shutil.which("rerun")
    if exe is None:
        return None, "no Rerun viewer on PATH (the 'rerun' command comes with rerun-sdk)"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    # the viewer's messages go to a file of its own (unlinked: gone when it exits)
    with tempfile.TemporaryFile() as log:
        try:
            proc = subprocess.Popen(
                [exe, "--port", str(port), "--expect-data-soon"],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                env={**os.environ, "RERUN_APP_ONLY": "true"},
                start_new_session=True,
            )
        except OSError as exc:
            return None, f"the Rerun viewer could not start ({exc})"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                return None, f"the Rerun viewer could not start ({_last_line(log)})"
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            except OSError:
                time.sleep(0.1)
                continue
            time.sleep(0.5)  # a viewer without a display listens, then exits
            if proc.poll() is not None:
                return None, f"the Rerun viewer could not start ({_last_line(log)})"
            return f"rerun+http://127.0.0.1:{port}/proxy", ""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    return None, f"the Rerun viewer did not answer within {timeout:.0f} s"


def _last_line(log: Any) -> str:
    """The last non-empty line a process wrote, without terminal colour codes."""
    log.seek(0)
    text = log.read().decode("utf-8", "replace")
    lines = [re.sub(r"\x1b\[[0-9;]*m", "", line).strip() for line in text.splitlines()]
    lines = [re.sub(r" at \S+\.rs:\d+", "", line) for line in lines]  # Rust source locations
    lines = [line for line in lines if line]
    return lines[-1][:300] if lines else "it exited without a message"


def cloud_radius(pts: np.ndarray) -> float:
    """The radius of a 3D cloud's points (in its unit): 0.8 % of the cloud's own size (its largest
    distance from its median along an axis), wherever it lies: a raw magnetometer's cloud sits
    thousands of counts from the origin, and a radius taken from the distance to the origin drew
    its points as balls that hid the ellipsoid."""
    finite = pts[np.isfinite(pts).all(axis=1)]
    if not len(finite):
        return 0.008
    return 0.008 * (float(np.abs(finite - np.median(finite, axis=0)).max()) or 1.0)
