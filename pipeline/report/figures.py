"""What a run shows, declared once by the stages and drawn twice: in ``recording.rrd`` (Rerun)
and in ``report.html`` (inline SVG, :mod:`imupipe.pipeline.report.svg_plot`).

A stage says *what* it shows (a signal, its SI unit, the names of its lines, the kind of plot);
:class:`Figures` keeps it as :class:`Plot` objects, one per plot, in the order they were first
declared; the sinks decide *how* to lay them out. The kinds:

- ``time``: signals over time (x = int64 ns timestamps),
- ``xy``: curves over something other than time (Allan deviation over tau, bias against
  temperature), on linear or logarithmic axes,
- ``bars``: one value per item (residual per pose, per transition),
- ``3d``: point clouds and ellipsoids (magnetometer coverage).

Every plot has one physical unit (a series declared into a plot of another unit gets a plot of
its own beside it). Values are stored in the unit they are shown in: SI, except
tesla, shown in microtesla (``DISPLAY_UNITS``). The kept copies are small: a signal longer than
``keep_points`` is kept as the envelope of consecutive blocks, each block's smallest and largest
value (:func:`decimate`), so its noise shows at full height (a block mean would hide it); the
recording holds more, the MCAP output all of it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

PlotKind = Literal["time", "xy", "bars", "3d"]
Style = Literal["line", "guide", "points", "band", "cloud", "ellipsoid"]

DISPLAY_UNITS: dict[str, tuple[str, float]] = {
    "T": ("uT", 1e6),
    "T/s": ("uT/s", 1e6),
    "T/A": ("uT/A", 1e6),
}
"""SI unit -> (unit shown, factor): the magnetometer is shown in microtesla."""

AXIS_COLORS: list[tuple[int, int, int]] = [(228, 26, 28), (30, 160, 60), (40, 100, 230)]
"""x, y, z: red, green, blue (readable on Rerun's dark and light themes)."""

PALETTE: list[tuple[int, int, int]] = [
    (40, 100, 230),
    (230, 120, 20),
    (30, 160, 60),
    (200, 40, 160),
    (140, 90, 40),
    (0, 170, 190),
    (120, 80, 210),
]
"""Colours for lines that are not axes (fitted terms, before/after...), in the order curves of
one plot take them."""


WALL_CLOCK_NS = 10**18
"""2001-09-09 UTC, in ns since the Unix epoch: times from here on are read as dates (a ROS or
MCAP stamp); earlier ones as time since the log's own origin (a CSV counting from 0, a PX4
ULog's time since boot), shown as a duration, never as a day in 1970."""


def is_wall_clock(t_ns: int) -> bool:
    """Whether ``t_ns`` (int64 ns) reads as a date; see :data:`WALL_CLOCK_NS`."""
    return int(t_ns) >= WALL_CLOCK_NS


def display_unit(unit: str | None) -> tuple[str, float]:
    """(unit shown, factor from SI) for an SI ``unit`` (None: dimensionless)."""
    if unit is None:
        return "", 1.0
    return DISPLAY_UNITS.get(unit, (unit, 1.0))


def lighter(color: Sequence[int], amount: float = 0.55) -> tuple[int, int, int]:
    """``color`` mixed with grey: the 'before' version of a line."""
    grey = 160.0
    return tuple(int(round(c + (grey - c) * amount)) for c in color[:3])  # type: ignore[return-value]


NAMED_COLORS: dict[str, tuple[int, int, int]] = {
    "grey": (150, 150, 150),
    "blue": (40, 100, 230),
    "orange": (230, 120, 20),
    "green": (30, 160, 60),
    "magenta": (200, 40, 160),
}
"""Colours that can be named in a title (bar charts, whose legend shows entity paths)."""


def colors_for(names: Sequence[str], colors: Sequence[Sequence[int]] | None) -> list[tuple]:
    """Colours for ``names``: the given ones, else x/y/z colours for up to 3 lines, else the
    palette."""
    if colors is not None and len(colors) >= len(names):
        return [tuple(c) for c in colors[: len(names)]]
    base = AXIS_COLORS if len(names) <= len(AXIS_COLORS) else PALETTE
    return [base[i % len(base)] for i in range(len(names))]


@dataclass
class Series:
    """One declared signal or curve: ``values`` (n, k) with one name and colour per column.

    For ``band``, ``values`` is (n, 2): lower and upper bound; for ``cloud`` (n, 3) points and
    for ``ellipsoid`` a (1, 3) centre with ``extra = {"half_sizes", "rotation"}``."""

    entity: str
    names: list[str]
    colors: list[tuple]
    x: np.ndarray
    values: np.ndarray
    style: Style = "line"
    extra: dict = field(default_factory=dict)


@dataclass
class Plot:
    """One plot: a view in the recording, a figure in the report."""

    stage: str
    key: str
    kind: PlotKind
    title: str
    unit: str
    """The unit shown (after :data:`DISPLAY_UNITS`); one per plot."""
    x_label: str = "time"
    x_unit: str = ""
    log_x: bool = False
    log_y: bool = False
    series: list[Series] = field(default_factory=list)
    origin: int | None = None
    """A ``time`` plot's time origin (int64 ns) when the run gives its plots one
    (:meth:`Figures.share_time_origin`); else the plot's own first sample."""

    @property
    def heading(self) -> str:
        """The title with the unit: ``gyro, raw and corrected (rad/s)``."""
        return f"{self.title} ({self.unit})" if self.unit else self.title

    @property
    def x_heading(self) -> str:
        return f"{self.x_label} ({self.x_unit})" if self.x_unit else self.x_label

    @property
    def entities(self) -> list[str]:
        return [s.entity for s in self.series]


def stage_of(entity: str) -> str:
    """The stage an entity belongs to: its first path part (``/allan/gyro/x`` -> ``allan``)."""
    return entity.strip("/").split("/", 1)[0]


def decimate(t: np.ndarray, values: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_points`` rows. A signal over time (``t`` int64 ns): the min/max envelope
    of consecutive blocks (:func:`decimate_columns`); a curve (float ``t``): every k-th point."""
    if len(t) <= max_points:
        return t, values
    return decimate_columns(t, list(values.reshape(len(t), -1).T), max_points)


def decimate_columns(
    t: np.ndarray, columns: Sequence[np.ndarray], max_points: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`decimate` of the (n, k) array whose columns are ``columns`` (each (n,)), without
    making that array: (times, (m, k) values).

    Over time, the signal is cut into ``max_points // 2`` blocks of consecutive samples and each
    block gives two rows: its smallest value at its first sample's time and its largest at its
    middle sample's time (per column; NaN ignored). Drawn as a line, the rows fill the band the
    raw samples fill at that zoom: the noise keeps its height (a block mean showed a 100 Hz gyro's
    0.0017 rad/s noise about 6x smaller)."""
    if len(t) <= max_points:
        return t, np.column_stack(columns)
    if np.issubdtype(t.dtype, np.integer):
        window = math.ceil(len(t) / max(1, max_points // 2))
        starts = np.arange(0, len(t), window)
        middles = np.minimum(starts + window // 2, len(t) - 1)
        times = np.empty(2 * len(starts), dtype=t.dtype)
        times[0::2], times[1::2] = t[starts], t[middles]
        out = np.empty((len(times), len(columns)))
        with np.errstate(invalid="ignore"):
            for j, c in enumerate(columns):
                out[0::2, j] = np.fmin.reduceat(c, starts)
                out[1::2, j] = np.fmax.reduceat(c, starts)
        return times, out
    window = math.ceil(len(t) / max_points)
    keep = np.arange(0, len(t), window)
    return t[keep], np.column_stack([c[keep] for c in columns])


SPARSE = 4
"""A series of points with at most 1/SPARSE of the densest one's points is drawn on top (the
soak blocks among heating and cooling): a few points amid many stay visible."""


def is_sparse(series: Series, among: Sequence[Series]) -> bool:
    """Whether ``series`` is a few points amid many of the series ``among`` it (:data:`SPARSE`):
    drawn on top."""
    dense = max((len(s.x) for s in among if s.style == "points"), default=0)
    return series.style == "points" and SPARSE * len(series.x) <= dense


def column_ranges(plot: Plot) -> list[tuple[str, str, float, float]]:
    """(entity, line name, smallest, largest finite value) of every line of a plot."""
    out = []
    for s in plot.series:
        values = s.values.reshape(len(s.x), -1)
        for j, name in enumerate(s.names):
            v = values[:, j][np.isfinite(values[:, j])]
            if len(v):
                out.append((s.entity, name, float(v.min()), float(v.max())))
    return out


def magnitude_groups(plot: Plot, flatten: float = 20.0) -> list[dict[str, set[str]]]:
    """The lines of a plot over time in groups that share a y range. Lines sorted by their
    middle join the group before them unless the group's range would grow past ``flatten``
    times the widest line's own range (that line would fill less than 1/``flatten`` of the
    view's height): accel x and y near 0 with z at 9.8 m/s^2 make two groups; gyro raw and
    corrected, 0.01 rad/s apart with 0.01 rad/s of noise, one. Each group maps entity -> the
    names of its lines shown there."""
    ranges = sorted(column_ranges(plot), key=lambda r: (r[2] + r[3]) / 2)
    groups: list[tuple[float, float, float, dict[str, set[str]]]] = []
    for entity, name, lo, hi in ranges:
        if groups:
            glo, ghi, widest, members = groups[-1]
            widest = max(widest, hi - lo, 1e-12 * max(abs(lo), abs(hi), 1.0))
            if max(ghi, hi) - min(glo, lo) <= flatten * widest:
                members.setdefault(entity, set()).add(name)
                groups[-1] = (min(glo, lo), max(ghi, hi), widest, members)
                continue
        groups.append((lo, hi, hi - lo, {entity: {name}}))
    return [members for *_, members in groups] or [{e: set() for e in plot.entities}]


def split_by_magnitude(plot: Plot) -> list[Plot]:
    """A ``time`` plot as one plot per group of :func:`magnitude_groups` (itself when there is
    one): each keeps the series' lines of its group, the title names them (``accel: z``)."""
    groups = magnitude_groups(plot) if plot.kind == "time" else []
    if len(groups) < 2:
        return [plot]
    out = []
    for group in groups:
        series = []
        for s in plot.series:
            cols = [j for j, n in enumerate(s.names) if n in group.get(s.entity, ())]
            if cols:
                values = s.values.reshape(len(s.x), -1)[:, cols]
                names, colors = [s.names[j] for j in cols], [s.colors[j] for j in cols]
                series.append(Series(s.entity, names, colors, s.x, values, s.style, s.extra))
        lines = [n for s in series for n in s.names]
        title = f"{plot.title}: " + ", ".join(dict.fromkeys(short_name(n) for n in lines))
        out.append(dataclasses.replace(plot, title=title, series=series))
    return out


def short_name(name: str) -> str:
    """What tells a line apart in a split plot's title: ``accel z raw`` -> ``z``."""
    words = name.split()
    return words[1] if len(words) > 2 else name


class Figures:
    """The plots of a run, in the order they were declared (see the module docstring)."""

    def __init__(self, keep_points: int = 2000) -> None:
        self.keep_points = keep_points
        self.plots: dict[tuple[str, str], Plot] = {}
        self.stages: list[str] = []

    def stage(self, name: str) -> None:
        """Register a stage (its tab) even if it declares nothing."""
        if name not in self.stages:
            self.stages.append(name)

    def plot(
        self,
        stage: str,
        key: str,
        kind: PlotKind,
        *,
        title: str | None,
        unit: str,
        x_label: str = "time",
        x_unit: str = "",
        log_x: bool = False,
        log_y: bool = False,
    ) -> Plot:
        """The plot ``key`` of ``stage`` (made on first use). A plot holds one unit and one
        kind: a series of another unit (raw counts beside m/s^2) goes to a plot of its own beside
        it, ``<key> [<unit>]``, with the same title."""
        self.stage(stage)
        plot = self.plots.get((stage, key))
        if plot is not None and (plot.unit != unit or plot.kind != kind):
            return self.plot(
                stage,
                f"{key} [{unit or kind}]",
                kind,
                title=plot.title,
                unit=unit,
                x_label=x_label,
                x_unit=x_unit,
                log_x=log_x,
                log_y=log_y,
            )
        if plot is None:
            plot = Plot(
                stage=stage,
                key=key,
                kind=kind,
                title=title or key.replace("_", " ").replace("/", " "),
                unit=unit,
                x_label=x_label,
                x_unit=x_unit,
                log_x=log_x,
                log_y=log_y,
            )
            self.plots[(stage, key)] = plot
        return plot

    def share_time_origin(self, within_ns: int = 86_400 * 10**9) -> int | None:
        """Give every ``time`` plot the run's first sample as its time origin, so that every
        plot counts time from the same instant (the block means of a stage start half a block
        after its raw samples: four origins in one report, before). A plot whose data starts
        more than ``within_ns`` (a day) later, another session, keeps its own."""
        firsts = {
            id(p): min(int(s.x[0]) for s in p.series if len(s.x))
            for p in self.plots.values()
            if p.kind == "time" and any(len(s.x) for s in p.series)
        }
        if not firsts:
            return None
        origin = min(firsts.values())
        for p in self.plots.values():
            if id(p) in firsts and firsts[id(p)] - origin <= within_ns:
                p.origin = origin
        return origin

    def of_stage(self, stage: str) -> list[Plot]:
        return [p for (s, _), p in self.plots.items() if s == stage]
