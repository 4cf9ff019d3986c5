"""``[inputs.NAME.fields]``: the sensors of any message type, by field path, into the common table.

The mapping (:class:`imupipe.readers.spec.FieldMapping`) names each sensor's fields as
``"TOPIC.FIELD.PATH"``; :func:`plan` resolves every path once against the definitions the log
carries (:mod:`imupipe.readers.message_fields`), so that a topic or field that does not exist,
or a field of the wrong shape, is one line naming it before any message is decoded. A source
(MCAP file, ROS 1 bag, ROS 2 storage file) then gives the payloads of the mapped topics chunk by
chunk (``payloads``), each decoded in a few numpy calls per field.

Rows: one per message of each mapped topic, holding the sensors mapped on that topic (the
others null on it: a gyro topic and an accel topic give an ``imu`` stream whose rows each carry
one of the two), sorted stably by time (at equal times: in the order gyro, accel, mag,
temperature topics, then message order); messages out of time order are counted and warned
about, none dropped.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from imupipe.readers.cdr import PayloadError
from imupipe.readers.errors import ReadError
from imupipe.readers.message_fields import (
    NANOS,
    SECONDS,
    Leaf,
    MessageType,
    Node,
    json_type,
    protobuf_type,
    ros_type,
)
from imupipe.readers.spec import (
    ACCEL_UNITS,
    GYRO_UNITS,
    MAG_UNITS,
    TIME_UNITS,
    FieldMapping,
    InputSpec,
)
from imupipe.readers.topics import normalize_type

SENSORS = ("gyro", "accel", "mag", "temperature")
UNITS = {"gyro": GYRO_UNITS, "accel": ACCEL_UNITS, "mag": MAG_UNITS}
TIME_FACTORS = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}


@dataclass
class Definition:
    """A topic's message type as the log carries it."""

    msgtype: str
    encoding: str
    """The message encoding: ``cdr``, ``ros1``, ``json``, ``protobuf``."""
    schema_encoding: str
    """``ros2msg``, ``ros2idl``, ``ros1msg``, ``jsonschema``, ``protobuf`` (empty: none)."""
    schema: bytes


@dataclass
class Batch:
    """One chunk's messages of a topic: payloads at ``starts``/``lengths`` of ``buf``, log
    times and (MCAP) publish times, int64 ns."""

    buf: np.ndarray
    starts: np.ndarray
    lengths: np.ndarray
    log: np.ndarray
    pub: np.ndarray | None = None


class MappedSource(Protocol):
    path: Path
    format: str

    def first_time(self) -> int:
        """Log time of the first message (ns), for ordering split files."""

    def definitions(self) -> dict[str, Definition]:
        """Topic -> its message definition."""

    def payloads(self, topics: set[str]) -> Iterator[list[tuple[str, Batch]]]:
        """Per chunk in file order: the messages of ``topics``."""


def message_type(defn: Definition) -> MessageType:
    """The field tree of a topic's type (ValueError when the definition cannot be used)."""
    if defn.encoding in ("cdr", "ros1"):
        return ros_type(
            defn.msgtype, defn.encoding, defn.schema_encoding, defn.schema.decode(errors="replace")
        )
    if defn.encoding == "json":
        return json_type(defn.msgtype, defn.schema)
    if defn.encoding == "protobuf":
        return protobuf_type(defn.msgtype, defn.schema)
    raise ValueError(f"message encoding '{defn.encoding}' is not supported")


# --- the plan ------------------------------------------------------------------------------


@dataclass
class TopicPlan:
    """What to read from one topic: its leaves, which sensor takes which, and its time."""

    topic: str
    mtype: MessageType
    leaves: list[Leaf] = field(default_factory=list)
    sensors: dict[str, list[int]] = field(default_factory=dict)
    """Sensor -> indices into ``leaves`` (x, y, z; or the one temperature)."""
    time: list[int] = field(default_factory=list)
    """Indices into ``leaves``: (seconds, nanoseconds) of a time struct, or one number; none:
    the log time."""

    def add(self, path: tuple[str | int, ...]) -> int:
        leaf = Leaf(path)
        for i, known in enumerate(self.leaves):
            if known.path == leaf.path:
                return i
        self.leaves.append(leaf)
        return len(self.leaves) - 1


def split_path(path: str, topics: Sequence[str], where: str) -> tuple[str, list[str]]:
    """``"TOPIC.FIELD.PATH"`` -> (topic, field names): the longest topic of the log the path
    starts with, followed by a dot."""
    best = max((t for t in topics if path.startswith(t + ".")), key=len, default=None)
    if best is None:
        raise ReadError(
            f"{where}: '{path}' names no topic of the log; topics: {', '.join(sorted(topics))}"
        )
    return best, path[len(best) + 1 :].split(".")


def mapped_topics(spec: InputSpec, topics: Sequence[str]) -> list[str]:
    """The topics the mapping reads, gyro's first."""
    mapping = spec.fields
    assert mapping is not None
    out: list[str] = []
    for sensor in SENSORS:
        value = getattr(mapping, sensor)
        for path in [value] if isinstance(value, str) else value or []:
            topic, _ = split_path(path, topics, _where(spec, sensor))
            if topic not in out:
                out.append(topic)
    return out


def _where(spec: InputSpec, key: str) -> str:
    return f"{spec.path}: [inputs.{spec.name}.fields] {key}"


def plan(spec: InputSpec, defs: Mapping[str, Definition]) -> dict[str, TopicPlan]:
    """Resolve the mapping against the log's definitions (see the module docstring)."""
    mapping = spec.fields
    assert mapping is not None
    topics = mapped_topics(spec, list(defs))
    plans: dict[str, TopicPlan] = {}
    for topic in topics:
        try:
            mtype = message_type(defs[topic])
        except Exception as exc:  # noqa: BLE001 - a definition rosbags/protobuf cannot parse
            raise ReadError(
                f"{spec.path}: topic '{topic}' ({defs[topic].msgtype}): cannot use its message "
                f"definition ({exc})"
            ) from None
        plans[topic] = TopicPlan(topic, mtype)
    for sensor in SENSORS:
        value = getattr(mapping, sensor)
        if value is None:
            continue
        where = _where(spec, sensor)
        paths = [value] if isinstance(value, str) else value
        split = [split_path(p, topics, where) for p in paths]
        if len({t for t, _ in split}) > 1:
            raise ReadError(f"{where}: the three fields must be on one topic, got {paths}")
        tp = plans[split[0][0]]
        if sensor == "temperature":
            leaf = _scalar(tp, split[0][1], where, value)  # type: ignore[arg-type]
            tp.sensors[sensor] = [tp.add(leaf)]
        elif len(paths) == 1:
            tp.sensors[sensor] = [tp.add(p) for p in _vector(tp, split[0][1], where, paths[0])]
        else:
            tp.sensors[sensor] = [
                tp.add(_scalar(tp, parts, where, p))
                for (_, parts), p in zip(split, paths, strict=True)
            ]
    if mapping.time not in ("header", "log"):
        topic, _ = split_path(mapping.time, list(defs), _where(spec, "time"))
        if topic not in plans:
            raise ReadError(
                f"{_where(spec, 'time')}: '{mapping.time}' is on topic '{topic}', which maps no "
                f"sensor (mapped: {', '.join(plans)})"
            )
    for tp in plans.values():
        _time(spec, mapping, tp, list(plans))
    return plans


def _resolve(tp: TopicPlan, parts: list[str], where: str, text: str) -> tuple[Node, tuple]:
    node = tp.mtype.root
    path: list[str | int] = []
    for part in parts:
        if node.kind in ("array", "sequence") and part.isdigit():
            if node.kind == "array" and int(part) >= node.count:
                raise ReadError(f"{where}: '{text}': index {part} is past {node.describe()}")
            path.append(int(part))
            node = node.item  # type: ignore[assignment]
            continue
        found = node.child(part) if node.kind == "struct" else None
        if found is None:
            have = ", ".join(p for p, _ in tp.mtype.leaves(24))
            raise ReadError(
                f"{where}: '{text}': topic '{tp.topic}' ({tp.mtype.name}) has no field "
                f"'{'.'.join(parts)}'; its fields: {have or 'none known'}"
            )
        path.append(part)
        node = found
    return node, tuple(path)


def _scalar(tp: TopicPlan, parts: list[str], where: str, text: str) -> tuple:
    node, path = _resolve(tp, parts, where, text)
    if node.kind != "number":
        raise ReadError(f"{where}: '{text}' is {node.describe()}, not one number")
    return path


def _vector(tp: TopicPlan, parts: list[str], where: str, text: str) -> list[tuple]:
    node, path = _resolve(tp, parts, where, text)
    if node.kind == "struct":
        numbers = [c for c in node.children if c.kind == "number"]
        named = {c.name.lower(): c for c in numbers}
        if all(a in named for a in "xyz"):
            return [(*path, named[a].name) for a in "xyz"]
        if len(node.children) == 3 and len(numbers) == 3:
            return [(*path, c.name) for c in numbers]
        fields = ", ".join(f"{c.name} {c.describe()}" for c in node.children)
        raise ReadError(
            f"{where}: '{text}' is a {node.describe()} ({fields}), not a Vector3-like struct "
            "(x, y, z) or a 3-element array"
        )
    item = node.item if node.kind in ("array", "sequence") else None
    if item is not None and item.kind == "number" and node.count in (0, 3):
        return [(*path, k) for k in range(3)]  # a sequence (count 0) is checked per message
    raise ReadError(
        f"{where}: '{text}' is {node.describe()}, not a Vector3-like struct (x, y, z) or a "
        "3-element array; or give a list of 3 field paths"
    )


def _time(spec: InputSpec, mapping: FieldMapping, tp: TopicPlan, topics: list[str]) -> None:
    """The time leaves of ``tp``: its header stamp, nothing (log time), or the time path's
    field, read on every mapped topic (``"/a.timestamp"`` with gyro on ``/a`` and accel on
    ``/b``: each topic's own ``timestamp``)."""
    where = _where(spec, "time")
    if mapping.time == "log":
        return
    if mapping.time == "header":
        header = tp.mtype.root.child("header")
        stamp = header.child("stamp") if header is not None else None
        pair = _time_struct(stamp) if stamp is not None else None
        if pair is None:
            raise ReadError(
                f"{where} = 'header': topic '{tp.topic}' ({tp.mtype.name}) has no header stamp; "
                'set time = "log" or time = "TOPIC.FIELD"'
            )
        tp.time = [tp.add(("header", "stamp", pair[0])), tp.add(("header", "stamp", pair[1]))]
        return
    topic, parts = split_path(mapping.time, topics, where)
    del topic  # the field is read on each mapped topic
    node, path = _resolve(tp, parts, where, mapping.time)
    pair = _time_struct(node)
    if pair is not None:
        tp.time = [tp.add((*path, pair[0])), tp.add((*path, pair[1]))]
    elif node.kind == "number":
        tp.time = [tp.add(path)]
    else:
        raise ReadError(f"{where}: '{mapping.time}' is {node.describe()}, not a number or a time")


def _time_struct(node: Node) -> tuple[str, str] | None:
    """(seconds field, nanoseconds field) of a time struct (builtin_interfaces/Time, ROS 1
    time, google.protobuf.Timestamp, foxglove's JSON time), else None."""
    if node.kind != "struct":
        return None
    names = {c.name: c for c in node.children if c.kind == "number"}
    sec = next((n for n in SECONDS if n in names), None)
    nsec = next((n for n in NANOS if n in names), None)
    return (sec, nsec) if sec and nsec else None


# --- reading -------------------------------------------------------------------------------


def decode_batch(tp: TopicPlan, batch: Batch, where: str) -> tuple[np.ndarray, list[np.ndarray]]:
    """(time ns or None for the log time, leaf values) of one batch."""
    try:
        values = tp.mtype.decode(batch.buf, batch.starts, batch.lengths, tp.leaves)
    except PayloadError as exc:
        raise ReadError(
            f"{where}: topic '{tp.topic}': message at log time {int(batch.log[exc.index])} is not "
            f"a valid {tp.mtype.name}: {exc.reason}"
        ) from None
    return values


def _ns(tp: TopicPlan, values: list[np.ndarray], log: np.ndarray, unit: str) -> np.ndarray:
    if not tp.time:
        return log
    if len(tp.time) == 2:
        sec, nsec = (values[i] for i in tp.time)
        return sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64)
    raw = values[tp.time[0]]
    if raw.dtype.kind in "iu":
        return raw.astype(np.int64) * TIME_FACTORS[unit]
    return np.round(raw * TIME_UNITS[unit]).astype(np.int64)


Part = tuple[np.ndarray, np.ndarray, "np.ndarray | None", list[np.ndarray]]
"""One batch of a topic, decoded: (time ns, log time ns, publish time ns or None, the mapped
sensors' leaf values in plan order)."""


def _plans(spec: InputSpec, sources: Sequence[MappedSource]) -> dict[str, TopicPlan]:
    defs: dict[str, Definition] = {}
    for src in sources:
        for topic, defn in src.definitions().items():
            defs.setdefault(topic, defn)
    return plan(spec, defs)


def _parts(
    spec: InputSpec, sources: Sequence[MappedSource], plans: Mapping[str, TopicPlan]
) -> Iterator[dict[str, list[Part]]]:
    """Per chunk of each source (split files in the order of their first message): the
    decoded batches of each mapped topic."""
    mapping = spec.fields
    assert mapping is not None
    for src in sorted(sources, key=lambda s: s.first_time()) if len(sources) > 1 else sources:
        for batches in src.payloads(set(plans)):
            out: dict[str, list[Part]] = {}
            for topic, batch in batches:
                tp = plans[topic]
                values = decode_batch(tp, batch, str(src.path))
                t = _ns(tp, values, batch.log, mapping.time_unit)
                keep = [values[i] for idx in tp.sensors.values() for i in idx]
                out.setdefault(topic, []).append((t, batch.log.astype(np.int64), batch.pub, keep))
            yield out


def read_mapped(spec: InputSpec, sources: Sequence[MappedSource]):  # noqa: ANN201
    """The whole input as one common table, read through its field mapping: (table,
    warnings)."""
    from imupipe.readers.table_buffer import order_warnings

    plans = _plans(spec, sources)
    parts: dict[str, list[Part]] = {t: [] for t in plans}
    for chunk in _parts(spec, sources, plans):
        for topic, got in chunk.items():
            parts[topic].extend(got)
    _check_counts(spec, {t: sum(len(g[0]) for g in got) for t, got in parts.items()})
    counts: dict[str, list[int]] = {}
    table = _table(spec, plans, parts, sources[0].format, counts)
    assert spec.fields is not None
    kind = spec.fields.time if spec.fields.time in ("header", "log") else "field"
    return table, order_warnings(str(spec.path), kind, counts)


def iter_mapped(
    spec: InputSpec,
    sources: Sequence[MappedSource],
    batch_rows: int,
    carried: Iterator[tuple[list, int]] | None = None,
    warnings: list[str] | None = None,
):  # noqa: ANN201
    """Batches of about ``batch_rows`` rows (whole chunks: a batch ends after the chunk that
    reaches ``batch_rows``), each sorted stably by time within itself, as
    :func:`imupipe.readers.sources.iter_sources` gives them; with each, the carried-over
    messages (``carried``: per chunk, its messages and the bound below which every message has
    been read) up to the batch's last log time. ``warnings``: after the last batch, the stamps
    out of order or repeated (summed over the batches; pairs across a boundary not compared).
    Memory: one batch plus the chunks of the carried messages that overlap it."""
    from imupipe.readers.table_buffer import order_warnings

    plans = _plans(spec, sources)
    parts: dict[str, list[Part]] = {t: [] for t in plans}
    total = dict.fromkeys(plans, 0)
    counts: dict[str, list[int]] = {}
    waiting: list = []
    done = [carried is None]

    def others(upto: int | None) -> list:
        """The carried messages with log time <= ``upto`` (all, when None), in log-time order."""
        nonlocal waiting
        while not done[0]:
            try:
                messages, bound = next(carried)  # type: ignore[arg-type]
            except StopIteration:
                done[0] = True
                break
            waiting.extend(messages)
            if upto is not None and bound > upto:
                break
        waiting.sort(key=lambda m: m.log_time)
        if upto is None:
            out, waiting = waiting, []
            return out
        k = next((i for i, m in enumerate(waiting) if m.log_time > upto), len(waiting))
        out, waiting = waiting[:k], waiting[k:]
        return out

    def flush(last: bool):  # noqa: ANN202
        upto = None if last else max(int(g[1].max()) for got in parts.values() for g in got)
        table = _table(spec, plans, parts, sources[0].format, counts)
        for topic in parts:
            parts[topic] = []
        return table, others(upto)

    rows = 0
    for chunk in _parts(spec, sources, plans):
        for topic, got in chunk.items():
            parts[topic].extend(got)
            n = sum(len(g[0]) for g in got)
            rows += n
            total[topic] += n
        if rows >= batch_rows and rows:
            yield flush(last=False)
            rows = 0
    _check_counts(spec, total)
    if rows:
        yield flush(last=True)
    else:
        rest = others(None)
        if rest:  # carried messages after the last batch's end: an empty table holds them
            yield _table(spec, plans, parts, sources[0].format, {}), rest
    if warnings is not None:
        assert spec.fields is not None
        kind = spec.fields.time if spec.fields.time in ("header", "log") else "field"
        warnings += order_warnings(str(spec.path), kind, counts)


def _check_counts(spec: InputSpec, total: Mapping[str, int]) -> None:
    for topic, n in total.items():
        if not n:
            raise ReadError(f"{spec.path}: topic '{topic}' has no messages")


def _table(
    spec: InputSpec,
    plans: Mapping[str, TopicPlan],
    parts: Mapping[str, list[Part]],
    fmt: str,
    counts: dict[str, list[int]],
):  # noqa: ANN202
    """The common table of ``parts`` (one row per message; see the module docstring); adds the
    stamps out of order / repeated per topic to ``counts``."""
    import pyarrow as pa

    from imupipe.readers.table import make_table

    mapping = spec.fields
    assert mapping is not None
    # one row per message, topics in mapping order, each topic's messages in log order; then
    # sorted stably by time (no sort when they already are: one topic, in order)
    empty = np.zeros(0, np.int64)
    ts = [np.concatenate([g[0] for g in parts[topic]] or [empty]) for topic in plans]
    sizes = [len(x) for x in ts]
    edges = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    t = np.concatenate(ts).astype(np.int64) if len(ts) > 1 else ts[0].astype(np.int64)
    log = np.concatenate([g[1] for topic in plans for g in parts[topic]] or [empty])
    has_pub = any(g[2] is not None for got in parts.values() for g in got)
    pub = (
        np.concatenate([g[1] if g[2] is None else g[2] for tp in plans for g in parts[tp]])
        if has_pub
        else None
    )
    for topic, tt in zip(plans, ts, strict=True):
        back = tt[1:] < tt[:-1]
        moved = int(np.count_nonzero(tt < np.maximum.accumulate(tt))) if back.any() else 0
        have = counts.setdefault(topic, [0, 0])
        have[0] += moved
        have[1] += int(np.count_nonzero(tt[1:] == tt[:-1]))
    n = len(t)
    order = None if bool(np.all(t[1:] >= t[:-1])) else np.argsort(t, kind="stable")
    given: dict[str, np.ndarray] = {}
    valid: dict[str, np.ndarray] = {}
    for k, (topic, tp) in enumerate(plans.items()):
        got = parts[topic]
        lo, hi = int(edges[k]), int(edges[k + 1])
        first = 0
        for sensor, idx in tp.sensors.items():
            # column-major (n, 3): each column one contiguous array, taken by the table as it
            # is (row-major, the table copied every column out of it)
            block = np.empty((len(idx), hi - lo)).T
            for c in range(len(idx)):
                if got:
                    np.concatenate(
                        [g[3][first + c] for g in got], out=block[:, c], casting="unsafe"
                    )
            first += len(idx)
            if sensor in UNITS and UNITS[sensor][getattr(mapping, f"{sensor}_unit")] != 1.0:
                block *= UNITS[sensor][getattr(mapping, f"{sensor}_unit")]
            if len(plans) == 1:
                full = block
            else:
                full = np.zeros((len(idx), n)).T
                full[lo:hi] = block
                mask = np.zeros(n, bool)
                mask[lo:hi] = True
                valid[sensor] = mask if order is None else mask[order]
            full = full if order is None else full.T[:, order].T
            given[sensor] = full if sensor != "temperature" else full[:, 0]
    if order is not None:
        t, log = t[order], log[order]
        pub = None if pub is None else pub[order]
    stream_topics = {}
    gyro_topic, accel_topic = _topic_of(plans, "gyro"), _topic_of(plans, "accel")
    if gyro_topic and accel_topic and gyro_topic != accel_topic:
        # sampled apart, as with gyro_topic/accel_topic: each row goes back to its own topic
        stream_topics.update(gyro=gyro_topic, accel=accel_topic)
    for sensor, stream in (("gyro", "imu"), ("accel", "imu"), ("mag", "mag")):
        if sensor not in stream_topics:
            stream_topics.setdefault(stream, _topic_of(plans, sensor))
    stream_topics["temperature"] = _topic_of(plans, "temperature")
    topics_meta = {s: t for s, t in stream_topics.items() if t is not None}
    meta = {
        "source": str(spec.path),
        "format": fmt,
        "topics": topics_meta,
        "types": {s: plans[t].mtype.name for s, t in topics_meta.items()},
        "fields": {s: _topic_of(plans, s) for s in SENSORS if _topic_of(plans, s)},
    }
    units = {s: "raw" for s in UNITS if s in given and getattr(mapping, f"{s}_unit") == "raw"}
    if units:
        meta["units"] = units
    extra: dict[str, np.ndarray] = {"log_time_ns": log}
    if pub is not None:
        extra["publish_time_ns"] = pub
    table = make_table(
        t,
        gyro=given.get("gyro"),
        accel=given.get("accel"),
        mag=given.get("mag"),
        temperature=given.get("temperature"),
        valid=valid,
        extra=extra,
        metadata=meta,
    )
    assert isinstance(table, pa.Table)
    return table


def _topic_of(plans: Mapping[str, TopicPlan], sensor: str) -> str | None:
    return next((t for t, tp in plans.items() if sensor in tp.sensors), None)


# --- what inspect shows ----------------------------------------------------------------------

KEYWORDS: dict[str, tuple[str, ...]] = {
    "gyro": ("gyro", "angular_velocity", "angular_rate", "ang_vel", "omega"),
    "accel": ("accel", "linear_acceleration", "acc", "specific_force"),
    "mag": ("mag", "magnetic_field", "compass"),
    "temperature": ("temperature", "temp"),
}
"""Field names (parts) that suggest a sensor, in order of preference."""


def suggest(topic: str, mtype: MessageType) -> dict[str, str]:
    """The ``[inputs.NAME.fields]`` keys that would read this topic's sensors, by the field
    names (``gyro_rad``, ``angular_velocity``, ``accelerometer_m_s2``...): a Vector3-like
    struct or 3-element array for gyro, accel and mag, a number for temperature; ``time`` is
    ``header`` when the message has a header stamp, else a time struct or a number named
    ``timestamp`` (its unit to be set), else absent (the log time)."""
    vectors: list[tuple[str, Node]] = []
    numbers: list[tuple[str, Node]] = []

    def visit(node: Node, prefix: str) -> None:
        for c in node.children:
            path = f"{prefix}{c.name}"
            if c.kind == "struct":
                if _time_struct(c) is None and len(_xyz(c)) == 3:
                    vectors.append((path, c))
                else:
                    visit(c, path + ".")
            elif c.kind == "array" and c.count == 3 and c.item and c.item.kind == "number":
                vectors.append((path, c))
            elif c.kind == "number":
                numbers.append((path, c))

    visit(mtype.root, "")
    out: dict[str, str] = {}
    for sensor, words in KEYWORDS.items():
        pool = numbers if sensor == "temperature" else vectors
        for word in words:
            hit = next((p for p, _ in pool if word in p.lower().split(".")[-1]), None)
            if hit is not None:
                out[sensor] = f"{topic}.{hit}"
                break
    if not out:
        return out
    header = mtype.root.child("header")
    stamp = header.child("stamp") if header is not None else None
    if stamp is not None and _time_struct(stamp) is not None:
        out["time"] = "header"
    else:
        for c in mtype.root.children:
            if c.name.lower() in ("timestamp", "stamp", "time", "t") and (
                c.kind == "number" or _time_struct(c) is not None
            ):
                out["time"] = f"{topic}.{c.name}"
                if c.kind == "number":
                    out["time_unit"] = "set: s, ms, us or ns"
                break
    return out


def _xyz(node: Node) -> list[Node]:
    named = {c.name.lower(): c for c in node.children if c.kind == "number"}
    return [named[a] for a in "xyz" if a in named]


def describe_topics(sources: Sequence[MappedSource], skip: set[str]) -> dict[str, dict]:
    """Topic -> {type, encoding, fields [(path, type)], mapping (suggested keys)} for every
    topic of a type outside ``skip`` (the sensor_msgs types the topic keys read); a
    definition that cannot be used is named in ``error``."""
    out: dict[str, dict] = {}
    for src in sources:
        for topic, defn in src.definitions().items():
            if topic in out or normalize_type(defn.msgtype) in skip:
                continue
            entry: dict = {"type": defn.msgtype, "encoding": defn.encoding}
            try:
                mtype = message_type(defn)
            except Exception as exc:  # noqa: BLE001 - shown, not raised: inspect describes
                entry["error"] = f"cannot use its definition ({exc})"
            else:
                entry["fields"] = mtype.leaves()
                entry["mapping"] = suggest(topic, mtype)
            out[topic] = entry
    return out
