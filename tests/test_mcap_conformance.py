"""The MCAP conformance suite (foxglove/mcap ``tests/conformance``, MIT) read by imupipe.

Every file of the suite (416, written by :mod:`mcap_conformance` and checked byte for byte
against the suite's checksums; seven of them also as the real files in
``tests/data/mcap_conformance``) is read by imupipe's MCAP reader and by ``imupipe inspect``,
and compared with the ``mcap`` library's ``NonSeekingReader`` (which reads the file record by
record, front to back, trusting no summary): the same topics with the same types, and per topic
the same messages (log time, publish time, payload).

The same feature combinations written around ROS 2 ``sensor_msgs/msg/Imu`` messages (out of
order, on two channels of one topic) are read by ``read_input`` (``run``) and ``iter_input``
(``convert``), and compared with ``mcap_ros2``'s decoding.
"""

from __future__ import annotations

import hashlib
from collections import Counter
from pathlib import Path

import mcap_conformance as mc
import numpy as np
import pytest

from imupipe.pipeline.inspect_log import inspect
from imupipe.readers.mcap.reader import McapSource
from imupipe.readers.spec import InputSpec

from conftest import TEST_DATA

DATA = TEST_DATA / "mcap_conformance"


def manifest() -> dict[str, tuple[str, int]]:
    """File name -> (sha256, size) of the suite's files."""
    out = {}
    for line in (DATA / "MANIFEST.txt").read_text().splitlines():
        digest, size, fname = line.split()
        out[fname] = (digest, int(size))
    return out


@pytest.fixture(scope="module")
def suite(tmp_path_factory) -> dict[str, Path]:
    """The whole suite written to a temporary folder: file name -> path."""
    folder = tmp_path_factory.mktemp("mcap_conformance")
    out = {}
    for fname, data in mc.variants():
        (folder / fname).write_bytes(data)
        out[fname] = folder / fname
    return out


def reference(path: Path) -> tuple[dict[str, str], list[tuple]]:
    """(topic -> schema name, messages as (topic, log time, publish time, payload)) by the
    ``mcap`` library reading the file front to back."""
    from mcap.reader import NonSeekingReader
    from mcap.records import Channel, Schema
    from mcap.stream_reader import StreamReader

    types: dict[str, str] = {}
    schemas: dict[int, str] = {}
    with open(path, "rb") as fh:
        for rec in StreamReader(fh).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec.name
            elif isinstance(rec, Channel):
                types[rec.topic] = schemas.get(rec.schema_id, "")
    with open(path, "rb") as fh:
        messages = [
            (channel.topic, m.log_time, m.publish_time, bytes(m.data))
            for _, channel, m in NonSeekingReader(fh).iter_messages(log_time_order=False)
        ]
    return types, messages


def observed(path: Path) -> tuple[dict[str, str], list[tuple], dict[str, np.ndarray]]:
    """(topic -> type, messages, topic -> log times) as imupipe's MCAP reader reads them."""
    src = McapSource(path)
    messages = [
        (m.topic, m.log_time, m.publish_time, m.data)
        for _, raw, _ in src.chunks({}, carry=True, decode=False)
        for m in raw
    ]
    return src.topic_types(), messages, src.topic_times()


def disagreement(path: Path) -> str | None:
    """What imupipe reads differently from the reference in ``path`` (None: nothing)."""
    want_types, want = reference(path)
    types, got, times = observed(path)
    if types != want_types:
        return f"topics {types} != {want_types}"
    if Counter(got) != Counter(want):
        return f"messages {sorted(got)} != {sorted(want)}"
    for topic in want_types:
        ref = sorted(t for tp, t, _, _ in want if tp == topic)
        if sorted(times.get(topic, np.zeros(0, np.int64)).tolist()) != ref:
            return f"log times of {topic}: {times.get(topic)} != {ref}"
    info = inspect(InputSpec(path=path))
    described = {
        topic: (v["count"], v["start_ns"], v["end_ns"]) for topic, v in info["topics"].items()
    }
    expected = {}
    for topic in want_types:
        ts = [t for tp, t, _, _ in want if tp == topic]
        expected[topic] = (len(ts), min(ts, default=None), max(ts, default=None))
    if described != expected:
        return f"inspect {described} != {expected}"
    return None


def test_generator_writes_the_suite_byte_for_byte(suite):
    """Each file written here is the suite's own, by its sha256; none missing, none extra."""
    want = manifest()
    assert set(suite) == set(want)
    assert len(suite) == 416
    for fname, path in suite.items():
        data = path.read_bytes()
        assert (hashlib.sha256(data).hexdigest(), len(data)) == want[fname], fname


def test_real_files_are_the_generated_ones(suite):
    real = sorted(DATA.glob("*.mcap"))
    assert len(real) == 7
    for path in real:
        assert path.read_bytes() == suite[path.name].read_bytes(), path.name


@pytest.mark.parametrize("path", sorted(DATA.glob("*.mcap")), ids=lambda p: p.stem)
def test_real_conformance_files_read_as_the_reference(path):
    assert disagreement(path) is None


def test_whole_suite_reads_as_the_reference(suite):
    """All 416 files: topics, types, messages and inspect's counts and times as the reference."""
    wrong = {fname: why for fname, path in sorted(suite.items()) if (why := disagreement(path))}
    assert not wrong, f"{len(wrong)} of {len(suite)} files differ: {dict(list(wrong.items())[:5])}"


def imu_records() -> tuple[mc.Record, ...]:
    """Ten ``sensor_msgs/msg/Imu`` messages on two channels of ``/imu`` (log times out of
    order, as the suite's TenMessages) and two Temperature messages on ``/temp``."""
    from mcap_ros2._dynamic import serialize_dynamic

    from imupipe.pipeline.writers.mcap import msgdef

    rng = np.random.default_rng(3)
    records: list[mc.Record] = []
    encoders = {}
    for sid, typ in ((1, "sensor_msgs/msg/Imu"), (2, "sensor_msgs/msg/Temperature")):
        records.append(mc.Schema(sid, typ, "ros2msg", msgdef(typ).encode()))
        encoders[sid] = serialize_dynamic(typ, msgdef(typ))[typ]
    records += [mc.Channel(1, 1, "/imu", "cdr"), mc.Channel(2, 1, "/imu", "cdr")]
    records.append(mc.Channel(3, 2, "/temp", "cdr"))
    for seq, t in enumerate([0, 2, 1, 3, 3, 5, 4, 7, 8, 9, 6, 10]):
        stamp = 10**18 + 10**6 * seq
        header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "f"}
        if seq < 10:
            v = rng.normal(size=10).tolist()
            fields = {
                "header": header,
                "orientation": dict(zip("xyzw", v[:4], strict=True)),
                "angular_velocity": dict(zip("xyz", v[4:7], strict=True)),
                "linear_acceleration": dict(zip("xyz", v[7:], strict=True)),
                **{
                    f"{n}_covariance": rng.uniform(0.1, 1, 9).tolist()
                    for n in ("orientation", "angular_velocity", "linear_acceleration")
                },
            }
            cid, data = 1 + seq % 2, encoders[1](fields)
        else:
            cid, data = (
                3,
                encoders[2]({"header": header, "temperature": 20.0 + seq, "variance": 0.5}),
            )
        records.append(mc.Message(cid, seq, 10**18 + t, 10**18 + t, data))
    return tuple(records)


def test_every_layout_of_imu_messages_runs_and_converts(tmp_path):
    """The suite's feature combinations around Imu and Temperature messages (two channels on
    the Imu topic): ``run``'s read, ``convert``'s batches and ``inspect`` as ``mcap_ros2``
    decodes them, for every layout (padded records, no summary, summaries without channels or
    schemas, unchunked)."""
    from test_mcap_writer_options import check

    layouts = list(mc.variants({"ImuMessages": imu_records()}))
    assert len(layouts) == 154  # as many as the suite writes of TenMessages
    for fname, data in layouts:
        path = tmp_path / fname
        path.write_bytes(data)
        check(path)


@pytest.mark.parametrize("features", [frozenset(), frozenset({"ch", "mx", "st", "chx"})])
def test_message_on_a_channel_never_defined_is_one_line(tmp_path, cli, features):
    """A message whose channel no record defines (invalid by the specification: "A Channel
    record must occur at least once in the file prior to any message referring to its channel
    ID") is refused by ``inspect`` with one line naming the file, exit 2."""
    path = tmp_path / "undefined.mcap"
    records = (*INPUT_EXAMPLE, mc.Message(7, 0, 5, 5, b"\x01"))
    path.write_bytes(mc.write(records, features))
    done = cli("inspect", path)
    assert done.returncode == 2
    assert done.stdout == ""
    (line,) = done.stderr.strip().splitlines()
    assert str(path) in line and "message on channel 7, which the file never defines" in line


INPUT_EXAMPLE = mc.INPUTS["OneMessage"]
