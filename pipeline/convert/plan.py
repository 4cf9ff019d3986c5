"""Planning a conversion: find the logs under the arguments and give each its output paths.

Folders are searched recursively for ``.mcap`` files, ROS 1 ``.bag`` files and ROS 2 bag folders
(a folder holding ``metadata.yaml``, a ``.db3`` or a ``.db3.zstd`` / ``.mcap.zstd``), and
``.csv`` files when ``--config`` is given; names starting with a dot and the output folder
itself are skipped. Each log becomes
``DIR/<stem>.mcap`` (a log found inside a folder argument keeps its sub-folder:
``LOG/robot1/a.mcap`` -> ``DIR/robot1/a.mcap``) and, with ``--parquet``,
``DIR/parquet/<stem>.parquet``. The plan is checked before anything is written:
two logs that would share an output, or an output that would replace an input, stop the command.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from imupipe.pipeline.atomic import OutputGuard
from imupipe.pipeline.convert.options import DEFAULT_BATCH_ROWS
from imupipe.pipeline.convert.settings import chain_sha256, settings_sha256
from imupipe.pipeline.errors import ConfigError
from imupipe.readers.spec import InputSpec

LOG_SUFFIXES = {".mcap": "mcap", ".bag": "ros1"}
"""File suffixes found in folders (``.csv`` too when ``--config`` is given)."""

PARQUET_DIR = "parquet"
"""``--parquet`` writes ``DIR/parquet/<log>.parquet``: a folder of Parquet files only."""


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
    log: str = ""
    """The log's name: its output path relative to DIR, without suffix (``robot1/day1``)."""
    on_mismatch: str = "warn"
    """What a log that is not from the calibration's sensor does: ``warn`` or ``refuse``."""


def is_ros2_bag_dir(path: Path) -> bool:
    """A folder with ``metadata.yaml``, or sqlite3 storage files (``.db3``, rosbag2's
    file-compressed ``.db3.zstd`` / ``.mcap.zstd``) without it."""
    return path.is_dir() and (
        (path / "metadata.yaml").exists()
        or any(any(path.glob(p)) for p in ("*.db3", "*.db3.zstd", "*.mcap.zstd"))
    )


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


def check_arguments(logs: Sequence[Path]) -> None:
    """Bad command before anything is written (exit 2): an argument that does not exist, or a
    file argument whose suffix names no log format (a README, ``notes.md``)."""
    from imupipe.readers.dispatch import detect_format

    for arg in logs:
        path = Path(arg)
        if not path.exists():
            raise ConfigError(f"{path}: no such file or folder")
        if path.is_file():
            detect_format(path)


@dataclass
class Plan:
    """The tasks, and the guard every path the conversion writes goes through."""

    tasks: list[LogTask]
    guard: OutputGuard

    def folders(self) -> list[Path]:
        """The folders this conversion writes into (``DIR`` and its outputs' folders)."""
        out = {self.guard.root}
        for task in self.tasks:
            out.add(task.output.parent)
            if task.parquet is not None:
                out.add(task.parquet.parent)
        return sorted(out)


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
    on_mismatch: str = "warn",
) -> Plan:
    """One task per log found; ConfigError when an argument is missing or not a log, two logs
    would share an output, or an output breaks the path rule
    (:class:`~imupipe.pipeline.atomic.OutputGuard`)."""
    check_arguments(logs)
    cal_sha, set_sha = chain_sha256(calibration), settings_sha256(settings)
    tasks: list[LogTask] = []
    owners: dict[Path, Path] = {}
    out_dir = out_dir.absolute()  # workers (Ray nodes) may run in another folder
    found = [(p.absolute(), rel) for p, rel in find_logs(logs, out_dir, csv=csv)]
    searched = [Path(a) for a in logs if Path(a).is_dir() and not is_ros2_bag_dir(Path(a))]
    guard = OutputGuard(out_dir, [p for p, _ in found], "--out", searched=searched)
    for path, rel in found:
        if rel.name in ("", ".", ".."):
            raise ConfigError(f"{path}: no file name to name its output after; name the log")
        output = guard.check(out_dir / rel.with_name(rel.name + ".mcap"))
        key = output.resolve()
        if key in owners and owners[key].resolve() == path.resolve():
            continue  # the same log named twice (a file and its folder)
        if key in owners:
            raise ConfigError(
                f"{owners[key]} and {path} would both be written to {output}; "
                "convert them into separate --out folders"
            )
        owners[key] = path
        if parquet and output.is_relative_to(out_dir / PARQUET_DIR):
            raise ConfigError(
                f"{path}: its output {output} would land in the Parquet folder "
                f"{out_dir / PARQUET_DIR}; rename its folder or give --out another folder"
            )
        spec = dataclasses.replace(settings, path=path, name=rel.name)
        tasks.append(
            LogTask(
                spec=spec,
                output=output,
                parquet=guard.check(out_dir / PARQUET_DIR / rel.with_name(rel.name + ".parquet"))
                if parquet
                else None,
                calibration=calibration,
                calibration_sha256=cal_sha,
                settings_sha256=set_sha,
                force=force,
                batch_rows=batch_rows,
                log=rel.as_posix(),
                on_mismatch=on_mismatch,
            )
        )
    return Plan(tasks, guard)
