"""imupipe's own MCAP records (``readers/mcap/records.py``, issue 39: the mcap library's record
classes cost a one-log ``convert`` 8-15 ms to import) against the mcap library: the same bytes
written, the same fields read, the same summary and attachments read from every MCAP of the
conformance set and from files imupipe writes; a record that does not fit its layout is refused
(:class:`RecordError`), and the count check then reads the file with the library as before."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap import records as lib
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader

from imupipe.pipeline.convert.verify import _library_summary, summary_of
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap
from imupipe.readers.mcap import records
from imupipe.readers.spec import RawMessage

CONFORMANCE = Path(__file__).parent / "data" / "mcap_conformance"

LIBRARY = [
    (records.OP_HEADER, lib.Header("ros2", "imupipe ü")),
    (records.OP_FOOTER, lib.Footer(123, 456, 0xDEADBEEF)),
    (
        records.OP_SCHEMA,
        lib.Schema(id=3, name="sensor_msgs/msg/Imu", encoding="ros2msg", data=b"x\0y"),
    ),
    (
        records.OP_CHANNEL,
        lib.Channel(id=7, topic="/imu", message_encoding="cdr", metadata={}, schema_id=3),
    ),
    (
        records.OP_CHANNEL,
        lib.Channel(
            id=8, topic="/m", message_encoding="cdr", metadata={"a": "b", "ké": ""}, schema_id=0
        ),
    ),
    (
        records.OP_CHUNK_INDEX,
        lib.ChunkIndex(
            chunk_length=99,
            chunk_start_offset=8,
            compression="zstd",
            compressed_size=50,
            message_end_time=2**63,
            message_index_length=30,
            message_index_offsets={1: 200, 65535: 300},
            message_start_time=5,
            uncompressed_size=80,
        ),
    ),
    (
        records.OP_ATTACHMENT,
        lib.Attachment(
            create_time=1,
            log_time=2,
            name="calibration.json",
            media_type="application/json",
            data=b'{"a": 1}',
        ),
    ),
    (
        records.OP_ATTACHMENT_INDEX,
        lib.AttachmentIndex(
            offset=1, length=2, log_time=3, create_time=4, data_size=5, name="n", media_type="t"
        ),
    ),
    (
        records.OP_STATISTICS,
        lib.Statistics(
            attachment_count=1,
            channel_count=2,
            channel_message_counts={1: 10, 2: 2**64 - 1},
            chunk_count=3,
            message_count=4,
            message_end_time=5,
            message_start_time=6,
            metadata_count=7,
            schema_count=8,
        ),
    ),
    (
        records.OP_STATISTICS,
        lib.Statistics(
            attachment_count=0,
            channel_count=0,
            channel_message_counts={},
            chunk_count=0,
            message_count=0,
            message_end_time=0,
            message_start_time=0,
            metadata_count=0,
            schema_count=0,
        ),
    ),
    (records.OP_METADATA_INDEX, lib.MetadataIndex(offset=1, length=2, name="m")),
    (
        records.OP_SUMMARY_OFFSET,
        lib.SummaryOffset(group_opcode=3, group_start=100, group_length=20),
    ),
    (records.OP_DATA_END, lib.DataEnd(0)),
]
"""Every record type imupipe reads or writes, as the library's objects."""


def _library_bytes(record: lib.McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return bytes(builder.end())


def _values(opcode: int, record: lib.McapRecord) -> list:
    """The fields of a library record in the order of :data:`records.LAYOUTS`."""
    names = {
        records.OP_HEADER: "profile library",
        records.OP_FOOTER: "summary_start summary_offset_start summary_crc",
        records.OP_SCHEMA: "id name encoding data",
        records.OP_CHANNEL: "id schema_id topic message_encoding metadata",
        records.OP_CHUNK_INDEX: "message_start_time message_end_time chunk_start_offset "
        "chunk_length message_index_offsets message_index_length compression compressed_size "
        "uncompressed_size",
        records.OP_ATTACHMENT: "log_time create_time name media_type data",
        records.OP_ATTACHMENT_INDEX: "offset length log_time create_time data_size name media_type",
        records.OP_STATISTICS: "message_count schema_count channel_count attachment_count "
        "metadata_count chunk_count message_start_time message_end_time channel_message_counts",
        records.OP_METADATA_INDEX: "offset length name",
        records.OP_SUMMARY_OFFSET: "group_opcode group_start group_length",
        records.OP_DATA_END: "data_section_crc",
    }[opcode]
    return [getattr(record, name) for name in names.split()]


@pytest.mark.parametrize("opcode,record", LIBRARY)
def test_pack_writes_the_library_bytes_and_unpack_reads_its_fields(opcode, record):
    want = _library_bytes(record)
    values = _values(opcode, record)
    crc = [0] if opcode == records.OP_ATTACHMENT else []  # computed by pack
    assert records.pack(opcode, *values, *crc) == want
    fields = records.unpack(opcode, want[9:])
    assert fields[: len(values)] == values
    assert records.unpack(opcode, want[9:] + b"more") == fields  # a grown record: rest left


def test_a_body_that_does_not_fit_its_layout_is_refused():
    body = _library_bytes(LIBRARY[4][1])[9:]  # a channel with metadata
    for cut in range(len(body)):
        with pytest.raises(records.RecordError):
            records.unpack(records.OP_CHANNEL, body[:cut])
    stats = _library_bytes(LIBRARY[8][1])[9:]
    odd = stats[:42] + (15).to_bytes(4, "little") + stats[46:]  # counts not whole entries
    with pytest.raises(records.RecordError):
        records.unpack(records.OP_STATISTICS, odd)
    bad = b"\x01\x00" + (2).to_bytes(4, "little") + b"\xff\xfe" + body[8:]  # not UTF-8
    with pytest.raises(records.RecordError):
        records.unpack(records.OP_SCHEMA, bad)


def _written(tmp: Path) -> list[Path]:
    """Files imupipe writes: with and without a calibration, carried-over messages, chunks."""
    table, _ = simulate("static", {"duration_s": 0.5, "rate_hz": 200.0}, 0)
    raw = [
        RawMessage(
            topic="/s",
            log_time=10**9 + i,
            publish_time=10**9 + i,
            data=b"\0\1\0\0" + bytes(i),
            schema_name="std_msgs/msg/String",
            schema_encoding="ros2msg",
            schema_data=b"string data",
            message_encoding="cdr",
        )
        for i in range(20)
    ]
    paths = [tmp / "plain.mcap", tmp / "cal.mcap", tmp / "empty.mcap"]
    write_mcap(paths[0], table)
    write_mcap(paths[1], table, calibration={"chain": []}, carry_over=raw, chunk_bytes=2000)
    write_mcap(paths[2], table.slice(0, 0), calibration={"chain": []})
    return paths


def vars_of(record: object) -> dict:
    """A record's fields by the names of the ``mcap`` library's (slots or dataclass fields)."""
    names = getattr(type(record), "__slots__", None) or list(vars(record))
    library = {"ChunkIndex", "Statistics"}
    assert type(record).__name__ in library
    return {name: getattr(record, name) for name in names}


def test_summary_as_the_library_reads_it(tmp_path):
    """The count check's summary (messages per topic, the attached calibration) of every
    conformance file and of files imupipe writes, read by imupipe and by the library; and the
    summary records ``inspect`` reads (schemas, statistics, chunk indexes) field by field."""
    paths = sorted(CONFORMANCE.glob("*.mcap")) + _written(tmp_path)
    own = 0
    for path in paths:
        with open(path, "rb") as fh:
            want = _library_summary(fh, True)
        with open(path, "rb") as fh:
            assert summary_of(fh) == want, path
            assert summary_of(fh, attachments=False) == (want and (want[0], None))
        with open(path, "rb") as fh:
            try:
                found = records.read_summary(fh)
            except records.RecordError:
                continue
            own += 1
            fh.seek(0)
            summary = make_reader(fh).get_summary()
        assert (found is None) == (summary is None), path
        if found is not None:
            assert {k: c.topic for k, c in found.channels.items()} == {
                k: c.topic for k, c in summary.channels.items()
            }
            assert [a.offset for a in summary.attachment_indexes] == found.attachments
            assert {k: (s.name, s.encoding, s.data) for k, s in found.schemas.items()} == {
                k: (s.name, s.encoding, s.data) for k, s in summary.schemas.items()
            }
            assert [vars_of(c) for c in found.chunk_indexes] == [
                vars_of(c) for c in summary.chunk_indexes
            ], path
            if found.statistics is not None:
                assert vars_of(found.statistics) == vars_of(summary.statistics)
    assert own >= len(paths) // 2  # most read without the library


def test_a_summary_imupipe_cannot_read_is_read_by_the_library(tmp_path):
    """A summary with a record that has no place there (a DataEnd): the library reads it, the
    count check gives what it gives."""
    path = _written(tmp_path)[0]
    data = bytearray(path.read_bytes())
    start = int.from_bytes(data[-37 + 9 : -37 + 17], "little")
    end_record = records.pack(records.OP_DATA_END, 0)
    patched = data[:start] + end_record + data[start:-37]
    footer = records.pack(records.OP_FOOTER, start, 0, 0)
    (tmp_path / "odd.mcap").write_bytes(bytes(patched) + footer + records.MAGIC)
    with open(tmp_path / "odd.mcap", "rb") as fh:
        with pytest.raises(records.RecordError):
            records.read_summary(fh)
        assert summary_of(fh) == _library_summary(fh, True) != None  # noqa: E711
