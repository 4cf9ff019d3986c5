"""Issue 37: the compiled protobuf pass (``readers/_protoscan.c``) against the numpy scan
(``_ProtoScan`` in ``readers/message_fields.py``) and against protobuf's own parser as
``mcap-protobuf-support`` decodes an MCAP channel.

Both paths must give the same columns, bit for bit (dtype and bytes), and the same error (index
and reason) for a bad message; the values must equal the reference decoder's. The messages are
built with google.protobuf from a schema holding every number type, nested messages, packed and
unpacked repeated fields; their records are shuffled, split, repeated and mixed with unknown
fields of every wire type, as a writer other than protobuf's own may send them.
"""

from __future__ import annotations

import contextlib
import struct

import numpy as np
import pytest
from test_mapped_fields import _proto_classes, write_protobuf_mcap

from imupipe.readers import message_fields
from imupipe.readers.cdr import PayloadError
from imupipe.readers.message_fields import Leaf, protobuf_type, protoscan_compiled
from imupipe.readers.record_walk import PURE_PYTHON_ENV

pytestmark = pytest.mark.skipif(
    not protoscan_compiled(), reason="imupipe.readers._protoscan is not built (setup.py)"
)

SCALARS = {  # name: (FieldDescriptor type, number)
    "d": (1, 1),  # double
    "f": (2, 2),  # float
    "i64": (3, 3),
    "u64": (4, 4),
    "i32": (5, 5),
    "fx64": (6, 6),
    "fx32": (7, 7),
    "b": (8, 8),  # bool
    "u32": (13, 9),
    "sf32": (15, 10),
    "sf64": (16, 11),
    "s32": (17, 12),
    "s64": (18, 13),
}
REPEATED = {  # name: (type, number, packed)
    "rd": (1, 16, True),
    "ri": (17, 17, False),  # sint32, unpacked
    "ru": (4, 18, True),
    "rf": (2, 19, False),
    "rfx": (7, 20, True),
}
LEAVES = [
    *[(k,) for k in SCALARS],
    ("v", "x"),
    ("v", "y"),
    ("v", "z"),
    ("inner", "v", "z"),
    ("inner", "k"),
    ("inner", "r", 1),
    ("rd", 0),
    ("rd", 2),
    ("ri", 1),
    ("ru", 0),
    ("rf", 0),
    ("rf", 1),
    ("rfx", 2),
    ("d",),  # the same leaf twice
]
WIDTH = {"rd": 3, "ri": 2, "ru": 1, "rf": 2, "rfx": 3, "r": 2}
"""Elements the leaves need of each repeated field."""


def _all_class():  # noqa: ANN202
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fd = descriptor_pb2.FileDescriptorProto(name="acme/all.proto", package="acme", syntax="proto3")
    vec = fd.message_type.add(name="V3")
    for i, k in enumerate("xyz", 1):
        vec.field.add(name=k, number=i, type=1, label=1)
    inner = fd.message_type.add(name="Inner")
    inner.field.add(name="v", number=1, type=11, label=1, type_name=".acme.V3")
    inner.field.add(name="k", number=2, type=18, label=1)
    inner.field.add(name="r", number=3, type=1, label=3)
    msg = fd.message_type.add(name="All")
    for name, (typ, number) in SCALARS.items():
        msg.field.add(name=name, number=number, type=typ, label=1)
    msg.field.add(name="v", number=14, type=11, label=1, type_name=".acme.V3")
    msg.field.add(name="inner", number=15, type=11, label=1, type_name=".acme.Inner")
    for name, (typ, number, packed) in REPEATED.items():
        f = msg.field.add(name=name, number=number, type=typ, label=3)
        if not packed:
            f.options.packed = False
    msg.field.add(name="name", number=21, type=9, label=1)
    msg.field.add(name="blob", number=22, type=12, label=1)
    pool = descriptor_pool.Default()
    with contextlib.suppress(TypeError):  # already added by an earlier test in this process
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("acme.All"))


def _schema(cls) -> bytes:  # noqa: ANN001
    from mcap_protobuf.schema import build_file_descriptor_set

    return build_file_descriptor_set(cls).SerializeToString()


def _varint(v: int) -> bytes:
    v &= (1 << 64) - 1
    out = bytearray()
    while v >= 0x80:
        out.append(v & 0x7F | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


def _unknown(rng: np.random.Generator) -> bytes:
    """One record of a field the schema does not have (numbers 40..2000), any wire type."""
    number = int(rng.choice([40, 41, 300, 2000]))
    wire = int(rng.choice([0, 1, 2, 5]))
    tag = _varint(number << 3 | wire)
    if wire == 0:
        return tag + _varint(int(rng.integers(-(2**63), 2**63)))
    if wire == 1:
        return tag + rng.bytes(8)
    if wire == 5:
        return tag + rng.bytes(4)
    body = rng.bytes(int(rng.integers(0, 20)))
    return tag + _varint(len(body)) + body


def _value(rng: np.random.Generator, typ: int) -> object:
    """A random value of a protobuf type, extremes included; 0 (absent in proto3) often."""
    if rng.random() < 0.25:
        return 0
    if typ in (1, 2):
        special = [
            np.inf,
            -np.inf,
            -0.0,
            5e-324 if typ == 1 else 1e-45,
            1e300 if typ == 1 else 3e38,
        ]
        v = float(rng.choice(special)) if rng.random() < 0.2 else float(rng.normal(0, 100))
        return float(np.float32(v)) if typ == 2 else v
    if typ == 8:
        return bool(rng.integers(0, 2))
    lo, hi = {
        3: (-(2**63), 2**63 - 1),
        4: (0, 2**64 - 1),
        5: (-(2**31), 2**31 - 1),
        6: (0, 2**64 - 1),
        7: (0, 2**32 - 1),
        13: (0, 2**32 - 1),
        15: (-(2**31), 2**31 - 1),
        16: (-(2**63), 2**63 - 1),
        17: (-(2**31), 2**31 - 1),
        18: (-(2**63), 2**63 - 1),
    }[typ]
    if rng.random() < 0.2:
        return [lo, hi, -1 if lo < 0 else 1][int(rng.integers(0, 3))]
    return int(rng.integers(lo, hi, endpoint=True, dtype=np.uint64 if lo >= 0 else np.int64))


def _random_payload(cls, rng: np.random.Generator) -> bytes:  # noqa: ANN001
    """One message as records in random order: each field set alone and serialized (a
    concatenation parses as the merge), repeated fields split over records, a scalar now and
    then twice (the last wins), unknown fields between them."""
    pieces = []
    for name, (typ, _) in SCALARS.items():
        for _ in range(2 if rng.random() < 0.1 else 1):
            m = cls()
            setattr(m, name, _value(rng, typ))
            pieces.append(m.SerializeToString())
    m = cls()
    m.v.x, m.v.y, m.v.z = (_value(rng, 1) for _ in range(3))
    if rng.random() < 0.8:  # else absent: every field under it 0
        pieces.append(m.SerializeToString())
    m = cls()
    m.inner.k = _value(rng, 18)
    m.inner.v.z = _value(rng, 1)
    m.inner.r.extend(_value(rng, 1) for _ in range(WIDTH["r"] + int(rng.integers(0, 3))))
    pieces.append(m.SerializeToString())
    for name, (typ, _, _) in REPEATED.items():
        values = [_value(rng, typ) for _ in range(WIDTH[name] + int(rng.integers(0, 4)))]
        cut = int(rng.integers(0, len(values) + 1))
        for part in (values[:cut], values[cut:]):
            m = cls()
            getattr(m, name).extend(part)
            pieces.append(m.SerializeToString())
    m = cls()
    m.name, m.blob = "imu", rng.bytes(5)
    pieces.append(m.SerializeToString())
    pieces += [_unknown(rng) for _ in range(int(rng.integers(0, 4)))]
    return b"".join(pieces[i] for i in rng.permutation(len(pieces)))


def _batch(payloads: list[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lengths = np.array([len(p) for p in payloads], np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    return np.frombuffer(b"".join(payloads), np.uint8), starts, lengths


def _both(monkeypatch, mtype, buf, starts, lengths, leaves):  # noqa: ANN001, ANN202
    """(compiled, numpy): each the columns or the PayloadError's (index, reason)."""
    got = []
    for pure in ("", "1"):
        monkeypatch.setenv(PURE_PYTHON_ENV, pure)
        try:
            got.append(mtype.decode(buf, starts, lengths, leaves))
        except PayloadError as exc:
            got.append((exc.index, exc.reason))
    monkeypatch.delenv(PURE_PYTHON_ENV)
    return got


def _flags(mtype, buf, starts, lengths, leaves) -> np.ndarray:  # noqa: ANN001
    """The messages the compiled pass leaves to the numpy scan."""
    plan = message_fields._proto_plan(mtype.root, leaves)
    out = np.zeros((len(plan.floats), len(starts)), np.int64)
    flags = np.empty(len(starts), np.uint8)
    module = message_fields._protoscan()
    module.scan(buf, starts, lengths, plan.fields, plan.seqs, plan.slots, out, flags)
    return flags


def _same(a, b) -> bool:  # noqa: ANN001
    if isinstance(a, tuple) or isinstance(b, tuple):
        return a == b
    return all(x.dtype == y.dtype and x.tobytes() == y.tobytes() for x, y in zip(a, b, strict=True))


def test_random_messages_equal_numpy_scan_and_mcap_protobuf(tmp_path, monkeypatch):
    from mcap.reader import make_reader
    from mcap.writer import Writer
    from mcap_protobuf.decoder import DecoderFactory

    cls = _all_class()
    schema = _schema(cls)
    mtype = protobuf_type("acme.All", schema)
    rng = np.random.default_rng(37)
    payloads = [_random_payload(cls, rng) for _ in range(400)]
    leaves = [Leaf(p) for p in LEAVES]
    compiled, numpy = _both(monkeypatch, mtype, *_batch(payloads), leaves)
    assert _same(compiled, numpy)
    assert not _flags(mtype, *_batch(payloads), leaves).any()  # all read by the compiled pass
    with open(tmp_path / "all.mcap", "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("acme.All", "protobuf", schema)
        cid = w.register_channel("/all", "protobuf", sid)
        for i, p in enumerate(payloads):
            w.add_message(cid, log_time=i, data=p, publish_time=i)
        w.finish()
    with open(tmp_path / "all.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        ref = [m for _, _, _, m in reader.iter_decoded_messages()]
    assert len(ref) == len(payloads)
    for leaf, column in zip(LEAVES, compiled, strict=True):
        want = []
        for m in ref:
            value = m
            for part in leaf:
                value = value[part] if isinstance(part, int) else getattr(value, part)
            want.append(value)
        if column.dtype.kind == "f":
            assert np.array_equal(column, np.array(want, np.float64)), leaf
        else:  # uint64 and fixed64 as their int64 bits
            bits = np.array([int(v) & (2**64 - 1) for v in want], np.uint64).view(np.int64)
            assert np.array_equal(column, bits), leaf


def test_existing_protobuf_cases_equal(tmp_path, monkeypatch):
    """The IMU channel of tests/test_mapped_fields.py (Timestamp, nested Vector3, packed and
    unpacked repeated fields, sint32, absent fields) and each of its messages cut short."""
    from mcap.reader import make_reader

    write_protobuf_mcap(tmp_path / "pb.mcap", 200)
    with open(tmp_path / "pb.mcap", "rb") as fh:
        reader = make_reader(fh)
        payloads = [m.data for _, _, m in reader.iter_messages()]
    Imu = _proto_classes()
    mtype = protobuf_type("acme.Imu", _schema(Imu))
    leaves = [
        Leaf(p)
        for p in (
            ("timestamp", "seconds"),
            ("timestamp", "nanos"),
            ("gyro", "x"),
            ("gyro", "y"),
            ("gyro", "z"),
            ("accel", 0),
            ("accel", 2),
            ("mag", 1),
            ("temp",),
        )
    ]
    compiled, numpy = _both(monkeypatch, mtype, *_batch(payloads), leaves)
    assert _same(compiled, numpy) and not isinstance(compiled, tuple)
    assert not _flags(mtype, *_batch(payloads), leaves).any()
    ref = mtype.decode_reference(*_batch(payloads), leaves)
    assert all(np.array_equal(a, b) for a, b in zip(compiled, ref, strict=True))
    full = payloads[3]
    for cut in range(len(full)):
        batch = _batch([payloads[0], full[:cut], full])
        compiled, numpy = _both(monkeypatch, mtype, *batch, leaves)
        assert _same(compiled, numpy), cut
        if isinstance(compiled, tuple):
            assert compiled[0] == 1, cut


def test_odd_encodings_go_to_the_numpy_scan(monkeypatch):
    """Messages the compiled pass leaves (flags) are read by the numpy scan, in place: a
    nested message in two records (protobuf merges them), a packed run not a whole number of
    items, fewer elements than mapped, a group, a varint of 11 bytes; and read as protobuf reads
    them by both: a non-canonical bool, a mapped field number of another wire type (an unknown
    field to protobuf)."""
    cls = _all_class()
    mtype = protobuf_type("acme.All", _schema(cls))
    rng = np.random.default_rng(5)
    good = [_random_payload(cls, rng) for _ in range(6)]
    a, b = cls(), cls()
    a.v.x, b.v.y = 1.5, 2.5
    odd = {
        "merged": good[0] + a.SerializeToString() + b.SerializeToString(),
        "bool 2": good[1] + _varint(8 << 3) + _varint(2),
        "bool 2^32": good[1] + _varint(8 << 3) + _varint(2**32),
        "wire": good[2] + _varint(1 << 3 | 5) + struct.pack("<f", 1.0),
        "packed cut": good[3] + _varint(20 << 3 | 2) + _varint(5) + bytes(5),
        "group": good[4] + _varint(40 << 3 | 3) + _varint(40 << 3 | 4),
        "long varint": good[5] + _varint(3 << 3) + b"\xff" * 10 + b"\x01",
    }
    leaves = [Leaf(p) for p in LEAVES]
    for what, payload in odd.items():
        batch = _batch([good[0], payload, good[5]])
        compiled, numpy = _both(monkeypatch, mtype, *batch, leaves)
        assert _same(compiled, numpy), what
        left = what not in ("bool 2", "bool 2^32", "wire")
        assert _flags(mtype, *batch, leaves).tolist() == [0, left, 0], what
        if what in ("merged", "bool 2", "bool 2^32", "wire"):  # valid: as protobuf reads it
            ref = mtype.decode_reference(*batch, leaves)
            assert all(np.array_equal(x, y) for x, y in zip(compiled, ref, strict=True)), what
        if what in ("group", "long varint", "packed cut", "packed varint cut"):
            assert isinstance(compiled, tuple) and compiled[0] == 1, what
    short = cls()
    short.rd.extend([1.0, 2.0])  # rd[2] is mapped
    batch = _batch([good[0], short.SerializeToString()])
    compiled, numpy = _both(monkeypatch, mtype, *batch, leaves)
    assert compiled == numpy and compiled[0] == 1 and "fewer than" in compiled[1]


def test_damaged_messages_equal(monkeypatch):
    """Random messages with bytes changed, cut or added: both paths give the same columns, or
    both name the same bad message (the compiled pass checks every length it follows)."""
    cls = _all_class()
    mtype = protobuf_type("acme.All", _schema(cls))
    rng = np.random.default_rng(11)
    leaves = [Leaf(p) for p in LEAVES]
    errors = 0
    for _ in range(60):
        payloads = [_random_payload(cls, rng) for _ in range(4)]
        k = int(rng.integers(0, 4))
        data = bytearray(payloads[k])
        for _ in range(int(rng.integers(1, 4))):
            data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
        if rng.random() < 0.3:
            data = data[: int(rng.integers(0, len(data)))]
        payloads[k] = bytes(data)
        compiled, numpy = _both(monkeypatch, mtype, *_batch(payloads), leaves)
        assert _same(compiled, numpy)
        errors += isinstance(compiled, tuple)
    assert 0 < errors < 60  # some damage is still valid protobuf, some is not
