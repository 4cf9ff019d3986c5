"""imupipe's own CSV: ``t_ns`` and the SI value columns of the sensors present (empty cell = no
sample of that sensor in the row; a sensor with no sample at all has no columns), plus
``ambient_temperature`` when present, written by pyarrow (shortest round-trip float formatting;
a NaN value is written as ``nan``)."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.csv as pacsv

from imupipe.readers.table import SENSOR_COLUMNS, has_sensor


def write_csv(path: str | Path, table: pa.Table) -> None:
    columns = ["t_ns"] + [
        c for s, cols in SENSOR_COLUMNS.items() if has_sensor(table, s) for c in cols
    ]
    columns += [c for c in ("ambient_temperature",) if c in table.column_names]
    pacsv.write_csv(
        table.select(columns).replace_schema_metadata(None),
        str(path),
        pacsv.WriteOptions(quoting_style="none", quoting_header="none"),
    )
