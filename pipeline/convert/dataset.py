"""The Parquet dataset written by ``convert --parquet``: ``DIR/parquet/<log>.parquet``.

One file per log (a log found in a sub-folder keeps it: ``DIR/parquet/robot1/day1.parquet``),
all with one schema, alone in their folder, so that each of these opens the whole dataset in
one call::

    pyarrow.dataset.dataset("DIR/parquet", format="parquet")
    polars.scan_parquet("DIR/parquet/**/*.parquet")
    duckdb.read_parquet("DIR/parquet/**/*.parquet")

**Schema.** The common table with every optional column (absent ones null), plus ``log`` (the
log's name, its output path without suffix: which log a row came from). ``t_ns`` and
``log_time_ns`` are ``timestamp[ns, tz=UTC]`` (nanoseconds since the UNIX epoch for ROS and MCAP
stamps; for a CSV whose clock starts at zero, since that zero). Every value column carries its
unit as field metadata ``unit`` (SI: ``rad/s``, ``m/s^2``, ``T``, ``degC``; covariances in the
square of their sensor's unit). The file's schema metadata ``imupipe`` (JSON) holds the log's
source, format, topics, types and frames, and ``calibration``: the whole calibration applied,
with its ``conversion`` record (the chain's SHA-256, the input, its size).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pyarrow as pa

from imupipe.readers.table import OPTIONAL_FIELDS, SCHEMA, SENSOR_UNITS, metadata, with_metadata

TIME = pa.timestamp("ns", tz="UTC")

UNITS: dict[str, str] = {
    **{f"{s}_{a}": SENSOR_UNITS[s] for s in ("gyro", "accel", "mag") for a in "xyz"},
    "temperature": SENSOR_UNITS["temperature"],
    "ambient_temperature": SENSOR_UNITS["temperature"],
    "pressure": "Pa",
    "orientation_x": "1",
    "orientation_y": "1",
    "orientation_z": "1",
    "orientation_w": "1",
    "orientation_cov": "rad^2",
    "gyro_cov": "(rad/s)^2",
    "accel_cov": "(m/s^2)^2",
    "mag_cov": "T^2",
    "temperature_var": "degC^2",
    "t_ns": "ns",
    "log_time_ns": "ns",
}
"""Each column's unit, written as the Parquet field's ``unit`` metadata."""


def _field(f: pa.Field) -> pa.Field:
    kind = TIME if f.name in ("t_ns", "log_time_ns") else f.type
    unit = UNITS.get(f.name)
    return pa.field(f.name, kind, f.nullable, None if unit is None else {"unit": unit})


DATASET_SCHEMA = pa.schema(
    [_field(f) for f in list(SCHEMA) + list(OPTIONAL_FIELDS)] + [pa.field("log", pa.string())]
)
"""The Parquet files' schema: the common table with every optional column, times as timestamps,
units as field metadata, and the log's name."""


def dataset_table(table: pa.Table, log: str, calibration: Mapping[str, Any]) -> pa.Table:
    """``table`` in :data:`DATASET_SCHEMA` (absent optional columns null), its rows labelled
    ``log``; its imupipe metadata (source, topics, ...) gets the ``calibration`` applied."""
    columns = []
    for f in DATASET_SCHEMA:
        if f.name == "log":
            columns.append(pa.repeat(pa.scalar(log, pa.string()), len(table)))
        elif f.name in table.column_names:
            columns.append(table.column(f.name).cast(f.type))
        else:
            columns.append(pa.nulls(len(table), f.type))
    return with_metadata(
        pa.Table.from_arrays(columns, schema=DATASET_SCHEMA),
        {**metadata(table), "calibration": dict(calibration)},
    )
