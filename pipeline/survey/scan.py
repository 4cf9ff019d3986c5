"""``imupipe survey LOG|FOLDER ... --out DIR``: every still moment of a fleet's logs, per IMU.

For each log (any format imupipe reads; a folder is searched as ``convert`` searches it) and
each IMU topic in it, a worker reads the topic (and the temperature topic of the same namespace,
or the log's only one) in batches, so that its memory is bounded by a batch and not by the log
(:mod:`imupipe.pipeline.survey.stream`), finds the still periods and measures each one
(:mod:`imupipe.stages.survey.stats`, :mod:`imupipe.stages.survey.streaming`); with ``--calibration`` the same figures are measured again
on the corrected samples (``cal_*`` columns: what is left is the calibration's error). The rows
of one log go to ``DIR/parts/<log>.parquet``; the driver appends one line per log to
``DIR/manifest.jsonl`` (:mod:`imupipe.pipeline.convert.manifest`), then joins the parts into
``DIR/survey.parquet`` (schema: ``docs/reference/survey.md``) and runs the fleet view
(:mod:`imupipe.pipeline.survey.report`).

Logs run on the engines of ``convert`` (:func:`imupipe.pipeline.convert.engines.run_tasks`: a local
process pool or Ray). A log that cannot be read is named on stderr and left out; the others go
on (exit status 1 when any failed). A log whose part exists, newer than the log and measured with
the same calibration and options, is not measured again (``--force`` to redo it).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import resource
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from imupipe.pipeline.digests import sha256_hex
from imupipe.pipeline.errors import ConfigError, one_line
from imupipe.pipeline.progress import progress_bar
from imupipe.pipeline.warm_imports import WarmImports
from imupipe.readers.errors import READ_TO_CUT
from imupipe.readers.topics import SPLIT

SURVEY_NAME = "survey.parquet"
RECORDING_NAME = "survey.rrd"
PARTS_DIR = "parts"
SCHEMA_VERSION = 1
DEFAULT_K = 5.0


@dataclasses.dataclass
class SurveyTask:
    """What a worker needs to survey one log (picklable, small)."""

    path: Path
    log: str
    """The log's name: its path relative to the folder given, without suffix."""
    vehicle: str
    part: Path
    calibration: dict[str, Any] | None
    calibration_sha256: str | None
    options: dict[str, float]
    options_sha256: str
    batch_rows: int | None = None
    """Rows per batch a worker holds (None: :data:`imupipe.pipeline.survey.stream.DEFAULT_BATCH_ROWS`)."""
    read_truncated: bool = False
    """Read an MCAP or ROS 1 log that is cut off up to the cut, with a warning
    (:attr:`~imupipe.readers.spec.InputSpec.read_truncated`); False: refuse it."""


FLIGHT_IMU_TYPES = {"ulog": ("sensor_gyro",), "dataflash": ("IMU", "IMU2", "IMU3")}
"""The message types of a flight log's raw IMU instances (each read as one device)."""


def _namespace(topic: str) -> str:
    return topic.split(SPLIT)[0].rsplit("/", 1)[0]


def split_topics(topic: str | None) -> dict[str, str | None]:
    """The spec keys that read the IMU named ``topic`` (:func:`imu_topics`): ``imu_topic``, or
    ``gyro_topic`` and ``accel_topic`` for a pair."""
    if topic is not None and SPLIT in topic:
        gyro, accel = topic.split(SPLIT, 1)
        return {"imu_topic": None, "gyro_topic": gyro, "accel_topic": accel}
    return {"imu_topic": topic}


def imu_topics(spec: Any) -> list[tuple[str | None, str | None, str | None]]:
    """(imu topic, temperature topic, magnetometer topic to name) per IMU instance of a log; one
    (None, None, None) for a CSV file (one IMU). A camera's gyro and accelerometer published
    apart (:func:`~imupipe.readers.topics.split_pairs`) are one IMU: its topic is
    ``GYRO_TOPIC+ACCEL_TOPIC`` (:func:`split_topics` reads it back)."""
    from imupipe.readers import dispatch
    from imupipe.readers.topics import STREAM_TYPES, normalize_type, split_pairs

    fmt = dispatch.detect_format(Path(spec.path))
    if fmt == "csv":
        return [(None, None, None)]
    types: dict[str, str] = {}
    for src in dispatch.log_sources(spec):
        types.update(src.topic_types())
    if fmt in FLIGHT_IMU_TYPES:  # each instance by its key; its reader picks its temperature
        return [(t, None, None) for t, ty in sorted(types.items()) if ty in FLIGHT_IMU_TYPES[fmt]]
    by_type: dict[str, list[str]] = {s: [] for s in STREAM_TYPES}
    for topic, ty in sorted(types.items()):
        for stream, msgtype in STREAM_TYPES.items():
            if normalize_type(ty) == msgtype:
                by_type[stream].append(topic)
    out = []
    pairs = split_pairs(by_type["imu"])
    paired = {t for pair in pairs for t in pair.values()}
    imus = [t for t in by_type["imu"] if t not in paired]
    for imu in sorted(imus + [f"{pair['gyro']}{SPLIT}{pair['accel']}" for pair in pairs]):
        near = (_namespace(imu), _namespace(_namespace(imu)))  # /camera of /camera/gyro/sample
        temps = [t for t in by_type["temperature"] if _namespace(t) in near]
        temp = (
            temps[0]
            if temps
            else (by_type["temperature"][0] if len(by_type["temperature"]) == 1 else None)
        )
        mag = by_type["mag"][0] if by_type["mag"] else None
        out.append((imu, temp, mag))
    return out


WORKER_PRELOAD = (
    "pyarrow.parquet",
    "pyarrow.compute",  # ~0.1 s: its functions' docstrings are built when it loads
    "numpy.ma",
    "zstandard",
    "imupipe.pipeline.atomic",
    "imupipe.pipeline.calibration_file",
    "imupipe.pipeline.survey.stream",
    "imupipe.pipeline.survey.compass",
    "imupipe.readers.spec",
    "imupipe.stages.steps",
    "imupipe.stages.survey.stats",
)
"""Imported once by the local pool's fork server (with the readers of the formats in the fleet,
:func:`worker_preload`), so that no worker pays for them on its first log (issue 39: with two
workers each first log took 0.8 s, four in ten of a 60-log fleet's worker time)."""


POST_MODULES = ("imupipe.pipeline.survey.report", "imupipe.pipeline.report.recording")
"""What the driver imports after the logs: the fleet view's and report's, then the recording's
(Rerun)."""


def worker_preload(paths: Sequence[Path]) -> list[str]:
    """:data:`WORKER_PRELOAD` and the reader module of each format among the logs ``paths``."""
    from imupipe.readers.dispatch import READERS, detect_format
    from imupipe.readers.errors import ReadError

    formats = set()
    for path in paths:
        try:
            formats.add(detect_format(Path(path)))
        except ReadError:
            continue  # the worker reports it
    return [*WORKER_PRELOAD, *(READERS[f].split(":")[0] for f in sorted(formats))]


def survey_log(task: SurveyTask) -> dict[str, Any]:
    """Survey one log (runs in a worker): write its part, return its manifest line. Each IMU
    topic streams in batches of ``task.batch_rows`` rows (:mod:`imupipe.pipeline.survey.stream`)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from imupipe.pipeline.atomic import staged_outputs
    from imupipe.pipeline.calibration_file import on_device
    from imupipe.pipeline.survey.stream import survey_topic
    from imupipe.readers.spec import InputSpec
    from imupipe.stages.steps import steps_from_json
    from imupipe.stages.survey.stats import StillOptions

    start, cpu = time.perf_counter(), time.process_time()
    opts = StillOptions(**task.options)
    spec = InputSpec(path=Path(task.path), name=task.vehicle, read_truncated=task.read_truncated)
    steps = None
    if task.calibration is not None:
        chain = task.calibration["chain"]
        steps = on_device(steps_from_json(chain), chain, lenient=True)
    rows: list[pa.Table] = []
    counts: dict[str, int] = {}
    warnings: list[str] = []
    topics = imu_topics(spec)
    for instance, (imu, temp, mag) in enumerate(topics):
        one = dataclasses.replace(spec, **split_topics(imu), temperature_topic=temp, mag_topic=mag)
        found = survey_topic(one, opts, steps, warnings, batch_rows=task.batch_rows)
        if found is None:
            continue
        topic = imu or "csv"
        m = len(found.stats["start_ns"])
        counts[topic] = m
        rows.append(_rows(task, topic, instance, found.frame, found.stats, found.cal, m))
    if not topics:
        warnings.append(f"{task.path}: no sensor_msgs/Imu topic: nothing to survey")
    table = pa.concat_tables(rows) if rows else _rows(task, "", 0, None, None, None, 0)
    from imupipe.pipeline.survey.compass import survey_compass  # flight logs: their compasses

    compass = survey_compass(task)  # writes parts/<log>.compass.parquet (before the log's part)
    task.part.parent.mkdir(parents=True, exist_ok=True)
    with staged_outputs() as out:
        pq.write_table(table, out.path(task.part), compression="zstd")
    return {
        "input": str(task.path),
        "output": str(task.part),
        "status": "surveyed",
        "counts": counts,
        "calibration_sha256": task.calibration_sha256,
        "mode": task.options_sha256,
        "seconds": round(time.perf_counter() - start, 4),
        "cpu_seconds": round(time.process_time() - cpu, 4),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "warnings": warnings + (compass or {}).get("warnings", []),
        **({"compass": compass} if compass else {}),
    }


FIGURES_3 = (
    "gyro_bias",
    "gyro_bias_se",
    "gyro_noise",
    "accel_mean",
    "accel_mean_se",
    "accel_noise",
)
FIGURES_1 = ("accel_norm_error", "accel_norm_error_se", "tilt_deg", "level")


def _rows(
    task: SurveyTask,
    topic: str,
    instance: int,
    frame: str | None,
    stats: dict[str, Any] | None,
    cal: dict[str, Any] | None,
    m: int,
) -> Any:
    """The dataset rows of one IMU instance of one log (see docs/reference/survey.md)."""
    import numpy as np
    import pyarrow as pa

    from imupipe.readers.arrays import arrow_array

    def col(name: str, values: Any, typ: pa.DataType) -> None:
        # numpy columns on their buffers: pa.array of an ndarray imports numpy.ma (9 ms, issue 39)
        numpy = isinstance(values, np.ndarray)
        arrays.append(arrow_array(values, typ) if numpy else pa.array(values, typ))
        names.append(name)

    arrays: list[pa.Array] = []
    names: list[str] = []
    col("log", [task.log] * m, pa.string())
    col("vehicle", [task.vehicle] * m, pa.string())
    col("topic", [topic] * m, pa.string())
    col("instance", np.full(m, instance, np.int32), pa.int32())
    col("frame_id", [frame] * m, pa.string())
    col("device_id", [f"{task.vehicle}:{topic}"] * m, pa.string())
    col("calibration_sha256", [task.calibration_sha256] * m, pa.string())
    col("period", np.arange(m, dtype=np.int32), pa.int32())
    z = np.zeros(m)
    s = stats or {}
    col("start_ns", s.get("start_ns", z.astype(np.int64)), pa.int64())
    start_us = np.asarray(s.get("start_ns", z.astype(np.int64))) // 1000  # us: datetime-friendly
    col(
        "start",
        arrow_array(start_us, pa.int64()).view(pa.timestamp("us", "UTC")),  # no compute: a cast
        pa.timestamp("us", "UTC"),
    )
    col("stop_ns", s.get("stop_ns", z.astype(np.int64)), pa.int64())
    col("duration_s", s.get("duration_s", z), pa.float64())
    col("samples", s.get("samples", z.astype(np.int64)), pa.int64())
    col("temperature", s.get("temperature", z), pa.float64())
    for prefix, figures in (("", stats), ("cal_", cal)):
        if prefix and cal is None and task.calibration is None:
            continue
        f = figures or {}
        for name in FIGURES_3:
            values = f.get(name, np.full((m, 3), np.nan))
            for i, axis in enumerate("xyz"):
                col(f"{prefix}{name}_{axis}", values[:, i], pa.float64())
        for name in FIGURES_1:
            typ = pa.bool_() if name == "level" else pa.float64()
            col(f"{prefix}{name}", f.get(name, np.zeros(m, bool) if name == "level" else z), typ)
    fields = [
        pa.field(n, a.type, metadata=None if column_unit(n) is None else {"unit": column_unit(n)})
        for n, a in zip(names, arrays, strict=True)
    ]
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


def column_unit(name: str) -> str | None:
    """The unit of a dataset column (its Parquet field's ``unit`` metadata), None for identity."""
    base = name.removeprefix("cal_")
    if base.endswith("_ns"):
        return "ns"
    for stem, unit in (
        ("gyro_bias", "rad/s"),
        ("gyro_noise", "rad/s/sqrt(Hz)"),
        ("accel_noise", "m/s^2/sqrt(Hz)"),
        ("accel_mean", "m/s^2"),
        ("accel_norm_error", "m/s^2"),
        ("tilt_deg", "deg"),
        ("duration_s", "s"),
        ("temperature", "degC"),
        ("samples", "1"),
    ):
        if base.startswith(stem):
            return unit
    return None


def _sha(value: Any) -> str:
    return sha256_hex(json.dumps(value, sort_keys=True).encode())


FLIGHT_SUFFIXES = (".ulg", ".bin")
"""Flight-controller logs (PX4 ULog, ArduPilot DataFlash), found in folders besides those
``convert`` finds (:func:`~imupipe.pipeline.convert.plan.find_logs`: MCAP, bags, CSV)."""


def guarded_logs(logs: Sequence[Path], out_dir: Path) -> tuple[list[tuple[Path, Path]], Any]:
    """(every log under ``logs`` as (absolute path, name), the
    :class:`~imupipe.pipeline.atomic.OutputGuard` of ``out_dir``): ``convert``'s rules. An
    argument that is missing or not a log (a README, a FIFO) is a ConfigError before anything is
    read (:func:`~imupipe.pipeline.convert.plan.check_arguments`: by its name and ``stat``,
    never by reading it); ``--out`` may not be an input, hold one, or be the folder searched."""
    from imupipe.pipeline.atomic import OutputGuard
    from imupipe.pipeline.convert.plan import check_arguments, find_logs, is_ros2_bag_dir

    check_arguments(logs)
    found = [
        (p.absolute(), rel) for p, rel in find_logs(logs, out_dir, csv=True, extra=FLIGHT_SUFFIXES)
    ]
    searched = [Path(a) for a in logs if Path(a).is_dir() and not is_ros2_bag_dir(Path(a))]
    guard = OutputGuard(out_dir, [p for p, _ in found], "--out", searched=searched)
    return found, guard


def skipped_folder(logs: Sequence[Path], out_dir: Path) -> Path | None:
    """``out_dir`` when it lies inside a folder searched for logs (its logs are not surveyed)."""
    out = Path(out_dir).absolute().resolve()
    for arg in logs:
        folder = Path(arg).absolute().resolve()
        if Path(arg).is_dir() and out != folder and out.is_relative_to(folder) and out.exists():
            return Path(out_dir)
    return None


def plan(
    logs: Sequence[Path],
    out_dir: Path,
    calibration: dict[str, Any] | None,
    options: dict[str, float],
    force: bool = False,
    batch_rows: int | None = None,
    read_truncated: bool = False,
) -> tuple[list[SurveyTask], list[SurveyTask]]:
    """(tasks to run, tasks already done) for every log under ``logs`` (``batch_rows``: see
    :class:`SurveyTask`; it does not change the figures, so a part surveyed with another batch
    size is kept; ``read_truncated`` does: it is in the mode a part was surveyed with)."""
    from imupipe.pipeline.convert.manifest import latest
    from imupipe.pipeline.convert.settings import chain_sha256
    from imupipe.pipeline.survey.compass import compass_part

    out_dir = out_dir.absolute()
    found, _ = guarded_logs(logs, out_dir)
    cal_sha = None if calibration is None else chain_sha256(calibration)
    opt_sha = _sha({**options, "read_truncated": True} if read_truncated else options)[:16]
    done = latest(out_dir)
    todo, skipped = [], []
    seen: dict[str, Path] = {}
    for path, rel in found:
        parent = rel.parent.name if rel.parent.name else path.parent.name
        part = out_dir / PARTS_DIR / rel.with_name(rel.name + ".parquet")
        if str(part) in seen:
            if seen[str(part)].resolve() == path.resolve():
                continue
            raise ConfigError(f"{seen[str(part)]} and {path} would both be surveyed into {part}")
        seen[str(part)] = path
        task = SurveyTask(
            path, rel.as_posix(), parent, part, calibration, cal_sha, options, opt_sha,
            batch_rows, read_truncated,
        )  # fmt: skip
        rec = done.get(str(path))
        fresh = (
            not force
            and rec is not None
            and rec.get("status") in ("surveyed", "skipped")
            and rec.get("calibration_sha256") == cal_sha
            and rec.get("mode") == opt_sha
            and part.exists()
            and part.stat().st_mtime >= path.stat().st_mtime
            and (path.suffix.lower() not in FLIGHT_SUFFIXES or compass_part(part).exists())
        )
        (skipped if fresh else todo).append(task)
    return todo, skipped


def survey(
    logs: Sequence[Path],
    out_dir: Path,
    *,
    calibration: Path | None = None,
    chamber: Path | None = None,
    engine: str = "local",
    jobs: int | None = None,
    address: str | None = None,
    retries: int = 2,
    force: bool = False,
    options: dict[str, float] | None = None,
    k: float = DEFAULT_K,
    quiet: bool = False,
    rerun: bool = True,
    batch_rows: int | None = None,
    read_truncated: bool = False,
) -> dict[str, Any]:
    """Survey ``logs`` into ``out_dir``; returns ``{"failed": [(path, why)], "surveyed": n,
    "skipped": n, "fleet": the fleet view}``. ``chamber``: the chamber calibrations the in-field
    thermal curves are compared with (:mod:`imupipe.pipeline.survey.chamber`; default: the
    thermal steps of ``calibration``). ``batch_rows``: rows per batch a worker reads (memory;
    the figures do not depend on it). ``read_truncated``: an MCAP or ROS 1 log that is cut off
    is read up to the cut, with a warning in the manifest (``--read-truncated``); else it fails."""
    from imupipe.pipeline.convert.engines import Outcome, run_tasks, start_forkserver

    out_dir = Path(out_dir).absolute()
    found, guard = guarded_logs(logs, out_dir)  # before anything is read or written
    preload = worker_preload([p for p, _ in found]) if engine == "local" else []
    if engine == "local" and jobs != 1 and len(found) > 1:
        # the workers' fork server imports their modules while this process imports its own
        # and plans (about 0.4 s of the ~0.6 s it takes; :func:`run_tasks` then finds it running)
        start_forkserver(survey_log, preload)

    import pyarrow.parquet as pq

    from imupipe.pipeline.atomic import remove_stale_temps, staged_outputs
    from imupipe.pipeline.calibration_file import load_calibration
    from imupipe.pipeline.convert.fleet import ENGINE_LOG
    from imupipe.pipeline.convert.manifest import Manifest
    from imupipe.pipeline.survey.compass import read_part

    doc = None
    chambers = None
    if calibration is not None:
        doc, cal_steps = load_calibration(calibration)
    if chamber is not None or calibration is not None:
        from imupipe.pipeline.survey import chamber as chamber_files

        chambers = (
            chamber_files.load_chambers(chamber)
            if chamber is not None
            else chamber_files.from_calibration(calibration, doc, cal_steps)
        )
    opts = dict(options or {})
    todo, skipped = plan(logs, out_dir, doc, opts, force, batch_rows, read_truncated)
    if not todo and not skipped:
        raise ConfigError(f"no log found under {', '.join(map(str, logs))}")
    out_dir.mkdir(parents=True, exist_ok=True)
    # the temporary files of a survey killed earlier (one survey at a time writes into DIR)
    for folder in {out_dir, *(t.part.parent for t in todo + skipped)}:
        remove_stale_temps(folder)
    manifest = Manifest(out_dir)
    failed: list[tuple[str, str]] = []
    without_still: list[str] = []  # (log, topic) surveyed with no still period
    cut_off: list[str] = []  # the warnings of the logs read up to a cut (--read-truncated)
    ok: list[SurveyTask] = list(skipped)
    tables: dict[str, Any] = {}  # log -> its part, read as soon as it is surveyed
    for task in skipped:
        manifest.append(
            {
                "input": str(task.path),
                "output": str(task.part),
                "status": "skipped",
                "calibration_sha256": task.calibration_sha256,
                "mode": task.options_sha256,
            }
        )

    def on_done(outcome: Outcome) -> None:
        task = outcome.task
        if outcome.error is not None:
            failed.append((str(task.path), outcome.error))
            manifest.append(
                {
                    "input": str(task.path),
                    "status": "failed",
                    "error": outcome.error,
                    "attempts": outcome.attempts,
                    "host": outcome.host,
                    "calibration_sha256": task.calibration_sha256,
                }
            )
            if outcome.fatal:
                raise ConfigError(outcome.error)
            return
        manifest.append({**outcome.result, "attempts": outcome.attempts, "host": outcome.host})
        ok.append(task)
        if outcome.pid != os.getpid():
            # surveyed by a worker: read now, while the workers survey the next logs (at the end
            # it was serial: 200 logs of the 20 s kind took 1.3 s to read back)
            tables[task.log] = read_part(task.part)
        counts = outcome.result.get("counts") or {}
        without_still.extend(f"{task.log} {topic}" for topic, n in counts.items() if n == 0)
        cut_off.extend(w for w in outcome.result.get("warnings", ()) if READ_TO_CUT in w)

    # as convert: Ray's own output goes to DIR/ray.log, the user's stderr holds imupipe's lines
    engine_log = out_dir / ENGINE_LOG if engine == "ray" else None
    # what the fleet view, the report and the recording import (Rerun: about 0.5 s), imported on
    # a thread of this process once a worker process has surveyed a log: this process then waits
    # for its workers. Not while it surveys logs itself (--jobs 1, or while the pool starts):
    # a log's survey holds the GIL most of the time, and on a busy machine the two threads took
    # longer than one after the other (40 logs: 5.4-5.8 s against 4.6-4.7 s).
    warm = WarmImports(POST_MODULES[: None if rerun else 1])
    with progress_bar("imupipe survey", total=len(todo), quiet=quiet, unit="logs") as bar:

        def counted(outcome: Outcome) -> None:
            on_done(outcome)
            bar.advance()
            if outcome.pid != os.getpid():
                warm.start()

        try:
            with bar.listen(within_items=True):  # a log read here (--jobs 1): by its bytes
                run_tasks(
                    survey_log,
                    todo,
                    counted,
                    engine=engine,
                    jobs=jobs,
                    address=address,
                    retries=retries,
                    preload=preload,
                    engine_log=engine_log,
                    driver_helps=True,
                )
        finally:
            warm.wait()  # no thread outlives the survey
    import pyarrow as pa

    parts = [
        tables[t.log] if t.log in tables else read_part(t.part)
        for t in sorted(ok, key=lambda t: t.log)
    ]
    table = pa.concat_tables(parts, promote_options="default") if parts else None
    fleet: dict[str, Any] = {}
    compass = None
    with staged_outputs(guard) as out:
        from imupipe.pipeline.survey.compass import write_compass

        compass = write_compass(out, out_dir, sorted(ok, key=lambda t: t.log), k)
        if table is not None:
            meta = {
                "imupipe_survey": json.dumps(
                    {"schema_version": SCHEMA_VERSION, "options": opts, "k": k}
                )
            }
            table = table.replace_schema_metadata(meta)
            if chambers:  # the chamber curve at each period (chamber_* columns)
                table = chamber_files.chamber_columns(table, chambers)
            from imupipe.pipeline.survey.report import fleet_view, still_column, write_report

            fleet = fleet_view(table, k=k, chambers=chambers)
            table = still_column(table, fleet)
            pq.write_table(table, out.path(out_dir / SURVEY_NAME), compression="zstd")
            out.write_text(
                out_dir / "fleet.json", json.dumps(fleet, indent=2, default=float) + "\n"
            )
            write_report(out.path(out_dir / "report.html"), table, fleet, compass=compass)
        if rerun and (table is not None or compass):
            from imupipe.pipeline.survey.report import write_recording

            write_recording(out.path(out_dir / RECORDING_NAME), table, fleet, compass)
    return {
        "failed": failed,
        "surveyed": len(ok) - len(skipped),
        "skipped": len(skipped),
        "fleet": fleet,
        "compass": compass,
        "rows": 0 if table is None else table.num_rows,
        "without_still": sorted(without_still),
        "cut_off": sorted(set(cut_off)),
    }


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "survey",
        help="every still moment of a fleet's logs: each IMU's bias, noise and temperature over time",
    )
    p.add_argument("logs", nargs="+", type=Path, metavar="LOG|FOLDER")
    p.add_argument(
        "--out", type=Path, required=True, help="output folder (survey.parquet, report.html)"
    )
    p.add_argument(
        "--calibration", type=Path, help="calibration.json: also measure after applying it"
    )
    p.add_argument(
        "--chamber",
        type=Path,
        metavar="CAL.json|FOLDER",
        help="chamber calibrations to compare the in-field thermal curves with (a file, or a "
        "folder of <vehicle>.json); default: --calibration's thermal steps",
    )
    p.add_argument("--engine", choices=("local", "ray"), default="local")
    p.add_argument("--jobs", type=int, help="worker processes (default: the usable cores)")
    p.add_argument("--address", help="Ray cluster address (--engine ray)")
    p.add_argument("--retries", type=int, default=2)
    p.add_argument("--force", action="store_true", help="survey every log again")
    p.add_argument(
        "--read-truncated",
        action="store_true",
        help="read an MCAP or ROS 1 log that is cut off up to the cut, with a warning naming "
        "the byte where the damage starts and the bytes skipped (default: the log fails)",
    )
    p.add_argument(
        "--min-still",
        type=float,
        default=5.0,
        metavar="S",
        help="shortest still period, s (default 5)",
    )
    p.add_argument(
        "--k",
        type=float,
        default=DEFAULT_K,
        help=f"outlier rule: k robust sigmas (default {DEFAULT_K:g})",
    )
    p.add_argument(
        "--no-rerun", action="store_true", help=f"do not write the Rerun recording {RECORDING_NAME}"
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs {args.jobs}: must be at least 1")
    if not 0 < args.min_still < math.inf:
        raise ConfigError(f"--min-still {args.min_still}: must be a positive number of seconds")
    if not 0 < args.k < math.inf:
        raise ConfigError(f"--k {args.k}: must be a positive number")
    skipped = skipped_folder(args.logs, args.out)
    if skipped is not None and not args.quiet:
        print(
            f"imupipe: note: {one_line(str(skipped))} is the output folder: the logs in it are "
            "not surveyed",
            file=sys.stderr,
        )
    result = survey(
        args.logs,
        args.out,
        calibration=args.calibration,
        chamber=args.chamber,
        engine=args.engine,
        jobs=args.jobs,
        address=args.address,
        retries=args.retries,
        force=args.force,
        options={"min_duration_s": float(args.min_still)},
        k=args.k,
        quiet=args.quiet,
        rerun=not args.no_rerun,
        read_truncated=args.read_truncated,
    )
    for path, why in result["failed"]:
        named = path in why or " ".join(path.split()) in why  # a worker's line: one line
        line = why if named else f"{path}: {why}"
        print(f"imupipe: error: {one_line(line)}", file=sys.stderr)
    if not args.quiet:
        for line in result["cut_off"]:
            print(f"imupipe: warning: {one_line(line)}", file=sys.stderr)
        from imupipe.pipeline.survey.compass import summary_lines as compass_lines
        from imupipe.pipeline.survey.report import summary_lines

        for line in summary_lines(result["fleet"]) + compass_lines(result["compass"]):
            print(line)
        if result["without_still"]:
            names = result["without_still"]
            more = f" (+{len(names) - 3} more)" if len(names) > 3 else ""
            print(
                f"imupipe survey: no still period in {len(names)} IMU topic-logs: "
                f"{', '.join(names[:3])}{more} (manifest.jsonl says why)"
            )
        print(
            f"imupipe survey: {result['surveyed']} surveyed, {result['skipped']} skipped (already "
            f"done), {len(result['failed'])} failed; {result['rows']} still periods -> "
            f"{args.out / SURVEY_NAME}"
        )
    return 1 if result["failed"] else 0
