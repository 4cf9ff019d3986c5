"""``imupipe inspect LOG``: what a log holds and what imupipe would read from it.

For MCAP and ROS bags: every topic with its message type, message count, mean rate (from the log
times: ``(count - 1) / span``) and time span, without decoding payloads (an MCAP file with a
summary section answers from it, :mod:`imupipe.readers.mcap.summary`, without reading a chunk
or importing numpy; else from every message's log time); then the topic each
stream would be read from (the same choice ``imupipe run`` makes, so an ambiguous choice is shown
with its candidates) and the common-table columns that would be filled. For a PX4 ULog: every
topic instance (``sensor_gyro_1`` is instance 1) with its uORB message, instance and device id,
the streams a read would fill, whether PX4 had already calibrated them, and the log's ``CAL_*``
and ``TC_*`` parameters; for an ArduPilot DataFlash log the same: every message instance
(``IMU_1``, ``IMU2``), the streams, and its calibration parameters (``INS_*``, ``COMPASS_*``).
For CSV: the columns mapped with the default mapping, samples per
stream, rate and span.

For MCAP and ROS bags, every topic whose type is not a ``sensor_msgs`` sensor type is listed with
its fields (from the definition the log carries) and the ``[inputs.NAME.fields]`` keys that would
read it (:func:`imupipe.readers.mapped.suggest`); given a field mapping (``--config``), the
streams it fills. (Listing fields reads the definitions with the readers, numpy included.)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from imupipe.pipeline.errors import ImupipeError, ReadError
from imupipe.readers.dispatch import detect_format
from imupipe.readers.spec import InputSpec
from imupipe.readers.topics import (
    COLUMNS,
    PIECE_TYPES,
    STREAM_TYPES,
    TYPE_STREAMS,
    normalize_type,
    select_topics,
)

BASE_COLUMNS = ["t_ns", "log_time_ns", "frame_id"]
FIELDS_SHOWN = 16
"""Fields of a topic the text lists (``--json``: every field, up to 64)."""


def _span(t: Any) -> dict[str, Any]:
    """Count, first and last time, duration and mean rate of the times ``t`` (int64 ns)."""
    n = len(t)
    return _counted(n, int(t.min()) if n else None, int(t.max()) if n else None)


def _counted(n: int, lo: int | None, hi: int | None) -> dict[str, Any]:
    if n == 0 or lo is None or hi is None:
        return {"count": 0, "start_ns": None, "end_ns": None, "duration_s": 0.0, "rate_hz": None}
    duration = (hi - lo) * 1e-9
    return {
        "count": n,
        "start_ns": lo,
        "end_ns": hi,
        "duration_s": duration,
        "rate_hz": (n - 1) / duration if n > 1 and duration > 0 else None,
    }


def inspect(spec: InputSpec) -> dict[str, Any]:
    """A description of the log (see the module docstring) as a JSON-able dict."""
    path = Path(spec.path)
    fmt = detect_format(path)
    if fmt == "csv":
        from imupipe.readers.dispatch import read_input
        from imupipe.readers.table import (
            SENSOR_COLUMNS,
            STREAM_OF_SENSOR,
            counts,
            has_sensor,
            stream_mask,
        )

        try:
            table, warnings = read_input(spec)
        except ReadError as exc:  # not read with this mapping: say what the file holds
            return _csv_layout(spec, str(exc))
        streams = {}
        filled = ["t_ns"]
        present = counts(table)
        from imupipe.readers.arrays import to_numpy  # numpy and pyarrow only where read

        t_ns = to_numpy(table.column("t_ns"))
        for stream in ("imu", "mag", "temperature"):
            if stream in present:
                streams[stream] = {
                    "source": "csv columns",
                    **_span(t_ns[stream_mask(table, stream)]),
                }
                filled += [
                    c
                    for s, cols in SENSOR_COLUMNS.items()
                    if STREAM_OF_SENSOR[s] == stream and has_sensor(table, s)
                    for c in cols
                ]
        return {
            "path": str(path),
            "format": fmt,
            "topics": {},
            "streams": streams,
            "columns": filled,
            "warnings": warnings,
        }

    described = _from_summary(path) if fmt == "mcap" else None
    warnings: list[str] = []
    types, topics = described if described is not None else _from_messages(spec, warnings)
    out: dict[str, Any] = {"path": str(path), "format": fmt, "topics": topics, "streams": {}}
    if warnings:
        out["warnings"] = warnings
    if fmt in ("ulog", "dataflash"):
        return _ulog(spec, out)
    if any(normalize_type(t) not in TYPE_STREAMS for t in types.values()) or spec.fields:
        _fields(spec, out)
    if spec.fields is not None:
        return out
    try:
        chosen = select_topics(path, spec, types)
    except ImupipeError as exc:
        out["columns"] = []
        out["selection_error"] = str(exc)
        return out
    columns = list(BASE_COLUMNS)
    for stream, topic in chosen.items():
        out["streams"][stream] = {
            "topic": topic,
            "type": PIECE_TYPES[stream],
            "count": topics[topic]["count"],
        }
        columns += [name for name, _, _ in COLUMNS[stream]]
    out["columns"] = columns
    return out


def _fields(spec: InputSpec, out: dict[str, Any]) -> None:
    """The fields of every topic that is not a sensor_msgs type the topic keys read, with the
    ``[inputs.NAME.fields]`` keys that would read it; with a field mapping, the streams it
    fills (or why it cannot: ``selection_error``)."""
    from imupipe.readers.dispatch import log_sources
    from imupipe.readers.mapped import describe_topics, plan

    sources = log_sources(spec)
    out["fields"] = describe_topics(sources, set(STREAM_TYPES.values()))  # type: ignore[arg-type]
    if spec.fields is None:
        return
    defs = {}
    for src in sources:
        for topic, defn in src.definitions().items():  # type: ignore[attr-defined]
            defs.setdefault(topic, defn)
    try:
        plans = plan(spec, defs)
    except ImupipeError as exc:
        out["columns"] = []
        out["selection_error"] = str(exc)
        return
    columns = ["t_ns", "log_time_ns"]
    for topic, tp in plans.items():
        for sensor in tp.sensors:
            stream = {"gyro": "imu", "accel": "imu"}.get(sensor, sensor)
            entry = out["streams"].setdefault(
                stream, {"topic": topic, "type": tp.mtype.name, "count": 0, "sensors": {}}
            )
            entry["sensors"][sensor] = topic
            if topic != entry["topic"]:
                entry["topic"] += f", {topic}"
            entry["count"] += out["topics"].get(topic, {}).get("count", 0)
            columns += [f"{sensor}_{a}" for a in "xyz"] if sensor != "temperature" else [sensor]
    out["columns"] = columns


def _from_summary(path: Path) -> tuple[dict[str, str], dict[str, Any]] | None:
    """(topic -> type, topic -> entry) from an MCAP summary section, or None when it cannot
    tell (:func:`imupipe.readers.mcap.summary.topic_summary`): no payload read, no numpy."""
    from imupipe.readers.mcap.summary import topic_summary

    summary = topic_summary(path)
    if summary is None:
        return None
    types = {topic: s.type for topic, s in summary.items()}
    topics = {
        topic: {
            "type": normalize_type(s.type),
            **_counted(s.count, s.start_ns, s.end_ns),
        }
        for topic, s in sorted(summary.items())
    }
    return types, topics


def _from_messages(
    spec: InputSpec, warnings: list[str] | None = None
) -> tuple[dict[str, str], dict[str, Any]]:
    """(topic -> type, topic -> entry) from the log times of every message of the log; the
    sources' warnings (an unindexed bag read by scanning) are appended to ``warnings``."""
    if warnings is None:
        warnings = []
    import numpy as np

    from imupipe.readers.dispatch import log_sources

    types: dict[str, str] = {}
    times: dict[str, list[np.ndarray]] = {}
    untimed: dict[str, int] = {}
    for src in log_sources(spec):
        warnings += getattr(src, "warnings", ())
        src_types = src.topic_types()
        types.update(src_types)
        src_times = src.topic_times()
        for topic, t in src_times.items():
            times.setdefault(topic, []).append(t)
        if set(src_types) - set(src_times):  # counted only when some topic has no times
            for topic, n in (src.topic_counts() or {}).items():
                untimed[topic] = untimed.get(topic, 0) + n
    topics = {}
    for topic in sorted(types):
        if topic in times:
            span = _span(np.concatenate(times[topic]))
        else:  # a message without a time (an old DataFlash PARM): its count alone
            span = {**_counted(0, None, None), "count": untimed.get(topic, 0)}
        topics[topic] = {"type": normalize_type(types[topic]), **span}
    return types, topics


def _ulog(spec: InputSpec, out: dict[str, Any]) -> dict[str, Any]:
    """The ULog (and ArduPilot DataFlash) part of :func:`inspect`: instances, chosen streams,
    the autopilot's calibration."""
    from imupipe.readers.table import SENSOR_COLUMNS, STREAM_OF_SENSOR

    if out["format"] == "dataflash":
        from imupipe.readers.dataflash.reader import describe
    else:
        from imupipe.readers.ulog.reader import describe

    info = describe(spec)
    for key, inst in info["instances"].items():
        out["topics"][key].update(instance=inst["instance"], device_id=inst["device_id"])
    if info["selection_error"]:
        out["selection_error"] = info["selection_error"]
    columns = list(BASE_COLUMNS[:2])
    for stream, key in info["chosen"].items():
        out["streams"][stream] = {
            "topic": key,
            "type": STREAM_TYPES[stream],
            "count": info["samples"][stream],
            "instance": info["instances"][key]["instance"],
            "device_id": info["device_id"][stream],
        }
        if stream in info["calibrated"]:
            autopilot = info.get("parameters_of", "PX4").lower()
            out["streams"][stream][f"{autopilot}_calibrated"] = info["calibrated"][stream]
        columns += [
            c for s, cols in SENSOR_COLUMNS.items() if STREAM_OF_SENSOR[s] == stream for c in cols
        ]
    out["columns"] = columns
    out["warnings"] = info["warnings"]
    out["parameters"] = info["parameters"]
    out["parameters_of"] = info.get("parameters_of", "PX4")
    return out


def _fmt_time(ns: int | None) -> str:
    return "-" if ns is None else f"{ns * 1e-9:.3f}"


def _csv_layout(spec: InputSpec, why: str) -> dict[str, Any]:
    """A CSV the mapping cannot read: its layout (delimiter, header, columns, lines skipped, a
    rate line) and why, so that the user can write the mapping (``--config``, or the run config's
    ``[inputs.NAME.csv]``). A file that is not a CSV at all is still an error."""
    from imupipe.readers.csv.layout import sniff

    m = spec.csv
    layout = sniff(
        Path(spec.path),
        delimiter=m.delimiter,
        header=m.header,
        skip_rows=m.skip_rows,
        comment=m.comment,
    )
    columns = layout.names or [str(i) for i in range(layout.fields)]
    return {
        "path": str(spec.path),
        "format": "csv",
        "topics": {},
        "streams": {},
        "columns": [],
        "layout": {
            "delimiter": layout.delimiter,
            "header": layout.header,
            "file_columns": columns,
            "first_data_line": layout.first_line,
            "lines_skipped": layout.skipped,
            "rate_hz": layout.rate_hz,
        },
        "warnings": [
            f"not read with this mapping: {why.split(': ', 1)[-1].split('; set [inputs.')[0]}; "
            "map the columns in a "
            "[csv] table (inspect --config READ.toml, or the run config's [inputs.NAME.csv])"
        ],
    }


def render(info: dict[str, Any]) -> str:
    """The inspect result as text."""
    lines = [f"{info['path']}  ({info['format']})"]
    if info["topics"]:
        width = max(len(t) for t in info["topics"])
        tw = max(len(v["type"]) for v in info["topics"].values())
        lines.append(
            f"  {'topic':<{width}}  {'type':<{tw}}  {'count':>9}  {'rate Hz':>9}  {'start s':>16}  {'span s':>9}"
        )
        for topic, v in info["topics"].items():
            rate = "-" if v["rate_hz"] is None else f"{v['rate_hz']:.2f}"
            lines.append(
                f"  {topic:<{width}}  {v['type']:<{tw}}  {v['count']:>9}  {rate:>9}  "
                f"{_fmt_time(v['start_ns']):>16}  {v['duration_s']:>9.3f}"
            )
    for topic, v in info.get("fields", {}).items():
        lines.append(f"fields of {topic} ({v['type']}, {v['encoding']}):")
        if "error" in v:
            lines.append(f"  {v['error']}")
            continue
        shown = ", ".join(f"{p} {t}" for p, t in v["fields"][:FIELDS_SHOWN])
        more = len(v["fields"]) - FIELDS_SHOWN
        lines.append(f"  {shown}" + (f", ... ({more} more; --json lists all)" if more > 0 else ""))
        if v["mapping"]:
            keys = ", ".join(f"{k} = {json.dumps(p)}" for k, p in v["mapping"].items())
            lines.append(f"  read by [inputs.NAME.fields]: {keys}")
        else:
            lines.append("  no field looks like gyro, accel, mag or temperature")
    if "selection_error" in info:
        lines.append(f"streams: not chosen: {info['selection_error']}")
        if any(v.get("mapping") for v in info.get("fields", {}).values()):
            lines.append("  (the [inputs.NAME.fields] keys above read the topics they name)")
    for stream, v in info["streams"].items():
        source = v.get("topic", v.get("source"))
        extra = "" if "rate_hz" not in v or v["rate_hz"] is None else f", {v['rate_hz']:.2f} Hz"
        if v.get("device_id") is not None:
            extra += f", device id {v['device_id']}"
        for by in ("PX4", "ArduPilot"):
            if f"{by.lower()}_calibrated" in v:
                done = v[f"{by.lower()}_calibrated"]
                extra += f", already calibrated by {by}" if done else ", raw"
        lines.append(f"stream {stream}: {source} ({v['count']} samples{extra})")
    if info["columns"]:
        lines.append("columns filled: " + ", ".join(info["columns"]))
    if "layout" in info:
        lay = info["layout"]
        named = "named by the header" if lay["header"] else "no header: named by index"
        lines.append(
            f"csv: {len(lay['file_columns'])} columns ({named}), delimiter "
            f"{lay['delimiter']!r}, data from line {lay['first_data_line']}"
            + (f", rate {lay['rate_hz']:g} Hz from the lines before" if lay["rate_hz"] else "")
        )
        lines.append("file columns: " + ", ".join(lay["file_columns"]))
    if info.get("parameters"):
        lines.append(
            f"{info.get('parameters_of', 'PX4')} parameters: "
            + ", ".join(
                f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}"
                for k, v in info["parameters"].items()
            )
        )
    for w in info.get("warnings", []):
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("inspect", help="topics, types, counts, rates and the columns a log fills")
    p.add_argument(
        "log", type=Path, help="a .csv, .mcap, ROS 1 .bag, ROS 2 bag folder, .db3 or PX4 .ulg"
    )
    p.add_argument("--imu-topic", help="as imu_topic in the config")
    p.add_argument("--mag-topic", help="as mag_topic in the config")
    p.add_argument("--temperature-topic", help="as temperature_topic in the config")
    p.add_argument(
        "--config",
        type=Path,
        help="how to read the log, as for convert: the keys of one [inputs.NAME] table without "
        "path (topics, time, a [csv] or [fields] mapping)",
    )
    p.add_argument(
        "--read-truncated",
        action="store_true",
        help="an MCAP or ROS 1 log that is cut off: describe what is read up to the cut, as "
        "convert and survey read it with this option (default: refuse it)",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    spec = InputSpec(path=args.log)
    if args.config is not None:  # the config parser: imported only when asked (start-up time)
        from imupipe.pipeline.convert.settings import load_read_settings

        spec = load_read_settings(args.config)
        spec.path = args.log
    for key in ("imu_topic", "mag_topic", "temperature_topic"):
        if getattr(args, key) is not None:
            setattr(spec, key, getattr(args, key))
    spec.read_truncated = args.read_truncated
    info = inspect(spec)
    print(json.dumps(info, indent=2) if args.json else render(info))
    return 0
