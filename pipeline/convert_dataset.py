"""The Parquet dataset written by ``convert --parquet``: one file per log, one schema for all."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pyarrow as pa

from imupipe.readers.table import OPTIONAL_FIELDS, SCHEMA, metadata, with_metadata

DATASET_SCHEMA = pa.schema(list(SCHEMA) + list(OPTIONAL_FIELDS))
"""The Parquet files' schema: the common table with every optional column."""


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
