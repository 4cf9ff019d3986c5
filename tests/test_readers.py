"""Issue 3: MCAP, ROS 1 bag and ROS 2 bag readers, cross-checked against the libraries' decoders.

A synthetic log with three streams at different rates (Imu 200 Hz, MagneticField 50 Hz,
Temperature 1 Hz), random orientations and covariances and frame_ids of different lengths in one
topic is written in every format and must read back to the same table; the numpy fast paths are
compared field by field with mcap_ros2's decoder and rosbags' deserializer.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.ipc  # noqa: F401
import pytest
from rosbags.highlevel import AnyReader

from imupipe.pipeline.errors import ReadError
from imupipe.pipeline.simulate import write_log
from imupipe.readers.dispatch import iter_input, read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import COV, make_table, metadata, sensor

from helpers import decode_mcap, resident

T0 = 1_700_000_000_123_456_789
FRAMES = np.array(["imu", "imu_link_long", "i", "imu_link_long_4567"])


def multi_stream_table(seed: int = 0) -> pa.Table:
    """Imu 200 Hz (4 frame_ids of different lengths), mag 50 Hz, temperature 1 Hz; every field
    random so that nothing is left at a default."""
    rng = np.random.default_rng(seed)
    t = {
        "imu": T0 + np.arange(600, dtype=np.int64) * 5_000_000,
        "mag": T0 + 1_000_001 + np.arange(150, dtype=np.int64) * 20_000_000,
        "temperature": T0 + 2_000_003 + np.arange(3, dtype=np.int64) * 1_000_000_000,
    }
    t_all = np.concatenate(list(t.values()))
    order = np.argsort(t_all, kind="stable")
    kind = np.repeat([0, 1, 2], [len(v) for v in t.values()])[order]
    t_all = t_all[order]
    n = len(t_all)
    imu, mag, tmp = kind == 0, kind == 1, kind == 2
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)

    def col(values: np.ndarray, mask: np.ndarray) -> pa.Array:
        if values.ndim == 1:
            return pa.array(values, pa.float64(), mask=~mask)
        flat = pa.array(values.reshape(-1), pa.float64())
        return pa.FixedSizeListArray.from_arrays(flat, 9, mask=pa.array(~mask))

    frames = np.where(imu, FRAMES[rng.integers(0, 4, n)], np.where(mag, "magnetometer", "t"))
    extra = {
        "log_time_ns": pa.array(t_all + rng.integers(0, 3_000_000, n)),
        "frame_id": pa.array(frames),
        **{f"orientation_{a}": col(quat[:, i], imu) for i, a in enumerate("xyzw")},
        "orientation_cov": col(rng.normal(size=(n, 9)), imu),
        "gyro_cov": col(rng.normal(size=(n, 9)), imu),
        "accel_cov": col(rng.normal(size=(n, 9)), imu),
        "mag_cov": col(rng.normal(size=(n, 9)), mag),
        "temperature_var": col(rng.uniform(0, 1, n), tmp),
    }
    table = make_table(
        t_all,
        gyro=rng.normal(0, 0.1, (n, 3)),
        accel=rng.normal(0, 1, (n, 3)) + [0, 0, 9.81],
        mag=rng.normal(0, 3e-5, (n, 3)),
        temperature=rng.normal(25, 1, n),
        valid={"imu": imu, "mag": mag, "temperature": tmp},
        metadata={"topics": {"imu": "/imu/data", "mag": "/imu/mag", "temperature": "/imu/temp"}},
    )
    for name, array in extra.items():
        table = table.append_column(pa.field(name, array.type), array)
    return table


def same_table(a: pa.Table, b: pa.Table) -> bool:
    """Bit-exact equality of two tables' columns (NaN payloads included; metadata ignored)."""

    def raw(t: pa.Table) -> bytes:
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, t.schema.remove_metadata()) as w:
            w.write_table(t.replace_schema_metadata(None).combine_chunks())
        return sink.getvalue().to_pybytes()

    return raw(a) == raw(b)


BINARY = ["log.mcap", "log.bag", "log.db3", "log_folder"]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The multi-stream table, written in every format (and read back once each)."""
    d = tmp_path_factory.mktemp("formats")
    table = multi_stream_table()
    for name in ["log.csv", *BINARY]:
        write_log(d / name, table)
    from imupipe.pipeline.writers.bag import write_ros1_bag, write_ros2_bag

    write_ros1_bag(d / "log_bz2.bag", table, compression="bz2")
    write_ros1_bag(d / "log_none.bag", table, compression="none")
    write_ros2_bag(d / "log_mcap2", table, storage="mcap")
    names = ["log.csv", *BINARY, "log_bz2.bag", "log_none.bag", "log_mcap2"]
    tables = {n: read_input(InputSpec(path=d / n)) for n in names}
    return d, table, tables


def test_every_binary_format_reads_to_the_same_table(written):
    _, table, tables = written
    ref, warnings = tables["log.mcap"]
    assert warnings == []
    assert ref.num_rows == table.num_rows
    for name, (other, w) in tables.items():
        if name != "log.csv":
            assert w == []
            # MCAP storage keeps publish times (here written as the log times), bags have none
            if "publish_time_ns" in other.column_names:
                assert other.column("publish_time_ns").equals(other.column("log_time_ns")), name
                other = other.drop_columns(["publish_time_ns"])
            assert other.equals(ref.drop_columns(["publish_time_ns"])), name  # bit-exact
    # and the table is the one written: every column, bit for bit (log_time_ns included)
    for col in table.column_names:
        assert ref.column(col).equals(table.column(col).cast(ref.schema.field(col).type)), col


def test_csv_matches_binary_per_stream(written):
    _, _, tables = written
    csv, _ = tables["log.csv"]
    ref, _ = tables["log.mcap"]
    for name in ("gyro", "accel", "mag", "temperature"):
        a, b = sensor(csv, name), sensor(ref, name)
        np.testing.assert_array_equal(a.t_ns, b.t_ns)
        np.testing.assert_array_equal(a.values, b.values)  # shortest round-trip text: exact


def _fields(msg) -> list[float]:
    if hasattr(msg, "angular_velocity"):
        q, g, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
        return [
            q.x, q.y, q.z, q.w, *msg.orientation_covariance,
            g.x, g.y, g.z, *msg.angular_velocity_covariance,
            a.x, a.y, a.z, *msg.linear_acceleration_covariance,
        ]  # fmt: skip
    if hasattr(msg, "magnetic_field"):
        m = msg.magnetic_field
        return [m.x, m.y, m.z, *msg.magnetic_field_covariance]
    return [msg.temperature, msg.variance]


def _table_fields(table: pa.Table, stream: str) -> tuple[np.ndarray, list[str], np.ndarray]:
    """(stamps, frame_ids, all float fields in message order) of one stream of a table."""
    key = {"imu": "gyro_x", "mag": "mag_x", "temperature": "temperature"}[stream]
    rows = table.filter(pa.compute.is_valid(table.column(key)))
    names = {
        "imu": [
            *(f"orientation_{a}" for a in "xyzw"), "orientation_cov", "gyro_x", "gyro_y", "gyro_z",
            "gyro_cov", "accel_x", "accel_y", "accel_z", "accel_cov",
        ],
        "mag": ["mag_x", "mag_y", "mag_z", "mag_cov"],
        "temperature": ["temperature", "temperature_var"],
    }[stream]  # fmt: skip
    cols = []
    for name in names:
        c = rows.column(name).combine_chunks()
        cols.append(
            c.flatten().to_numpy().reshape(-1, 9) if c.type == COV else c.to_numpy()[:, None]
        )
    return rows.column("t_ns").to_numpy(), rows.column("frame_id").to_pylist(), np.hstack(cols)


TOPIC_STREAM = {"/imu/data": "imu", "/imu/mag": "mag", "/imu/temp": "temperature"}


def test_mcap_fast_path_equals_mcap_ros2_decoder(written):
    d, _, tables = written
    ref, _ = tables["log.mcap"]
    decoded = decode_mcap(d / "log.mcap")
    assert set(decoded) == set(TOPIC_STREAM)
    for topic, stream in TOPIC_STREAM.items():
        msgs = sorted(decoded[topic], key=lambda m: m[0])
        stamps, frames, values = _table_fields(ref, stream)
        lib = np.array([_fields(m) for _, m in msgs])
        np.testing.assert_array_equal(
            stamps, [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in msgs]
        )
        assert frames == [m.header.frame_id for _, m in msgs]
        assert values.tobytes() == lib.tobytes()  # bit for bit


@pytest.mark.parametrize("name", ["log.bag", "log_bz2.bag", "log.db3", "log_folder", "log_mcap2"])
def test_bag_fast_paths_equal_rosbags(written, name):
    d, _, tables = written
    table, _ = tables[name]
    path = d / name
    with AnyReader([path]) as reader:
        by_topic: dict[str, list] = {}
        for conn, t, data in reader.messages():
            by_topic.setdefault(conn.topic, []).append((t, reader.deserialize(data, conn.msgtype)))
    for topic, stream in TOPIC_STREAM.items():
        msgs = by_topic[topic]
        stamps, frames, values = _table_fields(table, stream)
        np.testing.assert_array_equal(
            stamps, [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in msgs]
        )
        assert frames == [m.header.frame_id for _, m in msgs]
        assert values.tobytes() == np.array([_fields(m) for _, m in msgs]).tobytes()


def test_iter_input_batches_join_to_the_table(written):
    """Batches come in log-time order: with ``time = "log"`` they join to exactly the table
    ``read_input`` gives; with header stamps, each stream holds the same rows (a stamp may sit
    one batch away from its place in the global sort)."""
    d, _, tables = written
    for name in ("log.mcap", "log.bag", "log.db3", "log_mcap2"):
        spec = InputSpec(path=d / name, time="log")
        batches = list(iter_input(spec, batch_rows=100))
        assert all(raw == [] for _, raw in batches)
        joined = pa.concat_tables([b for b, _ in batches])
        assert joined.equals(read_input(spec)[0]), name
        header = pa.concat_tables([b for b, _ in iter_input(InputSpec(path=d / name), 100)])
        for sensor_name in ("gyro", "mag", "temperature"):
            a, b = sensor(header, sensor_name), sensor(tables[name][0], sensor_name)
            order = np.argsort(a.t_ns, kind="stable")
            np.testing.assert_array_equal(a.t_ns[order], b.t_ns)
            np.testing.assert_array_equal(a.values[order], b.values)


def test_iter_input_memory_is_bounded_by_batch_and_chunk(written, tmp_path):
    from imupipe.pipeline.writers.mcap import write_mcap

    _, table, _ = written
    path = tmp_path / "small_chunks.mcap"
    write_mcap(path, table, chunk_bytes=4096)  # ~12 Imu messages per chunk
    sizes = [b.num_rows for b, _ in iter_input(InputSpec(path=path), batch_rows=50)]
    assert sum(sizes) == table.num_rows
    assert len(sizes) >= 10 and max(sizes) < 50 + 100, sizes


def test_time_log_uses_log_times(written):
    d, table, _ = written
    got, _ = read_input(InputSpec(path=d / "log.bag", time="log"))
    for stream, key in (("imu", "gyro_x"), ("mag", "mag_x")):
        mask = pa.compute.is_valid(table.column(key))
        want = np.sort(table.filter(mask).column("log_time_ns").to_numpy())
        have = got.filter(pa.compute.is_valid(got.column(key))).column("t_ns").to_numpy()
        np.testing.assert_array_equal(have, want, stream)


def test_out_of_order_and_duplicate_stamps_sorted_stably_and_warned(tmp_path):
    rng = np.random.default_rng(5)
    n = 400
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    stamps = t.copy()
    swap = rng.choice(n - 1, 20, replace=False)
    stamps[swap], stamps[swap + 1] = t[swap + 1], t[swap]
    stamps[100] = stamps[99]  # a duplicate
    gyro = np.column_stack([np.arange(n, dtype=float)] * 3)
    table = make_table(
        stamps,
        gyro=gyro,
        accel=np.zeros((n, 3)),
        extra={"log_time_ns": t},
        metadata={"topics": {"imu": "/imu"}},
    )
    write_log(tmp_path / "ooo.mcap", table)
    got, warnings = read_input(InputSpec(path=tmp_path / "ooo.mcap"))
    assert got.num_rows == n  # nothing dropped
    order = np.argsort(stamps, kind="stable")
    np.testing.assert_array_equal(got.column("t_ns").to_numpy(), stamps[order])
    np.testing.assert_array_equal(got.column("gyro_x").to_numpy(), gyro[order, 0])
    moved = int(np.count_nonzero(order != np.arange(n)))
    assert any(f"{moved} messages out of header time order" in w for w in warnings), warnings
    dups = int(np.count_nonzero(np.diff(np.sort(stamps)) == 0))
    assert dups >= 1
    assert any(f"{dups} messages repeat the previous header stamp" in w for w in warnings)


def test_topic_selection_errors(written, tmp_path):
    d, table, _ = written
    path = d / "log.mcap"
    with pytest.raises(ReadError, match=r"imu_topic '/nope' is not in the log.*/imu/data"):
        read_input(InputSpec(path=path, imu_topic="/nope"))
    with pytest.raises(ReadError, match=r"topic '/imu/mag' \(imu_topic\) has type .*MagneticField"):
        read_input(InputSpec(path=path, imu_topic="/imu/mag"))
    # two Imu topics: omitted imu_topic lists the candidates
    from imupipe.pipeline.writers.mcap import McapTableWriter
    from imupipe.readers.table import with_metadata

    two = tmp_path / "two.mcap"
    with McapTableWriter(two) as w:
        w.write_table(table)
        w.write_table(
            with_metadata(table, {"topics": {"imu": "/imu2", "mag": "/m2", "temperature": "/t2"}})
        )
    with pytest.raises(ReadError, match=r"several sensor_msgs/msg/Imu topics \(/imu/data, /imu2\)"):
        read_input(InputSpec(path=two))
    got, _ = read_input(
        InputSpec(path=two, imu_topic="/imu2", mag_topic="/m2", temperature_topic="/t2")
    )
    assert got.num_rows == table.num_rows


def test_empty_topic_is_an_error(tmp_path):
    from mcap.writer import Writer

    from imupipe.pipeline.writers.mcap import msgdef

    path = tmp_path / "empty.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        sid = w.register_schema(
            "sensor_msgs/msg/Imu", "ros2msg", msgdef("sensor_msgs/msg/Imu").encode()
        )
        w.register_channel("/imu", "cdr", sid)
        w.finish()
    with pytest.raises(ReadError, match=r"empty.mcap: topic '/imu' has no messages"):
        read_input(InputSpec(path=path))


def test_wrong_payload_on_a_topic_names_file_and_topic(tmp_path):
    from mcap.writer import Writer

    from imupipe.pipeline.writers.mcap import msgdef

    path = tmp_path / "bad.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        sid = w.register_schema(
            "sensor_msgs/msg/Imu", "ros2msg", msgdef("sensor_msgs/msg/Imu").encode()
        )
        cid = w.register_channel("/imu", "cdr", sid)
        # a Temperature payload published on an Imu topic
        from imupipe.readers import cdr

        payload = cdr.encode(
            "sensor_msgs/msg/Temperature", np.array([T0]), b"imu", {"temperature": np.array([20.0])}
        )
        w.add_message(cid, log_time=T0, data=payload[0].tobytes(), publish_time=T0)
        w.finish()
    with pytest.raises(
        ReadError, match=r"bad.mcap: topic '/imu': .* too short for sensor_msgs/msg/Imu"
    ):
        read_input(InputSpec(path=path))


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_split_logs_in_a_folder_join_in_time_order(written, tmp_path, suffix):
    d, table, tables = written
    folder = tmp_path / "split"
    folder.mkdir()
    half = table.num_rows // 2
    # written in reverse name order: the join follows the first message, not the file name
    write_log(folder / f"b{suffix}", table.slice(0, half))
    write_log(folder / f"a{suffix}", table.slice(half))
    got, warnings = read_input(InputSpec(path=folder))
    assert warnings == []
    assert got.equals(tables["log" + suffix][0])


def _promised_order(table: pa.Table, time: str) -> np.ndarray:
    """The row order the readers promise, computed directly: per stream, log order, then
    stably by the chosen time; then the streams merged stably by time (imu, mag, temperature
    first at equal times). Rows of ``table`` are given in file order per stream."""
    log = table.column("log_time_ns").to_numpy()
    t = table.column("t_ns").to_numpy() if time == "header" else log
    parts = []
    for key in ("gyro_x", "mag_x", "temperature"):
        rows = np.flatnonzero(pa.compute.is_valid(table.column(key)).to_numpy())
        rows = rows[np.argsort(log[rows], kind="stable")]
        parts.append(rows[np.argsort(t[rows], kind="stable")])
    rows = np.concatenate(parts)
    return rows[np.argsort(t[rows], kind="stable")]


def _write_order(table, path, order: str, rng) -> pa.Table:
    """Write ``table``'s messages to an MCAP in one of four layouts; returns the table with its
    rows in the file's order per topic (what the readers see)."""
    from mcap.writer import CompressionType, Writer

    from imupipe.pipeline.writers.mcap import encode_stream, msgdef

    log = table.column("log_time_ns").to_numpy()
    if order == "imupipe":  # imupipe's writer: chunks of one topic each, by first log time
        from imupipe.pipeline.writers.mcap import write_mcap

        write_mcap(path, table, chunk_bytes=2000)
        return table
    messages = []  # (row, channel, payload)
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=3000)
        w.start(profile="ros2")
        for stream, typ in (
            ("imu", "sensor_msgs/msg/Imu"),
            ("mag", "sensor_msgs/msg/MagneticField"),
            ("temperature", "sensor_msgs/msg/Temperature"),
        ):
            schema = w.register_schema(typ, "ros2msg", msgdef(typ).encode())
            cid = w.register_channel(f"/{stream}", "cdr", schema)
            rows, groups = encode_stream(table, stream)
            for sel, payloads in groups:
                messages += [
                    (rows[i], cid, p.tobytes()) for i, p in zip(sel, payloads, strict=True)
                ]
        if order == "log":  # one chunk stream, every topic interleaved (rosbag record)
            messages.sort(key=lambda m: log[m[0]])
        elif order == "shuffled":  # chunks overlapping in time, messages out of log order
            messages = [messages[i] for i in rng.permutation(len(messages))]
        # "topics": each topic's messages after the other's (chunks of one topic each)
        for row, cid, data in messages:
            w.add_message(cid, log_time=int(log[row]), publish_time=int(log[row]), data=data)
        w.finish()
    return table.take(pa.array([m[0] for m in messages]))


@pytest.mark.parametrize("layout", ["log", "topics", "imupipe", "shuffled"])
@pytest.mark.parametrize("time", ["header", "log"])
@pytest.mark.parametrize("jitter", [True, False])
def test_streams_merge_in_the_promised_order(tmp_path, layout, time, jitter):
    """Jittered and repeated header stamps (or stamps in order, with ties across topics),
    repeated log times, chunks interleaved, per topic or shuffled: the table is the promised
    order, field for field, and the out-of-order and repeated stamps are counted per topic."""
    if layout == "imupipe" and jitter:
        pytest.skip("imupipe's writer orders each (topic, frame_id) on its own: no file order here")
    rng = np.random.default_rng(11)
    table = multi_stream_table(seed=3)
    table = table.filter(pa.compute.not_equal(table.column("frame_id"), "i"))  # 3 Imu frames
    n = table.num_rows
    t = table.column("t_ns").to_numpy().copy()
    log = table.column("log_time_ns").to_numpy().copy()
    if jitter:
        t += rng.integers(-12_000_000, 12_000_000, n)
        t[rng.choice(n, 30)] = t[rng.choice(n, 30)]
        log[rng.choice(n, 20)] = log[rng.choice(n, 20)]
    else:  # in order, one Imu frame_id, ties between topics at equal stamps
        t = (t // 20_000_000) * 20_000_000
        log = np.maximum.accumulate(log)
        frames = pa.array(np.where(pa.compute.is_valid(table.column("gyro_x")), "imu", "m"))
        table = table.set_column(table.schema.get_field_index("frame_id"), "frame_id", frames)
    table = table.set_column(0, "t_ns", pa.array(t))
    i = table.schema.get_field_index("log_time_ns")
    table = table.set_column(i, "log_time_ns", pa.array(log))
    in_file = _write_order(table, tmp_path / "m.mcap", layout, rng)
    got, warnings = read_input(InputSpec(path=tmp_path / "m.mcap", time=time))
    want = in_file.take(pa.array(_promised_order(in_file, time)))
    if time == "log":
        want = want.set_column(0, "t_ns", want.column("log_time_ns"))
    assert got.num_rows == n
    for name in want.column_names:
        assert got.column(name).equals(want.column(name)), name
    for name in ("gyro_x", "gyro_cov", "mag_y", "mag_cov", "temperature", "temperature_var"):
        column = got.column(name).combine_chunks()
        if isinstance(column, pa.FixedSizeListArray):
            under = column.values.to_numpy().reshape(-1, 9)[column.is_null().to_numpy(False)]
        else:
            raw = np.frombuffer(column.buffers()[1], np.float64)[column.offset :][: len(column)]
            under = raw[column.is_null().to_numpy(zero_copy_only=False)]
        assert not np.any(under), f"{name}: values under nulls are not 0 (not deterministic)"
    topics = metadata(got)["topics"]
    for topic, key in ((topics["imu"], "gyro_x"), (topics["mag"], "mag_x")):
        rows = np.flatnonzero(pa.compute.is_valid(in_file.column(key)).to_numpy())
        file_log = in_file.column("log_time_ns").to_numpy()[rows]
        file_t = file_log if time == "log" else in_file.column("t_ns").to_numpy()[rows]
        file_t = file_t[np.argsort(file_log, kind="stable")]
        moved = int(np.count_nonzero(np.argsort(file_t, kind="stable") != np.arange(len(rows))))
        said = [w for w in warnings if f"topic {topic}: " in w and "out of" in w]
        assert said == (
            [
                f"{tmp_path / 'm.mcap'} topic {topic}: {moved} messages out of {time} time order; sorted stably (none dropped)"
            ]
            if moved
            else []
        )


@pytest.mark.parametrize("sizes", [(2000, 3, 0), (600, 150, 3), (50, 900, 40), (1, 1, 1)])
def test_merge_rows_and_spread_equal_a_stable_sort(sizes):
    """The merge behind multi-topic reads (both of its ways of counting) and the in-place
    spread (run by run, block by block) against numpy's stable sort of the streams in order."""
    from imupipe.readers import table_buffer as tb

    rng = np.random.default_rng(sum(sizes))
    times = [np.sort(rng.integers(0, 300, k)) for k in sizes]
    rows = tb._merge_rows(times)
    order = np.argsort(np.concatenate(times), kind="stable")
    expected = np.empty(len(order), np.int64)
    expected[order] = np.arange(len(order))
    np.testing.assert_array_equal(np.concatenate(rows), expected)
    big = int(np.argmax(sizes))
    n = sum(sizes)
    for shape in ((n,), (n, 9)):
        values = rng.normal(size=(sizes[big],) + shape[1:])
        column = np.zeros(shape)
        column[: sizes[big]] = values
        tb._spread([column], rows[big])
        np.testing.assert_array_equal(column[rows[big]], values)


def test_prefault_maps_a_bounded_distance_ahead_and_stops():
    """The page-mapping helper maps at most AHEAD_ROWS past the filled rows (a log that states
    a wrong, huge message count costs no memory for it), follows the filled rows, changes no
    value, and its thread ends on close or when its owner is dropped. The arrays are fresh
    anonymous mappings (not the allocator's, which may hand out pages already mapped) and what
    is mapped is read with ``mincore`` (not the process's RSS, which other threads move)."""
    import gc
    import mmap
    import os
    import time

    from imupipe.readers import prefault

    if prefault._madvise is None:
        pytest.skip("no madvise here")
    ahead, step = prefault.AHEAD_ROWS, prefault.STEP_ROWS
    rows = 8 * ahead  # 2 M rows x 80 bytes: 168 MB if all were mapped
    maps = [mmap.mmap(-1, rows * 8), mmap.mmap(-1, rows * 72)]
    arrays = [np.frombuffer(maps[0], np.float64), np.frombuffer(maps[1]).reshape(rows, 9)]

    def mapped(lo: int, hi: int) -> float:
        """The least share of pages mapped among the arrays' rows lo:hi."""
        return min(
            resident(a.ctypes.data + lo * a.strides[0], (hi - lo) * a.strides[0]) for a in arrays
        )

    def wait_until(lo: int, hi: int) -> None:
        deadline = time.monotonic() + 20
        while mapped(lo, hi) < 1 and helper.thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)
        if helper.error:  # the kernel's refusal, not ours: the reader then maps pages itself
            pytest.skip(f"the kernel refused MADV_POPULATE_WRITE: {os.strerror(helper.error)}")

    helper = prefault.Prefault(arrays)
    helper.advance(0)
    wait_until(0, ahead)
    assert mapped(0, ahead) == 1, helper.thread.is_alive()
    assert mapped(ahead + step, rows) == 0  # nothing past the distance ahead
    helper.advance(3 * ahead)
    wait_until(0, 4 * ahead)
    assert mapped(0, 4 * ahead) == 1
    assert mapped(4 * ahead + step, rows) == 0
    helper.close()
    assert not helper.thread.is_alive()
    assert not arrays[1].any()
    dropped = prefault.Prefault([np.zeros(rows)])
    thread = dropped.thread
    del dropped
    gc.collect()
    thread.join(timeout=5)
    assert not thread.is_alive()
    arrays.clear()  # the views, before their mappings close
    for buffer in maps:
        buffer.close()


def test_prefault_stops_on_a_kernel_refusal_and_retries_an_interrupted_call(monkeypatch):
    """A kernel without MADV_POPULATE_WRITE (EINVAL) stops the helper, which records why; an
    interrupted call (EINTR) is made again."""
    import ctypes
    import errno

    from imupipe.readers import prefault

    calls: list[int] = []
    answers = {"refuse": errno.EINVAL, "interrupt": errno.EINTR}
    mode = "refuse"

    def fake(address: int, length: int, advice: int) -> int:
        calls.append(length)
        if mode == "interrupt" and len(calls) > 1:
            return 0
        ctypes.set_errno(answers[mode])
        return -1

    monkeypatch.setattr(prefault, "_madvise", fake)
    helper = prefault.Prefault([np.zeros(4 * prefault.STEP_ROWS)])
    helper.thread.join(timeout=5)
    assert not helper.thread.is_alive() and helper.error == errno.EINVAL and len(calls) == 1
    mode, calls[:] = "interrupt", []
    assert prefault._populate(np.zeros(1024), 0, 1024) == 0 and len(calls) == 2


def _bits(column: pa.ChunkedArray) -> np.ndarray:
    """A float or fixed-size-list column's values as uint64 bits (nulls' slots included)."""
    array = column.combine_chunks()
    if isinstance(array, pa.FixedSizeListArray):
        array = array.flatten()
    if pa.types.is_floating(array.type):
        return np.frombuffer(array.buffers()[1], np.uint64)[array.offset :][: len(array)]
    return np.asarray(array.to_numpy(zero_copy_only=False))


def test_mcap_fast_paths_read_what_the_general_ones_read(tmp_path, monkeypatch):
    """The MCAP read's fast paths against its general ones (issue 17), bit for bit: columns
    left unwritten while every message so far carried zeros (a covariance that turns non-zero
    late, one that carries -0.0, which is not zero), one frame_id per chunk checked message by
    message (two frame_ids of one length), decompression buffers used again, and batches that
    keep views into chunks while later chunks are read."""
    from imupipe.pipeline.writers.mcap import write_mcap
    from imupipe.readers import decoded, table_buffer

    rng = np.random.default_rng(17)
    n = 30_000
    t = T0 + np.arange(n, dtype=np.int64) * 2_500_000
    gyro_cov = np.zeros((n, 9))
    gyro_cov[20_000:20_010, 4] = 1e-3  # zeros, then values, then zeros again
    accel_cov = np.zeros((n, 9))
    accel_cov[25_000, 8] = -0.0
    frames = np.full(n, "imu_a")
    frames[rng.integers(0, n, 5)] = "imu_b"  # same length: the layout cannot tell them apart
    table = make_table(
        t,
        gyro=rng.normal(size=(n, 3)),
        accel=rng.normal(size=(n, 3)),
        extra={
            "frame_id": pa.array(frames),
            "orientation_w": np.ones(n),
            "gyro_cov": gyro_cov,
            "accel_cov": accel_cov,
        },
        metadata={"topics": {"imu": "/imu"}},
    )
    path = tmp_path / "fast.mcap"
    write_mcap(path, table, chunk_bytes=1 << 18)
    spec = InputSpec(path=path)
    fast, _ = read_input(spec)
    batches = pa.concat_tables([b for b, _ in iter_input(spec, batch_rows=2_000)])
    monkeypatch.setattr(decoded, "_uniform_cdr", lambda *args: None)
    monkeypatch.setattr(table_buffer, "_zeros_only", lambda column: False)
    general, _ = read_input(spec)
    assert fast.schema == general.schema and fast.num_rows == n
    for name in general.column_names:
        if pa.types.is_string(general.schema.field(name).type):
            assert fast.column(name).equals(general.column(name)), name
            assert batches.column(name).equals(general.column(name)), name
        else:
            np.testing.assert_array_equal(_bits(fast.column(name)), _bits(general.column(name)))
            np.testing.assert_array_equal(_bits(batches.column(name)), _bits(general.column(name)))
    assert _bits(fast.column("accel_cov"))[25_000 * 9 + 8] == 1 << 63  # -0.0 kept
    assert (fast.column("frame_id").to_numpy(zero_copy_only=False) == frames).all()


@pytest.mark.parametrize("frames", [["imu_a"] * 6, ["imu_a", "imu_a", "imu_b", "imu_a"], [""] * 3])
def test_uniform_cdr_decode_equals_the_general_decoder(frames):
    """Evenly spaced CDR messages of one length: the few-call decoder gives what the general
    one gives, and leaves a chunk whose frame_ids differ (same length) to it."""
    from imupipe.readers import cdr, decoded

    rng = np.random.default_rng(len(frames))
    fields = {name: rng.normal(size=(1, c)) for name, c in cdr.FIELDS["sensor_msgs/msg/Imu"]}
    rows = [
        cdr.encode("sensor_msgs/msg/Imu", np.array([T0 + i]), f.encode(), fields)[0]
        for i, f in enumerate(frames)
    ]
    buf = np.concatenate(rows)
    size = len(rows[0])
    starts = np.arange(len(rows), dtype=np.int64) * size
    lengths = np.full(len(rows), size)
    slots = [(first, count) for _, first, count in decoded.COLUMNS["imu"]]
    stamp, frame, values = cdr.decode(buf, starts, lengths, "sensor_msgs/msg/Imu", "cdr", slots)
    uniform = decoded._uniform_cdr(buf, starts, lengths, "sensor_msgs/msg/Imu", slots)
    if len(set(frames)) > 1:
        assert uniform is None
        return
    assert uniform is not None
    np.testing.assert_array_equal(uniform[0], stamp)
    assert uniform[1].equals(frame) and uniform[3] == frames[0]
    for got, want in zip(uniform[2], values, strict=True):
        np.testing.assert_array_equal(got, want)
