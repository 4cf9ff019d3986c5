"""``imupipe convert --calibration CAL.json --out DIR LOG [LOG ...]``: apply a saved calibration
to a fleet of logs, on this machine or on a Ray cluster.

**What is converted.** Every LOG is a file or a folder. Folders are searched recursively for
``.mcap`` files, ROS 1 ``.bag`` files and ROS 2 bag folders (a folder holding ``metadata.yaml`` or
a ``.db3``), and ``.csv`` files when ``--config`` is given; names starting with a dot and the
output folder itself are skipped. Each log becomes ``DIR/<stem>.mcap`` (a log found inside a
folder argument keeps its sub-folder: ``LOG/robot1/a.mcap`` -> ``DIR/robot1/a.mcap``) and, with
``--parquet``, ``DIR/<stem>.parquet`` (the common table's columns, every optional column
included so all files share one schema: a pyarrow dataset).

**What a worker does** (:func:`convert_log`): read the log, apply the calibration chain
(``corrected = matrix @ (raw - offset)`` for linear steps), write the corrected MCAP (every other
topic carried over), count the messages per topic in the written file and check them against the
input's own index (MCAP summary statistics, ROS 1 bag index, ROS 2 ``metadata.yaml``; for CSV,
the rows read), then rename the outputs into place. It returns statistics only.

**Streaming.** When every step of the chain corrects each sample on its own (``linear`` steps),
the log is read, corrected and written in batches of ``--batch-rows`` rows: a worker's memory is
bounded by the batch, not the log. A step that needs context from other samples or streams (the
``temperature`` step interpolates the temperature stream at the IMU stamps) makes that log be
read whole, corrected at once and written in batches: the same result as ``imupipe run``.

**Resuming.** The corrected MCAP carries the applied calibration as the attachment
``calibration.json``, extended with a ``conversion`` record: the SHA-256 of the chain, of the
read settings (topics, time source, CSV mapping) and the input's size. A log whose output already
holds the same three is skipped unless ``--force``. Outputs are written under temporary names and
renamed when complete, so an interrupted run leaves no half-written file and the next run picks
up where it stopped. ``DIR/manifest.jsonl`` gets one line per log (see
:mod:`imupipe.pipeline.manifest`).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import hashlib
import json
import os
import resource
import sys
import time
import tomllib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

from imupipe.pipeline.atomic import staged_outputs
from imupipe.pipeline.config import parse_input
from imupipe.pipeline.engines import ENGINES, Outcome, run_tasks
from imupipe.pipeline.errors import ConfigError, ImupipeError, ReadError
from imupipe.pipeline.manifest import Manifest
from imupipe.pipeline.mcap_writer import DEFAULT_TOPICS, McapTableWriter
from imupipe.pipeline.progress import progress_bar
from imupipe.readers import dispatch
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.readers.table import OPTIONAL_FIELDS, SCHEMA, counts, metadata, with_metadata
from imupipe.stages.steps import Step, apply_chain, steps_from_json

LOG_SUFFIXES = {".mcap": "mcap", ".bag": "ros1"}
"""File suffixes found in folders (``.csv`` too when ``--config`` is given)."""

STREAMABLE_KINDS = {"linear"}
"""Step kinds that correct each sample from that sample alone, so a log can be corrected batch by
batch. Any other kind (e.g. ``temperature``) makes the log be corrected whole."""

DEFAULT_BATCH_ROWS = 100_000

WORKER_PRELOAD = (
    "imupipe.readers.mcap_reader",
    "imupipe.readers.ros1_reader",
    "imupipe.readers.ros2_reader",
    "imupipe.readers.csv_reader",
    "rosbags.typesys.stores.ros2_humble",
    "rosbags.typesys.stores.ros1_noetic",
)
"""Imported once by the local pool's fork server, so that no worker pays for them on its first
log (the readers are otherwise imported lazily; the ROS 2 type store, ~0.15 s, makes the MCAP
schemas)."""

DATASET_SCHEMA = pa.schema(list(SCHEMA) + list(OPTIONAL_FIELDS))
"""The Parquet files' schema: the common table with every optional column."""


class VerifyError(ImupipeError):
    """The written output does not hold the input's messages, topic for topic."""


# --------------------------------------------------------------------------------------------
# Calibration and settings


def chain_sha256(calibration: Mapping[str, Any]) -> str:
    """SHA-256 of the calibration chain in canonical JSON (what decides the corrected values)."""
    canonical = json.dumps(calibration.get("chain", []), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def load_calibration(path: Path) -> tuple[dict[str, Any], list[Step]]:
    """Read a ``calibration.json`` and rebuild (and so validate) its chain."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"--calibration {path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"--calibration {path}: not a readable JSON file: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("chain"), list):
        raise ConfigError(f"--calibration {path}: no 'chain' list (is it a calibration.json?)")
    doc.pop("conversion", None)  # a calibration taken from a converted MCAP's attachment
    return doc, steps_from_json(doc["chain"], where=str(path))


def load_read_settings(path: Path | None) -> InputSpec:
    """The ``--config`` TOML: the keys of one ``[inputs.NAME]`` table except ``path``
    (``imu_topic``, ``mag_topic``, ``temperature_topic``, ``time`` and a ``[csv]`` mapping)."""
    if path is None:
        return InputSpec(path=Path("."))
    try:
        raw = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"--config {path}: no such file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"--config {path}: not a readable TOML file: {exc}") from None
    if "path" in raw:
        raise ConfigError(f"--config {path}: 'path' is not allowed (the logs are the arguments)")
    base = Path(path).resolve().parent
    return parse_input("convert", {**raw, "path": str(base)}, base, f"--config {path}")


def settings_sha256(spec: InputSpec) -> str:
    """SHA-256 of what decides how a log is read (topics, time source, CSV mapping)."""
    settings = dataclasses.asdict(spec)
    settings.pop("path"), settings.pop("name")
    canonical = json.dumps(settings, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


# --------------------------------------------------------------------------------------------
# Finding the logs


def is_ros2_bag_dir(path: Path) -> bool:
    return path.is_dir() and ((path / "metadata.yaml").exists() or any(path.glob("*.db3")))


def find_logs(args: Sequence[Path], out_dir: Path, *, csv: bool = False) -> list[tuple[Path, Path]]:
    """Every log under ``args`` as (path, output path relative to DIR, without suffix).

    A file argument is taken as it is (its format is judged when it is read); a folder argument is
    a ROS 2 bag or is searched recursively. The output folder is never searched.
    """
    suffixes = set(LOG_SUFFIXES) | ({".csv"} if csv else set())
    out_real = out_dir.resolve()
    found: list[tuple[Path, Path]] = []
    for arg in args:
        arg = Path(arg)
        if not arg.is_dir() or is_ros2_bag_dir(arg):
            found.append((arg, Path(arg.name if arg.is_dir() else arg.stem)))
            continue
        for root, dirs, files in os.walk(arg):
            here = Path(root)
            rel = here.relative_to(arg)
            keep = []
            for d in sorted(dirs):
                sub = here / d
                if d.startswith(".") or sub.resolve() == out_real:
                    continue
                if is_ros2_bag_dir(sub):
                    found.append((sub, rel / d))
                else:
                    keep.append(d)
            dirs[:] = keep
            for f in sorted(files):
                p = here / f
                if not f.startswith(".") and p.suffix.lower() in suffixes:
                    found.append((p, rel / p.stem))
    return found


# --------------------------------------------------------------------------------------------
# One log


@dataclass
class LogTask:
    """Everything a worker needs to convert one log (picklable, small)."""

    spec: InputSpec
    output: Path
    parquet: Path | None
    calibration: dict[str, Any]
    calibration_sha256: str
    settings_sha256: str
    force: bool = False
    batch_rows: int = DEFAULT_BATCH_ROWS


@dataclass
class LogStats:
    """What a worker returns: statistics only."""

    input: str
    output: str
    parquet: str | None
    status: str  # converted | skipped
    counts: dict[str, int]
    calibration_sha256: str
    seconds: float
    cpu_seconds: float
    """CPU time the worker spent on this log (user + system); ``seconds`` is wall time."""
    mode: str  # streamed | whole | -
    peak_rss_mb: float
    warnings: list[str] = field(default_factory=list)

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def _input_size(path: Path) -> int:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


def _mcap_summary(path: Path) -> tuple[dict[str, int], dict[str, Any] | None] | None:
    """(messages per topic, the attached calibration.json) of a finished MCAP; None when the file
    has no summary (unfinished, or written without one)."""
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            return None
        per_topic: collections.Counter[str] = collections.Counter()
        for cid, n in summary.statistics.channel_message_counts.items():
            per_topic[summary.channels[cid].topic] += n
        attached = None
        for att in reader.iter_attachments():
            if att.name == "calibration.json":
                attached = json.loads(att.data)
    return dict(per_topic), attached


def mcap_counts(path: Path) -> dict[str, int] | None:
    """Messages per topic from an MCAP's summary statistics (None when it has none)."""
    summary = _mcap_summary(path)
    return None if summary is None else summary[0]


def input_counts(path: Path, fmt: str) -> dict[str, int] | None:
    """Messages per topic from the log's own index, without reading the messages; None for CSV and
    for logs that have no index (then the counts read are the reference)."""
    try:
        if fmt == "mcap":
            return mcap_counts(path)
        if fmt in ("ros1", "ros2"):
            from rosbags.rosbag1 import Reader as Ros1Reader
            from rosbags.rosbag2 import Reader as Ros2Reader

            if fmt == "ros2" and not (path.is_dir() and (path / "metadata.yaml").exists()):
                return None
            per_topic: collections.Counter[str] = collections.Counter()
            with (Ros1Reader if fmt == "ros1" else Ros2Reader)(path) as reader:
                for conn in reader.connections:
                    per_topic[conn.topic] += conn.msgcount
            return dict(per_topic)
    except ImupipeError:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure to open the index is a bad log
        what = "truncated or corrupt" if fmt == "mcap" else "unreadable"
        raise ReadError(
            f"{path}: {what} {fmt} log (its index cannot be read: {' '.join(str(exc).split())})"
        ) from None
    return None


def existing_output(task: LogTask, input_size: int) -> dict[str, int] | None:
    """The output's counts when it already holds this log converted with this calibration and these
    settings (and the Parquet file exists when asked for); else None."""
    if not task.output.is_file() or (task.parquet is not None and not task.parquet.is_file()):
        return None
    try:
        summary = _mcap_summary(task.output)
    except Exception:  # noqa: BLE001 - an unreadable output is simply not done
        return None
    if summary is None or summary[1] is None:
        return None
    conversion = summary[1].get("conversion", {})
    same = (
        conversion.get("calibration_sha256") == task.calibration_sha256
        and conversion.get("settings_sha256") == task.settings_sha256
        and conversion.get("input_size") == input_size
    )
    return summary[0] if same else None


def _batches(
    spec: InputSpec, streamed: bool, batch_rows: int, warnings: list[str]
) -> Iterator[tuple[pa.Table, Iterable[RawMessage]]]:
    """(table batch, carry-over messages) in log order: batches of about ``batch_rows`` rows when
    ``streamed``, else the whole table (sorted by time) once, then the carry-over as a stream."""
    if streamed:
        yield from dispatch.iter_input(spec, batch_rows=batch_rows)
        return
    table, read_warnings = dispatch.read_input(spec)
    warnings.extend(read_warnings)
    yield table, dispatch.carry_over(spec)


def dataset_table(table: pa.Table, conversion: Mapping[str, Any]) -> pa.Table:
    """``table`` with every column of :data:`DATASET_SCHEMA` (absent optional columns null); its
    imupipe metadata (source, topics, ...) keeps the ``conversion`` record too."""
    columns = [
        table.column(f.name).cast(f.type)
        if f.name in table.column_names
        else pa.nulls(len(table), f.type)
        for f in DATASET_SCHEMA
    ]
    return with_metadata(
        pa.Table.from_arrays(columns, schema=DATASET_SCHEMA),
        {**metadata(table), "conversion": dict(conversion)},
    )


def _counts_by_topic(table: pa.Table) -> collections.Counter[str]:
    topics = {**DEFAULT_TOPICS, **metadata(table).get("topics", {})}
    return collections.Counter({topics[s]: n for s, n in counts(table).items() if n})


def verify_counts(where: Path, expected: Mapping[str, int], written: Mapping[str, int]) -> None:
    """Raise :class:`VerifyError` naming the first topic whose count differs."""
    for topic in sorted(set(expected) | set(written)):
        want, got = expected.get(topic, 0), written.get(topic, 0)
        if want != got:
            raise VerifyError(
                f"{where}: topic {topic}: the input has {want} messages but the output {got}"
            )


def convert_log(task: LogTask) -> LogStats:
    """Convert one log (runs in a worker); raises ImupipeError on bad input."""
    start, cpu_start = time.perf_counter(), time.process_time()
    spec = task.spec
    src = Path(spec.path)
    fmt = dispatch.detect_format(src)
    size = _input_size(src)
    mode, warnings = "-", []
    found = None if task.force else existing_output(task, size)
    if found is not None:
        status, written = "skipped", found
    else:
        steps = steps_from_json(task.calibration["chain"])
        streamed = all(step.kind in STREAMABLE_KINDS for step in steps)
        mode = "streamed" if streamed else "whole"
        expected = input_counts(src, fmt)
        doc = {
            **task.calibration,
            "conversion": {
                "calibration_sha256": task.calibration_sha256,
                "settings_sha256": task.settings_sha256,
                "input": str(src),
                "input_size": size,
            },
        }
        read: collections.Counter[str] = collections.Counter()
        with staged_outputs() as out:
            mcap_tmp = out.path(task.output)
            parquet_tmp = None if task.parquet is None else out.path(task.parquet)
            parquet = None
            try:
                with McapTableWriter(mcap_tmp, calibration=doc) as writer:
                    for batch, raw in _batches(spec, streamed, task.batch_rows, warnings):
                        corrected = apply_chain(batch, steps)
                        writer.write_table(corrected)
                        raw = list(raw)
                        writer.write_raw(raw)
                        read.update(_counts_by_topic(batch))
                        read.update(m.topic for m in raw)
                        if parquet_tmp is not None:
                            rows = dataset_table(corrected, doc["conversion"])
                            if parquet is None:
                                import pyarrow.parquet as pq

                                parquet = pq.ParquetWriter(
                                    parquet_tmp, rows.schema, compression="zstd"
                                )
                            parquet.write_table(rows)
            finally:
                if parquet is not None:
                    parquet.close()
            if parquet_tmp is not None and parquet is None:  # a log without samples
                import pyarrow.parquet as pq

                pq.write_table(DATASET_SCHEMA.empty_table(), parquet_tmp)
            written = mcap_counts(mcap_tmp) or {}
            verify_counts(src, expected if expected is not None else read, written)
        status = "converted"
    return LogStats(
        input=str(src),
        output=str(task.output),
        parquet=None if task.parquet is None else str(task.parquet),
        status=status,
        counts=written,
        calibration_sha256=task.calibration_sha256,
        seconds=round(time.perf_counter() - start, 4),
        cpu_seconds=round(time.process_time() - cpu_start, 4),
        mode=mode,
        peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        warnings=warnings,
    )


# --------------------------------------------------------------------------------------------
# Many logs


@dataclass
class ConvertSummary:
    out_dir: Path
    converted: list[LogStats] = field(default_factory=list)
    skipped: list[LogStats] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    """(input, why) of each log that could not be converted."""
    seconds: float = 0.0

    @property
    def messages(self) -> int:
        return sum(s.messages for s in self.converted)


def plan(
    logs: Sequence[Path],
    out_dir: Path,
    calibration: dict[str, Any],
    settings: InputSpec,
    *,
    parquet: bool = False,
    force: bool = False,
    batch_rows: int = DEFAULT_BATCH_ROWS,
    csv: bool = False,
) -> list[LogTask]:
    """One task per log found; ConfigError when two logs would share an output or an output
    would overwrite an input."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"--out {out_dir}: exists and is not a folder")
    cal_sha, set_sha = chain_sha256(calibration), settings_sha256(settings)
    tasks: list[LogTask] = []
    owners: dict[Path, Path] = {}
    out_dir = out_dir.absolute()  # workers (Ray nodes) may run in another folder
    found = [(p.absolute(), rel) for p, rel in find_logs(logs, out_dir, csv=csv)]
    inputs = {p.resolve() for p, _ in found}
    for path, rel in found:
        output = out_dir / rel.with_name(rel.name + ".mcap")
        key = output.resolve()
        if key in owners and owners[key].resolve() == path.resolve():
            continue  # the same log named twice (a file and its folder)
        if key in owners:
            raise ConfigError(
                f"{owners[key]} and {path} would both be written to {output}; "
                "convert them into separate --out folders"
            )
        if key in inputs or any(key.is_relative_to(i) for i in inputs if i.is_dir()):
            raise ConfigError(
                f"{path}: its output {output} would overwrite an input; choose another --out"
            )
        owners[key] = path
        spec = dataclasses.replace(settings, path=path, name=rel.name)
        tasks.append(
            LogTask(
                spec=spec,
                output=output,
                parquet=output.with_suffix(".parquet") if parquet else None,
                calibration=calibration,
                calibration_sha256=cal_sha,
                settings_sha256=set_sha,
                force=force,
                batch_rows=batch_rows,
            )
        )
    return tasks


def convert(
    logs: Sequence[str | os.PathLike[str]],
    calibration: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    config: str | os.PathLike[str] | None = None,
    engine: str = "local",
    jobs: int | None = None,
    address: str | None = None,
    retries: int = 2,
    parquet: bool = False,
    force: bool = False,
    batch_rows: int = DEFAULT_BATCH_ROWS,
    quiet: bool = True,
) -> ConvertSummary:
    """Convert every log under ``logs`` into ``out_dir``; see the module docstring."""
    start = time.perf_counter()
    out = Path(out_dir)
    doc, _ = load_calibration(Path(calibration))
    settings = load_read_settings(None if config is None else Path(config))
    tasks = plan(
        [Path(p) for p in logs],
        out,
        doc,
        settings,
        parquet=parquet,
        force=force,
        batch_rows=batch_rows,
        csv=config is not None,
    )
    summary = ConvertSummary(out_dir=out)
    if not tasks:
        raise ConfigError(f"no logs found in {', '.join(map(str, logs))}")
    manifest = Manifest(out)
    with progress_bar("imupipe convert", total=len(tasks), quiet=quiet) as bar:

        def on_done(outcome: Outcome) -> None:
            task: LogTask = outcome.task
            record: dict[str, Any] = {"attempts": outcome.attempts, "host": outcome.host}
            if outcome.error is None:
                stats: LogStats = outcome.result
                (summary.converted if stats.status == "converted" else summary.skipped).append(
                    stats
                )
                record.update(dataclasses.asdict(stats), messages=stats.messages)
                if not quiet:
                    for w in stats.warnings:
                        print(f"imupipe: warning: {w}", file=sys.stderr)
            else:
                summary.failed.append((str(task.spec.path), outcome.error))
                record.update(
                    input=str(task.spec.path),
                    status="failed",
                    error=outcome.error,
                    calibration_sha256=task.calibration_sha256,
                )
            manifest.append(record)
            bar.advance()
            bar.describe(f"imupipe convert: {summary.messages:,} messages")

        run_tasks(
            convert_log,
            tasks,
            on_done,
            engine=engine,
            jobs=jobs,
            address=address,
            retries=retries,
            preload=WORKER_PRELOAD,
        )
    summary.seconds = time.perf_counter() - start
    return summary


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "convert",
        help="apply a saved calibration to many logs (files or folders), locally or on Ray",
        description=(
            "Apply CAL.json to every log (files, or folders searched recursively for .mcap, .bag, "
            "ROS 2 bag folders and, with --config, .csv) and write DIR/<stem>.mcap per log."
        ),
    )
    p.add_argument("logs", nargs="+", type=Path, metavar="LOG", help="log files or folders")
    p.add_argument(
        "--calibration",
        type=Path,
        required=True,
        metavar="CAL.json",
        help="a calibration.json (from imupipe run, or attached to a converted MCAP)",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--config",
        type=Path,
        metavar="READ.toml",
        help="TOML with how to read the logs: imu_topic, mag_topic, temperature_topic, time and a "
        "[csv] mapping (the keys of an [inputs.NAME] table); also makes folders yield .csv files",
    )
    p.add_argument(
        "--engine", choices=ENGINES, default="local", help="where to run (default local)"
    )
    p.add_argument(
        "--jobs",
        "-j",
        type=int,
        metavar="N",
        default=None,
        help="worker processes (default: the CPUs available); with --engine ray and no "
        "--address, the CPUs of the local Ray it starts",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster: 'auto' (the cluster of this machine) or ray://HOST:10001; "
        "default: start a local Ray",
    )
    p.add_argument(
        "--retries",
        type=int,
        default=2,
        metavar="N",
        help="retries of a log after a crash (default 2)",
    )
    p.add_argument(
        "--batch-rows",
        type=int,
        metavar="ROWS",
        default=DEFAULT_BATCH_ROWS,
        help=f"rows per streamed batch (default {DEFAULT_BATCH_ROWS})",
    )
    p.add_argument("--parquet", action="store_true", help="also write DIR/<stem>.parquet per log")
    p.add_argument("--force", action="store_true", help="convert again even if already done")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs {args.jobs}: must be at least 1")
    if args.batch_rows < 1:
        raise ConfigError(f"--batch-rows {args.batch_rows}: must be at least 1")
    if args.retries < 0:
        raise ConfigError(f"--retries {args.retries}: must be at least 0")
    if args.address is not None and args.engine != "ray":
        raise ConfigError("--address is for --engine ray")
    summary = convert(
        args.logs,
        args.calibration,
        args.out,
        config=args.config,
        engine=args.engine,
        jobs=args.jobs,
        address=args.address,
        retries=args.retries,
        parquet=args.parquet,
        force=args.force,
        batch_rows=args.batch_rows,
        quiet=args.quiet,
    )
    for path, why in summary.failed:
        print(
            f"imupipe: error: {path}: {why}" if path not in why else f"imupipe: error: {why}",
            file=sys.stderr,
        )
    if not args.quiet:
        total = len(summary.converted) + len(summary.skipped) + len(summary.failed)
        print(
            f"imupipe convert: {len(summary.converted)} converted, {len(summary.skipped)} "
            f"skipped (already done), {len(summary.failed)} failed of {total} logs; "
            f"{summary.messages:,} messages in {summary.seconds:.1f} s -> {summary.out_dir}"
        )
    return 1 if summary.failed else 0
