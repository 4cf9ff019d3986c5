"""CSV (and blank-separated text, e.g. imu_tk's ``.mat``) into the common table.

Mapping and units per :class:`~imupipe.readers.spec.CsvMapping`. Three steps:

1. **Layout** (:func:`imupipe.readers.csv.layout.sniff`, the file's first 64 KiB): delimiter,
   decimal point, metadata lines before the header, the header, a trailing delimiter.
2. **Parse**: one multithreaded :func:`pyarrow.csv.read_csv` of the mapped columns only
   (``include_columns``), value columns as float64, a time column in ns as int64; other time
   units, and an ns column with a cell such as ``1.7e18``, go through an exact decimal parse
   (:mod:`imupipe.readers.csv.exact_time`), never through float64.
3. **Table**: each sensor's columns are scaled in place into SI (``scale``, ``offset``, then the
   unit) in column-major arrays that the common table takes without a further copy.

**Empty cells and NaN.** An empty cell holds no value. A row holds an IMU sample when any of its
gyro or accel cells holds a value (text ``nan`` is a value); the sample's empty cells are NaN,
and the samples with NaN are counted in one warning (stages fit on the finite samples; writers
keep every sample). Likewise a magnetometer sample; a temperature sample is its one cell. A row
whose cells of a stream are all empty has no sample of it: one CSV can hold streams at
different rates. Time comes from the time column (s/ms/us/ns) or, with ``rate_hz`` (or a rate
line in the metadata), from the row number.

Every problem is a :class:`~imupipe.readers.errors.ReadError` naming the file, and the line and
column where there is one.
"""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from imupipe.readers.arrays import valid_mask
from imupipe.readers.csv.exact_time import TimeCellError, scaled_ns, text_to_ns
from imupipe.readers.csv.layout import Layout, line_of_row, line_with_fields, sniff
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
from imupipe.readers.table_buffer import small_pages

BLANK_CELLS = ["", " ", "  ", "   ", "\t"]
"""Cells that hold no value (pyarrow matches null values before trimming blanks)."""
TIME_EXPONENT = {"ns": 0, "us": 3, "ms": 6, "s": 9}
"""Time unit -> the power of ten of nanoseconds it is worth."""
_CONVERSION = re.compile(
    r"In CSV column #(\d+): .*conversion error to (\w+): invalid value '(.*)'$"
)
_COLUMN = re.compile(r"In CSV column #(\d+): (.*)$")
_FIELD_COUNT = re.compile(r"CSV parse error: Expected (\d+) columns, got (\d+)")


def _clean_text(path: Path, layout: Layout, comment: str | None) -> bytes:
    """The data lines as bytes without comment lines and blank lines, runs of blanks turned
    into commas for a blank-separated file (the whole file in memory: for the layouts pyarrow
    cannot read as they are)."""
    with open(path, "rb") as fh:
        fh.seek(layout.data_offset)
        data = fh.read()
    data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    if comment:
        data = re.sub(rb"(?m)^[ \t]*" + re.escape(comment.encode()) + rb".*(\n|$)", b"", data)
    data = re.sub(rb"(?m)^[ \t]+$\n?", b"", data)
    if layout.delimiter == "whitespace":  # runs of spaces/tabs: commas (C-speed regex)
        data = re.sub(rb"(?m)^[ \t]+|[ \t]+$", b"", data)
        data = re.sub(rb"[ \t]+", b",", data)
    return data


class CsvFile:
    """One CSV file: its layout, and the columns the mapping names, parsed in one read.

    Columns are named by header name or by 0-based index (int, or its digits for a file
    without a header)."""

    def __init__(self, path: Path, mapping: CsvMapping) -> None:
        self.path = path
        self.mapping = mapping
        self.layout = sniff(
            path,
            delimiter=mapping.delimiter,
            decimal=mapping.decimal,
            header=mapping.header,
            skip_rows=mapping.skip_rows,
            comment=mapping.comment,
        )
        self.columns: dict[int, pa.ChunkedArray] = {}
        self.rows = 0

    # -- names -----------------------------------------------------------------------------
    def label(self, index: int) -> str:
        """How an error message names column ``index``."""
        names = self.layout.names
        return f"'{names[index]}'" if index < len(names) else f"index {index}"

    def index(self, key: str, name: str | int | None) -> int | None:
        """Column index of ``name`` (for config key ``csv.<key>``), None when the file lacks it;
        a name the header holds twice is an error."""
        if name is None:
            return None
        names = self.layout.names
        if isinstance(name, int) or (not names and str(name).isdigit()):
            i = int(name)
            return i if 0 <= i < self.layout.fields else None
        found = [i for i, n in enumerate(names) if n == name]
        if not found and names and names[0][:1] in ("#", "%") and names[0][1:].strip() == name:
            found = [0]  # a header written as a comment (numpy.savetxt: '# t,x'; rostopic: '%time')
        if len(found) > 1:
            raise ReadError(
                f"{self.path}: line {self.layout.header_line}: column '{name}' (csv.{key}) "
                f"appears {len(found)} times in the header (fields "
                f"{', '.join(str(i + 1) for i in found)}); rename one"
            )
        return found[0] if found else None

    def require(self, key: str, name: str | int) -> int:
        """Like :meth:`index`, but a missing column is an error listing the file's columns."""
        i = self.index(key, name)
        if i is None:
            names = self.layout.names
            if names:
                have = ", ".join(names[:20]) + (" ..." if len(names) > 20 else "")
                raise ReadError(
                    f"{self.path}: column '{name}' (csv.{key}) not found; the file has: {have}"
                )
            if isinstance(name, int) or str(name).isdigit():
                raise ReadError(
                    f"{self.path}: column index {name} (csv.{key}) not found; the file has "
                    f"{self.layout.fields} columns (no header)"
                )
            raise ReadError(
                f"{self.path}: column '{name}' (csv.{key}) not found: the file has no header "
                f"(name its {self.layout.fields} columns by 0-based index, or set csv.header)"
            )
        return i

    # -- parsing ---------------------------------------------------------------------------
    def _source(self) -> Any:
        if self.layout.clean:
            return io.BytesIO(_clean_text(self.path, self.layout, self.mapping.comment))
        source = pa.OSFile(str(self.path))
        source.seek(self.layout.data_offset)
        return source

    def _read(self, types: dict[int, pa.DataType], blanks: list[str]) -> pa.Table:
        layout = self.layout
        read = pacsv.ReadOptions(
            column_names=[f"c{i}" for i in range(layout.fields)], block_size=1 << 22
        )
        parse = pacsv.ParseOptions(delimiter="," if layout.clean else layout.delimiter)
        convert = pacsv.ConvertOptions(
            include_columns=[f"c{i}" for i in types],
            column_types={f"c{i}": t for i, t in types.items()},
            null_values=blanks,
            strings_can_be_null=True,
            quoted_strings_can_be_null=True,
            decimal_point=layout.decimal,
        )
        source = self._source()
        try:
            return pacsv.read_csv(source, read, parse, convert)
        finally:
            source.close()

    def load(self, types: dict[int, pa.DataType]) -> None:
        """Parse the columns ``types`` names (index -> Arrow type) in one read."""
        types = dict(types)
        while True:
            try:
                table = self._read(types, BLANK_CELLS)
                break
            except pa.ArrowInvalid as exc:
                message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                conversion = _CONVERSION.match(message)
                if conversion and types.get(int(conversion[1])) == pa.int64():
                    types[int(conversion[1])] = pa.string()  # an ns column with a float cell
                    continue
                if _FIELD_COUNT.match(message) and not self.layout.clean:
                    self.layout.clean = True  # e.g. a line of blanks: read once more, cleaned
                    continue
                raise self._error(message, conversion) from None
            except pa.ArrowException as exc:  # anything else pyarrow refuses
                line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise ReadError(f"{self.path}: not a readable CSV: {line}") from None
            except (OSError, MemoryError) as exc:
                raise ReadError(f"{self.path}: cannot read: {exc}") from None
        self.rows = table.num_rows
        self.columns = {int(name[1:]): table.column(name) for name in table.column_names}

    def _error(self, message: str, conversion: re.Match | None) -> ReadError:
        """The ReadError for a parser complaint, with the file line it is about."""
        comment = self.mapping.comment
        column = _COLUMN.match(message)
        if column:
            index = int(column[1])
            if conversion:
                value = conversion[3].strip()
                what = f"'{conversion[3]}' is not a number" if value else "a cell of blanks"

                def bad(cell: bytes) -> bool:
                    return cell.decode(errors="replace").strip() == value
            else:
                what = "not UTF-8 text" if "UTF8" in message else column[2]

                def bad(cell: bytes) -> bool:
                    try:
                        cell.decode()
                    except UnicodeDecodeError:
                        return True
                    return False

            try:
                cells = self._read({index: pa.binary()}, BLANK_CELLS).column(0).to_pylist()
            except pa.ArrowInvalid:
                cells = []
            row = next((i for i, c in enumerate(cells) if c is not None and bad(c)), None)
            line = None if row is None else line_of_row(self.path, self.layout, comment, row)
            where = f"line {line}, " if line else ""
            return ReadError(f"{self.path}: {where}column {self.label(index)}: {what}")
        count = _FIELD_COUNT.match(message)
        if count:
            found = line_with_fields(self.path, self.layout, comment)
            if found:
                line, fields, text = found
                hint = " (a comment line? set csv.comment)" if text.lstrip()[:1] in "#%;/" else ""
                return ReadError(
                    f"{self.path}: line {line}: {fields} field{'s' * (fields != 1)} where the data have "
                    f"{self.layout.fields} (from line {self.layout.first_line}){hint}"
                )
        return ReadError(f"{self.path}: not a readable CSV: {message}")

    def line(self, row: int) -> str:
        """'line N' of data row ``row`` (for messages)."""
        line = line_of_row(self.path, self.layout, self.mapping.comment, row)
        return f"line {line}" if line else f"data row {row + 1}"

    # -- columns ---------------------------------------------------------------------------
    def floats(self, index: int, out: np.ndarray) -> np.ndarray | None:
        """Write column ``index`` (float64, after ``csv.scale`` and ``csv.offset``) into
        ``out``, NaN where empty; returns the mask of the cells that hold a value (None: all).
        The parsed column is dropped."""
        column = self.columns.pop(index)
        pos = 0
        for chunk in column.chunks:
            m = len(chunk)
            if chunk.null_count:
                out[pos : pos + m] = chunk.fill_null(np.nan).to_numpy()
            else:
                out[pos : pos + m] = chunk.to_numpy()
            pos += m
        name = self.mapping_name(index)
        scale = (self.mapping.scale or {}).get(name)
        offset = (self.mapping.offset or {}).get(name)
        if scale is not None:
            out *= scale
        if offset is not None:
            out += offset
        if column.null_count == 0:
            return None
        return valid_mask(column)

    def mapping_name(self, index: int) -> str:
        """The key ``csv.scale`` / ``csv.offset`` use for column ``index``."""
        names = self.layout.names
        return names[index] if index < len(names) else str(index)


def _unit(path: Path, key: str, unit: str, table: dict[str, float]) -> float:
    if unit not in table:
        raise ReadError(f"{path}: csv.{key} = '{unit}' is not one of {', '.join(table)}")
    return table[unit]


class _Sensor:
    """One sensor's columns in SI: ``values`` (n, k) column-major, ``has`` (n,) the rows that
    hold a sample (None: every row), ``nan`` per column label, the NaN cells among them."""

    def __init__(self, values: np.ndarray, has: np.ndarray | None, nan: dict[str, int]) -> None:
        self.values = values
        self.has = has
        self.nan = nan


def _sensor(f: CsvFile, indices: list[int], factor: float) -> _Sensor:
    """Columns ``indices`` of ``f`` (loaded) into SI, with the rows that hold a sample."""
    with small_pages():  # filled once, in order: no huge-page compaction stall
        values = np.empty((f.rows, len(indices)), order="F")
    masks = [f.floats(i, values[:, k]) for k, i in enumerate(indices)]
    if factor != 1.0:
        values *= factor
    given = [m for m in masks if m is not None]
    has = None
    if given:
        has = np.logical_or.reduce(given) if len(given) == len(masks) else None
    nan: dict[str, int] = {}
    for k, i in enumerate(indices):
        column = values[:, k]
        bad = np.isnan(column)
        count = int(np.count_nonzero(bad if has is None else bad & has))
        if count:
            nan[f.mapping_name(i)] = count
    return _Sensor(values, has, nan)


def _check_linear(f: CsvFile, m: CsvMapping) -> None:
    """``csv.scale`` / ``csv.offset`` name mapped columns of the file."""
    mapped = {
        str(c)
        for c in [m.time, m.temperature, m.ambient_temperature, *(m.gyro or ()), *(m.accel or ())]
        + [*(m.mag or ())]
        if c is not None
    }
    for key in ("scale", "offset"):
        for col, value in (getattr(m, key) or {}).items():
            if col not in mapped:
                raise ReadError(
                    f"{f.path}: csv.{key}.{col}: not a mapped column "
                    f"(mapped: {', '.join(sorted(mapped))})"
                )
            if not np.isfinite(value):
                raise ReadError(f"{f.path}: csv.{key}.{col} = {value} is not a finite number")
            if m.gyro_file is None and f.index(f"{key}.{col}", col) is None:
                f.require(f"{key}.{col}", col)  # raises: not found, naming the columns


def _times(
    path: Path, m: CsvMapping, f: CsvFile, index: int | None, warnings: list[str]
) -> np.ndarray:
    """Sample times (int64 ns): ``csv.rate_hz``, else the time column, else a rate line."""
    rate = m.rate_hz
    n = f.rows
    if rate is None and index is None and m.time is not None and "time" not in m.required:
        rate = f.layout.rate_hz
        if rate is not None:
            warnings.append(
                f"{path}: no time column '{m.time}'; times from the rate {rate:g} Hz "
                "given in the lines before the header"
            )
    if rate is not None:
        if not (rate > 0 and np.isfinite(rate)):
            raise ReadError(f"{path}: csv.rate_hz must be > 0")
        if (n - 1) * 1e9 / rate >= 2**63:
            raise ReadError(f"{path}: csv.rate_hz = {rate:g} is too low for {n} rows (int64 ns)")
        return np.round(np.arange(n) * (1e9 / rate)).astype(np.int64)
    if m.time is None:
        raise ReadError(f"{path}: no time column and no csv.rate_hz")
    assert index is not None
    exponent = TIME_EXPONENT[m.time_unit]
    column = f.columns.pop(index)
    if column.null_count:
        row = int(np.flatnonzero(~valid_mask(column))[0])
        raise ReadError(f"{path}: {f.line(row)}, column {f.label(index)}: empty time")
    try:
        if pa.types.is_integer(column.type):
            t = scaled_ns(column.to_numpy(), exponent)
        else:
            text = column.combine_chunks() if column.num_chunks != 1 else column.chunk(0)
            if f.layout.decimal == ",":
                import pyarrow.compute as pc  # imported only here: 0.06-0.09 s CPU

                text = pc.replace_substring(text, ",", ".")
            t = text_to_ns(text, exponent)
    except TimeCellError as exc:
        value = column[exc.row].as_py()
        raise ReadError(
            f"{path}: {f.line(exc.row)}, column {f.label(index)}: '{value}' {exc.reason}"
        ) from None
    negative = np.flatnonzero(t < 0)
    if len(negative):
        row = int(negative[0])
        raise ReadError(
            f"{path}: {f.line(row)}, column {f.label(index)}: negative time "
            f"'{column[row].as_py()}' (logs hold times >= 0; shift the column, or set "
            "csv.rate_hz)"
        )
    return t


def read_csv(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a CSV input into the common table. Returns the table and any warnings."""
    path = Path(spec.path)
    m = spec.csv
    f = CsvFile(path, m)
    warnings: list[str] = []
    if f.layout.skipped:
        shown = " | ".join(f.layout.skipped[:4]) + (" | ..." if len(f.layout.skipped) > 4 else "")
        warnings.append(
            f"{path}: skipped {len(f.layout.skipped)} line(s) before the "
            f"{'header' if f.layout.header else 'data'}: {shown}"
        )
    _unit(path, "time_unit", m.time_unit, TIME_UNITS)
    vectors: dict[str, list[int] | None] = {}
    for key in ("gyro", "accel", "mag"):
        names = getattr(m, key)
        if names is None or (key == "gyro" and m.gyro_file is not None):
            continue
        if len(names) != 3:
            raise ReadError(f"{path}: csv.{key} must name 3 columns, got {len(names)}")
        found = [f.index(key, n) for n in names]
        if all(i is None for i in found) and key not in m.required:
            continue
        vectors[key] = [f.require(key, n) for n in names]
    singles: dict[str, int] = {}
    for key in ("temperature", "ambient_temperature", "label"):
        name = getattr(m, key)
        i = f.index(key, name)
        if i is None and name is not None and (key in m.required or key == "label"):
            i = f.require(key, name)
        if i is not None:
            singles[key] = i
    time_index = None
    if m.rate_hz is None and m.time is not None:
        time_index = f.index("time", m.time)
        if time_index is None and (f.layout.rate_hz is None or "time" in m.required):
            time_index = f.require("time", m.time)
    _check_linear(f, m)
    if not vectors and "temperature" not in singles and m.gyro_file is None:
        raise ReadError(
            f"{path}: no mapped column found (gyro {m.gyro}, accel {m.accel}, mag {m.mag}); "
            f"the file has: {', '.join(f.layout.names[:20]) or f'{f.layout.fields} columns'}; "
            + (
                f"set [inputs.{spec.name}.csv]"
                if spec.keys_in is None
                else f"set csv in {spec.keys_in}"
            )
        )

    types: dict[int, pa.DataType] = {i: pa.float64() for ix in vectors.values() for i in ix}
    types.update({i: pa.float64() for k, i in singles.items() if k != "label"})
    if "label" in singles:
        types[singles["label"]] = pa.string()
    if time_index is not None:
        types[time_index] = pa.int64() if m.time_unit == "ns" else pa.string()
    f.load(types)
    n = f.rows
    if n == 0:
        raise ReadError(f"{path}: the file has a header but no rows")

    units = {"gyro": GYRO_UNITS, "accel": ACCEL_UNITS, "mag": MAG_UNITS}
    sensors: dict[str, _Sensor] = {}
    for key, ix in vectors.items():
        factor = _unit(path, f"{key}_unit", getattr(m, f"{key}_unit"), units[key])
        sensors[key] = _sensor(f, ix, factor)
    if m.gyro_file is not None:
        sensors["gyro"] = _gyro_from_file(Path(m.gyro_file), m, n)
    if "temperature" in singles:
        sensors["temperature"] = _sensor(f, [singles["temperature"]], 1.0)
    extra: dict[str, Any] = {}
    if "label" in singles:
        extra["label"] = f.columns.pop(singles["label"]).combine_chunks()
    if "ambient_temperature" in singles:
        air = _sensor(f, [singles["ambient_temperature"]], 1.0)
        extra["ambient_temperature"] = pa.array(
            air.values[:, 0], pa.float64(), mask=None if air.has is None else ~air.has
        )
    t_ns = _times(path, m, f, time_index, warnings)
    f.columns.clear()

    gyro, accel = sensors.get("gyro"), sensors.get("accel")
    if gyro is not None or accel is not None:  # each sensor keeps its own validity (see table)
        imu = [s for s in (gyro, accel) if s is not None]
        has = (
            None if any(s.has is None for s in imu) else np.logical_or.reduce([s.has for s in imu])
        )
        nan = {k: v for s in imu for k, v in s.nan.items()}
        _nan_warning(path, "IMU", has, n, nan, warnings, *imu)
    for key, what in (("mag", "magnetometer"), ("temperature", "temperature")):
        s = sensors.get(key)
        if s is not None and s.nan:
            _nan_warning(path, what, s.has, n, s.nan, warnings, s)
    mag, temperature = sensors.get("mag"), sensors.get("temperature")
    meta = {"source": str(path), "format": "csv", "topics": {}, "types": {}, "frame_id": {}}
    raw = [k for k in ("gyro", "accel", "mag") if k in sensors and getattr(m, f"{k}_unit") == "raw"]
    if raw:  # the values are the sensor's own counts, not SI: stages word their figures so
        meta["units"] = dict.fromkeys(raw, "raw")
    valid = {
        key: _mask(sensors[key].has, n) if key in sensors else np.zeros(n, bool)
        for key in ("gyro", "accel", "mag", "temperature")
    }
    table = make_table(
        t_ns,
        gyro=None if gyro is None else gyro.values,
        accel=None if accel is None else accel.values,
        mag=None if mag is None else mag.values,
        temperature=None if temperature is None else temperature.values[:, 0],
        valid=valid,
        extra=extra or None,
        metadata=meta,
    )
    table, moved = sort_by_time(table)
    if moved:
        warnings.append(
            f"{path}: {moved} rows were out of time order; sorted stably (none dropped)"
        )
    return table, warnings


def _mask(has: np.ndarray | None, n: int) -> np.ndarray:
    return np.ones(n, bool) if has is None else has


def _nan_warning(
    path: Path,
    what: str,
    has: np.ndarray | None,
    n: int,
    nan: dict[str, int],
    warnings: list[str],
    *sensors: _Sensor,
) -> None:
    """One warning per stream: how many samples hold NaN (empty or ``nan`` cells)."""
    if not nan:
        return
    bad = np.zeros(n, bool)
    for s in sensors:
        bad |= np.isnan(s.values).any(axis=1)
    if has is not None:
        bad &= has
    samples = n if has is None else int(np.count_nonzero(has))
    cols = ", ".join(f"{c} {k}" for c, k in nan.items())
    warnings.append(
        f"{path}: {int(np.count_nonzero(bad))} of {samples} {what} samples have empty or NaN "
        f"cells ({cols}); kept as NaN, left out of fits"
    )


def _gyro_from_file(path: Path, m: CsvMapping, rows: int) -> _Sensor:
    """The gyro columns of ``csv.gyro_file``, which must have as many rows as the main file."""
    f = CsvFile(path, m)
    if m.gyro is None or len(m.gyro) != 3:
        raise ReadError(f"{path}: csv.gyro must name 3 columns of csv.gyro_file")
    indices = [f.require("gyro", n) for n in m.gyro]
    f.load({i: pa.float64() for i in indices})
    if f.rows != rows:
        raise ReadError(
            f"{path}: csv.gyro_file has {f.rows} rows, the main file {rows}; "
            "they must match row for row"
        )
    factor = _unit(path, "gyro_unit", m.gyro_unit, GYRO_UNITS)
    return _sensor(f, indices, factor)
