"""The fleet view of ``imupipe survey``: ``DIR/fleet.json``, ``DIR/report.html`` and the terminal
summary, from the survey dataset (the rules are :mod:`imupipe.stages.survey.fleet`'s).

With a calibration (``cal_*`` columns filled), the figures judged are those after the calibration
(what is left is its error); the raw ones remain in the dataset. ``report.html`` holds the fleet
table (sorted by how far each device has moved, in units of the fleet's ordinary log-to-log
change) and, per device, its gyro bias and ``|a| - g`` against calendar time (one point per log,
with its standard error as a band) and its gyro bias against temperature (one point per still
period: the in-field thermal curve), drawn by :mod:`imupipe.pipeline.report.svg_plot`.

With chamber calibrations (:mod:`imupipe.pipeline.survey.chamber`), each device's in-field curve
is compared with its chamber curve (:mod:`imupipe.stages.survey.chamber`, on the raw figures):
``fleet.json`` holds the comparison per device, the fleet table three more columns, the device's
section a table and a plot of its gyro axis furthest from the chamber curve against temperature,
the recording the raw gyro bias against temperature with the chamber curve, and the summary a
line on how many devices were compared and flown beyond their chamber's range.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.report.figures import Plot, Series, colors_for
from imupipe.pipeline.report.svg_plot import svg
from imupipe.stages.survey.fleet import FIGURES, DeviceHistory, device_history, fleet_flags
from imupipe.stages.survey.stats import StillOptions

if TYPE_CHECKING:
    from imupipe.pipeline.survey.chamber import Chambers


CURVE_POINTS = 60
"""Points of the chamber's gyro curve over the temperature range flown (fleet.json, the plot)."""


_CACHE: dict[str, Any] = {"table": None, "columns": {}, "rows": None}
"""The columns of the last table read (the fleet view reads the same columns for every device):
its numpy arrays, shared (never written to), and each device's row indices."""


def _cached(table: pa.Table) -> dict[str, Any]:
    if _CACHE["table"] is not table:
        _CACHE.update(table=table, columns={}, rows=None)
    return _CACHE


def _col(table: pa.Table, name: str, dtype: Any = None) -> np.ndarray:
    """Column ``name`` as a numpy array (cast to ``dtype``), read once per table."""
    columns = _cached(table)["columns"]
    if (name, dtype) not in columns:
        values = table.column(name).to_numpy(zero_copy_only=False)
        columns[(name, dtype)] = values if dtype is None else values.astype(dtype)
    return columns[(name, dtype)]


def _rows(table: pa.Table, device_id: str) -> np.ndarray:
    """The row indices of one device, in table order."""
    cache = _cached(table)
    if cache["rows"] is None:
        names, index = np.unique(_col(table, "device_id", str), return_inverse=True)
        order = np.argsort(index, kind="stable")
        bounds = np.searchsorted(index[order], np.arange(len(names) + 1))
        cache["rows"] = {str(n): order[bounds[i] : bounds[i + 1]] for i, n in enumerate(names)}
    return cache["rows"].get(device_id, np.zeros(0, np.int64))


def _prefix(table: pa.Table) -> str:
    """``cal_`` when the dataset holds figures after a calibration, else ``""``."""
    if "cal_gyro_bias_x" in table.column_names:
        values = table.column("cal_gyro_bias_x").to_numpy(zero_copy_only=False).astype(np.float64)
        if np.isfinite(values).any():
            return "cal_"
    return ""


def histories(table: pa.Table) -> list[DeviceHistory]:
    """Each device's per-log history (see :func:`device_history`); the devices with candidates
    but no still period go to the cache's ``unstill`` (device -> its logs)."""
    _cached(table)["unstill"] = {}
    p = _prefix(table)
    devices = _col(table, "device_id", str)
    start = _col(table, "start_ns", np.int64)
    t0 = int(start.min()) if len(start) else 0
    log = _col(table, "log", str)
    temp = _col(table, "temperature", np.float64)
    values = {f: _col(table, p + f, np.float64) for f in FIGURES}
    se = {
        f: _col(
            table,
            p + f.replace("gyro_bias_", "gyro_bias_se_")
            if f.startswith("gyro")
            else p + "accel_norm_error_se",
        ).astype(np.float64)
        for f in FIGURES
    }
    level = _col(table, p + "level", bool)
    accel = np.column_stack([_col(table, f"{p}accel_mean_{a}", np.float64) for a in "xyz"])
    noise = {
        s: np.mean([_col(table, f"{p}{s}_noise_{a}", np.float64) for a in "xyz"], axis=0)
        for s in ("gyro", "accel")
    }
    at_tau = np.zeros(table.num_rows, bool)  # the densities measured at tau_s
    if {"samples", "duration_s"} <= set(table.column_names):
        with np.errstate(invalid="ignore", divide="ignore"):  # the sensor's rate, Hz
            rate = _col(table, "samples", np.float64) / _col(table, "duration_s", np.float64)
        at_tau = rate * StillOptions().tau_s >= 1.0
    out = []
    for dev in sorted(set(devices)):
        rows = _rows(table, dev)
        h = device_history(
            dev,
            log[rows],
            start[rows],
            temp[rows],
            {f: v[rows] for f, v in values.items()},
            {f: v[rows] for f, v in se.items()},
            {s: v[rows] for s, v in noise.items()},
            t0,
            accel[rows],
            level[rows],
            at_tau[rows],
        )
        if h is None:  # candidates, none of them still
            _cached(table)["unstill"][dev] = sorted(set(log[rows]))
            continue
        out.append(h)
    return out


def chamber_view(
    table: pa.Table, h: DeviceHistory, chambers: Chambers, t0_ns: int, scales: dict[str, float]
) -> dict[str, Any] | None:
    """One device's in-field thermal curves against its chamber calibration
    (:mod:`imupipe.stages.survey.chamber`): ``source``, ``range`` (degC), the still periods
    ``outside`` it and their ``outside_span``, ``t_ns`` (the chamber's date), ``m`` (log
    intervals since it) and per figure the :func:`compare` result; None without a chamber curve."""
    from imupipe.pipeline.survey.chamber import device_model
    from imupipe.stages.survey import chamber as ch

    rows = _rows(table, h.device_id)
    vehicle = str(_col(table, "vehicle")[rows][0])
    topic = str(_col(table, "topic")[rows][0])
    model = device_model(chambers, vehicle, topic)
    if model is None:
        return None
    rejected = [r["start_ns"] for r in h.rejected]  # candidates that are not still periods
    rows = rows[~np.isin(_col(table, "start_ns", np.int64)[rows], rejected)]
    temp = _col(table, "temperature", np.float64)[rows]
    pred = {}
    for figure in ch.CHAMBER_FIGURES:  # the dataset's chamber columns (chamber_columns)
        values = _col(table, "chamber_" + figure, np.float64)[rows]
        if np.isfinite(values).any():
            pred[figure] = values
    index = {name: i for i, name in enumerate(h.logs)}
    names, inverse = np.unique(_col(table, "log", str)[rows], return_inverse=True)
    log_index = np.array([index[str(x)] for x in names])[inverse]
    figures = {}
    for figure, p in pred.items():
        se_name = (
            figure.replace("gyro_bias_", "gyro_bias_se_")
            if figure.startswith("gyro")
            else "accel_norm_error_se"
        )
        measured = _col(table, figure, np.float64)[rows]
        se = _col(table, se_name, np.float64)[rows]
        step = float(np.nan_to_num(scales.get(figure, 0.0)))
        figures[figure] = ch.compare(log_index, temp, measured, se, p, step)
    sensor = "gyro" if "gyro" in model.ranges else "accel"
    curve: dict[str, list[float]] = {}
    finite = temp[np.isfinite(temp)]
    if "gyro" in model.steps and len(finite):
        grid = np.linspace(finite.min(), finite.max(), CURVE_POINTS)
        curve = {"temperature": grid.tolist()}
        curve.update({f: v.tolist() for f, v in ch.predicted(model, grid).items()})
    return {
        "source": model.source,
        **ch.outside(temp, model.ranges[sensor]),
        "ranges": {s: list(r) for s, r in model.ranges.items()},
        "t_ns": model.t_ns,
        "m": ch.steps_since(model.t_ns, h.day, t0_ns),
        "figures": figures,
        "curve": curve,
    }


def fleet_view(table: pa.Table, k: float, chambers: Chambers | None = None) -> dict[str, Any]:
    """The fleet view as a JSON-ready dict: ``k``, the fleet's scales, per device its per-log
    figures, thermal slopes, drift, moved and flags, its comparison with its chamber calibration
    (``chamber``, with ``chambers``; see :func:`chamber_view`), and the devices to
    recalibrate."""
    if chambers and "chamber_gyro_bias_x" not in table.column_names:
        from imupipe.pipeline.survey.chamber import chamber_columns

        table = chamber_columns(table, chambers)
    hs = histories(table)
    fleet = fleet_flags(hs, k)
    start = _col(table, "start_ns", np.int64)
    t0 = int(start.min()) if len(start) else 0
    devices = []
    for h in hs:
        moved = max((abs(v) for v in h.moved.values()), default=0.0)
        devices.append(
            {
                "device_id": h.device_id,
                "logs": h.logs,
                "periods": h.periods,
                "day": h.day.tolist(),
                "temperature": h.temperature.tolist(),
                "figures": {f: v.tolist() for f, v in h.figures.items()},
                "se": {f: v.tolist() for f, v in h.se.items()},
                "noise": {s: v.tolist() for s, v in h.noise.items()},
                "thermal": {f: list(v) for f, v in h.thermal.items()},
                "figure_temperature": {f: v.temperature.tolist() for f, v in h.fits.items()},
                "t_ref": h.t_ref,
                "drift_per_day": h.drift,
                "moved": h.moved,
                "moved_max": moved,
                "flags": h.flags,
                "drift_detectable_per_week": {f: 7 * v for f, v in h.power.items()},
                "noise_floor": h.floors,
                "not_still": h.rejected,
                "logs_without_still_period": h.no_still,
                "chamber": chamber_view(table, h, chambers, t0, fleet["scales"])
                if chambers
                else None,
            }
        )
    if chambers:
        from imupipe.stages.survey.chamber import chamber_flags

        fleet["chamber_widen"] = chamber_flags(devices, fleet["scales"], k)
    devices.sort(key=lambda d: -d["moved_max"])
    recal = [
        {"device_id": d["device_id"], "why": list(dict.fromkeys(f["why"] for f in d["flags"]))}
        for d in devices
        if d["flags"]
    ]
    unstill = dict(_cached(table).get("unstill", {}))
    return {
        **fleet,
        "devices_without_still_period": unstill,
        "after_calibration": _prefix(table) == "cal_",
        "devices": devices,
        "recalibrate": recal,
    }


def summary_lines(fleet: dict[str, Any]) -> list[str]:
    """The terminal summary: the devices to recalibrate and why (the first reason found)."""
    if not fleet:
        return []
    recal = fleet["recalibrate"]
    n = len(fleet["devices"])
    quiet = _not_still_lines(fleet)
    if n == 0:
        return ["imupipe survey: no IMU has a still period in these logs", *quiet]
    if not recal:
        return [
            f"imupipe survey: {n} devices, none flagged (k = {fleet['k']:g} robust sigmas)",
            *_power_line(fleet),
            *quiet,
            *_chamber_line(fleet),
        ]
    lines = [
        f"imupipe survey: recalibrate {len(recal)} of {n} devices (k = {fleet['k']:g} robust sigmas):"
    ]
    for r in recal:
        why = r["why"]
        more = f" (+{len(why) - 1} more in report.html)" if len(why) > 1 else ""
        lines.append(f"  {r['device_id']}: {why[0]}{more}")
    return lines + _power_line(fleet) + quiet + _chamber_line(fleet)


def _not_still_lines(fleet: dict[str, Any]) -> list[str]:
    """The logs whose quiet stretches were judged not still (vibration, not stillness): one
    line per device."""
    lines = []
    for d in fleet["devices"]:
        logs = d.get("logs_without_still_period") or []
        if logs:
            worst = max(
                (r.get("gyro_ratio", float("nan")) for r in d["not_still"]), default=float("nan")
            )
            lines.append(
                f"  {d['device_id']}: no still period in {', '.join(logs)} (quiet stretches up to "
                f"x{worst:.3g} its gyro noise floor: vibration, not stillness)"
            )
    for dev, logs in (fleet.get("devices_without_still_period") or {}).items():
        lines.append(
            f"  {dev}: no still period in {', '.join(logs)}: its quiet stretches are noisier "
            "than a still MEMS IMU (vibration, not stillness)"
        )
    return lines


def still_column(table: pa.Table, fleet: dict[str, Any]) -> pa.Table:
    """The dataset with ``still``: False for a candidate period the fleet view judged not still
    (:func:`~imupipe.stages.survey.fleet.still_judged`), True for the others."""
    device = _col(table, "device_id", str)
    start = _col(table, "start_ns", np.int64)
    out = np.ones(table.num_rows, bool)
    out[np.isin(device, list(fleet.get("devices_without_still_period") or {}))] = False
    for d in fleet.get("devices") or []:
        rejected = [r["start_ns"] for r in d.get("not_still") or []]
        if rejected:
            out[(device == d["device_id"]) & np.isin(start, rejected)] = False
    if "still" in table.column_names:
        table = table.drop_columns(["still"])
    return table.append_column("still", pa.array(out, pa.bool_()))


def _power_line(fleet: dict[str, Any]) -> list[str]:
    """The drift test's power: the median over devices of the smallest gyro drift per week it
    finds with 90 % probability."""
    values = [
        v
        for d in fleet["devices"]
        for f, v in (d.get("drift_detectable_per_week") or {}).items()
        if f.startswith("gyro") and np.isfinite(v)
    ]
    if not values:
        return []
    return [
        f"  drift test: a gyro bias drift of {np.median(values):.2g} rad/s per week is found with "
        f"90 % probability (median over devices and axes; per device in fleet.json)"
    ]


def _chamber_line(fleet: dict[str, Any]) -> list[str]:
    """One line on the chamber comparison (none without a chamber calibration)."""
    compared = [d for d in fleet["devices"] if d.get("chamber")]
    if not compared:
        return []
    beyond = [d for d in compared if d["chamber"]["outside"]]
    line = (
        f"imupipe survey: {len(compared)} of {len(fleet['devices'])} devices compared with their "
        "chamber calibration"
    )
    if beyond:
        line += (
            f"; {len(beyond)} flown outside its calibrated range, where its curve is "
            "extrapolated (report.html names them)"
        )
    judged = [
        c for d in compared for c in d["chamber"]["figures"].values() if np.isfinite(c["offset"])
    ]
    if judged and not any(np.isfinite(c.get("limit_offset", np.nan)) for c in judged):
        line += "; offsets not judged (too few logs to tell the bias random walk since the chamber)"
    return [line]


def _chamber_plot(d: dict[str, Any], table: pa.Table) -> str | None:
    """The raw gyro bias of every still period against temperature, on the axis that departs most
    from its chamber curve (against its limits), with the chamber curve (dashed grey beyond the
    chamber's calibrated range: extrapolated) and the in-field curve fitted to the periods (the
    chamber curve moved by the offset and the slope difference, dashed)."""
    c = d["chamber"]
    curve = c.get("curve") or {}
    axis = _worst_axis(c["figures"])
    if "gyro_bias_x" not in curve or axis is None:
        return None
    figure = f"gyro_bias_{axis}"
    fit = c["figures"][figure]
    rows = _rows(table, d["device_id"])
    temp = _col(table, "temperature", np.float64)[rows]
    grid = np.asarray(curve["temperature"])
    lo, hi = c["ranges"]["gyro"]
    inside = (grid >= lo) & (grid <= hi)
    model = np.asarray(curve[figure])
    color = colors_for(["x", "y", "z"], None)["xyz".index(axis)]
    p = Plot(
        "survey",
        d["device_id"] + "/chamber",
        "xy",
        f"{d['device_id']}: gyro {axis} bias against temperature and its chamber curve",
        "rad/s",
        x_label="temperature",
        x_unit="degC",
    )
    measured = _col(table, figure, np.float64)[rows]
    grey = (110, 110, 110)
    p.series.append(
        Series("chamber/periods", ["still periods"], [color], temp, measured[:, None], "points")
    )
    chamber = np.where(inside, model, np.nan)
    p.series.append(
        Series(
            "chamber/curve",
            [f"chamber curve ({lo:.0f}..{hi:.0f} degC)"],
            [grey],
            grid,
            chamber[:, None],
            "line",
        )
    )
    if not inside.all():  # the extrapolated ends, joined to the line
        near = np.convolve((~inside).astype(int), [1, 1, 1], "same") > 0
        p.series.append(
            Series(
                "chamber/extrapolated",
                ["chamber curve, extrapolated"],
                [grey],
                grid,
                np.where(near, model, np.nan)[:, None],
                "guide",
            )
        )
    infield = model + fit["offset"] + fit["slope"] * (grid - fit["t_centre"])
    p.series.append(
        Series(
            "chamber/infield", ["in-field curve (fit)"], [color], grid, infield[:, None], "guide"
        )
    )
    return svg(p)


def _device_plots(d: dict[str, Any], table: pa.Table) -> list[str]:
    day = np.asarray(d["day"])
    plots = []
    gyro_names = [f"gyro bias {a}" for a in "xyz"]
    p = Plot(
        "survey",
        d["device_id"] + "/gyro",
        "xy",
        f"{d['device_id']}: gyro bias per log",
        "rad/s",
        x_label="days since the fleet's first log",
        x_unit="day",
    )
    colors = colors_for(gyro_names, None)
    for i, a in enumerate("xyz"):
        f = np.asarray(d["figures"][f"gyro_bias_{a}"])
        se = np.asarray(d["se"][f"gyro_bias_{a}"])
        p.series.append(Series(f"gyro/{a}", [gyro_names[i]], [colors[i]], day, f[:, None], "line"))
        p.series.append(
            Series(
                f"gyro/{a}/band",
                [gyro_names[i] + " +-2 se"],
                [colors[i]],
                day,
                np.column_stack([f - 2 * se, f + 2 * se]),
                "band",
            )
        )
    plots.append(svg(p))
    f = np.asarray(d["figures"]["accel_norm_error"])
    q = Plot(
        "survey",
        d["device_id"] + "/accel",
        "xy",
        f"{d['device_id']}: |a| - g per log",
        "m/s^2",
        x_label="days since the fleet's first log",
        x_unit="day",
    )
    q.series.append(Series("accel", ["|a| - g"], colors_for(["a"], None), day, f[:, None], "line"))
    plots.append(svg(q))
    rows = _rows(table, d["device_id"])
    pre = _prefix(table)
    temp = _col(table, "temperature", np.float64)[rows]
    if np.isfinite(temp).any():
        r = Plot(
            "survey",
            d["device_id"] + "/thermal",
            "xy",
            f"{d['device_id']}: gyro bias against temperature (still periods"
            + (", after the calibration)" if pre else ")"),
            "rad/s",
            x_label="temperature",
            x_unit="degC",
        )
        for i, a in enumerate("xyz"):
            y = _col(table, f"{pre}gyro_bias_{a}", np.float64)[rows]
            r.series.append(
                Series(f"thermal/{a}", [gyro_names[i]], [colors[i]], temp, y[:, None], "points")
            )
        plots.append(svg(r))
    if d.get("chamber"):
        plots.append(_chamber_plot(d, table))
    return [s for s in plots if s]


def _worst_axis(c: dict[str, Any], keys: tuple[str, ...] = ("offset", "slope")) -> str | None:
    """The gyro axis whose ``keys`` (``offset``, ``slope``) are the largest against their limits."""
    ratios = {}
    for a in "xyz":
        f = c.get(f"gyro_bias_{a}", {})
        r = [abs(f[k]) / f[f"limit_{k}"] for k in keys if f.get(f"limit_{k}", 0) > 0]
        if r:
            ratios[a] = max(r)
    return max(ratios, key=lambda a: ratios[a]) if ratios else None


CHAMBER_COLUMNS = (
    "vs chamber: offset (rad/s)",
    "vs chamber: slope (rad/s/K)",
    "periods beyond the chamber's range",
)
"""The fleet table's columns on the chamber calibration (only when a device has one)."""


def _chamber_cells(d: dict[str, Any]) -> tuple[str, str, str]:
    """The fleet table's chamber cells: the gyro axis furthest off in offset and in slope (value
    +- standard error), and the still periods beyond the chamber's calibrated range."""
    ch = d.get("chamber")
    if not ch:
        return "-", "-", "-"
    c = ch["figures"]
    cells = []
    for key, se in (("offset", "offset_se"), ("slope", "slope_se")):
        a = _worst_axis(c, (key,))
        cells.append(
            "-"
            if a is None
            else f"{a} {c[f'gyro_bias_{a}'][key]:+.1e} &plusmn; {c[f'gyro_bias_{a}'][se]:.0e}"
        )
    span = ch["outside_span"]
    cells.append(f"{ch['outside']} ({span[0]:.0f}..{span[1]:.0f} degC)" if span else "0")
    return cells[0], cells[1], cells[2]


def _chamber_text(d: dict[str, Any]) -> str:
    """The device section's line on its chamber calibration."""
    ch = d.get("chamber")
    if not ch:
        return ""
    esc = html.escape
    lo, hi = ch["range"]
    text = f"Chamber calibration {esc(ch['source'])}, calibrated over {lo:.0f}..{hi:.0f} degC"
    if ch["outside_span"]:
        a, b = ch["outside_span"]
        text += (
            f"; {ch['outside']} still period{'s' if ch['outside'] != 1 else ''} at "
            f"{a:.1f}..{b:.1f} degC {'lie' if ch['outside'] != 1 else 'lies'} beyond it: its curve "
            "is extrapolated there"
        )
    rows = []
    for figure, c in ch["figures"].items():
        if not np.isfinite(c["offset"]):
            continue
        unit = "rad/s" if figure.startswith("gyro") else "m/s^2"
        rows.append(
            f"<tr><td>{esc(figure)}</td><td>{c['offset']:+.2e} &plusmn; {c['offset_se']:.1e} "
            f"{unit} at {c['t_centre']:.1f} degC</td><td>{c.get('limit_offset', np.nan):.1e}</td>"
            f"<td>{c['slope']:+.2e} &plusmn; {c['slope_se']:.1e} {unit}/K</td>"
            f"<td>{c.get('limit_slope', np.nan):.1e}</td>"
            f"<td>{c['worst']:+.2e} at {c['worst_t']:.1f} degC</td></tr>"
        )
    head = "".join(
        f"<th>{h}</th>"
        for h in (
            "figure",
            "offset (in-field - chamber)",
            "limit",
            "slope difference",
            "limit",
            "largest departure in the range flown",
        )
    )
    return f"<p>{text}.</p><table><tr>{head}</tr>{''.join(rows)}</table>"


def write_report(
    path: Path, table: pa.Table, fleet: dict[str, Any], compass: dict[str, Any] | None = None
) -> None:
    """``report.html``: the fleet table, the devices to recalibrate, a section per device, and
    the compasses' section (:func:`imupipe.pipeline.survey.compass.report_section`)."""
    from imupipe.pipeline.survey.compass import report_section

    esc = html.escape
    k = fleet["k"]
    chambers = any(d.get("chamber") for d in fleet["devices"])
    head = "".join(
        f"<th>{esc(h)}</th>"
        for h in (
            "device",
            "logs",
            "still periods",
            "moved (fleet sigmas)",
            "gyro drift (rad/s/day)",
            "thermal slope (rad/s/K)",
            "gyro noise (rad/s/sqrt(Hz))",
            *(CHAMBER_COLUMNS if chambers else ()),
            "flags",
        )
    )
    rows = []
    for d in fleet["devices"]:
        drift = max(
            (abs(d["drift_per_day"][f"gyro_bias_{a}"]) for a in "xyz"), default=float("nan")
        )
        thermal = [d["thermal"][f"gyro_bias_{a}"][0] for a in "xyz"]
        noise = d["noise"]["gyro"][-1] if d["noise"]["gyro"] else float("nan")
        rows.append(
            "<tr>"
            + "".join(
                f"<td>{c}</td>"
                for c in (
                    f"<a href='#{esc(d['device_id'])}'>{esc(d['device_id'])}</a>",
                    len(d["logs"]),
                    d["periods"],
                    f"{d['moved_max']:.1f}",
                    f"{drift:.2e}",
                    " ".join(f"{t:.1e}" for t in thermal),
                    f"{noise:.2e}",
                    *(_chamber_cells(d) if chambers else ()),
                    len(d["flags"]),
                )
            )
            + "</tr>"
        )
    recal = (
        "".join(
            f"<li><b>{esc(r['device_id'])}</b>: {esc('; '.join(r['why']))}</li>"
            for r in fleet["recalibrate"]
        )
        or "<li>none</li>"
    )
    sections = []
    for d in fleet["devices"]:
        flags = "".join(f"<li>{esc(f['why'])}</li>" for f in d["flags"]) or "<li>no flag</li>"
        sections.append(
            f"<section id='{esc(d['device_id'])}'><h2>{esc(d['device_id'])}</h2><ul>{flags}</ul>"
            + _chamber_text(d)
            + "".join(_device_plots(d, table))
            + "</section>"
        )
    after = "after the calibration" if fleet["after_calibration"] else "raw (no calibration given)"
    n_compass = len((compass or {}).get("devices") or [])
    title = f"{len(fleet['devices'])} IMUs" + (f", {n_compass} compasses" if n_compass else "")
    if fleet["devices"]:
        imus = (
            f"<p>Figures {after}. Flags: k = {k:g} robust sigmas (1.4826 MAD).</p>"
            f"<h2>Recalibrate</h2><ul>{recal}</ul>"
            f"<h2>Fleet</h2><table><tr>{head}</tr>{''.join(rows)}</table>" + "".join(sections)
        )
    else:  # flight logs alone: they move, no still moment to measure an IMU in
        imus = "<p>No IMU has a still period in these logs: the IMU figures are empty.</p>"
    text = (
        "<!doctype html><html><head><meta charset='utf-8'><title>imupipe survey</title>"
        "<style>body{font-family:system-ui,sans-serif;max-width:980px;margin:auto}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}"
        "svg{max-width:640px}</style></head><body>"
        f"<h1>imupipe survey: {title}</h1>" + imus + report_section(compass) + "</body></html>\n"
    )
    Path(path).write_text(text, encoding="utf-8")


def _entity_part(device_id: str) -> str:
    """A device id as one part of an entity path (letters and digits; the rest ``_``)."""
    return "".join(c if c.isalnum() else "_" for c in device_id).strip("_")


def write_recording(
    path: Path,
    table: pa.Table | None,
    fleet: dict[str, Any] | None = None,
    compass: dict[str, Any] | None = None,
) -> None:
    """``survey.rrd``: a Rerun recording with, per device, its still periods' gyro bias,
    ``|a| - g``, noise densities and temperature on the calendar timeline (one point per
    period; the figures after the calibration when the dataset has them), with a chamber
    calibration its raw gyro bias against temperature with the chamber curve
    (``/survey/<device>/chamber/...``), and per compass of the compass fleet view
    (``compass.json``) its offsets and motor term per flight on the same timeline
    (``/survey/compass/<device>/offset/offset_x``..., ``.../motor/motor_x``...)."""
    from imupipe.pipeline.report.recording import Recorder

    recorder = Recorder(Path(path), application_id="imupipe survey", elapsed=False)  # calendar
    if table is not None:
        _record_imus(recorder, table, fleet)
    _record_compasses(recorder, compass)
    recorder.close()


def _record_compasses(recorder: Any, compass: dict[str, Any] | None) -> None:
    """Per compass, one view of its offsets (uT) and one of its motor term (uT/A, or uT at full
    throttle) on the calendar timeline, one point per fitted flight (in the sensor's axes, or
    as fitted on the field as logged: ``domain``)."""
    from imupipe.pipeline.survey.compass import UT

    si = {"uT": "T", "uT/A": "T/A"}  # the recorder takes SI and shows tesla as uT
    for d in (compass or {}).get("devices", []):
        t = np.asarray(d.get("start_ns", []), dtype=np.int64)
        if not len(t):
            continue
        dev, base = d["device_id"], "/survey/compass/" + _entity_part(d["device_id"])
        # short titles: a narrow view still shows the unit
        what = "offsets" + (", fitted as logged" if d["domain"] != "sensor" else "")
        shown = (
            ("offset", d["offset_ut"], "uT", what),
            ("motor", d["motor"], d["motor_unit"], f"motor, {d['motor_source']}"),
        )
        for key, values, unit, title in shown:
            v = np.asarray(values, dtype=np.float64).reshape(len(t), 3) / UT
            recorder.series(
                f"{base}/{key}", t, v, [f"{key} {a}" for a in "xyz"], unit=si[unit],
                plot=f"compass {dev} {key}", title=f"{dev} {title}", points=True,
            )  # fmt: skip


def _record_imus(recorder: Any, table: pa.Table, fleet: dict[str, Any] | None) -> None:
    pre = _prefix(table)
    devices = _col(table, "device_id", str)
    start = _col(table, "start_ns", np.int64)
    by_id = {d["device_id"]: d.get("chamber") for d in (fleet or {}).get("devices", [])}
    for dev in sorted(set(devices)):
        rows = _rows(table, dev)
        rows = rows[np.argsort(start[rows], kind="stable")]
        t = start[rows]
        base = "/survey/" + _entity_part(dev)

        axes = list("xyz")
        shown = (
            ("gyro_bias", [f"gyro bias {a}" for a in axes], [f"{pre}gyro_bias_{a}" for a in axes],
             "rad/s", "gyro bias"),
            ("accel_norm_error", ["|a| - g"], [f"{pre}accel_norm_error"], "m/s^2", "|a| - g"),
            ("gyro_noise", [f"gyro noise {a}" for a in axes], [f"{pre}gyro_noise_{a}" for a in axes],
             "rad/s/sqrt(Hz)", "gyro noise density"),
            ("temperature", ["temperature"], ["temperature"], "degC", "temperature"),
        )  # fmt: skip
        for entity, names, columns, unit, title in shown:
            values = np.column_stack([_col(table, c, np.float64)[rows] for c in columns])
            recorder.series(
                f"{base}/{entity}", t, values, names, unit=unit, plot=f"{dev} {title}",
                title=f"{dev}: {title}", points=True,
            )  # fmt: skip
        chamber = by_id.get(dev)
        if chamber and chamber.get("curve", {}).get("gyro_bias_x") is not None:
            temp = _col(table, "temperature", np.float64)[rows]
            names = [f"gyro bias {a}" for a in axes]
            plot = base.rsplit("/", 1)[1] + "_chamber"  # an entity path: no blanks
            title = f"{dev}: gyro bias against temperature, still periods and chamber curve"
            raw = np.column_stack([_col(table, f"gyro_bias_{a}", np.float64)[rows] for a in axes])
            colors = colors_for(names, None)  # an axis's periods and curve in one colour
            recorder.curve(
                f"{base}/chamber/periods", temp, raw, [f"{a}, still periods" for a in axes],
                x_label="temperature", x_unit="degC", unit="rad/s", plot=plot, title=title,
                points=True, colors=colors,
            )  # fmt: skip
            curve = chamber["curve"]
            recorder.curve(
                f"{base}/chamber/curve", np.asarray(curve["temperature"]),
                np.column_stack([curve[f"gyro_bias_{a}"] for a in axes]),
                [f"{a}, chamber curve" for a in axes], x_label="temperature", x_unit="degC",
                unit="rad/s", plot=plot, title=title, colors=colors,
            )  # fmt: skip
