"""CSV (and whitespace ASCII, e.g. imu_tk's ``.mat``) into the common table, via pyarrow's reader.

Mapping and units per :class:`~imupipe.readers.spec.CsvMapping`. A cell left empty means "no
sample of that stream in this row" (so one CSV can hold streams at different rates). Time comes
from the time column (s/ms/us/ns) or, with ``rate_hz``, from the row number.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv

from imupipe.readers.errors import ReadError
from imupipe.readers.spec import (
    ACCEL_UNITS,
    GYRO_UNITS,
    MAG_UNITS,
    TIME_UNITS,
    CsvMapping,
    InputSpec,
)
from imupipe.readers.table import make_table, sort_by_time

_NUMBER = r"^\s*[-+]?(\d+\.?\d*([eE][-+]?\d+)?|\.\d+([eE][-+]?\d+)?|nan|NaN|inf|-inf|Inf)\s*$"


def _sniff(first_line: str, mapping: CsvMapping) -> tuple[str, bool]:
    delimiter = mapping.delimiter
    if delimiter == "auto":
        for cand in (",", ";", "\t"):
            if cand in first_line:
                delimiter = cand
                break
        else:
            delimiter = "whitespace"
    if delimiter == "\\t":
        delimiter = "\t"
    cells = first_line.split() if delimiter == "whitespace" else first_line.split(delimiter)
    header = mapping.header
    if header is None:
        header = any(c.strip() and not re.match(_NUMBER, c) for c in cells)
    return delimiter, header


def _first_line(path: Path) -> str:
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError as exc:
        raise ReadError(f"{path}: cannot read: {exc.strerror or exc}") from None
    text = head.lstrip().decode("utf-8", errors="replace")
    return text.splitlines()[0] if text.strip() else ""


def _raw_table(path: Path, mapping: CsvMapping) -> tuple[pa.Table, bool]:
    first_line = _first_line(path)
    if not first_line.strip():
        raise ReadError(f"{path}: the file is empty")
    delimiter, header = _sniff(first_line, mapping)
    source: str | io.BytesIO = str(path)
    if delimiter == "whitespace":  # runs of spaces/tabs: normalise to commas (C-speed regex)
        data = re.sub(rb"(?m)^[ \t]+", b"", path.read_bytes())
        source = io.BytesIO(re.sub(rb"[ \t]+", b",", data))
        del data
        delimiter = ","
    read = pacsv.ReadOptions(autogenerate_column_names=not header, block_size=1 << 22)
    parse = pacsv.ParseOptions(delimiter=delimiter)
    convert = pacsv.ConvertOptions(strings_can_be_null=True)
    try:
        # streamed in blocks: the peak stays near the table's size, not the text's
        table = pacsv.open_csv(source, read, parse, convert).read_all()
    except pa.ArrowInvalid:
        # types inferred from the first block did not fit a later one (or a cell is bad):
        # read whole, so the offending row can be named
        if isinstance(source, io.BytesIO):
            source.seek(0)
        try:
            table = pacsv.read_csv(source, read, parse, convert)
        except pa.ArrowInvalid as exc:
            raise ReadError(f"{path}: not a readable CSV: {str(exc).splitlines()[0]}") from None
    if not header:
        table = table.rename_columns([str(i) for i in range(table.num_columns)])
    return table, header


def _column(table: pa.Table, path: Path, key: str, name: str | int, header: bool) -> pa.Array:
    col = str(name)
    if col not in table.column_names:
        have = ", ".join(table.column_names[:20])
        what = f"column '{col}'" if header else f"column index {col}"
        raise ReadError(f"{path}: {what} (csv.{key}) not found; the file has: {have}")
    array = table.column(col)
    if pa.types.is_floating(array.type) or pa.types.is_integer(array.type):
        return array.cast(pa.float64()) if not pa.types.is_integer(array.type) else array
    if pa.types.is_null(array.type):
        return pa.nulls(len(array), pa.float64())
    strings = array.cast(pa.string())
    ok = pc.or_(pc.is_null(strings), pc.match_substring_regex(strings, _NUMBER))
    bad = np.flatnonzero(~ok.to_numpy(zero_copy_only=False))
    if len(bad):
        row = int(bad[0]) + (2 if header else 1)
        value = strings[int(bad[0])].as_py()
        raise ReadError(f"{path}: row {row}, column '{col}': '{value}' is not a number")
    return pc.cast(pc.utf8_trim_whitespace(strings), pa.float64())


def _column_text(table: pa.Table, path: Path, name: str | int, header: bool) -> pa.Array:
    """A column as text (the ``label`` key): numbers are kept as their text."""
    col = str(name)
    if col not in table.column_names:
        what = f"column '{col}'" if header else f"column index {col}"
        raise ReadError(
            f"{path}: {what} (csv.label) not found; the file has: {', '.join(table.column_names[:20])}"
        )
    return table.column(col).cast(pa.string())


def _gyro_from_file(path: Path, m: CsvMapping, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """The gyro columns of ``csv.gyro_file``, which must have as many rows as the main file."""
    raw, header = _raw_table(path, m)
    if raw.num_rows != rows:
        raise ReadError(
            f"{path}: csv.gyro_file has {raw.num_rows} rows, the main file {rows}; "
            "they must match row for row"
        )
    if m.gyro is None or len(m.gyro) != 3:
        raise ReadError(f"{path}: csv.gyro must name 3 columns of csv.gyro_file")
    cols = [_column(raw, path, "gyro", n, header) for n in m.gyro]
    return _scaled(cols, _unit(path, "gyro_unit", m.gyro_unit, GYRO_UNITS))


def _scaled(columns: list[pa.Array], factor: float) -> tuple[np.ndarray, np.ndarray]:
    values = np.empty((len(columns[0]), len(columns)), dtype=np.float64)
    for i, column in enumerate(columns):
        values[:, i] = column.to_numpy(zero_copy_only=False)
    if factor != 1.0:
        values *= factor
    # a row holds a sample where any axis has a value; an empty cell beside it is NaN (kept)
    valid = np.column_stack([pc.is_valid(c).to_numpy(zero_copy_only=False) for c in columns]).any(
        axis=1
    )
    return values, valid


def _unit(path: Path, key: str, unit: str, table: dict[str, float]) -> float:
    if unit not in table:
        raise ReadError(f"{path}: csv.{key} = '{unit}' is not one of {', '.join(table)}")
    return table[unit]


def read_csv(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a CSV input into the common table. Returns the table and any warnings."""
    path = Path(spec.path)
    m = spec.csv
    raw, header = _raw_table(path, m)
    if raw.num_rows == 0:
        raise ReadError(f"{path}: the file has a header but no rows")
    warnings: list[str] = []

    def vector(
        key: str, unit_key: str, units: dict[str, float]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        names = getattr(m, key)
        if names is None:
            return None
        if len(names) != 3:
            raise ReadError(f"{path}: csv.{key} must name 3 columns, got {len(names)}")
        present = [str(n) in raw.column_names for n in names]
        if not any(present) and key not in m.required:
            return None
        cols = [_column(raw, path, key, n, header) for n in names]
        return _scaled(cols, _unit(path, unit_key, getattr(m, unit_key), units))

    gyro = vector("gyro", "gyro_unit", GYRO_UNITS)
    if m.gyro_file is not None:
        gyro = _gyro_from_file(Path(m.gyro_file), m, raw.num_rows)
    accel = vector("accel", "accel_unit", ACCEL_UNITS)
    mag = vector("mag", "mag_unit", MAG_UNITS)
    temperature = None
    if m.temperature is not None and (
        str(m.temperature) in raw.column_names or "temperature" in m.required
    ):
        temperature = _scaled([_column(raw, path, "temperature", m.temperature, header)], 1.0)
    if gyro is None and accel is None and mag is None and temperature is None:
        raise ReadError(
            f"{path}: no mapped column found (gyro {m.gyro}, accel {m.accel}, mag {m.mag}); "
            f"the file has: {', '.join(raw.column_names[:20])}; set [inputs.{spec.name}.csv]"
        )

    n = raw.num_rows
    labels = None
    if m.label is not None:
        labels = _column_text(raw, path, m.label, header)
    extra: dict[str, pa.Array] = {} if labels is None else {"label": labels}
    if m.ambient_temperature is not None and (
        str(m.ambient_temperature) in raw.column_names or "ambient_temperature" in m.required
    ):
        extra["ambient_temperature"] = _column(
            raw, path, "ambient_temperature", m.ambient_temperature, header
        )
    if m.rate_hz is not None:
        if m.rate_hz <= 0:
            raise ReadError(f"{path}: csv.rate_hz must be > 0")
        t_ns = np.round(np.arange(n) * (1e9 / m.rate_hz)).astype(np.int64)
    elif m.time is not None:
        scale = _unit(path, "time_unit", m.time_unit, TIME_UNITS)
        tcol = _column(raw, path, "time", m.time, header)
        if tcol.null_count:
            row = int(np.flatnonzero(~pc.is_valid(tcol).to_numpy(zero_copy_only=False))[0])
            raise ReadError(
                f"{path}: row {row + (2 if header else 1)}, column '{m.time}': empty time"
            )
        if pa.types.is_integer(tcol.type) and scale == 1.0:
            t_ns = tcol.to_numpy().astype(np.int64)
        else:
            t_ns = np.round(tcol.to_numpy(zero_copy_only=False).astype(np.float64) * scale).astype(
                np.int64
            )
    else:
        raise ReadError(f"{path}: no time column and no csv.rate_hz")
    raw = tcol = None  # free the parsed columns before the table is built (peak memory)

    # each sensor keeps its own validity: a row with gyro but no accel (or a file with only one
    # of them) is an IMU sample whose other sensor is absent (null), never zeros
    table = make_table(
        t_ns,
        gyro=None if gyro is None else gyro[0],
        accel=None if accel is None else accel[0],
        mag=None if mag is None else mag[0],
        temperature=None if temperature is None else temperature[0][:, 0],
        valid={
            "gyro": gyro[1] if gyro is not None else np.zeros(n, bool),
            "accel": accel[1] if accel is not None else np.zeros(n, bool),
            "mag": mag[1] if mag is not None else np.zeros(n, bool),
            "temperature": temperature[1] if temperature is not None else np.zeros(n, bool),
        },
        extra=extra or None,
        metadata={"source": str(path), "format": "csv", "topics": {}, "types": {}, "frame_id": {}},
    )
    table, moved = sort_by_time(table)
    if moved:
        warnings.append(
            f"{path}: {moved} rows were out of time order; sorted stably (none dropped)"
        )
    return table, warnings
