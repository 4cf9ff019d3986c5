"""The fleet view of ``imupipe survey``: ``DIR/fleet.json``, ``DIR/report.html`` and the terminal
summary, from the survey dataset (the rules are :mod:`imupipe.stages.survey.fleet`'s).

With a calibration (``cal_*`` columns filled), the figures judged are those after the calibration
(what is left is its error); the raw ones remain in the dataset. ``report.html`` holds the fleet
table (sorted by how far each device has moved, in units of the fleet's ordinary log-to-log
change) and, per device, its gyro bias and ``|a| - g`` against calendar time (one point per log,
with its standard error as a band) and its gyro bias against temperature (one point per still
period: the in-field thermal curve), drawn by :mod:`imupipe.pipeline.report.svg_plot`.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.report.figures import Plot, Series, colors_for
from imupipe.pipeline.report.svg_plot import svg
from imupipe.stages.survey.fleet import FIGURES, DeviceHistory, device_history, fleet_flags


def _col(table: pa.Table, name: str) -> np.ndarray:
    return table.column(name).to_numpy(zero_copy_only=False)


def _prefix(table: pa.Table) -> str:
    """``cal_`` when the dataset holds figures after a calibration, else ``""``."""
    if "cal_gyro_bias_x" in table.column_names:
        values = table.column("cal_gyro_bias_x").to_numpy(zero_copy_only=False).astype(np.float64)
        if np.isfinite(values).any():
            return "cal_"
    return ""


def histories(table: pa.Table) -> list[DeviceHistory]:
    """Each device's per-log history (see :func:`device_history`)."""
    p = _prefix(table)
    devices = _col(table, "device_id").astype(str)
    start = _col(table, "start_ns").astype(np.int64)
    t0 = int(start.min()) if len(start) else 0
    log = _col(table, "log").astype(str)
    temp = _col(table, "temperature").astype(np.float64)
    values = {f: _col(table, p + f).astype(np.float64) for f in FIGURES}
    se = {
        f: _col(
            table,
            p + f.replace("gyro_bias_", "gyro_bias_se_")
            if f.startswith("gyro")
            else p + "accel_norm_error_se",
        ).astype(np.float64)
        for f in FIGURES
    }
    level = _col(table, p + "level").astype(bool)
    se["accel_norm_error"] = np.where(level, se["accel_norm_error"], np.nan)
    noise = {
        s: np.mean([_col(table, f"{p}{s}_noise_{a}").astype(np.float64) for a in "xyz"], axis=0)
        for s in ("gyro", "accel")
    }
    out = []
    for dev in sorted(set(devices)):
        rows = devices == dev
        out.append(
            device_history(
                dev,
                log[rows],
                start[rows],
                temp[rows],
                {f: v[rows] for f, v in values.items()},
                {f: v[rows] for f, v in se.items()},
                {s: v[rows] for s, v in noise.items()},
                t0,
            )
        )
    return out


def fleet_view(table: pa.Table, k: float) -> dict[str, Any]:
    """The fleet view as a JSON-ready dict: ``k``, the fleet's scales, per device its per-log
    figures, thermal slopes, drift, moved and flags, and the devices to recalibrate."""
    hs = histories(table)
    fleet = fleet_flags(hs, k)
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
                "t_ref": h.t_ref,
                "drift_per_day": h.drift,
                "moved": h.moved,
                "moved_max": moved,
                "flags": h.flags,
            }
        )
    devices.sort(key=lambda d: -d["moved_max"])
    recal = [
        {"device_id": d["device_id"], "why": list(dict.fromkeys(f["why"] for f in d["flags"]))}
        for d in devices
        if d["flags"]
    ]
    return {
        **fleet,
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
    if not recal:
        return [f"imupipe survey: {n} devices, none flagged (k = {fleet['k']:g} robust sigmas)"]
    lines = [
        f"imupipe survey: recalibrate {len(recal)} of {n} devices (k = {fleet['k']:g} robust sigmas):"
    ]
    for r in recal:
        why = r["why"]
        more = f" (+{len(why) - 1} more in report.html)" if len(why) > 1 else ""
        lines.append(f"  {r['device_id']}: {why[0]}{more}")
    return lines


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
    rows = _col(table, "device_id").astype(str) == d["device_id"]
    pre = _prefix(table)
    temp = _col(table, "temperature").astype(np.float64)[rows]
    if np.isfinite(temp).any():
        r = Plot(
            "survey",
            d["device_id"] + "/thermal",
            "xy",
            f"{d['device_id']}: gyro bias against temperature (still periods)",
            "rad/s",
            x_label="temperature",
            x_unit="degC",
        )
        for i, a in enumerate("xyz"):
            y = _col(table, f"{pre}gyro_bias_{a}").astype(np.float64)[rows]
            r.series.append(
                Series(f"thermal/{a}", [gyro_names[i]], [colors[i]], temp, y[:, None], "points")
            )
        plots.append(svg(r))
    return [s for s in plots if s]


def write_report(
    path: Path, table: pa.Table, fleet: dict[str, Any], compass: dict[str, Any] | None = None
) -> None:
    """``report.html``: the fleet table, the devices to recalibrate, a section per device, and
    the compasses' section (:func:`imupipe.pipeline.survey.compass.report_section`)."""
    from imupipe.pipeline.survey.compass import report_section

    esc = html.escape
    k = fleet["k"]
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
            + "".join(_device_plots(d, table))
            + "</section>"
        )
    after = "after the calibration" if fleet["after_calibration"] else "raw (no calibration given)"
    text = (
        "<!doctype html><html><head><meta charset='utf-8'><title>imupipe survey</title>"
        "<style>body{font-family:system-ui,sans-serif;max-width:980px;margin:auto}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}"
        "svg{max-width:640px}</style></head><body>"
        f"<h1>imupipe survey: {len(fleet['devices'])} devices</h1>"
        f"<p>Figures {after}. Flags: k = {k:g} robust sigmas (1.4826 MAD).</p>"
        f"<h2>Recalibrate</h2><ul>{recal}</ul>"
        f"<h2>Fleet</h2><table><tr>{head}</tr>{''.join(rows)}</table>"
        + "".join(sections)
        + report_section(compass)
        + "</body></html>\n"
    )
    Path(path).write_text(text, encoding="utf-8")


def write_recording(path: Path, table: pa.Table) -> None:
    """``survey.rrd``: a Rerun recording with, per device, its still periods' gyro bias,
    ``|a| - g``, noise densities and temperature on the calendar timeline (one point per
    period; the figures after the calibration when the dataset has them)."""
    from imupipe.pipeline.report.recording import Recorder

    pre = _prefix(table)
    devices = _col(table, "device_id").astype(str)
    start = _col(table, "start_ns").astype(np.int64)
    recorder = Recorder(Path(path), application_id="imupipe survey")
    for dev in sorted(set(devices)):
        rows = np.flatnonzero(devices == dev)
        rows = rows[np.argsort(start[rows], kind="stable")]
        t = start[rows]
        base = "/survey/" + "".join(c if c.isalnum() else "_" for c in dev).strip("_")

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
            values = np.column_stack([_col(table, c).astype(np.float64)[rows] for c in columns])
            recorder.series(
                f"{base}/{entity}", t, values, names, unit=unit, plot=f"{dev} {title}",
                title=f"{dev}: {title}", points=True,
            )  # fmt: skip
    recorder.close()
