"""The common table: the one Arrow schema every reader fills and every stage reads.

One row per *sample event*, rows in time order (stable: equal stamps keep their input order).

| column | type | unit | meaning |
|---|---|---|---|
| ``t_ns`` | int64 | ns | sample time (header stamp by default; log time with ``time = "log"``) |
| ``gyro_x``, ``gyro_y``, ``gyro_z`` | float64 | rad/s | angular rate; null where the row has no gyro sample |
| ``accel_x``, ``accel_y``, ``accel_z`` | float64 | m/s^2 | specific force; null where the row has no accel sample |
| ``mag_x``, ``mag_y``, ``mag_z`` | float64 | T | magnetic field; null where the row has no magnetometer sample |
| ``temperature`` | float64 | degC | temperature; null where the row has no temperature sample |

Null means "no sample"; NaN is a sample whose value came as NaN (it is kept and written back as
NaN; stages leave it out of their fits, see :func:`finite`).

Optional columns, filled by the binary readers so that a log can be written back message for
message (absent or null: the writer uses ROS defaults):

| column | type | meaning |
|---|---|---|
| ``log_time_ns`` | int64 | the log (receive) time of the message, ns |
| ``header_stamp_ns`` | int64 | the message's header stamp, ns, where it differs from ``t_ns``: filled with ``time = "log"`` (with ``time = "header"``, ``t_ns`` is the header stamp) |
| ``publish_time_ns`` | int64 | the MCAP publish time, ns (MCAP inputs; ROS 1/ROS 2 bags have none: the log time stands for it) |
| ``frame_id`` | string | the message header's frame_id |
| ``orientation_x/y/z/w`` | float64 | sensor_msgs/Imu orientation quaternion |
| ``orientation_cov``, ``gyro_cov``, ``accel_cov``, ``mag_cov`` | fixed_size_list<float64, 9> | covariances |
| ``temperature_var`` | float64 | sensor_msgs/Temperature variance |
| ``label`` | string | a CSV's segment label (csv ``label`` key), e.g. a calibration pose name |
| ``ambient_temperature`` | float64 | degC, the air (chamber) temperature around the IMU (csv ``ambient_temperature`` key); null where absent |
| ``pressure`` | float64 | Pa, a barometer's static pressure, on the ``temperature`` rows read from a barometer (ULog ``sensor_baro``, DataFlash ``BARO``: the temperature stream carries the barometer's own temperature); null elsewhere |
| ``attitude_w/x/y/z`` | float64 | the vehicle's attitude, a unit quaternion (Hamilton, scalar first) rotating body (FRD) vectors into the local NED frame, on rows of the ``attitude`` flight stream |
| ``latitude``, ``longitude``, ``altitude`` | float64 | deg, deg (WGS-84), m above mean sea level: the GNSS position, on rows of the ``position`` flight stream |
| ``current`` | float64 | A, the battery current, on rows of the ``current`` flight stream |
| ``throttle`` | float64 | 1, the motors' collective throttle 0..1 (what the flight controller's compass motor compensation multiplies: ArduCopter's ``CTUN.ThO``, PX4's thrust setpoint), on rows of the ``throttle`` flight stream |

**Flight streams** (:data:`FLIGHT_COLUMNS`: ``attitude``, ``position``, ``current``,
``throttle``) are what a flight controller's log adds to its sensors (ULog ``vehicle_attitude``,
``vehicle_gps_position`` or ``vehicle_global_position``, ``battery_status``,
``vehicle_thrust_setpoint`` or ``actuator_controls_0``; DataFlash ``ATT``, ``GPS``, ``BAT`` or
``CURR``, ``CTUN``). Each sample is a row of its own on which every sensor column is null (the row belongs
to none of :data:`STREAMS`, so the message writers and sensor stages never see it; the Parquet
dataset keeps it); a stage reads one with
:func:`flight_stream` and puts it on its sensor's stamps with :func:`interpolate`.

**Streams.** Each sensor has its own validity (the first column of the sensor is valid). A row
belongs to the ``imu`` stream where gyro *or* accel is valid, to the ``mag`` stream where
``mag_x`` is valid, and to the ``temperature`` stream where ``temperature`` is valid. An Imu
message from a log carries both gyro and accel; a CSV with only accel columns (or only gyro)
gives an ``imu`` stream whose other sensor is null on every row: it is absent, never zeros
(:func:`has_sensor` is false; :func:`sensor` gives NaN for it on every IMU row). The
corrected MCAP writes such a row as a ``sensor_msgs/Imu`` whose missing vector is NaN with
element 0 of its covariance set to -1 (the message's own convention for "no data"), and the
readers read that back as null. A CSV row may belong to all three streams; a message from a bag
belongs to exactly one. A gyro and an accelerometer read from topics of their own
(``gyro_topic``, ``accel_topic``) give IMU rows that hold one of them each, the other null:
:func:`split_imu`; :func:`sensor` then gives each sensor's own rows, :func:`imu_pairs` the two
row for row (interpolated explicitly), and the metadata names streams ``gyro`` and ``accel``. Streams at different rates keep their own timestamps: nothing is
resampled silently; a stage that needs one stream at another's timestamps calls
:func:`interpolate` explicitly.

**Metadata** (schema metadata key ``imupipe``, JSON): ``source`` (file), ``format``, ``topics``
(stream -> topic name), ``types`` (stream -> message type) and ``frame_id`` (stream -> frame);
``units`` (sensor -> ``"raw"``) where a sensor's values are its own counts, not SI (a CSV
mapped with ``mag_unit = "raw"``...), so that stages word their figures in counts.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import arrow_array, take, to_numpy, valid_mask

SENSOR_COLUMNS: dict[str, tuple[str, ...]] = {
    "gyro": ("gyro_x", "gyro_y", "gyro_z"),
    "accel": ("accel_x", "accel_y", "accel_z"),
    "mag": ("mag_x", "mag_y", "mag_z"),
    "temperature": ("temperature",),
}
"""Each sensor's value columns, in SI units."""

SENSOR_UNITS: dict[str, str] = {
    "gyro": "rad/s",
    "accel": "m/s^2",
    "mag": "T",
    "temperature": "degC",
}

STREAM_OF_SENSOR: dict[str, str] = {
    "gyro": "imu",
    "accel": "imu",
    "mag": "mag",
    "temperature": "temperature",
}
"""The stream (message) each sensor travels in."""

STREAM_SENSORS: dict[str, tuple[str, ...]] = {
    "imu": ("gyro", "accel"),
    "mag": ("mag",),
    "temperature": ("temperature",),
}
"""The sensors each stream carries: a row belongs to a stream where any of them is valid."""

STREAMS: tuple[str, ...] = ("imu", "mag", "temperature")

COV = pa.list_(pa.float64(), 9)

SCHEMA = pa.schema(
    [pa.field("t_ns", pa.int64(), nullable=False)]
    + [pa.field(c, pa.float64()) for cols in SENSOR_COLUMNS.values() for c in cols]
)
"""The required columns (value columns are nullable: null means "no sample of that stream")."""

OPTIONAL_FIELDS = pa.schema(
    [
        pa.field("log_time_ns", pa.int64()),
        pa.field("header_stamp_ns", pa.int64()),
        pa.field("publish_time_ns", pa.int64()),
        pa.field("frame_id", pa.string()),
        pa.field("orientation_x", pa.float64()),
        pa.field("orientation_y", pa.float64()),
        pa.field("orientation_z", pa.float64()),
        pa.field("orientation_w", pa.float64()),
        pa.field("orientation_cov", COV),
        pa.field("gyro_cov", COV),
        pa.field("accel_cov", COV),
        pa.field("mag_cov", COV),
        pa.field("temperature_var", pa.float64()),
        pa.field("label", pa.string()),
        pa.field("ambient_temperature", pa.float64()),
        pa.field("pressure", pa.float64()),
        pa.field("attitude_w", pa.float64()),
        pa.field("attitude_x", pa.float64()),
        pa.field("attitude_y", pa.float64()),
        pa.field("attitude_z", pa.float64()),
        pa.field("latitude", pa.float64()),
        pa.field("longitude", pa.float64()),
        pa.field("altitude", pa.float64()),
        pa.field("current", pa.float64()),
        pa.field("throttle", pa.float64()),
    ]
)

FLIGHT_COLUMNS: dict[str, tuple[str, ...]] = {
    "attitude": ("attitude_w", "attitude_x", "attitude_y", "attitude_z"),
    "position": ("latitude", "longitude", "altitude"),
    "current": ("current",),
    "throttle": ("throttle",),
}
"""The flight streams' columns: attitude quaternion (w, x, y, z; body FRD to NED), position
(deg, deg, m), battery current (A) and collective throttle (0..1). Each sample is a row of its own (no sensor column valid)."""

META_KEY = b"imupipe"


def make_table(
    t_ns: np.ndarray,
    *,
    gyro: np.ndarray | None = None,
    accel: np.ndarray | None = None,
    mag: np.ndarray | None = None,
    temperature: np.ndarray | None = None,
    valid: Mapping[str, np.ndarray] | None = None,
    extra: Mapping[str, pa.Array | np.ndarray] | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> pa.Table:
    """Build a common table from numpy arrays (SI units, ``t_ns`` int64 ns).

    ``gyro``, ``accel``, ``mag`` are (n, 3), ``temperature`` is (n,). A sensor left out is all
    null. ``valid`` maps a stream name (``imu``, ``mag``, ``temperature``) or a sensor name
    (``gyro``, ``accel``: its own entry wins over its stream's) to a boolean mask of the rows
    that hold a sample of it (default: every row, for the sensors given). ``extra`` adds
    optional columns (see :data:`OPTIONAL_FIELDS`). Rows are kept in the order given.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.shape[0]
    valid = dict(valid or {})
    given = {"gyro": gyro, "accel": accel, "mag": mag, "temperature": temperature}
    arrays: list[pa.Array] = [arrow_array(t_ns, pa.int64())]
    empty: pa.Array | None = None
    for sensor, cols in SENSOR_COLUMNS.items():
        values = given[sensor]
        stream = STREAM_OF_SENSOR[sensor]
        if values is None:
            empty = null_floats(n) if empty is None else empty
            arrays += [empty] * len(cols)
            continue
        values = np.asarray(values, dtype=np.float64).reshape(n, len(cols))
        mask = valid.get(sensor, valid.get(stream))
        null_mask = None if mask is None else ~np.asarray(mask, dtype=bool)
        arrays += [arrow_array(values[:, i], pa.float64(), null_mask) for i in range(len(cols))]
    table = pa.Table.from_arrays(arrays, schema=SCHEMA)
    for name, column in (extra or {}).items():
        field = OPTIONAL_FIELDS.field(name)
        table = table.append_column(field, _as_arrow(column, field.type))
    return with_metadata(table, metadata or {})


def null_floats(n: int) -> pa.Array:
    """An all-null float64 array of ``n`` rows whose buffers are never written: numpy's zeroed
    allocation (``calloc``) leaves the pages unmapped until read, where ``pa.nulls`` fills them
    (0.05 s for each 2.88 M-row column of an absent sensor, 4 of them in a gyro+accel CSV).
    Arrays are immutable: one serves every absent column of a table."""
    validity = pa.py_buffer(np.zeros((n + 7) // 8, dtype=np.uint8))
    data = pa.py_buffer(np.zeros(n, dtype=np.float64))
    return pa.Array.from_buffers(pa.float64(), n, [validity, data], null_count=n)


def _as_arrow(column: pa.Array | np.ndarray, typ: pa.DataType) -> pa.Array:
    if isinstance(column, pa.Array | pa.ChunkedArray):
        return column.cast(typ)
    column = np.asarray(column)
    if isinstance(typ, pa.FixedSizeListType):
        flat = np.ascontiguousarray(column, dtype=np.float64).reshape(-1)
        return pa.FixedSizeListArray.from_arrays(arrow_array(flat), typ.list_size)
    return arrow_array(column, typ)


def metadata(table: pa.Table) -> dict[str, Any]:
    """The table's imupipe metadata (source, format, topics, types, frame_id, units)."""
    raw = (table.schema.metadata or {}).get(META_KEY)
    return json.loads(raw) if raw else {}


def metadata_bytes(meta: Mapping[str, Any]) -> bytes:
    """``meta`` as the schema metadata's imupipe value (JSON, keys sorted)."""
    return json.dumps(dict(meta), sort_keys=True).encode()


def with_metadata(table: pa.Table, meta: Mapping[str, Any]) -> pa.Table:
    """A copy of ``table`` whose imupipe metadata is ``meta``."""
    old = dict(table.schema.metadata or {})
    old[META_KEY] = metadata_bytes(meta)
    return table.replace_schema_metadata(old)


def _valid(table: pa.Table, column_name: str) -> np.ndarray | None:
    """Validity of a column as a boolean mask; None when every row is valid."""
    column = table.column(column_name)
    if column.null_count == 0:
        return None
    return valid_mask(column)


def sensor_mask(table: pa.Table, name: str) -> np.ndarray:
    """Boolean mask of the rows that hold a sample of sensor ``name`` (gyro, accel, mag,
    temperature): its first column is valid."""
    mask = _valid(table, SENSOR_COLUMNS[name][0])
    return np.ones(len(table), dtype=bool) if mask is None else mask


def stream_mask(table: pa.Table, stream: str) -> np.ndarray:
    """Boolean mask of the rows that hold a sample of ``stream`` (imu, mag, temperature): any of
    its sensors is valid."""
    mask = np.zeros(len(table), dtype=bool)
    for name in STREAM_SENSORS[stream]:
        valid = _valid(table, SENSOR_COLUMNS[name][0])
        if valid is None:
            return np.ones(len(table), dtype=bool)
        mask |= valid
    return mask


def with_stream_column(
    table: pa.Table, stream: str, name: str, t_ns: np.ndarray, values: np.ndarray
) -> pa.Table:
    """``table`` with the optional column ``name`` (float64, see :data:`OPTIONAL_FIELDS`)
    holding ``values`` on the rows of ``stream`` and null elsewhere.

    ``values`` and ``t_ns`` are one per message of the stream in the order the reader decoded
    them; the table holds a stream's messages sorted stably by ``t_ns``, so the values go to
    the rows in that order. ValueError when the rows do not match ``t_ns``.
    """
    rows = np.flatnonzero(stream_mask(table, stream))
    order = np.argsort(np.asarray(t_ns, dtype=np.int64), kind="stable")
    stamps = to_numpy(table.column("t_ns"))[rows]
    if len(rows) != len(order) or not np.array_equal(stamps, np.asarray(t_ns)[order]):
        raise ValueError(f"the {stream} rows do not match the {len(order)} stamps given")
    full = np.zeros(len(table), dtype=np.float64)
    full[rows] = np.asarray(values, dtype=np.float64)[order]
    valid = np.zeros(len(table), dtype=bool)
    valid[rows] = True
    field = OPTIONAL_FIELDS.field(name)
    column = arrow_array(full, pa.float64(), ~valid)
    if name in table.schema.names:
        return table.set_column(table.schema.names.index(name), field, column)
    return table.append_column(field, column)


def has_sensor(table: pa.Table, name: str) -> bool:
    """Whether sensor ``name`` has at least one sample in ``table``."""
    return table.column(SENSOR_COLUMNS[name][0]).null_count < len(table)


def has_stream(table: pa.Table, stream: str) -> bool:
    """Whether ``stream`` has at least one sample (row) in ``table``."""
    return any(has_sensor(table, name) for name in STREAM_SENSORS[stream])


def _column_f64(table: pa.Table, name: str, rows: np.ndarray | None) -> np.ndarray:
    column = table.column(name)
    values = to_numpy(column)  # NaN at nulls
    return values if rows is None else values[rows]


@dataclass(frozen=True)
class SensorData:
    """One sensor's samples as numpy: ``t_ns`` (n,) int64, ``values`` (n, k) float64 SI, and
    ``rows``, the indices of those samples in the table (for writing corrected values back)."""

    t_ns: np.ndarray
    values: np.ndarray
    rows: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def t_s(self) -> np.ndarray:
        """Seconds since the first sample (float64), for fitting and plotting."""
        if len(self) == 0:
            return np.zeros(0)
        return (self.t_ns - self.t_ns[0]).astype(np.float64) * 1e-9


def _stream_rows(table: pa.Table, name: str) -> np.ndarray | None:
    """The rows of sensor ``name``'s stream (None: every row); in a table whose gyro and
    accelerometer come apart (:func:`split_imu`), the rows that hold a sample of ``name``."""
    if STREAM_OF_SENSOR[name] == "imu" and split_imu(table):
        return np.flatnonzero(sensor_mask(table, name))
    mask = stream_mask(table, STREAM_OF_SENSOR[name])
    return None if mask.all() else np.flatnonzero(mask)


def _rate(t_ns: np.ndarray) -> float:
    """Mean sample rate of stamps, Hz (0 for fewer than two)."""
    span = (int(t_ns[-1]) - int(t_ns[0])) * 1e-9 if len(t_ns) > 1 else 0.0
    return (len(t_ns) - 1) / span if span > 0 else 0.0


def split_imu(table: pa.Table) -> bool:
    """Whether the gyro and the accelerometer were sampled apart: read from topics of their own
    (``gyro_topic``, ``accel_topic``: the metadata's ``topics`` name ``gyro`` or ``accel``), so
    that each IMU row holds one of them. (A CSV row with empty accel cells is an IMU sample
    without accel: its table stays row for row.)"""
    topics = metadata(table).get("topics") or {}
    return "gyro" in topics or "accel" in topics


def imu_pairs(table: pa.Table, on: str = "gyro") -> tuple[SensorData, SensorData, str | None]:
    """Gyro and accelerometer row for row, for what needs both at once (a pose's gravity and
    rotation, a g-sensitivity, a stillness test): ``(gyro, accel, note)``.

    Where each IMU row holds both (an Imu message, a CSV row): :func:`sensor` of each, note
    None. Where they are sampled apart (:func:`split_imu`): both on the own stamps of sensor
    ``on`` (its rows, so that its correction goes back where it came from), the other linearly
    interpolated onto them (:func:`interpolate`: held at the other's first and last usable
    sample up to one of its periods beyond them, NaN further out: never extrapolated), and a
    note saying so. Nothing is resampled
    silently: the caller passes the note on."""
    gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
    if len(gyro) == len(accel) and np.array_equal(gyro.rows, accel.rows):
        return gyro, accel, None
    own, other = (gyro, accel) if on == "gyro" else (accel, gyro)
    values = np.full((len(own), 3), np.nan)
    ok = usable(other.values).all(axis=1)
    t_o = other.t_ns[ok]
    if len(t_o) >= 2:
        period = int(np.median(np.diff(t_o)))  # up to one period beyond the ends: held
        inside = (own.t_ns >= t_o[0] - period) & (own.t_ns <= t_o[-1] + period)
        values[inside] = interpolate(t_o, other.values[ok], own.t_ns[inside])
    names = {"gyro": "gyro", "accel": "accelerometer"}
    off = "accel" if on == "gyro" else "gyro"
    moved = SensorData(own.t_ns, values, own.rows)
    if not len(other):  # the other topic not read: absent, NaN (as a CSV without it)
        return (own, moved, None) if on == "gyro" else (moved, own, None)
    note = (
        f"gyro ({len(gyro)} samples, {_rate(gyro.t_ns):.4g} Hz) and accelerometer ({len(accel)} "
        f"samples, {_rate(accel.t_ns):.4g} Hz) are sampled apart: the {names[off]} is "
        f"interpolated linearly onto the {names[on]}'s stamps where both are needed together"
    )
    return (own, moved, note) if on == "gyro" else (moved, own, note)


def _sensor_columns(
    table: pa.Table, name: str, rows: np.ndarray | None
) -> tuple[np.ndarray, list[np.ndarray]]:
    t_ns = to_numpy(table.column("t_ns"))
    columns = [_column_f64(table, c, rows) for c in SENSOR_COLUMNS[name]]
    return (t_ns if rows is None else t_ns[rows]), columns


def sensor_columns(table: pa.Table, name: str) -> tuple[np.ndarray, list[np.ndarray]]:
    """:func:`sensor` column by column, without its (n, k) copy: the stamps and one float64
    array per column over the rows of the sensor's stream (NaN where a row has no sample of
    it). Where the stream holds every row and a column is one chunk without nulls, the array is
    a read-only view of the table's own buffer."""
    return _sensor_columns(table, name, _stream_rows(table, name))


def sensor(table: pa.Table, name: str) -> SensorData:
    """The samples of sensor ``name`` (gyro, accel, mag, temperature) as :class:`SensorData`:
    one per row of its stream, so that gyro and accel stay row for row; NaN where that row has
    no sample of this sensor (an IMU stream from a CSV without accel columns: accel all NaN; see
    :func:`has_sensor`). Where gyro and accelerometer are sampled apart (:func:`split_imu`),
    each at its own rows and stamps only (:func:`imu_pairs` puts them row for row)."""
    rows = _stream_rows(table, name)
    t_ns, columns = _sensor_columns(table, name, rows)
    idx = np.arange(len(table)) if rows is None else rows
    return SensorData(t_ns=t_ns, values=np.column_stack(columns), rows=idx)


MAX_MAGNITUDE = 1e100
"""The largest magnitude a sample may have to enter a fit. No sensor reports beyond it in SI
units (a damaged cell reads 1e308), and the square of such a value overflows the sums of a
least-squares fit; like NaN and Inf it is left out of fits, and written back as it came."""


def usable(values: np.ndarray) -> np.ndarray:
    """Elementwise: finite and within +-:data:`MAX_MAGNITUDE` (False for NaN and Inf)."""
    return np.abs(values) <= MAX_MAGNITUDE


def finite(data: SensorData) -> tuple[SensorData, int]:
    """The samples of ``data`` whose values are all :func:`usable`, and how many were not (NaN,
    Inf, or beyond :data:`MAX_MAGNITUDE`).

    Stages fit on these samples only; writers keep every sample as it came."""
    ok = usable(data.values).all(axis=1)
    bad = int(len(ok) - np.count_nonzero(ok))
    if bad == 0:
        return data, 0
    return SensorData(t_ns=data.t_ns[ok], values=data.values[ok], rows=data.rows[ok]), bad


def replace_sensor(table: pa.Table, name: str, rows: np.ndarray, values: np.ndarray) -> pa.Table:
    """A copy of ``table`` with sensor ``name`` set to ``values`` (n, k) at ``rows``.

    Rows not listed keep their values; validity (which rows hold a sample) never changes.
    """
    values = np.asarray(values, dtype=np.float64).reshape(len(rows), -1)
    valid = _valid(table, SENSOR_COLUMNS[name][0])
    null_mask = None if valid is None else ~valid
    for i, col in enumerate(SENSOR_COLUMNS[name]):
        full = _column_f64(table, col, None).copy()
        full[rows] = values[:, i]
        idx = table.schema.get_field_index(col)
        table = table.set_column(idx, table.schema.field(idx), arrow_array(full, mask=null_mask))
    return table


def counts(table: pa.Table) -> dict[str, int]:
    """Samples per stream: what a writer must emit, message for message."""
    return {s: int(stream_mask(table, s).sum()) for s in STREAMS if has_stream(table, s)}


def interpolate(t_src_ns: np.ndarray, values: np.ndarray, t_dst_ns: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values`` (n,) or (n, k) sampled at ``t_src_ns`` onto
    ``t_dst_ns``; held constant beyond the ends. The explicit way to put one stream on
    another's timestamps."""
    t0 = t_src_ns[0] if len(t_src_ns) else 0
    xs = (t_src_ns - t0).astype(np.float64)
    xd = (t_dst_ns - t0).astype(np.float64)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        return np.interp(xd, xs, values)
    return np.column_stack([np.interp(xd, xs, values[:, i]) for i in range(values.shape[1])])


def sort_by_time(table: pa.Table) -> tuple[pa.Table, int]:
    """Stable sort by ``t_ns``; returns the table and how many rows were out of order."""
    t = to_numpy(table.column("t_ns"))
    if len(t) < 2 or bool(np.all(t[1:] >= t[:-1])):
        return table, 0
    order = np.argsort(t, kind="stable")
    moved = int(np.count_nonzero(order != np.arange(len(t))))
    return take(table, order), moved


def with_flight_stream(
    table: pa.Table, stream: str, t_ns: np.ndarray, values: np.ndarray
) -> pa.Table:
    """``table`` with the samples of flight stream ``stream`` (:data:`FLIGHT_COLUMNS`) added as
    rows of their own: ``values`` (n, k) at ``t_ns`` (int64 ns), every other column null; rows
    sorted stably by time (the table's rows first at equal stamps). The metadata is kept."""
    return with_flight_streams(table, {stream: (t_ns, values)})


def with_flight_streams(
    table: pa.Table, streams: Mapping[str, tuple[np.ndarray, np.ndarray]]
) -> pa.Table:
    """``table`` with several flight streams added (stream -> (``t_ns``, ``values``)), one
    merge and one stable sort by time: the same table as :func:`with_flight_stream` applied to
    each stream in turn (the table's rows first at equal stamps, then each stream's in the
    order given; the new columns appended in that order), without re-sorting the table once per
    stream."""
    given = []
    for stream, (t_ns, values) in streams.items():
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if len(t_ns):
            cols = FLIGHT_COLUMNS[stream]
            given.append((cols, t_ns, np.asarray(values, np.float64).reshape(len(t_ns), len(cols))))
    if not given:
        return table
    meta = metadata(table)
    schema = table.schema.remove_metadata()
    for cols, _, _ in given:
        for name in cols:
            if name not in schema.names:
                schema = schema.append(OPTIONAL_FIELDS.field(name))
    # the stable sort of the table's rows and then each stream's, by time: row ``order[i]`` of
    # that concatenation is row i of the result; ``moved_to`` is the inverse
    t_all = np.concatenate([to_numpy(table.column("t_ns")), *(t for _, t, _ in given)])
    order = np.argsort(t_all, kind="stable")
    moved_to = np.empty_like(order)
    moved_to[order] = np.arange(len(order))
    n = len(table)
    taken = take(table.drop_columns(["t_ns"]), np.where(order < n, order, -1))  # null: a stream's
    columns: dict[str, pa.Array | pa.ChunkedArray] = {
        "t_ns": arrow_array(t_all[order], pa.int64()),
        **dict(zip(taken.column_names, taken.columns, strict=True)),
    }
    start = n
    for cols, t_ns, values in given:  # each stream's values at its rows' places
        at = moved_to[start : start + len(t_ns)]
        start += len(t_ns)
        for j, name in enumerate(cols):
            if name in columns:
                filled, valid = to_numpy(columns[name]).copy(), valid_mask(columns[name])
            else:
                filled, valid = np.zeros(len(order)), np.zeros(len(order), dtype=bool)
            filled[at], valid[at] = values[:, j], True
            columns[name] = arrow_array(filled, pa.float64(), mask=~valid)
    merged = pa.Table.from_arrays([columns[f.name] for f in schema], schema=schema)
    return with_metadata(merged, meta)


def has_flight_stream(table: pa.Table, stream: str) -> bool:
    """Whether flight stream ``stream`` has at least one sample in ``table``."""
    first = FLIGHT_COLUMNS[stream][0]
    return first in table.schema.names and table.column(first).null_count < len(table)


def flight_stream(table: pa.Table, stream: str) -> SensorData:
    """The samples of flight stream ``stream`` (attitude, position, current) as
    :class:`SensorData` (values (n, k) in the units of :data:`FLIGHT_COLUMNS`); empty when the
    table has none."""
    cols = FLIGHT_COLUMNS[stream]
    if not has_flight_stream(table, stream):
        return SensorData(np.zeros(0, np.int64), np.zeros((0, len(cols))), np.zeros(0, np.int64))
    rows = np.flatnonzero(valid_mask(table.column(cols[0])))
    t_ns = to_numpy(table.column("t_ns"))[rows]
    values = np.column_stack([_column_f64(table, c, rows) for c in cols])
    return SensorData(t_ns=t_ns, values=values, rows=rows)


CARRIED_COLUMNS: tuple[str, ...] = (
    "mag_x",
    "mag_y",
    "mag_z",
    "temperature",
    "temperature_var",
    "ambient_temperature",
    "pressure",
)
"""The value columns :func:`on_imu_rows` carries onto the IMU stream's rows."""


def on_imu_rows(table: pa.Table) -> tuple[pa.Table, dict[str, int]]:
    """``table`` with one row per sample of the ``imu`` stream: the columns of
    :data:`CARRIED_COLUMNS` (magnetometer, temperature, pressure) put on the IMU stamps by
    :func:`interpolate` (linear in time between their own samples, held constant beyond the
    first and last) where an IMU row has no value of its own; a row that has one keeps it.
    Rows of no IMU sample are dropped (a flight stream's with them).

    Returns the table and the number of rows dropped per stream (``mag``, ``temperature``,
    the flight streams) that had rows of their own. A table without IMU samples, or whose every
    row is one, is returned as it is. The metadata records ``rows = "samples"`` and the columns
    filled (``carried``) and the rows left out (``left_out``). For a notebook (``imupipe.read``'s default); the readers and the
    pipeline keep one row per message."""
    imu = stream_mask(table, "imu")
    if not imu.any() or imu.all():
        return table, {}
    dropped: dict[str, int] = {}
    for stream in ("mag", "temperature"):
        n = int(np.count_nonzero(stream_mask(table, stream) & ~imu))
        if n:
            dropped[stream] = n
    for stream in FLIGHT_COLUMNS:
        if has_flight_stream(table, stream):
            dropped[stream] = len(table) - int(table.column(FLIGHT_COLUMNS[stream][0]).null_count)
    rows = np.flatnonzero(imu)
    t_ns = to_numpy(table.column("t_ns"))
    out = take(table, rows)
    carried: list[str] = []
    for name in CARRIED_COLUMNS:
        if name not in table.schema.names:
            continue
        valid = _valid(table, name)
        source = np.ones(len(table), dtype=bool) if valid is None else valid
        if source[rows].all() or not source.any():
            continue  # every IMU row has its own value, or there is none to carry
        values = _column_f64(table, name, None)
        have = source[rows]
        filled = np.where(have, values[rows], interpolate(t_ns[source], values[source], t_ns[rows]))
        index = out.schema.names.index(name)
        out = out.set_column(index, out.schema.field(index), arrow_array(filled, pa.float64()))
        carried.append(name)
    meta = metadata(table)
    meta.update({"rows": "samples", "carried": carried, "left_out": dropped})
    return with_metadata(out, meta), dropped
