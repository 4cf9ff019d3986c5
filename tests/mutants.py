"""Seeded mutation fuzzing of real logs, judged against each format's reference library (issue 40).

Each mutant is a real log (``tests/data``, ``../shared/data``) with one damage: cut short, bits
flipped, a range zeroed, a range repeated, or one record edited where the format keeps its
structure (a ULog record's size, type or ``msg_id``; a DataFlash ``FMT``'s length, field
formats, column names or name). imupipe reads it (``read_input``, then ``inspect``); the
reference library reads the same bytes:

| format | reference |
|---|---|
| ULog | pyulog's ``ULog`` (stock) |
| DataFlash | pymavlink's ``DFReader_binary``, ``recv_msg`` to the end |
| MCAP | mcap's ``StreamReader`` (CRCs checked), messages up to its first error |
| ROS 1 bag | rosbags' ``AnyReader``, messages up to its first error |
| ROS 2 bag (sqlite3) | the ``messages`` table, per topic |

The verdict of a mutant (:func:`judge`): ``refused`` (an ``ImupipeError``: one line), ``equal``
(every stream imupipe read from the clean log has, in the mutant, at least the reference's
count of its topic), ``warned`` (fewer, with a warning saying what was skipped), or one of the
failures ``silent loss`` (fewer without such a warning), ``traceback`` (any other exception)
and ``hang`` (past :data:`LIMIT_S`).
"""

from __future__ import annotations

import collections
import contextlib
import io
import re
import signal
import sqlite3
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imupipe.pipeline.errors import ImupipeError
from imupipe.pipeline.inspect_log import inspect
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import counts, metadata

from conftest import REPO, SHARED

LIMIT_S = 60
"""A mutant read for longer than this is a hang."""
WARNED = re.compile(
    r"damaged|corrupt|skipped|no whole record|belong to no record|cut|truncat|not read|dropped",
    re.IGNORECASE,
)
"""A warning that says the reader skipped something."""
FAILURES = ("silent loss", "traceback", "hang")


def derived(workdir: Path) -> list[tuple[str, Path]]:
    """An MCAP and a ROS 2 sqlite3 bag made by imupipe's writers from a real ROS 1 bag (the
    razor bag of ``../shared/data``; without it, the readers' test table): no real IMU log of
    those formats is stored."""
    from test_readers import multi_stream_table

    from imupipe.pipeline.writers.bag import write_ros2_bag
    from imupipe.pipeline.writers.mcap import McapTableWriter

    razor = SHARED / "logs" / "madgwick_sparkfun_razor.bag"
    if razor.is_file():
        table, _ = read_input(InputSpec(path=razor))
    else:
        table = multi_stream_table(seed=4).slice(0, 2000)
    with McapTableWriter(workdir / "derived.mcap") as w:
        w.write_table(table)
    write_ros2_bag(workdir / "derived.db3", table)
    return [("mcap", workdir / "derived.mcap"), ("ros2", workdir / "derived.db3")]


def seeds() -> list[tuple[str, Path]]:
    """(format, path) of the real logs present (``../shared/data`` may be absent)."""
    data = REPO / "tests" / "data"
    logs = SHARED / "logs"
    found = [("ulog", p) for p in sorted((data / "px4_ulog").glob("*.ulg"))]
    found += [("ulog", p) for p in sorted((logs / "px4_ulog").glob("*.ulg"))]
    found += [("ulog", p) for p in sorted((logs / "peer_fixtures").glob("*.ulg"))]
    found += [
        ("dataflash", p) for p in sorted((logs / "ardupilot_flights").glob("*/*.[bB][iI][nN]"))
    ]
    found += [("ros1", p) for p in sorted(logs.glob("*.bag"))]
    return [(f, p) for f, p in found if p.is_file()]


# -- mutations -------------------------------------------------------------------------------


def _ulog_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, size, type) of a ULog's records after its 16-byte header."""
    out, at = [], 16
    while at + 3 <= len(data):
        size, typ = struct.unpack_from("<HB", data, at)
        out.append((at, size, typ))
        at += 3 + size
    return out


def _fmt_records(data: bytes) -> list[int]:
    """Offsets of a DataFlash log's ``FMT`` records."""
    return [m.start() for m in re.finditer(b"\xa3\x95\x80", data)]


def _record_edit(fmt: str, data: bytearray, rng: np.random.Generator) -> str:
    """One targeted edit of a record header (ULog) or an ``FMT`` (DataFlash), in place."""
    if fmt == "ulog":
        recs = [r for r in _ulog_records(bytes(data)) if r[2] in (ord("D"), ord("A"))]
        at, size, typ = recs[int(rng.integers(len(recs)))]
        how = ["size 0", "msg_id 0", "type", "size"][int(rng.integers(4))]
        if how == "size 0":
            data[at : at + 2] = b"\0\0"
        elif how == "msg_id 0":
            data[at + 3 + (typ == ord("A")) : at + 5 + (typ == ord("A"))] = b"\0\0"
        elif how == "type":
            data[at + 2] = int(rng.integers(256))
        else:
            data[at : at + 2] = int(rng.integers(65536)).to_bytes(2, "little")
        return f"{chr(typ)} record at byte {at}: {how}"
    if fmt == "dataflash":
        fmts = _fmt_records(bytes(data))
        at = fmts[int(rng.integers(len(fmts)))]
        how = ["length", "format", "column", "name"][int(rng.integers(4))]
        if how == "length":
            data[at + 4] = (data[at + 4] + int(rng.choice([-4, -2, -1, 1, 2, 4]))) % 256
        elif how == "format":
            end = data.index(0, at + 9) if 0 in data[at + 9 : at + 25] else at + 25
            data[at + 9 + int(rng.integers(max(end - at - 9, 1)))] = ord(
                rng.choice(list("BhIfQcZ"))
            )
        elif how == "column":
            data[at + 25 + int(rng.integers(8))] = ord(rng.choice(list("XYZ_q")))
        else:
            data[at + 5 + int(rng.integers(3))] = ord(rng.choice(list("XYZ")))
        return f"FMT at byte {at}: {how}"
    i = int(rng.integers(min(len(data), 4096)))  # the header, schemas, first records
    data[i] ^= 1 << int(rng.integers(8))
    return f"flip in the head at byte {i}"


KINDS = ("truncate", "flip", "zero", "duplicate", "record")


def mutate(fmt: str, data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """One mutant of ``data`` and what was done to it."""
    buf = bytearray(data)
    kind = KINDS[int(rng.integers(len(KINDS)))]
    n = len(buf)
    if kind == "truncate":
        cut = int(rng.integers(1, n))
        return bytes(buf[:cut]), f"cut at byte {cut}"
    if kind == "flip":
        where = sorted(int(i) for i in rng.integers(0, n, int(rng.integers(1, 9))))
        for i in where:
            buf[i] ^= 1 << int(rng.integers(8))
        return bytes(buf), f"bits flipped at bytes {where}"
    if kind == "zero":
        i, k = int(rng.integers(n)), int(rng.integers(1, 4097))
        buf[i : i + k] = bytes(len(buf[i : i + k]))
        return bytes(buf), f"{k} bytes zeroed at byte {i}"
    if kind == "duplicate":
        i, k = int(rng.integers(n)), int(rng.integers(1, 4097))
        return bytes(buf[: i + k] + buf[i : i + k] + buf[i + k :]), f"{k} bytes at {i} repeated"
    what = _record_edit(fmt, buf, rng)
    return bytes(buf), what


# -- the references --------------------------------------------------------------------------


def _pyulog(path: Path) -> dict[str, int]:
    from pyulog import ULog

    try:
        with contextlib.redirect_stdout(io.StringIO()):
            log = ULog(str(path))
    except Exception:  # noqa: BLE001 - the reference refuses the file
        return {}
    return {
        d.name if d.multi_id == 0 else f"{d.name}_{d.multi_id}": len(d.data["timestamp"])
        for d in log.data_list
        if "timestamp" in d.data
    }


def _pymavlink(path: Path) -> dict[str, int]:
    from pymavlink import DFReader

    found: collections.Counter[str] = collections.Counter()
    quiet = io.StringIO()
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            reader = DFReader.DFReader_binary(str(path), zero_time_base=True)
            while (msg := reader.recv_msg()) is not None:
                name, i = msg.get_type(), getattr(msg, "I", 0)
                found[name if not isinstance(i, int) or i == 0 else f"{name}_{i}"] += 1
    except Exception:  # noqa: BLE001 - the reference stops at its first error
        pass
    return dict(found)


def _rosbags(path: Path) -> dict[str, int]:
    from rosbags.highlevel import AnyReader

    found: collections.Counter[str] = collections.Counter()
    try:
        with AnyReader([path]) as reader:
            for conn, _, _ in reader.messages():
                found[conn.topic] += 1
    except Exception:  # noqa: BLE001 - the reference stops at its first error
        pass
    return dict(found)


def _mcap(path: Path) -> dict[str, int]:
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    found: collections.Counter[str] = collections.Counter()
    topics: dict[int, str] = {}
    try:
        with open(path, "rb") as fh:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    found[topics.get(rec.channel_id, "?")] += 1
    except Exception:  # noqa: BLE001 - the reference stops at its first error
        pass
    return dict(found)


def _sqlite(path: Path) -> dict[str, int]:
    try:
        with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
            rows = db.execute(
                "SELECT topics.name, count(*) FROM messages JOIN topics "
                "ON messages.topic_id = topics.id GROUP BY topics.name"
            ).fetchall()
    except sqlite3.Error:
        return {}
    return {str(n): int(c) for n, c in rows}


REFERENCES: dict[str, Callable[[Path], dict[str, int]]] = {
    "ulog": _pyulog,
    "dataflash": _pymavlink,
    "ros1": _rosbags,
    "mcap": _mcap,
    "ros2": _sqlite,
}


# -- the verdict -----------------------------------------------------------------------------


@dataclass
class Verdict:
    kind: str
    detail: str = ""
    unsaid: str = ""
    """Streams with fewer rows than the clean log's and no warning, where the reference lost
    them too (a cut or zeroed tail: nothing in the file says it is damaged); a figure of the
    campaign, not a failure."""


def clean_read(path: Path) -> tuple[dict[str, str], dict[str, tuple[str, int]]]:
    """(the input keys a read of the clean log needs: ``imu_topic`` for a log of several IMUs,
    its first; stream -> (its topic, rows) of that read)."""
    keys: dict[str, str] = {}
    try:
        table, _ = read_input(InputSpec(path=path))
    except ImupipeError as exc:
        several = re.search(r"several IMU instances \(([^,)]+)", str(exc))
        if several is None:
            raise
        keys = {"imu_topic": several.group(1)}
        table, _ = read_input(InputSpec(path=path, **keys))
    topics = metadata(table).get("topics", {})
    return keys, {s: (_topic(topics.get(s, "")), n) for s, n in counts(table).items()}


def _topic(name: str) -> str:
    """The reference's name of a table topic (a ULog or DataFlash temperature is a field of
    its sensor's topic; ROS names keep their slash)."""
    return name.removesuffix("/temperature")


class _Alarm(Exception):
    pass


def _on_alarm(*_: object) -> None:
    raise _Alarm


def judge(fmt: str, path: Path, clean: dict[str, tuple[str, int]], keys: dict[str, str]) -> Verdict:
    """The verdict on the mutant at ``path`` (see the module docstring); ``keys`` and
    ``clean`` are :func:`clean_read` of the log it was made from."""
    old = signal.signal(signal.SIGALRM, _on_alarm)
    signal.alarm(LIMIT_S)
    try:
        try:
            table, warnings = read_input(InputSpec(path=path, **keys))
            inspect(InputSpec(path=path, **keys))
        except ImupipeError as exc:
            if "\n" in str(exc):
                return Verdict("traceback", f"an error of several lines: {exc!r}")
            return Verdict("refused", str(exc))
        except _Alarm:
            return Verdict("hang")
        except Exception as exc:  # noqa: BLE001 - what the campaign looks for
            return Verdict("traceback", f"{type(exc).__name__}: {exc}")
        reference = REFERENCES[fmt](path)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    topics = metadata(table).get("topics", {})
    ours = counts(table)
    short = []
    for stream, (topic, _) in clean.items():
        if topic.endswith("/magnetometer"):
            continue  # old PX4 sensor_combined: a subset of the topic's messages
        want = reference.get(topic, 0)
        got = ours.get(stream, 0) if _topic(topics.get(stream, "")) == topic else 0
        if got < want:
            short.append(f"{stream} ({topic}): {got} of {want}")
    said = [w for w in warnings if WARNED.search(w)]
    fewer = [
        f"{stream}: {ours.get(stream, 0)} of {n}"
        for stream, (_, n) in clean.items()
        if ours.get(stream, 0) < n
    ]
    unsaid = "" if said else "; ".join(fewer)
    if not short:
        return Verdict("equal", unsaid=unsaid)
    if said:
        return Verdict("warned", "; ".join(short))
    return Verdict("silent loss", "; ".join(short) + f"; warnings: {warnings}", unsaid)


def campaign(
    count: int,
    seed: int,
    workdir: Path,
    limit_bytes: int | None = None,
    only: set[int] | None = None,
) -> list[tuple[str, str, str, Verdict]]:
    """``count`` mutants spread over every seed log (seeded), each judged: (log, format, what
    was done, verdict). ``limit_bytes`` cuts each seed log first (a real log's first part is
    a shorter real log: the quick run); ``only``: judge only the mutants of these indexes."""
    rng = np.random.default_rng(seed)
    logs = seeds() + derived(workdir)
    out = []
    clean_of: dict[Path, tuple[bytes, tuple[dict[str, str], dict[str, tuple[str, int]]]]] = {}
    for i in range(count):
        fmt, src = logs[i % len(logs)]
        if src not in clean_of:
            data = src.read_bytes()
            if limit_bytes is not None and len(data) > limit_bytes and fmt in ("ulog", "dataflash"):
                data = data[:limit_bytes]
            base = workdir / f"clean{len(clean_of)}{src.suffix}"
            base.write_bytes(data)
            clean_of[src] = (data, clean_read(base))
        data, (keys, clean) = clean_of[src]
        mutant, what = mutate(fmt, data, rng)
        if only is not None and i not in only:  # drawn all the same: the sequence is kept
            continue
        path = workdir / f"mutant{src.suffix}"
        path.write_bytes(mutant)
        out.append((src.name, fmt, what, judge(fmt, path, clean, keys)))
    return out


def chunked_campaign(
    count: int, seed: int, workdir: Path, limit_bytes: int | None, chunk: int = 50
) -> list[tuple[str, str, str, Verdict]]:
    """``count`` mutants as :func:`campaign` runs of ``chunk`` (seeds ``seed * 1000 + k``): the
    campaign of the robustness page (``tests/test_fuzz_mutants.py``, slow)."""
    out = []
    for k in range(count // chunk):
        folder = workdir / f"chunk{k}"
        folder.mkdir()
        out += campaign(chunk, seed * 1000 + k, folder, limit_bytes)
    return out
