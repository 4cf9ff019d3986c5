"""Issue 17 item 4: ``imupipe inspect`` answers an MCAP file from its summary section (no chunk
read, no numpy) and gives exactly what reading every message's log time gives; a file whose
summary cannot tell (none, no statistics, no message indexes, messages outside chunks) is read
message by message. Files written by the ``mcap`` library's own writer (foxglove/mcap, Python
``mcap.writer.Writer``), with chunks whose times overlap and two channels on one topic."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from mcap.writer import CompressionType, IndexType, Writer

from imupipe.pipeline.inspect_log import _from_messages, _from_summary
from imupipe.readers.spec import InputSpec


def write(path, *, chunked=True, stats=True, indexes=IndexType.ALL, summary=True, seed=0):
    """Three topics (one of them on two channels), log times out of order across chunks."""
    rng = np.random.default_rng(seed)
    with open(path, "wb") as f:
        writer = Writer(
            f,
            chunk_size=2048,
            compression=CompressionType.NONE,
            index_types=indexes,
            use_chunking=chunked,
            use_statistics=stats,
            use_summary_offsets=summary,
            repeat_channels=summary,
            repeat_schemas=summary,
        )
        writer.start()
        imu = writer.register_schema("sensor_msgs/msg/Imu", "ros2msg", b"")
        mag = writer.register_schema("sensor_msgs/MagneticField", "ros1msg", b"")
        channels = [
            writer.register_channel("/imu", "cdr", imu),
            writer.register_channel("/mag", "ros1", mag),
            writer.register_channel("/imu", "cdr", imu),  # a second channel on /imu
            writer.register_channel("/quiet", "cdr", imu),  # no message
        ]
        t = 1_700_000_000_000_000_000 + np.cumsum(rng.integers(1_000_000, 9_000_000, 900))
        t = t + rng.integers(-30_000_000, 30_000_000, len(t))  # not in order
        for i, ti in enumerate(t.tolist()):
            cid = channels[int(rng.choice(3, p=[0.6, 0.3, 0.1]))]
            writer.add_message(cid, ti, bytes(40 + i % 7), ti + 5)
        writer.finish()
    return path


@pytest.mark.parametrize("seed", [0, 1])
def test_summary_answers_as_the_messages_do(tmp_path, seed):
    path = write(tmp_path / "log.mcap", seed=seed)
    described = _from_summary(path)
    assert described is not None
    assert described == _from_messages(InputSpec(path=path))
    types, topics = described
    assert topics["/quiet"]["count"] == 0 and topics["/quiet"]["start_ns"] is None
    assert topics["/imu"]["count"] + topics["/mag"]["count"] == 900


@pytest.mark.parametrize(
    "kind",
    [
        {"summary": False, "stats": False, "indexes": IndexType.NONE},
        {"stats": False},
        {"indexes": IndexType.CHUNK},  # chunk indexes without message indexes
        {"chunked": False},  # messages outside chunks
    ],
)
def test_summary_that_cannot_tell_falls_back(tmp_path, kind):
    path = write(tmp_path / "log.mcap", **kind)
    assert _from_summary(path) is None
    entries = _from_messages(InputSpec(path=path))[1]
    assert entries["/imu"]["count"] + entries["/mag"]["count"] == 900


def test_inspect_mcap_imports_neither_numpy_nor_pyarrow(tmp_path):
    """Nor the ``mcap`` library: the summary is read by :mod:`imupipe.readers.mcap.records`."""
    path = write(tmp_path / "log.mcap")
    code = (
        "import sys; from imupipe.pipeline.cli import main; main(['inspect', sys.argv[1]]); "
        "print(sorted(m for m in ('numpy', 'pyarrow', 'mcap') if m in sys.modules))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert "/imu" in proc.stdout
    assert proc.stdout.strip().splitlines()[-1] == "[]"
