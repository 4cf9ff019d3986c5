"""CSV (and whitespace ASCII, e.g. imu_tk's ``.mat``) into the common table, via pyarrow's reader.

Mapping and units per :class:`~imupipe.readers.spec.CsvMapping`. A cell left empty means "no
sample of that stream in this row" (so one CSV can hold streams at different rates). Time comes
from the time column (s/ms/us/ns) or, with ``rate_hz``, from the row number.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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


HEAD_BYTES = 1 << 16
"""How much of the file's start is looked at to find the delimiter, the header and metadata."""
_RATE_KEY = re.compile(
    r"^(fs|rate|odr|frequency|sample[ _-]?rate|sampling[ _-]?(rate|frequency))"
    r"\s*(\(hz\)|\[hz\]|hz)?$",
    re.IGNORECASE,
)


@dataclass
class Layout:
    """Where a CSV's data start and how its lines split.

    ``skip`` lines (``skipped``: their text) come before the header (``header`` True) or the
    first data line; ``first_line`` is the 1-based line number of the first data row, for error
    messages; ``rate_hz`` is a sample rate read from a metadata line such as ``Fs,100``."""

    delimiter: str
    header: bool
    skip: int = 0
    skipped: list[str] = field(default_factory=list)
    first_line: int = 1
    rate_hz: float | None = None


def _split(line: str, delimiter: str) -> list[str]:
    return line.split() if delimiter == "whitespace" else line.split(delimiter)


def _is_number(cell: str) -> bool:
    return bool(re.match(_NUMBER, cell))


def _head_lines(path: Path, comment: str | None) -> list[tuple[int, str]]:
    """(0-based line number, text) of the non-blank, non-comment lines of the file's start."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(HEAD_BYTES)
    except OSError as exc:
        raise ReadError(f"{path}: cannot read: {exc.strerror or exc}") from None
    text = head.decode("utf-8", errors="replace")
    lines = text.splitlines()
    if len(head) == HEAD_BYTES and len(lines) > 1:
        lines = lines[:-1]  # the last line may be cut
    return [
        (i, line)
        for i, line in enumerate(lines)
        if line.strip() and not (comment and line.lstrip().startswith(comment))
    ]


def _delimiter(lines: list[str], wanted: str) -> tuple[str, int]:
    """The delimiter and the data's number of fields: the candidate whose field count is the
    same on most of the last half of the lines, with the most fields."""
    candidates = [wanted] if wanted != "auto" else [",", ";", "\t", "whitespace"]
    tail = lines[len(lines) // 2 :] or lines
    best = (candidates[0], 1, 0.0)
    for cand in candidates:
        counts = [len(_split(line, cand)) for line in tail]
        mode = max(set(counts), key=counts.count)
        share = counts.count(mode) / len(counts)
        if share >= 0.9 and (mode > best[1] or (mode == best[1] and share > best[2])):
            best = (cand, mode, share)
    return best[0], best[1]


def _layout(path: Path, mapping: CsvMapping) -> Layout:
    """Find the delimiter, the metadata lines before the header, and the header."""
    lines = _head_lines(path, mapping.comment)
    if not lines:
        raise ReadError(f"{path}: the file is empty")
    wanted = "\t" if mapping.delimiter == "\\t" else mapping.delimiter
    delimiter, fields = _delimiter([t for _, t in lines], wanted)
    if mapping.skip_rows is not None:
        if mapping.skip_rows < 0:
            raise ReadError(f"{path}: csv.skip_rows must be >= 0")
        start = next((k for k, (i, _) in enumerate(lines) if i >= mapping.skip_rows), len(lines))
    else:  # the block of lines with the data's field count that runs to the end of the head
        start = len(lines)
        while start > 0 and len(_split(lines[start - 1][1], delimiter)) == fields:
            start -= 1
    if start >= len(lines):
        raise ReadError(f"{path}: no data lines after the {len(lines)} lines skipped")
    first_index, first = lines[start]
    header = mapping.header
    if header is None:
        header = any(c.strip() and not _is_number(c) for c in _split(first, delimiter))
    layout = Layout(
        delimiter=delimiter,
        header=header,
        skip=first_index,
        skipped=[t.strip() for _, t in lines[:start]],
        first_line=first_index + (2 if header else 1),
    )
    for line in layout.skipped:
        key, _, value = line.replace("\t", ",").replace(":", ",").replace("=", ",").partition(",")
        value = value.strip().strip(",").strip()
        if _RATE_KEY.match(key.strip()) and _is_number(value) and float(value) > 0:
            layout.rate_hz = float(value)
    return layout


def _source(path: Path, layout: Layout, comment: str | None) -> tuple[Any, str]:
    """A readable for pyarrow positioned at the header (or first data line), and its delimiter
    (runs of blanks normalised to commas for ``whitespace``; comment lines removed)."""
    if layout.delimiter != "whitespace" and not comment:
        fh = open(path, "rb")  # noqa: SIM115 (closed by the caller)
        for _ in range(layout.skip):
            fh.readline()
        return fh, layout.delimiter
    data = path.read_bytes()
    if layout.skip:
        data = data.split(b"\n", layout.skip)[-1] if data.count(b"\n") >= layout.skip else b""
    if comment:
        data = re.sub(rb"(?m)^[ \t]*" + re.escape(comment.encode()) + rb".*(\r?\n|$)", b"", data)
    if layout.delimiter == "whitespace":  # runs of spaces/tabs: commas (C-speed regex)
        data = re.sub(rb"(?m)^[ \t]+", b"", data)
        data = re.sub(rb"[ \t]+", b",", data)
        return io.BytesIO(data), ","
    return io.BytesIO(data), layout.delimiter


def _raw_table(path: Path, mapping: CsvMapping) -> tuple[pa.Table, Layout]:
    layout = _layout(path, mapping)
    source, delimiter = _source(path, layout, mapping.comment)
    read = pacsv.ReadOptions(autogenerate_column_names=not layout.header, block_size=1 << 22)
    parse = pacsv.ParseOptions(delimiter=delimiter)
    convert = pacsv.ConvertOptions(strings_can_be_null=True)
    start = source.tell()
    try:
        try:
            # streamed in blocks: the peak stays near the table's size, not the text's
            table = pacsv.open_csv(source, read, parse, convert).read_all()
        except pa.ArrowInvalid:
            # types inferred from the first block did not fit a later one (or a cell is bad):
            # read whole, so the offending row can be named
            source.seek(start)
            try:
                table = pacsv.read_csv(source, read, parse, convert)
            except pa.ArrowInvalid as exc:
                raise ReadError(f"{path}: not a readable CSV: {str(exc).splitlines()[0]}") from None
    finally:
        source.close()
    if not layout.header:
        table = table.rename_columns([str(i) for i in range(table.num_columns)])
    return table, layout


class _Columns:
    """The parsed columns of one CSV file, looked up by the mapping's names, as float64 in the
    column's own unit (after ``csv.scale`` and ``csv.offset``)."""

    def __init__(self, path: Path, mapping: CsvMapping) -> None:
        self.path = path
        self.mapping = mapping
        self.table, self.layout = _raw_table(path, mapping)

    def has(self, name: str | int | None) -> bool:
        return name is not None and str(name) in self.table.column_names

    def _get(self, key: str, name: str | int) -> pa.ChunkedArray:
        col = str(name)
        if col not in self.table.column_names:
            have = ", ".join(self.table.column_names[:20])
            what = f"column '{col}'" if self.layout.header else f"column index {col}"
            raise ReadError(f"{self.path}: {what} (csv.{key}) not found; the file has: {have}")
        return self.table.column(col)

    def number(self, key: str, name: str | int) -> pa.Array:
        """Column ``name`` (for config key ``key``) as float64 or int64, nulls where empty."""
        col = str(name)
        array = self._get(key, name)
        if pa.types.is_null(array.type):
            array = pa.nulls(len(array), pa.float64())
        elif pa.types.is_floating(array.type):
            array = array.cast(pa.float64())
        elif not pa.types.is_integer(array.type):
            strings = array.cast(pa.string())
            ok = pc.or_(pc.is_null(strings), pc.match_substring_regex(strings, _NUMBER))
            bad = np.flatnonzero(~ok.to_numpy(zero_copy_only=False))
            if len(bad):
                line = int(bad[0]) + self.layout.first_line
                value = strings[int(bad[0])].as_py()
                raise ReadError(
                    f"{self.path}: line {line}, column '{col}': '{value}' is not a number"
                )
            array = pc.cast(pc.utf8_trim_whitespace(strings), pa.float64())
        scale = (self.mapping.scale or {}).get(col)
        offset = (self.mapping.offset or {}).get(col)
        if scale is not None:
            array = pc.multiply(array.cast(pa.float64()), scale)
        if offset is not None:
            array = pc.add(array.cast(pa.float64()), offset)
        return array

    def text(self, key: str, name: str | int) -> pa.Array:
        """Column ``name`` as text (the ``label`` key): numbers are kept as their text."""
        return self._get(key, name).cast(pa.string())

    def first_null(self, array: pa.Array) -> int:
        """The file line of the first empty cell of ``array``."""
        return int(np.flatnonzero(~pc.is_valid(array).to_numpy(zero_copy_only=False))[0]) + (
            self.layout.first_line
        )


def _gyro_from_file(path: Path, m: CsvMapping, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """The gyro columns of ``csv.gyro_file``, which must have as many rows as the main file."""
    cols = _Columns(path, m)
    if cols.table.num_rows != rows:
        raise ReadError(
            f"{path}: csv.gyro_file has {cols.table.num_rows} rows, the main file {rows}; "
            "they must match row for row"
        )
    if m.gyro is None or len(m.gyro) != 3:
        raise ReadError(f"{path}: csv.gyro must name 3 columns of csv.gyro_file")
    arrays = [cols.number("gyro", n) for n in m.gyro]
    return _scaled(arrays, _unit(path, "gyro_unit", m.gyro_unit, GYRO_UNITS))


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


def _check_linear(path: Path, m: CsvMapping, cols: _Columns) -> None:
    """``csv.scale`` / ``csv.offset`` name mapped columns of the file."""
    mapped = {
        str(c)
        for c in [m.time, m.temperature, m.ambient_temperature, *(m.gyro or ()), *(m.accel or ())]
        + [*(m.mag or ())]
        if c is not None
    }
    for key in ("scale", "offset"):
        for col in getattr(m, key) or {}:
            if col not in mapped:
                raise ReadError(
                    f"{path}: csv.{key}.{col}: not a mapped column "
                    f"(mapped: {', '.join(sorted(mapped))})"
                )
            if m.gyro_file is None and not cols.has(col):
                cols.number(f"{key}.{col}", col)  # raises: not found, naming the columns


def _time_ns(path: Path, m: CsvMapping, cols: _Columns, n: int, warnings: list[str]) -> np.ndarray:
    """Sample times: ``csv.rate_hz``, else the time column, else a rate line of the metadata."""
    rate = m.rate_hz
    if rate is None and m.time is not None and not cols.has(m.time) and "time" not in m.required:
        rate = cols.layout.rate_hz
        if rate is not None:
            warnings.append(
                f"{path}: no time column '{m.time}'; times from the rate {rate:g} Hz "
                "given in the lines before the header"
            )
    if rate is not None:
        if rate <= 0:
            raise ReadError(f"{path}: csv.rate_hz must be > 0")
        return np.round(np.arange(n) * (1e9 / rate)).astype(np.int64)
    if m.time is None:
        raise ReadError(f"{path}: no time column and no csv.rate_hz")
    scale = _unit(path, "time_unit", m.time_unit, TIME_UNITS)
    tcol = cols.number("time", m.time)
    if tcol.null_count:
        raise ReadError(f"{path}: line {cols.first_null(tcol)}, column '{m.time}': empty time")
    if pa.types.is_integer(tcol.type) and scale == 1.0:
        return tcol.to_numpy().astype(np.int64)
    return np.round(tcol.to_numpy(zero_copy_only=False).astype(np.float64) * scale).astype(np.int64)


def read_csv(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a CSV input into the common table. Returns the table and any warnings."""
    path = Path(spec.path)
    m = spec.csv
    cols = _Columns(path, m)
    if cols.table.num_rows == 0:
        raise ReadError(f"{path}: the file has a header but no rows")
    warnings: list[str] = []
    if cols.layout.skipped:
        shown = " | ".join(cols.layout.skipped[:4]) + (
            " | ..." if len(cols.layout.skipped) > 4 else ""
        )
        warnings.append(
            f"{path}: skipped {len(cols.layout.skipped)} line(s) before the "
            f"{'header' if cols.layout.header else 'data'}: {shown}"
        )
    _check_linear(path, m, cols)

    def vector(
        key: str, unit_key: str, units: dict[str, float]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        names = getattr(m, key)
        if names is None:
            return None
        if len(names) != 3:
            raise ReadError(f"{path}: csv.{key} must name 3 columns, got {len(names)}")
        if not any(cols.has(n) for n in names) and key not in m.required:
            return None
        arrays = [cols.number(key, n) for n in names]
        return _scaled(arrays, _unit(path, unit_key, getattr(m, unit_key), units))

    gyro = vector("gyro", "gyro_unit", GYRO_UNITS)
    n = cols.table.num_rows
    if m.gyro_file is not None:
        gyro = _gyro_from_file(Path(m.gyro_file), m, n)
    accel = vector("accel", "accel_unit", ACCEL_UNITS)
    mag = vector("mag", "mag_unit", MAG_UNITS)
    temperature = None
    if cols.has(m.temperature) or (m.temperature is not None and "temperature" in m.required):
        temperature = _scaled([cols.number("temperature", m.temperature)], 1.0)
    if gyro is None and accel is None and mag is None and temperature is None:
        raise ReadError(
            f"{path}: no mapped column found (gyro {m.gyro}, accel {m.accel}, mag {m.mag}); "
            f"the file has: {', '.join(cols.table.column_names[:20])}; set [inputs.{spec.name}.csv]"
        )

    extra: dict[str, pa.Array] = {}
    if m.label is not None:
        extra["label"] = cols.text("label", m.label)
    if cols.has(m.ambient_temperature) or (
        m.ambient_temperature is not None and "ambient_temperature" in m.required
    ):
        extra["ambient_temperature"] = cols.number("ambient_temperature", m.ambient_temperature)
    t_ns = _time_ns(path, m, cols, n, warnings)
    cols = None  # free the parsed columns before the table is built (peak memory)

    # each sensor keeps its own validity: a row with gyro but no accel (or a file with only one
    # of them) is an IMU sample whose other sensor is absent (null), never zeros
    meta = {"source": str(path), "format": "csv", "topics": {}, "types": {}, "frame_id": {}}
    raw = [k for k, v in (("gyro", gyro), ("accel", accel), ("mag", mag)) if v is not None]
    raw = [k for k in raw if getattr(m, f"{k}_unit") == "raw"]
    if raw:  # the values are the sensor's own counts, not SI: stages word their figures so
        meta["units"] = dict.fromkeys(raw, "raw")
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
        metadata=meta,
    )
    table, moved = sort_by_time(table)
    if moved:
        warnings.append(
            f"{path}: {moved} rows were out of time order; sorted stably (none dropped)"
        )
    return table, warnings
