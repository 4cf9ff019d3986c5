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
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from imupipe.pipeline.atomic import OutputGuard
from imupipe.pipeline.convert.options import DEFAULT_BATCH_ROWS, is_url, local_path
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
    source_url: str | None = None
    """The input's URL when it is an object (``s3://...``): the worker copies it to a local
    temporary file first (:mod:`imupipe.pipeline.convert.remote`)."""
    output_url: str | None = None
    """The output's URL when ``--out`` is on an object store (``output`` is then its name
    relative to DIR; the worker writes it locally, verifies it, then publishes it)."""
    parquet_url: str | None = None
    source: str = ""
    """How the manifest and the attached record name the input when ``spec.path`` is a local
    copy of it (its URL); empty: ``spec.path``."""


def is_ros2_bag_dir(path: Path) -> bool:
    """A folder with ``metadata.yaml``, or sqlite3 storage files (``.db3``, rosbag2's
    file-compressed ``.db3.zstd`` / ``.mcap.zstd``) without it."""
    return path.is_dir() and (
        (path / "metadata.yaml").exists()
        or any(any(path.glob(p)) for p in ("*.db3", "*.db3.zstd", "*.mcap.zstd"))
    )


def find_logs(
    args: Sequence[Path], out_dir: Path, *, csv: bool = False, extra: Collection[str] = ()
) -> list[tuple[Path, Path]]:
    """Every log under ``args`` as (path, output path relative to DIR, without suffix).

    A file argument is taken as it is (its format is judged when it is read); a folder argument is
    a ROS 2 bag or is searched recursively for MCAP and ROS 1 logs, CSV files with ``csv`` and
    the suffixes in ``extra`` (``survey``: ``.ulg``, ``.bin``). Hidden files and folders and the
    output folder are never searched.
    """
    suffixes = set(LOG_SUFFIXES) | ({".csv"} if csv else set()) | set(extra)
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
                if not f.startswith(".") and p.suffix.lower() in suffixes and p.is_file():
                    found.append((p, rel / p.stem))  # a FIFO, socket or device is no log
    return found


def check_arguments(logs: Sequence[Path]) -> None:
    """Bad command before anything is written (exit 2): an argument that does not exist, or a
    file argument whose suffix names no log format (a README, ``notes.md``)."""
    from imupipe.readers.dispatch import detect_format

    for arg in logs:
        path = Path(arg)
        if not path.exists():
            raise ConfigError(f"{path}: no such file or folder")
        if not path.is_dir():
            detect_format(path)  # by its name and stat: a FIFO or a device is never opened


@dataclass
class Plan:
    """The tasks, and the guard every local path the conversion writes goes through (None when
    ``--out`` is a URL: ``out_url``)."""

    tasks: list[LogTask]
    guard: OutputGuard | None
    out_url: str | None = None

    def remote_folders(self) -> list[str]:
        """The prefixes a conversion to an object store writes into (DIR and its outputs')."""
        if self.out_url is None:
            return []
        urls = {self.out_url.rstrip("/")}
        for task in self.tasks:
            for url in (task.output_url, task.parquet_url):
                if url is not None:
                    urls.add(url.rpartition("/")[0])
        return sorted(urls)

    def folders(self) -> list[Path]:
        """The folders this conversion writes into (``DIR`` and its outputs' folders)."""
        if self.guard is None:
            return []
        out = {self.guard.root}
        for task in self.tasks:
            out.add(task.output.parent)
            if task.parquet is not None:
                out.add(task.parquet.parent)
        return sorted(out)


def plan(
    logs: Sequence[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    calibration: dict[str, Any],
    settings: InputSpec,
    *,
    parquet: bool = False,
    force: bool = False,
    batch_rows: int = DEFAULT_BATCH_ROWS,
    csv: bool = False,
    on_mismatch: str = "warn",
) -> Plan:
    """One task per log found (see :func:`plan_local`); logs or ``out_dir`` given as URLs
    (``s3://bucket/prefix``) are planned by :func:`plan_remote`."""
    keywords: dict[str, Any] = dict(
        parquet=parquet, force=force, batch_rows=batch_rows, csv=csv, on_mismatch=on_mismatch
    )
    if not is_url(out_dir) and not any(is_url(a) for a in logs):
        paths = [local_path(a) for a in logs]
        return plan_local(paths, local_path(out_dir), calibration, settings, **keywords)
    return plan_remote(logs, out_dir, calibration, settings, **keywords)


def plan_remote(
    logs: Sequence[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    calibration: dict[str, Any],
    settings: InputSpec,
    *,
    parquet: bool = False,
    force: bool = False,
    batch_rows: int = DEFAULT_BATCH_ROWS,
    csv: bool = False,
    on_mismatch: str = "warn",
) -> Plan:
    """:func:`plan_local` when inputs or ``out_dir`` are URLs. A URL argument is an object or a
    prefix searched recursively (:func:`imupipe.pipeline.convert.remote.find_logs`); local
    arguments are found as by :func:`find_logs`. The path rule on an object store: no output
    key equal to an input key, ``DIR`` not a prefix searched for logs, and (a prefix is not a
    folder: no symbolic links) nothing outside ``DIR`` (every output is ``DIR/<name>``)."""
    from imupipe.pipeline.convert import remote
    from imupipe.readers.dispatch import CSV_SUFFIXES

    urls = [remote.check_url(a) for a in logs if remote.is_url(a)]
    paths = [remote.local_path(a) for a in logs if not remote.is_url(a)]
    check_arguments(paths)
    out_url = remote.check_url(out_dir, "--out") if remote.is_url(out_dir) else None
    local_out = None if out_url is not None else remote.local_path(out_dir).absolute()
    suffixes = set(LOG_SUFFIXES) | ({".csv"} if csv else set())
    known = set(LOG_SUFFIXES) | {".ulg", ".bin", ".db3"} | CSV_SUFFIXES
    found: list[tuple[str | Path, Path]] = []
    for url in urls:
        if out_url is not None and url == out_url:
            raise ConfigError(
                f"--out {out_url}: is the prefix searched for logs, so its outputs would sit "
                "among the inputs; choose another prefix (one inside it is not searched)"
            )
        for item in remote.find_logs(url, suffixes, known):
            if out_url is None or not item.url.startswith(out_url + "/"):
                found.append((item.url, Path(item.rel.as_posix())))
    nowhere = Path(os.devnull)  # local searches skip DIR; a remote DIR is never local
    found += [(p.absolute(), rel) for p, rel in find_logs(paths, local_out or nowhere, csv=csv)]
    guard = None
    if local_out is not None:
        searched = [p for p in paths if p.is_dir() and not is_ros2_bag_dir(p)]
        local_inputs = [p for p, _ in found if isinstance(p, Path)]
        guard = OutputGuard(local_out, local_inputs, "--out", searched=searched)
    cal_sha, set_sha = chain_sha256(calibration), settings_sha256(settings)
    inputs = {str(p) for p, _ in found}
    tasks: list[LogTask] = []
    owners: dict[str, str | Path] = {}
    for source, rel in found:
        if rel.name in ("", ".", ".."):
            raise ConfigError(f"{source}: no file name to name its output after; name the log")
        name_mcap = rel.with_name(rel.name + ".mcap")
        name_parquet = Path(PARQUET_DIR) / rel.with_name(rel.name + ".parquet")
        if out_url is not None:
            output, output_url = name_mcap, remote.join(out_url, name_mcap.as_posix())
            parquet_url = remote.join(out_url, name_parquet.as_posix()) if parquet else None
            parquet_path = name_parquet if parquet else None
            key = output_url
            if output_url in inputs or parquet_url in inputs:
                raise ConfigError(f"{output_url}: would overwrite an input; choose another --out")
        else:
            assert guard is not None and local_out is not None
            output, output_url, parquet_url = guard.check(local_out / name_mcap), None, None
            parquet_path = guard.check(local_out / name_parquet) if parquet else None
            key = str(output.resolve())
        if key in owners and str(owners[key]) == str(source):
            continue  # the same log named twice
        if key in owners:
            raise ConfigError(
                f"{owners[key]} and {source} would both be written to {output_url or output}; "
                "convert them into separate --out folders"
            )
        owners[key] = source
        is_remote = isinstance(source, str)
        spec_path = Path(PurePosixPath(source).name) if is_remote else source
        spec = dataclasses.replace(settings, path=spec_path, name=rel.name)
        tasks.append(
            LogTask(
                spec=spec,
                output=output,
                parquet=parquet_path,
                calibration=calibration,
                calibration_sha256=cal_sha,
                settings_sha256=set_sha,
                force=force,
                batch_rows=batch_rows,
                log=rel.as_posix(),
                on_mismatch=on_mismatch,
                source_url=source if is_remote else None,
                output_url=output_url,
                parquet_url=parquet_url,
                source=source if is_remote else "",
            )
        )
    return Plan(tasks, guard, out_url)


def plan_local(
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
        output, key = guard.check_resolved(out_dir / rel.with_name(rel.name + ".mcap"))
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
