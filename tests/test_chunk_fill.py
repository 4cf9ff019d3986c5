"""The compiled pass over MCAP chunks (``readers/_chunks.c``, :mod:`imupipe.readers.chunk_fill`)
gives the numpy path's tables, byte for byte.

Every file is read twice, with the compiled helper and with ``IMUPIPE_PURE_PYTHON=1`` (the numpy
path, the fallback): ``read_input`` (what ``run`` reads) and ``iter_input``'s batches (what
``convert`` reads) must be the same Arrow bytes, schema metadata included, with the same
warnings. The files: the MCAP conformance suite's layouts written around ``sensor_msgs/msg/Imu``
and ``Temperature`` messages (padded records, no summary, unchunked, two channels on one topic,
log times out of order), ROS 2 bags in MCAP storage, and logs that reach each branch of the
fill (a column of zeros that gets values mid-file, -0.0, the "no data" marks of a sensor
absent, an Imu stream with a 1 Hz topic beside it, frame_ids of several lengths). The helper's
own checks (a record of another channel, a damaged record, rows past a column) are tested on
the functions.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.ipc  # noqa: F401
import pytest

from imupipe.pipeline.simulate import write_log
from imupipe.readers import chunk_fill
from imupipe.readers.dispatch import iter_input, read_input
from imupipe.readers.mcap.fast import McapFile
from imupipe.readers.record_walk import PURE_PYTHON_ENV
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import make_table

T0 = 1_700_000_000_000_000_000


@pytest.fixture(autouse=True)
def _built():
    try:
        from imupipe.readers import _chunks  # noqa: F401
    except ImportError:
        pytest.skip("the compiled helper is not built (python setup.py build_ext --inplace)")


def raw(table: pa.Table) -> bytes:
    """The table as Arrow IPC bytes, schema metadata included."""
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as w:
        w.write_table(table.combine_chunks())
    return sink.getvalue().to_pybytes()


def reads(path, monkeypatch, compiled: bool, batches: bool = True) -> tuple:
    """(table, warnings, batches, their warnings) of ``path`` on one path (``batches``: with
    ``iter_input``'s, else the table's only)."""
    if compiled:
        monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    else:
        monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    assert chunk_fill.compiled() == compiled
    spec = InputSpec(path=path)
    table, warnings = read_input(spec)
    if not batches:
        return raw(table), warnings
    batch_warnings: list[str] = []
    parts = [raw(t) for t, _ in iter_input(spec, batch_rows=3000, warnings=batch_warnings)]
    return raw(table), warnings, parts, batch_warnings


def assert_both_paths_equal(path, monkeypatch, batches: bool = True) -> None:
    compiled = reads(path, monkeypatch, True, batches)
    assert compiled == reads(path, monkeypatch, False, batches), path.name


def imu_log(n: int = 12_000, seed: int = 0, **kw) -> pa.Table:
    """n Imu messages at 400 Hz, one frame_id; what each branch of the fill needs:
    ``cov_from``: the gyro covariances zeros before that row, values after (a clean column that
    gets values mid-file), one accel covariance -0.0 (not a zero, bit for bit);
    ``absent``: accel "no data" (NaN, covariance[0] = -1) in rows ``absent``;
    ``temperature_hz``/``mag``: other streams beside the Imu (the gapped table)."""
    rng = np.random.default_rng(seed)
    t = T0 + np.round(np.arange(n) * 2.5e6).astype(np.int64)
    extra: dict = {"frame_id": pa.array(np.full(n, kw.get("frame", "imu_link")))}
    if "cov_from" in kw:
        gyro_cov = rng.normal(size=(n, 9))
        gyro_cov[: kw["cov_from"]] = 0.0
        accel_cov = np.zeros((n, 9))
        accel_cov[n // 3, 4] = -0.0
        extra["gyro_cov"] = pa.FixedSizeListArray.from_arrays(pa.array(gyro_cov.ravel()), 9)
        extra["accel_cov"] = pa.FixedSizeListArray.from_arrays(pa.array(accel_cov.ravel()), 9)
    valid = {}
    if "absent" in kw:
        valid["accel"] = np.ones(n, bool)
        valid["accel"][kw["absent"]] = False
    gyro = rng.normal(0, 0.01, (n, 3))
    accel = rng.normal(0, 0.1, (n, 3)) + [0, 0, 9.81]
    topics = {"imu": "/imu/data"}
    if not kw.get("temperature_hz") and not kw.get("mag"):
        return make_table(t, gyro=gyro, accel=accel, valid=valid, extra=extra,
                          metadata={"topics": topics})  # fmt: skip
    # other streams at their own rows, merged in time order
    parts = {"imu": t}
    if kw.get("temperature_hz"):
        m = int(n / 400 * kw["temperature_hz"])
        parts["temperature"] = T0 + 1_234 + np.round(np.arange(m) * 1e9 / kw["temperature_hz"])
        topics["temperature"] = "/imu/temperature"
    if kw.get("mag"):
        parts["mag"] = T0 + 7 + np.arange(n // 8, dtype=np.int64) * 20_000_000
        topics["mag"] = "/imu/mag"
    t_all = np.concatenate([p.astype(np.int64) for p in parts.values()])
    order = np.argsort(t_all, kind="stable")
    kind = np.repeat(np.arange(len(parts)), [len(p) for p in parts.values()])[order]
    k = len(t_all)
    masks = {s: kind == i for i, s in enumerate(parts)}
    imu = masks["imu"]
    g, a = np.zeros((k, 3)), np.zeros((k, 3))
    g[imu], a[imu] = gyro, accel
    if "accel" in valid:
        masks["accel"] = np.zeros(k, bool)
        masks["accel"][imu] = valid["accel"]
    frames = np.full(k, kw.get("frame", "imu_link"))
    return make_table(
        t_all[order],
        gyro=g,
        accel=a,
        mag=rng.normal(0, 3e-5, (k, 3)) if "mag" in parts else None,
        temperature=25 + rng.normal(0, 0.1, k) if "temperature" in parts else None,
        valid=masks,
        extra={"frame_id": pa.array(frames)},
        metadata={"topics": topics},
    )


LOGS = {
    "imu_only": {},
    "cov_mid_file": {"cov_from": 7_000},
    "accel_absent": {"absent": slice(2_000, 2_600)},
    "imu_temperature": {"temperature_hz": 1.0},
    "imu_mag_temperature_absent": {"temperature_hz": 3.0, "mag": True, "absent": [5, 9000]},
    "empty_frame_id": {"frame": ""},
    "utf8_frame_id": {"frame": "imu_λ"},
}


@pytest.mark.parametrize("name", list(LOGS))
@pytest.mark.parametrize("fmt", ["log.mcap", "log_mcap2"])
def test_compiled_fill_gives_the_numpy_tables(tmp_path, monkeypatch, name, fmt):
    path = tmp_path / fmt
    if fmt == "log.mcap":
        write_log(path, imu_log(**LOGS[name]))
    else:  # a ROS 2 bag in MCAP storage
        from imupipe.pipeline.writers.bag import write_ros2_bag

        write_ros2_bag(path, imu_log(**LOGS[name]), storage="mcap")
    assert_both_paths_equal(path, monkeypatch)
    # the compiled pass did read it (one layout per channel and chunk)
    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    mcap = path if fmt == "log.mcap" else next(path.glob("*.mcap"))
    file = McapFile(mcap)
    chunk = next(iter(file.chunks()))
    cid = next(c for c, info in file.channels.items() if info.topic == "/imu/data")
    assert chunk_fill.walk(chunk.buf, chunk.offsets[cid], cid, "imu") is not None


def test_conformance_layouts_of_imu_messages(tmp_path, monkeypatch):
    """The suite's feature combinations around Imu and Temperature messages (the 154 layouts
    of ``test_mcap_conformance``) read the same on both paths: every layout's table, and every
    fourth layout's batches too (in the interest of time: each feature is in many)."""
    import mcap_conformance as mc
    from test_mcap_conformance import imu_records

    layouts = list(mc.variants({"ImuMessages": imu_records()}))
    assert len(layouts) == 154
    for i, (fname, data) in enumerate(layouts):
        path = tmp_path / fname
        path.write_bytes(data)
        assert_both_paths_equal(path, monkeypatch, batches=i % 4 == 0)


def test_frame_ids_of_several_lengths_take_the_numpy_path(tmp_path, monkeypatch):
    from test_readers import multi_stream_table

    path = tmp_path / "log.mcap"
    write_log(path, multi_stream_table())
    assert_both_paths_equal(path, monkeypatch)


# --- the helper's own checks ------------------------------------------------------------------


def _chunk(tmp_path, n=500):
    path = tmp_path / "log.mcap"
    write_log(path, imu_log(n))
    file = McapFile(path)
    chunk = next(iter(file.chunks()))
    cid = next(iter(chunk.offsets))
    return chunk, cid


def test_walk_takes_one_layout_and_leaves_the_rest(tmp_path, monkeypatch):
    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    chunk, cid = _chunk(tmp_path)
    off = chunk.offsets[cid]
    piece = chunk_fill.walk(chunk.buf, off, cid, "imu")
    assert piece is not None
    log, pub, _, _ = chunk.records(cid)
    assert np.array_equal(piece.log, log) and np.array_equal(piece.pub, pub)
    assert piece.one_frame == "imu_link" and len(piece) == len(off)
    assert chunk_fill.walk(chunk.buf, off, cid + 1, "imu") is None  # another channel's
    assert chunk_fill.walk(chunk.buf, off, cid, "gyro") is None  # a split stream: numpy
    assert chunk_fill.walk(chunk.buf, off + 1, cid, "imu") is None  # not at a record
    assert chunk_fill.walk(chunk.buf, off[:0], cid, "imu") is None
    assert chunk_fill.walk(chunk.buf, np.array([len(chunk.buf) - 10]), cid, "imu") is None
    for byte, value in ((1, 0), (0, 1)):  # big-endian CDR; not CDR
        buf = chunk.buf.copy()
        buf[int(off[7]) + 31 + byte] = value
        assert chunk_fill.walk(buf, off, cid, "imu") is None
    buf = chunk.buf.copy()
    buf[int(off[3]) + 31 + 16] ^= 1  # another frame_id
    assert chunk_fill.walk(buf, off, cid, "imu") is None
    monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    assert chunk_fill.walk(chunk.buf, off, cid, "imu") is None  # the fallback asked for


def test_fill_writes_from_the_first_value_not_zero_and_checks_its_bounds(tmp_path, monkeypatch):
    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    chunk, cid = _chunk(tmp_path)
    piece = chunk_fill.walk(chunk.buf, chunk.offsets[cid], cid, "imu")
    want = piece.records.columns()
    n = len(piece)
    columns = {name: np.zeros((n + 5,) + v.shape[1:]) for name, v in want.items()}
    clean = {"orientation_x", "gyro_cov", "gyro_x"}
    runs = [(slice(0, 10), slice(0, 10)), (slice(10, n), slice(15, n + 5))]
    written, nan = chunk_fill.fill(piece.records, columns, clean, runs)
    assert written == {"gyro_x"} and nan == set()  # orientation_x and gyro_cov are zeros
    rows = np.r_[0:10, 15 : n + 5]
    for name, column in columns.items():
        assert np.array_equal(column[rows], want[name]), name
        assert not column[10:15].any()
    with pytest.raises(IndexError):
        chunk_fill.fill(piece.records, columns, set(), [(slice(0, n), slice(6, n + 6))])
    with pytest.raises(IndexError):
        chunk_fill.fill(piece.records, columns, set(), [(slice(0, n + 1), slice(0, n + 1))])


# --- chunks read as one group (issue 39) -------------------------------------------------------


def test_chunks_read_as_groups_give_the_tables_of_chunks_one_by_one(tmp_path, monkeypatch):
    """A whole-table read decodes chunks that lie back to back in one arena as one group: the
    same table as chunk by chunk (GROUP_BYTES 0), with decompression threads or without (no
    CPU free)."""
    from imupipe.readers.mcap import fast
    from imupipe.readers.mcap import reader as mcap_reader

    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    monkeypatch.setattr(fast, "no_spare_cpu", lambda: False)
    path = tmp_path / "log.mcap"  # above SMALL_FILE: read by the decompression threads
    write_log(path, imu_log(20_000, temperature_hz=3.0, mag=True, absent=[5, 9000]))
    assert path.stat().st_size > fast.SMALL_FILE
    source = mcap_reader.McapSource(path)
    groups = [c for c in source.file.chunks(mcap_reader.GROUP_BYTES) if c.parts]
    assert groups and len(groups[0].parts) >= 2
    by_topic = {"/imu/data": "imu", "/imu/mag": "mag", "/imu/temperature": "temperature"}
    stream_of: dict = {}
    pieces = source._decode_group(groups[0], by_topic, stream_of)
    assert pieces is not None and set(pieces) == {"imu", "mag", "temperature"}
    imu = next(cid for cid, stream in stream_of.items() if stream == "imu")
    assert len(pieces["imu"]) == sum(len(p.offsets.get(imu, ())) for p in groups[0].parts)
    grouped = reads(path, monkeypatch, True, batches=False)
    monkeypatch.setattr(mcap_reader, "GROUP_BYTES", 0)
    assert reads(path, monkeypatch, True, batches=False) == grouped
    monkeypatch.setattr(fast, "no_spare_cpu", lambda: True)
    monkeypatch.setattr(mcap_reader, "GROUP_BYTES", 4 << 20)
    assert reads(path, monkeypatch, True, batches=False) == grouped


def test_an_index_past_its_chunk_is_caught_inside_a_group(tmp_path, monkeypatch):
    """A message index entry of the first chunk pointing past the chunk's end lands on the next
    chunk's first record in the group's buffer: the group is not taken, and the chunk's error
    is the one read chunk by chunk gives."""
    from imupipe.readers.compression import BufferPool
    from imupipe.readers.errors import ReadError
    from imupipe.readers.mcap.fast import OP_CHUNK, OP_MESSAGE_INDEX, ChunkFields

    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    path = tmp_path / "log.mcap"
    write_log(path, imu_log())
    file = McapFile(path)
    with open(path, "rb") as fh:
        records = list(file._records(fh, 8, file.size))
    k = next(i for i, r in enumerate(records) if r[0] == OP_CHUNK)
    chunk_pos, body = records[k][1], records[k][2]
    size = ChunkFields.of(body, "").size
    op, index_pos, index = records[k + 1]
    assert op == OP_MESSAGE_INDEX and records[k + 2][0] == OP_CHUNK  # a chunk follows
    data = bytearray(path.read_bytes())
    last = index_pos + 9 + len(index) - 8  # the last entry's offset
    data[last : last + 8] = BufferPool.after(0, size).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    for compiled in (True, False):
        with pytest.raises(ReadError, match=f"chunk at byte {chunk_pos}: message index points"):
            reads(path, monkeypatch, compiled, batches=False)


@pytest.mark.parametrize("length", [1, 7, 9, 16, 17, 30])
def test_walk_compares_every_byte_of_a_frame_id(tmp_path, monkeypatch, length):
    """frame_ids of 1 to 16 bytes are compared as words, longer ones with memcmp: a record whose
    first or last frame_id byte differs takes the numpy path."""
    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    path = tmp_path / "log.mcap"
    write_log(path, imu_log(300, frame="f" * length))
    chunk = next(iter(McapFile(path).chunks()))
    cid = next(iter(chunk.offsets))
    off = chunk.offsets[cid]
    piece = chunk_fill.walk(chunk.buf, off, cid, "imu")
    assert piece is not None and piece.one_frame == "f" * length
    for at in (0, length - 1):
        buf = chunk.buf.copy()
        buf[int(off[5]) + 31 + 16 + at] = ord("g")
        assert chunk_fill.walk(buf, off, cid, "imu") is None, at


def test_no_spare_cpu_when_one_cpu_is_allowed_or_all_are_busy(monkeypatch):
    import os

    from imupipe.readers.compression import no_spare_cpu

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    assert no_spare_cpu()  # taskset -c 0
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert not no_spare_cpu()
    monkeypatch.setattr(os, "getloadavg", lambda: (1.4, 0.0, 0.0))
    assert not no_spare_cpu()  # one CPU free: the read itself is one of the load
    monkeypatch.setattr(os, "getloadavg", lambda: (1.6, 0.0, 0.0))
    assert no_spare_cpu()


def test_crc32_is_zlibs_at_every_length_and_alignment(monkeypatch):
    """The compiled CRC (carry-less multiply, 64-byte folds) is ``zlib.crc32``: every length
    from 0 to 300 bytes (the byte loop, one fold, the 16-byte folds, the tail) at 17
    alignments, from a start value too, and large buffers; the numpy path is zlib itself."""
    import zlib

    from imupipe.readers import _chunks

    if _chunks.crc32(b"") is None:
        pytest.skip("this CPU has no carry-less multiply: zlib.crc32 is used")
    rng = np.random.default_rng(5)
    data = rng.integers(0, 256, 400, dtype=np.uint8).tobytes()
    for n in range(301):
        for at in range(17):
            piece = data[at : at + n]
            assert _chunks.crc32(piece) == zlib.crc32(piece), (n, at)
            assert _chunks.crc32(piece, 0xDEADBEEF) == zlib.crc32(piece, 0xDEADBEEF), (n, at)
    big = rng.integers(0, 256, (1 << 20) + 77, dtype=np.uint8)
    assert _chunks.crc32(big[3:]) == zlib.crc32(big[3:])
    assert _chunks.crc32(np.zeros(1 << 16, np.uint8)) == zlib.crc32(bytes(1 << 16))
    for compiled in (True, False):
        if compiled:
            monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
        else:
            monkeypatch.setenv(PURE_PYTHON_ENV, "1")
        assert chunk_fill.crc32(memoryview(big)) == zlib.crc32(big)


def test_a_chunk_crc_mismatch_is_named_on_both_paths(tmp_path, monkeypatch):
    """A chunk whose stated CRC differs from its decompressed bytes' by one bit is a
    ReadError naming the chunk, with the compiled CRC and with zlib's."""
    from imupipe.readers.errors import ReadError

    path = tmp_path / "log.mcap"
    write_log(path, imu_log(3000))
    data = bytearray(path.read_bytes())
    pos = 8
    while data[pos] != 0x06:  # the first chunk record
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    data[pos + 9 + 24] ^= 0x10  # its uncompressed_crc field (after start, end, size)
    path.write_bytes(bytes(data))
    for compiled in (True, False):
        with pytest.raises(ReadError, match=f"chunk at byte {pos}: chunk CRC mismatch"):
            reads(path, monkeypatch, compiled, batches=False)


@pytest.mark.parametrize("threads", [False, True])
def test_chunks_prefilled_after_their_decompression_give_the_same_table(
    tmp_path, monkeypatch, threads
):
    """A table of one stream gets each chunk's values right after the chunk's decompression
    (``McapSource._prefill``): the same table as the chunks filled after the walk of their
    group (``prefills`` off), with and without decompression threads; also when the frame_id
    changes length mid-file (its chunks' pieces differ: the group is walked, or read chunk by
    chunk with the prefilled pieces) and when covariances start mid-file."""
    from imupipe.readers import table_buffer
    from imupipe.readers.mcap import fast
    from imupipe.readers.mcap import reader as mcap_reader

    monkeypatch.setattr(fast, "no_spare_cpu", lambda: not threads)
    whole = imu_log(20_000, cov_from=11_000)
    frames = np.where(np.arange(20_000) < 9_500, "imu_link", "imu_link_2")
    short = imu_log(20_000, cov_from=11_000).set_column(
        whole.schema.get_field_index("frame_id"), "frame_id", pa.array(frames)
    )
    calls: list[bool] = []
    prefill = table_buffer._Stream.prefill

    def counted(st, piece) -> bool:
        calls.append(prefill(st, piece))
        return calls[-1]

    monkeypatch.setattr(table_buffer._Stream, "prefill", counted)
    for name, table in (("same", whole), ("frames", short)):
        path = tmp_path / f"{name}.mcap"
        write_log(path, table)
        assert path.stat().st_size > fast.SMALL_FILE
        calls.clear()
        prefilled = reads(path, monkeypatch, True, batches=False)
        assert calls and all(calls), name  # every chunk prefilled
        monkeypatch.setattr(mcap_reader.McapSource, "prefills", False)
        assert reads(path, monkeypatch, True, batches=False) == prefilled, name
        monkeypatch.setattr(mcap_reader.McapSource, "prefills", True)
        assert reads(path, monkeypatch, False, batches=False) == prefilled, name


def test_a_prefilled_piece_added_at_other_rows_is_filled_again(tmp_path, monkeypatch):
    """Pieces prefilled in one order and added in another are filled again at the rows they
    are added at: the table of the pieces added without prefill."""
    from imupipe.readers.table_buffer import TableBuffer

    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    chunk, cid = _chunk(tmp_path, 500)
    off = chunk.offsets[cid]

    def table(prefill: bool) -> bytes:
        a = chunk_fill.walk(chunk.buf, off[:200], cid, "imu")
        b = chunk_fill.walk(chunk.buf, off[200:], cid, "imu")
        buffer = TableBuffer(["imu"], "header", {"imu": 500})
        if prefill:
            assert buffer.prefill("imu", b) and buffer.prefill("imu", a)
            assert not buffer.prefill("imu", b)  # no room left
        buffer.add({"imu": a})
        buffer.add({"imu": b})
        topics = {"imu": "/imu/data"}
        kw = {"source": "x", "fmt": "mcap", "topics": topics, "where": "x", "warnings": []}
        return raw(buffer.table(sort=True, **kw))

    assert table(True) == table(False)


def test_buffer_pool_takes_back_a_buffer_each_time_it_is_given(monkeypatch):
    """An arena taken again from the pool and filled is given back again (the pool once kept
    the ids of the buffers it had held, and refused an arena the second time: a new 4 MiB
    arena for every other group of chunks, 27 of them for a million Imu messages instead of
    2)."""
    import types

    from imupipe.readers import compression

    made = []
    numpy = types.SimpleNamespace(**vars(np))
    numpy.empty = lambda *a, **k: made.append(a) or np.empty(*a, **k)
    monkeypatch.setattr(compression, "np", numpy)
    pool = compression.BufferPool(1 << 16)
    for _ in range(32):  # two chunks per arena; each chunk done before the next is taken
        chunk = pool.take(1 << 15)
        pool.give(chunk)
        del chunk
    assert len(made) == 2  # the arena being filled is still held while the next is taken


@pytest.mark.parametrize("time", ["header", "log"])
@pytest.mark.parametrize(
    "case", ["equal", "pub_from_middle", "log_first_rows", "temperature_pub", "gapped_pub"]
)
def test_time_columns_equal_so_far_share_one_array(tmp_path, monkeypatch, time, case):
    """Time columns equal row for row are one array while they are (an MCAP's log and publish
    times, a writer's header stamps), their Arrow columns one buffer; a column that differs from
    some message on, or from the first, has its own, the same values as written; with a 1 Hz
    Temperature topic whose publish times differ (the large stream's shared column is split
    before the other stream's rows go in). Both paths."""
    table = imu_log(6_000, temperature_hz=1.0 if "pub" in case and case != "pub_from_middle" else 0)
    t = table["t_ns"].to_numpy()
    log, pub = t.copy(), t.copy()
    if case == "pub_from_middle":
        pub[len(t) // 2 :] += 7
    elif case == "log_first_rows":
        log[:3] += 1000
        pub = log.copy()
    elif case == "temperature_pub":
        pub[table["temperature"].is_valid().to_numpy(zero_copy_only=False)] += 5
    elif case == "gapped_pub":
        pub[table["gyro_x"].is_valid().to_numpy(zero_copy_only=False)] += 5
    table = table.append_column("log_time_ns", pa.array(log))
    table = table.append_column("publish_time_ns", pa.array(pub))
    path = tmp_path / "log.mcap"
    write_log(path, table)
    for compiled in (True, False):
        if compiled:
            monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
        else:
            monkeypatch.setenv(PURE_PYTHON_ENV, "1")
        out, _ = read_input(InputSpec(path=path, time=time))
        got = {c: out[c].to_numpy() for c in out.column_names if c.endswith("_ns")}
        order = np.argsort(t if time == "header" else log, kind="stable")
        assert np.array_equal(got["log_time_ns"], log[order])
        assert np.array_equal(got["publish_time_ns"], pub[order])
        assert np.array_equal(got["header_stamp_ns" if time == "log" else "t_ns"], t[order])
        shared = {c: out[c].chunk(0).buffers()[1].address for c in got}
        if case == "equal":
            assert len(set(shared.values())) == 1
        if case == "pub_from_middle":
            assert shared["publish_time_ns"] != shared["log_time_ns"]
            assert shared["log_time_ns"] == shared["t_ns"]
