"""``imupipe convert``: apply a saved calibration to a fleet of logs, on this machine or on a Ray
cluster. :func:`convert` is the Python API; the command line is
:mod:`imupipe.pipeline.convert.cli`.

The work is split by responsibility:

- :mod:`~imupipe.pipeline.convert.settings`: the calibration and the read settings, their hashes;
- :mod:`~imupipe.pipeline.convert.plan`: finding the logs and their output paths;
- :mod:`~imupipe.pipeline.convert.worker`: one log (read, correct, write, verify, commit);
- :mod:`~imupipe.pipeline.convert.done`: skip-if-done;
- :mod:`~imupipe.pipeline.convert.verify`: the written file against the input's own index;
- :mod:`~imupipe.pipeline.convert.dataset`: the Parquet dataset;
- :mod:`~imupipe.pipeline.convert.remote`: logs, outputs and the manifest on object storage;
- this module: the driver (engine, progress, manifest).

**Resuming.** Outputs are written under temporary names and renamed when complete, so an
interrupted run leaves no half-written file and the next run picks up where it stopped (a log
already converted the same way is skipped). ``DIR/manifest.jsonl`` gets one line per log (see
:mod:`imupipe.pipeline.convert.manifest`).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from imupipe.pipeline.atomic import remove_stale_temps
from imupipe.pipeline.calibration_file import load_calibration
from imupipe.pipeline.convert.engines import Outcome, run_tasks
from imupipe.pipeline.convert.manifest import Manifest
from imupipe.pipeline.convert.options import DEFAULT_BATCH_ROWS, ON_MISMATCH, is_url, local_path
from imupipe.pipeline.convert.plan import LogTask, plan
from imupipe.pipeline.convert.provenance import fitted_on
from imupipe.pipeline.convert.settings import load_read_settings
from imupipe.pipeline.convert.worker import (
    OUTPUT_FAULTS,
    LogStats,
    OutputFolderError,
    convert_log,
)
from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.progress import progress_bar

if TYPE_CHECKING:
    from imupipe.pipeline.convert.remote import RemoteManifest

WORKER_PRELOAD = (
    "imupipe.readers.mcap.reader",
    "imupipe.readers.ros1.reader",
    "imupipe.readers.ros2.reader",
    "imupipe.readers.csv.reader",
    "rosbags.typesys.stores.ros2_humble",
    "rosbags.typesys.stores.ros1_noetic",
)
"""Imported once by the local pool's fork server, so that no worker pays for them on its first
log (the readers are otherwise imported lazily; the ROS 2 type store, ~0.15 s, makes the MCAP
schemas)."""


ENGINE_LOG = "ray.log"
"""With ``--engine ray``: ``DIR/ray.log`` takes Ray's own output (named in each manifest line's
``engine_log``), so the user's stderr holds imupipe's lines only; with ``--out`` on an object
store, ``$TMPDIR/imupipe-convert-<pid>-ray.log`` on the driver's machine."""


@dataclass
class ConvertSummary:
    out_dir: Path | str
    """The output folder (a URL when ``--out`` is on an object store)."""
    converted: list[LogStats] = field(default_factory=list)
    skipped: list[LogStats] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    """(input, why) of each log that could not be converted."""
    seconds: float = 0.0

    @property
    def messages(self) -> int:
        return sum(s.messages for s in self.converted)


def check_options(
    engine: str,
    jobs: int | None,
    retries: int,
    batch_rows: int,
    address: str | None,
    dashboard: bool,
    on_mismatch: str,
) -> None:
    """ConfigError (the command line's one line, named by its option) for a wrong option of
    :func:`convert`, from the command line or the Python API."""
    from imupipe.pipeline.convert.options import ENGINES

    def whole(value: object) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    if engine not in ENGINES:
        raise ConfigError(f"--engine {engine}: must be one of {', '.join(ENGINES)}")
    if on_mismatch not in ON_MISMATCH:
        raise ConfigError(f"--on-mismatch {on_mismatch}: must be one of {', '.join(ON_MISMATCH)}")
    if jobs is not None and (not whole(jobs) or jobs < 1):
        raise ConfigError(f"--jobs {jobs}: must be at least 1")
    if not whole(batch_rows) or batch_rows < 1:
        raise ConfigError(f"--batch-rows {batch_rows}: must be at least 1")
    if not whole(retries) or retries < 0:
        raise ConfigError(f"--retries {retries}: must be at least 0")
    if address is not None and engine != "ray":
        raise ConfigError("--address is for --engine ray")
    if dashboard and (engine != "ray" or address is not None):
        raise ConfigError("--dashboard is for --engine ray without --address")


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
    dashboard: bool = False,
    on_mismatch: str = "warn",
    read_truncated: bool = False,
) -> ConvertSummary:
    """Convert every log under ``logs`` (files or folders) into ``out_dir``: each log read,
    corrected by the chain of ``calibration`` (a ``calibration.json``) and written as MCAP (or a
    Parquet dataset with ``parquet``), resuming where an interrupted conversion stopped (see the
    module docstring). The keywords are the options of ``imupipe convert``: ``config`` (a TOML
    file whose ``[inputs.NAME]`` settings say how to read the logs), ``engine`` (``local`` or
    ``ray``), ``jobs``, ``address``, ``retries``, ``force``, ``batch_rows``, ``on_mismatch``
    (``warn`` or ``refuse``: a log from another sensor than the calibration's). ``logs`` and
    ``out_dir`` may be URLs (``s3://bucket/prefix``, :mod:`imupipe.pipeline.convert.remote`).

    Raises :class:`~imupipe.pipeline.errors.ImupipeError` before anything is written when the
    plan is wrong (no logs, an output over an input or outside ``out_dir``, an output folder
    that cannot be written), and :class:`OutputFolderError` when the output folder fails during
    the run (full, read-only): the other logs are stopped, the same command resumes."""
    check_options(engine, jobs, retries, batch_rows, address, dashboard, on_mismatch)
    start = time.perf_counter()
    remote = None  # --out on an object store only (issue 39: not on a local conversion's cost)
    if is_url(out_dir):
        from imupipe.pipeline.convert import remote
    out_url = None if remote is None else remote.check_url(out_dir, "--out")
    out: Path | str = local_path(out_dir) if out_url is None else out_url
    doc, _ = load_calibration(Path(calibration))
    settings = load_read_settings(None if config is None else Path(config))
    if read_truncated:  # an MCAP or ROS 1 log cut off is read up to the cut, with a warning
        settings = dataclasses.replace(settings, read_truncated=True)
    planned = plan(
        list(logs),
        out,
        doc,
        settings,
        parquet=parquet,
        force=force,
        batch_rows=batch_rows,
        csv=config is not None,
        on_mismatch=on_mismatch,
    )
    tasks, guard = planned.tasks, planned.guard
    summary = ConvertSummary(out_dir=out)
    if not tasks:
        raise ConfigError(f"no logs found in {', '.join(map(str, logs))}")
    if on_mismatch not in ON_MISMATCH:
        raise ConfigError(f"--on-mismatch {on_mismatch}: not one of {', '.join(ON_MISMATCH)}")
    manifest: Manifest | RemoteManifest
    engine_log: Path | None = None
    if guard is not None:
        manifest = Manifest(out, guard)  # checked by the path rule before anything is written
        engine_log = guard.check(ENGINE_LOG, in_place=True) if engine == "ray" else None
        guard.probe()
    else:  # --out on an object store: Ray's own output goes to a file of the driver's machine
        assert remote is not None and out_url is not None
        remote.probe(out_url)
        manifest = remote.RemoteManifest(out_url)
        if engine == "ray":
            import tempfile

            engine_log = Path(tempfile.gettempdir()) / f"imupipe-convert-{os.getpid()}-{ENGINE_LOG}"
    if not fitted_on(doc["chain"]) and not quiet:
        print(
            f"imupipe: note: {calibration} does not record which sensor it was fitted on "
            "(written by an older imupipe): the logs are not checked against it",
            file=sys.stderr,
        )
    # temporary files of workers killed in an earlier run (on this machine, or on any Ray node:
    # no worker of this run has started yet, and one conversion at a time writes into DIR), in
    # the folders this run writes into only
    for folder in planned.folders():
        remove_stale_temps(folder, other_hosts=True)
    for prefix in planned.remote_folders() if remote is not None else ():
        remote.remove_stale_temps(prefix)
    fatal: list[str] = []
    converted_messages = 0  # the bar's running count (summary.messages sums every log: O(logs))
    with progress_bar("imupipe convert", total=len(tasks), quiet=quiet, unit="logs") as bar:

        def on_done(outcome: Outcome) -> None:
            nonlocal converted_messages
            task: LogTask = outcome.task
            record: dict[str, Any] = {
                "attempts": outcome.attempts,
                "host": outcome.host,
                "engine_log": None if engine_log is None else str(engine_log),
            }
            if outcome.error is None:
                stats: LogStats = outcome.result
                (summary.converted if stats.status == "converted" else summary.skipped).append(
                    stats
                )
                record.update(dataclasses.asdict(stats), messages=stats.messages)
                if stats.status == "converted":
                    converted_messages += stats.messages
                if not quiet:
                    for w in stats.warnings:
                        where = "" if w.startswith(f"{stats.input}: ") else f"{stats.input}: "
                        print(f"imupipe: warning: {where}{w}", file=sys.stderr)
            else:
                name = task.source or str(task.spec.path)
                summary.failed.append((name, outcome.error))
                record.update(
                    input=name,
                    status="failed",
                    error=outcome.error,
                    calibration_sha256=task.calibration_sha256,
                )
            try:
                manifest.append(record)
            except OSError as exc:  # the manifest is on the output folder's disk too
                if exc.errno not in OUTPUT_FAULTS:
                    raise
                if not outcome.fatal:
                    fatal.append(f"{manifest.path}: {OUTPUT_FAULTS[exc.errno]}")
                    raise _Stop() from None
            bar.advance()
            bar.describe(f"imupipe convert: {converted_messages:,} messages")
            if outcome.fatal:
                fatal.append(outcome.error or "")
                raise _Stop()

        try:
            with bar.listen(within_items=True):  # a log converted here (one, --jobs 1): bytes
                run_tasks(
                    convert_log,
                    tasks,
                    on_done,
                    engine=engine,
                    jobs=jobs,
                    address=address,
                    retries=retries,
                    preload=WORKER_PRELOAD,
                    dashboard=dashboard,
                    engine_log=engine_log,
                )
        except _Stop:
            done = len(summary.converted) + len(summary.skipped)
            raise OutputFolderError(
                f"{fatal[0]} ({done} of {len(tasks)} logs done; "
                "the same command resumes where this one stopped)"
            ) from None
        finally:  # also on SIGINT/SIGTERM: what stopped workers could not remove
            for folder in planned.folders():
                remove_stale_temps(folder)
            if remote is not None:  # temporaries of workers killed while publishing
                for prefix in planned.remote_folders():
                    remote.remove_stale_temps(prefix)
                if isinstance(manifest, remote.RemoteManifest):
                    manifest.flush()
    summary.seconds = time.perf_counter() - start
    return summary


class _Stop(Exception):
    """Raised in ``on_done`` to stop the engine (its workers are stopped)."""
