"""Issue 37: a field mapping's read against the sensor_msgs/Imu read, per message, same run.

The same IMU samples (N messages, 200 Hz) written to MCAP files (zstd chunks, mcap's writer) as:

- ``sensor_msgs/msg/Imu`` read by ``imu_topic`` (the peer: imupipe's Imu path);
- ``px4_msgs/msg/SensorCombined`` (ROS 2 CDR) read by ``[fields]`` (gyro_rad, accelerometer_m_s2,
  timestamp in us);
- ``sensor_msgs/msg/Imu`` read by ``[fields]`` (angular_velocity, linear_acceleration, header);
- JSON (jsonschema) and protobuf channels read by ``[fields]``.

Prints the wall-clock and CPU seconds per read (min and median of ``--repeat`` runs,
interleaved) and the ratio of the mins to the Imu path's (target: at most 2x). On a shared
machine the CPU time (the process's, all threads) is the steadier of the two. ``--fallback``
adds the JSON and protobuf reads with their numpy decoding (``imupipe.readers.json_numbers``
without ``_jsonscan``, ``imupipe.readers.message_fields`` without ``_protoscan``) to the same
interleaved runs. Each case's ratio to the Imu read of the same repeat is printed too (min and
median over the repeats).

    PYTHONPATH=.shim python benchmarks/bench_mapped_fields.py [--messages 200000] [--repeat 3]
        [--fallback]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from imupipe.readers import json_numbers, message_fields
from imupipe.readers.cdr import encode
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import FieldMapping, InputSpec

SENSOR_COMBINED = """uint64 timestamp
float32[3] gyro_rad
uint32 gyro_integral_dt
int32 accelerometer_timestamp_relative
float32[3] accelerometer_m_s2
uint32 accelerometer_integral_dt
uint8 accelerometer_clipping
uint8 gyro_clipping
uint8 accel_calibration_count
uint8 gyro_calibration_count
"""


def _writer(path: Path):  # noqa: ANN202
    from mcap.writer import CompressionType, Writer

    fh = open(path, "wb")  # noqa: SIM115 - closed by finish()
    w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=1 << 20)
    w.start()
    return fh, w


def write_all(folder: Path, n: int) -> dict[str, Path]:
    from rosbags.typesys import Stores, get_typestore

    rng = np.random.default_rng(0)
    t = 10**18 + np.arange(n, dtype=np.int64) * 5_000_000
    gyro = rng.normal(0, 0.01, (n, 3)).astype(np.float32)
    accel = (rng.normal(0, 0.05, (n, 3)) + [0, 0, 9.81]).astype(np.float32)
    paths = {}

    imu = encode(
        "sensor_msgs/msg/Imu",
        t,
        b"imu_link",
        {"angular_velocity": gyro.astype(float), "linear_acceleration": accel.astype(float)},
    )
    schema = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef("sensor_msgs/msg/Imu")[0]
    paths["imu"] = folder / "imu.mcap"
    fh, w = _writer(paths["imu"])
    sid = w.register_schema("sensor_msgs/msg/Imu", "ros2msg", schema.encode())
    cid = w.register_channel("/imu/data", "cdr", sid)
    for i in range(n):
        w.add_message(cid, log_time=int(t[i]), data=imu[i].tobytes(), publish_time=int(t[i]))
    w.finish()
    fh.close()

    # px4_msgs/msg/SensorCombined, CDR: encapsulation, then (from the end of it) uint64 @0,
    # float32[3] @8, uint32 @20, int32 @24, float32[3] @28, uint32 @40, 4 x uint8 @44: 52 bytes
    sc = np.zeros((n, 52), np.uint8)
    sc[:, 1] = 1
    sc[:, 4:12] = (t // 1000).astype("<u8").view(np.uint8).reshape(n, 8)
    sc[:, 12:24] = gyro.astype("<f4").view(np.uint8).reshape(n, 12)
    sc[:, 32:44] = accel.astype("<f4").view(np.uint8).reshape(n, 12)
    paths["px4"] = folder / "px4.mcap"
    fh, w = _writer(paths["px4"])
    sid = w.register_schema("px4_msgs/msg/SensorCombined", "ros2msg", SENSOR_COMBINED.encode())
    cid = w.register_channel("/fmu/out/sensor_combined", "cdr", sid)
    for i in range(n):
        w.add_message(cid, log_time=int(t[i]), data=sc[i].tobytes(), publish_time=int(t[i]))
    w.finish()
    fh.close()

    paths["json"] = folder / "json.mcap"
    fh, w = _writer(paths["json"])
    js = {
        "type": "object",
        "properties": {
            "t": {"type": "integer"},
            "g": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
            "a": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        },
    }
    sid = w.register_schema("imu_json", "jsonschema", json.dumps(js).encode())
    cid = w.register_channel("/imu_json", "json", sid)
    g64, a64 = gyro.astype(float).tolist(), accel.astype(float).tolist()
    for i in range(n):
        doc = json.dumps({"t": int(t[i]), "g": g64[i], "a": a64[i]}).encode()
        w.add_message(cid, log_time=int(t[i]), data=doc, publish_time=int(t[i]))
    w.finish()
    fh.close()

    paths["protobuf"] = folder / "pb.mcap"
    _write_protobuf(paths["protobuf"], t, gyro, accel)
    return paths


def _write_protobuf(path: Path, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
    from google.protobuf import (
        descriptor_pb2,
        descriptor_pool,
        message_factory,
        timestamp_pb2,  # noqa: F401 - registers timestamp.proto
    )
    from mcap_protobuf.writer import Writer

    fd = descriptor_pb2.FileDescriptorProto(
        name="bench/imu.proto",
        package="bench",
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
    imu.field.add(name="gyro", number=2, type=11, label=1, type_name=".bench.Vector3")
    imu.field.add(name="accel", number=3, type=11, label=1, type_name=".bench.Vector3")
    pool = descriptor_pool.Default()
    pool.Add(fd)
    Imu = message_factory.GetMessageClass(pool.FindMessageTypeByName("bench.Imu"))
    g64, a64 = gyro.astype(float).tolist(), accel.astype(float).tolist()
    with open(path, "wb") as fh, Writer(fh) as w:
        for i, ti in enumerate(t.tolist()):
            m = Imu()
            m.timestamp.seconds, m.timestamp.nanos = divmod(ti, 10**9)
            m.gyro.x, m.gyro.y, m.gyro.z = g64[i]
            m.accel.x, m.accel.y, m.accel.z = a64[i]
            w.write_message("/imu_pb", m, log_time=ti, publish_time=ti)


CASES = {
    "Imu, imu_topic (peer)": ("imu", None),
    "Imu, [fields]": (
        "imu",
        FieldMapping(gyro="/imu/data.angular_velocity", accel="/imu/data.linear_acceleration"),
    ),
    "px4 SensorCombined, [fields]": (
        "px4",
        FieldMapping(
            gyro="/fmu/out/sensor_combined.gyro_rad",
            accel="/fmu/out/sensor_combined.accelerometer_m_s2",
            time="/fmu/out/sensor_combined.timestamp",
            time_unit="us",
        ),
    ),
    "JSON, [fields]": (
        "json",
        FieldMapping(gyro="/imu_json.g", accel="/imu_json.a", time="/imu_json.t"),
    ),
    "protobuf, [fields]": (
        "protobuf",
        FieldMapping(gyro="/imu_pb.gyro", accel="/imu_pb.accel", time="/imu_pb.timestamp"),
    ),
}


FALLBACK = {
    "JSON, [fields], numpy decoding": ("JSON, [fields]", json_numbers, "_module"),
    "protobuf, [fields], numpy decoding": ("protobuf, [fields]", message_fields, "_protoscan"),
}
"""Case -> (the case it repeats, the module and the function that finds its compiled pass)."""


@contextlib.contextmanager
def _numpy_decoding(name: str) -> Iterator[None]:
    """Case ``name`` without its compiled pass (a ``FALLBACK`` case)."""
    if name not in FALLBACK:
        yield
        return
    _, module, attr = FALLBACK[name]
    found = getattr(module, attr)
    setattr(module, attr, lambda: None)
    try:
        yield
    finally:
        setattr(module, attr, found)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--messages", type=int, default=200_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--fallback", action="store_true", help="also the numpy JSON and protobuf decoding"
    )
    args = ap.parse_args()
    cases = dict(CASES)
    if args.fallback:
        cases.update({name: CASES[case] for name, (case, _, _) in FALLBACK.items()})
    print(f"JSON compiled pass: {'built' if json_numbers.compiled() else 'not used'}")
    print(
        f"protobuf compiled pass: {'built' if message_fields.protoscan_compiled() else 'not used'}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_all(Path(tmp), args.messages)
        wall: dict[str, list[float]] = {name: [] for name in cases}
        cpu: dict[str, list[float]] = {name: [] for name in cases}
        for _ in range(args.repeat):  # interleaved, so that machine load hits every case
            for name, (kind, mapping) in cases.items():
                spec = InputSpec(path=paths[kind], fields=mapping)
                t0, c0 = time.perf_counter(), time.process_time()
                with _numpy_decoding(name):
                    table, _ = read_input(spec)
                wall[name].append(time.perf_counter() - t0)
                cpu[name].append(time.process_time() - c0)
                assert table.num_rows == args.messages
        peer = "Imu, imu_topic (peer)"
        print(f"{args.messages} messages per file, {args.repeat} runs each (interleaved)")
        print(
            f"{'':36s} {'wall min':>9s} {'median':>7s} {'ratio':>6s}   {'CPU min':>8s} {'median':>7s} {'ratio':>6s}"
        )
        for name in cases:
            w, c = np.array(wall[name]), np.array(cpu[name])
            rw = w.min() / min(wall[peer])
            rc = c.min() / min(cpu[peer])
            print(
                f"{name:36s} {w.min():8.3f}s {np.median(w):6.3f}s {rw:5.2f}x   "
                f"{c.min():7.3f}s {np.median(c):6.3f}s {rc:5.2f}x"
            )
        print(
            "ratio: min over runs against the Imu path's min (wall clock; CPU time of the process)"
        )
        print(f"\nper repeat, against the Imu read of the same repeat ({args.repeat} repeats)")
        print(f"{'':36s} {'wall min':>9s} {'median':>7s}   {'CPU min':>8s} {'median':>7s}")
        for name in cases:
            rw = np.array(wall[name]) / np.array(wall[peer])
            rc = np.array(cpu[name]) / np.array(cpu[peer])
            print(
                f"{name:36s} {rw.min():8.2f}x {np.median(rw):6.2f}x   "
                f"{rc.min():7.2f}x {np.median(rc):6.2f}x"
            )


if __name__ == "__main__":
    main()
