"""Issue 24 (items 3 and 4): every ROS 2 and ROS 1 bag layout rosbag2 / rosbag write, read by
imupipe as ``rosbags``' ``AnyReader`` reads it.

The bags are written by rosbags' own writers (``tests/bag_variants.py``): ROS 2 with sqlite3 and
mcap storage, uncompressed and zstd-compressed per file and per message, the metadata rewritten
as every version rosbag2 wrote (1 to 9), split bags; ROS 1 with uncompressed, bz2 and lz4
chunks, indexed and unindexed (its index cut off, as an interrupted recording leaves it), and
the rosbag.js fixture of a bag without messages. For each, the differential check
(:func:`agree`): the same topics, types and counts as ``inspect`` lists them, every message's log
time and payload (carried over: ROS 2 bytes for bytes, ROS 1 converted to CDR field for field),
and the Imu / MagneticField values of the table, value for value.
"""

from __future__ import annotations

import collections
import json
import re
import shutil
from pathlib import Path

import bag_variants as bv
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imupipe.pipeline.convert.verify import input_counts
from imupipe.pipeline.inspect_log import inspect
from imupipe.readers.dispatch import detect_format, log_sources, read_input
from imupipe.readers.errors import ImupipeError, ReadError
from imupipe.readers.ros2.reader import read_metadata
from imupipe.readers.spec import InputSpec
from imupipe.readers.topics import normalize_type

from conftest import run_cli

DATA = Path(__file__).parent / "data" / "rosbag_peers"


def _plain(value):
    """A rosbags message as nested lists / dicts of numbers (the ROS 1 ``seq`` left out)."""
    if hasattr(value, "__dataclass_fields__"):
        return {
            k: _plain(getattr(value, k))
            for k in value.__dataclass_fields__
            if k not in ("seq", "__msgtype__")
        }
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def _decoded(deserialize, raw: bytes, typename: str):
    """The plain message, or None where the type's definition is not the typestore's (a
    ``rcl_interfaces/Log`` of an older distribution): then the bytes alone are compared."""
    try:
        return _plain(deserialize(raw, typename))
    except Exception:  # noqa: BLE001
        return None


def reference(path: Path) -> dict:
    """What rosbags' AnyReader reads: topic -> (type, [(log ns, plain message, raw bytes)]);
    ROS 2 messages are deserialized only where the Humble typestore knows their type (their
    bytes are compared), a bag without definitions gets that typestore.

    rosbags' bag-level reader yields no message of a connection whose QoS in
    ``metadata.yaml`` differs from the storage file's (rosbag2's own test bags of versions 4
    and 5, whose QoS strings the storage does not repeat), though it counts them: the messages
    are then taken from rosbags reading each storage file alone."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    ros1 = detect_format(path) == "ros1"
    paths = sorted(path.glob("*.bag")) if path.is_dir() and ros1 else [path]
    default = None if ros1 else get_typestore(Stores.ROS2_HUMBLE)
    out = _read_with(AnyReader(paths, default_typestore=default), default)
    stated = sum(c for _, c, _ in out.values())
    if not ros1 and path.is_dir() and stated and not any(m for _, _, m in out.values()):
        files = read_metadata(path).files
        if all(f.suffix in (".db3", ".mcap") for f in files):
            out = {}
            for f in files:
                for topic, (typ, count, msgs) in _read_with(
                    AnyReader([f], default_typestore=default), default
                ).items():
                    entry = out.setdefault(topic, (typ, 0, []))
                    out[topic] = (typ, entry[1] + count, entry[2] + msgs)
    return {topic: (typ, msgs) for topic, (typ, _, msgs) in out.items()}


def _read_with(reader, store) -> dict:
    """topic -> (type, stated count, [(log ns, plain message, raw bytes)]) of an AnyReader."""
    out: dict = {}
    with reader:
        for conn in reader.connections:
            typ, n, msgs = out.get(conn.topic, (conn.msgtype, 0, []))
            out[conn.topic] = (typ, n + conn.msgcount, msgs)
        for conn, t, raw in reader.messages():
            known = store is None or conn.msgtype in store.fielddefs
            msg = _decoded(reader.deserialize, raw, conn.msgtype) if known else None
            out[conn.topic][2].append((t, msg, bytes(raw)))
    return out


def ours(path: Path) -> tuple[dict, dict]:
    """(inspect's topics, topic -> [(log ns, plain message, CDR bytes)]) as imupipe reads them:
    every message of every topic, carried over (ROS 1 converted to ROS 2 CDR, deserialized with
    rosbags' Humble typestore where it knows the type)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    spec = InputSpec(path=path)
    listed = inspect(spec)["topics"]
    messages: dict = collections.defaultdict(list)
    sources = log_sources(spec)
    for src in sorted(sources, key=lambda s: s.first_time()):
        for _, raw, _ in src.chunks({}, carry=True, decode=False):
            for m in raw:
                known = m.schema_name in store.fielddefs
                msg = _decoded(store.deserialize_cdr, m.data, m.schema_name) if known else None
                messages[m.topic].append((m.log_time, msg, m.data))
    return listed, messages


def agree(path: Path) -> None:
    """imupipe reads ``path`` as rosbags' AnyReader does (see the module docstring)."""
    ref = reference(path)
    listed, got = ours(path)
    ros1 = detect_format(path) == "ros1"
    assert sorted(listed) == sorted(ref), path
    for topic, (typ, msgs) in ref.items():
        assert listed[topic]["type"] == normalize_type(typ), (path, topic)
        assert listed[topic]["count"] == len(msgs), (path, topic)
        mine = sorted(got[topic], key=lambda m: m[0])
        theirs = sorted(msgs, key=lambda m: m[0])
        assert [m[0] for m in mine] == [m[0] for m in theirs], (path, topic)
        pairs = [(a[1], b[1]) for a, b in zip(mine, theirs, strict=True)]
        same = [repr(a) == repr(b) for a, b in pairs if a is not None and b is not None]
        assert all(same), (path, topic)  # repr: NaN fields equal NaN
        if ros1:  # converted to CDR: compared field for field, every message
            assert all(a is not None and b is not None for a, b in pairs), (path, topic)
        if not ros1:
            assert [m[2] for m in mine] == [m[2] for m in theirs], (path, topic)
    sensors = {t for t, (typ, m) in ref.items() if typ == "sensor_msgs/msg/Imu" and m}
    if sensors:
        _table_agrees(path, ref)


def _table_agrees(path: Path, ref: dict) -> None:
    """The common table's Imu (and MagneticField) values equal the messages rosbags reads."""
    table, _ = read_input(InputSpec(path=path))
    imu = [m for t, (typ, ms) in ref.items() if typ == "sensor_msgs/msg/Imu" for m in ms]
    rows = table.filter(table.column("gyro_x").is_valid())
    imu.sort(key=lambda m: (m[1]["header"]["stamp"]["sec"], m[1]["header"]["stamp"]["nanosec"]))
    stamp = [
        m[1]["header"]["stamp"]["sec"] * 10**9 + m[1]["header"]["stamp"]["nanosec"] for m in imu
    ]
    np.testing.assert_array_equal(rows.column("t_ns").to_numpy(), stamp)
    np.testing.assert_array_equal(rows.column("log_time_ns").to_numpy(), [m[0] for m in imu])
    for col, field in (("gyro", "angular_velocity"), ("accel", "linear_acceleration")):
        want = np.array([[m[1][field][a] for a in "xyz"] for m in imu])
        got = np.stack([rows.column(f"{col}_{a}").to_numpy() for a in "xyz"], axis=1)
        np.testing.assert_array_equal(got, want)
    mags = [m for t, (typ, ms) in ref.items() if typ == "sensor_msgs/msg/MagneticField" for m in ms]
    if mags and "mag_x" in table.column_names:
        rows = table.filter(table.column("mag_x").is_valid())
        mags.sort(key=lambda m: m[0])
        want = np.array([[m[1]["magnetic_field"][a] for a in "xyz"] for m in mags])
        got = np.stack([rows.column(f"mag_{a}").to_numpy() for a in "xyz"], axis=1)
        np.testing.assert_array_equal(got, want)


# ---------------------------------------------------------------- the bags written by rosbags


@pytest.fixture(scope="module")
def ros2_bags(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ros2")
    bags = {}
    for storage, mode in bv.ROS2_VARIANTS:
        bags[f"{storage}-{mode}"] = bv.write_ros2(d / f"{storage}_{mode}", storage, mode)
    for version in range(1, 9):
        for key in ("sqlite3-none", "mcap-message"):
            if version < 3 and key.endswith("message"):
                continue  # compression came with version 3
            name = f"{key}-v{version}"
            bags[name] = bv.with_version(bags[key], d / name.replace("-", "_"), version)
    for storage, mode in (("sqlite3", "file"), ("mcap", "message"), ("mcap", "file")):
        parts = [
            bv.write_ros2(d / f"part{k}_{storage}_{mode}", storage, mode, n=120, seed=k + 5)
            for k in range(3)
        ]
        bags[f"{storage}-{mode}-split"] = bv.split(parts, d / f"split_{storage}_{mode}")
    return bags


@pytest.fixture(scope="module")
def ros1_bags(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ros1")
    bags = {}
    for comp in bv.ROS1_VARIANTS:
        bags[comp] = bv.write_ros1(d / f"{comp}.bag", comp)
    return bags


def unindexed(bag: Path, dst: Path, cut: int = 0) -> Path:
    """``bag`` as an interrupted recording leaves it: ``index_pos`` 0, no index section, and
    ``cut`` more bytes cut off its end."""
    data = bytearray(bag.read_bytes())
    at = data.index(b"index_pos=") + len(b"index_pos=")
    index_pos = int.from_bytes(data[at : at + 8], "little")
    data[at : at + 8] = bytes(8)
    dst.write_bytes(bytes(data[: index_pos - cut]))
    return dst


@pytest.mark.parametrize("mode", ["none", "file", "message"])
@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_ros2_compression_agrees_with_rosbags(ros2_bags, storage, mode):
    agree(ros2_bags[f"{storage}-{mode}"])


@pytest.mark.parametrize("version", range(1, 9))
def test_ros2_every_metadata_version_agrees_with_rosbags(ros2_bags, version):
    for key in ("sqlite3-none", "mcap-message"):
        name = f"{key}-v{version}"
        if name in ros2_bags:
            agree(ros2_bags[name])


@pytest.mark.parametrize("key", ["sqlite3-file", "mcap-message", "mcap-file"])
def test_ros2_split_bags_agree_with_rosbags(ros2_bags, key):
    bag = ros2_bags[f"{key}-split"]
    assert len(log_sources(InputSpec(path=bag))) == 3
    agree(bag)


@pytest.mark.parametrize("comp", bv.ROS1_VARIANTS)
def test_ros1_chunk_compression_agrees_with_rosbags(ros1_bags, comp):
    agree(ros1_bags[comp])


@pytest.mark.parametrize("comp", bv.ROS1_VARIANTS)
def test_ros1_unindexed_bag_reads_as_its_indexed_original(ros1_bags, comp, tmp_path):
    """rosbags refuses an unindexed bag; imupipe scans it, warns, and reads every message of
    the original (that rosbags reads)."""
    bag = unindexed(ros1_bags[comp], tmp_path / "unindexed.bag")
    with pytest.raises(Exception, match="not indexed"):
        reference(bag)
    ref = reference(ros1_bags[comp])
    listed, got = ours(bag)
    assert {t: e["count"] for t, e in listed.items()} == {t: len(m) for t, (_, m) in ref.items()}
    for topic, (_, msgs) in ref.items():
        assert [m[:2] for m in got[topic]] == [m[:2] for m in msgs], topic
    table, warnings = read_input(InputSpec(path=bag))
    assert any("not indexed" in w and "scanning" in w for w in warnings), warnings
    want, _ = read_input(InputSpec(path=ros1_bags[comp]))
    assert table.equals(want)
    said: list[str] = []
    assert input_counts(bag, "ros1", said) is None  # convert counts what it reads, and warns
    assert len(said) == 1 and said[0].startswith("the bag is not indexed"), said


@pytest.mark.parametrize("comp", bv.ROS1_VARIANTS)
def test_ros1_cut_off_recording_keeps_the_messages_before_the_cut(ros1_bags, comp, tmp_path):
    """An unindexed bag cut inside its last chunk: the chunks before it are read, the cut is
    warned about; cut just after the last chunk (its IndexData gone), the chunk is walked."""
    full = reference(ros1_bags[comp])
    data = ros1_bags[comp].read_bytes()
    at = data.index(b"index_pos=") + len(b"index_pos=")
    index_pos = int.from_bytes(data[at : at + 8], "little")
    # the last chunk record starts at the last b"op=\x05" header before the index
    last_chunk = data.rfind(b"op=\x05", 0, index_pos)
    last_chunk = data.rfind(b"compression=", 0, last_chunk + 1) - 4 - 4
    for cut in (3000, 50):
        bag = unindexed(ros1_bags[comp], tmp_path / f"cut{cut}.bag", cut=cut)
        listed, got = ours(bag)
        table, warnings = read_input(InputSpec(path=bag))
        assert any("cut off" in w for w in warnings), warnings
        for topic, (_, msgs) in full.items():
            mine = [m[:2] for m in got.get(topic, [])]
            assert mine == [m[:2] for m in msgs[: len(mine)]], topic  # a prefix, in order
            assert listed[topic]["count"] == len(mine)
        n = sum(len(v) for v in got.values())
        total = sum(len(m) for _, m in full.values())
        # a 50-byte cut loses only IndexData records: the last chunk is walked, nothing lost
        assert (n == total) if cut == 50 else (0 < n < total), (cut, n, total)
    del last_chunk


def interrupted(bag: Path, dst: Path, cut: int = 0) -> Path:
    """``bag`` as ``rosbag record`` leaves it when stopped while writing its last chunk: no
    index, the bag header's ``index_pos`` 0, the last chunk's header with the place-holder sizes
    (0) rosbag writes when it opens a chunk, its records (compressed or not) to the end of the
    file, no IndexData after it; and ``cut`` more bytes cut off."""
    from imupipe.readers.ros1.reader import Ros1Bag, _fields

    data = bag.read_bytes()
    last = max(pos for pos, _, _ in Ros1Bag(bag).chunk_infos)
    hl = int.from_bytes(data[last : last + 4], "little")
    fields = _fields(data[last + 4 : last + 4 + hl], "test")
    dl = int.from_bytes(data[last + 4 + hl : last + 8 + hl], "little")
    fields["size"] = bytes(4)
    header = b"".join(
        len(k.encode() + b"=" + v).to_bytes(4, "little") + k.encode() + b"=" + v
        for k, v in fields.items()
    )
    body = data[last + 8 + hl : last + 8 + hl + dl]
    out = bytearray(data[:last] + len(header).to_bytes(4, "little") + header + bytes(4) + body)
    at = out.index(b"index_pos=") + len(b"index_pos=")
    out[at : at + 8] = bytes(8)
    dst.write_bytes(bytes(out[: len(out) - cut]))
    return dst


@pytest.mark.parametrize("comp", bv.ROS1_VARIANTS)
def test_ros1_recording_stopped_inside_a_chunk(ros1_bags, comp, tmp_path):
    """The chunk rosbag was writing is read up to its last complete record (whole, when its
    bytes all reached the file), with a warning; every chunk before it as usual."""
    full = reference(ros1_bags[comp])
    total = sum(len(m) for _, m in full.values())
    for cut in (0, 300):
        bag = interrupted(ros1_bags[comp], tmp_path / f"open{cut}.bag", cut)
        listed, got = ours(bag)
        _, warnings = read_input(InputSpec(path=bag))
        assert any("was not closed" in w for w in warnings), warnings
        for topic, (_, msgs) in full.items():
            mine = [m[:2] for m in got.get(topic, [])]
            assert mine == [m[:2] for m in msgs[: len(mine)]], topic  # a prefix, in order
            assert listed[topic]["count"] == len(mine)
        n = sum(len(v) for v in got.values())
        assert (n == total) if cut == 0 else (total - 40 < n < total), (comp, cut, n, total)


def test_ros1_bag_without_messages_is_empty_not_truncated():
    """rosbag.js's ``no-messages.bag`` fixture (Apache-2.0, tests/data/rosbag_peers): its index
    position is the end of the file. rosbags reads it as empty; so does imupipe."""
    bag = DATA / "rosbagjs_no-messages.bag"
    agree(bag)
    assert inspect(InputSpec(path=bag))["topics"] == {}
    assert input_counts(bag, "ros1") == {}
    proc = run_cli("inspect", bag)
    assert proc.returncode == 0, proc.stderr
    assert "topics: none" in proc.stdout
    with pytest.raises(ReadError, match="no sensor_msgs/Imu.*topics: none"):
        read_input(InputSpec(path=bag))  # what ``run`` says of it: nothing to calibrate


PEERS = sorted((DATA / "rosbag2").glob("*__*"))


@pytest.mark.parametrize("bag", PEERS, ids=[p.name for p in PEERS])
def test_rosbag2_own_test_bags_agree_with_rosbags(bag):
    """rosbag2's own test bags (Apache-2.0, tests/data/rosbag_peers): versions 4 to 8, both
    storages, split files, service events, an empty bag."""
    agree(bag)


def test_encrypted_ros1_bag_is_refused_in_one_line(tmp_path):
    """A bag whose header names an ``encryptor`` (rosbag's AES encryption), as rosbags refuses it."""

    def field(name: bytes, value: bytes) -> bytes:
        return len(name + b"=" + value).to_bytes(4, "little") + name + b"=" + value

    header = b"".join([
        field(b"op", b"\x03"), field(b"index_pos", bytes(8)), field(b"conn_count", bytes(4)),
        field(b"chunk_count", bytes(4)), field(b"encryptor", b"rosbag/AesCbcEncryptor"),
    ])  # fmt: skip
    bag = tmp_path / "secret.bag"
    padding = bytes(4096 - len(header))
    bag.write_bytes(
        b"#ROSBAG V2.0\n" + len(header).to_bytes(4, "little") + header
        + len(padding).to_bytes(4, "little") + padding
    )  # fmt: skip
    _bad(bag, bag, "encrypted bag .rosbag/AesCbcEncryptor. is not supported")


REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "logs"


@pytest.mark.parametrize(
    "name",
    [
        "madgwick_sparkfun_razor.bag",
        pytest.param("madgwick_ardrone_imu.bag", marks=pytest.mark.slow),
        pytest.param("madgwick_phidgets_imu_upside_down.bag", marks=pytest.mark.slow),
        pytest.param("rl_test1.bag", marks=pytest.mark.slow),
        pytest.param("rl_test2.bag", marks=pytest.mark.slow),
    ],
)
def test_real_ros1_bags_agree_with_rosbags(name):
    """The recorded bags of the shared test data (imu_tools, robot_localization)."""
    bag = REAL / name
    if not bag.exists():
        pytest.skip(f"{bag} is not here (the shared test data)")
    agree(bag)


@pytest.mark.parametrize("key", ["sqlite3-file", "sqlite3-message", "mcap-file"])
def test_ros2_storage_files_alone_read_as_their_bag(ros2_bags, key, tmp_path):
    """A storage file given alone, or a folder without ``metadata.yaml``: a ``.db3.zstd`` /
    ``.mcap.zstd`` is decompressed, a sqlite3 file whose payloads are zstd frames is read as
    message-compressed (its first payload tells): the same as the bag."""
    bag = ros2_bags[key]
    (storage,) = [f for f in bag.iterdir() if f.name != "metadata.yaml"]
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(storage, bare / storage.name)
    want, _ = read_input(InputSpec(path=bag))
    _, want_raw = ours(bag)
    for path in (bare / storage.name, bare):
        assert detect_format(path) == "ros2"
        got, _ = read_input(InputSpec(path=path))
        assert got.equals(want)
        _, raw = ours(path)
        assert raw == want_raw
    from imupipe.pipeline.convert.plan import find_logs

    assert find_logs([tmp_path], tmp_path / "out") == [(bare, Path("bare"))]  # convert finds it


# ---------------------------------------------------------------- one rule for every command


def test_metadata_version_10_is_accepted_by_inspect_run_and_convert(ros2_bags, tmp_path):
    """rosbag2 reads a metadata version by the fields it has, with no upper limit: so do
    ``inspect``, ``run`` and ``convert`` (rosbags refuses versions above 9)."""
    v9 = ros2_bags["sqlite3-message"]
    bag = bv.with_version(v9, tmp_path / "v10", 10)
    spec = InputSpec(path=bag)
    assert inspect(spec)["topics"] == inspect(InputSpec(path=v9))["topics"]
    assert read_input(spec)[0].equals(read_input(InputSpec(path=v9))[0])
    assert input_counts(bag, "ros2") == input_counts(v9, "ros2") == {
        "/imu/data": 300, "/imu/mag": 75, "/chatter": 43,
    }  # fmt: skip
    cal = tmp_path / "calibration.json"
    chain = [{"type": "gyro_calibration", "sensor": "gyro", "kind": "linear",
              "matrix": np.eye(3).tolist(), "offset": [0.01, 0.0, 0.0]}]  # fmt: skip
    cal.write_text(json.dumps({"imupipe_version": "test", "chain": chain, "results": {}}))
    from helpers import decode_mcap

    out = tmp_path / "out"
    proc = run_cli("convert", "--calibration", cal, "--out", out, bag, ros2_bags["mcap-file"])
    assert proc.returncode == 0, proc.stderr
    for name in ("v10", "mcap_file"):
        written = decode_mcap(out / f"{name}.mcap")
        assert {t: len(m) for t, m in written.items()} == {
            "/imu/data": 300, "/imu/mag": 75, "/chatter": 43,
        }, name  # fmt: skip


@pytest.mark.parametrize("mode", ["file", "message"])
def test_ros2_zstd_bags_stream_in_batches(ros2_bags, mode, monkeypatch):
    """``convert``'s bounded-memory batches of a compressed bag hold every message once."""
    from imupipe.readers.dispatch import iter_input
    from imupipe.readers.ros2 import reader as ros2_reader

    monkeypatch.setattr(ros2_reader, "BLOCK_ROWS", 64)
    bag = ros2_bags[f"sqlite3-{mode}"]
    table, _ = read_input(InputSpec(path=bag))
    batches = list(iter_input(InputSpec(path=bag), batch_rows=50))
    assert len(batches) > 2
    assert sum(t.num_rows for t, _ in batches) == table.num_rows
    assert sum(len(raw) for _, raw in batches) == 43


def test_file_compressed_bag_leaves_no_temporary_file(ros2_bags, tmp_path, monkeypatch):
    """The decompressed copy lives in the temporary directory as long as its reader: none is
    left after a read, a carry-over, or a read that fails."""
    import gc
    import tempfile

    from imupipe.readers.dispatch import carry_over

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    for key in ("sqlite3-file", "mcap-file", "mcap-file-split"):
        spec = InputSpec(path=ros2_bags[key])
        read_input(spec)
        assert len(list(carry_over(spec))) == (43 if key != "mcap-file-split" else 18 * 3)
    with pytest.raises(ReadError):
        read_input(InputSpec(path=ros2_bags["mcap-file"], imu_topic="/nope"))
    gc.collect()
    assert list(tmp_path.glob("imupipe-bag-*")) == []


# ---------------------------------------------------------------- bad input: one line


@pytest.fixture(scope="module")
def damaged_seeds(ros1_bags, ros2_bags, tmp_path_factory) -> dict[str, bytes]:
    """The layouts added here, small, as bytes to damage: unindexed and interrupted ROS 1
    bags, a bare message-compressed .db3 and a bare .db3.zstd."""
    d = tmp_path_factory.mktemp("seeds")
    small = bv.write_ros1(d / "small.bag", "lz4", n=60)
    out = {
        "unindexed.bag": unindexed(small, d / "u.bag").read_bytes(),
        "open.bag": interrupted(
            bv.write_ros1(d / "s2.bag", "none", n=60), d / "o.bag"
        ).read_bytes(),
    }
    for key, name in (("sqlite3-message", "message.db3"), ("sqlite3-file", "file.db3.zstd")):
        (f,) = [x for x in ros2_bags[key].iterdir() if x.name != "metadata.yaml"]
        out[name] = f.read_bytes()
    return out


@pytest.mark.parametrize("name", ["unindexed.bag", "open.bag", "message.db3", "file.db3.zstd"])
@settings(
    max_examples=25,
    derandomize=True,
    deadline=5000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    cut=st.floats(0.0, 1.0),
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), max_size=6),
)
def test_damaged_bags_are_read_or_one_line(damaged_seeds, tmp_path, name, cut, flips):
    """Truncated and flipped copies: read, or refused with one ReadError line (never a crash)."""
    from imupipe.readers.dispatch import carry_over

    data = bytearray(damaged_seeds[name])
    for where, xor in flips:
        data[min(int(where * len(data)), len(data) - 1)] ^= xor
    if cut < 0.5:
        data = data[: int(cut * 2 * len(data))]
    path = tmp_path / name
    path.write_bytes(bytes(data))
    for fn in (read_input, carry_over, inspect):
        try:
            fn(InputSpec(path=path))
        except ImupipeError as exc:
            assert "\n" not in str(exc)


def _bad(bag: Path, named: Path, match: str, listed: bool = False) -> None:
    """Reading ``bag`` is one ReadError line naming ``named``; ``inspect`` exits 2 with it
    (``listed``: inspect, which reads no payload, still lists the topics)."""
    with pytest.raises(ReadError, match=match) as info:
        read_input(InputSpec(path=bag))
    assert str(named) in str(info.value) and "\n" not in str(info.value)
    proc = run_cli("inspect", bag)
    if listed:
        assert proc.returncode == 0, proc.stderr
        return
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and re.search(match, proc.stderr), proc.stderr


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_truncated_zstd_file_is_one_line(ros2_bags, storage, tmp_path):
    bag = tmp_path / "bag"
    shutil.copytree(ros2_bags[f"{storage}-file"], bag)
    (f,) = bag.glob("*.zstd")
    f.write_bytes(f.read_bytes()[:-100])
    _bad(bag, f, "truncated zstd file")
    f.write_bytes(b"not a zstd frame" * 20)
    _bad(bag, f, "corrupt zstd file")
    # whole zstd, of a storage file cut in half: the storage's own error, naming the .zstd
    import zstandard

    with zstandard.ZstdDecompressor().stream_reader(
        (ros2_bags[f"{storage}-file"] / f.name).read_bytes()
    ) as reader:
        plain = reader.read()
    f.write_bytes(zstandard.ZstdCompressor().compress(plain[: len(plain) // 2]))
    _bad(bag, f, "truncated|corrupt")


def test_corrupt_zstd_message_is_one_line(ros2_bags, tmp_path):
    import sqlite3

    bag = tmp_path / "bag"
    shutil.copytree(ros2_bags["sqlite3-message"], bag)
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as con:
        con.execute("UPDATE messages SET data = substr(data, 1, 10) WHERE id = 5")
    _bad(bag, db, "zstd", listed=True)


def test_bad_metadata_is_one_line(ros2_bags, tmp_path):
    bag = tmp_path / "bag"
    shutil.copytree(ros2_bags["sqlite3-message"], bag)
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    meta.write_text(text.replace("compression_format: zstd", "compression_format: lz4"))
    _bad(bag, meta, "compression format 'lz4' is not supported")
    meta.write_text(text.replace("storage_identifier: sqlite3", "storage_identifier: hdf5"))
    _bad(bag, meta, "storage 'hdf5' is not supported")
    meta.write_text(text)
    (db,) = bag.glob("*.db3")
    db.unlink()
    with pytest.raises(ReadError, match="storage file .* is missing"):
        read_input(InputSpec(path=bag))
