"""PX4 ULog files written from arrays (the simulator's ``.ulg`` output).

The file layout is the ULog specification's (https://docs.px4.io/main/en/dev_log/
ulog_file_format.html): the 16-byte header (magic ``ULog\\x01\\x12\\x35``, version 1, start
time in microseconds), a flag-bits message (``B``: no incompatible flags), the definitions
(``F`` message formats, ``I`` information such as ``sys_name``, ``P`` parameters at start),
then the data: one ``A`` (add logged message: topic, ``multi_id``) per topic instance and its
``D`` messages (``msg_id`` then the fields packed little-endian, in format order, without
padding, trailing ``_padding`` fields left out as PX4's logger does; every format starts with
``uint64_t timestamp``), all in timestamp order.

:data:`PX4_V1_11` holds the message formats of the sensor topics as PX4 v1.11 logs them
(``sensor_gyro``, ``sensor_accel``, ``sensor_baro``, ``sensor_mag``; the field lists of a v1.11.2
CubeOrange log), so pyulog, imupipe's reader and PX4's own tools read the file as a v1.11 log. The rows of
every topic are packed with one numpy structured array and merged by one stable sort of the
timestamps: no Python loop over messages.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MAGIC = b"ULog\x01\x12\x35"
VERSION = 1
PX4_V1_11: dict[str, tuple[tuple[str, str], ...]] = {
    "sensor_gyro": (
        ("uint64_t", "timestamp"),
        ("uint64_t", "timestamp_sample"),
        ("uint32_t", "device_id"),
        ("float", "x"),
        ("float", "y"),
        ("float", "z"),
        ("float", "temperature"),
        ("uint32_t", "error_count"),
    ),
    "sensor_accel": (
        ("uint64_t", "timestamp"),
        ("uint64_t", "timestamp_sample"),
        ("uint32_t", "device_id"),
        ("float", "x"),
        ("float", "y"),
        ("float", "z"),
        ("float", "temperature"),
        ("uint32_t", "error_count"),
        ("uint8_t[3]", "clip_counter"),
        ("uint8_t[5]", "_padding0"),
    ),
    "sensor_baro": (
        ("uint64_t", "timestamp"),
        ("uint64_t", "timestamp_sample"),
        ("uint32_t", "device_id"),
        ("uint32_t", "error_count"),
        ("float", "pressure"),
        ("float", "temperature"),
    ),
    "sensor_mag": (
        ("uint64_t", "timestamp"),
        ("uint64_t", "timestamp_sample"),
        ("uint32_t", "device_id"),
        ("float", "x"),
        ("float", "y"),
        ("float", "z"),
        ("float", "temperature"),
        ("uint32_t", "error_count"),
        ("bool", "is_external"),
        ("uint8_t[7]", "_padding0"),
    ),
}
"""(type, field) of each sensor topic in PX4 v1.11's formats."""
NUMPY = {
    "uint64_t": "<u8",
    "int64_t": "<i8",
    "uint32_t": "<u4",
    "int32_t": "<i4",
    "uint16_t": "<u2",
    "int16_t": "<i2",
    "uint8_t": "u1",
    "int8_t": "i1",
    "float": "<f4",
    "double": "<f8",
    "bool": "u1",
}


@dataclass
class Topic:
    """One logged instance of a uORB topic: ``fields`` (type, name) in format order, ``data``
    field -> array (n,) or (n, k) for a ``type[k]`` field; absent fields are zeros."""

    name: str
    multi_id: int
    data: Mapping[str, np.ndarray]
    fields: Sequence[tuple[str, str]] = ()

    def format(self) -> tuple[tuple[str, str], ...]:
        return tuple(self.fields) or PX4_V1_11[self.name]


@dataclass
class UlogData:
    """What a ULog holds: topic instances, the parameters at start (int -> ``int32_t``, else
    ``float``) and information strings (``sys_name`` ...)."""

    topics: list[Topic]
    parameters: dict[str, float | int] = field(default_factory=dict)
    info: dict[str, str] = field(default_factory=dict)


def _dtype(fmt: Sequence[tuple[str, str]]) -> np.dtype:
    """The packed payload of a ``D`` message (trailing padding not written)."""
    fmt = list(fmt)
    while fmt and fmt[-1][1].startswith("_padding"):
        fmt.pop()
    parts = []
    for kind, name in fmt:
        base, _, count = kind.partition("[")
        shape = (int(count.rstrip("]")),) if count else ()
        parts.append((name, NUMPY[base], shape))
    return np.dtype(parts)


def _message(kind: bytes, body: bytes) -> bytes:
    return struct.pack("<HB", len(body), kind[0]) + body


def _key_value(kind: bytes, key: str, value: bytes) -> bytes:
    k = key.encode()
    return _message(kind, struct.pack("<B", len(k)) + k + value)


def ulog_bytes(log: UlogData) -> bytes:
    """The file's bytes (see the module docstring)."""
    formats: dict[str, tuple[tuple[str, str], ...]] = {}
    for topic in log.topics:
        formats.setdefault(topic.name, topic.format())
    starts = [int(np.min(t.data["timestamp"])) for t in log.topics if len(t.data["timestamp"])]
    head = MAGIC + bytes([VERSION]) + struct.pack("<Q", min(starts, default=0))
    out = [head, _message(b"B", bytes(16) + bytes(24))]
    for name, fmt in formats.items():
        text = f"{name}:" + "".join(f"{kind} {fname};" for kind, fname in fmt)
        out.append(_message(b"F", text.encode()))
    for key, value in log.info.items():
        data = value.encode()
        out.append(_key_value(b"I", f"char[{len(data)}] {key}", data))
    for key, value in log.parameters.items():
        if isinstance(value, int | np.integer) and not isinstance(value, bool):
            out.append(_key_value(b"P", f"int32_t {key}", struct.pack("<i", int(value))))
        else:
            out.append(_key_value(b"P", f"float {key}", struct.pack("<f", float(value))))
    records, stamps = [], []
    for msg_id, topic in enumerate(log.topics):
        name = topic.name.encode()
        out.append(_message(b"A", struct.pack("<BH", topic.multi_id, msg_id) + name))
        payload = _dtype(formats[topic.name])
        row = np.dtype([("size", "<u2"), ("kind", "u1"), ("msg_id", "<u2"), ("p", payload)])
        n = len(topic.data["timestamp"])
        rec = np.zeros(n, dtype=row)
        rec["size"], rec["kind"], rec["msg_id"] = payload.itemsize + 2, ord("D"), msg_id
        for fname, values in topic.data.items():
            rec["p"][fname] = values
        records.append(rec.view(np.uint8).reshape(n, row.itemsize))
        stamps.append(np.asarray(topic.data["timestamp"], dtype=np.int64))
    if records:
        sizes = np.concatenate([np.full(len(r), r.shape[1]) for r in records])
        order = np.argsort(np.concatenate(stamps), kind="stable")
        offset = np.empty(len(order), dtype=np.int64)
        offset[order] = np.concatenate([[0], np.cumsum(sizes[order])[:-1]])
        body = np.empty(int(sizes.sum()), dtype=np.uint8)
        first = 0
        for rec in records:  # one scatter per topic instance
            at = offset[first : first + len(rec)]
            body[at[:, None] + np.arange(rec.shape[1])] = rec
            first += len(rec)
        out.append(body.tobytes())
    return b"".join(out)


def write_ulog(path: Path, log: UlogData) -> None:
    """Write ``log`` to ``path`` as a ULog."""
    Path(path).write_bytes(ulog_bytes(log))
