"""A log corrected by a calibration chain and written as MCAP, streamed: memory bounded by a batch.

``write_corrected(path, spec, chain, calibration)`` reads the input in batches
(:func:`~imupipe.readers.dispatch.iter_input`), corrects them
(:func:`~imupipe.stages.steps.apply_chain_stream`: each step's ``apply_stream``) and writes them
with :class:`~imupipe.pipeline.writers.mcap.McapTableWriter`, every other topic carried over. The
writer's bytes do not depend on the batches, so for a log in time order the file equals, byte for
byte, the one written from the whole corrected table
(:func:`~imupipe.pipeline.writers.mcap.write_mcap`).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow as pa

from imupipe.pipeline.writers.mcap import SLICE_ROWS, McapTableWriter
from imupipe.readers.dispatch import iter_input
from imupipe.readers.spec import InputSpec
from imupipe.stages.steps import Step, apply_chain_stream


def write_corrected(
    path: Path,
    spec: InputSpec,
    chain: list[Step],
    calibration: dict[str, Any] | None,
    *,
    batch_rows: int = 200_000,
    slice_rows: int = SLICE_ROWS,
) -> dict[str, int]:
    """Write ``spec`` corrected by ``chain`` to ``path`` (``calibration``: the attached
    ``calibration.json``, None for none); returns messages per topic. ``batch_rows``: rows read
    at once; ``slice_rows``: rows encoded at once (see :class:`McapTableWriter`)."""
    with McapTableWriter(path, calibration=calibration, slice_rows=slice_rows) as writer:

        def batches() -> Iterator[pa.Table]:
            for table, carried in iter_input(spec, batch_rows=batch_rows):
                writer.write_raw(carried)  # before the rows that pass their log times
                yield table

        for corrected in apply_chain_stream(batches(), chain):
            writer.write_table(corrected)
    return writer.counts()
