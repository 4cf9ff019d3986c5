"""The MCAP reader's per-file shortcuts (issue 39) read what the general path reads, byte for byte.

A small file (:data:`imupipe.readers.mcap.fast.SMALL_FILE`) is read whole in one read and its
chunks decompressed in the reading thread; a large one is walked record by record with its
chunks read by ``pread`` in worker threads. The Schema and Channel records are parsed once per
process (by their bytes) and the Statistics record is unpacked at once. Each test here reads the
same files both ways and compares the Arrow IPC bytes of every table (metadata included), the
carried-over messages and the warnings.
"""

from __future__ import annotations

import functools
import io
from pathlib import Path

import pyarrow as pa
import pyarrow.ipc  # noqa: F401
import pytest
from mcap.data_stream import ReadDataStream
from mcap.records import Statistics
from test_readers import multi_stream_table

from imupipe.pipeline.writers.mcap import write_mcap
from imupipe.readers import dispatch
from imupipe.readers.errors import ReadError
from imupipe.readers.mcap import fast, records
from imupipe.readers.spec import InputSpec

CONFORMANCE = Path(__file__).parent / "data" / "mcap_conformance"


def _ipc(table: pa.Table) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()


def _everything(path: Path, read_truncated: bool = False) -> object:
    """Every table (whole and in batches of 200 rows), carried-over message and warning a read of
    ``path`` gives, or the error it raises."""
    spec = InputSpec(path=path, read_truncated=read_truncated)
    try:
        table, warned = dispatch.read_input(spec)
        batches, warnings = [], []
        for batch, raw in dispatch.iter_input(spec, batch_rows=200, warnings=warnings):
            batches.append((_ipc(batch), [(m.topic, m.log_time, m.data) for m in raw]))
        return _ipc(table), warned, batches, warnings
    except ReadError as exc:
        return str(exc)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """A multi-stream log in small chunks (several per stream), a copy cut off inside its
    chunks, and the conformance files."""
    d = tmp_path_factory.mktemp("small")
    full = d / "chunks.mcap"
    write_mcap(full, multi_stream_table(), chunk_bytes=4000)
    data = full.read_bytes()
    (d / "cut.mcap").write_bytes(data[: len(data) * 2 // 3])
    return [full, d / "cut.mcap", *sorted(CONFORMANCE.glob("*.mcap"))]


def test_small_file_path_reads_what_the_large_one_reads(logs, monkeypatch):
    """Read whole (one read, chunks in the reading thread) and walked record by record (pread,
    worker threads): the same tables, batches, carried-over messages, warnings and errors."""
    assert all(p.stat().st_size <= fast.SMALL_FILE for p in logs)
    small = {p: _everything(p, p.name == "cut.mcap") for p in logs}
    monkeypatch.setattr(fast, "SMALL_FILE", 0)
    fast._PARSED.clear()  # the records parsed afresh too
    large = {p: _everything(p, p.name == "cut.mcap") for p in logs}
    assert small == large
    assert isinstance(small[logs[0]], tuple) and len(small[logs[0]][2]) > 1  # batches read


def test_statistics_unpacked_as_the_mcap_library_reads_them(logs):
    """The Statistics record of every file, unpacked by imupipe (issue 39: the mcap library's
    record classes are not imported), equals the mcap library's; one whose counts are not whole
    entries or run past the record is left to the library (which reads what it can, or fails:
    an error naming the record)."""
    seen = 0
    for path in logs[:1] + logs[2:]:
        data = path.read_bytes()
        mcap = fast.McapFile(path)
        pos = 8
        while pos + 9 <= len(data) - 8:
            opcode, length = data[pos], int.from_bytes(data[pos + 1 : pos + 9], "little")
            body = data[pos + 9 : pos + 9 + length]
            if opcode == fast.OP_STATISTICS:
                want = Statistics.read(ReadDataStream(io.BytesIO(body)))
                assert _fields(mcap._read_record(fast.OP_STATISTICS, body)) == _fields(want)
                seen += 1
            pos += 9 + length
    assert seen >= 3
    for length in (0, 7, 10, 1000):  # whole entries or not, within the record or past it
        odd = bytearray(body)
        odd[42:46] = length.to_bytes(4, "little")
        try:
            want = _fields(Statistics.read(ReadDataStream(io.BytesIO(bytes(odd)))))
        except Exception as exc:  # noqa: BLE001 - the library's own error, named in ReadError
            want = f"{path}: corrupt MCAP record (opcode 0xb): {exc}"
        got = _outcome(functools.partial(mcap._read_record, fast.OP_STATISTICS), bytes(odd))
        assert (got if isinstance(got, str) else _fields(got)) == want


def _fields(stats: object) -> tuple:
    """A Statistics record's fields (imupipe's or the mcap library's)."""
    return tuple(getattr(stats, name) for name in records.Statistics.__slots__)


def _outcome(fn, *args) -> object:  # noqa: ANN001
    """What ``fn(*args)`` returns, or the message of the ReadError it raises."""
    try:
        return fn(*args)
    except ReadError as exc:
        return str(exc)
