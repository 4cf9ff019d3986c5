"""ROS bags written by rosbags' own writers in every layout rosbag2 / rosbag write, for the
differential tests against rosbags' ``AnyReader`` (``tests/test_bag_variants.py``).

Each bag holds ``/imu/data`` (``sensor_msgs/Imu``, random values), ``/imu/mag``
(``MagneticField``) and ``/chatter`` (``std_msgs/String``, carried over), interleaved in log
time.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import yaml

ROS2_VARIANTS = [
    (storage, mode) for storage in ("sqlite3", "mcap") for mode in ("none", "file", "message")
]
"""(storage plugin, compression mode) of the ROS 2 bags rosbags' Writer makes."""
ROS1_VARIANTS = ["none", "bz2", "lz4"]


def _messages(store, ros: int, n: int, seed: int):
    """(topic, type, log ns, message) in log order."""
    rng = np.random.default_rng(seed)
    Imu = store.types["sensor_msgs/msg/Imu"]
    Mag = store.types["sensor_msgs/msg/MagneticField"]
    String = store.types["std_msgs/msg/String"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    V3 = store.types["geometry_msgs/msg/Vector3"]
    Q = store.types["geometry_msgs/msg/Quaternion"]
    out = []
    t0 = 1_700_000_000_000_000_000
    for i in range(n):
        t = t0 + i * 5_000_000 + int(rng.integers(0, 1000))
        sec, nsec = divmod(t - 1000, 1_000_000_000)
        hdr = (
            Header(seq=i, stamp=Time(sec=sec, nanosec=nsec), frame_id="imu")
            if ros == 1
            else Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="imu")
        )
        g, a, q = rng.normal(size=3), rng.normal(size=3) + [0, 0, 9.81], rng.normal(size=4)
        cov = rng.normal(size=9)
        out.append((
            "/imu/data", "sensor_msgs/msg/Imu", t,
            Imu(header=hdr, orientation=Q(*q), orientation_covariance=cov,
                angular_velocity=V3(*g), angular_velocity_covariance=cov,
                linear_acceleration=V3(*a), linear_acceleration_covariance=cov),
        ))  # fmt: skip
        if i % 4 == 0:
            m = rng.normal(size=3) * 1e-5
            out.append((
                "/imu/mag", "sensor_msgs/msg/MagneticField", t + 10,
                Mag(header=hdr, magnetic_field=V3(*m), magnetic_field_covariance=cov),
            ))  # fmt: skip
        if i % 7 == 0:
            out.append(("/chatter", "std_msgs/msg/String", t + 20, String(data=f"hello {i}")))
    return out


def write_ros2(path: Path, storage: str, mode: str, n: int = 300, seed: int = 0) -> Path:
    """A ROS 2 bag folder written by rosbags' ``rosbag2.Writer`` (metadata version 9)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(path, version=9, storage_plugin=plugin)
    if mode != "none":
        writer.set_compression(CompressionMode[mode.upper()], CompressionFormat.ZSTD)
    with writer:
        conns = {}
        for topic, typ, t, msg in _messages(store, 2, n, seed):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, typ, typestore=store)
            writer.write(conns[topic], t, store.serialize_cdr(msg, typ))
    return path


def write_ros1(
    path: Path, compression: str, n: int = 300, seed: int = 0, chunk: int = 4096
) -> Path:
    """A ROS 1 bag written by rosbags' ``rosbag1.Writer`` (small chunks: many of them)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    writer = Writer(path)
    if compression != "none":
        writer.set_compression(Writer.CompressionFormat[compression.upper()])
    writer.chunk_threshold = chunk
    with writer:
        conns = {}
        for topic, typ, t, msg in _messages(store, 1, n, seed):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, typ, typestore=store)
            writer.write(conns[topic], t, store.serialize_ros1(msg, typ))
    return path


def with_version(src: Path, dst: Path, version: int) -> Path:
    """A copy of the rosbags-written bag ``src`` whose ``metadata.yaml`` is rewritten as
    rosbag2 wrote that version (fields added later dropped, QoS as a YAML string from 4 to 8)."""
    shutil.copytree(src, dst)
    meta = yaml.safe_load((dst / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    info["version"] = version
    for key, since in (("files", 5), ("custom_data", 6), ("ros_distro", 8)):
        if version < since:
            info.pop(key, None)
    if version < 3:
        info.pop("compression_mode", None)
        info.pop("compression_format", None)
    for t in info["topics_with_message_count"]:
        tm = t["topic_metadata"]
        if version < 7:
            tm.pop("type_description_hash", None)
        if version < 4:
            tm.pop("offered_qos_profiles", None)
        elif version < 9:
            tm["offered_qos_profiles"] = ""
    if version < 4:  # paths then included the bag folder
        info["relative_file_paths"] = [f"{dst.name}/{p}" for p in info["relative_file_paths"]]
    (dst / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return dst


def split(parts: list[Path], dst: Path) -> Path:
    """One bag folder of several bags' storage files (a split bag): files renamed
    ``<name>_<k>``, metadata joined."""
    dst.mkdir()
    metas = [yaml.safe_load((p / "metadata.yaml").read_text()) for p in parts]
    info = metas[0]["rosbag2_bagfile_information"]
    paths, files, topics = [], [], {}
    for k, (p, m) in enumerate(zip(parts, metas, strict=True)):
        i = m["rosbag2_bagfile_information"]
        (name,) = i["relative_file_paths"]
        new = name.replace(p.name, f"{dst.name}_{k}", 1) if p.name in name else f"{k}_{name}"
        shutil.copy(p / name, dst / new)
        paths.append(new)
        files.append({**i["files"][0], "path": new})
        for t in i["topics_with_message_count"]:
            key = t["topic_metadata"]["name"]
            if key in topics:
                topics[key]["message_count"] += t["message_count"]
            else:
                topics[key] = dict(t)
    info.update(
        relative_file_paths=paths,
        files=files,
        topics_with_message_count=list(topics.values()),
        message_count=sum(t["message_count"] for t in topics.values()),
    )
    (dst / "metadata.yaml").write_text(yaml.safe_dump(metas[0]))
    return dst
