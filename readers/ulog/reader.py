"""PX4 ULog files (``.ulg``) into the common table: pyulog's parse, done by imupipe's own record
walk (:mod:`imupipe.readers.ulog.records`) or, for a file it leaves out, by pyulog.

A ULog (PX4's log format, https://docs.px4.io/main/en/dev_log/ulog_file_format.html) holds uORB
topics, each possibly in several *instances* (``multi_id``: one per sensor of a kind), the
parameters at start and the firmware's info. imupipe names a topic instance ``<topic>`` for
instance 0 and ``<topic>_<instance>`` for the others (``sensor_gyro``, ``sensor_gyro_1``), as
pyulog's ``ulog2csv`` names its files.

**What fills the streams** (units converted to SI):

| stream | topics (first default) | fields |
|---|---|---|
| ``imu`` | ``sensor_combined`` (PX4's primary IMU, *already corrected* by PX4's ``CAL_*``); ``vehicle_imu[_N]`` (every IMU PX4 integrates, corrected, delta angle and velocity over their interval); or a raw ``sensor_gyro[_N]`` instance with its ``sensor_accel`` partner (see :func:`accel_partner`) | ``gyro_rad``, ``accelerometer_m_s2``; ``delta_angle / delta_angle_dt``, ``delta_velocity / delta_velocity_dt``; or ``x, y, z`` of each |
| ``mag`` | ``vehicle_magnetometer`` (corrected), old firmware's ``sensor_combined.magnetometer_ga``, or a raw ``sensor_mag[_N]`` | gauss -> tesla (x 1e-4) |
| ``temperature`` | the ``temperature`` of the IMU's own ``sensor_gyro`` instance, or any ``sensor_gyro``/``sensor_accel``/``sensor_mag``/``sensor_baro`` instance, or old firmware's ``sensor_combined.baro_temp_celcius`` | degC |

A ``sensor_baro`` instance read as the temperature stream also fills the optional ``pressure``
column (Pa; :func:`baro_pascal`) on the same rows.

Defaults: ``imu_topic`` unset takes ``sensor_combined`` when logged, else the only
``sensor_gyro`` instance (several: an error naming them). ``mag_topic`` unset takes the
magnetometer that matches the IMU's kind (corrected ``vehicle_magnetometer`` or old
``sensor_combined`` with ``sensor_combined``; the only raw ``sensor_mag`` with a raw IMU; the
only magnetometer of a log without an IMU);
``temperature_topic`` unset takes the temperature of the ``sensor_gyro`` instance of the IMU's
device (for ``sensor_combined``: the gyro PX4 selected, ``sensor_selection.gyro_device_id`` or
``CAL_GYRO_PRIME``). When no default applies the stream is left out with a warning naming the
candidates and the key to set.

**Time**: ULog stamps are microseconds since boot (PX4's ``hrt_absolute_time``); imupipe keeps
them as nanoseconds since boot (x 1000), not wall time. The header time is ``timestamp_sample``
where the topic has it (the sensor's sampling instant) and it is not 0 (PX4 v1.14's GPS
topics leave it 0), else ``timestamp``; the log time is
``timestamp`` (publication). A ``sensor_combined`` row keeps PX4's pairing of gyro and accel
(the accel's ``accelerometer_timestamp_relative`` offset, 0 in the logs tested, is not applied
to the row's stamp). A raw gyro sample is paired with the sample of its accelerometer
(:func:`accel_partner`: PX4's own pairing) nearest in ``timestamp_sample`` (within half a gyro
period; PX4's FIFO drivers stamp a chip's two sensors identically); a ``vehicle_imu`` row is
stamped at its ``timestamp_sample``, the end of its integration interval; a gyro sample without a partner keeps NaN accel (counted in a warning), an accel
sample without a partner is not read (counted).

**Metadata** (besides the common keys): ``instance`` (stream -> ``multi_id``), ``device_id``
(stream -> PX4 device id, when known) and ``px4``: ``calibrated`` (stream -> whether PX4 had
already applied its ``CAL_*`` calibration), ``parameters`` (the log's ``CAL_*``, ``TC_*`` and
``SENS_BOARD_*`` values at start), ``software`` and ``hardware``, and for a raw
magnetometer (``sensor_mag``) whose device a ``CAL_MAGn_ID`` names, ``rotation.mag``: the
rotation PX4 applies to it after its calibration, into the body frame (``matrix``, body <-
sensor, and the ``parameters`` it was made of: ``CAL_MAGn_ROT``, ``SENS_BOARD_ROT``,
``SENS_BOARD_{X,Y,Z}_OFF``; :mod:`imupipe.readers.ulog.rotation`).

**Damaged files**: stock pyulog (1.3) ends its parse, without a word, at the first record whose
payload it cannot unpack (a data record of size 0 or 1, an info or dropout record cut short:
its ``struct.error`` is taken for the end of the file), and skips data records of an unknown
``msg_id`` or a wrong size uncounted. A file whose first parse met such damage is parsed again
by a subclass of pyulog's ``ULog`` that skips each damaged record and goes on (what pyulog
does for the damage it knows), recording its offset, size and topic; one warning says how many
records and bytes were skipped, between which offsets, and which topics' messages were among
them (:meth:`UlogFile.damage_warning`). An undamaged file is parsed once, by imupipe's own parse
(:func:`imupipe.readers.ulog.records.parse`: pyulog's result, its record walk compiled), which
leaves every file pyulog would call damaged or warn about to pyulog.

**Not carried**: ULog topics other than the ones read have no ROS message type; they are not
written to the corrected MCAP and one warning lists them.
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import unique
from imupipe.readers.decoded import Piece, repeat_string
from imupipe.readers.errors import ReadError
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import (
    metadata,
    with_flight_streams,
    with_metadata,
    with_stream_column,
)
from imupipe.readers.table_buffer import assemble
from imupipe.readers.topics import NOT_CARRIED, asked_topics, some_of
from imupipe.readers.ulog import records
from imupipe.readers.ulog.rotation import mag_rotation, mag_slot

US_TO_NS = 1000
"""ULog timestamps are microseconds since boot."""
GAUSS = 1e-4
"""Tesla per gauss (PX4 publishes magnetic fields in gauss)."""
RELATIVE_INVALID = 2**31 - 1
"""``sensor_combined``'s ``*_timestamp_relative`` value meaning "no sample" (uORB's
``RELATIVE_TIMESTAMP_INVALID``)."""
READ_TOPICS = (
    "sensor_combined",
    "sensor_gyro",
    "sensor_accel",
    "sensor_mag",
    "vehicle_magnetometer",
    "sensor_baro",
    "sensor_selection",
    "vehicle_imu",
    "vehicle_attitude",
    "vehicle_gps_position",
    "sensor_gps",
    "vehicle_global_position",
    "battery_status",
    "vehicle_thrust_setpoint",
    "actuator_controls_0",
    "vehicle_control_mode",
    "actuator_armed",
    "vehicle_status",
)
"""The topics a read parses (pyulog skips the payload of every other topic)."""
ARMED_STATE = (
    ("vehicle_control_mode", "flag_armed", 1),
    ("actuator_armed", "armed", 1),
    ("vehicle_status", "arming_state", 2),
)
"""Where a log says the vehicle is armed (topic, field, the armed value: ``ARMING_STATE_ARMED``
= 2), in the order tried; ``VehicleMagnetometer`` reads ``vehicle_control_mode.flag_armed``."""
PARAMETER_PREFIXES = ("CAL_", "TC_", "SENS_BOARD_")
"""Parameters kept in the table's metadata (calibration, thermal compensation, board rotation)."""
TEMPERATURE_TOPICS = ("sensor_gyro", "sensor_accel", "sensor_mag", "sensor_baro")
VEHICLE_IMU_FIELDS = (
    "delta_angle[0]",
    "delta_velocity[0]",
    "delta_angle_dt",
    "delta_velocity_dt",
)
"""The ``vehicle_imu`` fields a read needs."""
CALIBRATED_TOPICS = ("sensor_combined", "vehicle_imu", "vehicle_magnetometer")
"""Topics PX4 publishes after applying its ``CAL_*`` (and thermal) corrections."""


def topic_key(name: str, instance: int) -> str:
    """``sensor_gyro``, ``sensor_gyro_1``: how imupipe names a topic instance."""
    return name if instance == 0 else f"{name}_{instance}"


@dataclass(frozen=True)
class Instance:
    """One logged instance of a uORB topic: its name, ``multi_id`` and field arrays."""

    name: str
    instance: int
    data: Mapping[str, np.ndarray]

    @property
    def key(self) -> str:
        return topic_key(self.name, self.instance)

    def __len__(self) -> int:
        return int(len(self.data["timestamp"]))

    def has(self, *fields: str) -> bool:
        return all(f in self.data for f in fields)

    def vector(self, *fields: str) -> np.ndarray:
        """(n, k) float64 of the given fields."""
        return np.column_stack([self.data[f].astype(np.float64) for f in fields])

    def stamps(self, time: str) -> tuple[np.ndarray, np.ndarray]:
        """(header, log) times in ns: ``timestamp_sample`` (or ``timestamp``), ``timestamp``.
        A ``timestamp_sample`` of 0 is "not set" (PX4 v1.14's ``vehicle_gps_position`` leaves
        it 0 in every message: the GPS drivers do not fill it): that message's ``timestamp``."""
        log = self.data["timestamp"].astype(np.int64) * US_TO_NS
        if time == "header" and "timestamp_sample" in self.data:
            sample = self.data["timestamp_sample"].astype(np.int64) * US_TO_NS
            return np.where(sample == 0, log, sample), log
        return log, log

    def device_id(self) -> int | None:
        ids = self.data.get("device_id")
        return int(ids[0]) if ids is not None and len(ids) else None


class UlogFile:
    """A ULog read with pyulog (the whole file, or only ``topics``); also the
    :class:`~imupipe.readers.sources.LogSource` view ``inspect`` uses (topics and their stamps)."""

    format = "ulog"

    def __init__(self, path: str | Path, topics: Sequence[str] | None = None) -> None:
        from pyulog.core import ULogException

        self.path = Path(path)
        if not self.path.is_file():
            raise ReadError(f"{self.path}: no such file")
        wanted = None if topics is None else _TopicFilter(topics)
        said = io.StringIO()  # pyulog prints its corruption notices: keep them for a warning
        try:
            with contextlib.redirect_stdout(said):
                self.ulog, cut = _parse(self.path, wanted)
        except ULogException as exc:
            raise ReadError(f"{self.path}: not a readable ULog file ({exc})") from None
        except (OSError, ValueError, IndexError, KeyError, TypeError, struct.error) as exc:
            raise ReadError(
                f"{self.path}: corrupt ULog file ({type(exc).__name__}: {exc})"
            ) from None
        self.notices = [line for line in said.getvalue().splitlines() if line.strip()]
        """What pyulog said while parsing (corruption it skipped)."""
        self.instances: dict[str, Instance] = {}
        for d in sorted(self.ulog.data_list, key=lambda d: (d.name, d.multi_id)):
            inst = Instance(d.name, int(d.multi_id), d.data)
            if "timestamp" in d.data:  # a damaged format definition can lose it
                self.instances[inst.key] = inst
            else:
                self.notices.append(f"topic {inst.key} has no timestamp field: not read")
        self._named: dict[str, list[Instance]] | None = None
        """Topic name -> its instances, once made (:meth:`named`)."""
        self.imu_pairs: dict[int, int] | None = None
        """:func:`_imu_pairs`, once made."""
        self.skipped: list[str] = [] if wanted is None else sorted(wanted.seen - wanted.names)
        """Topics the log holds that were not parsed (names, every instance)."""
        self.damage: list[Damage] = list(getattr(self.ulog, "damage", ()))
        """The damaged records the parse skipped (offset, bytes, what), in file order."""
        if cut is not None:
            at, claimed, left = cut
            self.damage.append(
                Damage(at, left, f"the file ends inside a record ({left} of {claimed} bytes)")
            )

    def damage_warning(self) -> str | None:
        """One line saying what the parse skipped (where, how many records and bytes), or
        None for an undamaged file."""
        if not self.damage and not (self.ulog.file_corruption or self.notices):
            return None
        if not self.damage:
            said = f"; pyulog: {self.notices[0]}" if self.notices else ""
            return f"the file is corrupt in places (the damaged messages were skipped{said})"
        nbytes = sum(d.size for d in self.damage)
        first, last = self.damage[0], self.damage[-1]
        topics = sorted({d.topic for d in self.damage if d.topic})
        named = f"; messages of {', '.join(topics)} among them" if topics else ""
        where = (
            f"at byte {first.offset}"
            if len(self.damage) == 1
            else f"between bytes {first.offset} and {last.offset + last.size}"
        )
        return (
            f"the file is damaged: {len(self.damage)} records skipped ({nbytes} bytes) {where}"
            f"{named} (first: {first.what} at byte {first.offset}); the rest was read"
        )

    # -- LogSource view, for inspect ----------------------------------------------------------
    def topic_types(self) -> dict[str, str]:
        """Topic instance -> its uORB message name."""
        return {k: v.name for k, v in self.instances.items()}

    def topic_counts(self) -> dict[str, int]:
        return {k: len(v) for k, v in self.instances.items()}

    def first_time(self) -> int:
        return int(self.ulog.start_timestamp) * US_TO_NS

    def topic_times(self) -> dict[str, np.ndarray]:
        return {k: v.stamps("log")[1] for k, v in self.instances.items()}

    # -- what the log says about itself --------------------------------------------------------
    def parameters(self) -> dict[str, float | int]:
        """The calibration-related parameters at start (:data:`PARAMETER_PREFIXES`)."""
        params = self.ulog.initial_parameters
        kept = sorted([k for k in params if k.startswith(PARAMETER_PREFIXES)])  # keys: str
        return {
            k: v if isinstance(v, int) else float(v)
            for k in kept
            if isinstance(v := params[k], int | float)
        }

    def info(self, key: str) -> str | None:
        value = self.ulog.msg_info_dict.get(key)
        return None if value is None else str(value)

    def named(self, name: str) -> list[Instance]:
        if self._named is None:  # one pass over the instances, in their order
            self._named = {}
            for v in self.instances.values():
                self._named.setdefault(v.name, []).append(v)
        return list(self._named.get(name, ()))

    def dropouts(self) -> tuple[int, int]:
        """(count, total ms) of the logger's dropouts."""
        drops = self.ulog.dropouts
        return len(drops), int(sum(d.duration for d in drops))


@dataclass(frozen=True)
class Damage:
    """A damaged ULog record skipped by the parse: its offset in the file, the bytes skipped,
    what was wrong and, for a data record of a known subscription, its topic."""

    offset: int
    size: int
    what: str
    topic: str = ""


class _Ending(io.BufferedReader):
    """The log file as pyulog reads it, remembering where the parse ended (``end``, at
    ``close``) and the file's ``size``."""

    def __init__(self, path: Path) -> None:
        super().__init__(io.FileIO(path, "rb"))
        self.size = os.fstat(self.fileno()).st_size
        self.end = self.size
        self.cut: tuple[int, int, int] | None = None

    def close(self) -> None:
        if not self.closed:
            self.end = self.tell()
        super().close()


class _Probe(_Ending):
    """:class:`_Ending` that also remembers a read cut short by the end of the file (``cut``:
    offset, bytes asked, bytes left): pyulog ends its parse there without a word."""

    def read(self, n: int = -1, /) -> bytes:
        data = super().read(n)
        if 0 < len(data) < n:
            self.cut = (self.tell() - len(data), n, len(data))
        return data


PYULOG_RECORDS = (
    "_MessageInfo",
    "_MessageParameterDefault",
    "_MessageAddLogged",
    "MessageLogging",
    "MessageLoggingTagged",
    "MessageDropout",
    "MessageFormat",
)
"""pyulog's record classes whose decoding of a damaged payload can raise ``struct.error``,
which pyulog takes for the end of the file (``_read_file_data``'s ``except struct.error``)."""


def _parse(path: Path, wanted: _TopicFilter | None) -> tuple[Any, tuple[int, int, int] | None]:
    """pyulog's parse of ``path``, and the last record cut by the end of the file when known.

    The parse is imupipe's own (:func:`imupipe.readers.ulog.records.parse`: pyulog's result,
    the record walk compiled) for every file it handles; for the others (damage, records pyulog
    warns about) a first parse is pyulog's own; when it met damage (``_file_corrupt``), ended
    before the end of the file (a record it could not unpack) or walked records that do not end
    at the end of the file (a record cut, or a damaged size field that sent the parse past the
    end: pyulog takes either for the end of the log), the file is parsed again by
    :func:`_ulog_classes`' tolerant class, which reads past the damaged records and says where
    they are."""
    own = records.parse(path, None if wanted is None else wanted.names)
    if own is not None:
        ulog, seen, cut = own
        if wanted is not None:
            wanted.seen |= seen
        return ulog, cut
    fast, tolerant = _ulog_classes()
    with _Ending(path) as handle:
        ulog = fast(handle, wanted)
    if not ulog.damaged and handle.end >= handle.size:
        if ulog.data_end == handle.size:
            return ulog, None
        if ulog.data_end > handle.size:  # the last record is cut: everything before it was read
            at = ulog.data_end - 3 - ulog.last_size
            return ulog, (at, 3 + ulog.last_size, handle.size - at)
        if handle.size - ulog.data_end < 3:  # a header cut
            return ulog, (ulog.data_end, 3, handle.size - ulog.data_end)
    with _Probe(path) as handle:
        ulog = tolerant(handle, wanted)
    return ulog, handle.cut


@functools.cache
def _ulog_classes() -> tuple[type, type]:
    """pyulog's ``ULog``, reading past damaged records and counting them (``damage``).

    Stock pyulog 1.3 ends its parse at the first record whose payload is too short to unpack
    (a data record of size 0 or 1, an info or dropout record cut short: its ``struct.error`` is
    taken for the end of the file) and skips a data record of an unknown ``msg_id`` or a wrong
    size without saying where. This subclass makes such a record one skipped record (pyulog's
    own handling of a corrupt record: ``_file_corrupt`` set, the parse goes on at the next
    record) and records each skip: its offset, bytes and topic when known."""
    import struct as _struct

    from pyulog import ULog

    class Data(ULog._MessageData):  # type: ignore[name-defined]
        def initialize(self, data: bytes, header: Any, subscriptions: Any, ulog: Any) -> bool:
            if len(data) >= 2 and not super().initialize(data, header, subscriptions, ulog):
                return False
            self.timestamp = 0
            at = ulog._file_handle.tell() - len(data) - 3
            if len(data) < 2:
                ulog._note(at, 3 + len(data), f"a data record of {len(data)} bytes")
            else:
                msg_id = int.from_bytes(data[:2], "little")
                sub = subscriptions.get(msg_id)
                if sub is None:
                    what, topic = f"a data record of unknown msg_id {msg_id}", ""
                else:
                    what = f"a data record of {len(data) - 2} bytes for {sub.message_name}"
                    topic = str(sub.message_name)
                ulog._note(at, 3 + len(data), what, topic)
            return True

    def tolerant(cls: type, name: str) -> type:
        def init(self: Any, data: bytes, header: Any, *args: Any, **kwargs: Any) -> None:
            try:
                cls.__init__(self, data, header, *args, **kwargs)
            except UnicodeDecodeError:
                raise
            except (_struct.error, IndexError, KeyError, ValueError, OverflowError) as exc:
                owner = _PARSING[-1]
                at = owner._file_handle.tell() - len(data) - 3
                owner._note(at, 3 + len(data), f"a {name.strip('_')} record ({exc})")
                raise ValueError(str(exc)) from None

        return type(cls.__name__, (cls,), {"__init__": init})

    header_fields = _struct.Struct("<HB").unpack

    class Header(ULog._MessageHeader):  # type: ignore[name-defined]
        """pyulog's record header, summing the lengths of the records it was read for
        (``walked``)."""

        walked = 0

        def initialize(self, data: bytes) -> None:
            self.msg_size, self.msg_type = header_fields(data)
            self.walked += 3 + self.msg_size

    class Fast(ULog):  # type: ignore[misc, valid-type]
        """pyulog's ``ULog`` noting whether it met a damaged record (``damaged``) and where the
        records it walked in its last data section end (``data_end``: past the end of the
        file when the last record was cut, or a damaged size field sent the parse there)."""

        damaged = False
        damage: tuple[Damage, ...] = ()
        header: Any = None
        last_size = 0
        data_end = -1

        def _MessageHeader(self) -> Any:  # noqa: N802 - pyulog's name
            self.header = Header()
            return self.header

        def _check_packet_corruption(self, header: Any) -> bool:
            # called for a record of a type pyulog does not know only: skipped, so said
            self.damaged = True
            return bool(super()._check_packet_corruption(header))

        def _read_file_data(self, *args: Any, **kwargs: Any) -> None:
            start = self._file_handle.tell()
            super()._read_file_data(*args, **kwargs)  # its first call makes self.header
            self.data_end = start + self.header.walked
            self.last_size = self.header.msg_size

        @property
        def _file_corrupt(self) -> bool:
            return bool(self.__dict__.get("_corrupt", False))

        @_file_corrupt.setter
        def _file_corrupt(self, value: bool) -> None:
            self.__dict__["_corrupt"] = value
            if value:
                self.damaged = True

    class Tolerant(Fast):
        _MessageData = Data

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            self.damage: list[Damage] = []
            _PARSING.append(self)
            try:
                super().__init__(*args, **kwargs)
            finally:
                _PARSING.pop()

        def _note(self, at: int, size: int, what: str, topic: str = "") -> None:
            self.damage.append(Damage(int(at), int(size), what, topic))

        def _check_packet_corruption(self, header: Any) -> bool:
            corrupt = bool(super()._check_packet_corruption(header))
            at = self._file_handle.tell() - 3 - header.msg_size
            if corrupt:  # pyulog steps one byte on and looks for the next record
                self._note(
                    at, 1, f"a record header (type {header.msg_type}, {header.msg_size} bytes)"
                )
            else:  # a record of a type pyulog does not know: skipped whole
                self._note(at, 3 + header.msg_size, f"a record of unknown type {header.msg_type}")
            return corrupt

        def _find_sync(self, last_n_bytes: int = -1) -> bool:
            start = self._file_handle.tell()
            found = bool(super()._find_sync(last_n_bytes))
            if found and self._file_handle.tell() > start:
                self._note(start, self._file_handle.tell() - start, "bytes up to the next sync")
            return found

    for name in PYULOG_RECORDS:
        setattr(Tolerant, name, tolerant(getattr(ULog, name), name))
    return Fast, Tolerant


_PARSING: list[Any] = []
"""The tolerant ULogs being parsed (innermost last): the record classes report to it."""


class _TopicFilter:
    """pyulog's ``message_name_filter_list``: parse only ``names``, remember every topic asked
    about (pyulog keeps nothing of the topics it filters out)."""

    def __init__(self, names: Sequence[str]) -> None:
        self.names = set(names)
        self.seen: set[str] = set()

    def __contains__(self, name: object) -> bool:
        self.seen.add(str(name))
        return name in self.names


# -- choosing the topics -------------------------------------------------------------------------


def _old_combined(f: UlogFile, prefix: str) -> Instance | None:
    """Old firmware's ``sensor_combined`` when it holds valid ``<prefix>_timestamp_relative``
    samples (magnetometer or baro)."""
    inst = f.instances.get("sensor_combined")
    if inst is None or f"{prefix}_timestamp_relative" not in inst.data:
        return None
    rel = inst.data[f"{prefix}_timestamp_relative"]
    return inst if bool(np.any(rel != RELATIVE_INVALID)) else None


def _imu_pairs(f: UlogFile) -> dict[int, int]:
    """Gyro device id -> accel device id, as PX4 paired them in ``vehicle_imu`` (every
    message of every instance; a pair with a zero id is no pair); made once per file."""
    if f.imu_pairs is None:
        f.imu_pairs = _pairs_of(f)
    return f.imu_pairs


def _pairs_of(f: UlogFile) -> dict[int, int]:
    pairs: dict[int, int] = {}
    for imu in f.named("vehicle_imu"):
        if not imu.has("gyro_device_id", "accel_device_id"):
            continue
        both = np.column_stack(
            [imu.data["gyro_device_id"].astype(np.int64), imu.data["accel_device_id"]]
        )
        for gyro_id, accel_id in unique(both, axis=0).tolist():
            if gyro_id and accel_id:
                pairs.setdefault(gyro_id, accel_id)
    return pairs


def accel_partner(f: UlogFile, gyro: Instance) -> Instance | None:
    """The ``sensor_accel`` instance PX4 pairs with a ``sensor_gyro`` instance.

    PX4's ``sensors`` module builds ``VehicleIMU(i, accel_index=i, gyro_index=i)``: instance
    *i* of ``sensor_accel`` with instance *i* of ``sensor_gyro``
    (``src/modules/sensors/sensors.cpp``, ``InitializeVehicleIMU``), and ``vehicle_imu``
    records the pair's ``accel_device_id`` and ``gyro_device_id``. The partner is, in order:
    the accel of the device ``vehicle_imu`` pairs with the gyro's device (an accelerometer and
    a gyroscope of one chip are two devices, e.g. a BMI055); the accel of the same device id;
    the accel of the same instance number.
    """
    accels = f.named("sensor_accel")
    dev = gyro.device_id()
    wanted = [_imu_pairs(f).get(dev), dev] if dev is not None else []
    for want in wanted:
        for acc in accels:
            if want is not None and acc.device_id() == want:
                return acc
    same = [a for a in accels if a.instance == gyro.instance]
    return same[0] if same else None


def candidates(f: UlogFile) -> dict[str, list[str]]:
    """Stream -> the topic instances that can fill it, defaults first."""
    imu = [k for k in ("sensor_combined",) if k in f.instances]
    imu += [v.key for v in f.named("vehicle_imu") if v.has(*VEHICLE_IMU_FIELDS)]
    imu += [g.key for g in f.named("sensor_gyro") if accel_partner(f, g) is not None]
    mag = [v.key for v in f.named("vehicle_magnetometer")]
    mag += ["sensor_combined"] if _old_combined(f, "magnetometer") else []
    mag += [v.key for v in f.named("sensor_mag")]
    temperature = [
        v.key for name in TEMPERATURE_TOPICS for v in f.named(name) if v.has("temperature")
    ]
    temperature += ["sensor_combined"] if _old_combined(f, "baro") else []
    return {"imu": imu, "mag": mag, "temperature": temperature}


def _selected_gyro_device(f: UlogFile) -> int | None:
    """The gyro device PX4 used for ``sensor_combined``: ``sensor_selection.gyro_device_id``
    (first message), else ``CAL_GYRO_PRIME`` (older firmware)."""
    sel = f.instances.get("sensor_selection")
    if sel is not None and "gyro_device_id" in sel.data and len(sel):
        return int(sel.data["gyro_device_id"][0])
    prime = f.ulog.initial_parameters.get("CAL_GYRO_PRIME")
    return int(prime) if prime else None


def _imu_gyro_device(f: UlogFile, key: str) -> int | None:
    """The gyro device of an IMU topic instance: its own ``device_id`` (``sensor_gyro``), the
    first ``gyro_device_id`` (``vehicle_imu``) or the gyro PX4 selected (``sensor_combined``)."""
    inst = f.instances[key]
    if inst.name == "sensor_combined":
        return _selected_gyro_device(f)
    if inst.name == "vehicle_imu":
        ids = inst.data.get("gyro_device_id")
        return int(ids[0]) if ids is not None and len(ids) else None
    return inst.device_id()


def choose_topics(spec: InputSpec, f: UlogFile) -> tuple[dict[str, str], list[str]]:
    """Stream -> topic instance, from the spec's topic settings and the log (see the module
    docstring); returns (choice, warnings). A setting naming a topic that cannot fill its
    stream is an error listing the ones that can."""
    cands = candidates(f)
    chosen, off = asked_topics(spec, cands, f.instances, f.path, "ULog topics")
    warnings: list[str] = []
    if "imu" not in chosen and "imu" not in off:
        raw = [k for k in cands["imu"] if f.instances[k].name == "sensor_gyro"]
        integrated = [k for k in cands["imu"] if f.instances[k].name == "vehicle_imu"]
        if "sensor_combined" in cands["imu"]:
            chosen["imu"] = "sensor_combined"
        elif len(raw) == 1 or (not raw and len(integrated) == 1):
            chosen["imu"] = (raw or integrated)[0]
        elif raw or integrated:
            raise ReadError(
                f"{f.path}: several IMU instances ({', '.join(raw + integrated)}); set "
                f"imu_topic in {spec.settings_place}"
            )
    imu = chosen.get("imu")
    raw_imu = imu is not None and f.instances[imu].name == "sensor_gyro"
    if "mag" not in chosen and "mag" not in off:
        if raw_imu:
            pick = [k for k in cands["mag"] if k.startswith("sensor_mag")]
        elif imu is None:  # a log without an IMU (a compass-only flight): its only magnetometer
            pick = list(cands["mag"])
        else:
            pick = [k for k in cands["mag"] if not k.startswith("sensor_mag")]
        if len(pick) == 1:
            chosen["mag"] = pick[0]
        elif cands["mag"]:
            warnings.append(
                f"magnetometer not read: several candidates ({', '.join(cands['mag'])}); "
                f"set mag_topic in {spec.settings_place}"
            )
    if "temperature" not in chosen and imu is not None and "temperature" not in off:
        device = _imu_gyro_device(f, imu)
        own = [
            g.key
            for g in f.named("sensor_gyro")
            if g.has("temperature") and device is not None and g.device_id() == device
        ]
        if len(own) == 1:
            chosen["temperature"] = own[0]
        elif cands["temperature"]:
            warnings.append(
                "temperature not read: the IMU's own sensor_gyro instance is not logged; "
                f"candidates: {', '.join(cands['temperature'])}; set temperature_topic in "
                f"{spec.settings_place}"
            )
    if "imu" not in chosen and "mag" not in chosen and "temperature" not in chosen:
        raise ReadError(
            f"{f.path}: no IMU, magnetometer or temperature topic (sensor_combined, "
            f"sensor_gyro/sensor_accel, sensor_mag, vehicle_magnetometer); topics: "
            f"{', '.join(f.instances) or 'none'}"
        )
    return chosen, warnings


# -- decoding ------------------------------------------------------------------------------------


def _piece(stamp: np.ndarray, log: np.ndarray, columns: dict[str, np.ndarray]) -> Piece:
    return Piece(stamp, log, repeat_string("", len(stamp)), columns, one_frame="")


def _xyz(prefix: str, values: np.ndarray) -> dict[str, np.ndarray]:
    return {f"{prefix}_{a}": np.ascontiguousarray(values[:, i]) for i, a in enumerate("xyz")}


def _pair(gyro_t: np.ndarray, accel_t: np.ndarray) -> np.ndarray:
    """For each gyro stamp, the index of the nearest accel stamp within half the median gyro
    period (-1: none); each accel sample is used at most once (first come)."""
    if len(accel_t) == 0 or len(gyro_t) == 0:
        return np.full(len(gyro_t), -1, dtype=np.int64)
    order = np.argsort(accel_t, kind="stable")
    sorted_t = accel_t[order]
    pos = (
        np.clip(np.searchsorted(sorted_t, gyro_t), 1, len(sorted_t) - 1)
        if len(sorted_t) > 1
        else np.zeros(len(gyro_t), dtype=np.int64)
    )
    left = np.maximum(pos - 1, 0)
    pick = np.where(np.abs(sorted_t[left] - gyro_t) <= np.abs(sorted_t[pos] - gyro_t), left, pos)
    half = np.median(np.diff(gyro_t)) / 2 if len(gyro_t) > 1 else np.inf
    idx = np.where(np.abs(sorted_t[pick] - gyro_t) <= half, order[pick], -1)
    valid = idx >= 0
    _, first = np.unique(idx[valid], return_index=True)
    keep = np.zeros(int(valid.sum()), dtype=bool)
    keep[first] = True
    out = np.full(len(gyro_t), -1, dtype=np.int64)
    out[np.flatnonzero(valid)[keep]] = idx[valid][keep]
    return out


def _vehicle_imu_rates(inst: Instance, warnings: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(gyro rad/s, accel m/s^2) of ``vehicle_imu``: ``delta_angle`` (rad) over
    ``delta_angle_dt`` and ``delta_velocity`` (m/s) over ``delta_velocity_dt`` (both
    microseconds, ``msg/VehicleImu.msg``): the mean rate and specific force over the
    integration interval that ends at ``timestamp_sample``. A zero interval gives NaN
    (counted in a warning)."""
    rates = []
    for delta, dt_field in (
        ("delta_angle", "delta_angle_dt"),
        ("delta_velocity", "delta_velocity_dt"),
    ):
        dt = inst.data[dt_field].astype(np.float64) * 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            value = inst.vector(*(f"{delta}[{i}]" for i in range(3))) / dt[:, None]
        empty = dt <= 0
        value[empty] = np.nan
        if empty.any():
            warnings.append(
                f"topic {inst.key}: {int(empty.sum())} messages with {dt_field} = 0 (read as NaN)"
            )
        rates.append(value)
    return rates[0], rates[1]


def _imu_piece(f: UlogFile, key: str, time: str, warnings: list[str]) -> Piece:
    inst = f.instances[key]
    if inst.name == "vehicle_imu":
        stamp, log = inst.stamps(time)
        gyro, accel = _vehicle_imu_rates(inst, warnings)
        return _piece(stamp, log, {**_xyz("gyro", gyro), **_xyz("accel", accel)})
    if key == "sensor_combined":
        stamp, log = inst.stamps(time)
        gyro = inst.vector(*(f"gyro_rad[{i}]" for i in range(3)))
        accel = inst.vector(*(f"accelerometer_m_s2[{i}]" for i in range(3)))
        return _piece(stamp, log, {**_xyz("gyro", gyro), **_xyz("accel", accel)})
    acc = accel_partner(f, inst)
    assert acc is not None  # a candidate has a partner
    stamp, log = inst.stamps(time)
    acc_stamp, _ = acc.stamps("header")
    match = _pair(inst.stamps("header")[0], acc_stamp)
    accel = np.full((len(inst), 3), np.nan)
    paired = match >= 0
    accel[paired] = acc.vector("x", "y", "z")[match[paired]]
    lonely_gyro = int(np.count_nonzero(~paired))
    lonely_accel = len(acc) - int(np.count_nonzero(paired))
    if lonely_gyro or lonely_accel:
        warnings.append(
            f"topic {key}: {lonely_gyro} gyro samples have no {acc.key} sample within half a "
            f"period (accel NaN) and {lonely_accel} {acc.key} samples no gyro sample (not read)"
        )
    offsets = np.abs(acc_stamp[match[paired]] - inst.stamps("header")[0][paired])
    if len(offsets) and offsets.max() > 0:
        warnings.append(
            f"topic {key}: gyro and {acc.key} samples paired by nearest timestamp_sample, up "
            f"to {offsets.max() / 1e6:.3f} ms apart"
        )
    return _piece(stamp, log, {**_xyz("gyro", inst.vector("x", "y", "z")), **_xyz("accel", accel)})


def _relative(inst: Instance, prefix: str) -> np.ndarray:
    """Row indices of old ``sensor_combined``'s distinct ``<prefix>`` samples: a sample repeats
    on every row until the next arrives (same absolute stamp)."""
    rel = inst.data[f"{prefix}_timestamp_relative"].astype(np.int64)
    t = inst.data["timestamp"].astype(np.int64) + rel
    valid = np.flatnonzero(rel != RELATIVE_INVALID)
    _, first = np.unique(t[valid], return_index=True)
    return valid[np.sort(first)]


def _combined_sub(
    inst: Instance, prefix: str, time: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, header stamps, log stamps) of old ``sensor_combined``'s distinct ``<prefix>``
    samples (magnetometer or baro)."""
    rows = _relative(inst, prefix)
    log = inst.data["timestamp"].astype(np.int64)[rows] * US_TO_NS
    rel = inst.data[f"{prefix}_timestamp_relative"].astype(np.int64)[rows] * US_TO_NS
    return rows, (log + rel) if time == "header" else log, log


def _mag_piece(f: UlogFile, key: str, time: str) -> Piece:
    inst = f.instances[key]
    if inst.name == "sensor_combined":
        rows, stamp, log = _combined_sub(inst, "magnetometer", time)
        values = inst.vector(*(f"magnetometer_ga[{i}]" for i in range(3)))[rows]
    else:
        stamp, log = inst.stamps(time)
        fields = (
            ("x", "y", "z")
            if inst.name == "sensor_mag"
            else tuple(f"magnetometer_ga[{i}]" for i in range(3))
        )
        values = inst.vector(*fields)
    return _piece(stamp, log, _xyz("mag", values * GAUSS))


def _temperature_piece(f: UlogFile, key: str, time: str) -> Piece:
    inst = f.instances[key]
    if inst.name == "sensor_combined":
        rows, stamp, log = _combined_sub(inst, "baro", time)
        values = inst.data["baro_temp_celcius"].astype(np.float64)[rows]
    else:
        stamp, log = inst.stamps(time)
        values = inst.data["temperature"].astype(np.float64)
    return _piece(stamp, log, {"temperature": values})


def _device_id(f: UlogFile, stream: str, key: str) -> int | None:
    inst = f.instances[key]
    if inst.device_id() is not None:
        return inst.device_id()
    if stream == "imu":
        return _imu_gyro_device(f, key)
    if stream == "mag" and inst.name != "sensor_mag":
        prime = f.ulog.initial_parameters.get("CAL_MAG_PRIME")
        return int(prime) if prime else None
    return None


def _samples(f: UlogFile, stream: str, key: str) -> int:
    """How many samples a read of ``stream`` from ``key`` gives."""
    inst = f.instances[key]
    if inst.name == "sensor_combined" and stream != "imu":
        return len(_relative(inst, "magnetometer" if stream == "mag" else "baro"))
    return len(inst)


def _mag_rotation(
    px4: Mapping[str, Any], device_id: int | None, warnings: list[str]
) -> dict[str, Any] | None:
    """The rotation PX4 applies to the raw magnetometer read (``sensor_mag``) after its
    calibration, into the body frame (:func:`imupipe.readers.ulog.rotation.mag_rotation`):
    ``{"matrix": R (3x3, body <- sensor), "parameters": the ones it was made of}``; None for a
    field PX4 had already corrected (``vehicle_magnetometer``: body frame), a device no
    ``CAL_MAGn_ID`` names, or a rotation PX4 does not define (warned)."""
    if device_id is None or (px4.get("calibrated") or {}).get("mag", True):
        return None
    params = px4.get("parameters") or {}
    slot = mag_slot(params, int(device_id))
    if slot is None:
        return None
    try:
        matrix, used = mag_rotation(params, slot)
    except ValueError as exc:
        warnings.append(f"magnetometer {device_id}: {exc}; its rotation to the body is unknown")
        return None
    return {"matrix": matrix.tolist(), "parameters": used}


def _calibrated(f: UlogFile, chosen: Mapping[str, str]) -> dict[str, bool]:
    """Stream -> whether PX4 had applied its ``CAL_*`` corrections (imu and mag streams)."""
    return {
        s: f.instances[k].name in CALIBRATED_TOPICS for s, k in chosen.items() if s != "temperature"
    }


MILLIBAR_BELOW = 2000.0
"""A ``sensor_baro.pressure`` median below this is millibar (PX4 up to v1.12 logged millibar,
later firmware pascal; Earth's air pressure is 30-110 kPa, so the ranges never overlap)."""


def baro_pascal(baro: Instance) -> np.ndarray:
    """A ``sensor_baro`` instance's pressure in Pa (millibar x 100 for older firmware)."""
    p = baro.data["pressure"].astype(np.float64)
    return p * 100.0 if len(p) and np.nanmedian(p) < MILLIBAR_BELOW else p


def output_topic(stream: str, inst: Instance) -> str:
    """The table's (and the corrected MCAP's) topic name of a stream read from ``inst``: the
    instance's key, with ``/temperature`` (or ``/magnetometer`` for old firmware's
    ``sensor_combined``) appended when the stream is one field of a topic that carries more: a
    ROS topic has one message type."""
    if stream == "temperature":
        return f"{inst.key}/temperature"
    if stream == "mag" and inst.name == "sensor_combined":
        return f"{inst.key}/magnetometer"
    return inst.key


def _position(inst: Instance) -> np.ndarray | None:
    """(n, 3) latitude, longitude (deg), altitude (m AMSL) of a GNSS or global-position topic:
    ``latitude_deg``/``longitude_deg``/``altitude_msl_m`` (PX4 1.14+), ``lat``/``lon`` as 1e-7
    deg integers with ``alt`` in mm (older ``vehicle_gps_position``), or ``lat``/``lon`` as deg
    with ``alt`` in m (``vehicle_global_position``)."""
    if inst.has("latitude_deg", "longitude_deg", "altitude_msl_m"):
        return inst.vector("latitude_deg", "longitude_deg", "altitude_msl_m")
    if not inst.has("lat", "lon", "alt"):
        return None
    lla = inst.vector("lat", "lon", "alt")
    if inst.data["lat"].dtype.kind in "iu":
        lla *= np.array([1e-7, 1e-7, 1e-3])
    return lla


def flight_streams(f: UlogFile, time: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The flight streams the log holds (see :data:`~imupipe.readers.table.FLIGHT_COLUMNS`),
    stream -> (t_ns, values), stamped as the sensors are (``time``):

    - ``attitude``: ``vehicle_attitude`` ``q[0..3]`` (w, x, y, z; body FRD -> NED);
    - ``position``: ``vehicle_gps_position`` (or ``sensor_gps``) instance 0 with ``fix_type``
      >= 3, else ``vehicle_global_position``;
    - ``current``: ``battery_status`` instance 0 ``current_a`` (A), where it is measured (PX4
      logs -1 for "unknown");
    - ``throttle``: what PX4's throttle-based magnetometer power compensation
      (``CAL_MAG_COMP_TYP = 1``) multiplies ``CAL_MAGn_*COMP`` by, 0..1: the norm of
      ``vehicle_thrust_setpoint`` instance 0 ``xyz`` (PX4 v1.14 and later), else
      ``actuator_controls_0`` ``control[3]`` (``INDEX_THROTTLE``, up to v1.13), and 0 while the
      vehicle is disarmed (:data:`ARMED_STATE`, step-held onto the setpoint's stamps; disarmed
      before the first message, as PX4 starts; kept as logged when no arming topic is logged).
      Source: ``VehicleMagnetometer::UpdatePowerCompensation`` in
      ``src/modules/sensors/vehicle_magnetometer/VehicleMagnetometer.cpp``: while armed with
      ``MagCompensationType::Throttle`` it passes ``Vector3f(vehicle_thrust_setpoint.xyz)
      .length()`` of ``_vehicle_thrust_setpoint_0_sub`` (instance 0) to
      ``Magnetometer::UpdatePower``, otherwise (disarmed) 0; current-based types pass
      ``battery_status.current_a * 0.001`` (kA) armed or not. Read in PX4-Autopilot forks
      slgrobotics/PX4-Autopilot at 3efbf961e6879fef15ef4bb57dd08eadf732c59f and
      Renwang-Huang/Entropix-PX4-Autopilot at 94f121e7e55e2bf93e84fa6e96c44911c17946ac (the
      stored upstream snapshot, ce74a10ad409cd0ecf2f5b008b1983bb4e7f8cf4, predates the change
      and reads ``actuator_controls_0.control[INDEX_THROTTLE]`` while armed); PX4's own
      identification script (``mag_compensation/python/mag_compensation.py``, upstream
      1c4a11fba675db013cee3a8eb436dff400b8632e) uses the same norm for its ``thrust`` type.
    """
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def stamp(inst: Instance) -> np.ndarray:
        header, log = inst.stamps(time)
        return header if time == "header" else log

    att = f.instances.get("vehicle_attitude")
    if att is not None and att.has("q[0]", "q[1]", "q[2]", "q[3]") and len(att):
        out["attitude"] = (stamp(att), att.vector("q[0]", "q[1]", "q[2]", "q[3]"))
    for name in ("vehicle_gps_position", "sensor_gps", "vehicle_global_position"):
        inst = f.instances.get(name)
        lla = None if inst is None or not len(inst) else _position(inst)
        if inst is None or lla is None:
            continue
        keep = np.ones(len(inst), dtype=bool)
        if "fix_type" in inst.data:
            keep = inst.data["fix_type"] >= 3
        if keep.any():
            out["position"] = (stamp(inst)[keep], lla[keep])
            break
    bat = f.instances.get("battery_status")
    if bat is not None and bat.has("current_a") and len(bat):
        amps = bat.data["current_a"].astype(np.float64)
        keep = amps >= 0
        if keep.any():
            out["current"] = (stamp(bat)[keep], amps[keep])
    thrust = f.instances.get("vehicle_thrust_setpoint")
    controls = f.instances.get("actuator_controls_0")
    throttle = None
    if thrust is not None and thrust.has("xyz[0]", "xyz[1]", "xyz[2]") and len(thrust):
        xyz = thrust.vector("xyz[0]", "xyz[1]", "xyz[2]")
        throttle = (stamp(thrust), np.linalg.norm(xyz, axis=1))
    elif controls is not None and controls.has("control[3]") and len(controls):
        throttle = (stamp(controls), controls.vector("control[3]")[:, 0])
    if throttle is not None:
        armed = armed_at(f, throttle[0], stamp)
        out["throttle"] = throttle if armed is None else (throttle[0], throttle[1] * armed)
    return out


def armed_at(
    f: UlogFile, t_ns: np.ndarray, stamp: Callable[[Instance], np.ndarray]
) -> np.ndarray | None:
    """Whether the vehicle was armed at each of ``t_ns`` (the first logged topic of
    :data:`ARMED_STATE`, step-held; disarmed before its first message); None when the log holds
    none. ``stamp(inst)`` gives an instance's stamps in the time base of ``t_ns``."""
    for name, field, value in ARMED_STATE:
        inst = f.instances.get(name)
        if inst is None or not len(inst) or not inst.has(field):
            continue
        state = inst.data[field] == value
        i = np.searchsorted(stamp(inst), t_ns, side="right") - 1
        return np.where(i >= 0, state[np.maximum(i, 0)], False)
    return None


def gps_year(f: UlogFile) -> float | None:
    """The decimal year (UTC) of the first GNSS fix (``vehicle_gps_position`` or ``sensor_gps``
    with ``fix_type`` >= 3 and ``time_utc_usec`` set, microseconds since 1970); None without."""
    for name in ("vehicle_gps_position", "sensor_gps"):
        inst = f.instances.get(name)
        if inst is None or not len(inst) or not inst.has("time_utc_usec", "fix_type"):
            continue
        ok = np.flatnonzero((inst.data["fix_type"] >= 3) & (inst.data["time_utc_usec"] > 0))
        if len(ok):
            unix = float(inst.data["time_utc_usec"][ok[0]]) / 1e6
            return 1970.0 + unix / (365.2425 * 86400.0)
    return None


def read_ulog(spec: InputSpec) -> tuple[pa.Table, list[str]]:
    """Read a ULog input into the common table; returns (table, warnings)."""
    f = UlogFile(spec.path, READ_TOPICS)
    chosen, warnings = choose_topics(spec, f)
    builders = {"imu": _imu_piece, "mag": _mag_piece, "temperature": _temperature_piece}
    pieces: dict[str, Piece] = {}
    for stream, key in chosen.items():
        try:
            if stream == "imu":
                pieces[stream] = _imu_piece(f, key, spec.time, warnings)
            else:
                pieces[stream] = builders[stream](f, key, spec.time)
        except KeyError as exc:  # a damaged format definition lost a field
            raise ReadError(
                f"{spec.path}: topic '{key}' has no field {exc} (corrupt log?)"
            ) from None
        if len(pieces[stream]) == 0:
            raise ReadError(f"{spec.path}: topic '{key}' has no messages")
    table = assemble(
        pieces,
        time=spec.time,
        source=str(spec.path),
        fmt="ulog",
        topics={s: output_topic(s, f.instances[k]) for s, k in chosen.items()},
        where=str(spec.path),
        warnings=warnings,
    )
    baro = f.instances.get(chosen.get("temperature", ""))
    if baro is not None and baro.name == "sensor_baro" and baro.has("pressure"):
        piece = pieces["temperature"]
        t = piece.log if spec.time == "log" else piece.stamp  # the table's t_ns
        table = with_stream_column(table, "temperature", "pressure", t, baro_pascal(baro))
    table = with_flight_streams(table, flight_streams(f, spec.time))
    meta = metadata(table)
    meta.pop("frame_id", None)  # a ULog names no frames
    year = gps_year(f)
    if year is not None:
        meta["gps_year"] = year
    unread = candidates(f)["mag"]
    if "mag" not in chosen and unread:  # named by a stage that needs a compass
        meta["mag_candidates"] = unread
    meta["instance"] = {s: f.instances[k].instance for s, k in chosen.items()}
    devices = {s: _device_id(f, s, k) for s, k in chosen.items()}
    meta["device_id"] = {s: d for s, d in devices.items() if d is not None}
    meta["px4"] = {
        "calibrated": _calibrated(f, chosen),
        "parameters": f.parameters(),
        "software": f.info("ver_sw"),
        "hardware": f.info("ver_hw"),
    }
    turned = _mag_rotation(meta["px4"], meta["device_id"].get("mag"), warnings)
    if turned is not None:
        meta["px4"]["rotation"] = {"mag": turned}
    count, ms = f.dropouts()
    if count:
        warnings.append(f"the logger dropped data {count} times ({ms} ms in total)")
    damaged = f.damage_warning()
    if damaged:
        warnings.append(damaged)
    others = sorted(set(f.instances) - set(chosen.values())) + f.skipped
    if others:
        shown = some_of(others)
        warnings.append(
            f"{len(others)} other ULog topics are {NOT_CARRIED} (they "
            f"have no ROS message type; imupipe inspect lists them): {shown}"
        )
    return with_metadata(table, meta), warnings


def ulog_sources(path: Path) -> list[UlogFile]:
    """The one source of a ULog file, every topic parsed (the ``log_sources`` entry)."""
    return [UlogFile(path)]


RAW_INSTANCE_TOPICS = ("sensor_gyro", "sensor_accel", "sensor_mag", "sensor_baro", "vehicle_imu")
"""The topics parsed to list a log's raw sensor instances (``vehicle_imu``: PX4's pairing)."""


def raw_instances(path: Path) -> dict[str, list[str]]:
    """Kind -> the log's raw sensor instances, in instance order: ``imu`` the ``sensor_gyro``
    instances with an accelerometer partner (:func:`accel_partner`), ``mag`` the ``sensor_mag``
    instances, ``baro`` the ``sensor_baro`` instances that log a pressure, ``temperature`` the
    instances with a temperature; the names the topic keys take (``imu_topic``, ``mag_topic``, ``temperature_topic``)."""
    f = UlogFile(path, RAW_INSTANCE_TOPICS)
    return {
        "imu": [g.key for g in f.named("sensor_gyro") if accel_partner(f, g) is not None],
        "mag": [m.key for m in f.named("sensor_mag")],
        "baro": [b.key for b in f.named("sensor_baro") if b.has("pressure", "temperature")],
        "temperature": candidates(f)["temperature"],
    }


def describe(spec: InputSpec) -> dict[str, Any]:
    """What ``inspect`` shows beyond the topics: the instance and device of every topic
    instance, the streams a read would fill and why not, and the calibration parameters."""
    f = UlogFile(spec.path)
    try:
        chosen, warnings = choose_topics(spec, f)
        error = None
    except ReadError as exc:
        chosen, warnings, error = {}, [], str(exc)
    return {
        "instances": {
            k: {"topic": v.name, "instance": v.instance, "device_id": v.device_id()}
            for k, v in f.instances.items()
        },
        "chosen": chosen,
        "device_id": {s: _device_id(f, s, k) for s, k in chosen.items()},
        "samples": {s: _samples(f, s, k) for s, k in chosen.items()},
        "warnings": warnings,
        "selection_error": error,
        "calibrated": _calibrated(f, chosen),
        "parameters": f.parameters(),
    }
