"""Corrected logs as MCAP (SPEC "Corrected MCAP").

Profile ``ros2``, message encoding ``cdr``, schemas ``ros2msg`` (the message definitions rosbags
generates), so the ``mcap`` library's ROS 2 decoder, rosbags, Foxglove and ``ros2 bag`` read it.
The IMU stream is written as ``sensor_msgs/msg/Imu``, the magnetometer as
``sensor_msgs/msg/MagneticField`` (tesla), the temperature as ``sensor_msgs/msg/Temperature``
(degC), each row of the table exactly once, with the table's timestamps (header stamp = ``t_ns``,
log time = ``log_time_ns`` when the reader kept it, else ``t_ns``). The calibration that was
applied travels as the attachment ``calibration.json``. Messages of other topics given as
``carry_over`` are written unchanged.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from mcap.writer import CompressionType, Writer

from imupipe.pipeline.table import metadata, sensor, stream_mask
from imupipe.readers import cdr
from imupipe.readers.spec import RawMessage

DEFAULT_TOPICS = {"imu": "/imu/data", "mag": "/imu/mag", "temperature": "/imu/temperature"}
STREAM_TYPES = {
    "imu": "sensor_msgs/msg/Imu",
    "mag": "sensor_msgs/msg/MagneticField",
    "temperature": "sensor_msgs/msg/Temperature",
}
DEFAULT_FRAME = "imu"


@cache
def msgdef(msgtype: str) -> str:
    """The ros2msg schema text of a message type (as rosbags generates it)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(msgtype, ros_version=2)[0]


def _column_or(table: pa.Table, name: str, rows: np.ndarray, default: np.ndarray) -> np.ndarray:
    if name not in table.column_names:
        return default
    column = table.column(name).take(pa.array(rows))
    if isinstance(column.type, pa.FixedSizeListType):
        filled = column.combine_chunks()
        if filled.null_count:
            filled = pc.if_else(
                pc.is_valid(filled), filled, pa.scalar(default[0].tolist(), column.type)
            )
        return np.asarray(filled.flatten().to_numpy(zero_copy_only=False)).reshape(len(rows), -1)
    values = column.to_numpy(zero_copy_only=False)
    if values.dtype == object or np.issubdtype(values.dtype, np.floating):
        values = np.where(pc.is_valid(column).to_numpy(zero_copy_only=False), values, default)
    return values


def encode_stream(table: pa.Table, stream: str) -> tuple[np.ndarray, list[bytes]]:
    """Encode every row of ``stream`` as CDR. Returns (rows, payloads) in row order."""
    mask = stream_mask(table, stream)
    rows = np.flatnonzero(mask)
    n = len(rows)
    t_ns = table.column("t_ns").to_numpy()[rows]
    meta_frame = metadata(table).get("frame_id", {}).get(stream, DEFAULT_FRAME)
    if "frame_id" in table.column_names:
        frames = table.column("frame_id").take(pa.array(rows)).fill_null(meta_frame)
        frames = frames.to_numpy(zero_copy_only=False)
    else:
        frames = np.full(n, meta_frame, dtype=object)
    fields: dict[str, np.ndarray] = {}
    if stream == "imu":
        fields["angular_velocity"] = sensor(table, "gyro").values
        fields["linear_acceleration"] = sensor(table, "accel").values
        default_q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        quat = [
            _column_or(table, f"orientation_{a}", rows, default_q[:, i])
            for i, a in enumerate("xyzw")
        ]
        fields["orientation"] = np.column_stack(quat) if n else default_q
        no_orientation = np.zeros((n, 9))
        no_orientation[:, 0] = -1.0
        fields["orientation_covariance"] = _column_or(
            table, "orientation_cov", rows, no_orientation
        )
        zeros = np.zeros((n, 9))
        fields["angular_velocity_covariance"] = _column_or(table, "gyro_cov", rows, zeros)
        fields["linear_acceleration_covariance"] = _column_or(table, "accel_cov", rows, zeros)
    elif stream == "mag":
        fields["magnetic_field"] = sensor(table, "mag").values
        fields["magnetic_field_covariance"] = _column_or(table, "mag_cov", rows, np.zeros((n, 9)))
    else:
        fields["temperature"] = sensor(table, "temperature").values[:, 0]
        fields["variance"] = _column_or(table, "temperature_var", rows, np.zeros(n))
    payloads: list[bytes] = [b""] * n
    for frame in np.unique(frames) if n else []:
        sel = np.flatnonzero(frames == frame)
        frame_bytes = str(frame).encode()
        enc = cdr.encode(
            STREAM_TYPES[stream],
            t_ns[sel],
            frame_bytes,
            {k: v[sel] for k, v in fields.items()},
        )
        for j, i in enumerate(sel):
            payloads[i] = enc[j].tobytes()
    return rows, payloads


def write_mcap(
    path: str | Path,
    table: pa.Table,
    *,
    calibration: Mapping[str, Any] | None = None,
    topics: Mapping[str, str] | None = None,
    carry_over: Iterable[RawMessage] = (),
    library: str = "imupipe",
) -> dict[str, int]:
    """Write ``table`` (and ``carry_over`` messages) to ``path``; returns messages per topic."""
    topics = {**DEFAULT_TOPICS, **metadata(table).get("topics", {}), **(topics or {})}
    log_col = "log_time_ns" if "log_time_ns" in table.column_names else "t_ns"
    log_all = (
        table.column(log_col).fill_null(table.column("t_ns")).to_numpy()
        if log_col != "t_ns"
        else table.column("t_ns").to_numpy()
    )
    counts: dict[str, int] = {}
    with open(path, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library=library)
        for stream in ("imu", "mag", "temperature"):
            rows, payloads = encode_stream(table, stream)
            if not len(rows):
                continue
            schema_id = writer.register_schema(
                name=STREAM_TYPES[stream],
                encoding="ros2msg",
                data=msgdef(STREAM_TYPES[stream]).encode(),
            )
            channel_id = writer.register_channel(
                topic=topics[stream], message_encoding="cdr", schema_id=schema_id
            )
            log_times = log_all[rows]
            for seq, (lt, payload) in enumerate(zip(log_times.tolist(), payloads, strict=True)):
                writer.add_message(
                    channel_id, log_time=lt, data=payload, publish_time=lt, sequence=seq
                )
            counts[topics[stream]] = len(rows)
        channels: dict[str, int] = {}
        for msg in carry_over:
            if msg.topic not in channels:
                sid = writer.register_schema(msg.schema_name, msg.schema_encoding, msg.schema_data)
                channels[msg.topic] = writer.register_channel(msg.topic, msg.message_encoding, sid)
            writer.add_message(
                channels[msg.topic],
                log_time=msg.log_time,
                data=msg.data,
                publish_time=msg.publish_time,
            )
            counts[msg.topic] = counts.get(msg.topic, 0) + 1
        if calibration is not None:
            now = time.time_ns()
            writer.add_attachment(
                now,
                now,
                "calibration.json",
                "application/json",
                json.dumps(calibration, indent=2).encode(),
            )
        writer.finish()
    return counts
