"""MCAP files written by the ``mcap`` library's Writer, with its options, read by imupipe.

Differential property test: ``sensor_msgs/msg/Imu`` and ``sensor_msgs/msg/Temperature``
messages encoded with ``mcap_ros2``'s serializer and written by ``mcap.writer.Writer`` with a
drawn combination of its options (chunked or not, zstd/lz4/none, chunk size, channels and
schemas repeated in the summary or not, statistics, chunk and message indexes, summary offsets,
messages out of log-time order, the Imu topic on one or two channels) are read by imupipe
(``read_input``: what ``run`` reads; ``iter_input``: what ``convert`` reads; ``inspect``) and
decoded by ``mcap``'s ``NonSeekingReader`` with ``mcap_ros2``'s decoder: the same table, value
for value.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imupipe.pipeline.inspect_log import inspect
from imupipe.pipeline.writers.mcap import msgdef
from imupipe.readers.dispatch import iter_input, read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import stream_mask

IMU, TEMP = "sensor_msgs/msg/Imu", "sensor_msgs/msg/Temperature"
IMU_COLUMNS = [
    *(f"orientation_{a}" for a in "xyzw"),
    *(f"gyro_{a}" for a in "xyz"),
    *(f"accel_{a}" for a in "xyz"),
]
COVS = ["orientation_cov", "gyro_cov", "accel_cov"]


def write(options: dict, n_imu: int, n_temp: int, seed: int) -> tuple[bytes, list[dict]]:
    """An MCAP written by ``mcap``'s Writer with ``options`` (see :func:`layouts`): ``n_imu``
    Imu messages on ``/imu`` (on two channels when ``options["split"]``) and ``n_temp``
    Temperature messages on ``/temp``, random values and distinct header stamps, in file order
    shuffled when ``options["shuffle"]``. Returns the file's bytes and the messages written
    (topic, log time, publish time, fields)."""
    from mcap.writer import CompressionType, IndexType, Writer
    from mcap_ros2._dynamic import serialize_dynamic

    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000_000_000_000
    stamps = t0 + np.sort(rng.choice(10**9, n_imu + n_temp, replace=False))
    messages = []
    for k, stamp in enumerate(stamps.tolist()):
        header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "imu"}
        log = stamp + int(rng.integers(0, 10**6))
        if k < n_imu:
            v = rng.normal(size=10)
            fields = {
                "header": header,
                "orientation": dict(zip("xyzw", v[:4].tolist(), strict=True)),
                "angular_velocity": dict(zip("xyz", v[4:7].tolist(), strict=True)),
                "linear_acceleration": dict(zip("xyz", v[7:].tolist(), strict=True)),
                **{
                    f"{name}_covariance": rng.uniform(0.1, 1.0, 9).tolist()
                    for name in ("orientation", "angular_velocity", "linear_acceleration")
                },
            }
            topic = "/imu"
        else:
            fields = {
                "header": header,
                "temperature": float(rng.normal(30, 5)),
                "variance": float(rng.uniform(0, 1)),
            }
            topic = "/temp"
        messages.append((topic, log, log + int(rng.integers(0, 1000)), fields))
    if options["shuffle"]:
        messages = [messages[i] for i in rng.permutation(len(messages))]
    indexes = {"all": IndexType.ALL, "none": IndexType.NONE, "chunk": IndexType.CHUNK}
    out = io.BytesIO()
    w = Writer(
        out,
        chunk_size=options["chunk_size"],
        compression=getattr(CompressionType, options["compression"]),
        index_types=indexes[options["indexes"]],
        repeat_channels=options["repeat_channels"],
        repeat_schemas=options["repeat_schemas"],
        use_chunking=options["chunked"],
        use_statistics=options["statistics"],
        use_summary_offsets=options["summary_offsets"],
    )
    w.start(profile="ros2")
    encode = {t: serialize_dynamic(t, msgdef(t))[t] for t in (IMU, TEMP)}
    imu_schema = w.register_schema(IMU, "ros2msg", msgdef(IMU).encode())
    temp_schema = w.register_schema(TEMP, "ros2msg", msgdef(TEMP).encode())
    channels = [w.register_channel("/imu", "cdr", imu_schema)]
    if options["split"]:  # a second channel on the same topic, with its own copy of the schema
        copy = w.register_schema(IMU, "ros2msg", msgdef(IMU).encode())
        channels.append(w.register_channel("/imu", "cdr", copy))
    # a selected topic without messages is an error of its own: /temp only when it has some
    temp = w.register_channel("/temp", "cdr", temp_schema) if n_temp else None
    for k, (topic, log, pub, fields) in enumerate(messages):
        cid = channels[k % len(channels)] if topic == "/imu" else temp
        assert cid is not None
        data = encode[IMU if topic == "/imu" else TEMP](fields)
        w.add_message(cid, log_time=log, publish_time=pub, data=data, sequence=k)
    w.finish()
    return out.getvalue(), messages


def reference(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """Per stream, the columns the table should hold, from ``mcap``'s NonSeekingReader and
    ``mcap_ros2``'s decoder, rows in header-stamp order."""
    from mcap.reader import NonSeekingReader
    from mcap_ros2.decoder import DecoderFactory

    rows: dict[str, list[dict]] = {"imu": [], "temperature": []}
    with open(path, "rb") as fh:
        reader = NonSeekingReader(fh, decoder_factories=[DecoderFactory()])
        for schema, _, message, m in reader.iter_decoded_messages(log_time_order=False):
            row = {
                "t_ns": m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                "log_time_ns": message.log_time,
                "publish_time_ns": message.publish_time,
            }
            if schema.name == IMU:
                for name, vec in (
                    ("orientation", m.orientation),
                    ("gyro", m.angular_velocity),
                    ("accel", m.linear_acceleration),
                ):
                    for a in "xyzw" if name == "orientation" else "xyz":
                        row[f"{name}_{a}"] = getattr(vec, a)
                row["orientation_cov"] = list(m.orientation_covariance)
                row["gyro_cov"] = list(m.angular_velocity_covariance)
                row["accel_cov"] = list(m.linear_acceleration_covariance)
                rows["imu"].append(row)
            else:
                row["temperature"] = m.temperature
                row["temperature_var"] = m.variance
                rows["temperature"].append(row)
    out = {}
    for stream, rs in rows.items():
        rs.sort(key=lambda r: r["t_ns"])
        out[stream] = {k: np.array([r[k] for r in rs]) for k in (rs[0] if rs else {})}
    return out


def columns(table: pa.Table) -> dict[str, dict[str, np.ndarray]]:
    """Per stream, the table's columns (those :func:`reference` gives), rows by ``t_ns``."""
    out = {}
    for stream, names in (
        ("imu", ["t_ns", "log_time_ns", "publish_time_ns", *IMU_COLUMNS, *COVS]),
        (
            "temperature",
            ["t_ns", "log_time_ns", "publish_time_ns", "temperature", "temperature_var"],
        ),
    ):
        rows = table.filter(pa.array(stream_mask(table, stream))).sort_by("t_ns")
        if len(rows) == 0:
            continue
        out[stream] = {}
        for name in names:
            col = rows.column(name).combine_chunks()
            if isinstance(col.type, pa.FixedSizeListType):
                out[stream][name] = col.flatten().to_numpy().reshape(len(rows), -1)
            else:
                out[stream][name] = col.to_numpy()
    return out


def assert_same(got: dict, want: dict) -> None:
    assert set(got) == {s for s, cols in want.items() if cols}
    for stream, cols in got.items():
        assert set(cols) == set(want[stream]), stream
        for name, values in cols.items():
            np.testing.assert_array_equal(values, want[stream][name], err_msg=f"{stream}.{name}")


WRITER_DEFAULTS = {
    "chunked": True,
    "compression": "ZSTD",
    "chunk_size": 1 << 20,
    "repeat_channels": True,
    "repeat_schemas": True,
    "statistics": True,
    "indexes": "all",
    "summary_offsets": True,
    "shuffle": False,
    "split": False,
}
"""The Writer's own defaults, messages in time order on one channel per topic."""


def layouts() -> st.SearchStrategy[dict]:
    """The Writer's options, and how the messages are laid out."""
    return st.fixed_dictionaries(
        {
            "chunked": st.booleans(),
            "compression": st.sampled_from(["ZSTD", "LZ4", "NONE"]),
            "chunk_size": st.sampled_from([200, 2000, 1 << 20]),
            "repeat_channels": st.booleans(),
            "repeat_schemas": st.booleans(),
            "statistics": st.booleans(),
            "indexes": st.sampled_from(["all", "none", "chunk"]),
            "summary_offsets": st.booleans(),
            "shuffle": st.booleans(),
            "split": st.booleans(),
        }
    )


def check(path: Path) -> None:
    """imupipe's reads of ``path`` (run's, convert's, inspect's) against the reference."""
    want = reference(path)
    spec = InputSpec(path=path)
    table, _ = read_input(spec)
    assert_same(columns(table), want)
    batches = [t for t, _ in iter_input(spec, batch_rows=7)]
    assert_same(columns(pa.concat_tables(batches)), want)
    described = inspect(spec)
    for topic, stream in (("/imu", "imu"), ("/temp", "temperature")):
        n = len(want[stream].get("t_ns", ()))
        assert described["topics"].get(topic, {"count": 0})["count"] == n
        if n:
            assert described["topics"][topic]["start_ns"] == int(want[stream]["log_time_ns"].min())
            assert described["topics"][topic]["end_ns"] == int(want[stream]["log_time_ns"].max())


def differential(examples: int, most_imu: int, most_temp: int):
    """The property test: ``examples`` drawn layouts of up to ``most_imu`` Imu and
    ``most_temp`` Temperature messages, each read by imupipe as ``mcap_ros2`` decodes it."""

    @settings(
        max_examples=examples,
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture],
    )
    @given(
        options=layouts(),
        n_imu=st.integers(1, most_imu),
        n_temp=st.integers(0, most_temp),
        seed=st.integers(0, 2**32 - 1),
    )
    def test(tmp_path, options, n_imu, n_temp, seed):
        data, _ = write(options, n_imu, n_temp, seed)
        path = tmp_path / "log.mcap"
        path.write_bytes(data)
        check(path)

    return test


test_writer_options_read_as_mcap_ros2_decodes = differential(40, 40, 6)
test_writer_options_read_as_mcap_ros2_decodes_more = pytest.mark.slow(differential(400, 400, 30))


def test_summary_without_channels_runs_and_converts(tmp_path, cli):
    """Issue 24: ``Writer(repeat_channels=False)`` (statistics on, the library's defaults
    otherwise) wrote a file whose Imu topic ``run`` did not find and whose index ``convert``
    called corrupt. Now: ``inspect`` lists it, ``run``'s read and ``convert`` take every message."""
    options = {**WRITER_DEFAULTS, "chunk_size": 2000, "repeat_channels": False}
    data, messages = write(options, 50, 3, seed=1)
    logs = tmp_path / "logs"
    logs.mkdir()
    path = logs / "log.mcap"
    path.write_bytes(data)
    check(path)
    shown = cli("inspect", path, "--json")
    assert shown.returncode == 0, shown.stderr
    topics = json.loads(shown.stdout)["topics"]
    assert {t: v["count"] for t, v in topics.items()} == {"/imu": 50, "/temp": 3}
    assert topics["/imu"]["type"] == IMU
    cal = tmp_path / "cal.json"
    chain = [
        {
            "type": "gyro_calibration",
            "sensor": "gyro",
            "kind": "linear",
            "matrix": np.eye(3).tolist(),
            "offset": [0.1, 0.0, 0.0],
        }
    ]
    cal.write_text(json.dumps({"imupipe_version": "test", "chain": chain, "results": {}}))
    done = cli("convert", "--calibration", cal, "--out", tmp_path / "out", logs)
    assert done.returncode == 0, done.stderr
    from mcap.reader import make_reader

    with open(tmp_path / "out" / "log.mcap", "rb") as fh:
        stats = make_reader(fh).get_summary().statistics
    assert stats.message_count == len(messages)


def test_summary_without_channels_costs_one_chunk(tmp_path, monkeypatch):
    """The channels a summary counts messages on but does not define are looked for in the data
    section only until they are found: the first chunk of a many-chunk file, here."""
    from imupipe.readers.mcap import fast as fast_mcap

    options = {
        **WRITER_DEFAULTS,
        "compression": "LZ4",
        "chunk_size": 2000,
        "repeat_channels": False,
        "repeat_schemas": False,
        "split": True,
    }
    data, _ = write(options, 400, 5, seed=2)
    path = tmp_path / "log.mcap"
    path.write_bytes(data)
    decompressed = []
    original = fast_mcap.McapFile._decompress
    monkeypatch.setattr(
        fast_mcap.McapFile,
        "_decompress",
        lambda self, body, pos: decompressed.append(pos) or original(self, body, pos),
    )
    opened = fast_mcap.McapFile(path)
    assert {c.topic: c.schema_name for c in opened.channels.values()} == {
        "/imu": IMU,
        "/temp": TEMP,
    }
    assert len(decompressed) == 1
    assert len(fast_mcap.McapFile(path).chunk_starts) > 20  # a many-chunk file
