"""Issue 37 item 5: a real recording through the containers of issue 37, value for value equal
to the reference readers.

No real recording of these kinds (a RealSense bag with separate IMU topics, a PX4 ROS 2 bag of
``px4_msgs``, a Foxglove JSON or protobuf MCAP) could be found in a public repository under a
licence that lets it be copied here, at a size a test can carry (docs/how-to/test-data.md lists
what was searched). So the values here are real and the containers are written with the
reference writers: the Pixhawk 6C ULog in ``tests/data/px4_ulog`` (foxglove/mcap's fixture, MIT)
is read with pyulog, and its ``sensor_combined`` (1,297 samples) and raw ``sensor_gyro`` /
``sensor_accel`` instances are written

* as PX4's ROS 2 bridge publishes them (``px4_msgs/msg/SensorCombined`` on
  ``/fmu/out/sensor_combined``, PX4's .msg text) with rosbags' rosbag2 writer, MCAP and sqlite3;
* as two ``sensor_msgs/msg/Imu`` topics, realsense-ros' ``/camera/gyro/sample`` and
  ``/camera/accel/sample`` (the other vector zeros), ROS 2 and ROS 1, read with ``gyro_topic``
  and ``accel_topic``;
* in the layout of foxglove/mcap's ``python/examples/ulog2mcap`` converter (one channel per
  ULog topic and instance, ``/sensor_gyro/1``; a proto3 message ``ulog.<topic>`` of the ULog
  fields but ``timestamp``, arrays as packed repeated fields, the ULog time as log time) with
  mcap's writer and mcap-protobuf-support's schema builder, and the same as ``json`` channels
  with a jsonschema.

Every sample read by imupipe equals what the reference reader decodes (rosbags' deserializer,
mcap-protobuf-support's decoder, ``json.loads``) and what pyulog read from the ULog (float32
values widened to float64 exactly; times in int64 ns), counts equal.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_mapped_fields import PX4_MAPPING, SENSOR_COMBINED, TOPIC, _store, reference_rosbag2

from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import FieldMapping, InputSpec
from imupipe.readers.table import sensor

ULOG = Path(__file__).parent / "data" / "px4_ulog" / "pixhawk6c_bmi055.ulg"
EPOCH_NS = 1_700_000_000 * 10**9
"""Wall-clock time at PX4's boot for the bags' log times (ULog times are since boot)."""


@pytest.fixture(scope="module")
def ulog():
    from pyulog import ULog

    return ULog(str(ULOG), ["sensor_combined", "sensor_gyro", "sensor_accel"])


def _combined(ulog) -> dict[str, np.ndarray]:
    """sensor_combined as pyulog reads it: time (us since boot), gyro and accel (n, 3) float32."""
    d = ulog.get_dataset("sensor_combined").data
    return {
        "t_us": d["timestamp"].astype(np.int64),
        "gyro": np.stack([d[f"gyro_rad[{i}]"] for i in range(3)], axis=1),
        "accel": np.stack([d[f"accelerometer_m_s2[{i}]"] for i in range(3)], axis=1),
        "raw": d,
    }


def _rows(table, name: str):
    """The rows of the table where sensor ``name`` is valid: t_ns and the (n, 3) values."""
    valid = table.column(f"{name}_x").is_valid().to_numpy(zero_copy_only=False)
    rows = table.filter(valid)
    values = np.stack([rows.column(f"{name}_{a}").to_numpy() for a in "xyz"], axis=1)
    return rows.column("t_ns").to_numpy(), values


# --- a PX4 ROS 2 bag of px4_msgs -------------------------------------------------------------


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_px4_bag_of_real_sensor_combined(tmp_path, ulog, storage):
    from rosbags.rosbag2 import StoragePlugin, Writer

    sc = _combined(ulog)
    store = _store(2, {"px4_msgs/msg/SensorCombined": SENSOR_COMBINED})
    M = store.types["px4_msgs/msg/SensorCombined"]
    raw = sc["raw"]
    folder = tmp_path / "px4"
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(folder, version=9, storage_plugin=plugin) as w:
        c = w.add_connection(TOPIC, M.__msgtype__, typestore=store)
        for i in range(len(sc["t_us"])):
            m = M(
                timestamp=np.uint64(sc["t_us"][i]),
                gyro_rad=sc["gyro"][i],
                gyro_integral_dt=int(raw["gyro_integral_dt"][i]),
                accelerometer_timestamp_relative=int(raw["accelerometer_timestamp_relative"][i]),
                accelerometer_m_s2=sc["accel"][i],
                accelerometer_integral_dt=int(raw["accelerometer_integral_dt"][i]),
                accelerometer_clipping=int(raw["accelerometer_clipping"][i]),
                gyro_clipping=int(raw["gyro_clipping"][i]),
                accel_calibration_count=int(raw["accel_calibration_count"][i]),
                gyro_calibration_count=int(raw["gyro_calibration_count"][i]),
            )
            # the bridge's arrival time: boot time plus the sample time plus a transport delay
            log_ns = EPOCH_NS + int(sc["t_us"][i]) * 1000 + 150_000 + 1000 * (i % 7)
            w.write(c, log_ns, store.serialize_cdr(m, M.__msgtype__))
    ref = reference_rosbag2(folder, TOPIC, store)
    table, warnings = read_input(InputSpec(path=folder, fields=PX4_MAPPING))
    assert warnings == []
    assert table.num_rows == len(ref) == len(sc["t_us"]) == 1297
    gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
    assert np.array_equal(gyro.t_ns, [int(m.timestamp) * 1000 for _, m in ref])
    assert np.array_equal(gyro.t_ns, sc["t_us"] * 1000)
    assert np.array_equal(gyro.values, np.array([m.gyro_rad for _, m in ref], np.float64))
    assert np.array_equal(gyro.values, sc["gyro"].astype(np.float64))
    assert np.array_equal(accel.values, np.array([m.accelerometer_m_s2 for _, m in ref], float))
    assert np.array_equal(accel.values, sc["accel"].astype(np.float64))
    assert np.array_equal(table.column("log_time_ns").to_numpy(), [t for t, _ in ref])

    # time = "log": the arrival times, as recorded
    by_log = FieldMapping(gyro=PX4_MAPPING.gyro, accel=PX4_MAPPING.accel, time="log")
    table, _ = read_input(InputSpec(path=folder, fields=by_log))
    assert np.array_equal(table.column("t_ns").to_numpy(), [t for t, _ in ref])


# --- a camera's gyro and accelerometer on two sensor_msgs/Imu topics -------------------------

GYRO_TOPIC, ACCEL_TOPIC = "/camera/gyro/sample", "/camera/accel/sample"


def _split_imu_messages(store, sc, ros: int):
    """realsense-ros' two topics from sensor_combined: the gyro's message with zero linear
    acceleration, the accelerometer's with zero angular velocity, each stamped with the sample
    time (PX4 here samples both on one clock, so every gyro stamp has an equal accel stamp)."""
    Imu = store.types["sensor_msgs/msg/Imu"]
    H = store.types["std_msgs/msg/Header"]
    V = store.types["geometry_msgs/msg/Vector3"]
    Q = store.types["geometry_msgs/msg/Quaternion"]
    Time = store.types["builtin_interfaces/msg/Time"]
    cov = np.zeros(9)
    events = []
    for i, t_us in enumerate(sc["t_us"]):
        t = EPOCH_NS + int(t_us) * 1000
        stamp = Time(t // 10**9, t % 10**9)
        zero = V(0.0, 0.0, 0.0)
        for k, (topic, frame) in enumerate(
            ((GYRO_TOPIC, "camera_gyro_optical_frame"), (ACCEL_TOPIC, "camera_accel_optical_frame"))
        ):
            vec = V(*(float(v) for v in sc["gyro" if k == 0 else "accel"][i]))
            header = H(stamp, frame) if ros == 2 else H(i, stamp, frame)
            msg = Imu(
                header, Q(0.0, 0.0, 0.0, 1.0), cov, vec if k == 0 else zero, cov,
                zero if k == 0 else vec, cov,
            )  # fmt: skip
            # the accel's message reaches the recorder before the gyro's every third sample
            events.append((t + 200_000 + (30_000 if (k == 0 and i % 3 == 0) else k), topic, msg))
    events.sort(key=lambda e: e[0])
    return Imu, events


@pytest.mark.parametrize("ros", [1, 2])
def test_two_imu_topics_of_real_values(tmp_path, ulog, ros):
    sc = _combined(ulog)
    store = _store(ros, {})
    Imu, events = _split_imu_messages(store, sc, ros)
    msgtype = Imu.__msgtype__
    if ros == 2:
        from rosbags.rosbag2 import StoragePlugin, Writer

        path = tmp_path / "cam"
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns = {
                t: w.add_connection(t, msgtype, typestore=store) for t in (GYRO_TOPIC, ACCEL_TOPIC)
            }
            for lt, topic, msg in events:
                w.write(conns[topic], lt, store.serialize_cdr(msg, msgtype))
        ref = {
            t: [m for _, m in reference_rosbag2(path, t, store)] for t in (GYRO_TOPIC, ACCEL_TOPIC)
        }
    else:
        from rosbags.rosbag1 import Reader, Writer

        path = tmp_path / "cam.bag"
        with Writer(path) as w:
            conns = {
                t: w.add_connection(t, msgtype, typestore=store) for t in (GYRO_TOPIC, ACCEL_TOPIC)
            }
            for lt, topic, msg in events:
                w.write(conns[topic], lt, store.serialize_ros1(msg, msgtype))
        ref = {}
        with Reader(path) as r:
            for t in (GYRO_TOPIC, ACCEL_TOPIC):
                cs = [c for c in r.connections if c.topic == t]
                ref[t] = [store.deserialize_ros1(raw, msgtype) for _, _, raw in r.messages(cs)]
    n = len(sc["t_us"])
    assert len(ref[GYRO_TOPIC]) == len(ref[ACCEL_TOPIC]) == n == 1297

    def stamps(msgs):
        return [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs]

    def vec(msgs, field):
        return [[getattr(m, field).x, getattr(m, field).y, getattr(m, field).z] for m in msgs]

    spec = InputSpec(path=path, gyro_topic=GYRO_TOPIC, accel_topic=ACCEL_TOPIC)
    mapping = FieldMapping(
        gyro=f"{GYRO_TOPIC}.angular_velocity", accel=f"{ACCEL_TOPIC}.linear_acceleration"
    )
    # no topic named: two Imu topics named for the gyro and the accel are read apart, with a
    # warning naming the choice
    auto, warnings = read_input(InputSpec(path=path))
    assert any(GYRO_TOPIC in w and ACCEL_TOPIC in w for w in warnings), warnings
    assert read_input(spec)[0].equals(auto)
    for table, _ in ((auto, None), read_input(InputSpec(path=path, fields=mapping))):
        assert table.num_rows == 2 * n  # a row per message, none merged, none dropped
        t_g, g = _rows(table, "gyro")
        t_a, a = _rows(table, "accel")
        assert np.array_equal(t_g, stamps(ref[GYRO_TOPIC]))
        assert np.array_equal(t_a, stamps(ref[ACCEL_TOPIC]))
        assert np.array_equal(g, vec(ref[GYRO_TOPIC], "angular_velocity"))
        assert np.array_equal(a, vec(ref[ACCEL_TOPIC], "linear_acceleration"))
        assert np.array_equal(g, sc["gyro"].astype(np.float64))
        assert np.array_equal(a, sc["accel"].astype(np.float64))
        # equal stamps: the gyro's row first, then the accel's (the documented order)
        gyro_valid = table.column("gyro_x").is_valid().to_numpy(zero_copy_only=False)
        assert np.array_equal(gyro_valid, np.tile([True, False], n))
        assert table.column("accel_x").null_count == n == table.column("gyro_x").null_count


# --- Foxglove protobuf and JSON MCAP (ulog2mcap's layout) ------------------------------------

_PB_TYPE = {
    "int8_t": 5, "int16_t": 5, "int32_t": 5, "uint8_t": 13, "uint16_t": 13, "uint32_t": 13,
    "int64_t": 3, "uint64_t": 4, "float": 2, "double": 1, "bool": 8,
}  # fmt: skip
"""ULog primitive type -> FieldDescriptorProto.Type (int32, uint32, int64, uint64, float,
double, bool), the widening protobuf needs for the 8- and 16-bit types."""

_JSON_TYPE = {"float": "number", "double": "number", "bool": "boolean"}


def _channels(ulog):
    """(topic, message name, fields, pyulog dataset) per ULog dataset: ulog2mcap's topic
    ``/<name>`` or ``/<name>/<multi_id>``, its fields all but ``timestamp`` and padding."""
    out = []
    for d in ulog.data_list:
        topic = f"/{d.name}/{d.multi_id}" if d.multi_id else f"/{d.name}"
        fields = [
            (typ, n, name)
            for typ, n, name in ulog.message_formats[d.name].fields
            if name != "timestamp" and not name.startswith("_padding")
        ]
        out.append((topic, d.name, fields, d))
    return out


def _values(d, typ: str, n: int, name: str, i: int):
    if n:
        return [d.data[f"{name}[{k}]"][i].item() for k in range(n)]
    return d.data[name][i].item()


def write_ulog_protobuf_mcap(path: Path, ulog) -> None:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.writer import Writer
    from mcap_protobuf.schema import build_file_descriptor_set

    fd = descriptor_pb2.FileDescriptorProto(
        name="ulog_messages_test.proto", package="ulog", syntax="proto3"
    )
    chans = _channels(ulog)
    for name in dict.fromkeys(c[1] for c in chans):
        desc = fd.message_type.add(name=name)
        fields = next(c[2] for c in chans if c[1] == name)
        for number, (typ, n, fname) in enumerate(fields, 1):
            desc.field.add(name=fname, number=number, type=_PB_TYPE[typ], label=3 if n else 1)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fd)
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        for topic, name, fields, d in chans:
            cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(f"ulog.{name}"))
            fds = build_file_descriptor_set(cls)
            sid = w.register_schema(f"ulog.{name}", "protobuf", fds.SerializeToString())
            cid = w.register_channel(topic, "protobuf", sid)
            for i, t_us in enumerate(d.data["timestamp"]):
                m = cls()
                for typ, n, fname in fields:
                    v = _values(d, typ, n, fname, i)
                    getattr(m, fname).extend(v) if n else setattr(m, fname, v)
                t = int(t_us) * 1000
                w.add_message(cid, log_time=t, data=m.SerializeToString(), publish_time=t)
        w.finish()


def write_ulog_json_mcap(path: Path, ulog) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        for topic, name, fields, d in _channels(ulog):
            props = {}
            for typ, n, fname in fields:
                kind = {"type": _JSON_TYPE.get(typ, "integer")}
                props[fname] = {"type": "array", "items": kind} if n else kind
            schema = json.dumps({"type": "object", "properties": props}).encode()
            cid = w.register_channel(topic, "json", w.register_schema(name, "jsonschema", schema))
            for i, t_us in enumerate(d.data["timestamp"]):
                doc = {fname: _values(d, typ, n, fname, i) for typ, n, fname in fields}
                t = int(t_us) * 1000
                w.add_message(cid, log_time=t, data=json.dumps(doc).encode(), publish_time=t)
        w.finish()


def _decoded(path: Path, encoding: str) -> dict[str, list]:
    """Every message per topic as the reference decoder gives it (a protobuf message, a dict)."""
    from mcap.reader import make_reader

    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        if encoding == "protobuf":
            from mcap_protobuf.decoder import DecoderFactory

            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, ch, msg, m in reader.iter_decoded_messages():
                out.setdefault(ch.topic, []).append((msg.log_time, m))
        else:
            for _, ch, msg in make_reader(fh).iter_messages():
                out.setdefault(ch.topic, []).append((msg.log_time, json.loads(msg.data)))
    return out


def _get(m, field):
    return m[field] if isinstance(m, dict) else getattr(m, field)


@pytest.mark.parametrize("encoding", ["protobuf", "json"])
def test_ulog2mcap_layout_of_real_log(tmp_path, ulog, encoding):
    path = tmp_path / f"ulog_{encoding}.mcap"
    (write_ulog_protobuf_mcap if encoding == "protobuf" else write_ulog_json_mcap)(path, ulog)
    ref = _decoded(path, encoding)
    sc = _combined(ulog)

    # sensor_combined: the arrays, the log time (ulog2mcap drops the timestamp field)
    mapping = FieldMapping(
        gyro="/sensor_combined.gyro_rad", accel="/sensor_combined.accelerometer_m_s2", time="log"
    )
    table, warnings = read_input(InputSpec(path=path, fields=mapping))
    assert warnings == []
    want = ref["/sensor_combined"]
    assert table.num_rows == len(want) == 1297
    assert np.array_equal(table.column("t_ns").to_numpy(), [t for t, _ in want])
    assert np.array_equal(table.column("t_ns").to_numpy(), sc["t_us"] * 1000)
    for name, field in (("gyro", "gyro_rad"), ("accel", "accelerometer_m_s2")):
        values = sensor(table, name).values
        assert np.array_equal(values, [list(_get(m, field)) for _, m in want])
        assert np.array_equal(values, sc[name].astype(np.float64))

    # the raw instance 1 of the chip: gyro and accel on their own topics and sample clocks,
    # three scalar fields each, the chip temperature, time = each message's timestamp_sample
    mapping = FieldMapping(
        gyro=[f"/sensor_gyro/1.{k}" for k in "xyz"],
        accel=[f"/sensor_accel/1.{k}" for k in "xyz"],
        temperature="/sensor_gyro/1.temperature",
        time="/sensor_gyro/1.timestamp_sample",
        time_unit="us",
    )
    table, _ = read_input(InputSpec(path=path, fields=mapping))
    g_ref, a_ref = ref["/sensor_gyro/1"], ref["/sensor_accel/1"]
    assert table.num_rows == len(g_ref) + len(a_ref) == 12
    for name, msgs in (("gyro", g_ref), ("accel", a_ref)):
        t, values = _rows(table, name)
        assert np.array_equal(t, [int(_get(m, "timestamp_sample")) * 1000 for _, m in msgs])
        assert np.array_equal(values, [[_get(m, k) for k in "xyz"] for _, m in msgs])
    temp = table.column("temperature").to_numpy(zero_copy_only=False)
    gyro_rows = table.column("gyro_x").is_valid().to_numpy(zero_copy_only=False)
    assert np.array_equal(temp[gyro_rows], [_get(m, "temperature") for _, m in g_ref])
    pyulog_gyro = next(d for d in ulog.data_list if d.name == "sensor_gyro" and d.multi_id == 1)
    assert np.array_equal(temp[gyro_rows], pyulog_gyro.data["temperature"].astype(np.float64))


def test_written_layout_is_ulog2mcap(tmp_path, ulog):
    """The channels are ulog2mcap's: one per dataset, its topic and count, the message name."""
    path = tmp_path / "u.mcap"
    write_ulog_protobuf_mcap(path, ulog)
    ref = _decoded(path, "protobuf")
    assert {k: len(v) for k, v in ref.items()} == {
        "/sensor_combined": 1297,
        "/sensor_gyro": 6,
        "/sensor_gyro/1": 6,
        "/sensor_accel": 6,
        "/sensor_accel/1": 6,
    }
    m = ref["/sensor_combined"][0][1]
    assert m.DESCRIPTOR.full_name == "ulog.sensor_combined"
    assert "timestamp" not in m.DESCRIPTOR.fields_by_name


def _inspect_fields(path: Path) -> dict:
    from conftest import run_cli

    proc = run_cli("inspect", path, "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)["fields"]


def test_inspect_suggests_ulog2mcap_sensor_combined(tmp_path, ulog):
    path = tmp_path / "u.mcap"
    write_ulog_protobuf_mcap(path, ulog)
    info = _inspect_fields(path)["/sensor_combined"]
    assert info["mapping"].get("gyro") == "/sensor_combined.gyro_rad"
    assert info["mapping"].get("accel") == "/sensor_combined.accelerometer_m_s2"


def test_inspect_suggests_xyz_scalars_of_sensor_gyro(tmp_path, ulog):
    path = tmp_path / "u.mcap"
    write_ulog_protobuf_mcap(path, ulog)
    info = _inspect_fields(path)["/sensor_gyro/1"]
    assert info["mapping"].get("gyro") == [f"/sensor_gyro/1.{k}" for k in "xyz"]
    assert info["mapping"].get("time") == "/sensor_gyro/1.timestamp_sample"
