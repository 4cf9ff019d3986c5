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

import numpy as np

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


def layout(msgtype: str, frame_id_len: int) -> np.dtype:
    """Structured dtype of a whole message (encapsulation included) for a frame_id of
    ``frame_id_len`` bytes (without the NUL)."""
    strlen = frame_id_len + 1
    body = 12 + strlen
    body += (-body) % 8
    names = ["encap", "sec", "nanosec", "strlen"]
    formats: list = [("u1", 4), "<i4", "<u4", "<u4"]
    offsets = [0, 4, 8, 12]
    if frame_id_len:
        names.append("frame_id")
        formats.append((np.bytes_, frame_id_len))
        offsets.append(16)
    pos = 4 + body
    for name, count in FIELDS[msgtype]:
        names.append(name)
        formats.append(("<f8", count) if count > 1 else "<f8")
        offsets.append(pos)
        pos += 8 * count
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": pos})


def split_stamp(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int64 ns -> (sec int32, nanosec uint32), as builtin_interfaces/Time."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    return sec.astype(np.int32), nsec.astype(np.uint32)


def encode(
    msgtype: str, t_ns: np.ndarray, frame_id: bytes, fields: dict[str, np.ndarray]
) -> np.ndarray:
    """Encode ``n`` messages with one frame_id into an (n, itemsize) uint8 array.

    ``fields`` maps each float field name of :data:`FIELDS` to an (n,) or (n, count) array; a
    missing field is zeros.
    """
    dt = layout(msgtype, len(frame_id))
    n = len(t_ns)
    out = np.zeros(n, dtype=dt)
    out["encap"] = np.frombuffer(ENCAPSULATION, dtype=np.uint8)
    out["sec"], out["nanosec"] = split_stamp(t_ns)
    out["strlen"] = len(frame_id) + 1
    if frame_id:
        out["frame_id"] = frame_id
    for name, _ in FIELDS[msgtype]:
        if name in fields:
            out[name] = fields[name]
    return out.view(np.uint8).reshape(n, dt.itemsize)
