"""Any message's fields by path: a channel's definition parsed once, its messages decoded with numpy.

A :class:`MessageType` is the field tree of one channel's message type, built from the
definition the log carries:

- ROS 2 CDR and ROS 1 messages: the ``ros2msg`` / ``ros2idl`` / ``ros1msg`` text (MCAP schema,
  ROS 1 connection header, a ROS 2 bag's ``message_definitions``), parsed by rosbags
  (``get_types_from_msg``, ``get_types_from_idl``); types the text only names (``std_msgs/Header``,
  ``builtin_interfaces/Time``) come from rosbags' own store for the distribution.
- MCAP ``json`` channels: the ``jsonschema`` (``properties``, ``type``, ``items``).
- MCAP ``protobuf`` channels: the ``FileDescriptorSet`` (google.protobuf's descriptor pool).

:meth:`MessageType.decode` reads the wanted leaves (numeric fields, or one element of a numeric
array) of many messages at once from one buffer (a decompressed chunk), given each payload's
start and length:

- ROS (CDR, ROS 1): the definition is walked field by field with a vector of every message's
  current offset (a Python step per *field*, never per message). While every message has the
  same layout (one frame_id length...) the offset stays one number and each leaf is one strided
  view of the chunk; a string or sequence of varying length turns it into a per-message vector
  (one gather per leaf). CDR alignment (XCDR1: each primitive aligned to its size, counted from
  the end of the 4-byte encapsulation header) and byte order (the header's flag) as the OMG
  DDS-XTypes 1.3 spec (7.4.3) and rosbags' deserializer have them. Only a sequence of structs
  before a wanted leaf makes the layout one the walk cannot follow: those messages are read
  with rosbags' deserializer, one at a time.
- JSON: by template (:mod:`imupipe.readers.json_numbers`): messages with the text of a template
  message around their numbers have their numbers found and parsed in a few numpy passes and one
  Arrow cast per chunk; the others are joined as newline-delimited JSON and parsed by Arrow's
  JSON reader (``pyarrow.json``) with a schema holding only the wanted fields, and what Arrow
  refuses (``NaN``, ``Infinity``) by ``json``.
- Protobuf: the wire format (protobuf encoding spec: varint tags, wire types 0/1/2/5), nested
  messages as sub-ranges, packed and unpacked repeated fields, absent fields their proto3
  default (0), a record of another wire type than its field's an unknown field (as upb has
  it). With the optional extension ``imupipe.readers._protoscan`` (``readers/_protoscan.c``)
  each message's records are walked once in one compiled pass per chunk that writes the mapped
  fields into the columns (:func:`_decode_protobuf`); the messages it leaves, and all of them
  when it is not built or ``IMUPIPE_PURE_PYTHON=1``, are scanned in lockstep in numpy
  (:class:`_ProtoScan`), one tag per message per step, which gives the same columns and names a
  bad message. A nested message split over two records (protobuf merges them) is read by
  protobuf's parser.

Every decoder is tested equal to its reference library (rosbags, ``mcap``'s JSON and
``mcap-protobuf-support`` decoders) in ``tests/test_mapped_fields.py``.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from types import ModuleType

import numpy as np

from imupipe.readers.cdr import PayloadError, at, even_step, unaligned
from imupipe.readers.errors import ReadError
from imupipe.readers.record_walk import PURE_PYTHON_ENV

ROS_BASE: dict[str, str] = {
    "bool": "u1",
    "byte": "u1",
    "char": "u1",
    "octet": "u1",
    "int8": "i1",
    "uint8": "u1",
    "int16": "i2",
    "uint16": "u2",
    "int32": "i4",
    "uint32": "u4",
    "int64": "i8",
    "uint64": "u8",
    "float32": "f4",
    "float64": "f8",
}
"""ROS primitive types -> numpy dtype (byte order added per message)."""

SECONDS = ("sec", "secs", "seconds")
NANOS = ("nanosec", "nsec", "nsecs", "nanos")


@dataclass
class Node:
    """One field of a message type.

    ``kind``: ``number`` (``dtype`` set; an int or float), ``string``, ``struct`` (``children``),
    ``array`` (``count`` elements of ``item``), ``sequence`` (a length-prefixed run of ``item``),
    ``other`` (bytes, enums of protobuf...: never a value). ``number`` fields of protobuf carry
    their field ``tag`` and ``wire`` format (``varint``, ``zigzag``, ``<f8``...)."""

    name: str
    kind: str
    dtype: str = ""
    children: list[Node] = field(default_factory=list)
    item: Node | None = None
    count: int = 0
    type_name: str = ""
    tag: int = 0
    wire: str = ""

    def child(self, name: str) -> Node | None:
        for c in self.children:
            if c.name == name:
                return c
        return None

    def describe(self) -> str:
        if self.kind == "number":
            return self.dtype_name()
        if self.kind == "array":
            return f"{self.item.describe()}[{self.count}]"  # type: ignore[union-attr]
        if self.kind == "sequence":
            return f"{self.item.describe()}[]"  # type: ignore[union-attr]
        if self.kind == "struct":
            return self.type_name or "object"
        return self.kind if self.kind != "other" else self.type_name or "other"

    def dtype_name(self) -> str:
        return {
            "f8": "float64",
            "f4": "float32",
            "u1": "uint8",
            "i1": "int8",
            "i2": "int16",
            "u2": "uint16",
            "i4": "int32",
            "u4": "uint32",
            "i8": "int64",
            "u8": "uint64",
        }.get(self.dtype, self.dtype)


class NotFastPath(ValueError):
    """The walk cannot follow this layout (a sequence of structs or a wstring before a wanted
    field, a repeated protobuf message): the reference decoder reads it."""


@dataclass
class Leaf:
    """One scalar to read: the field path (names; an int indexes an array or sequence)."""

    path: tuple[str | int, ...]

    def __str__(self) -> str:
        return ".".join(str(p) for p in self.path)


class MessageType:
    """A channel's message type as a field tree (see the module docstring)."""

    def __init__(self, name: str, encoding: str, root: Node, source: object = None) -> None:
        self.name = name
        self.encoding = encoding
        """``cdr``, ``ros1``, ``json`` or ``protobuf``."""
        self.root = root
        self._source = source
        """What the reference decoder needs (rosbags types, the protobuf descriptor)."""
        self.json_shapes: dict[tuple, list] = {}
        """JSON: the templates of the batches read so far, per set of leaves (see
        :func:`imupipe.readers.json_numbers.decode_by_template`)."""
        self.proto_plans: dict[tuple, _ProtoPlan | None] = {}
        """Protobuf: the compiled pass's plan per set of leaves (None: the numpy scan reads
        them)."""

    # -- paths ------------------------------------------------------------------------------
    def node(self, path: tuple[str, ...]) -> Node | None:
        """The node at ``path`` (names; digits index an array or sequence), None when absent."""
        node = self.root
        for part in path:
            if node.kind in ("array", "sequence") and part.isdigit():
                if node.kind == "array" and int(part) >= node.count:
                    return None
                node = node.item  # type: ignore[assignment]
            else:
                found = node.child(part) if node.kind == "struct" else None
                if found is None:
                    return None
                node = found
        return node

    def leaves(self, max_items: int = 64) -> list[tuple[str, str]]:
        """Every field as (path, type), nested structs flattened (for ``inspect``)."""
        out: list[tuple[str, str]] = []

        def visit(node: Node, prefix: str) -> None:
            for c in node.children:
                path = f"{prefix}{c.name}"
                if c.kind == "struct" and c.children:
                    visit(c, path + ".")
                else:
                    out.append((path, c.describe()))

        visit(self.root, "")
        return out[:max_items]

    # -- decoding ---------------------------------------------------------------------------
    def decode(
        self, buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray, leaves: list[Leaf]
    ) -> list[np.ndarray]:
        """The value of each leaf for every message (int64 for integer fields, else float64).

        Raises :class:`imupipe.readers.cdr.PayloadError` for a payload that does not hold the
        type (too short, a sequence shorter than the index asked)."""
        starts = np.asarray(starts, np.int64)
        lengths = np.asarray(lengths, np.int64)
        if not len(starts):
            return [np.zeros(0) for _ in leaves]
        if self.encoding in ("cdr", "ros1"):
            try:
                return _RosWalk(self, buf, starts, lengths, leaves).run()
            except NotFastPath:
                return self.decode_reference(buf, starts, lengths, leaves)
        if self.encoding == "json":
            return _decode_json(self, buf, starts, lengths, leaves)
        if self.encoding == "protobuf":
            return _decode_protobuf(self, buf, starts, lengths, leaves)
        raise ReadError(f"message encoding '{self.encoding}' is not supported")

    def decode_reference(
        self, buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray, leaves: list[Leaf]
    ) -> list[np.ndarray]:
        """What :meth:`decode` gives, one message at a time with the reference library
        (rosbags for ROS; ``json`` for JSON; protobuf's own parser): the fallback for layouts
        the walk cannot follow, and the tests' reference."""
        rows: list[list] = [[] for _ in leaves]
        for i, (s, n) in enumerate(zip(starts.tolist(), lengths.tolist(), strict=True)):
            data = buf[s : s + n].tobytes()
            try:
                msg = self._deserialize(data)
                for j, leaf in enumerate(leaves):
                    value = msg
                    for part in leaf.path:
                        if isinstance(part, int) or isinstance(value, dict):
                            value = value[part]
                        else:
                            value = getattr(value, part)
                    rows[j].append(value)
            except (IndexError, KeyError, AttributeError, TypeError) as exc:
                raise PayloadError(i, f"field not found ({exc})") from None
            except Exception as exc:  # noqa: BLE001 - any deserializer failure is a bad payload
                raise PayloadError(i, f"cannot be decoded as {self.name} ({exc})") from None
        out = []
        for values in rows:
            ints = all(isinstance(v, int | np.integer) for v in values)
            if ints and any(v >= 1 << 63 for v in values):  # a uint64 past int64: its bits
                out.append(np.array([int(v) & ((1 << 64) - 1) for v in values], np.uint64))
                out[-1] = out[-1].view(np.int64)
                continue
            out.append(np.asarray(values, np.int64 if ints else np.float64))
        return out

    def _deserialize(self, data: bytes) -> object:
        if self.encoding == "cdr":
            return self._source.deserialize_cdr(data, self.name)  # type: ignore[union-attr]
        if self.encoding == "ros1":
            return self._source.deserialize_ros1(data, self.name)  # type: ignore[union-attr]
        if self.encoding == "json":
            import json

            return json.loads(data)
        msg = self._source()  # type: ignore[misc]
        msg.ParseFromString(data)
        return msg


# --- ROS definitions ----------------------------------------------------------------------


def ros_type(name: str, encoding: str, schema_encoding: str, text: str) -> MessageType:
    """The :class:`MessageType` of a ROS message type from its definition text (``ros2msg``,
    ``ros2idl`` or ``ros1msg``; empty: rosbags' own definition for the distribution, for
    standard types)."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    full = name if "/msg/" in name or name.count("/") != 1 else name.replace("/", "/msg/")
    base = get_typestore(Stores.ROS1_NOETIC if encoding == "ros1" else Stores.ROS2_HUMBLE)
    types: dict = {}
    if text.strip():
        if schema_encoding == "ros2idl":
            types = get_types_from_idl(text)
        else:
            types = get_types_from_msg(text, full)
    elif schema_encoding:  # a definition without fields (test_msgs/Empty)
        types = {} if full in base.fielddefs else {full: ([], [])}
    elif full not in base.fielddefs:
        raise ValueError(f"the log carries no definition of {full}")
    defs = {**base.fielddefs, **types}
    needed: dict = {}

    def need(typename: str) -> None:
        if typename in needed:
            return
        if typename not in defs:
            raise ValueError(f"no definition of {typename}")
        needed[typename] = defs[typename]
        for _, (kind, rest) in defs[typename][1]:
            for sub in _named(kind, rest):
                need(sub)

    need(full)
    store = get_typestore(Stores.EMPTY)
    store.register({k: v for k, v in needed.items() if k not in store.fielddefs})
    root = _ros_node(full, "", needed, encoding)
    return MessageType(full, encoding, root, store)


def _named(kind: object, rest: object) -> list[str]:
    """Type names a rosbags field definition refers to."""
    value = getattr(kind, "value", kind)
    if value == 2:  # NAME
        return [rest]  # type: ignore[list-item]
    if value in (3, 4):  # ARRAY, SEQUENCE
        (ikind, irest), _ = rest  # type: ignore[misc]
        return _named(ikind, irest)
    return []


def _ros_node(typename: str, name: str, defs: dict, encoding: str) -> Node:
    children = []
    for fname, (kind, rest) in defs[typename][1]:
        children.append(_ros_field(fname, kind, rest, defs, encoding))
    return Node(name, "struct", children=children, type_name=typename)


def _ros_field(name: str, kind: object, rest: object, defs: dict, encoding: str) -> Node:
    value = getattr(kind, "value", kind)
    if value == 1:  # BASE
        base = rest[0]  # type: ignore[index]
        if base in ROS_BASE:
            return Node(name, "number", ROS_BASE[base], type_name=base)
        return Node(name, "string" if base == "string" else "other", type_name=base)
    if value == 2:
        return _ros_node(rest, name, defs, encoding)  # type: ignore[arg-type]
    (ikind, irest), count = rest  # type: ignore[misc]
    item = _ros_field("", ikind, irest, defs, encoding)
    if value == 3:
        return Node(name, "array", item=item, count=int(count))
    return Node(name, "sequence", item=item)


class _RosWalk:
    """One batch of CDR or ROS 1 messages walked field by field (see the module docstring)."""

    def __init__(
        self,
        mtype: MessageType,
        buf: np.ndarray,
        starts: np.ndarray,
        lengths: np.ndarray,
        leaves: list[Leaf],
    ) -> None:
        self.cdr = mtype.encoding == "cdr"
        self.buf, self.starts, self.lengths = buf, starts, lengths
        self.mtype = mtype
        self.n = len(starts)
        self.even = even_step(starts)
        self.want: dict[tuple, int] = {}
        for i, leaf in enumerate(leaves):
            self.want.setdefault(tuple(leaf.path), i)
        self.prefixes = {p[:k] for p in self.want for k in range(len(p) + 1)}
        self.out: list[np.ndarray | None] = [None] * len(leaves)
        self.leaves = leaves
        self.remaining = set(self.want)
        self.order = "<"
        self.rel: int | np.ndarray = 4 if self.cdr else 0
        short = np.flatnonzero(lengths < (4 if self.cdr else 0))
        if len(short):
            raise PayloadError(int(short[0]), f"payload of {int(lengths[short[0]])} bytes")

    def run(self) -> list[np.ndarray]:
        if self.cdr:
            head = at(self.buf, self.starts, 0, "<u2", self.even)
            if np.any((head != 0x0100) & (head != 0x0000)):
                bad = int(np.flatnonzero((head != 0x0100) & (head != 0x0000))[0])
                raise PayloadError(bad, "not a CDR payload (bad encapsulation header)")
            if np.all(head == 0):
                self.order = ">"
            elif np.any(head == 0):
                raise NotFastPath("mixed byte orders")
        self.struct(self.mtype.root, ())
        for i, leaf in enumerate(self.leaves):
            if self.out[i] is None:
                self.out[i] = self.out[self.want[tuple(leaf.path)]]
        return self.out  # type: ignore[return-value]

    # offsets ------------------------------------------------------------------------------
    def align(self, size: int) -> None:
        if self.cdr and size > 1:
            self.rel = self.rel + (-(self.rel - 4)) % size

    def check(self, size: int | np.ndarray, what: str) -> None:
        over = np.flatnonzero(self.rel + size > self.lengths)
        if len(over):
            i = int(over[0])
            raise PayloadError(
                i, f"payload of {int(self.lengths[i])} bytes is too short for {what}"
            )

    def read(self, dtype: str, what: str) -> np.ndarray:
        dt = np.dtype(self.order + dtype)
        self.align(dt.itemsize)
        self.check(dt.itemsize, what)
        if isinstance(self.rel, int):
            values = at(self.buf, self.starts, self.rel, dt.str, self.even)
        else:
            values = unaligned(self.buf, dt)[self.starts + self.rel]
        self.rel = self.rel + dt.itemsize
        return values

    def skip(self, size: int | np.ndarray) -> None:
        self.rel = self.rel + size
        if isinstance(self.rel, np.ndarray) and bool(np.all(self.rel == self.rel[0])):
            self.rel = int(self.rel[0])

    # the walk -----------------------------------------------------------------------------
    def store(self, path: tuple, values: np.ndarray) -> None:
        i = self.want[path]
        kind = values.dtype.kind
        self.out[i] = values.astype(np.int64 if kind in "iub" else np.float64)
        self.remaining.discard(path)

    def struct(self, node: Node, path: tuple) -> None:
        for c in node.children:
            if not self.remaining:
                return
            self.field(c, (*path, c.name))

    def field(self, node: Node, path: tuple) -> None:
        what = f"{self.mtype.name} field {'.'.join(map(str, path))}"
        if node.kind == "number":
            if path in self.want:
                self.store(path, self.read(node.dtype, what))
            else:
                size = np.dtype(node.dtype).itemsize
                self.align(size)
                self.skip(size)
        elif node.kind == "string":
            length = self.read("u4", what).astype(np.int64)
            self.check(length, what)
            self.skip(length)
        elif node.kind == "struct":
            self.struct(node, path)
        elif node.kind == "array":
            self.elements(node, path, node.count, what)
        elif node.kind == "sequence":
            count = self.read("u4", what).astype(np.int64)
            self.elements(node, path, count, what)
        else:
            raise NotFastPath(f"field {what} of type {node.type_name}")

    def elements(self, node: Node, path: tuple, count: int | np.ndarray, what: str) -> None:
        item = node.item
        assert item is not None
        if isinstance(count, np.ndarray) and len(count) and bool(np.all(count == count[0])):
            count = int(count[0])
        if item.kind == "number":
            size = np.dtype(item.dtype).itemsize
            self.align(size)
            wanted = sorted(p[-1] for p in self.remaining if p[:-1] == path)
            if wanted:
                short = np.flatnonzero(np.asarray(count) <= wanted[-1])
                if len(short):
                    i = int(short[0]) if np.ndim(count) else 0
                    raise PayloadError(i, f"{what} has fewer than {wanted[-1] + 1} elements")
                self.check(size * count, what)
                base = self.rel
                for k in wanted:
                    self.rel = base + size * k
                    self.store((*path, k), self.read(item.dtype, what))
                self.rel = base
            self.skip(size * count)
            return
        if isinstance(count, int):
            for k in range(count):
                if not self.remaining:
                    return
                self.field(item, (*path, k))
            return
        if self.remaining:  # wanted fields after a sequence of structs: offsets unknown
            raise NotFastPath(f"{what}: a sequence of {item.describe()} of varying length")


# --- JSON -----------------------------------------------------------------------------------


def json_type(name: str, schema: bytes) -> MessageType:
    """The :class:`MessageType` of a JSON channel from its ``jsonschema`` (ValueError without
    one: the fields would have to be guessed from the messages)."""
    import json

    if not schema.strip():
        raise ValueError("a json channel without a jsonschema: its fields are unknown")
    try:
        doc = json.loads(schema)
    except ValueError as exc:
        raise ValueError(f"the jsonschema is not JSON ({exc})") from None
    root = _json_node("", doc if isinstance(doc, dict) else {})
    root.kind = "struct"
    return MessageType(name, "json", root)


def _json_node(name: str, doc: dict) -> Node:
    kind = doc.get("type")
    if isinstance(kind, list):
        kind = next((k for k in kind if k != "null"), None)
    if kind == "object" or "properties" in doc:
        props = doc.get("properties") or {}
        children = [_json_node(k, v if isinstance(v, dict) else {}) for k, v in props.items()]
        return Node(name, "struct", children=children, type_name=str(doc.get("title", "object")))
    if kind == "array":
        item = _json_node("", doc.get("items") if isinstance(doc.get("items"), dict) else {})
        lo, hi = doc.get("minItems"), doc.get("maxItems")
        if isinstance(lo, int) and lo == hi:
            return Node(name, "array", item=item, count=lo)
        return Node(name, "sequence", item=item)
    if kind == "number":
        return Node(name, "number", "f8")
    if kind == "integer":
        return Node(name, "number", "i8")
    if kind == "string":
        return Node(name, "string")
    return Node(name, "other", type_name=str(kind or "any"))


def _decode_json(
    mtype: MessageType,
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    leaves: list[Leaf],
) -> list[np.ndarray]:
    """JSON payloads by template (:mod:`imupipe.readers.json_numbers`), the messages no
    template fits (or the whole batch, when something is off) by Arrow's JSON reader, and what
    Arrow refuses (``NaN``, ``Infinity``, which ``json`` reads; a bad payload) by ``json``, one
    message at a time."""
    from imupipe.readers.json_numbers import decode_by_template

    integer = []
    for leaf in leaves:
        names = tuple(str(p) for p in leaf.path if isinstance(p, str))
        node = mtype.node(names)
        while node is not None and node.kind in ("array", "sequence"):
            node = node.item
        integer.append(node is not None and node.dtype == "i8")

    def rest(rows: np.ndarray) -> list[np.ndarray]:
        s, n = starts[rows], lengths[rows]
        try:
            return _decode_json_arrow(mtype, buf, s, n, leaves)
        except PayloadError:
            pass
        try:  # what Arrow refuses (NaN, Infinity; or a bad payload): json's verdict
            return mtype.decode_reference(buf, s, n, leaves)
        except PayloadError as exc:
            raise PayloadError(int(rows[exc.index]), exc.reason) from None

    paths = [leaf.path for leaf in leaves]
    shapes = mtype.json_shapes.setdefault(tuple(paths), [])
    got = decode_by_template(buf, starts, lengths, paths, integer, rest, shapes)
    return got if got is not None else rest(np.arange(len(starts)))


def _decode_json_arrow(
    mtype: MessageType,
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    leaves: list[Leaf],
) -> list[np.ndarray]:
    """JSON payloads through Arrow's JSON reader (see the module docstring)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.json as pj

    n = len(starts)
    ends = np.cumsum(lengths + 1)  # in the joined text: each payload, then a newline
    tstart = np.cumsum(lengths) - lengths
    idx = np.repeat(starts - tstart, lengths) + np.arange(int(ends[-1]) - n)
    data = np.full(int(ends[-1]), 10, np.uint8)
    keep = np.ones(len(data), bool)
    keep[ends - 1] = False
    text = buf[idx]
    text[(text == 10) | (text == 13)] = 32  # raw newlines are whitespace in JSON, never in strings
    data[keep] = text
    schema = _arrow_schema(mtype, leaves)
    try:
        table = pj.read_json(
            pa.BufferReader(pa.py_buffer(data)),
            read_options=pj.ReadOptions(
                block_size=max(1 << 22, int(lengths.max()) * 4 + 64), use_threads=False
            ),
            parse_options=pj.ParseOptions(
                explicit_schema=schema, unexpected_field_behavior="ignore"
            ),
        )
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        bad = _first_bad_json(buf, starts, lengths)
        raise PayloadError(bad, f"not JSON of the mapped shape ({exc})") from None
    if table.num_rows != n:
        bad = _first_bad_json(buf, starts, lengths)
        raise PayloadError(bad, "not one JSON object")
    out = []
    for leaf in leaves:
        names = [p for p in leaf.path if isinstance(p, str)]
        column = table.column(names[0]).combine_chunks()
        for part in leaf.path[1:]:
            if isinstance(part, int):
                sizes = pc.list_value_length(column).to_numpy(zero_copy_only=False)
                short = np.flatnonzero(~(sizes > part))
                if len(short):
                    raise PayloadError(int(short[0]), f"field {leaf} is missing")
                column = pc.list_element(column, part)
            else:
                column = pc.struct_field(column, part)
        if column.null_count:
            bad = int(np.flatnonzero(column.is_null().to_numpy(zero_copy_only=False))[0])
            raise PayloadError(bad, f"field {leaf} is missing or null")
        values = column.to_numpy(zero_copy_only=False)
        out.append(values.astype(np.int64 if values.dtype.kind in "iu" else np.float64))
    # Arrow reads "-0" as -0.0, json as the integer 0: the (rare) messages with a -0.0 by json
    minus = np.flatnonzero(
        np.any([(v == 0) & np.signbit(v) for v in out if v.dtype.kind == "f"] or [[False]], 0)
    )
    if len(minus):
        exact = mtype.decode_reference(buf, starts[minus], lengths[minus], leaves)
        for v, e in zip(out, exact, strict=True):
            v[minus] = e
    return out


def _arrow_schema(mtype: MessageType, leaves: list[Leaf]):  # noqa: ANN202
    """An Arrow schema with the fields of ``leaves`` only (numbers as the jsonschema types
    them, float64 where it says nothing)."""
    import pyarrow as pa

    tree: dict = {}
    for leaf in leaves:
        node = tree
        for k, part in enumerate(leaf.path):
            if isinstance(part, int):
                node["__list__"] = True
                continue
            last = k == len(leaf.path) - 1 or (
                k == len(leaf.path) - 2 and isinstance(leaf.path[-1], int)
            )
            if last:
                found = mtype.node(tuple(str(p) for p in leaf.path[: k + 1]))
                if found is not None and found.kind in ("array", "sequence"):
                    found = found.item
                integer = found is not None and found.dtype == "i8"
                node.setdefault(part, {"__leaf__": pa.int64() if integer else pa.float64()})
                node = node[part]
            else:
                node = node.setdefault(part, {})

    def build(spec: dict) -> pa.DataType:
        if "__leaf__" in spec:
            leaf_type = spec["__leaf__"]
            return pa.list_(leaf_type) if spec.get("__list__") else leaf_type
        typ = pa.struct([pa.field(k, build(v)) for k, v in spec.items() if not k.startswith("__")])
        return pa.list_(typ) if spec.get("__list__") else typ

    return pa.schema([pa.field(k, build(v)) for k, v in tree.items()])


def _first_bad_json(buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> int:
    """The first payload that is not one JSON object (found one at a time: an error path)."""
    import json

    for i, (s, n) in enumerate(zip(starts.tolist(), lengths.tolist(), strict=True)):
        try:
            if not isinstance(json.loads(buf[s : s + n].tobytes()), dict):
                return i
        except ValueError:
            return i
    return 0


# --- Protobuf -------------------------------------------------------------------------------

PROTO_WIRE = {
    1: ("f8", "<f8"),  # TYPE_DOUBLE
    2: ("f4", "<f4"),  # TYPE_FLOAT
    3: ("i8", "varint"),  # TYPE_INT64
    4: ("u8", "varint"),  # TYPE_UINT64
    5: ("i4", "varint"),  # TYPE_INT32
    6: ("u8", "<u8"),  # TYPE_FIXED64
    7: ("u4", "<u4"),  # TYPE_FIXED32
    8: ("u1", "varint"),  # TYPE_BOOL
    13: ("u4", "varint"),  # TYPE_UINT32
    15: ("i4", "<i4"),  # TYPE_SFIXED32
    16: ("i8", "<i8"),  # TYPE_SFIXED64
    17: ("i4", "zigzag"),  # TYPE_SINT32
    18: ("i8", "zigzag"),  # TYPE_SINT64
}
"""protobuf FieldDescriptor type -> (dtype, wire decoding)."""


def protobuf_type(name: str, schema: bytes) -> MessageType:
    """The :class:`MessageType` of a protobuf channel from its ``FileDescriptorSet``."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(schema)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    desc = pool.FindMessageTypeByName(name)
    root = _proto_node("", desc, 0)
    root.kind = "struct"
    return MessageType(name, "protobuf", root, message_factory.GetMessageClass(desc))


def _proto_node(name: str, desc: object, depth: int) -> Node:
    children = []
    for f in desc.fields:  # type: ignore[attr-defined]
        children.append(_proto_field(f, depth))
    return Node(name, "struct", children=children, type_name=desc.full_name)  # type: ignore[attr-defined]


def _proto_field(f: object, depth: int) -> Node:
    typ = f.type  # type: ignore[attr-defined]
    repeated = getattr(f, "is_repeated", None)
    repeated = repeated if isinstance(repeated, bool) else f.label == 3  # type: ignore[attr-defined]
    if typ == 11 and depth < 16:  # TYPE_MESSAGE
        node = _proto_node(f.name, f.message_type, depth + 1)  # type: ignore[attr-defined]
    elif typ in PROTO_WIRE:
        dtype, wire = PROTO_WIRE[typ]
        node = Node(f.name, "number", dtype, wire=wire)  # type: ignore[attr-defined]
    elif typ == 9:
        node = Node(f.name, "string")  # type: ignore[attr-defined]
    else:
        node = Node(f.name, "other", type_name="bytes" if typ == 12 else "enum")  # type: ignore[attr-defined]
    node.tag = f.number  # type: ignore[attr-defined]
    if repeated:
        item = node
        node = Node(item.name, "sequence", item=item, tag=item.tag)
        item.name = ""
    return node


class _Pad(threading.local):
    """A work array kept per thread: a fresh chunk-sized copy costs its page faults."""

    def __init__(self) -> None:
        self.buf = np.empty(0, np.uint8)


_PAD = _Pad()


def _padded(buf: np.ndarray) -> np.ndarray:
    """``buf`` followed by 16 zero bytes, in this thread's work array (valid until the next
    call in the thread)."""
    need = len(buf) + 16
    if len(_PAD.buf) < need:
        _PAD.buf = np.empty(int(need * 1.25), np.uint8)
    out = _PAD.buf[:need]
    out[: len(buf)] = buf
    out[len(buf) :] = 0
    return out


_WIRE_TYPES = np.array([True, True, True, False, False, True, False, False])
"""The protobuf wire types read (varint, 64-bit, length-delimited, 32-bit), by the tag's low 3
bits."""


class _ProtoScan:
    """Protobuf messages scanned in lockstep (see the module docstring)."""

    def __init__(
        self,
        mtype: MessageType,
        buf: np.ndarray,
        starts: np.ndarray,
        lengths: np.ndarray,
        leaves: list[Leaf],
    ) -> None:
        self.mtype = mtype
        self.buf = _padded(buf)  # varints read 10 bytes
        self.starts, self.lengths, self.leaves = starts, lengths, leaves
        self.n = len(starts)

    def run(self) -> list[np.ndarray]:
        out: dict[tuple, np.ndarray] = {}
        wanted = [tuple(leaf.path) for leaf in self.leaves]
        self.message(self.mtype.root, (), self.starts, self.starts + self.lengths, wanted, out)
        return [out[w] for w in wanted]

    def varint(self, pos: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(value uint64, size in bytes) of the varint at each position (of message ``rows``,
        which a varint past 10 bytes names): one byte read where it is below 0x80 (tags of
        fields 1-15, short lengths), ten where it is not."""
        first = self.buf[pos]
        value = first.astype(np.uint64)
        size = np.ones(len(pos), np.int64)
        long = np.flatnonzero(first >= 0x80)
        if len(long):  # byte k of the varints still going, for k = 1..9
            value[long] &= np.uint64(0x7F)
            live, p = long, pos[long]
            for k in range(1, 10):
                b = self.buf[p + k]
                value[live] |= (b & 0x7F).astype(np.uint64) << np.uint64(7 * k)
                size[live] = k + 1
                going = b >= 0x80
                live, p = live[going], p[going]
                if not len(live):
                    break
            else:
                raise PayloadError(int(rows[live[0]]), "varint past 10 bytes")
        return value, size

    def message(
        self,
        node: Node,
        path: tuple,
        lo: np.ndarray,
        hi: np.ndarray,
        wanted: list[tuple],
        out: dict[tuple, np.ndarray],
    ) -> None:
        """Fill ``out`` for the ``wanted`` paths under ``path``, messages at ``[lo, hi)``."""
        n = len(lo)
        here = [w for w in wanted if w[: len(path)] == path and len(w) > len(path)]
        by_tag: dict[int, Node] = {}
        for w in here:
            child = node.child(w[len(path)])  # type: ignore[arg-type]
            if child is None:
                raise PayloadError(0, f"no field {'.'.join(map(str, w))}")
            by_tag[child.tag] = child
        found: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = {}
        pos = lo.copy()
        active = np.flatnonzero(pos < hi)
        while len(active):
            p = pos[active]
            tag, size = self.varint(p, active)
            number = (tag >> np.uint64(3)).astype(np.int64)
            wire = (tag & np.uint64(7)).astype(np.int64)
            p = p + size
            step = np.zeros(len(active), np.int64)
            body = p.copy()
            step[wire == 1] = 8
            step[wire == 5] = 4
            if np.any(wire == 0):
                sel = np.flatnonzero(wire == 0)
                _, vsize = self.varint(p[sel], active[sel])
                step[sel] = vsize
            if np.any(wire == 2):
                sel = np.flatnonzero(wire == 2)
                length, lsize = self.varint(p[sel], active[sel])
                body[sel] = p[sel] + lsize
                step[sel] = lsize + length.astype(np.int64)
            bad = np.flatnonzero(~_WIRE_TYPES[wire])
            if len(bad):
                raise PayloadError(int(active[bad[0]]), "unsupported protobuf wire type")
            end = p + step
            over = np.flatnonzero(end > hi[active])
            if len(over):
                raise PayloadError(int(active[over[0]]), "field runs past the message")
            for t, child in by_tag.items():
                sel = np.flatnonzero((number == t) & _wire_fits(child, wire))
                if len(sel):
                    found.setdefault(t, []).append((active[sel], body[sel], end[sel], wire[sel]))
            pos[active] = end
            active = active[end < hi[active]]
        for t, child in by_tag.items():
            hits = found.get(t, [])
            cpath = (*path, child.name)
            sub = [w for w in here if w[: len(cpath)] == cpath]
            self.field(child, cpath, hits, n, sub, out)

    def field(
        self,
        child: Node,
        cpath: tuple,
        hits: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
        n: int,
        sub: list[tuple],
        out: dict[tuple, np.ndarray],
    ) -> None:
        if child.kind == "struct":
            lo, hi = np.zeros(n, np.int64), np.zeros(n, np.int64)
            seen = np.zeros(n, np.int64)
            for rows, body, end, _ in hits:
                lo[rows], hi[rows] = body, end
                seen[rows] += 1
            if np.any(seen > 1):  # protobuf merges a message split over records
                raise NotFastPath(f"field {'.'.join(map(str, cpath))}: a message in pieces")
            self.message(child, cpath, lo, hi, sub, out)
            return
        if child.kind == "number":
            values = np.zeros(n, np.dtype(child.dtype))
            for rows, body, _, _ in hits:
                values[rows] = self.scalar(child, body, rows)
            out[cpath] = _widen(values)
            return
        if child.kind == "sequence" and child.item is not None and child.item.kind == "number":
            item = child.item
            wanted = sorted({w[len(cpath)] for w in sub})
            values = np.zeros((n, max(wanted) + 1), np.dtype(item.dtype))
            count = np.zeros(n, np.int64)
            for rows, body, end, wire in hits:
                packed = wire == 2
                if np.any(~packed):
                    r, b = rows[~packed], body[~packed]
                    slot = count[r]
                    ok = slot < values.shape[1]
                    values[r[ok], slot[ok]] = self.scalar(item, b[ok], r[ok])
                    count[r] += 1
                if np.any(packed):
                    self.packed(item, rows[packed], body[packed], end[packed], values, count)
            short = np.flatnonzero(count <= wanted[-1])
            if len(short):
                raise PayloadError(
                    int(short[0]),
                    f"field {'.'.join(map(str, cpath))} has fewer than {wanted[-1] + 1} elements",
                )
            for k in wanted:
                out[(*cpath, k)] = _widen(values[:, k])
            return
        raise NotFastPath(f"field {'.'.join(map(str, cpath))}: a repeated message")

    def packed(
        self,
        item: Node,
        rows: np.ndarray,
        body: np.ndarray,
        end: np.ndarray,
        values: np.ndarray,
        count: np.ndarray,
    ) -> None:
        """Packed runs (one per row of ``rows``, ``[body, end)``): their first elements into
        ``values`` after the ``count`` each row has so far; ``count`` grows by each run's
        length. Fixed-width items are read at ``body + k * size``; varints one element of
        every run per step."""
        width = values.shape[1]
        if item.wire not in ("varint", "zigzag"):
            size = np.dtype(item.wire).itemsize
            n_items, rest = np.divmod(end - body, size)
            if np.any(rest):
                bad = int(rows[np.flatnonzero(rest)[0]])
                raise PayloadError(bad, "a packed field is not a whole number of items")
            for k in range(width):
                slot = count[rows] + k
                ok = (k < n_items) & (slot < width)
                values[rows[ok], slot[ok]] = self.scalar(item, body[ok] + k * size, rows[ok])
            count[rows] += n_items
            return
        p = body.copy()
        live = np.flatnonzero(p < end)
        while len(live):
            r = rows[live]
            slot = count[r]
            ok = slot < width
            values[r[ok], slot[ok]] = self.scalar(item, p[live][ok], r[ok])
            count[r] += 1
            p[live] += self.varint(p[live], r)[1]
            over = np.flatnonzero(p[live] > end[live])
            if len(over):
                raise PayloadError(int(rows[live[over[0]]]), "a packed varint runs past its field")
            live = live[p[live] < end[live]]

    def scalar(self, node: Node, body: np.ndarray, rows: np.ndarray) -> np.ndarray:
        if node.wire in ("varint", "zigzag"):
            raw, _ = self.varint(body, rows)
            if node.wire == "zigzag":
                return ((raw >> np.uint64(1)).astype(np.int64)) ^ -(raw & np.uint64(1)).astype(
                    np.int64
                )
            if node.dtype == "u1":  # bool: any value but 0 is true
                return (raw != 0).astype(np.uint8)
            return raw.astype(np.int64) if node.dtype[0] == "i" else raw
        return unaligned(self.buf, node.wire)[body]


_WIRE_OF = {"varint": 0, "zigzag": 0, "<f8": 1, "<u8": 1, "<i8": 1, "<f4": 5, "<u4": 5, "<i4": 5}
"""The wire type of a protobuf number's encoding."""


def _wire_fits(node: Node, wire: np.ndarray) -> np.ndarray | bool:
    """Where a record's wire type is the one of ``node``'s type (length-delimited for a
    message, also for a packed run of a repeated number): a record of another wire type is an
    unknown field to protobuf's parsers (upb), never a value."""
    if node.kind == "struct":
        return wire == 2
    if node.kind == "number":
        return wire == _WIRE_OF[node.wire]
    if node.kind == "sequence" and node.item is not None and node.item.kind == "number":
        return (wire == 2) | (wire == _WIRE_OF[node.item.wire])
    return True


def _widen(values: np.ndarray) -> np.ndarray:
    return values.astype(np.int64 if values.dtype.kind in "iub" else np.float64)


# --- Protobuf, compiled --------------------------------------------------------------------

_PROTO_CODES = {
    ("i8", "varint"): 0,
    ("u8", "varint"): 1,
    ("i4", "varint"): 2,
    ("u4", "varint"): 3,
    ("u1", "varint"): 4,
    ("i4", "zigzag"): 5,
    ("i8", "zigzag"): 6,
    ("f8", "<f8"): 7,
    ("f4", "<f4"): 8,
    ("u8", "<u8"): 9,
    ("u4", "<u4"): 10,
    ("i4", "<i4"): 11,
    ("i8", "<i8"): 12,
}
"""(dtype, wire) of a protobuf number -> its decoding in ``readers/_protoscan.c`` (CODE_*)."""


@dataclass
class _ProtoPlan:
    """What ``readers/_protoscan.c`` reads (see its header): per nested message on a mapped
    path, the wanted field numbers (``fields``), the wanted elements of repeated numbers
    (``seqs``, ``slots``); one output column per distinct leaf path (``column`` of each leaf),
    ``floats`` the columns holding doubles."""

    fields: np.ndarray
    seqs: np.ndarray
    slots: np.ndarray
    column: list[int]
    floats: list[bool]


def _proto_plan(root: Node, leaves: list[Leaf]) -> _ProtoPlan | None:
    """The compiled pass's plan for ``leaves``, or None when one is not a number reachable
    through singular nested messages (a name that is not there, a repeated message, an enum
    or bytes: the numpy scan raises or falls back as it does)."""
    structs: dict[tuple, int] = {(): 0}
    rows: dict[tuple[int, int], list[int]] = {}
    seqs: dict[tuple, dict[int, int]] = {}
    columns: dict[tuple, int] = {}
    floats: list[bool] = []
    column = []
    for leaf in leaves:
        path = tuple(leaf.path)
        if path not in columns:
            columns[path] = len(columns)
            floats.append(False)
        col = columns[path]
        column.append(col)
        node, sid = root, 0
        names = path[:-1] if path and isinstance(path[-1], int) else path
        if not names or not all(isinstance(p, str) for p in names):
            return None
        for j, part in enumerate(names):
            child = node.child(part) if node.kind == "struct" else None  # type: ignore[arg-type]
            if child is None:
                return None
            last = j == len(names) - 1
            if child.kind == "struct" and not last:
                sub = structs.setdefault(names[: j + 1], len(structs))
                rows[(sid, child.tag)] = [sid, child.tag, 1, 0, sub]
                node, sid = child, sub
                continue
            item = child.item if child.kind == "sequence" else child
            indexed = len(names) < len(path)
            if not last or item is None or item.kind != "number" or indexed != (item is not child):
                return None
            code = _PROTO_CODES.get((item.dtype, item.wire))
            if code is None:
                return None
            floats[col] = item.dtype[0] == "f"
            if indexed:
                seq = seqs.setdefault(names, {})
                seq[int(path[-1])] = col  # type: ignore[arg-type]
                rows[(sid, child.tag)] = [sid, child.tag, 2, code, list(seqs).index(names)]
            else:
                rows[(sid, child.tag)] = [sid, child.tag, 0, code, col]
    seq_rows, slots = [], []
    for wanted in seqs.values():
        width = max(wanted) + 1
        seq_rows.append([len(slots), width])
        slots.extend(wanted.get(k, -1) for k in range(width))
    return _ProtoPlan(
        np.array(sorted(rows.values()), np.int64).reshape(-1, 5),
        np.array(seq_rows, np.int64).reshape(-1, 2),
        np.array(slots, np.int64),
        column,
        floats,
    )


def _protoscan() -> ModuleType | None:
    """The compiled pass (``imupipe.readers._protoscan``), or None (not built, or
    ``IMUPIPE_PURE_PYTHON`` set)."""
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None
    try:
        from imupipe.readers import _protoscan  # type: ignore[attr-defined]
    except ImportError:
        return None
    return _protoscan


def protoscan_compiled() -> bool:
    """Whether protobuf channels are read by the compiled pass: built, and not turned off by
    ``IMUPIPE_PURE_PYTHON``."""
    return _protoscan() is not None


def _decode_protobuf(
    mtype: MessageType,
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    leaves: list[Leaf],
) -> list[np.ndarray]:
    """:meth:`MessageType.decode` of protobuf messages: the compiled pass
    (``readers/_protoscan.c``) walks each message once and writes the mapped fields; the
    messages it leaves (flagged), and every message when it is not built, go to the numpy scan
    (:class:`_ProtoScan`), which gives the same columns and names a bad message."""
    module = _protoscan()
    key = tuple(tuple(leaf.path) for leaf in leaves)
    if module is not None and key not in mtype.proto_plans:
        mtype.proto_plans[key] = _proto_plan(mtype.root, leaves)
    plan = mtype.proto_plans.get(key) if module is not None else None
    if plan is None or buf.dtype != np.uint8 or not buf.flags.c_contiguous:
        return _proto_numpy(mtype, buf, starts, lengths, leaves)
    n = len(starts)
    out = np.zeros((len(plan.floats), n), np.int64)
    flags = np.empty(n, np.uint8)
    starts = np.ascontiguousarray(starts, np.int64)
    lengths = np.ascontiguousarray(lengths, np.int64)
    flagged = module.scan(buf, starts, lengths, plan.fields, plan.seqs, plan.slots, out, flags)
    columns = [row.view(np.float64) if f else row for row, f in zip(out, plan.floats, strict=True)]
    if flagged:
        rest = np.flatnonzero(flags)
        try:
            got = _proto_numpy(mtype, buf, starts[rest], lengths[rest], leaves)
        except PayloadError as exc:
            raise PayloadError(int(rest[exc.index]), exc.reason) from None
        for col, values in zip(plan.column, got, strict=True):
            columns[col][rest] = values
    return [columns[col] for col in plan.column]


def _proto_numpy(
    mtype: MessageType,
    buf: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    leaves: list[Leaf],
) -> list[np.ndarray]:
    """The numpy scan (:class:`_ProtoScan`); protobuf's own parser where it cannot follow."""
    try:
        return _ProtoScan(mtype, buf, starts, lengths, leaves).run()
    except NotFastPath:
        return mtype.decode_reference(buf, starts, lengths, leaves)
