"""imupipe's ROS 1 bag writer (numpy, a chunk at a time) against rosbags' ``rosbag1.Writer``.

The same table (Imu, MagneticField and Temperature streams; NaN values; two frame_ids; rows not
in time order; equal log times across streams) is written by ``write_ros1_bag`` and by a
reference that feeds rosbags' writer one message at a time (the code ``write_ros1_bag`` had
before). The two files must be the same byte for byte, and read the same through rosbags'
``AnyReader`` (connections, counts, times, raw payloads, chunk infos, reads by topic and time
range) and through imupipe's own ROS 1 reader (its chunks' indexes and payloads)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.writers import bag
from imupipe.readers.ros1.reader import Ros1Bag

T0 = 1_700_000_000_000_000_000


def mixed_table(n_imu: int = 6000, seed: int = 0, t0: int = T0) -> pa.Table:
    """Imu at 400 Hz, mag at 100 Hz (1 us before an Imu row: the first message of the bag),
    temperature at 1 Hz (at the log times of Imu rows); 1 % NaN in each vector, every 7th
    temperature NaN; rows shuffled."""
    rng = np.random.default_rng(seed)
    t_imu = t0 + np.arange(n_imu, dtype=np.int64) * 2_500_000
    t = np.concatenate([t_imu, t_imu[::4] - 1_000, t_imu[::400]])
    kind = np.repeat([0, 1, 2], [n_imu, len(t_imu[::4]), len(t_imu[::400])])
    n = len(t)
    cols: dict[str, pa.Array] = {"t_ns": pa.array(t, pa.int64())}
    for name, k in (("gyro", 0), ("accel", 0), ("mag", 1)):
        for a in "xyz":
            v = rng.normal(size=n)
            v[rng.random(n) < 0.01] = np.nan
            cols[f"{name}_{a}"] = pa.array(v, mask=kind != k)
    temp = 25 + rng.normal(size=n)
    temp[::7] = np.nan
    cols["temperature"] = pa.array(temp, mask=kind != 2)
    cols["frame_id"] = pa.array(np.where(rng.random(n) < 0.5, "imu", "imu_link_b"))
    return pa.table(cols).take(rng.permutation(n))


def _rosbags_reference(path: Path, table: pa.Table, compression: str) -> None:
    """The writer before: rosbags' ``Writer.write`` once per message, in log-time order."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    streams, items = bag._ordered(table, "ros1")
    writer = Writer(path)
    if compression != "none":
        writer.set_compression(Writer.CompressionFormat[compression.upper()])
    with writer:
        conns = {
            s: writer.add_connection(topic, typ, typestore=store)
            for s, (topic, typ) in streams.items()
        }
        for t, _, stream, payload in items:
            writer.write(conns[stream], t, payload)


def _anyreader_view(path: Path) -> dict:
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        (raw,) = reader.readers
        conns = sorted(
            (c.id, c.topic, c.msgtype, c.msgdef.data, c.digest, c.msgcount)
            for c in reader.connections
        )
        msgs = [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]
        imu = [c for c in reader.connections if c.topic == "/imu/data"]
        t_mid = msgs[len(msgs) // 2][1]
        window = [(c.topic, t, bytes(d)) for c, t, d in reader.messages(imu, T0 + 10**9, t_mid)]
        return {
            "conns": conns,
            "msgs": msgs,
            "window": window,
            "chunks": [(x.start_time, x.end_time, x.connection_counts) for x in raw.chunk_infos],
            "indexes": {k: [(i.time, i.offset) for i in v] for k, v in raw.indexes.items()},
        }


def _imupipe_view(path: Path) -> dict:
    src = Ros1Bag(path)
    out = []
    for chunk in src.bag_chunks():
        for cid in sorted(chunk.index):
            log, start, length = chunk.payloads(cid)
            out += [
                (src.connections[cid].topic, int(t), chunk.buf[s : s + n].tobytes())
                for t, s, n in zip(log.tolist(), start.tolist(), length.tolist(), strict=True)
            ]
    return {
        "types": src.topic_types(),
        "counts": src.topic_counts(),
        "defs": {c.topic: c.msgdef for c in src.connections.values()},
        "chunk_infos": src.chunk_infos,
        "msgs": sorted(out, key=lambda m: (m[1], m[0])),
    }


@pytest.mark.parametrize("compression", ["none", "lz4", "bz2"])
def test_same_bag_as_rosbags_writer(tmp_path: Path, compression: str) -> None:
    table = mixed_table()
    ours, ref = tmp_path / "ours.bag", tmp_path / "ref.bag"
    bag.write_ros1_bag(ours, table, compression)
    _rosbags_reference(ref, table, compression)
    assert ours.read_bytes() == ref.read_bytes()

    a, b = _anyreader_view(ours), _anyreader_view(ref)
    assert a == b
    assert [c[1:3] for c in a["conns"]] == [
        ("/imu/data", "sensor_msgs/msg/Imu"),
        ("/imu/mag", "sensor_msgs/msg/MagneticField"),
        ("/imu/temperature", "sensor_msgs/msg/Temperature"),
    ]
    assert [c[5] for c in a["conns"]] == [6000, 1500, 15]  # every row a message
    assert len(a["chunks"]) >= 3  # several chunks, each indexed per connection
    times = [t for _, t, _ in a["msgs"]]
    assert times == sorted(times)
    assert sorted(times) == sorted(table.column("t_ns").to_pylist())
    assert a["window"] and all(m[0] == "/imu/data" for m in a["window"])

    mine, theirs = _imupipe_view(ours), _imupipe_view(ref)
    assert mine == theirs
    assert mine["counts"] == {"/imu/data": 6000, "/imu/mag": 1500, "/imu/temperature": 15}
    assert sorted(mine["msgs"]) == sorted(a["msgs"])  # both readers: the same payload bytes


def test_nan_payloads_are_kept(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    table = mixed_table(n_imu=800)
    path = tmp_path / "nan.bag"
    bag.write_ros1_bag(path, table, "none")
    with AnyReader([path]) as reader:
        temps = [
            reader.deserialize(d, c.msgtype).temperature
            for c, _, d in reader.messages()
            if c.topic == "/imu/temperature"
        ]
    expected = table.sort_by("t_ns").column("temperature").drop_null().to_numpy()
    np.testing.assert_array_equal(np.array(temps), expected)  # NaN where NaN
    assert np.isnan(temps).any()


def test_one_connection_only_and_time_past_2106(tmp_path: Path) -> None:
    table = mixed_table(n_imu=40)
    only_temp = table.filter(table.column("temperature").is_valid())
    ours, ref = tmp_path / "a.bag", tmp_path / "b.bag"
    bag.write_ros1_bag(ours, only_temp, "lz4")
    _rosbags_reference(ref, only_temp, "lz4")
    assert ours.read_bytes() == ref.read_bytes()

    late = mixed_table(n_imu=40, t0=2**32 * 10**9)
    with pytest.raises(ConfigError, match="2106"):
        bag.write_ros1_bag(tmp_path / "late.bag", late)
    assert not list(tmp_path.glob("late*"))  # nothing written
