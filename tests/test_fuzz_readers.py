"""Issue 3: random truncations and byte flips of valid logs never crash the readers.

Hypothesis cuts and flips bytes of small MCAP files (zstd, and uncompressed without CRCs so that
flips reach the payloads), ROS 1 bags (lz4 and uncompressed) and a ROS 2 sqlite3 bag, then reads
each with ``read_input``, ``carry_over`` and ``inspect``: the only acceptable failure is an
``ImupipeError`` (one line for the user); nothing may raise anything else or hang (deadline).
CI runs a fixed set of 40 examples per file; ``IMUPIPE_FUZZ_EXAMPLES=600`` explores at random.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType, Writer
from test_readers import multi_stream_table

from imupipe.pipeline.errors import ImupipeError
from imupipe.pipeline.inspect_log import inspect
from imupipe.pipeline.writers.bag import write_ros1_bag, write_ros2_bag
from imupipe.pipeline.writers.mcap import McapTableWriter, encode_stream, msgdef
from imupipe.readers.dispatch import carry_over, read_input
from imupipe.readers.spec import InputSpec, RawMessage
from imupipe.readers.table import counts, sensor

CHATTER = b"string data\n"


def _small_table():
    return multi_stream_table(seed=4).slice(0, 60)


def _chatter(n: int = 4) -> list[RawMessage]:
    out = []
    for i in range(n):
        s = f"hi {i}".encode() + b"\0"
        cdr = b"\x00\x01\x00\x00" + len(s).to_bytes(4, "little") + s
        out.append(
            RawMessage("/chatter", "std_msgs/msg/String", "ros2msg", CHATTER, "cdr", cdr, i, i)
        )
    return out


def _plain_mcap(path, table) -> None:
    """Uncompressed, no CRCs: flipped bytes reach the payloads and record headers."""
    log = table.column("log_time_ns").to_numpy()
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE, enable_crcs=False, chunk_size=600)
        w.start(profile="ros2")
        for stream, typ in (
            ("imu", "sensor_msgs/msg/Imu"),
            ("mag", "sensor_msgs/msg/MagneticField"),
        ):
            cid = w.register_channel(
                f"/{stream}", "cdr", w.register_schema(typ, "ros2msg", msgdef(typ).encode())
            )
            rows, groups = encode_stream(table, stream)
            for sel, payloads in groups:
                for i, p in zip(sel.tolist(), payloads, strict=True):
                    t = int(log[rows[i]])
                    w.add_message(cid, log_time=t, publish_time=t, data=p.tobytes())
        w.finish()


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    table = _small_table()
    with McapTableWriter(d / "zstd.mcap", calibration={"x": 1}) as w:
        w.write_table(table)
        w.write_raw(_chatter())
    _plain_mcap(d / "plain.mcap", table)
    write_ros1_bag(d / "lz4.bag", table)
    write_ros1_bag(d / "plain.bag", table, compression="none")
    write_ros2_bag(d / "bag.db3", table)
    return {p.name: p.read_bytes() for p in d.iterdir()}


def _read_everything(path) -> None:
    spec = InputSpec(path=path)
    for fn in (read_input, carry_over, inspect):
        try:
            fn(spec)
        except ImupipeError as exc:
            assert "\n" not in str(exc)


NAMES = ["zstd.mcap", "plain.mcap", "lz4.bag", "plain.bag", "bag.db3"]


@pytest.mark.parametrize("name", NAMES)
def test_seed_files_read(seeds, tmp_path, name):
    path = tmp_path / name
    path.write_bytes(seeds[name])
    table, _ = read_input(InputSpec(path=path))
    assert table.num_rows > 0


@pytest.mark.parametrize("name", NAMES)
@settings(
    max_examples=int(os.environ.get("IMUPIPE_FUZZ_EXAMPLES", "40")),
    derandomize="IMUPIPE_FUZZ_EXAMPLES" not in os.environ,  # CI: the same 40; set it to explore
    deadline=5000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    cut=st.floats(0.0, 1.0),
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), max_size=6),
)
def test_truncations_and_byte_flips_never_crash(seeds, tmp_path, name, cut, flips):
    data = bytearray(seeds[name])
    for where, xor in flips:
        data[min(int(where * len(data)), len(data) - 1)] ^= xor
    if cut < 0.5:  # half the examples are truncated too
        data = data[: int(cut * 2 * len(data))]
    path = tmp_path / name
    path.write_bytes(bytes(data))
    _read_everything(path)


def test_flipped_payload_is_caught_not_misread(seeds, tmp_path):
    """A flipped string length inside an uncompressed Imu payload is an error naming the topic,
    never a silently shifted decode."""
    data = bytearray(seeds["plain.mcap"])
    rows, groups = encode_stream(_small_table(), "imu")
    payload = groups[0][1][0].tobytes()
    start = bytes(data).index(payload)
    data[start + 12] = 250  # the frame_id length (uint32 after encapsulation, sec, nanosec)
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(ImupipeError, match=r"flipped.mcap: topic '/(imu|mag)'"):
        read_input(InputSpec(path=path))


# -- CSV -------------------------------------------------------------------------------------

CSV_NAMES = ["t_ns", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)


@st.composite
def csv_layouts(draw):
    """A small IMU table and a way of writing it as text (what loggers and spreadsheets do)."""
    n = draw(st.integers(1, 25))
    t = np.cumsum(draw(st.lists(st.integers(1, 2**40), min_size=n, max_size=n)))
    values = np.array(draw(st.lists(FINITE, min_size=6 * n, max_size=6 * n))).reshape(n, 6)
    empty = np.array(draw(st.lists(st.booleans(), min_size=6 * n, max_size=6 * n))).reshape(n, 6)
    nan = np.array(draw(st.lists(st.booleans(), min_size=6 * n, max_size=6 * n))).reshape(n, 6)
    delimiter = draw(st.sampled_from([",", ";", "\t"]))
    return {
        "t": t,
        "values": np.where(nan & ~empty, np.nan, values),
        "empty": empty,
        "delimiter": delimiter,
        "comma": delimiter != "," and draw(st.booleans()),
        "end": draw(st.sampled_from(["\n", "\r\n"])),
        "bom": draw(st.booleans()),
        "quote": draw(st.booleans()),
        "trailing": draw(st.booleans()),
        "metadata": draw(st.lists(st.sampled_from(["logger v2", "Fs,100", "a;b"]), max_size=3)),
        "last_newline": draw(st.booleans()),
    }


def _csv_text(c) -> bytes:
    def cell(v: float) -> str:
        s = repr(float(v))
        return s.replace(".", ",") if c["comma"] else s

    q = '"' if c["quote"] else ""
    d = c["delimiter"]
    lines = list(c["metadata"]) + [
        d.join(q + n + q for n in CSV_NAMES) + (d if c["trailing"] else "")
    ]
    for ti, row, empty in zip(c["t"], c["values"], c["empty"], strict=True):
        cells = [str(int(ti))] + ["" if e else cell(v) for v, e in zip(row, empty, strict=True)]
        lines.append(d.join(q + x + q if x else x for x in cells) + (d if c["trailing"] else ""))
    text = c["end"].join(lines) + (c["end"] if c["last_newline"] else "")
    return (b"\xef\xbb\xbf" if c["bom"] else b"") + text.encode()


@settings(
    max_examples=int(os.environ.get("IMUPIPE_FUZZ_EXAMPLES", "60")),
    derandomize="IMUPIPE_FUZZ_EXAMPLES" not in os.environ,
    deadline=5000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(c=csv_layouts())
def test_csv_layouts_read_back_exactly(tmp_path, c):
    """Every way of writing the table reads back to it: same stamps, every row with an IMU
    cell an IMU sample, its empty cells NaN, values bit for bit."""
    path = tmp_path / "w.csv"
    path.write_bytes(_csv_text(c))
    table, _ = read_input(InputSpec(path=path))
    np.testing.assert_array_equal(table.column("t_ns").to_numpy(), c["t"])
    has = ~c["empty"].all(axis=1)
    expected = np.where(c["empty"], np.nan, c["values"])[has]
    got = (
        np.column_stack([sensor(table, "gyro").values, sensor(table, "accel").values])
        if has.any()
        else np.zeros((0, 6))
    )
    np.testing.assert_array_equal(got, expected)
    assert counts(table).get("imu", 0) == int(has.sum())


@settings(
    max_examples=int(os.environ.get("IMUPIPE_FUZZ_EXAMPLES", "60")),
    derandomize="IMUPIPE_FUZZ_EXAMPLES" not in os.environ,
    deadline=5000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    c=csv_layouts(),
    edits=st.lists(
        st.tuples(
            st.floats(0.0, 1.0),
            st.sampled_from(
                ["", ",", ";", '"', "\n", "\r", "\x00", "\xff", "x", "-", "e", "1e400", "nan"]
            ),
            st.integers(0, 3),
        ),
        max_size=5,
    ),
)
def test_damaged_csv_is_read_or_one_line(tmp_path, c, edits):
    """Cells and bytes replaced, inserted or removed: the file is read or refused in one line."""
    data = bytearray(_csv_text(c))
    for where, text, cut in edits:
        i = min(int(where * len(data)), len(data))
        data[i : i + cut] = text.encode("latin-1")
    path = tmp_path / "d.csv"
    path.write_bytes(bytes(data))
    try:
        read_input(InputSpec(path=path))
    except ImupipeError as exc:
        assert "\n" not in str(exc)
