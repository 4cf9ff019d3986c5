"""Issue 3 on the five real ROS 1 bags of ../shared/data/logs (README there: counts, topics).

Each bag is read with the numpy fast path and compared field by field with rosbags' AnyReader;
all are converted to ROS 2 (sqlite3 and mcap storage) with rosbags' converter in the test, read
again, and must give the same table and the same carried-over bytes; one goes through
``imupipe run`` and comes back as MCAP with every message.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pytest
from rosbags.convert.converter import convert
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from test_readers import _fields, _table_fields, same_table

from imupipe.readers.dispatch import carry_over, read_input
from imupipe.readers.spec import InputSpec

from conftest import run_cli, shared_path
from helpers import decode_mcap, stamps_ns

# file -> {topic: (stream, messages)} from ../shared/data/logs/README.md
BAGS = {
    "madgwick_ardrone_imu.bag": {"/ardrone/imu": ("imu", 4308), "/ardrone/mag": ("mag", 4308)},
    "madgwick_phidgets_imu_upside_down.bag": {
        "/imu/data_raw": ("imu", 13964),
        "/imu/mag": ("mag", 13964),
    },
    "madgwick_sparkfun_razor.bag": {"/imu/data_raw": ("imu", 2144), "/imu/mag": ("mag", 2144)},
    "rl_test1.bag": {"/imu/data": ("imu", 11865)},
    "rl_test2.bag": {"/imu/data": ("imu", 3061)},
}
OTHER = {
    "rl_test1.bag": {"/husky_velocity_controller/odom": 3952, "/fix": 989},
    "rl_test2.bag": {"/jackal_velocity_controller/odom": 3060},
}


def _rosbags_messages(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, t, data in reader.messages():
            if conn.msgtype.startswith("sensor_msgs/msg/"):
                out.setdefault(conn.topic, []).append((t, reader.deserialize(data, conn.msgtype)))
            else:
                out.setdefault(conn.topic, []).append((t, None))
    return out


@pytest.mark.parametrize("name", sorted(BAGS))
def test_real_bag_equals_rosbags(name):
    path = shared_path("logs", name)
    table, warnings = read_input(InputSpec(path=path))
    assert warnings == []  # the README: header stamps increase strictly in every topic
    lib = _rosbags_messages(path)
    for topic, (stream, count) in BAGS[name].items():
        msgs = lib[topic]
        assert len(msgs) == count
        stamps, frames, values = _table_fields(table, stream)
        np.testing.assert_array_equal(stamps, stamps_ns(msgs))
        assert frames == [m.header.frame_id for _, m in msgs]
        assert values.tobytes() == np.array([_fields(m) for _, m in msgs]).tobytes()
        key = "gyro_x" if stream == "imu" else "mag_x"
        log = table.filter(pc.is_valid(table.column(key))).column("log_time_ns").to_numpy()
        np.testing.assert_array_equal(log, [t for t, _ in msgs])
    raw = carry_over(InputSpec(path=path))
    counts: dict[str, int] = {}
    for m in raw:
        counts[m.topic] = counts.get(m.topic, 0) + 1
    assert counts == OTHER.get(name, {})


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    """The five bags converted to ROS 2 sqlite3 and mcap with rosbags' converter."""
    d = tmp_path_factory.mktemp("ros2")
    out = {}
    for name in sorted(BAGS):
        src = shared_path("logs", name)
        for storage in ("sqlite3", "mcap"):
            dst = d / f"{Path(name).stem}_{storage}"
            convert(
                [src], dst, storage, 9, None, "file", None,
                get_typestore(Stores.ROS2_HUMBLE), [], [], [], [],
            )  # fmt: skip
            out[(name, storage)] = (src, dst)
    return out


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("name", sorted(BAGS))
def test_ros2_conversions_read_the_same(converted, name, storage):
    src, dst = converted[(name, storage)]
    a, _ = read_input(InputSpec(path=src))
    b, _ = read_input(InputSpec(path=dst))
    if "publish_time_ns" in b.column_names:  # mcap storage keeps publish times; a bag has none
        assert b.column("publish_time_ns").equals(b.column("log_time_ns"))
        b = b.drop_columns(["publish_time_ns"])
    assert same_table(a, b)  # the phidgets magnetometer holds NaNs: compare bits
    # ROS 1 carry-over converted to CDR byte for byte as rosbags-convert does it
    ra, rb = carry_over(InputSpec(path=src)), carry_over(InputSpec(path=dst))
    assert len(ra) == len(rb) == sum(OTHER.get(name, {}).values())
    assert [(m.topic, m.log_time, m.data) for m in ra] == [
        (m.topic, m.log_time, m.data) for m in rb
    ]
    assert all(x.schema_data == y.schema_data for x, y in zip(ra, rb, strict=True))


def test_run_writes_every_message_of_a_real_bag(tmp_path):
    src = shared_path("logs", "rl_test2.bag")
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.jackal]\npath = "{src}"\n\n[[stages]]\ntype = "gyro_bias"\n'
        # the robot moves: its bias fails gyro_bias's motion check, accepted here
        "accept_failed_checks = true\n\n"
        '[output]\ndir = "out"\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    out = decode_mcap(tmp_path / "out" / "jackal.mcap")
    lib = _rosbags_messages(src)
    assert {t: len(v) for t, v in out.items()} == {t: len(v) for t, v in lib.items()}
    imu = sorted(out["/imu/data"], key=lambda m: m[0])
    np.testing.assert_array_equal(stamps_ns(imu), stamps_ns(lib["/imu/data"]))
    assert [t for t, _ in imu] == [t for t, _ in lib["/imu/data"]]  # original log times
    # the odometry decodes with the mcap library's ROS 2 decoder, unchanged
    odom = sorted(out["/jackal_velocity_controller/odom"], key=lambda m: m[0])
    with AnyReader([src]) as reader:
        conns = [c for c in reader.connections if c.msgtype == "nav_msgs/msg/Odometry"]
        first = reader.deserialize(next(reader.messages(connections=conns))[2], conns[0].msgtype)
    assert odom[0][1].pose.pose.position.x == first.pose.pose.position.x
    assert odom[0][1].header.frame_id == first.header.frame_id
