"""imupipe's own CSV: ``t_ns`` and the SI value columns of the streams present (empty cell = no
sample of that stream in the row), plus ``ambient_temperature`` when present, written by pyarrow
(shortest round-trip float formatting)."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.csv as pacsv

from imupipe.readers.table import SENSOR_COLUMNS, STREAM_OF_SENSOR, has_stream


def write_csv(path: str | Path, table: pa.Table) -> None:
    columns = ["t_ns"] + [
        c
        for s, cols in SENSOR_COLUMNS.items()
        if has_stream(table, STREAM_OF_SENSOR[s])
        for c in cols
    ]
    columns += [c for c in ("ambient_temperature",) if c in table.column_names]
    pacsv.write_csv(
        table.select(columns).replace_schema_metadata(None),
        str(path),
        pacsv.WriteOptions(quoting_style="none", quoting_header="none"),
    )
