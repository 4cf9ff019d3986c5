"""Issue 37 items 2, 3: ``[inputs.NAME.fields]`` reads any message's fields, value for value
equal to the reference libraries (rosbags, mcap's JSON and protobuf decoders).

The logs are written here with the reference writers (rosbags' rosbag1/rosbag2 writers with a
custom ``px4_msgs/SensorCombined`` type from its .msg text, mcap's writer with JSON and
protobuf schemas), so that every value read can be compared with what was written and with what
the reference reader decodes.
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from imupipe.readers.cdr import unaligned
from imupipe.readers.dispatch import read_input
from imupipe.readers.errors import ReadError
from imupipe.readers.message_fields import Leaf, json_type, protobuf_type, ros_type
from imupipe.readers.record_walk import PURE_PYTHON_ENV
from imupipe.readers.spec import FieldMapping, InputSpec
from imupipe.readers.table import metadata, sensor, split_imu

from conftest import run_cli

SENSOR_COMBINED = """uint64 timestamp # time since system start (microseconds)
int32 RELATIVE_TIMESTAMP_INVALID = 2147483647
float32[3] gyro_rad
uint32 gyro_integral_dt
int32 accelerometer_timestamp_relative
float32[3] accelerometer_m_s2
uint32 accelerometer_integral_dt
uint8 CLIPPING_X = 1
uint8 accelerometer_clipping
uint8 gyro_clipping
uint8 accel_calibration_count
uint8 gyro_calibration_count
"""
"""px4_msgs/msg/SensorCombined as PX4's ``msg/SensorCombined.msg`` (v1.14) defines it."""

DRIVER = """std_msgs/Header header
string serial
float64[] raw
geometry_msgs/Vector3 rate
float32 temp_c
"""
"""A driver's own message with a variable layout (a string and a sequence before the values)."""

TOPIC = "/fmu/out/sensor_combined"


def _store(version: int, extra: dict[str, str]):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if version == 2 else Stores.ROS1_NOETIC)
    for name, text in extra.items():
        store.register(get_types_from_msg(text, name))
    return store


def _px4_messages(store, n: int, rng: np.random.Generator) -> list:
    M = store.types["px4_msgs/msg/SensorCombined"]
    gyro = rng.normal(0, 0.1, (n, 3)).astype(np.float32)
    accel = (rng.normal(0, 0.1, (n, 3)) + [0, 0, -9.81]).astype(np.float32)
    return [
        M(
            timestamp=np.uint64(2_000_000 + 4000 * i + int(rng.integers(0, 3))),
            gyro_rad=gyro[i],
            gyro_integral_dt=4000,
            accelerometer_timestamp_relative=0,
            accelerometer_m_s2=accel[i],
            accelerometer_integral_dt=4000,
            accelerometer_clipping=0,
            gyro_clipping=0,
            accel_calibration_count=1,
            gyro_calibration_count=2,
        )
        for i in range(n)
    ]


def write_px4_bag(folder: Path, storage: str, n: int = 2000) -> None:
    """A ROS 2 bag (rosbags' writer) of ``px4_msgs/msg/SensorCombined`` on PX4's topic."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = _store(2, {"px4_msgs/msg/SensorCombined": SENSOR_COMBINED})
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    shutil.rmtree(folder, ignore_errors=True)
    msgs = _px4_messages(store, n, np.random.default_rng(1))
    with Writer(folder, version=9, storage_plugin=plugin) as w:
        c = w.add_connection(TOPIC, "px4_msgs/msg/SensorCombined", typestore=store)
        for i, m in enumerate(msgs):
            w.write(c, 10**9 + 4_000_000 * i, store.serialize_cdr(m, c.msgtype))


def reference_rosbag2(folder: Path, topic: str, store) -> list:
    from rosbags.rosbag2 import Reader

    with Reader(folder) as r:
        conns = [c for c in r.connections if c.topic == topic]
        return [
            (t, store.deserialize_cdr(raw, c.msgtype))
            for c, t, raw in r.messages(connections=conns)
        ]


PX4_MAPPING = FieldMapping(
    gyro=f"{TOPIC}.gyro_rad",
    accel=f"{TOPIC}.accelerometer_m_s2",
    time=f"{TOPIC}.timestamp",
    time_unit="us",
)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_px4_sensor_combined_equals_rosbags(tmp_path, storage):
    folder = tmp_path / "px4"
    write_px4_bag(folder, storage)
    store = _store(2, {"px4_msgs/msg/SensorCombined": SENSOR_COMBINED})
    ref = reference_rosbag2(folder, TOPIC, store)
    table, warnings = read_input(InputSpec(path=folder, fields=PX4_MAPPING))
    assert warnings == []
    gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
    assert table.num_rows == len(ref) == 2000
    want_t = np.array([int(m.timestamp) * 1000 for _, m in ref])
    assert np.array_equal(gyro.t_ns, want_t)
    assert np.array_equal(gyro.values, np.array([m.gyro_rad for _, m in ref], np.float64))
    assert np.array_equal(accel.values, np.array([m.accelerometer_m_s2 for _, m in ref], float))
    assert np.array_equal(table.column("log_time_ns").to_numpy(), [t for t, _ in ref])


def test_units_and_scalar_paths(tmp_path):
    folder = tmp_path / "px4"
    write_px4_bag(folder, "mcap", 50)
    store = _store(2, {"px4_msgs/msg/SensorCombined": SENSOR_COMBINED})
    ref = reference_rosbag2(folder, TOPIC, store)
    mapping = FieldMapping(
        gyro=[f"{TOPIC}.gyro_rad.2", f"{TOPIC}.gyro_rad.0", f"{TOPIC}.gyro_rad.1"],
        gyro_unit="deg/s",
        accel=f"{TOPIC}.accelerometer_m_s2",
        accel_unit="g",
        temperature=f"{TOPIC}.gyro_integral_dt",
        time="log",
    )
    table, _ = read_input(InputSpec(path=folder, fields=mapping))
    g = np.array([m.gyro_rad for _, m in ref], float)[:, [2, 0, 1]] * (np.pi / 180)
    assert np.array_equal(sensor(table, "gyro").values, g)
    a = np.array([m.accelerometer_m_s2 for _, m in ref], float) * 9.80665
    assert np.array_equal(sensor(table, "accel").values, a)
    assert np.array_equal(sensor(table, "temperature").values[:, 0], np.full(50, 4000.0))
    assert np.array_equal(table.column("t_ns").to_numpy(), [t for t, _ in ref])


def test_two_topics_rows_per_message(tmp_path):
    """Gyro and accel on their own topics (geometry_msgs/Vector3Stamped pairs, 400 and 250 Hz),
    header stamps: one row per message, the other sensor null on it; counts and values equal
    to rosbags'."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = _store(2, {})
    V = store.types["geometry_msgs/msg/Vector3Stamped"]
    H = store.types["std_msgs/msg/Header"]
    T = store.types["builtin_interfaces/msg/Time"]
    Vec = store.types["geometry_msgs/msg/Vector3"]
    folder = tmp_path / "pair"
    rng = np.random.default_rng(2)
    events = []
    for topic, rate, n in (("/cam/gyro", 400, 800), ("/cam/accel", 250, 500)):
        for i in range(n):
            t = 5 * 10**9 + i * 10**9 // rate
            x, y, z = rng.normal(size=3)
            frame = "imu_" + "x" * int(rng.integers(0, 4))  # frame_ids of varying length
            msg = V(H(T(t // 10**9, t % 10**9), frame), Vec(x, y, z))
            events.append((t + 1000, topic, msg))
    events.sort(key=lambda e: e[0])
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {
            t: w.add_connection(t, V.__msgtype__, typestore=store)
            for t in ("/cam/gyro", "/cam/accel")
        }
        for lt, topic, msg in events:
            w.write(conns[topic], lt, store.serialize_cdr(msg, V.__msgtype__))
    mapping = FieldMapping(gyro="/cam/gyro.vector", accel="/cam/accel.vector")
    table, _ = read_input(InputSpec(path=folder, fields=mapping))
    assert table.num_rows == 1300
    for name, topic in (("gyro", "/cam/gyro"), ("accel", "/cam/accel")):
        ref = reference_rosbag2(folder, topic, store)
        valid = table.column(f"{name}_x").is_valid().to_numpy(zero_copy_only=False)
        rows = table.filter(valid)
        stamp = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in ref]
        assert np.array_equal(rows.column("t_ns").to_numpy(), stamp)
        values = np.stack([rows.column(f"{name}_{a}").to_numpy() for a in "xyz"], axis=1)
        assert np.array_equal(values, [[m.vector.x, m.vector.y, m.vector.z] for _, m in ref])
    gyro_null = table.column("gyro_x").is_null().to_numpy(zero_copy_only=False)
    accel_null = table.column("accel_x").is_null().to_numpy(zero_copy_only=False)
    assert np.array_equal(gyro_null, ~accel_null)
    assert np.count_nonzero(~gyro_null) == 800
    # sampled apart: the table says so, and a corrected log writes each row back to its topic
    assert split_imu(table)
    assert metadata(table)["topics"] == {"gyro": "/cam/gyro", "accel": "/cam/accel"}
    chain = [
        {"type": "gyro_bias", "sensor": "gyro", "kind": "linear",
         "matrix": np.eye(3).tolist(), "offset": [0.01, -0.02, 0.005]},
    ]  # fmt: skip
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"imupipe_version": "test", "chain": chain, "results": {}}))
    read = tmp_path / "read.toml"
    read.write_text('[fields]\ngyro = "/cam/gyro.vector"\naccel = "/cam/accel.vector"\n')
    proc = run_cli(
        "convert", folder, "--calibration", cal, "--out", tmp_path / "conv",
        "--config", read, "--jobs", "1", "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    from mcap.reader import make_reader

    with open(next((tmp_path / "conv").rglob("*.mcap")), "rb") as fh:
        counts = Counter(c.topic for _, c, _ in make_reader(fh).iter_messages())
    assert counts == {"/cam/gyro": 800, "/cam/accel": 500}


def test_ros1_driver_message_equals_rosbags(tmp_path):
    """A ROS 1 bag of a driver's own message (definition from the connection header), with a
    string and a sequence of varying length before the values: the per-message offsets."""
    from rosbags.rosbag1 import Writer

    store = _store(1, {"acme_msgs/msg/Rate": DRIVER})
    M = store.types["acme_msgs/msg/Rate"]
    H = store.types["std_msgs/msg/Header"]
    T = store.types["builtin_interfaces/msg/Time"]
    Vec = store.types["geometry_msgs/msg/Vector3"]
    rng = np.random.default_rng(3)
    path = tmp_path / "driver.bag"
    with Writer(path) as w:
        c = w.add_connection("/acme/rate", M.__msgtype__, typestore=store)
        for i in range(300):
            t = 10**9 + i * 5_000_000
            msg = M(
                H(i, T(t // 10**9, t % 10**9), "imu"),
                "SN" + "7" * int(rng.integers(0, 5)),
                rng.normal(size=int(rng.integers(0, 4))),
                Vec(*rng.normal(size=3)),
                np.float32(rng.normal(30, 1)),
            )
            w.write(c, t + 777, store.serialize_ros1(msg, M.__msgtype__))
    from rosbags.rosbag1 import Reader

    with Reader(path) as r:
        ref = [store.deserialize_ros1(raw, c.msgtype) for c, _, raw in r.messages()]
    mapping = FieldMapping(gyro="/acme/rate.rate", temperature="/acme/rate.temp_c")
    table, _ = read_input(InputSpec(path=path, fields=mapping))
    assert table.num_rows == 300
    g = sensor(table, "gyro")
    assert np.array_equal(g.values, [[m.rate.x, m.rate.y, m.rate.z] for m in ref])
    assert np.array_equal(
        g.t_ns, [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in ref]
    )
    assert np.array_equal(sensor(table, "temperature").values[:, 0], [float(m.temp_c) for m in ref])


@pytest.mark.parametrize("little", [True, False])
def test_walk_equals_rosbags_deserializer(little):
    """The numpy walk against rosbags' deserializer on random messages of a variable layout:
    both byte orders, frame_ids and sequences of varying length, evenly and unevenly spaced."""
    store = _store(2, {"acme_msgs/msg/Rate": DRIVER})
    M = store.types["acme_msgs/msg/Rate"]
    H = store.types["std_msgs/msg/Header"]
    T = store.types["builtin_interfaces/msg/Time"]
    Vec = store.types["geometry_msgs/msg/Vector3"]
    rng = np.random.default_rng(4)
    payloads = []
    for i in range(200):
        msg = M(
            H(T(int(rng.integers(0, 2**31)), int(rng.integers(0, 10**9))), "f" * (i % 5)),
            "s" * int(rng.integers(0, 9)),
            rng.normal(size=int(rng.integers(3, 6))),
            Vec(*rng.normal(size=3)),
            np.float32(rng.normal()),
        )
        payloads.append(bytes(store.serialize_cdr(msg, M.__msgtype__, little_endian=little)))
    text = store.generate_msgdef("acme_msgs/msg/Rate", ros_version=2)[0]
    mtype = ros_type("acme_msgs/msg/Rate", "cdr", "ros2msg", text)
    leaves = [
        Leaf(p)
        for p in (
            ("header", "stamp", "sec"),
            ("header", "stamp", "nanosec"),
            ("raw", 2),
            ("rate", "x"),
            ("rate", "y"),
            ("rate", "z"),
            ("temp_c",),
        )
    ]
    gap = b"\x00" * 3
    buf = np.frombuffer(gap.join(payloads), np.uint8)
    lengths = np.array([len(p) for p in payloads])
    starts = np.concatenate([[0], np.cumsum(lengths + 3)[:-1]])
    fast = mtype.decode(buf, starts, lengths, leaves)
    ref = mtype.decode_reference(buf, starts, lengths, leaves)
    for a, b in zip(fast, ref, strict=True):
        assert a.dtype == b.dtype
        assert np.array_equal(a, b)
    # one layout throughout (equal frame_ids, strings, sequences): the strided views
    same = [payloads[0]] * 50
    buf = np.frombuffer(b"".join(same), np.uint8)
    lengths = np.full(50, len(same[0]))
    starts = np.arange(50) * len(same[0])
    fast = mtype.decode(buf, starts, lengths, leaves)
    ref = mtype.decode_reference(buf, starts, lengths, leaves)
    assert all(np.array_equal(a, b) for a, b in zip(fast, ref, strict=True))


def test_sequence_of_structs_falls_back_to_rosbags():
    text = "geometry_msgs/Vector3[] points\ngeometry_msgs/Vector3 rate\n"
    store = _store(2, {"acme_msgs/msg/Cloud": text})
    M = store.types["acme_msgs/msg/Cloud"]
    Vec = store.types["geometry_msgs/msg/Vector3"]
    payloads = [
        bytes(store.serialize_cdr(M([Vec(1, 2, 3)] * k, Vec(k, -k, 0.5)), M.__msgtype__))
        for k in range(5)
    ]
    mtype = ros_type("acme_msgs/msg/Cloud", "cdr", "ros2msg", text)
    buf = np.frombuffer(b"".join(payloads), np.uint8)
    lengths = np.array([len(p) for p in payloads])
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    x, y = mtype.decode(buf, starts, lengths, [Leaf(("rate", "x")), Leaf(("rate", "y"))])
    assert np.array_equal(x, np.arange(5.0)) and np.array_equal(y, -np.arange(5.0))


# --- JSON and protobuf MCAP ------------------------------------------------------------------

JSON_SCHEMA = {
    "type": "object",
    "properties": {
        "t": {"type": "integer"},
        "g": {
            "type": "object",
            "properties": {k: {"type": "number"} for k in "xyz"},
        },
        "a": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        "label": {"type": "string"},
    },
}


def write_json_mcap(path: Path, n: int = 500) -> list[bytes]:
    from mcap.writer import Writer

    rng = np.random.default_rng(5)
    payloads = []
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("imu_json", "jsonschema", json.dumps(JSON_SCHEMA).encode())
        cid = w.register_channel("/imu_json", "json", sid)
        for i in range(n):
            doc = {
                "label": "a\nb" if i % 7 == 0 else "x" * (i % 4),
                "g": dict(zip("xyz", rng.normal(size=3).tolist(), strict=True)),
                "a": (rng.normal(size=3) + [0, 0, 9.8]).tolist(),
                "t": 10**18 + i * 2_500_000 + 1,
            }
            if i % 3 == 0:
                doc["g"]["x"] = int(i)  # an integer where the schema says number
            text = json.dumps(doc, indent=2 if i % 5 == 0 else None).encode()
            payloads.append(text)
            w.add_message(cid, log_time=i * 1000, data=text, publish_time=i * 1000)
        w.finish()
    return payloads


def test_json_mcap_equals_json_decoder(tmp_path):
    path = tmp_path / "imu.mcap"
    write_json_mcap(path)
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        ref = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages()]
    mapping = FieldMapping(
        gyro=["/imu_json.g.x", "/imu_json.g.y", "/imu_json.g.z"],
        accel="/imu_json.a",
        time="/imu_json.t",
    )
    table, _ = read_input(InputSpec(path=path, fields=mapping))
    assert table.num_rows == len(ref) == 500
    assert np.array_equal(sensor(table, "gyro").values, [[d["g"][k] for k in "xyz"] for d in ref])
    assert np.array_equal(sensor(table, "accel").values, [d["a"] for d in ref])
    assert np.array_equal(table.column("t_ns").to_numpy(), [d["t"] for d in ref])


def _proto_classes():
    """An IMU message type built from a FileDescriptorProto (as protoc would), using
    google.protobuf.Timestamp, a nested Vector3, packed and unpacked repeated fields, sint32."""
    from google.protobuf import (
        descriptor_pb2,
        descriptor_pool,
        message_factory,
        timestamp_pb2,  # noqa: F401 - registers timestamp.proto
    )

    fd = descriptor_pb2.FileDescriptorProto(
        name="acme/imu.proto",
        package="acme",
        syntax="proto3",
        dependency=["google/protobuf/timestamp.proto"],
    )
    vec = fd.message_type.add(name="Vector3")
    for i, k in enumerate("xyz", 1):
        vec.field.add(name=k, number=i, type=1, label=1)
    imu = fd.message_type.add(name="Imu")
    imu.field.add(
        name="timestamp", number=1, type=11, label=1, type_name=".google.protobuf.Timestamp"
    )
    imu.field.add(name="gyro", number=2, type=11, label=1, type_name=".acme.Vector3")
    imu.field.add(name="accel", number=3, type=1, label=3)  # packed (proto3 default)
    f = imu.field.add(name="mag", number=4, type=2, label=3)  # float, unpacked
    f.options.packed = False
    imu.field.add(name="temp", number=5, type=17, label=1)  # sint32
    pool = descriptor_pool.Default()
    with contextlib.suppress(TypeError):  # already added by an earlier test in this process
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("acme.Imu"))


def write_protobuf_mcap(path: Path, n: int = 500) -> None:
    from mcap_protobuf.writer import Writer

    Imu = _proto_classes()
    rng = np.random.default_rng(6)
    with open(path, "wb") as fh, Writer(fh) as w:
        for i in range(n):
            m = Imu()
            t = 1_700_000_000 * 10**9 + i * 2_500_000
            m.timestamp.seconds, m.timestamp.nanos = divmod(t, 10**9)
            if i % 4:  # proto3: a zero field is absent from the wire; a message may be too
                m.gyro.x, m.gyro.y, m.gyro.z = rng.normal(size=3)
            if i % 9 == 0:
                m.gyro.y = 0.0
            m.accel.extend((rng.normal(size=3) + [0, 0, 9.8]).tolist())
            m.mag.extend(rng.normal(size=3).tolist())
            m.temp = int(rng.integers(-40, 85))
            w.write_message("/imu_pb", m, log_time=t + 10, publish_time=t + 10)


@pytest.mark.parametrize("pure", ["", "1"], ids=["compiled", "numpy"])
def test_protobuf_mcap_equals_mcap_protobuf_decoder(tmp_path, monkeypatch, pure):
    """Both protobuf decodings (``readers/_protoscan.c`` when built, the numpy scan) against
    ``mcap-protobuf-support``, through the whole read."""
    monkeypatch.setenv(PURE_PYTHON_ENV, pure)
    path = tmp_path / "imu_pb.mcap"
    write_protobuf_mcap(path)
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        ref = [m for _, _, _, m in reader.iter_decoded_messages()]
    mapping = FieldMapping(
        gyro="/imu_pb.gyro",
        accel="/imu_pb.accel",
        mag="/imu_pb.mag",
        mag_unit="uT",
        temperature="/imu_pb.temp",
        time="/imu_pb.timestamp",
    )
    table, _ = read_input(InputSpec(path=path, fields=mapping))
    assert table.num_rows == len(ref) == 500
    assert np.array_equal(
        sensor(table, "gyro").values, [[m.gyro.x, m.gyro.y, m.gyro.z] for m in ref]
    )
    assert np.array_equal(sensor(table, "accel").values, [list(m.accel) for m in ref])
    assert np.array_equal(sensor(table, "mag").values, np.array([list(m.mag) for m in ref]) * 1e-6)
    assert np.array_equal(sensor(table, "temperature").values[:, 0], [m.temp for m in ref])
    want = [m.timestamp.seconds * 10**9 + m.timestamp.nanos for m in ref]
    assert np.array_equal(table.column("t_ns").to_numpy(), want)


def test_protobuf_field_tree():
    path_type = _proto_classes()
    from mcap_protobuf.schema import build_file_descriptor_set

    fds = build_file_descriptor_set(path_type).SerializeToString()
    mtype = protobuf_type("acme.Imu", fds)
    leaves = dict(mtype.leaves())
    assert leaves["gyro.x"] == "float64" and leaves["accel"] == "float64[]"
    assert leaves["timestamp.seconds"] == "int64"


def test_json_type_from_schema():
    mtype = json_type("imu_json", json.dumps(JSON_SCHEMA).encode())
    assert dict(mtype.leaves()) == {
        "t": "int64",
        "g.x": "float64",
        "g.y": "float64",
        "g.z": "float64",
        "a": "float64[3]",
        "label": "string",
    }


def test_unaligned_helper_reads_what_was_written():
    buf = np.frombuffer(b"\x00" + np.float64(1.5).tobytes(), np.uint8)
    assert unaligned(buf, "<f8")[1] == 1.5


# --- bad mappings: one line naming it, exit 2 ------------------------------------------------


def _cfg(tmp_path: Path, fields: str) -> Path:
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        f'[inputs.px4]\npath = "px4"\n\n[inputs.px4.fields]\n{fields}\n\n'
        '[[stages]]\ntype = "gyro_bias"\naccept_failed_checks = true\n\n'
        '[output]\ndir = "out"\nrerun = false\n'
    )
    return cfg


@pytest.mark.parametrize(
    ("fields", "needles"),
    [
        ('gyro = "/fmu/out/nope.gyro_rad"', ["gyro", "/fmu/out/nope.gyro_rad", "names no topic"]),
        (f'gyro = "{TOPIC}.gyro"', ["gyro", "has no field 'gyro'", "gyro_rad"]),
        (f'gyro = "{TOPIC}.gyro_integral_dt"', ["gyro", "uint32, not a Vector3-like"]),
        (
            f'gyro = ["{TOPIC}.gyro_rad", "{TOPIC}.gyro_rad.1", "{TOPIC}.gyro_rad.2"]',
            ["gyro", "float32[3], not one number"],
        ),
        (f'gyro = "{TOPIC}.gyro_rad"', ["time = 'header'", "has no header stamp"]),
        (f'gyro = "{TOPIC}.gyro_rad"\ntime = "{TOPIC}.nope"', ["time", "has no field 'nope'"]),
        (f'gyro = "{TOPIC}.gyro_rad"\ngyro_unit = "rpm"', ["gyro_unit", "'rpm' is not one of"]),
        (f'gyro = ["{TOPIC}.gyro_rad.0"]', ["gyro: must name 3 fields"]),
    ],
)
def test_bad_mapping_one_line_exit_2(tmp_path, fields, needles):
    write_px4_bag(tmp_path / "px4", "mcap", 20)
    proc = run_cli("run", _cfg(tmp_path, fields), "--quiet")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert not (tmp_path / "out").exists()


def test_mapped_run_end_to_end(tmp_path):
    write_px4_bag(tmp_path / "px4", "mcap", 400)
    proc = run_cli(
        "run",
        _cfg(
            tmp_path,
            f'gyro = "{TOPIC}.gyro_rad"\naccel = "{TOPIC}.accelerometer_m_s2"\n'
            f'time = "{TOPIC}.timestamp"\ntime_unit = "us"',
        ),
        "--quiet",
    )
    assert proc.returncode == 0, proc.stderr
    from mcap.reader import make_reader

    with open(tmp_path / "out" / "px4.mcap", "rb") as fh:
        got = [(c.topic, s.name) for s, c, _ in make_reader(fh).iter_messages()]
    assert len(got) == 400 and set(got) == {(TOPIC, "sensor_msgs/msg/Imu")}
    # convert reads the same mapping from --config
    read = tmp_path / "read.toml"
    read.write_text(
        f'[fields]\ngyro = "{TOPIC}.gyro_rad"\naccel = "{TOPIC}.accelerometer_m_s2"\ntime = "log"\n'
    )
    proc = run_cli(
        "convert",
        tmp_path / "px4",
        "--calibration",
        tmp_path / "out" / "calibration.json",
        "--out",
        tmp_path / "conv",
        "--config",
        read,
        "--jobs",
        "1",
        "--quiet",
    )
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "conv" / "px4.mcap", "rb") as fh:
        assert sum(1 for _ in make_reader(fh).iter_messages()) == 400


def test_short_sequence_is_a_read_error(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    text = "float64[] rate\n"
    store = _store(2, {"acme_msgs/msg/Seq": text})
    M = store.types["acme_msgs/msg/Seq"]
    folder = tmp_path / "seq"
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/seq", M.__msgtype__, typestore=store)
        for i, k in enumerate((3, 3, 2)):
            w.write(c, 10 + i, store.serialize_cdr(M(np.arange(k, dtype=float)), M.__msgtype__))
    with pytest.raises(ReadError, match=r"topic '/seq': message at log time 12 .*fewer than 3"):
        read_input(InputSpec(path=folder, fields=FieldMapping(gyro="/seq.rate", time="log")))


# --- inspect ----------------------------------------------------------------------------------


def test_inspect_lists_fields_and_the_mapping(tmp_path):
    write_px4_bag(tmp_path / "px4", "mcap", 30)
    write_protobuf_mcap(tmp_path / "pb.mcap", 20)
    write_json_mcap(tmp_path / "js.mcap", 20)
    proc = run_cli("inspect", tmp_path / "px4", "--json")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)["fields"][TOPIC]
    assert ["gyro_rad", "float32[3]"] in info["fields"]
    assert info["mapping"]["gyro"] == f"{TOPIC}.gyro_rad"
    assert info["mapping"]["accel"] == f"{TOPIC}.accelerometer_m_s2"
    assert info["mapping"]["time"] == f"{TOPIC}.timestamp"
    pb = json.loads(run_cli("inspect", tmp_path / "pb.mcap", "--json").stdout)["fields"]["/imu_pb"]
    assert pb["encoding"] == "protobuf"
    assert pb["mapping"] == {  # repeated fields too: a 3-element sequence reads as a vector
        "gyro": "/imu_pb.gyro",
        "accel": "/imu_pb.accel",
        "mag": "/imu_pb.mag",
        "temperature": "/imu_pb.temp",
        "time": "/imu_pb.timestamp",
    }
    text = run_cli("inspect", tmp_path / "js.mcap").stdout
    assert "fields of /imu_json (imu_json, json):" in text and "g.x float64" in text
    # with the mapping: the streams it fills
    cfg = tmp_path / "read.toml"
    cfg.write_text(f'[fields]\ngyro = "{TOPIC}.gyro_rad"\ntime = "log"\n')
    proc = run_cli("inspect", tmp_path / "px4", "--config", cfg, "--json")
    info = json.loads(proc.stdout)
    assert info["streams"]["imu"]["sensors"] == {"gyro": TOPIC}
    assert info["streams"]["imu"]["count"] == 30
    assert info["columns"] == ["t_ns", "log_time_ns", "gyro_x", "gyro_y", "gyro_z"]


def test_config_fields_table(tmp_path):
    from imupipe.pipeline.config import parse_input
    from imupipe.pipeline.errors import ConfigError

    (tmp_path / "a.mcap").touch()
    spec = parse_input(
        "a",
        {"path": "a.mcap", "time": "log", "fields": {"gyro": "/t.g", "gyro_unit": "deg/s"}},
        tmp_path,
        "[inputs.a]",
    )
    assert spec.fields == FieldMapping(gyro="/t.g", gyro_unit="deg/s", time="log")
    for raw, needle in (
        ({"imu_topic": "/imu", "fields": {"gyro": "/t.g"}}, "imu_topic: not used with [fields]"),
        ({"fields": {"time": "log"}}, "maps no sensor"),
        ({"fields": {"gyro": "nodot"}}, "is not TOPIC.FIELD"),
        ({"fields": {"gyro": "/t.g", "bogus": 1}}, "bogus"),
        ({"fields": {"gyro": 3}}, "gyro"),
    ):
        with pytest.raises(ConfigError, match=re.escape(needle)):
            parse_input("a", {"path": "a.mcap", **raw}, tmp_path, "[inputs.a]")


# --- real recordings (../shared/data, skipped when absent) ------------------------------------


def _rosbag1_reference(path: Path, topic: str) -> list:
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    with Reader(path) as r:
        conns = [c for c in r.connections if c.topic == topic]
        for c in conns:
            types = get_types_from_msg(c.msgdef.data, c.msgtype)
            store.register({k: v for k, v in types.items() if k not in store.fielddefs})
        return [store.deserialize_ros1(raw, c.msgtype) for c, _, raw in r.messages(conns)]


def _stamp(m) -> int:
    return m.header.stamp.sec * 10**9 + m.header.stamp.nanosec


def _valid_rows(table, column: str):
    return table.filter(table.column(column).is_valid())


@pytest.mark.parametrize(
    ("bag", "gyro_topic", "gyro_field", "mag_topic"),
    [
        ("madgwick_phidgets_imu_upside_down.bag", "/imu/data_raw", "angular_velocity", "/imu/mag"),
        ("madgwick_ardrone_imu.bag", "/ardrone/imu", "angular_velocity", "/ardrone/mag"),
        ("rl_test1.bag", "/husky_velocity_controller/odom", "twist.twist.angular", None),
    ],
)
def test_real_ros1_bags_equal_rosbags(bag, gyro_topic, gyro_field, mag_topic):
    """Recorded ROS 1 bags (imu_tools, robot_localization): each topic's definition from its
    connection header; nav_msgs/Odometry has strings and covariances before its twist."""
    from conftest import shared_path

    path = shared_path("logs", bag)
    mapping = FieldMapping(
        gyro=f"{gyro_topic}.{gyro_field}",
        mag=None if mag_topic is None else f"{mag_topic}.magnetic_field",
        mag_unit="T",
    )
    table, _ = read_input(InputSpec(path=path, fields=mapping))
    ref = _rosbag1_reference(path, gyro_topic)
    rows = _valid_rows(table, "gyro_x")
    assert rows.num_rows == len(ref) > 1000
    # stable time order: compare as sets of (stamp, values) sorted the same way
    want = np.array(
        [[_stamp(m), *(lambda v: (v.x, v.y, v.z))(_dig(m, gyro_field))] for m in ref],
        dtype=object,
    )
    order = np.argsort(np.array([w[0] for w in want], np.int64), kind="stable")
    want = want[order]
    assert np.array_equal(rows.column("t_ns").to_numpy(), want[:, 0].astype(np.int64))
    got = np.stack([rows.column(f"gyro_{a}").to_numpy() for a in "xyz"], axis=1)
    assert np.array_equal(got, want[:, 1:].astype(float), equal_nan=True)
    if mag_topic is not None:
        mref = _rosbag1_reference(path, mag_topic)
        mrows = _valid_rows(table, "mag_x")
        assert mrows.num_rows == len(mref)
        mags = np.array(
            [[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z] for m in mref]
        )
        stamps = np.array([_stamp(m) for m in mref])
        k = np.argsort(stamps, kind="stable")
        got = np.stack([mrows.column(f"mag_{a}").to_numpy() for a in "xyz"], axis=1)
        assert np.array_equal(got, mags[k], equal_nan=True)  # the recording has NaN fields
        # the same values as the sensor_msgs path reads from the same bag
        plain, _ = read_input(InputSpec(path=path))
        assert np.array_equal(
            np.sort(plain.column("gyro_x").drop_null().to_numpy()),
            np.sort(rows.column("gyro_x").to_numpy()),
        )
    assert table.num_rows == rows.num_rows + (0 if mag_topic is None else mrows.num_rows)


def _dig(msg, path: str):
    for part in path.split("."):
        msg = getattr(msg, part)
    return msg


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rosbag2_own_test_bags_equal_rosbags(storage):
    """rosbag2's own test bags (written by rosbag2's C++ serializer; Apache-2.0, in tests/data):
    test_msgs/Arrays (bool, byte and char arrays before float32[3]: CDR alignment) and
    test_msgs/BasicTypes on two topics, definitions from the bag."""
    from rosbags.highlevel import AnyReader

    from conftest import TEST_DATA

    path = TEST_DATA / "rosbag_peers" / "rosbag2" / f"rosbag2_tests__{storage}__cdr_test"
    mapping = FieldMapping(
        gyro="/array_topic.float64_values",
        accel="/array_topic.float32_values",
        mag=[
            "/array_topic.int32_values.0",
            "/array_topic.uint64_values.1",
            "/array_topic.int8_values.2",
        ],
        mag_unit="raw",
        temperature="/test_topic.float64_value",
        time="log",
    )
    table, _ = read_input(InputSpec(path=path, fields=mapping))
    with AnyReader([path]) as r:
        got = {c.topic: [] for c in r.connections}
        for c, t, raw in r.messages():
            got[c.topic].append((t, r.deserialize(raw, c.msgtype)))
    arrays, basics = got["/array_topic"], got["/test_topic"]
    assert table.num_rows == len(arrays) + len(basics) > 0
    rows = _valid_rows(table, "gyro_x")
    assert np.array_equal(rows.column("t_ns").to_numpy(), [t for t, _ in arrays])
    for name, field in (("gyro", "float64_values"), ("accel", "float32_values")):
        values = np.stack([rows.column(f"{name}_{a}").to_numpy() for a in "xyz"], axis=1)
        assert np.array_equal(values, [getattr(m, field).astype(float) for _, m in arrays])
    mag = np.stack([rows.column(f"mag_{a}").to_numpy() for a in "xyz"], axis=1)
    want = [[m.int32_values[0], m.uint64_values[1], m.int8_values[2]] for _, m in arrays]
    assert np.array_equal(mag, np.array(want, float))
    temp = _valid_rows(table, "temperature")
    assert np.array_equal(
        temp.column("temperature").to_numpy(), [m.float64_value for _, m in basics]
    )
    assert np.array_equal(temp.column("t_ns").to_numpy(), [t for t, _ in basics])


def test_protobuf_repeated_message_falls_back_to_protobuf():
    from google.protobuf import descriptor_pb2

    fd = descriptor_pb2.FileDescriptorProto(
        name="acme/multi.proto", package="acme", syntax="proto3"
    )
    vec = fd.message_type.add(name="V")
    for i, k in enumerate("xyz", 1):
        vec.field.add(name=k, number=i, type=1, label=1)
    multi = fd.message_type.add(name="Multi")
    multi.field.add(name="imus", number=1, type=11, label=3, type_name=".acme.V")
    fds = descriptor_pb2.FileDescriptorSet(file=[fd]).SerializeToString()
    mtype = protobuf_type("acme.Multi", fds)
    msg = mtype._source()
    payloads = []
    for k in range(4):
        msg.Clear()
        for j in range(2):
            v = msg.imus.add()
            v.x, v.y, v.z = k, j, k * j + 0.5
        payloads.append(msg.SerializeToString())
    buf = np.frombuffer(b"".join(payloads), np.uint8)
    lengths = np.array([len(p) for p in payloads])
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    (z,) = mtype.decode(buf, starts, lengths, [Leaf(("imus", 1, "z"))])
    assert np.array_equal(z, [0.5, 1.5, 2.5, 3.5])


def test_python_api_read_with_fields(tmp_path):
    import imupipe

    write_px4_bag(tmp_path / "px4", "mcap", 40)
    table = imupipe.read(
        tmp_path / "px4",
        fields={"gyro": f"{TOPIC}.gyro_rad", "time": f"{TOPIC}.timestamp", "time_unit": "us"},
    )
    assert table.num_rows == 40 and table.column("gyro_x").null_count == 0
    info = imupipe.inspect(tmp_path / "px4", fields={"gyro": f"{TOPIC}.gyro_rad", "time": "log"})
    assert info.info["streams"]["imu"]["sensors"] == {"gyro": TOPIC}


def test_cut_payloads_are_payload_errors():
    """Every payload cut short is a PayloadError naming the message, never an IndexError or a
    value read past the payload (the next message's bytes)."""
    from imupipe.readers.cdr import PayloadError

    store = _store(2, {"acme_msgs/msg/Rate": DRIVER})
    M = store.types["acme_msgs/msg/Rate"]
    H = store.types["std_msgs/msg/Header"]
    T = store.types["builtin_interfaces/msg/Time"]
    Vec = store.types["geometry_msgs/msg/Vector3"]
    full = bytes(
        store.serialize_cdr(
            M(H(T(1, 2), "imu"), "SN1", np.arange(3.0), Vec(1, 2, 3), np.float32(4)),
            M.__msgtype__,
        )
    )
    mtype = ros_type(
        "acme_msgs/msg/Rate", "cdr", "ros2msg", store.generate_msgdef(M.__msgtype__)[0]
    )
    leaves = [Leaf(("rate", "x")), Leaf(("temp_c",)), Leaf(("raw", 2))]
    Imu = _proto_classes()
    pmsg = Imu()
    pmsg.timestamp.seconds = 5
    pmsg.gyro.x, pmsg.gyro.y, pmsg.gyro.z = 1.0, 2.0, 3.0
    pmsg.accel.extend([1.0, 2.0, 3.0])
    from mcap_protobuf.schema import build_file_descriptor_set

    ptype = protobuf_type("acme.Imu", build_file_descriptor_set(Imu).SerializeToString())
    pfull = pmsg.SerializeToString()
    pleaves = [Leaf(("gyro", "z")), Leaf(("accel", 2))]
    for payload, mt, lv in ((full, mtype, leaves), (pfull, ptype, pleaves)):
        for cut in range(1, len(payload)):
            data = payload[:cut] + payload  # the cut message, then a whole one after it
            buf = np.frombuffer(data, np.uint8)
            starts, lengths = np.array([0, cut]), np.array([cut, len(payload)])
            try:
                values = mt.decode(buf, starts, lengths, lv)
            except PayloadError as exc:
                assert exc.index == 0
                continue
            # a protobuf message cut between fields is a valid, shorter message
            ref = mt.decode_reference(buf, starts, lengths, lv)
            assert all(np.array_equal(a, b) for a, b in zip(values, ref, strict=True)), cut


def write_split_json_mcap(path: Path, n: int = 900) -> None:
    """Gyro at 400 Hz and accel at 250 Hz on JSON topics of their own, a text topic beside
    them, in small chunks (many per file), in log-time order."""
    from mcap.writer import Writer

    rng = np.random.default_rng(8)
    schema = json.dumps(
        {"type": "object", "properties": {"v": {"type": "array", "items": {"type": "number"}}}}
    ).encode()
    events = []
    for topic, rate in (("/gyro", 400), ("/accel", 250), ("/note", 7)):
        for i in range(n * rate // 400):
            t = 10**18 + i * 10**9 // rate + {"/gyro": 0, "/accel": 1, "/note": 2}[topic]
            events.append((t, topic, rng.normal(size=3).tolist()))
    events.sort()
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=4096)
        w.start()
        sid = w.register_schema("vec", "jsonschema", schema)
        cids = {t: w.register_channel(t, "json", sid) for t in ("/gyro", "/accel", "/note")}
        for t, topic, v in events:
            w.add_message(
                cids[topic], log_time=t, data=json.dumps({"v": v}).encode(), publish_time=t
            )
        w.finish()


def test_mapped_input_streams_in_batches(tmp_path):
    """iter_input reads a mapped input in batches of about batch_rows (whole chunks): together
    the rows of one read, each carried-over message once, in log-time order."""
    import pyarrow as pa

    from imupipe.readers.dispatch import iter_input

    path = tmp_path / "split.mcap"
    write_split_json_mcap(path)
    mapping = FieldMapping(gyro="/gyro.v", accel="/accel.v", time="log")
    spec = InputSpec(path=path, fields=mapping)
    whole, _ = read_input(spec)
    warned: list[str] = []
    batches = list(iter_input(spec, batch_rows=300, warnings=warned))
    assert len(batches) > 3
    assert all(b.num_rows < 300 + 200 for b, _ in batches)  # a batch: rows of whole chunks
    joined = pa.concat_tables([b for b, _ in batches])
    assert joined.num_rows == whole.num_rows == 900 + 562
    for name in ("t_ns", "log_time_ns", "gyro_x", "accel_z"):
        assert joined.column(name).equals(whole.column(name)), name
    notes = [m for _, carried in batches for m in carried]
    assert [m.topic for m in notes] == ["/note"] * (900 * 7 // 400)
    times = [m.log_time for m in notes]
    assert times == sorted(times)
    for table, carried in batches[:-1]:  # a batch carries what was logged up to its end
        assert all(m.log_time <= table.column("log_time_ns").to_numpy().max() for m in carried)


def test_mapped_convert_is_the_same_whatever_the_batch(tmp_path):
    """convert of a mapped input several batches long writes the same messages, byte for byte
    and in the same order, as in one batch; every carried-over message once."""
    from test_convert import raw_messages

    from imupipe.pipeline.convert.fleet import convert

    log = tmp_path / "split.mcap"
    write_split_json_mcap(log, n=600)
    read = tmp_path / "read.toml"
    read.write_text('[fields]\ngyro = "/gyro.v"\naccel = "/accel.v"\ntime = "log"\n')
    chain = [
        {"type": "gyro_bias", "sensor": "gyro", "kind": "linear",
         "matrix": np.eye(3).tolist(), "offset": [0.01, -0.02, 0.005]},
    ]  # fmt: skip
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"imupipe_version": "test", "chain": chain, "results": {}}))
    outputs = {}
    for rows in (200, 10**9):
        out = tmp_path / f"out{rows}"
        summary = convert([log], cal, out, config=read, jobs=1, batch_rows=rows)
        assert not summary.failed and len(summary.converted) == 1
        outputs[rows] = raw_messages(out / "split.mcap")
    assert outputs[200] == outputs[10**9]
    assert {t: len(m) for t, m in outputs[200].items()} == {
        "/gyro": 600, "/accel": 375, "/note": 600 * 7 // 400,
    }  # fmt: skip
