"""Issue 3: the MCAP reader's fallbacks give the same table as the indexed fast path.

Files are written with the ``mcap`` library's own writer in the layouts the fast path does not
take: no message index (foxglove/mcap#1735), no summary at all, no chunks, lz4 chunks, ROS 1
encoded messages (with a carried-over ROS 1 channel), big-endian CDR.
"""

from __future__ import annotations

import pyarrow as pa
import pytest
from mcap.writer import CompressionType, IndexType, Writer
from rosbags.typesys import Stores, get_typestore
from test_readers import multi_stream_table

from imupipe.pipeline.writers.mcap import McapTableWriter, encode_stream, msgdef
from imupipe.readers.dispatch import carry_over, read_input
from imupipe.readers.spec import InputSpec

TOPICS = {"imu": "/imu/data", "mag": "/imu/mag", "temperature": "/imu/temp"}
TYPES = {
    "imu": "sensor_msgs/msg/Imu",
    "mag": "sensor_msgs/msg/MagneticField",
    "temperature": "sensor_msgs/msg/Temperature",
}


def _messages(table: pa.Table, encoding: str) -> list[tuple[int, str, bytes]]:
    """(log time, stream, payload) of every message, in log order, encoded with numpy."""
    log = table.column("log_time_ns").to_numpy()
    out = []
    for stream in TYPES:
        rows, groups = encode_stream(table, stream, encoding)
        for sel, payloads in groups:
            out += [
                (int(log[rows[i]]), stream, p.tobytes()) for i, p in zip(sel, payloads, strict=True)
            ]
    return sorted(out, key=lambda m: m[0])


def _write(path, table, encoding="cdr", payload=None, extra_ros1=False, **writer_args) -> None:
    ros1 = get_typestore(Stores.ROS1_NOETIC)
    with open(path, "wb") as fh:
        w = Writer(fh, **writer_args)
        w.start(profile="ros1" if encoding == "ros1" else "ros2")
        channels = {}
        for stream, typ in TYPES.items():
            if encoding == "ros1":
                sid = w.register_schema(
                    typ.replace("/msg/", "/"), "ros1msg", ros1.generate_msgdef(typ)[0].encode()
                )
            else:
                sid = w.register_schema(typ, "ros2msg", msgdef(typ).encode())
            channels[stream] = w.register_channel(TOPICS[stream], encoding, sid)
        if extra_ros1:
            sid = w.register_schema("std_msgs/String", "ros1msg", b"string data\n")
            text = w.register_channel("/chatter", "ros1", sid)
            for i in range(5):
                s = f"hello {i}".encode()
                w.add_message(
                    text, log_time=i, publish_time=i, data=len(s).to_bytes(4, "little") + s
                )
        for t, stream, data in _messages(table, encoding):
            w.add_message(
                channels[stream],
                log_time=t,
                publish_time=t,
                data=payload(stream, data) if payload else data,
            )
        w.finish()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    table = multi_stream_table(seed=1)
    path = tmp_path_factory.mktemp("ref") / "ref.mcap"
    with McapTableWriter(path) as w:
        w.write_table(table)
    got, _ = read_input(InputSpec(path=path))
    return table, got, path.parent


CASES = {
    "no_message_index": dict(index_types=IndexType.NONE),
    "no_summary": dict(
        index_types=IndexType.NONE,
        repeat_channels=False,
        repeat_schemas=False,
        use_statistics=False,
        use_summary_offsets=False,
    ),
    "no_chunks": dict(use_chunking=False),
    "lz4_small_chunks": dict(compression=CompressionType.LZ4, chunk_size=2000),
    "uncompressed": dict(compression=CompressionType.NONE),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_layouts_read_the_same(reference, case):
    table, ref, d = reference
    path = d / f"{case}.mcap"
    _write(path, table, **CASES[case])
    got, warnings = read_input(InputSpec(path=path))
    assert warnings == []
    assert got.equals(ref)


def test_ros1_encoded_mcap_and_its_carry_over(reference):
    table, ref, d = reference
    path = d / "ros1.mcap"
    _write(path, table, encoding="ros1", extra_ros1=True)
    got, _ = read_input(InputSpec(path=path))
    assert got.equals(ref)
    raw = carry_over(InputSpec(path=path))
    assert [m.topic for m in raw] == ["/chatter"] * 5
    assert raw[0].message_encoding == "cdr" and raw[0].schema_encoding == "ros2msg"
    store = get_typestore(Stores.ROS2_HUMBLE)
    assert store.deserialize_cdr(raw[3].data, "std_msgs/msg/String").data == "hello 3"


def test_big_endian_cdr_falls_back_to_rosbags(reference):
    table, ref, d = reference
    store = get_typestore(Stores.ROS2_HUMBLE)

    def big_endian(stream: str, data: bytes) -> bytes:
        msg = store.deserialize_cdr(data, TYPES[stream])
        return bytes(store.serialize_cdr(msg, TYPES[stream], little_endian=False))

    path = d / "be.mcap"
    _write(path, table, payload=big_endian)
    got, _ = read_input(InputSpec(path=path))
    assert got.equals(ref)
