"""Which topic fills which stream, and which table columns a stream's message fills.

No numpy or pyarrow here: ``imupipe inspect`` answers from an MCAP summary with these alone
(:mod:`imupipe.readers.mcap.summary`), so it starts without importing either.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

from imupipe.readers.errors import ReadError
from imupipe.readers.spec import InputSpec

STREAM_TYPES: dict[str, str] = {
    "imu": "sensor_msgs/msg/Imu",
    "mag": "sensor_msgs/msg/MagneticField",
    "temperature": "sensor_msgs/msg/Temperature",
}
TYPE_STREAMS = {v: k for k, v in STREAM_TYPES.items()}
TOPIC_KEYS = {"imu": "imu_topic", "mag": "mag_topic", "temperature": "temperature_topic"}
SPLIT_KEYS = {"gyro": "gyro_topic", "accel": "accel_topic"}
"""The reader streams of an IMU whose gyro and accelerometer come on topics of their own (a
RealSense camera's ``/camera/gyro/sample`` and ``/camera/accel/sample``): each a
``sensor_msgs/Imu`` topic read for one vector; their rows form the table's ``imu`` stream, each
with one sensor valid and the other null (see :mod:`imupipe.readers.table`)."""
PIECE_TYPES: dict[str, str] = {
    "imu": STREAM_TYPES["imu"],
    "gyro": STREAM_TYPES["imu"],
    "accel": STREAM_TYPES["imu"],
    "mag": STREAM_TYPES["mag"],
    "temperature": STREAM_TYPES["temperature"],
}
"""Every stream a binary reader decodes, with its message type, in the table's order at equal
stamps."""

COLUMNS: dict[str, list[tuple[str, int, int]]] = {
    "imu": [
        ("orientation_x", 0, 1),
        ("orientation_y", 1, 1),
        ("orientation_z", 2, 1),
        ("orientation_w", 3, 1),
        ("orientation_cov", 4, 9),
        ("gyro_x", 13, 1),
        ("gyro_y", 14, 1),
        ("gyro_z", 15, 1),
        ("gyro_cov", 16, 9),
        ("accel_x", 25, 1),
        ("accel_y", 26, 1),
        ("accel_z", 27, 1),
        ("accel_cov", 28, 9),
    ],
    "mag": [("mag_x", 0, 1), ("mag_y", 1, 1), ("mag_z", 2, 1), ("mag_cov", 3, 9)],
    "temperature": [("temperature", 0, 1), ("temperature_var", 1, 1)],
}
COLUMNS["gyro"] = COLUMNS["imu"][:9]  # orientation and angular_velocity, with covariances
COLUMNS["accel"] = COLUMNS["imu"][9:]
OTHER_VECTOR = {"gyro": (25, 3), "accel": (13, 3)}
"""Per split stream: the Imu vector it does not read (first float field, count), which such a
driver fills with zeros (checked: see :func:`imupipe.readers.decoded.decode_piece`)."""
"""Per stream: the table columns its message fills, as (column, first float field, count) over
the float fields of :data:`imupipe.readers.cdr.FIELDS`."""


def normalize_type(name: str) -> str:
    """``sensor_msgs/Imu`` (ROS 1, MCAP ros1msg) -> ``sensor_msgs/msg/Imu``."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def _named(topic: str, word: str) -> bool:
    """``word`` (gyro, accel) begins a part of the topic name, case ignored (``/camera/gyro/
    sample``, ``/device_0/sensor_2/Accel_0/imu/data``)."""
    return any(p.startswith(word) for p in re.split(r"[^a-z0-9]+", topic.lower()))


def split_pair(candidates: list[str]) -> dict[str, str] | None:
    """The gyro and accelerometer topics of a camera that publishes them apart: exactly two Imu
    topics, one named for the gyro (and not the accelerometer), the other for the
    accelerometer; else None."""
    if len(candidates) != 2:
        return None
    gyro = [t for t in candidates if _named(t, "gyro") and not _named(t, "acc")]
    accel = [t for t in candidates if _named(t, "acc") and not _named(t, "gyro")]
    if len(gyro) != 1 or len(accel) != 1:
        return None
    return {"gyro": gyro[0], "accel": accel[0]}


SPLIT = "+"
"""Joins a split IMU's gyro and accelerometer topics into its one name (``imupipe survey``'s
``GYRO_TOPIC+ACCEL_TOPIC``); never in a ROS topic name."""


def split_pairs(candidates: list[str]) -> list[dict[str, str]]:
    """Every camera's gyro and accelerometer topics among Imu topics ``candidates``: the pair of
    :func:`split_pair` when there are two; with more, the topics whose names differ only in the
    part named for the sensor (``/cam1/gyro/sample`` and ``/cam1/accel/sample``), one of each."""
    if len(candidates) == 2:
        pair = split_pair(candidates)
        return [pair] if pair is not None else []

    def key(topic: str) -> str:
        parts = re.split(r"([^a-z0-9]+)", topic.lower())
        return "".join("*" if p.startswith(("gyro", "acc")) else p for p in parts)

    by_key: dict[str, dict[str, list[str]]] = {}
    for t in candidates:
        gyro, acc = _named(t, "gyro"), _named(t, "acc")
        if gyro != acc:
            by_key.setdefault(key(t), {"gyro": [], "accel": []})[
                "gyro" if gyro else "accel"
            ].append(t)
    return [
        {"gyro": two["gyro"][0], "accel": two["accel"][0]}
        for _, two in sorted(by_key.items())
        if len(two["gyro"]) == 1 and len(two["accel"]) == 1
    ]


def _wanted(path: Path | str, key: str, wanted: str, types: Mapping[str, str], msgtype: str) -> str:
    if wanted not in types:
        have = ", ".join(f"{t} ({normalize_type(ty)})" for t, ty in sorted(types.items()))
        raise ReadError(f"{path}: {key} '{wanted}' is not in the log; topics: {have}")
    if normalize_type(types[wanted]) != msgtype:
        raise ReadError(
            f"{path}: topic '{wanted}' ({key}) has type {normalize_type(types[wanted])}, "
            f"expected {msgtype}"
        )
    return wanted


def select_topics(
    path: Path | str,
    spec: InputSpec,
    types: Mapping[str, str],
    notes: list[str] | None = None,
) -> dict[str, str]:
    """Stream -> topic, from the spec's topic settings and the log's ``topic -> type``.

    A setting that names a missing topic or one of another type is an error; an omitted setting
    takes the only topic of the stream's type (several: an error listing them; none: the stream
    is absent). At least one stream must be found.

    ``gyro_topic`` / ``accel_topic`` (either or both; not with ``imu_topic``) give the split
    streams ``gyro`` and ``accel`` instead of ``imu`` (:data:`SPLIT_KEYS`). With no IMU topic
    set, a log with exactly two Imu topics named for the gyro and the accelerometer
    (:func:`split_pair`) is read that way, and ``notes`` gets a line saying so.
    """
    chosen: dict[str, str] = {}
    imu = STREAM_TYPES["imu"]
    split = {s: getattr(spec, k) for s, k in SPLIT_KEYS.items() if getattr(spec, k) is not None}
    if split and spec.imu_topic is not None:
        raise ReadError(
            f"{path}: [inputs.{spec.name}] sets imu_topic and "
            f"{' and '.join(SPLIT_KEYS[s] for s in split)}: set imu_topic for one topic that "
            "carries both sensors, or gyro_topic and accel_topic for one topic each"
        )
    for stream, wanted in split.items():
        if wanted == "":
            continue
        chosen[stream] = _wanted(path, SPLIT_KEYS[stream], wanted, types, imu)
    if len(set(chosen.values())) < len(chosen):
        raise ReadError(f"{path}: gyro_topic and accel_topic name the same topic '{split['gyro']}'")
    for stream, msgtype in STREAM_TYPES.items():
        key = TOPIC_KEYS[stream]
        wanted = getattr(spec, key)
        candidates = sorted(t for t, ty in types.items() if normalize_type(ty) == msgtype)
        if stream == "imu" and split:
            continue
        if wanted is not None:
            chosen[stream] = _wanted(path, key, wanted, types, msgtype)
        elif len(candidates) == 1:
            chosen[stream] = candidates[0]
        elif stream == "imu" and (pair := split_pair(candidates)) is not None:
            chosen.update(pair)
            if notes is not None:
                notes.append(
                    f"{path}: gyro from {pair['gyro']}, accelerometer from {pair['accel']} (two "
                    "Imu topics named for one sensor each, read each at its own stamps; set "
                    f"imu_topic, or gyro_topic and accel_topic, in [inputs.{spec.name}] to choose)"
                )
        elif len(candidates) > 1:
            raise ReadError(
                f"{path}: several {msgtype} topics ({', '.join(candidates)}); "
                f"set {key} in {spec.settings_place}"
                + (" (or gyro_topic and accel_topic)" if stream == "imu" else "")
            )
    if not chosen:
        have = ", ".join(f"{t} ({normalize_type(ty)})" for t, ty in sorted(types.items()))
        raise ReadError(
            f"{path}: no sensor_msgs/Imu, MagneticField or Temperature topic; topics: "
            f"{have or 'none'}"
        )
    return chosen


def asked_topics(
    spec: InputSpec,
    candidates: Mapping[str, list[str]],
    known: Mapping[str, object],
    path: Path | str,
    what: str,
) -> tuple[dict[str, str], set[str]]:
    """The streams the spec names a topic (an autopilot log's instance) for, and those it turns
    off (a topic key set to ``""``): (stream -> topic, off). A named topic that cannot fill its
    stream is an error naming ``what`` can (``"ULog topics"``, ``"DataFlash messages"``):
    ``is not in the log`` when ``known`` (every topic of the log) lacks it, else ``cannot fill
    it``."""
    for key in SPLIT_KEYS.values():
        if getattr(spec, key, None) is not None:
            raise ReadError(f"{path}: {key} is for ROS logs (MCAP, bags); {what} hold both sensors")
    off = {s for s, key in TOPIC_KEYS.items() if getattr(spec, key) == ""}
    chosen: dict[str, str] = {}
    for stream, key in TOPIC_KEYS.items():
        wanted = getattr(spec, key)
        if wanted is None or stream in off:
            continue
        if wanted not in candidates[stream]:
            where = "is not in the log" if wanted not in known else "cannot fill it"
            raise ReadError(
                f"{path}: {key} '{wanted}' {where}; {what} that can: "
                f"{', '.join(candidates[stream]) or 'none'}"
            )
        chosen[stream] = wanted
    return chosen, off


NOT_CARRIED = "not carried into the corrected MCAP"
"""The words of every warning that names a log's topics a corrected MCAP does not carry (the
ULog and DataFlash readers' note, ``convert``'s count of them): ``convert`` keeps only its own,
which has the counts."""

SHOWN = 5
"""How many names a warning lists before "... (N more)"."""


def some_of(names: list[str]) -> str:
    """The first :data:`SHOWN` of ``names``, then how many more: a list that fits one line."""
    more = f", ... ({len(names) - SHOWN} more)" if len(names) > SHOWN else ""
    return ", ".join(names[:SHOWN]) + more
