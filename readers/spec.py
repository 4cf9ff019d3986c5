"""What to read: an input's path, topics, time source and (for CSV) column mapping."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

TIME_UNITS = {"s": 1e9, "ms": 1e6, "us": 1e3, "ns": 1.0}
GYRO_UNITS = {"rad/s": 1.0, "deg/s": 0.017453292519943295, "raw": 1.0}
G0 = 9.80665
ACCEL_UNITS = {"m/s^2": 1.0, "g": G0, "mg": G0 * 1e-3, "raw": 1.0}
MAG_UNITS = {
    "T": 1.0,
    "mT": 1e-3,
    "uT": 1e-6,
    "nT": 1e-9,
    "gauss": 1e-4,
    "mgauss": 1e-7,
    "raw": 1.0,
}
TEMPERATURE_UNITS = {"degC": 1.0}


@dataclass
class CsvMapping:
    """Which CSV columns hold what, in which unit (converted to SI on reading).

    Columns are named by header name, or by 0-based index (int) for files without a header.
    The defaults are imupipe's own CSV (what ``imupipe simulate`` writes): ``t_ns`` and SI columns.
    """

    time: str | int | None = "t_ns"
    """The time column (name, or 0-based index); none with ``rate_hz``."""
    time_unit: str = "ns"
    """Unit of the time column: s, ms, us or ns."""
    gyro: list[str | int] | None = field(default_factory=lambda: ["gyro_x", "gyro_y", "gyro_z"])
    """The three gyroscope columns (x, y, z)."""
    gyro_unit: str = "rad/s"
    """rad/s, deg/s, or raw (counts, left unscaled)."""
    accel: list[str | int] | None = field(default_factory=lambda: ["accel_x", "accel_y", "accel_z"])
    """The three accelerometer columns (x, y, z)."""
    accel_unit: str = "m/s^2"
    """m/s^2, g, mg, or raw (counts, left unscaled)."""
    mag: list[str | int] | None = field(default_factory=lambda: ["mag_x", "mag_y", "mag_z"])
    """The three magnetometer columns (x, y, z)."""
    mag_unit: str = "T"
    """T, mT, uT, nT, gauss, mgauss, or raw (counts, left unscaled)."""
    temperature: str | int | None = "temperature"
    """The temperature column, degC (after ``scale``/``offset``)."""
    rate_hz: float | None = None
    """Sample rate, Hz: times from the row number instead of a time column."""
    delimiter: str = "auto"
    """``,`` ``;`` ``\\t`` ``whitespace`` (runs of blanks) or ``auto`` (sniffed from the file's
    first 64 KiB)."""
    decimal: str = "auto"
    """The decimal point: ``.``, ``,`` (``1,5``; with a ``;``, tab or blank delimiter) or ``auto``
    (sniffed: ``,`` when the data's numbers are written with a comma)."""
    header: bool | None = None
    """Whether the first line names the columns; None: sniffed (a non-numeric first line)."""
    gyro_file: str | None = None
    """A second file holding the gyro columns, row for row with the main file (imu_tk ships
    ``*_acc.mat`` and ``*_gyro.mat`` with the same timestamps); relative to the config like
    ``path``. Same delimiter and header rules; ``gyro`` names its columns."""
    label: str | int | None = None
    """A text column labelling segments of the log (e.g. imucal's ``part``: x_p, x_rot...);
    goes to the common table's optional ``label`` column."""
    ambient_temperature: str | int | None = "ambient_temperature"
    """The ambient (chamber air) temperature column, degC (optional; used by the ``temperature``
    stage's stepwise model); goes to the common table's optional ``ambient_temperature`` column."""
    skip_rows: int | None = None
    """Lines before the header (or the first data line) to skip, e.g. metadata lines such as
    ``Fs,100``; None: detected (the lines before the block of lines that all have the data's
    number of fields). Skipped lines are reported; a ``rate``/``Fs`` line among them gives the
    sample rate when the file has no time column."""
    comment: str | None = None
    """Lines starting with this text (after blanks), anywhere in the file, are ignored."""
    scale: dict[str, float] | None = None
    """Per column (by name, or index for files without a header): the file's value is
    multiplied by this, then ``offset`` is added, giving the value in the column's unit
    (``gyro_unit``, ..., degC for temperature), which is then converted to SI. For raw
    registers with a known LSB: ``scale = {temp = 0.00390625}``, ``offset = {temp = -231.0}``."""
    offset: dict[str, float] | None = None
    """Per column: added after ``scale`` (see ``scale``)."""
    required: tuple[str, ...] = ()
    """Sensors the user mapped explicitly: a missing column is then an error, not an absent sensor."""


@dataclass
class FieldMapping:
    """Which message fields hold what, for a log of any message type (``[inputs.NAME.fields]``).

    A path is ``"TOPIC.FIELD.PATH"`` (the topic, then field names joined by ``.``; an array
    element by its index, ``gyro_rad.0``). A sensor is one path naming a Vector3-like struct
    (three numeric fields) or a 3-element array, or a list of three scalar paths (x, y, z).
    Each sensor may come from its own topic: each message of a topic is one row of the table,
    the sensors of other topics null on it. Values are converted to SI by the ``*_unit`` keys.
    """

    gyro: str | list[str] | None = None
    """The angular rate (x, y, z)."""
    gyro_unit: str = "rad/s"
    """rad/s, deg/s, or raw (counts, left unscaled)."""
    accel: str | list[str] | None = None
    """The specific force (x, y, z)."""
    accel_unit: str = "m/s^2"
    """m/s^2, g, mg, or raw."""
    mag: str | list[str] | None = None
    """The magnetic field (x, y, z)."""
    mag_unit: str = "T"
    """T, mT, uT, nT, gauss, mgauss, or raw."""
    temperature: str | None = None
    """The temperature, degC: one scalar path."""
    time: str = "header"
    """``header`` (each message's ``header.stamp``), ``log`` (its log time), or a path
    ``"TOPIC.FIELD"`` (an integer or float field in ``time_unit``, or a time struct such as
    ``builtin_interfaces/Time``); a path's field is read on every mapped topic."""
    time_unit: str = "ns"
    """Unit of a numeric time field: s, ms, us or ns."""


@dataclass
class InputSpec:
    """One named input of the config (or one log given to ``convert``)."""

    path: Path
    name: str = "input"
    imu_topic: str | None = None
    gyro_topic: str | None = None
    """A topic of ``sensor_msgs/Imu`` read for its angular_velocity only (a camera's separate
    gyro topic; ``accel_topic`` beside it): each sensor at its own stamps."""
    accel_topic: str | None = None
    """A topic of ``sensor_msgs/Imu`` read for its linear_acceleration only."""
    mag_topic: str | None = None
    temperature_topic: str | None = None
    time: str = "header"
    """``header``: message header stamps; ``log``: the log (receive) time of each message."""
    csv: CsvMapping = field(default_factory=CsvMapping)
    fields: FieldMapping | None = None
    """A field mapping (``[inputs.NAME.fields]``): the sensors read from any message's fields
    instead of from sensor_msgs topics."""
    read_truncated: bool = False
    """Read an MCAP or ROS 1 log that is cut off (a copy or recording stopped part-way) up to
    the cut: every complete chunk before the damage is read and a warning names the byte where
    it starts and the bytes skipped (``--read-truncated``); False: such a log is refused."""
    keys_in: str | None = None
    """Where the user sets this input's keys, as a message says it ("set mag_topic in ..."):
    None for a config's ``[inputs.NAME]`` table; ``imupipe convert`` names its ``--config``
    file, the Python API its keywords. Not a read setting (no hash includes it)."""

    @property
    def settings_place(self) -> str:
        """``[inputs.NAME]``, or :attr:`keys_in` when the keys are set elsewhere."""
        return self.keys_in or f"[inputs.{self.name}]"


@dataclass
class RawMessage:
    """A message of a topic the pipeline does not correct, carried over to the output unchanged
    (ROS 1 payloads already converted to ROS 2 CDR): topic, schema, encodings, payload, times."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    data: bytes
    log_time: int
    publish_time: int
