"""One log of a conversion, in a worker: read, correct, write, verify, commit.

:func:`convert_log` reads the log, applies the calibration chain (``corrected = matrix @ (raw -
offset)`` for linear steps), writes the corrected MCAP (every other topic carried over), counts
the messages per topic in the written file and checks them against the input's own index
(:mod:`imupipe.pipeline.convert.verify`), then renames the outputs into place. It returns
statistics only.

**Every chain streams.** The log is read with :func:`imupipe.readers.dispatch.iter_input` in
batches of about ``batch_rows`` rows, corrected with
:func:`imupipe.stages.steps.apply_chain_stream` (each step's ``apply_stream``: a step that needs
context beyond one sample, such as the temperature step, holds rows back until their context has
arrived) and written batch by batch with :class:`~imupipe.pipeline.writers.mcap.McapTableWriter`,
so a worker's memory is bounded by the batch, not by the log. The other topics' messages are
written as they are read.
"""

from __future__ import annotations

import collections
import contextlib
import copy
import errno
import os
import resource
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

from imupipe.pipeline.atomic import HOST_KEY, staged_outputs
from imupipe.pipeline.calibration_file import on_device
from imupipe.pipeline.convert.done import existing_output, input_size
from imupipe.pipeline.convert.plan import LogTask
from imupipe.pipeline.convert.provenance import ProvenanceCheck
from imupipe.pipeline.convert.verify import (
    counts_by_topic,
    input_counts,
    lost_topics,
    mcap_counts,
    not_carried,
    source_counts,
    verify_counts,
)
from imupipe.pipeline.errors import ImupipeError, ReadError
from imupipe.pipeline.writers.mcap import McapTableWriter
from imupipe.readers import dispatch
from imupipe.readers.spec import RawMessage
from imupipe.readers.table import SCHEMA, STREAM_OF_SENSOR, STREAM_SENSORS, has_stream, metadata
from imupipe.readers.topics import NOT_CARRIED
from imupipe.stages.steps import apply_chain_stream, steps_from_json

OUTPUT_FAULTS = {
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EFBIG: "file too large for the file system",
}
"""File-system errors that hit every log alike when they come from the output folder."""


class OutputFolderError(ImupipeError):
    """The output folder cannot take the outputs (full, read-only, no permission): every other
    log would fail the same way, so the conversion stops (``fatal``)."""

    fatal = True


def _os_fault(exc: OSError, task: LogTask) -> BaseException:
    """The error to raise for a file-system error while converting ``task``: the output folder's
    faults are fatal, the input's are final for this log, others are retried (unchanged)."""
    where = None if exc.filename is None else Path(exc.filename).absolute()
    src = Path(task.spec.path).absolute()
    outs = [task.output.parent] + ([task.parquet.parent] if task.parquet is not None else [])
    if where is not None and (where == src or where.is_relative_to(src)):
        return ReadError(f"{src}: cannot read: {exc.strerror or exc}")
    if exc.errno in OUTPUT_FAULTS:
        out = next((o for o in outs if where is None or where.is_relative_to(o)), None)
        if out is not None:
            return OutputFolderError(f"{out}: {OUTPUT_FAULTS[exc.errno]}")
    return exc


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
    mode: str  # streamed | - (skipped)
    peak_rss_mb: float
    warnings: list[str] = field(default_factory=list)
    provenance: str = "-"
    """``match``, ``mismatch: ...`` or ``unknown`` (see :mod:`convert_provenance`); ``-`` when
    skipped."""
    not_carried: dict[str, int] = field(default_factory=dict)
    """Every topic of the log the corrected MCAP does not carry, with its message count (the
    warning names the largest few)."""

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def _tables(
    pairs: Iterable[tuple[pa.Table, list[RawMessage]]],
    carried: list[RawMessage],
    read: collections.Counter[str],
    provenance: ProvenanceCheck,
    warnings: list[str],
    streams: set[str],
) -> Iterator[pa.Table]:
    """The table batches of ``iter_input``'s pairs; each batch's carried-over messages are
    appended to ``carried`` (for the writer), every message is counted in ``read``, the streams
    with samples are added to ``streams`` and each batch's topics and frames are checked against
    the calibration's provenance."""
    for table, raw in pairs:
        warnings += provenance.check(metadata(table))
        streams.update(s for s in STREAM_SENSORS if s not in streams and has_stream(table, s))
        raw = list(raw)
        read.update(counts_by_topic(table))
        read.update(m.topic for m in raw)
        carried.extend(raw)
        yield table


def _nothing_applies(chain: list[dict[str, Any]], streams: set[str]) -> list[str]:
    """A warning when no step of ``chain`` corrects a sensor the log has samples of (a
    magnetometer calibration on a log without a magnetometer): the log is written as it came."""
    sensors = sorted({str(e.get("sensor")) for e in chain if e.get("sensor") in STREAM_OF_SENSOR})
    if not sensors or any(STREAM_OF_SENSOR[s] in streams for s in sensors):
        return []
    return [
        f"no step of the calibration applies (it corrects {', '.join(sensors)}; the log has no "
        f"{' or '.join(sensors)} samples): written uncorrected"
    ]


def convert_log(task: LogTask) -> LogStats:
    """Convert one log (runs in a worker); raises ImupipeError on bad input, and
    :class:`OutputFolderError` when the output folder cannot take the outputs. A log or an
    output on an object store goes through :func:`convert_remote`."""
    if task.source_url is not None or task.output_url is not None:
        return convert_remote(task)
    return _convert_local(task)


def _convert_local(task: LogTask) -> LogStats:
    try:
        return _convert_log(task)
    except OSError as exc:
        fault = _os_fault(exc, task)
        if fault is exc:
            raise
        raise fault from None


_STEPS: list[tuple[list, list]] = []
"""The last calibration chain and its steps: a fleet's logs share one chain, and rebuilding its
steps took 0.16 ms a log (issue 39). Steps keep no state between logs (a streamed step's state
lives in its ``apply_stream`` generator)."""


def _steps(task: LogTask) -> list:
    """The steps of ``task``'s calibration chain, each on its device (built again only for
    another chain than the last)."""
    chain = task.calibration["chain"]
    if not _STEPS or _STEPS[0][0] != chain:
        _STEPS[:] = [(copy.deepcopy(chain), on_device(steps_from_json(chain), chain, lenient=True))]
    return _STEPS[0][1]


def _convert_log(task: LogTask) -> LogStats:
    start, cpu_start = time.perf_counter(), time.process_time()
    spec = task.spec
    src = Path(spec.path)
    fmt = dispatch.detect_format(src)
    size = input_size(src)
    mode, warnings, checked = "-", [], "-"
    dropped: dict[str, int] = {}
    found = None if task.force else existing_output(task, size)
    if found is not None:
        status, written = "skipped", found
    else:
        steps = _steps(task)
        mode = "streamed"
        expected = input_counts(src, fmt, warnings, spec.read_truncated)
        doc = {
            **task.calibration,
            "conversion": {
                "calibration_sha256": task.calibration_sha256,
                "settings_sha256": task.settings_sha256,
                "input": task.source or str(src),
                "input_size": size,
            },
        }
        read: collections.Counter[str] = collections.Counter()
        provenance = ProvenanceCheck(task.calibration["chain"], task.on_mismatch, str(src))
        with staged_outputs() as out:
            mcap_tmp = out.path(task.output)
            parquet_tmp = None if task.parquet is None else out.path(task.parquet)
            parquet = None
            if parquet_tmp is not None:  # builds its schema at import: --parquet only (issue 39)
                from imupipe.pipeline.convert.dataset import dataset_table
            try:
                with McapTableWriter(mcap_tmp, calibration=doc) as writer:
                    carried: list[RawMessage] = []
                    pairs = dispatch.iter_input(spec, batch_rows=task.batch_rows, warnings=warnings)
                    streams: set[str] = set()
                    batches = _tables(pairs, carried, read, provenance, warnings, streams)
                    for corrected in apply_chain_stream(batches, steps):
                        writer.write_table(corrected)
                        writer.write_raw(carried)
                        carried.clear()
                        if parquet_tmp is not None:
                            rows = dataset_table(corrected, task.log, doc)
                            if parquet is None:
                                import pyarrow.parquet as pq

                                parquet = pq.ParquetWriter(
                                    parquet_tmp, rows.schema, compression="zstd"
                                )
                            parquet.write_table(rows)
                    writer.write_raw(carried)
            finally:
                if parquet is not None:
                    parquet.close()
            if parquet_tmp is not None and parquet is None:  # a log without samples
                import pyarrow.parquet as pq

                pq.write_table(dataset_table(SCHEMA.empty_table(), task.log, doc), parquet_tmp)
            written = mcap_counts(mcap_tmp) or {}
            warnings += _nothing_applies(task.calibration["chain"], streams)
            verify_counts(src, expected if expected is not None else read, written)
            in_log = source_counts(src, fmt)
            dropped = lost_topics(in_log, written)
            lost = not_carried(fmt, in_log, written)
            if lost:  # the count of what is not carried replaces the reader's note of it
                warnings[:] = [w for w in warnings if NOT_CARRIED not in w]
            warnings += lost
        status, checked = "converted", provenance.status
    return LogStats(
        input=task.source or str(src),
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
        provenance=checked,
        not_carried=dropped,
    )


COPY_PREFIX = "imupipe-convert-"
"""The local copies of a remote log live in ``$TMPDIR/imupipe-convert-<pid>@<host key>-*``."""


def remove_stale_copies() -> list[Path]:
    """Remove the folders of local copies (:data:`COPY_PREFIX`) of this machine's workers that
    no longer run (a worker killed by SIGKILL cannot remove its own)."""
    import re
    import shutil
    import tempfile

    from imupipe.pipeline.atomic import _alive

    pattern = re.compile(rf"^{COPY_PREFIX}(?P<pid>\d+)@{HOST_KEY}-[a-z0-9_]+$")
    root = Path(tempfile.gettempdir())
    removed = []
    with contextlib.suppress(OSError):
        for name in os.listdir(root):
            m = pattern.match(name)
            if m is None or int(m["pid"]) == os.getpid() or _alive(int(m["pid"])):
                continue
            path = root / name
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
    return removed


def convert_remote(task: LogTask) -> LogStats:
    """Convert a log whose input or output is an object (:mod:`imupipe.pipeline.convert.remote`):
    skip it when its published output already holds it converted the same way; else copy the
    input to a local temporary folder (bounded memory), convert it there exactly as a local log
    (write, verify the counts), then publish the outputs (the Parquet file first, the MCAP that
    marks the log done last). Errors name the URL, not the local copy."""
    import dataclasses
    import shutil
    import tempfile

    from imupipe.pipeline.convert import remote
    from imupipe.pipeline.convert.done import same_conversion

    start, cpu_start = time.perf_counter(), time.process_time()
    remove_stale_copies()
    tmp = Path(tempfile.mkdtemp(prefix=f"{COPY_PREFIX}{os.getpid()}@{HOST_KEY}-"))
    src_name = task.source_url or str(task.spec.path)
    local_src = Path(task.spec.path)
    try:
        if task.source_url is not None:
            size = remote.object_size(task.source_url)
            if size is None:
                raise ReadError(f"{task.source_url}: no such object")
        else:
            size = input_size(local_src)
        found = None
        if task.output_url is not None and not task.force:
            try:
                summary = remote.read_mcap_summary(task.output_url)
            except Exception:  # noqa: BLE001 - an unreadable output is simply not done
                summary = None
            parquet_there = task.parquet_url is None or remote.object_size(task.parquet_url)
            found = None if parquet_there is None else same_conversion(summary, task, size)
        elif not task.force:
            found = existing_output(task, size)
        if found is not None:
            return LogStats(
                input=src_name,
                output=task.output_url or str(task.output),
                parquet=task.parquet_url or (None if task.parquet is None else str(task.parquet)),
                status="skipped",
                counts=found,
                calibration_sha256=task.calibration_sha256,
                seconds=round(time.perf_counter() - start, 4),
                cpu_seconds=round(time.process_time() - cpu_start, 4),
                mode="-",
                peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            )
        if task.source_url is not None:
            local_src = tmp / "in" / task.spec.path.name
            remote.download(task.source_url, local_src)
        out_dir = tmp / "out"
        local = dataclasses.replace(
            task,
            spec=dataclasses.replace(task.spec, path=local_src),
            output=out_dir / task.output.name if task.output_url else task.output,
            parquet=None
            if task.parquet is None
            else (out_dir / "parquet" / task.parquet.name if task.output_url else task.parquet),
            force=True,  # judged above
            source_url=None,
            output_url=None,
            parquet_url=None,
            source=src_name,
        )
        try:
            stats = _convert_local(local)
        except ImupipeError as exc:
            message = str(exc).replace(str(local_src), src_name).replace(str(tmp), "(local copy)")
            if message == str(exc):
                raise
            raise type(exc)(message) from None
        if task.output_url is not None and stats.status == "converted":
            items = [] if local.parquet is None else [(local.parquet, task.parquet_url or "")]
            remote.publish([*items, (local.output, task.output_url)])
        if task.output_url is not None:
            stats.output, stats.parquet = task.output_url, task.parquet_url
        stats.seconds = round(time.perf_counter() - start, 4)
        stats.cpu_seconds = round(time.process_time() - cpu_start, 4)
        return stats
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
