"""ROS 2 CDR (little-endian) layouts of the fixed-shape sensor messages, encoded with numpy.

A message is a 4-byte encapsulation header (``00 01 00 00``), then ``std_msgs/Header`` (``int32
sec``, ``uint32 nanosec``, ``uint32`` string length including the NUL, the frame_id bytes, NUL),
padding to 8 bytes (offsets count from the end of the encapsulation header), then float64 fields:

- ``sensor_msgs/msg/Imu``: orientation (4), orientation_covariance (9), angular_velocity (3),
  angular_velocity_covariance (9), linear_acceleration (3), linear_acceleration_covariance (9)
- ``sensor_msgs/msg/MagneticField``: magnetic_field (3), magnetic_field_covariance (9)
- ``sensor_msgs/msg/Temperature``: temperature, variance

All messages of one frame_id length share one layout, so a batch is one numpy structured array.
"""

from __future__ import annotations

import functools

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import string_array

ENCAPSULATION = b"\x00\x01\x00\x00"

FIELDS: dict[str, list[tuple[str, int]]] = {
    "sensor_msgs/msg/Imu": [
        ("orientation", 4),
        ("orientation_covariance", 9),
        ("angular_velocity", 3),
        ("angular_velocity_covariance", 9),
        ("linear_acceleration", 3),
        ("linear_acceleration_covariance", 9),
    ],
    "sensor_msgs/msg/MagneticField": [("magnetic_field", 3), ("magnetic_field_covariance", 9)],
    "sensor_msgs/msg/Temperature": [("temperature", 1), ("variance", 1)],
}


def layout(msgtype: str, frame_id_len: int, encoding: str = "cdr", prefix: int = 0) -> np.dtype:
    """Structured dtype of a whole message (encapsulation included) for a frame_id of
    ``frame_id_len`` bytes (without the NUL). ``encoding="ros1"``: the ROS 1 layout
    (``seq, secs, nsecs``, string length without NUL, frame_id, float64 fields unpadded).
    ``prefix`` leaves that many bytes in front of the message (e.g. for a record header)."""
    if encoding == "ros1":
        names = ["seq", "sec", "nanosec", "strlen"]
        formats: list = ["<u4", "<u4", "<u4", "<u4"]
        offsets = [0, 4, 8, 12]
        pos = 16 + frame_id_len
    else:
        strlen = frame_id_len + 1
        body = 12 + strlen
        body += (-body) % 8
        names = ["encap", "sec", "nanosec", "strlen"]
        formats = [("u1", 4), "<i4", "<u4", "<u4"]
        offsets = [0, 4, 8, 12]
        pos = 4 + body
    if frame_id_len:
        names.append("frame_id")
        formats.append((np.bytes_, frame_id_len))
        offsets.append(16)
    for name, count in FIELDS[msgtype]:
        names.append(name)
        formats.append(("<f8", count) if count > 1 else "<f8")
        offsets.append(pos)
        pos += 8 * count
    offsets = [o + prefix for o in offsets]
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": pos + prefix}
    )


def split_stamp(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int64 ns -> (sec int32, nanosec uint32), as builtin_interfaces/Time."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    return sec.astype(np.int32), nsec.astype(np.uint32)


def encode(
    msgtype: str,
    t_ns: np.ndarray,
    frame_id: bytes,
    fields: dict[str, np.ndarray],
    encoding: str = "cdr",
    prefix: int = 0,
) -> np.ndarray:
    """Encode ``n`` messages with one frame_id into an (n, prefix + itemsize) uint8 array.

    ``fields`` maps each float field name of :data:`FIELDS` to an (n,) or (n, count) array, or
    one row ((1,) or (1, count)) that every message gets; a missing field is zeros. Values are
    written as given, NaN included. ``encoding``: ``cdr`` (ROS 2) or ``ros1`` (header ``seq`` 0).
    ``prefix`` bytes (zeros) precede each message, for the caller to fill (a record header).
    """
    dt = layout(msgtype, len(frame_id), encoding, prefix)
    n = len(t_ns)
    out = np.zeros(n, dtype=dt)
    out["sec"], out["nanosec"] = split_stamp(t_ns)
    if encoding == "ros1":
        out["strlen"] = len(frame_id)
    else:
        out["encap"] = np.frombuffer(ENCAPSULATION, dtype=np.uint8)
        out["strlen"] = len(frame_id) + 1
    if frame_id:
        out["frame_id"] = frame_id
    for name, _ in FIELDS[msgtype]:
        if name in fields:
            out[name] = fields[name]
    return out.view(np.uint8).reshape(n, dt.itemsize)


# --- decoding -------------------------------------------------------------------------------
#
# The decoders below read many messages at once out of one byte buffer (a decompressed MCAP or
# bag chunk), given each message's payload start and length. Every field is gathered with one
# numpy fancy index over an unaligned view of the buffer, so a chunk costs a few numpy calls
# whatever its message count, and messages whose frame_ids differ in length need no grouping.
#
# Wire formats (``encoding``):
#
# - ``cdr`` (ROS 2, little-endian): encapsulation (4), ``int32 sec``, ``uint32 nanosec``,
#   ``uint32`` string length n including the NUL, n bytes, padding so that the float64 fields
#   start at a multiple of 8 counted from the end of the encapsulation header.
# - ``ros1``: ``uint32 seq``, ``uint32 secs``, ``uint32 nsecs``, ``uint32`` string length n
#   (no NUL), n bytes, then the float64 fields packed without padding.


class PayloadError(ValueError):
    """A payload does not hold the message type it claims (too short, bad encapsulation).

    ``index`` is the position of the first bad payload in the batch."""

    def __init__(self, index: int, reason: str) -> None:
        super().__init__(reason)
        self.index = index
        self.reason = reason


class NotFastPath(ValueError):
    """The batch is valid but not in a layout the numpy path decodes (e.g. big-endian CDR)."""


@functools.cache
def field_count(msgtype: str) -> int:
    """Number of float64 values after the header of ``msgtype`` (looked up per chunk: cached)."""
    return sum(count for _, count in FIELDS[msgtype])


def unaligned(buf: np.ndarray, dtype: str | np.dtype) -> np.ndarray:
    """A view of ``buf`` (uint8) in which element ``i`` is the ``dtype`` value starting at byte
    ``i``: fancy-indexing it with byte offsets gathers (possibly unaligned) scalars."""
    dt = np.dtype(dtype)
    n = max(buf.shape[0] - dt.itemsize + 1, 0)
    return np.ndarray((n,), dtype=dt, buffer=buf, offset=0, strides=(1,)) if n else np.empty(0, dt)


def even_step(starts: np.ndarray) -> int | None:
    """The distance between consecutive ``starts`` when it is one positive constant (records
    of one size, one after the other), else None."""
    n = len(starts)
    if n < 2:
        return 1 if n else None
    step = int(starts[1] - starts[0])
    if step <= 0 or int(starts[-1] - starts[0]) != step * (n - 1):
        return None
    return step if bool(np.all(starts[1:] - starts[:-1] == step)) else None


def at(
    buf: np.ndarray, starts: np.ndarray, offset: int, dtype: str, step: int | None
) -> np.ndarray:
    """The ``dtype`` value at byte ``start + offset`` of ``buf`` for every start (the caller
    has checked the bounds): a strided view when the starts are ``step`` apart (see
    :func:`even_step`), else a gather through :func:`unaligned`."""
    dt = np.dtype(dtype)
    if step is None:
        return unaligned(buf, dt)[starts + offset]
    n = len(starts)
    return np.ndarray((n,), dt, buffer=buf, offset=int(starts[0]) + offset, strides=(step,))


def gather_strings(
    buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray, step: int | None = None
) -> pa.Array:
    """The byte ranges ``buf[starts[i] : starts[i] + lengths[i]]`` as an Arrow string array
    (UTF-8 validated), built with one ragged gather (one strided copy when the ranges have one
    length and lie ``step`` apart; the UTF-8 check of one string when they are all equal, as a
    sensor's frame_id is)."""
    lengths = lengths.astype(np.int64)
    n = len(lengths)
    size = int(lengths[0]) if n else 0
    if n and step is not None and size and bool(np.all(lengths == size)):
        rows = np.ndarray((n, size), np.uint8, buffer=buf, offset=int(starts[0]), strides=(step, 1))
        data = rows.copy().reshape(-1)  # a copy: the chunk's buffer is not kept alive
        offsets = np.arange(0, (n + 1) * size, size, dtype=np.int32)
        raw = data.tobytes()
        if raw == raw[:size] * n:  # one frame_id: check its UTF-8 once
            try:
                raw[:size].decode()
            except UnicodeDecodeError:
                raise PayloadError(0, "frame_id is not valid UTF-8") from None
            return pa.StringArray.from_buffers(n, pa.py_buffer(offsets), pa.py_buffer(data))
        ends = offsets[1:].astype(np.int64)
    else:
        ends = np.cumsum(lengths)
        total = int(ends[-1]) if n else 0
        if total:
            idx = np.repeat(starts.astype(np.int64) - (ends - lengths), lengths)
            idx += np.arange(total, dtype=np.int64)
            data = buf[idx]
        else:
            data = np.zeros(0, np.uint8)
    offsets = np.concatenate([[0], ends]).astype(np.int32)
    array = pa.StringArray.from_buffers(n, pa.py_buffer(offsets), pa.py_buffer(data))
    try:
        array.validate(full=True)
    except pa.ArrowInvalid:
        raise PayloadError(0, "frame_id is not valid UTF-8") from None
    return array


def decode(
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    msgtype: str,
    encoding: str,
    slots: list[tuple[int, int]] | None = None,
) -> tuple[np.ndarray, pa.Array, np.ndarray | list[np.ndarray]]:
    """Decode ``len(starts)`` messages of ``msgtype`` whose payloads lie in ``buf`` (uint8).

    Returns ``(stamp_ns int64 (n,), frame_id string array (n,), values)`` where ``values`` is
    float64 (n, k), the float fields of :data:`FIELDS` in order, or with ``slots`` (a list of
    ``(first float, count)``) one array per slot, (n,) for count 1 else (n, count), which may
    be a read-only view into ``buf``.
    Raises :class:`PayloadError` for a payload that cannot hold the type, :class:`NotFastPath`
    for a valid layout this function does not handle (big-endian CDR).
    """
    k = field_count(msgtype)
    starts = np.asarray(starts, dtype=np.int64)
    ends = starts + np.asarray(lengths, dtype=np.int64)
    n = len(starts)
    if n == 0:
        empty = np.zeros((0, k))
        out = (
            empty if slots is None else [empty[:, 0] if c == 1 else empty[:, :c] for _, c in slots]
        )
        return np.zeros(0, np.int64), string_array([]), out
    short = np.flatnonzero(ends - starts < 16)
    if len(short):
        raise PayloadError(
            int(short[0]), f"payload of {int(ends[short[0]] - starts[short[0]])} bytes"
        )
    even = even_step(starts)
    strlen = at(buf, starts, 12, "<u4", even).astype(np.int64)
    if encoding == "cdr":
        zero, encap = at(buf, starts, 0, "u1", even), at(buf, starts, 1, "u1", even)
        if np.any(zero != 0) or np.any((encap != 1) & (encap != 0)):
            bad = int(np.flatnonzero((zero != 0) | ((encap != 1) & (encap != 0)))[0])
            raise PayloadError(bad, "not a CDR payload (bad encapsulation header)")
        if np.any(encap == 0):
            raise NotFastPath("big-endian CDR")
        sec = at(buf, starts, 4, "<i4", even).astype(np.int64)
        bad = np.flatnonzero(strlen < 1)
        if len(bad):
            raise PayloadError(int(bad[0]), "string length 0 (CDR strings end with a NUL)")
        frame_len = strlen - 1
        body = 12 + strlen
        fstart = starts + 4 + body + (-body) % 8
    elif encoding == "ros1":
        sec = at(buf, starts, 4, "<u4", even).astype(np.int64)
        frame_len = strlen
        fstart = starts + 16 + strlen
    else:
        raise NotFastPath(f"message encoding {encoding!r}")
    bad = np.flatnonzero(fstart + 8 * k > ends)
    if len(bad):
        i = int(bad[0])
        raise PayloadError(
            i, f"payload of {int(ends[i] - starts[i])} bytes is too short for {msgtype}"
        )
    stamp = sec * 1_000_000_000 + at(buf, starts, 8, "<u4", even).astype(np.int64)
    frames = gather_strings(buf, starts + 16, frame_len, even)
    step = int(fstart[1] - fstart[0]) if n > 1 else 8 * k
    if step >= 8 * k and np.all(fstart[1:] - fstart[:-1] == step):
        # evenly spaced messages (one frame_id length, one channel per run): a strided view
        # replaces the gather. The slots are read-only views into ``buf`` (no copy here: the
        # reader copies them once, into the table's columns)
        rows = np.ndarray((n, k), "<f8", buffer=buf, offset=int(fstart[0]), strides=(step, 8))
        if slots is None:
            return stamp, frames, rows.copy()
        return stamp, frames, [rows[:, f] if c == 1 else rows[:, f : f + c] for f, c in slots]
    f8 = unaligned(buf, "<f8")
    if slots is None:
        return stamp, frames, f8[fstart[:, None] + 8 * np.arange(k)]
    columns = [
        f8[fstart + 8 * first]
        if count == 1
        else f8[fstart[:, None] + 8 * (first + np.arange(count))]
        for first, count in slots
    ]
    return stamp, frames, columns


def decode_with_rosbags(
    payloads: list[bytes], msgtype: str, encoding: str
) -> tuple[np.ndarray, pa.Array, np.ndarray]:
    """The same result as :func:`decode`, one message at a time with rosbags' deserializers:
    the fallback for layouts the numpy path does not take (big-endian CDR)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if encoding == "cdr" else Stores.ROS1_NOETIC)
    deserialize = store.deserialize_cdr if encoding == "cdr" else store.deserialize_ros1
    k = field_count(msgtype)
    stamps = np.zeros(len(payloads), np.int64)
    values = np.zeros((len(payloads), k))
    frames = []
    for i, data in enumerate(payloads):
        try:
            msg = deserialize(data, msgtype)
        except Exception as exc:  # noqa: BLE001 - any deserializer failure is a bad payload
            raise PayloadError(i, f"cannot be decoded as {msgtype} ({exc})") from None
        stamps[i] = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        frames.append(msg.header.frame_id)
        row = []
        for name, count in FIELDS[msgtype]:
            value = getattr(msg, name)
            if count == 1:
                row.append([value])
            elif count == 9:
                row.append(np.asarray(value, dtype=np.float64))
            else:
                row.append([getattr(value, a) for a in "xyzw"[:count]])
        values[i] = np.concatenate(row)
    return stamps, string_array(frames), values
