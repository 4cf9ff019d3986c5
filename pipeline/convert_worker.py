"""One log of a conversion, in a worker: read, correct, write, verify, commit.

:func:`convert_log` reads the log, applies the calibration chain (``corrected = matrix @ (raw -
offset)`` for linear steps), writes the corrected MCAP (every other topic carried over), counts
the messages per topic in the written file and checks them against the input's own index
(:mod:`imupipe.pipeline.convert_verify`), then renames the outputs into place. It returns
statistics only.
"""

from __future__ import annotations

import collections
import resource
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa

from imupipe.pipeline.atomic import staged_outputs
from imupipe.pipeline.convert_dataset import DATASET_SCHEMA, dataset_table
from imupipe.pipeline.convert_done import existing_output, input_size
from imupipe.pipeline.convert_plan import LogTask
from imupipe.pipeline.convert_verify import (
    counts_by_topic,
    input_counts,
    mcap_counts,
    verify_counts,
)
from imupipe.pipeline.mcap_writer import McapTableWriter
from imupipe.readers import dispatch
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.stages.steps import apply_chain, steps_from_json

STREAMABLE_KINDS = {"linear"}
"""Step kinds that correct each sample from that sample alone, so a log can be corrected batch by
batch. Any other kind (e.g. ``temperature``) makes the log be corrected whole."""


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


def convert_log(task: LogTask) -> LogStats:
    """Convert one log (runs in a worker); raises ImupipeError on bad input."""
    start, cpu_start = time.perf_counter(), time.process_time()
    spec = task.spec
    src = Path(spec.path)
    fmt = dispatch.detect_format(src)
    size = input_size(src)
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
                        read.update(counts_by_topic(batch))
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
