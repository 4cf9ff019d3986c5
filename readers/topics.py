"""Which topic fills which stream, and which table columns a stream's message fills.

No numpy or pyarrow here: ``imupipe inspect`` answers from an MCAP summary with these alone
(:mod:`imupipe.readers.mcap.summary`), so it starts without importing either.
"""

from __future__ import annotations

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
"""Per stream: the table columns its message fills, as (column, first float field, count) over
the float fields of :data:`imupipe.readers.cdr.FIELDS`."""


def normalize_type(name: str) -> str:
    """``sensor_msgs/Imu`` (ROS 1, MCAP ros1msg) -> ``sensor_msgs/msg/Imu``."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def select_topics(path: Path | str, spec: InputSpec, types: Mapping[str, str]) -> dict[str, str]:
    """Stream -> topic, from the spec's topic settings and the log's ``topic -> type``.

    A setting that names a missing topic or one of another type is an error; an omitted setting
    takes the only topic of the stream's type (several: an error listing them; none: the stream
    is absent). At least one stream must be found.
    """
    chosen: dict[str, str] = {}
    for stream, msgtype in STREAM_TYPES.items():
        key = TOPIC_KEYS[stream]
        wanted = getattr(spec, key)
        candidates = sorted(t for t, ty in types.items() if normalize_type(ty) == msgtype)
        if wanted is not None:
            if wanted not in types:
                have = ", ".join(f"{t} ({normalize_type(ty)})" for t, ty in sorted(types.items()))
                raise ReadError(f"{path}: {key} '{wanted}' is not in the log; topics: {have}")
            if normalize_type(types[wanted]) != msgtype:
                raise ReadError(
                    f"{path}: topic '{wanted}' ({key}) has type {normalize_type(types[wanted])}, "
                    f"expected {msgtype}"
                )
            chosen[stream] = wanted
        elif len(candidates) == 1:
            chosen[stream] = candidates[0]
        elif len(candidates) > 1:
            raise ReadError(
                f"{path}: several {msgtype} topics ({', '.join(candidates)}); "
                f"set {key} in {spec.settings_place}"
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
