"""Issue 39: imupipe's own parse of a ULog's records (``imupipe.readers.ulog.records``, the
record walk compiled in ``readers/_records.c``) gives pyulog's result, attribute for attribute
and array for array (dtype and bytes), on every ULog of ``tests/data`` and
``../shared/data``; the pure-Python walk gives the compiled walk's bytes; the records pyulog
decodes without a word (dropouts, logging, sync, changed parameters, info, appended data, a
last record cut by the end of the file) are read as pyulog reads them, and a file the parse does
not handle (damage pyulog reports) is left to pyulog.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from pyulog import ULog

from imupipe.readers import record_walk
from imupipe.readers.ulog import reader, records
from imupipe.readers.ulog.reader import READ_TOPICS, UlogFile, _TopicFilter

from conftest import SHARED, TEST_DATA

OURS = sorted(TEST_DATA.rglob("*.ulg"))
THEIRS = sorted(SHARED.rglob("*.ulg")) if SHARED.exists() else []
SMALL = TEST_DATA / "px4_ulog" / "sample_log_small.ulg"


def _compiled():
    try:
        from imupipe.readers import _records
    except ImportError:
        pytest.skip("the compiled helper is not built (python setup.py build_ext --inplace)")
    return _records


def assert_same(ref: ULog, own: ULog) -> None:
    """pyulog's own comparison of every attribute it holds, and each array's dtype and bytes,
    and the value types of the parameters and infos."""
    assert ref == own
    assert [(d.name, d.multi_id, d.msg_id) for d in ref.data_list] == [
        (d.name, d.multi_id, d.msg_id) for d in own.data_list
    ]
    for a, b in zip(ref.data_list, own.data_list, strict=True):
        assert list(a.data) == list(b.data)
        for k in a.data:
            assert a.data[k].dtype == b.data[k].dtype, (a.name, k)
            assert a.data[k].tobytes() == b.data[k].tobytes(), (a.name, k)
    for attr in ("initial_parameters", "msg_info_dict"):
        assert [(k, type(v)) for k, v in getattr(ref, attr).items()] == [
            (k, type(v)) for k, v in getattr(own, attr).items()
        ]
    assert ref.last_timestamp == own.last_timestamp
    assert [(d.timestamp, d.duration) for d in ref.dropouts] == [
        (d.timestamp, d.duration) for d in own.dropouts
    ]


def _compare(path: Path, names) -> None:
    got = records.parse(path, None if names is None else set(names))
    assert got is not None, f"{path}: the own parse left the file to pyulog"
    own, seen, cut = got
    ref = ULog(str(path), message_name_filter_list=None if names is None else list(names))
    assert_same(ref, own)
    if names is not None:  # the topics pyulog was asked about: every subscription's name
        asked = _TopicFilter(names)
        ULog(str(path), message_name_filter_list=asked)
        assert seen == asked.seen
    assert cut is None


@pytest.mark.parametrize("path", OURS + THEIRS, ids=lambda p: p.name)
def test_every_ulog_is_pyulogs(path):
    """Every ULog of tests/data and ../shared/data, the reader's topics and every topic."""
    for names in (READ_TOPICS, None):
        _compare(path, names)


def test_shared_logs_are_there():
    if not THEIRS:
        pytest.skip(f"shared data not present: {SHARED} (docs/how-to/test-data.md)")
    assert len(THEIRS) >= 7


@pytest.mark.parametrize("path", OURS, ids=lambda p: p.name)
def test_pure_python_walk_is_the_compiled_walk(path, monkeypatch):
    """The pure-Python walk and gather give the compiled helper's bytes (whole file, sections,
    a cut end), and a parse without the helper gives the same arrays."""
    compiled = _compiled()
    buf = path.read_bytes()
    for start, limit in ((16, len(buf)), (16, len(buf) // 2), (16, len(buf) + 99), (0, 40)):
        assert compiled.ulog_walk(buf, start, limit) == record_walk.py_ulog_walk(buf, start, limit)
    odd = bytes(16) + _rec("D", b"") + _rec("X", b"\x01") + _rec("D", b"\x05\x00abc") + b"\x09"
    for start, limit in ((16, len(odd)), (16, 25), (17, len(odd))):
        assert compiled.ulog_walk(odd, start, limit) == record_walk.py_ulog_walk(odd, start, limit)
    offsets = record_walk.ulog_walk(buf, 16, len(buf)).offsets
    for skip, size in ((0, 3), (5, 8), (3, 0)):
        assert bytes(compiled.gather(buf, offsets, skip, size)) == bytes(
            record_walk.py_gather(buf, offsets, skip, size)
        )
    with pytest.raises(IndexError):
        compiled.gather(buf, np.array([len(buf) - 1], dtype=np.int64), 0, 2)
    with pytest.raises(IndexError):
        record_walk.py_gather(buf, np.array([len(buf) - 1], dtype=np.int64), 0, 2)
    assert record_walk.compiled()
    fast, _, _ = records.parse(path, None)
    monkeypatch.setenv(record_walk.PURE_PYTHON_ENV, "1")
    assert not record_walk.compiled()
    slow, _, _ = records.parse(path, None)
    assert_same(fast, slow)


ODD_FORMATS = (
    b"a:float x;;int32_t[3] y;",  # an empty entry
    b"a:float  x;",  # two spaces: an empty field name
    b"a:float x y;",  # a third word, dropped
    b"a:x[0] y;",
    b"a:x[01] y;",
    b"a:x[3]z y;",  # text after the ']'
    b"a:x y",  # no ';' at the end
    b"a:",
    b":x y;",
    b"a:x[12345] y;",  # five digits: Python's split
    b"a:x[1 y;",
    b"a:x]1[ y;",
    b"a:x[] y;",
    b"a:x[a] y;",
    b"a:x;",  # no space
    b"a:b:c",
    b"ab",  # no ':'
    "\u00e9:x y;".encode(),  # not ASCII
)


@pytest.mark.parametrize("path", OURS, ids=lambda p: p.name)
def test_compiled_format_split_is_pythons(path):
    """The compiled split of the format records (``ulog_formats``) gives what the Python split
    (``records._format``, pyulog's) gives for every record it takes (every format of the logs),
    and leaves to Python (None) the ones it does not: odd forms, where Python's own error or
    result comes from."""
    compiled = _compiled()

    def both(buf, walk):
        at = walk.kinds == ord("F")
        offsets, sizes = walk.offsets[at], walk.sizes[at].astype(np.int64)
        split = compiled.ulog_formats(buf, offsets, sizes)
        for o, n, got in zip(offsets.tolist(), sizes.tolist(), split, strict=True):
            try:
                fmt = records._format(buf[o + 3 : o + 3 + n])
                ref = (fmt.name, fmt.fields)
            except (IndexError, ValueError) as exc:
                ref = exc
            yield ref, got

    buf = path.read_bytes()
    pairs = list(both(buf, record_walk.ulog_walk(buf, 16, len(buf))))
    assert pairs and all(got == ref for ref, got in pairs)
    odd = b"".join(_rec("F", d) for d in ODD_FORMATS)
    pairs = list(both(odd, record_walk.ulog_walk(odd, 0, len(odd))))
    assert len(pairs) == len(ODD_FORMATS)
    assert all(got is None or got == ref for ref, got in pairs)
    assert sum(got is not None for _, got in pairs) == 9  # the first nine: taken in C
    assert all(got is None for _, got in pairs[9:])


# -- records pyulog reads without a word, put into a real log -----------------------------------


def _rec(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _info(kind: str, key: str, value: bytes) -> bytes:
    name = f"{kind} {key}".encode()
    return bytes([len(name)]) + name + value


def _boundary(buf: bytes, kind: str = "D") -> int:
    """The offset of a record of ``kind`` in the middle of the data section."""
    offsets = record_walk.ulog_walk(buf, 16, len(buf)).offsets
    at = offsets[np.frombuffer(buf, np.uint8)[offsets + 2] == ord(kind)]
    return int(at[len(at) // 2])


def _both(path: Path, names=READ_TOPICS) -> tuple:
    """The reader's parse (own) and the parse it falls back to (pyulog's), checked equal (the
    record cut by the end of the file, the topics seen) and against plain pyulog."""
    own_filter, ref_filter = _TopicFilter(names), _TopicFilter(names)
    own, own_cut = reader._parse(path, own_filter)
    assert not hasattr(own, "damaged"), "the own parse left the file to pyulog"
    original = records.parse
    try:
        records.parse = lambda *args: None
        old, old_cut = reader._parse(path, ref_filter)
    finally:
        records.parse = original
    assert own_cut == old_cut
    assert own_filter.seen == ref_filter.seen
    assert_same(ULog(str(path), message_name_filter_list=list(names)), own)
    return own, own_cut


def test_dropouts_logging_sync_parameters_and_info(tmp_path):
    buf = SMALL.read_bytes()
    at = _boundary(buf)
    extra = b"".join(
        [
            _rec("O", struct.pack("<H", 321)),
            _rec("L", b"6" + struct.pack("<Q", 123456) + b"hello"),
            _rec("C", b"4" + struct.pack("<HQ", 7, 123457) + b"tagged"),
            _rec("S", ULog.SYNC_BYTES),
            _rec("P", _info("float", "CAL_GYRO0_XOFF", struct.pack("<f", 0.25))),
            _rec("P", _info("int32_t", "SENS_BOARD_ROT", struct.pack("<i", 4))),
            _rec("I", _info("char[5]", "ver_hw", b"NEW\xff!")),
            _rec("M", b"\x00" + _info("char[3]", "perf", b"abc")),
            _rec("M", b"\x01" + _info("char[3]", "perf", b"def")),
            _rec("Q", b"\x03" + _info("float", "CAL_ACC0_XOFF", struct.pack("<f", 1.5))),
        ]
    )
    path = tmp_path / "extra.ulg"
    path.write_bytes(buf[:at] + extra + buf[at:])
    own, cut = _both(path)
    assert cut is None
    assert any(d.duration == 321 for d in own.dropouts)
    assert own.changed_parameters[-2][1:] == ("CAL_GYRO0_XOFF", 0.25)
    assert own.changed_parameters[-2][0] > own.start_timestamp  # the last data stamp before it
    assert own.msg_info_dict["ver_hw"] == "NEW!"  # pyulog drops undecodable bytes
    assert own.logged_messages_tagged[7][0].message == "tagged"
    assert own.msg_info_multiple_dict["perf"][-1] == ["abc", "def"]


@pytest.mark.parametrize("left", [0, 1, 2, 3, 4, 9])
def test_a_record_cut_by_the_end_of_the_file(tmp_path, left):
    """The last record cut (header, or payload): the records before it, the cut where the
    reader's pyulog path puts it."""
    buf = SMALL.read_bytes()
    at = _boundary(buf)
    path = tmp_path / "cut.ulg"
    path.write_bytes(buf[: at + left])
    own, cut = _both(path)
    assert cut == (
        None if left == 0 else (at, 3 if left < 3 else 3 + buf[at] + 256 * buf[at + 1], left)
    )


def _appended(tmp_path: Path, section: bytes) -> Path:
    """SMALL with ``section`` appended after its end (flag bits' appended offset, incompat flag
    1), behind a record the offset cuts."""
    buf = bytearray(SMALL.read_bytes())
    assert buf[18] == ord("B")
    junk = struct.pack("<HB", 50, ord("D")) + bytes(10)  # a record the offset cuts
    new = bytearray(buf + junk + section)
    new[19 + 8] |= 1  # incompat_flags[0]: data appended
    struct.pack_into("<Q", new, 19 + 16, len(buf) + len(junk))
    path = tmp_path / "appended.ulg"
    path.write_bytes(bytes(new))
    return path


def test_appended_data(tmp_path):
    """Flag bits' appended offset: the section before it ends at the offset (a record crossing
    it is dropped, as pyulog drops it), the appended section is read on from the offset with its
    own subscriptions (pyulog 1.3 ends a section's subscriptions with the section)."""
    full = ULog(str(SMALL), message_name_filter_list=["sensor_combined"])
    combined = full.get_dataset("sensor_combined")
    n = combined.data["timestamp"].size
    sub = _rec("A", struct.pack("<BH", 5, 900) + b"sensor_combined")
    values = np.zeros(3, dtype=np.dtype([(k, v.dtype) for k, v in combined.data.items()]))
    values["timestamp"] = [10**9, 10**9 + 5, 10**9 + 9]
    data = b"".join(_rec("D", struct.pack("<H", 900) + v.tobytes()) for v in values)
    section = sub + data + _rec("I", _info("char[4]", "crash", b"dump"))
    own, cut = _both(_appended(tmp_path, section))
    assert cut is None
    got = {(d.name, d.multi_id): len(d.data["timestamp"]) for d in own.data_list}
    assert got[("sensor_combined", 5)] == 3
    assert got[("sensor_combined", 0)] == n  # both sections
    assert own.msg_info_dict["crash"] == "dump"
    assert own.last_timestamp == 10**9 + 9


def test_appended_data_of_an_earlier_subscription_is_left_to_pyulog(tmp_path):
    """Data of a subscription of the section before: pyulog has no subscription for it then
    ("no subscription found"): its parse, and the damage warning."""
    buf = SMALL.read_bytes()
    at = _boundary(buf)
    path = _appended(tmp_path, buf[at : at + 3 + buf[at] + 256 * buf[at + 1]])
    assert records.parse(path, set(READ_TOPICS)) is None


def _insert(tmp_path: Path, record: bytes, kind: str = "D") -> Path:
    buf = SMALL.read_bytes()
    at = _boundary(buf, kind)
    path = tmp_path / "odd.ulg"
    path.write_bytes(buf[:at] + record + buf[at:])
    return path


def _subscription(buf: bytes) -> bytes:
    at = _boundary(buf, "A")
    return buf[at : at + 3 + buf[at] + 256 * buf[at + 1]]


@pytest.mark.parametrize(
    "record",
    [
        _rec("X", b"abc"),  # a type pyulog does not know
        _rec("R", b"\x01\x00"),  # remove subscription: unknown to pyulog 1.3
        _rec("D", struct.pack("<H", 4321) + bytes(8)),  # no subscription
        _rec("D", b"\x00"),  # too short for a msg_id
        _rec("O", b"\x01"),  # a dropout pyulog cannot unpack: the end of its parse
    ],
    ids=["unknown", "remove", "unsubscribed", "short", "dropout"],
)
def test_what_pyulog_reports_is_left_to_it(tmp_path, record):
    path = _insert(tmp_path, record)
    assert records.parse(path, set(READ_TOPICS)) is None
    f = UlogFile(path, READ_TOPICS)  # pyulog's path: what it says becomes the damage warning
    assert f.damage_warning() is not None


def test_a_second_subscription_of_a_msg_id_is_left_to_pyulog(tmp_path):
    buf = SMALL.read_bytes()
    path = _insert(tmp_path, _subscription(buf))
    assert records.parse(path, set(READ_TOPICS)) is None


def test_a_data_record_of_another_size_is_left_to_pyulog(tmp_path):
    full = ULog(str(SMALL), message_name_filter_list=["sensor_combined"])
    msg_id = full.get_dataset("sensor_combined").msg_id
    path = _insert(tmp_path, _rec("D", struct.pack("<H", msg_id) + bytes(7)))
    assert records.parse(path, {"sensor_combined"}) is None
    # a topic not read is not checked by pyulog either: the own parse takes the file
    assert records.parse(path, {"vehicle_magnetometer"}) is not None


def _with_topic(tmp_path: Path, fmt: bytes, name: bytes) -> Path:
    """SMALL with one more format (before the first subscription) and its subscription."""
    buf = SMALL.read_bytes()
    offsets = record_walk.ulog_walk(buf, 16, len(buf)).offsets
    kinds = np.frombuffer(buf, np.uint8)[offsets + 2]
    first = int(offsets[np.flatnonzero(kinds == ord("A"))[0]])
    sub = _rec("A", struct.pack("<BH", 0, 3000) + name)
    path = tmp_path / "topic.ulg"
    path.write_bytes(buf[:first] + _rec("F", fmt) + sub + buf[first:])
    return path


def test_a_topic_not_read_is_checked_as_pyulog_makes_it(tmp_path):
    """A topic not read: its fields are checked as pyulog's dtype checks them. Field names with
    brackets that flatten to unique names: read; a name twice: left to pyulog (numpy refuses
    the dtype, pyulog calls the file corrupt)."""
    path = _with_topic(tmp_path, b"odd_topic:uint64_t timestamp;float a[0];float a;", b"odd_topic")
    own, _ = _both(path)
    assert 3000 in own._filtered_message_ids
    path = _with_topic(tmp_path, b"dup_topic:uint64_t timestamp;float x;float x;", b"dup_topic")
    assert records.parse(path, set(READ_TOPICS)) is None
    assert UlogFile(path, READ_TOPICS).damage_warning() is not None


def _in_definitions(tmp_path: Path, records_: bytes) -> Path:
    """SMALL with ``records_`` put just before its first subscription (definitions section)."""
    buf = SMALL.read_bytes()
    offsets = record_walk.ulog_walk(buf, 16, len(buf)).offsets
    kinds = np.frombuffer(buf, np.uint8)[offsets + 2]
    first = int(offsets[np.flatnonzero(kinds == ord("A"))[0]])
    path = tmp_path / "definitions.ulg"
    path.write_bytes(buf[:first] + records_ + buf[first:])
    return path


@pytest.mark.parametrize(
    ("record", "plain"),
    [
        (_rec("P", _info("double", "ODD_DOUBLE", struct.pack("<d", 1.5))), False),
        (_rec("P", _info("float", "CAL_\xe9", struct.pack("<f", 2.5))), False),
        (_rec("P", _info("int32_t", "CAL_GYRO0_ID", struct.pack("<i", -7))), True),  # again
        (_rec("P", _info("float", "A B", struct.pack("<f", 1.0))), False),  # pyulog keeps "A"
    ],
    ids=["double", "non-ascii", "twice", "space"],
)
def test_parameters_of_every_form_are_pyulogs(tmp_path, record, plain):
    """The parameters at start are decoded at once when all are plain (float or int32_t, an
    ASCII key without a space); one of another form sends them all the way pyulog's record
    class goes. Either way: pyulog's parameters, in its order, the last of a name winning."""
    path = _in_definitions(tmp_path, record)
    buf = path.read_bytes()
    raw = np.frombuffer(buf, np.uint8)
    offsets = record_walk.ulog_walk(buf, 16, len(buf)).offsets
    kinds = raw[offsets + 2]
    at = offsets[: np.flatnonzero(kinds == ord("A"))[0]]
    at = at[raw[at + 2] == ord("P")]
    sizes = raw[at].astype(np.int64) | (raw[at + 1].astype(np.int64) << 8)
    assert (records._plain_parameters(raw, at, sizes) is not None) == plain
    own, _ = _both(path)
    assert len(own.initial_parameters) > 900


def test_damaged_copies_are_pyulogs_or_left_to_it(tmp_path, capsys):
    """16 damaged copies of a log (bytes changed, half of them in the definitions and
    subscriptions at its start; cut): the own parse gives pyulog's result exactly, with pyulog
    finding nothing to say, or leaves the file to pyulog (None)."""
    rng = np.random.default_rng(39)
    data = SMALL.read_bytes()
    path = tmp_path / "damaged.ulg"
    taken = left = 0
    for i in range(16):
        damaged = bytearray(data)
        reach = len(data) if i % 2 else len(data) // 10
        for at in rng.integers(0, reach, rng.integers(1, 4)):
            damaged[at] = int(rng.integers(0, 256))
        path.write_bytes(bytes(damaged[: int(rng.integers(len(data) * 9 // 10, len(data) + 1))]))
        got = records.parse(path, set(READ_TOPICS))
        if got is None:
            left += 1
            continue
        capsys.readouterr()
        ref = ULog(str(path), message_name_filter_list=list(READ_TOPICS))
        assert capsys.readouterr().out == "", "pyulog spoke about a file the own parse took"
        assert not ref.file_corruption
        assert_same(ref, got[0])
        taken += 1
    assert taken >= 4 and left >= 1, (taken, left)  # both ways are exercised


def test_a_read_without_the_compiled_walk_is_the_same_table(monkeypatch):
    """imupipe's read of a ULog, with the compiled walk and without it: the same table."""
    from imupipe.readers.dispatch import read_input
    from imupipe.readers.spec import InputSpec

    _compiled()
    fast, warned = read_input(InputSpec(path=SMALL))
    monkeypatch.setenv(record_walk.PURE_PYTHON_ENV, "1")
    slow, said = read_input(InputSpec(path=SMALL))
    assert fast.schema.equals(slow.schema, check_metadata=True) and warned == said
    for name in fast.column_names:
        a, b = fast.column(name).combine_chunks(), slow.column(name).combine_chunks()
        assert a.type == b.type and a.null_count == b.null_count, name
        assert [x and x.to_pybytes() for x in a.buffers()] == [
            x and x.to_pybytes() for x in b.buffers()
        ], name
