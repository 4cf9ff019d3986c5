"""Messages in = messages out, fields as they came (issue 18 item 2, issue 13 item 1).

Every field of every message of the input and of the corrected MCAP is compared: header stamp,
frame_id, orientation, every covariance, the values (corrected by the chain where a step applies,
NaN kept as NaN), log time and publish time, and every carried-over message. Inputs: MCAP, ROS 1
bag, ROS 2 bag (sqlite3) and CSV, generated here with rosbags' and the mcap library's writers
(never imupipe's), plus the real bags of ``../shared/data/logs``; ``time = "header"`` and
``"log"``; through ``imupipe run`` and ``imupipe convert``. Both sides are decoded with
independent decoders: ``mcap`` + ``mcap_ros2`` for MCAP files, ``rosbags`` for bags, Python's
``csv`` for CSV.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer as RawMcapWriter
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.base import Nodetype

from imupipe.pipeline.writers.corrected import write_corrected
from imupipe.pipeline.writers.mcap import McapTableWriter, write_mcap
from imupipe.readers.dispatch import carry_over, iter_input, read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import has_sensor, sensor
from imupipe.stages.steps import LinearStep, apply_chain

from conftest import SHARED, run_cli

T0 = 1_700_000_000_000_000_000
IMU, MAG, TEMP, FIX, NOTE = "/imu/data", "/imu/mag", "/imu/temp", "/gps/fix", "/note"
TYPES = {
    IMU: "sensor_msgs/msg/Imu",
    MAG: "sensor_msgs/msg/MagneticField",
    TEMP: "sensor_msgs/msg/Temperature",
    FIX: "sensor_msgs/msg/NavSatFix",
    NOTE: "std_msgs/msg/String",
}
CORRECTED = {
    "sensor_msgs/msg/Imu": {"angular_velocity": "gyro", "linear_acceleration": "accel"},
    "sensor_msgs/msg/MagneticField": {"magnetic_field": "mag"},
}
"""Per message type: the vector fields a linear step of each sensor corrects."""

CHAIN = [
    LinearStep(
        "test",
        "gyro",
        np.array([[1.01, 0.002, 0], [0, 0.99, 0.003], [0.001, 0, 1.02]]),
        [0.01, -0.02, 0.005],
    ),
    LinearStep("test", "accel", np.diag([1.001, 0.998, 1.003]), [0.05, -0.03, 0.1]),
    LinearStep("test", "mag", np.diag([1.1, 0.9, 1.05]), [1e-6, -2e-6, 3e-6]),
]
"""A calibration whose every step changes its sensor's values (and nothing else)."""


# --- generated logs, written with rosbags' and the mcap library's writers --------------------


def _stamp(t: int) -> dict[str, int]:
    return {"sec": int(t // 1_000_000_000), "nanosec": int(t % 1_000_000_000)}


def _vec(v: np.ndarray) -> dict[str, float]:
    return {a: float(x) for a, x in zip("xyz", v, strict=False)}


def generated_messages(n_imu: int = 1200, seed: int = 7) -> dict[str, list[tuple[int, int, dict]]]:
    """topic -> [(log time, publish time, message as nested dicts)], in log order.

    Imu at 200 Hz with two frame_ids, MagneticField at 50 Hz, Temperature at 2 Hz, and two topics
    to carry over (NavSatFix, String). Header stamps are 3-3.4 ms before the log time (jitter),
    publish times between the two; header order and log order agree across topics (a log in time
    order). Some values are NaN: gyro x of one message, a whole gyro vector, one accel axis, a
    whole orientation, a whole magnetic field, a temperature."""
    rng = np.random.default_rng(seed)

    def times(n: int, offset: int, period: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        stamp = T0 + offset + np.arange(n, dtype=np.int64) * period
        log = stamp + 3_000_000 + rng.integers(0, 400_000, n)
        pub = stamp + rng.integers(1_000_000, 2_000_000, n)
        return stamp, log, pub

    out: dict[str, list[tuple[int, int, dict]]] = {}
    stamp, log, pub = times(n_imu, 0, 5_000_000)
    gyro = rng.normal(0.0, 0.01, (n_imu, 3)) + [0.002, -0.001, 0.003]
    accel = rng.normal(0.0, 0.05, (n_imu, 3)) + [0.0, 0.0, 9.81]
    quat = rng.normal(size=(n_imu, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    gyro[100, 0] = np.nan
    gyro[200] = np.nan
    accel[300, 1] = np.nan
    quat[400] = np.nan
    frames = np.where(rng.random(n_imu) < 0.5, "imu_link", "imu")
    out[IMU] = [
        (
            int(log[i]),
            int(pub[i]),
            {
                "header": {"stamp": _stamp(stamp[i]), "frame_id": str(frames[i])},
                "orientation": {a: float(x) for a, x in zip("xyzw", quat[i], strict=True)},
                "orientation_covariance": rng.normal(size=9).tolist(),
                "angular_velocity": _vec(gyro[i]),
                "angular_velocity_covariance": rng.normal(size=9).tolist(),
                "linear_acceleration": _vec(accel[i]),
                "linear_acceleration_covariance": rng.normal(size=9).tolist(),
            },
        )
        for i in range(n_imu)
    ]
    n = n_imu // 4
    stamp, log, pub = times(n, 2_500_000, 20_000_000)
    mag = rng.normal(0.0, 3e-5, (n, 3))
    mag[50] = np.nan
    out[MAG] = [
        (
            int(log[i]),
            int(pub[i]),
            {
                "header": {"stamp": _stamp(stamp[i]), "frame_id": "magnetometer"},
                "magnetic_field": _vec(mag[i]),
                "magnetic_field_covariance": rng.normal(size=9).tolist(),
            },
        )
        for i in range(n)
    ]
    n = n_imu // 100
    stamp, log, pub = times(n, 1_300_000, 500_000_000)
    temp = rng.normal(25.0, 1.0, n)
    temp[3] = np.nan
    out[TEMP] = [
        (
            int(log[i]),
            int(pub[i]),
            {
                "header": {"stamp": _stamp(stamp[i]), "frame_id": "t"},
                "temperature": float(temp[i]),
                "variance": float(rng.uniform()),
            },
        )
        for i in range(n)
    ]
    n = n_imu // 40
    stamp, log, pub = times(n, 3_700_000, 200_000_000)
    out[FIX] = [
        (
            int(log[i]),
            int(pub[i]),
            {
                "header": {"stamp": _stamp(stamp[i]), "frame_id": "gps"},
                "status": {"status": 0, "service": 1},
                "latitude": float(rng.uniform(-90, 90)),
                "longitude": float(rng.uniform(-180, 180)),
                "altitude": float(rng.normal(100, 10)),
                "position_covariance": rng.uniform(0, 1, 9).tolist(),
                "position_covariance_type": 2,
            },
        )
        for i in range(n)
    ]
    out[NOTE] = [
        (int(T0 + 4_100_000 + i * 1_000_000_000), int(T0 + i * 1_000_000_000), {"data": f"n{i}"})
        for i in range(n_imu // 200)
    ]
    return out


def _build(store: Any, typename: str, value: dict) -> Any:
    """A rosbags message object of ``typename`` from nested dicts (ROS 1 headers get a seq)."""
    kwargs = {}
    for name, (kind, spec) in store.fielddefs[typename][1]:
        if name == "seq" and name not in value:
            kwargs[name] = 0
        elif kind == Nodetype.NAME:
            kwargs[name] = _build(store, spec, value[name])
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            kwargs[name] = np.asarray(value[name], dtype=np.float64)
        else:
            kwargs[name] = value[name]
    return store.types[typename](**kwargs)


def _log_order(messages: dict[str, list]) -> list[tuple[int, int, str, dict]]:
    items = [(log, pub, topic, msg) for topic, ms in messages.items() for log, pub, msg in ms]
    return sorted(items, key=lambda x: x[0])


def write_generated_mcap(path: Path, messages: dict[str, list]) -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "wb") as fh:
        writer = RawMcapWriter(fh, chunk_size=32 << 10)  # small chunks: a log many batches long
        writer.start(profile="ros2", library="test")
        channels = {}
        for topic, typename in TYPES.items():
            text = store.generate_msgdef(typename, ros_version=2)[0]
            sid = writer.register_schema(typename, "ros2msg", text.encode())
            channels[topic] = writer.register_channel(topic, "cdr", sid)
        for seq, (log, pub, topic, msg) in enumerate(_log_order(messages)):
            data = store.serialize_cdr(_build(store, TYPES[topic], msg), TYPES[topic])
            writer.add_message(channels[topic], log, bytes(data), pub, seq)
        writer.finish()


def write_generated_bag(path: Path, messages: dict[str, list]) -> None:
    from rosbags.rosbag1 import Writer

    store = get_typestore(Stores.ROS1_NOETIC)
    writer = Writer(path)
    writer.chunk_threshold = 32 << 10  # small chunks: a log many batches long
    with writer:
        conns = {t: writer.add_connection(t, ty, typestore=store) for t, ty in TYPES.items()}
        for log, _pub, topic, msg in _log_order(messages):
            data = store.serialize_ros1(_build(store, TYPES[topic], msg), TYPES[topic])
            writer.write(conns[topic], log, data)


def write_generated_db3(path: Path, messages: dict[str, list]) -> None:
    from rosbags.rosbag2 import Writer

    store = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=9) as writer:
        conns = {t: writer.add_connection(t, ty, typestore=store) for t, ty in TYPES.items()}
        for log, _pub, topic, msg in _log_order(messages):
            data = store.serialize_cdr(_build(store, TYPES[topic], msg), TYPES[topic])
            writer.write(conns[topic], log, data)


def write_generated_csv(path: Path, messages: dict[str, list]) -> None:
    """imupipe's own CSV layout: one row per Imu/MagneticField/Temperature message, at its header
    stamp, empty cells for the other streams ("nan" where a value is NaN)."""
    rows = []
    for topic, columns in ((IMU, 6), (MAG, 3), (TEMP, 1)):
        start = {IMU: 0, MAG: 6, TEMP: 9}[topic]
        for _, _, msg in messages[topic]:
            cells = [""] * 10
            if topic == IMU:
                values = [*msg["angular_velocity"].values(), *msg["linear_acceleration"].values()]
            elif topic == MAG:
                values = list(msg["magnetic_field"].values())
            else:
                values = [msg["temperature"]]
            cells[start : start + columns] = [repr(v) for v in values]
            st = msg["header"]["stamp"]
            rows.append((st["sec"] * 1_000_000_000 + st["nanosec"], cells))
    rows.sort(key=lambda r: r[0])
    names = [f"{s}_{a}" for s in ("gyro", "accel", "mag") for a in "xyz"] + ["temperature"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_ns", *names])
        for t, cells in rows:
            w.writerow([t, *cells])


WRITERS = {
    "gen_mcap.mcap": write_generated_mcap,
    "gen_ros1.bag": write_generated_bag,
    "gen_ros2": write_generated_db3,
    "gen_csv.csv": write_generated_csv,
}
"""Generated inputs, by file name (distinct stems: convert names its outputs by stem)."""


# --- independent decoding ---------------------------------------------------------------------


def _xyz(v: Any, axes: str = "xyz") -> dict[str, str]:
    return {a: repr(float(getattr(v, a))) for a in axes}


def plain(msg: Any) -> dict[str, Any]:
    """A decoded sensor message (rosbags, ROS 1 or ROS 2) as nested dicts: floats as their repr
    (exact; NaN equal to NaN), float arrays as their bytes; a ROS 1 header's seq left out (ROS 2
    has none)."""
    stamp = msg.header.stamp
    out: dict[str, Any] = {
        "header": {
            "stamp": {"sec": int(stamp.sec), "nanosec": int(stamp.nanosec)},
            "frame_id": msg.header.frame_id,
        }
    }
    if hasattr(msg, "angular_velocity"):
        out["orientation"] = _xyz(msg.orientation, "xyzw")
        for name in ("orientation", "angular_velocity", "linear_acceleration"):
            if name != "orientation":
                out[name] = _xyz(getattr(msg, name))
            out[f"{name}_covariance"] = getattr(msg, f"{name}_covariance").astype("<f8").tobytes()
    elif hasattr(msg, "magnetic_field"):
        out["magnetic_field"] = _xyz(msg.magnetic_field)
        out["magnetic_field_covariance"] = msg.magnetic_field_covariance.astype("<f8").tobytes()
    else:
        out["temperature"] = repr(float(msg.temperature))
        out["variance"] = repr(float(msg.variance))
    return out


Message = tuple[int, int, dict | None, bytes]
"""(log time, publish time, plain message (sensor messages), ROS 2 CDR payload)."""

SENSOR_TYPES = {
    "sensor_msgs/msg/Imu",
    "sensor_msgs/msg/MagneticField",
    "sensor_msgs/msg/Temperature",
}
"""Decoded field by field; every other message is compared by its CDR bytes."""


def decode_mcap_file(path: Path) -> dict[str, list[Message]]:
    """An MCAP's messages: records by the ``mcap`` library, sensor payloads by rosbags' CDR
    deserializer (the standard ROS 2 Humble types)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    out: dict[str, list[Message]] = defaultdict(list)
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            msg = None
            if schema.name in SENSOR_TYPES:
                msg = plain(store.deserialize_cdr(message.data, schema.name))
            out[channel.topic].append(
                (message.log_time, message.publish_time, msg, bytes(message.data))
            )
    return dict(out)


def decode_bag(path: Path) -> dict[str, list[Message]]:
    """A ROS 1 or ROS 2 bag with rosbags (bags have no publish time: the log time). ROS 1
    payloads of other topics are converted to CDR by rosbags (``ros1_to_cdr``, the conversion
    ``rosbags-convert`` makes)."""
    from rosbags.highlevel import AnyReader

    store = get_typestore(Stores.ROS2_HUMBLE)
    out: dict[str, list[Message]] = defaultdict(list)
    with AnyReader([path], default_typestore=store) as reader:
        for conn, t, data in reader.messages():
            msg = None
            if conn.msgtype in SENSOR_TYPES:
                msg = plain(reader.deserialize(data, conn.msgtype))
            elif reader.is2:
                data = bytes(data)
            else:
                data = bytes(store.ros1_to_cdr(data, conn.msgtype))
            out[conn.topic].append((t, t, msg, data))
    return dict(out)


def decode_csv(path: Path) -> dict[str, list[Message]]:
    """The CSV's rows as the messages the corrected MCAP must hold (CSV defaults: topics
    /imu/data, /imu/mag, /imu/temperature, frame_id ``imu``, log time = t_ns, zero covariances,
    no orientation). A row's absent vector: NaN with covariance element 0 = -1."""
    zeros = np.zeros(9).tobytes()
    marked = np.array([-1.0] + [0.0] * 8).tobytes()  # element 0 = -1: "no data"
    out: dict[str, list[Message]] = defaultdict(list)
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            t = int(row["t_ns"])
            header = {"stamp": _stamp(t), "frame_id": "imu"}

            def vec(name: str, row: dict = row) -> tuple[dict, bool]:
                cells = [row[f"{name}_{a}"] for a in "xyz"]
                there = any(c != "" for c in cells)
                return {
                    a: repr(float(c) if c else np.nan) for a, c in zip("xyz", cells, strict=True)
                }, there

            gyro, has_gyro = vec("gyro")
            accel, has_accel = vec("accel")
            if has_gyro or has_accel:
                msg = {
                    "header": header,
                    "orientation": {
                        a: repr(v) for a, v in zip("xyzw", [0.0, 0.0, 0.0, 1.0], strict=True)
                    },
                    "orientation_covariance": marked,
                    "angular_velocity": gyro,
                    "angular_velocity_covariance": zeros if has_gyro else marked,
                    "linear_acceleration": accel,
                    "linear_acceleration_covariance": zeros if has_accel else marked,
                }
                out["/imu/data"].append((t, t, msg, b""))
            mag, has_mag = vec("mag")
            if has_mag:
                msg = {"header": header, "magnetic_field": mag, "magnetic_field_covariance": zeros}
                out["/imu/mag"].append((t, t, msg, b""))
            if row["temperature"] != "":
                msg = {
                    "header": header,
                    "temperature": repr(float(row["temperature"])),
                    "variance": repr(0.0),
                }
                out["/imu/temperature"].append((t, t, msg, b""))
    return dict(out)


_DECODED: dict[Path, dict[str, list[Message]]] = {}


def decode_input(path: Path) -> dict[str, list[Message]]:
    """An input log's messages, decoded once per test session."""
    if path not in _DECODED:
        if path.suffix == ".mcap":
            _DECODED[path] = decode_mcap_file(path)
        elif path.suffix == ".csv":
            _DECODED[path] = decode_csv(path)
        else:
            _DECODED[path] = decode_bag(path)
    return _DECODED[path]


# --- the comparison ---------------------------------------------------------------------------


def _vector(msg: dict, field: str) -> np.ndarray:
    return np.array([float(msg[field][a]) for a in "xyz"])


def _key(message: Message, moved: set[str]) -> tuple:
    log, pub, msg, data = message
    if msg is None:
        return (log, pub, data)
    return (log, pub, repr({k: v for k, v in msg.items() if k not in moved}))


def assert_same_messages(
    given: dict[str, list[Message]],
    written: dict[str, list[Message]],
    chain: list[LinearStep],
    types: dict[str, str],
    topic_map: dict[str, str] | None = None,
    bytes_equal: bool = False,
) -> dict[str, int]:
    """Every message of ``given`` is in ``written`` once, every field equal, except the vector
    fields a step of ``chain`` corrects, which must equal the step applied to the input's values
    (computed here with numpy). ``types``: topic -> message type of the input; ``topic_map``:
    input topic -> output topic (CSV). Returns messages per output topic."""
    topic_map = topic_map or {}
    steps = {step.sensor: step for step in chain}
    out_topics = {topic_map.get(t, t) for t in given}
    assert set(written) == out_topics, (sorted(written), sorted(out_topics))
    counts = {}
    for topic, messages in given.items():
        got = written[topic_map.get(topic, topic)]
        assert len(got) == len(messages), (topic, len(messages), len(got))
        fields = {f: s for f, s in CORRECTED.get(types.get(topic, ""), {}).items() if s in steps}
        key_in = [_key(m, set(fields)) for m in messages]  # each key once (repr is the cost)
        key_out = [_key(m, set(fields)) for m in got]
        a = [messages[i] for i in sorted(range(len(messages)), key=key_in.__getitem__)]
        b = [got[i] for i in sorted(range(len(got)), key=key_out.__getitem__)]
        key_in.sort()
        key_out.sort()
        for k_in, k_out, m_in, m_out in zip(key_in, key_out, a, b, strict=True):
            assert k_in == k_out, (topic, m_in, m_out)
            if bytes_equal and not fields:
                assert m_in[3] == m_out[3], topic
            assert (m_in[2] is None) == (m_out[2] is None), topic
        for field, name in fields.items():  # the step on every input row at once (row-wise math)
            raw = np.array([_vector(m[2], field) for m in a]).reshape(-1, 3)
            out = np.array([_vector(m[2], field) for m in b]).reshape(-1, 3)
            want = steps[name].apply_values(raw)
            np.testing.assert_allclose(
                out, want, rtol=1e-12, atol=1e-300, err_msg=f"{topic} {field}"
            )
        counts[topic_map.get(topic, topic)] = len(got)
    return counts


def _csv_types() -> dict[str, str]:
    return {
        "/imu/data": "sensor_msgs/msg/Imu",
        "/imu/mag": "sensor_msgs/msg/MagneticField",
        "/imu/temperature": "sensor_msgs/msg/Temperature",
    }


def input_types(name: str, given: dict[str, list]) -> dict[str, str]:
    if name.endswith(".csv"):
        return _csv_types()
    if name.startswith("gen"):
        return TYPES
    return {t: REAL_TYPES.get(t, "") for t in given}


REAL_TYPES = {
    "/ardrone/imu": "sensor_msgs/msg/Imu",
    "/ardrone/mag": "sensor_msgs/msg/MagneticField",
    "/imu/data_raw": "sensor_msgs/msg/Imu",
    "/imu/data": "sensor_msgs/msg/Imu",
    "/imu/mag": "sensor_msgs/msg/MagneticField",
}


# --- fixtures: the generated logs, the CLI runs -------------------------------------------------


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    d = tmp_path_factory.mktemp("gen")
    messages = generated_messages()
    for name, write in WRITERS.items():
        write(d / name, messages)
    return d


def _calibration(path: Path, chain: list[LinearStep]) -> Path:
    path.write_text(json.dumps({"imupipe_version": "test", "chain": [s.to_json() for s in chain]}))
    return path


def _run_config(d: Path, inputs: dict[str, tuple[Path, str]], out: str) -> Path:
    """A config that reads every input (name -> (path, time)) and writes it corrected. Its one
    stage, gyro_bias, fits on a still CSV written here; its step is the chain to check."""
    rng = np.random.default_rng(5)
    still = rng.normal(0, 0.002, (4000, 6)) + [0.01, -0.02, 0.005, 0.0, 0.0, 9.81]
    cols = [f"{s}_{a}" for s in ("gyro", "accel") for a in "xyz"]
    _csv(d / "still.csv", 4000, cols, lambda i, c: still[i, cols.index(c)])
    text = '[inputs.still]\npath = "still.csv"\n'
    for name, (path, time) in inputs.items():
        text += f'[inputs.{name}]\npath = "{path}"\ntime = "{time}"\n'
    text += '[[stages]]\ntype = "gyro_bias"\ninput = "still"\n'
    text += f'[output]\ndir = "{out}"\nrerun = false\napply_to = {json.dumps(list(inputs))}\n'
    cfg = d / f"{out}.toml"
    cfg.write_text(text)
    return cfg


def _chain_of(calibration: Path) -> list[LinearStep]:
    doc = json.loads(calibration.read_text())
    return [LinearStep.from_json(e) for e in doc["chain"]]


TIMES = ["header", "log"]


@pytest.fixture(scope="module")
def run_outputs(generated, tmp_path_factory):
    """``imupipe run`` on every generated log, with time = header and log, in one config."""
    d = tmp_path_factory.mktemp("run")
    inputs = {
        f"{Path(name).stem}_{time}": (generated / name, time) for name in WRITERS for time in TIMES
    }
    proc = run_cli("run", _run_config(d, inputs, "out"), "--quiet", cwd=d)
    assert proc.returncode == 0, proc.stderr
    return d / "out", inputs


GENERATED = list(WRITERS)
"""The generated CSV has rows whose whole gyro (or magnetic field, or temperature) is 'nan'."""


@pytest.mark.parametrize("time", TIMES)
@pytest.mark.parametrize("name", GENERATED)
def test_run_keeps_every_field_of_every_message(generated, run_outputs, name, time):
    out, inputs = run_outputs
    (key,) = [k for k, (p, t) in inputs.items() if p.name == name and t == time]
    chain = _chain_of(out / "calibration.json")
    assert [s.sensor for s in chain] == ["gyro"] and np.any(chain[0].offset != 0)
    given = decode_input(generated / name)
    written = decode_mcap_file(out / f"{key}.mcap")
    topic_map = {"/imu/data": "/imu/data"} if name.endswith(".csv") else None
    counts = assert_same_messages(
        given,
        written,
        chain,
        input_types(name, given),
        topic_map,
        bytes_equal=name.endswith(".mcap") or name.endswith("ros2"),
    )
    assert sum(counts.values()) == sum(len(v) for v in given.values())


@pytest.fixture(scope="module")
def convert_outputs(generated, tmp_path_factory):
    """``imupipe convert`` of every generated log with a three-sensor linear calibration, once
    per time source, streamed in batches of 150 rows (``imupipe run`` above reads each of these
    logs as one batch)."""
    d = tmp_path_factory.mktemp("convert")
    cal = _calibration(d / "cal.json", CHAIN)
    outs = {}
    for time in TIMES:
        (d / f"{time}.toml").write_text(f'time = "{time}"\n')
        logs = [generated / name for name in WRITERS]
        proc = run_cli(
            "convert", "--calibration", cal, "--out", d / time, "--config", d / f"{time}.toml",
            "-j", "1", "--batch-rows", "150", "--quiet", *logs,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        outs[time] = d / time
    return outs


@pytest.mark.parametrize("time", TIMES)
@pytest.mark.parametrize("name", GENERATED)
def test_convert_keeps_every_field_of_every_message(generated, convert_outputs, name, time):
    given = decode_input(generated / name)
    written = decode_mcap_file(convert_outputs[time] / f"{Path(name).stem}.mcap")
    assert_same_messages(
        given,
        written,
        CHAIN,
        input_types(name, given),
        bytes_equal=name.endswith(".mcap") or name.endswith("ros2"),
    )


# --- the real bags ----------------------------------------------------------------------------

REAL = [
    "rl_test1.bag",
    "madgwick_phidgets_imu_upside_down.bag",
    "rl_test2.bag",
    "madgwick_ardrone_imu.bag",
    "madgwick_sparkfun_razor.bag",
]
REAL_CI = {
    "rl_test1.bag": ("run", "convert"),
    "madgwick_phidgets_imu_upside_down.bag": ("convert",),
}
"""In CI, with ``time = "log"``: the Husky log (carried-over Odometry and NavSatFix; header
stamps up to 36 ms from the log times) through both commands, and the Phidgets log (6990 of
13964 MagneticField messages hold NaN) through ``convert``. Every bag, both time sources and both
commands: the slow test."""


def _real_outputs(d: Path, runs: dict[str, tuple[str, ...]], times: list[str]) -> tuple[Path, Path]:
    """The real bags through ``run`` (no stage: the identity chain) and ``convert`` (the
    three-sensor calibration); ``runs``: bag -> the commands."""
    logs = SHARED / "logs"
    if not all((logs / name).exists() for name in runs):
        pytest.skip(f"shared data not present: {logs} (GPL data is not copied into the repo)")
    text, names = "", []
    for name in (n for n, commands in runs.items() if "run" in commands):
        for time in times:
            names.append(f"{Path(name).stem}_{time}")
            text += f'[inputs.{names[-1]}]\npath = "{logs / name}"\ntime = "{time}"\n'
    if text:  # no stage: apply_to must name the inputs (its default is the inputs a chain corrects)
        text += f'[output]\ndir = "run"\nrerun = false\napply_to = {json.dumps(names)}\n'
        (d / "run.toml").write_text(text)
        proc = run_cli("run", d / "run.toml", "--quiet", cwd=d)
        assert proc.returncode == 0, proc.stderr
    cal = _calibration(d / "cal.json", CHAIN)
    converted = [logs / n for n, commands in runs.items() if "convert" in commands]
    for time in times:
        (d / f"{time}.toml").write_text(f'time = "{time}"\n')
        proc = run_cli(
            "convert", "--calibration", cal, "--out", d / time, "--config", d / f"{time}.toml",
            "-j", "1", "--quiet", *converted,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
    return logs, d


@pytest.fixture(scope="module")
def real_outputs(tmp_path_factory):
    return _real_outputs(tmp_path_factory.mktemp("real"), REAL_CI, ["log"])


@pytest.fixture(scope="module")
def real_outputs_all(tmp_path_factory):
    every = dict.fromkeys(REAL, ("run", "convert"))
    return _real_outputs(tmp_path_factory.mktemp("real_all"), every, TIMES)


def _check_real(logs: Path, d: Path, name: str, time: str, commands: tuple[str, ...]) -> None:
    given = decode_input(logs / name)
    types = input_types(name, given)
    if "run" in commands:
        by_run = decode_mcap_file(d / "run" / f"{Path(name).stem}_{time}.mcap")
        assert_same_messages(given, by_run, [], types)
    if "convert" in commands:
        by_convert = decode_mcap_file(d / time / f"{Path(name).stem}.mcap")
        assert_same_messages(given, by_convert, CHAIN, types)


@pytest.mark.parametrize("name", list(REAL_CI))
def test_real_bags_keep_every_field(real_outputs, name):
    _check_real(*real_outputs, name, "log", REAL_CI[name])


@pytest.mark.slow
@pytest.mark.parametrize("time", TIMES)
@pytest.mark.parametrize("name", REAL)
def test_every_real_bag_keeps_every_field(real_outputs_all, name, time):
    _check_real(*real_outputs_all, name, time, ("run", "convert"))


def test_real_time_log_keeps_header_stamps(real_outputs):
    """Issue 18: with ``time = "log"`` every Imu header stamp of rl_test1 was replaced by its log
    time (11,865 of 11,865, up to 36 ms apart). Now the header stamps are the input's."""
    logs, d = real_outputs
    given = decode_input(logs / "rl_test1.bag")["/imu/data"]
    written = decode_mcap_file(d / "run" / "rl_test1_log.mcap")["/imu/data"]
    assert len(written) == len(given) == 11865

    def stamps(messages: list[Message]) -> np.ndarray:
        s = [(m[2]["header"]["stamp"]["sec"], m[2]["header"]["stamp"]["nanosec"]) for m in messages]
        return np.array([a * 1_000_000_000 + b for a, b in s])

    order_in = np.argsort([m[0] for m in given], kind="stable")
    order_out = np.argsort([m[0] for m in written], kind="stable")
    np.testing.assert_array_equal(stamps(written)[order_out], stamps(given)[order_in])
    log = np.sort([m[0] for m in given])
    assert np.abs(stamps(given)[order_in] - log).max() > 30_000_000  # the case the issue saw


def test_real_nan_magnetometer_travels_as_nan(real_outputs):
    """6990 of the 13964 MagneticField messages of the Phidgets bag hold NaN: every one is in
    the corrected MCAP, NaN where the input had NaN."""
    logs, d = real_outputs
    written = decode_mcap_file(d / "log" / "madgwick_phidgets_imu_upside_down.mcap")
    values = np.array([_vector(m[2], "magnetic_field") for m in written["/imu/mag"]])
    assert len(values) == 13964
    assert int(np.isnan(values).any(axis=1).sum()) == 6990


# --- streamed = whole, byte for byte ----------------------------------------------------------


@pytest.mark.parametrize("time", TIMES)
@pytest.mark.parametrize("name", ["gen_mcap.mcap", "gen_ros1.bag", "gen_ros2"])
def test_streamed_output_equals_whole_table_output(generated, tmp_path, monkeypatch, name, time):
    """``imupipe run``'s streamed write (batches of 200 rows, slices of 300) gives the same file,
    byte for byte, as correcting the whole table and writing it, on a log 5 to 8 batches long."""
    from imupipe.readers.ros2 import reader as ros2_reader

    monkeypatch.setattr(ros2_reader, "BLOCK_ROWS", 150)  # sqlite rows fetched at once
    spec = InputSpec(path=generated / name, time=time)
    assert sum(1 for _ in iter_input(spec, batch_rows=200)) >= 5
    whole = tmp_path / "whole.mcap"
    table, _ = read_input(spec)
    write_mcap(whole, apply_chain(table, CHAIN), carry_over=carry_over(spec), slice_rows=300)
    streamed = tmp_path / "streamed.mcap"
    write_corrected(streamed, spec, CHAIN, None, batch_rows=200, slice_rows=300)
    assert streamed.read_bytes() == whole.read_bytes()


def test_writer_output_does_not_depend_on_batches(generated, tmp_path):
    """One whole table, or the same rows in uneven batches (carried messages given before each
    batch), give the same bytes."""
    spec = InputSpec(path=generated / "gen_mcap.mcap", time="log")
    table, _ = read_input(spec)
    raw = sorted(carry_over(spec), key=lambda m: m.log_time)
    write_mcap(tmp_path / "a.mcap", table, carry_over=raw, slice_rows=400)
    with McapTableWriter(tmp_path / "b.mcap", slice_rows=400) as writer:
        start, done = 0, 0
        for size in [1, 399, 17, 900, 3, 100]:
            part = table.slice(start, size)
            start += size
            last = part.column("log_time_ns").to_numpy().max() if part.num_rows else 0
            upto = done
            while upto < len(raw) and raw[upto].log_time < last:
                upto += 1
            writer.write_raw(raw[done:upto])
            done = upto
            writer.write_table(part)
        writer.write_table(table.slice(start))
        writer.write_raw(raw[done:])
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()


# --- NaN and absent sensors from CSV ------------------------------------------------------------

CFG = '[inputs.a]\npath = "{csv}"\n[output]\ndir = "{out}"\nrerun = false\napply_to = ["a"]\n'


def _cov0(message: Message, vector: str) -> float:
    """Element 0 of a vector's covariance (-1: "no data")."""
    return float(np.frombuffer(message[2][f"{vector}_covariance"])[0])


def _csv(path: Path, n: int, columns: list[str], cell) -> Path:
    with open(path, "w") as fh:
        fh.write(",".join(["t_ns", *columns]) + "\n")
        for i in range(n):
            cells = [cell(i, c) for c in columns]
            cells = [c if isinstance(c, str) else repr(float(c)) for c in cells]
            fh.write(",".join([str(T0 + i * 2_500_000), *cells]) + "\n")
    return path


def test_csv_nan_cell_is_a_message_with_nan(tmp_path):
    """Issue 13: one NaN accelerometer cell in 6000 rows lost its Imu message (5999 out)."""
    rng = np.random.default_rng(1)
    values = rng.normal(size=(6000, 6))
    cols = [f"{s}_{a}" for s in ("gyro", "accel") for a in "xyz"]
    _csv(
        tmp_path / "a.csv",
        6000,
        cols,
        lambda i, c: "nan" if (i, c) == (100, "accel_x") else values[i, cols.index(c)],
    )
    (tmp_path / "cfg.toml").write_text(CFG.format(csv="a.csv", out="out"))
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    written = decode_mcap_file(tmp_path / "out" / "a.mcap")
    msgs = sorted(written["/imu/data"], key=lambda m: m[0])
    assert len(msgs) == 6000
    accel = np.array([_vector(m[2], "linear_acceleration") for m in msgs])
    gyro = np.array([_vector(m[2], "angular_velocity") for m in msgs])
    assert np.isnan(accel[100, 0]) and np.isnan(accel).sum() == 1
    np.testing.assert_array_equal(accel[:, 1:], values[:, 4:])
    np.testing.assert_array_equal(gyro, values[:, :3])
    assert all(_cov0(m, "linear_acceleration") == 0.0 for m in msgs)


@pytest.mark.parametrize("present", ["accel", "gyro"])
def test_csv_without_a_sensor_invents_nothing(tmp_path, present):
    """Issue 13: a CSV with no gyro columns got 6000 Imu messages with zero gyro invented. The
    absent vector is NaN with covariance element 0 = -1 (sensor_msgs/Imu: "no data"), and reads
    back as absent."""
    rng = np.random.default_rng(2)
    values = rng.normal(size=(6000, 3))
    cols = [f"{present}_{a}" for a in "xyz"]
    _csv(tmp_path / "a.csv", 6000, cols, lambda i, c: values[i, cols.index(c)])
    (tmp_path / "cfg.toml").write_text(CFG.format(csv="a.csv", out="out"))
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "zeros" not in proc.stderr
    out = tmp_path / "out" / "a.mcap"
    msgs = sorted(decode_mcap_file(out)["/imu/data"], key=lambda m: m[0])
    assert len(msgs) == 6000
    field = {"gyro": "angular_velocity", "accel": "linear_acceleration"}
    missing = "gyro" if present == "accel" else "accel"
    np.testing.assert_array_equal(np.array([_vector(m[2], field[present]) for m in msgs]), values)
    assert np.isnan(np.array([_vector(m[2], field[missing]) for m in msgs])).all()
    assert {_cov0(m, field[missing]) for m in msgs} == {-1.0}
    assert {_cov0(m, field[present]) for m in msgs} == {0.0}
    # read back (and converted again): still absent, never NaN samples or zeros
    table, _ = read_input(InputSpec(path=out))
    assert has_sensor(table, present) and not has_sensor(table, missing)
    np.testing.assert_array_equal(sensor(table, present).values, values)


def test_csv_writer_keeps_nan_and_leaves_absent_sensors_out(tmp_path):
    from imupipe.pipeline.writers.csv import write_csv
    from imupipe.readers.table import make_table

    accel = np.array([[1.0, np.nan, 3.0], [4.0, 5.0, 6.0]])
    table = make_table(np.array([1, 2]), accel=accel)
    write_csv(tmp_path / "a.csv", table)
    lines = (tmp_path / "a.csv").read_text().splitlines()
    assert (
        lines[0] == '"t_ns","accel_x","accel_y","accel_z"'
        or lines[0] == "t_ns,accel_x,accel_y,accel_z"
    )
    assert lines[1] == "1,1,nan,3"


# --- a bounded writer ---------------------------------------------------------------------------


def test_writer_memory_is_bounded_by_a_slice(tmp_path):
    """``write_table`` of a 200,000-row table encodes 10,000 rows at a time: the numpy memory it
    allocates stays near a slice's (tracemalloc sees numpy's allocations). A slice's records are
    encoded a chunk at a time (issue 39): even the whole table as one slice holds only its
    field arrays (18 MB; 92 MB when the slice's records were all encoded at once)."""
    import tracemalloc

    n = 200_000
    rng = np.random.default_rng(0)
    from imupipe.readers.table import make_table

    table = make_table(
        T0 + np.arange(n, dtype=np.int64) * 2_500_000,
        gyro=rng.normal(size=(n, 3)),
        accel=rng.normal(size=(n, 3)),
        metadata={"topics": {"imu": IMU}},
    )
    peaks = {}
    for rows in (10_000, n):
        tracemalloc.start()
        with McapTableWriter(tmp_path / f"{rows}.mcap", slice_rows=rows) as writer:
            writer.write_table(table)
        peaks[rows] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert (tmp_path / "10000.mcap").stat().st_size > 0
    assert peaks[10_000] < peaks[n] / 4, peaks
    assert peaks[10_000] < 30e6, peaks
    assert peaks[n] < 40e6, peaks


@pytest.mark.parametrize("name", ["log.mcap", "log.bag", "log.db3", "log.csv"])
def test_every_writer_round_trips_nan_and_absent_sensors(tmp_path, name):
    """``imupipe simulate``'s writers (MCAP, ROS 1 bag, ROS 2 bag, CSV) keep a NaN value as NaN
    and an absent gyro absent: read back, the table holds the same samples."""
    from imupipe.pipeline.simulate import write_log
    from imupipe.readers.table import make_table

    rng = np.random.default_rng(3)
    accel = rng.normal(size=(50, 3))
    accel[7, 0] = np.nan  # one axis: the CSV's other cells keep the row a sample
    mag = rng.normal(0, 3e-5, (50, 3))
    mag[9, 1] = np.nan  # (a row of three 'nan' CSV cells: see NAN_CELLS)
    t = T0 + np.arange(50, dtype=np.int64) * 10_000_000
    table = make_table(t, accel=accel, mag=mag)
    write_log(tmp_path / name, table)
    back, _ = read_input(InputSpec(path=tmp_path / name))
    assert not has_sensor(back, "gyro") and has_sensor(back, "accel")
    np.testing.assert_array_equal(sensor(back, "accel").values, accel)
    np.testing.assert_array_equal(sensor(back, "accel").t_ns, t)
    np.testing.assert_array_equal(sensor(back, "mag").values, mag)
    np.testing.assert_array_equal(sensor(back, "mag").t_ns, t)
