"""ArduPilot DataFlash logs (``readers/dataflash/reader.py``): value for value against pymavlink's
``DFReader`` on a synthetic log written here (FMT + records with ``struct``) and on the real
logs of ../shared/data/logs/ardupilot_flights (skipped when absent), the streams, instance
names, ``inspect``, ``run`` and ``convert``, and damaged files."""

from __future__ import annotations

import contextlib
import json
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink import DFReader

from imupipe.pipeline.inspect_log import inspect
from imupipe.readers.dataflash.reader import DataFlashLog, record_offsets
from imupipe.readers.dispatch import detect_format, read_input
from imupipe.readers.errors import ImupipeError, ReadError
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import counts, metadata, sensor

from conftest import run_cli, shared_path
from helpers import decode_mcap, vec

FLIGHTS = (
    "erle_pxf_118/118.BIN",
    "erle_pxf_218/218.BIN",
    "forum13645_ac344/log_0036.bin",
    "spark404_utrecht/log.bin",
)
"""The real logs (../shared/data/logs/ardupilot_flights, its README)."""

STRUCT = {
    "B": "B",
    "b": "b",
    "h": "h",
    "H": "H",
    "i": "i",
    "I": "I",
    "f": "f",
    "d": "d",
    "Q": "Q",
    "q": "q",
    "n": "4s",
    "N": "16s",
    "Z": "64s",
    "c": "h",
    "C": "H",
    "e": "i",
    "E": "I",
    "L": "i",
    "M": "b",
}
"""DataFlash field characters as ``struct`` codes (what ``AP_Logger`` writes, little-endian)."""

# (type, name, format, columns) of the synthetic log: ArduPilot 4.x messages with an instance
# field I, and a PARM
MESSAGES = [
    (129, "IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    (130, "MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    (131, "BARO", "QBffcfIffB", "TimeUS,I,Alt,Press,Temp,CRt,SMS,Offset,GndTemp,Health"),
    (132, "PARM", "QNf", "TimeUS,Name,Value"),
    (133, "ATT", "QccccCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
    (134, "POS", "QLLfff", "TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt"),
]


def _record(msg_type: int, fmt: str, values: tuple) -> bytes:
    return bytes([0xA3, 0x95, msg_type]) + struct.pack(
        "<" + "".join(STRUCT[c] for c in fmt), *values
    )


def write_dataflash(path: Path, seconds: float = 3.0, garbage: bool = True) -> dict:
    """A DataFlash log written with ``struct`` (FMT records, then records in time order): two
    IMUs at 400 Hz as ``IMU`` with ``I`` = 0, 1 (gyro bias per instance, gravity on z,
    temperature rising), one compass at 100 Hz, a barometer at 50 Hz, four parameters, and
    (with ``garbage``) a run of junk bytes between records and a cut record at the end, as
    ``DFReader`` skips them. Returns what was written (for the tests to compare)."""
    rng = np.random.default_rng(7)
    fmts = {name: (t, f) for t, name, f, _ in MESSAGES}
    out = bytearray()
    fmt_fmt = "BBnNZ"
    out += _record(128, fmt_fmt, (128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns"))
    for t, name, f, cols in MESSAGES:
        length = 3 + struct.calcsize("<" + "".join(STRUCT[c] for c in f))
        out += _record(128, fmt_fmt, (t, length, name.encode(), f.encode(), cols.encode()))
    params = {
        "INS_GYROFFS_X": 0.0125,
        "COMPASS_OFS_X": -41.0,
        "AHRS_ORIENTATION": 0.0,
        "SYSID_THISMAV": 1.0,
    }
    for name, value in params.items():
        out += _record(fmts["PARM"][0], "QNf", (1_000_000, name.encode(), value))
    bias = np.array([[0.01, -0.02, 0.005], [-0.003, 0.004, 0.011]])
    t0 = 2_000_000
    n = int(seconds * 400)
    truth: dict = {"imu": {0: [], 1: []}, "params": params, "bias": bias}
    for k in range(n):
        t = t0 + k * 2500
        for i in (0, 1):
            gyro = bias[i] + rng.normal(0, 1e-3, 3)
            accel = np.array([0.0, 0.0, -9.80665]) + rng.normal(0, 0.02, 3)
            temp = 30.0 + k / n
            vals = (t, i, *gyro, *accel, 0, 0, temp, 1, 1, 400, 400)
            out += _record(fmts["IMU"][0], MESSAGES[0][2], vals)
            truth["imu"][i].append((t, *np.float32(gyro), *np.float32(accel), np.float32(temp)))
        if k % 4 == 0:
            mag = (210 + k % 7, -35, 420)
            out += _record(fmts["MAG"][0], MESSAGES[1][2], (t, 0, *mag, 10, 20, 30, 0, 0, 0, 1, t))
            out += _record(fmts["ATT"][0], "QccccCC", (t, 100, -250, 3, 4, 35000, 35999))
        if k % 8 == 0:
            out += _record(
                fmts["BARO"][0],
                MESSAGES[2][2],
                (t, 0, 1.5, 101325.0, 2550, 0.1, t // 1000, 0.0, 25.0, 1),
            )
            out += _record(fmts["POS"][0], "QLLfff", (t, 520380000, 51450000, 3.0, 1.0, 1.0))
        if garbage and k == n // 2:
            out += bytes([0xA3, 0x95, 7, 1, 2, 0xA3]) + bytes(
                rng.integers(0, 256, 40, dtype=np.uint8)
            )
    if garbage:
        out += _record(
            fmts["IMU"][0], MESSAGES[0][2], (t0 + n * 2500, 0, *[0.0] * 6, 0, 0, 0.0, 1, 1, 0, 0)
        )[:30]
    path.write_bytes(bytes(out))
    return truth


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> tuple[Path, dict]:
    path = tmp_path_factory.mktemp("df") / "synthetic.bin"
    return path, write_dataflash(path)


def _dfreader(path: Path) -> dict[str, list]:
    """Every message of the log as DFReader reads it: name -> messages, in file order."""
    r = DFReader.DFReader_binary(str(path), zero_time_base=False)
    out: dict[str, list] = {}
    while (m := r.recv_msg()) is not None:
        out.setdefault(m.get_type(), []).append(m)
    return out


def _same_as_dfreader(path: Path) -> int:
    """Compares every field of every record with DFReader's; returns the values compared."""
    ref = _dfreader(path)
    f = DataFlashLog(path)
    compared = 0
    for name, msgs in ref.items():
        fmt = f.by_name[name]
        assert len(f.records(name)) == len(msgs), name
        for col, code in zip(fmt.columns, fmt.format, strict=True):
            want = [getattr(m, col) for m in msgs]
            if code in "nNZ":
                got = [
                    bytes(v).split(b"\0", 1)[0].decode("ascii", "replace")
                    for v in f.field(name, col)
                ]
                assert got == want, (name, col)
            elif code == "a":
                assert np.array_equal(np.array([list(w) for w in want]), f.field(name, col))
            else:
                assert np.array_equal(f.field(name, col), np.array(want, dtype=np.float64)), (
                    name,
                    col,
                )
            compared += len(msgs)
    return compared


def test_detect_format():
    assert detect_format(Path(shared_path("logs", "ardupilot_flights", FLIGHTS[0]))) == "dataflash"


def test_synthetic_is_dfreaders(synthetic):
    path, _ = synthetic
    assert _same_as_dfreader(path) > 10_000


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) for n in FLIGHTS[:3]] + [FLIGHTS[3]]
)
def test_real_logs_value_for_value(name):
    """Every field of every record of the real logs equals DFReader's (counts too)."""
    path = shared_path("logs", "ardupilot_flights", name)
    assert _same_as_dfreader(path) > 100_000


def test_streams_in_si(synthetic):
    path, truth = synthetic
    table, warnings = read_input(InputSpec(path=path, imu_topic="IMU_1"))
    want = np.array(truth["imu"][1], dtype=np.float64)
    gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
    assert np.array_equal(gyro.t_ns, want[:, 0].astype(np.int64) * 1000)  # TimeUS
    assert np.array_equal(gyro.values, want[:, 1:4])  # rad/s as logged
    assert np.array_equal(accel.values, want[:, 4:7])  # m/s^2 as logged
    assert np.array_equal(sensor(table, "temperature").values[:, 0], want[:, 7])
    assert np.allclose(gyro.values.mean(axis=0), truth["bias"][1], atol=2e-4)
    mag = sensor(table, "mag")
    assert np.allclose(mag.values[0], np.array([210, -35, 420]) * 1e-7)  # milligauss -> T
    meta = metadata(table)
    assert meta["format"] == "dataflash"
    assert meta["topics"] == {"imu": "IMU_1", "mag": "MAG", "temperature": "IMU_1/temperature"}
    assert meta["instance"] == {"imu": 1, "mag": 0, "temperature": 1}
    assert meta["ardupilot"]["calibrated"] == {"imu": True, "mag": True}
    assert meta["ardupilot"]["parameters"] == {
        "AHRS_ORIENTATION": 0.0,
        "COMPASS_OFS_X": -41.0,
        "INS_GYROFFS_X": pytest.approx(0.0125),
    }
    assert any("belong to no record" in w for w in warnings)
    assert any("no whole record" in w for w in warnings)


def test_baro_temperature_and_choice_errors(synthetic):
    path, _ = synthetic
    table, _ = read_input(InputSpec(path=path, imu_topic="IMU", temperature_topic="BARO"))
    assert np.all(sensor(table, "temperature").values == 25.5)  # int16 centi-degC
    pressure = table.column("pressure").to_numpy(zero_copy_only=False)
    rows = ~np.isnan(table.column("temperature").to_numpy(zero_copy_only=False))
    assert np.all(pressure[rows] == 101325.0) and np.isnan(pressure[~rows]).all()  # Pa
    with pytest.raises(ReadError, match="several IMU instances \\(IMU, IMU_1\\)"):
        read_input(InputSpec(path=path))
    with pytest.raises(ReadError, match="imu_topic 'IMU2' is not in the log.*IMU, IMU_1"):
        read_input(InputSpec(path=path, imu_topic="IMU2"))
    with pytest.raises(ReadError, match="mag_topic 'BARO' cannot fill it"):
        read_input(InputSpec(path=path, imu_topic="IMU", mag_topic="BARO"))


def test_old_style_instances_named_by_message():
    """Copter 3.4: IMU and IMU2 messages (no I field): instances 0 and 1 under their names."""
    path = shared_path("logs", "ardupilot_flights", "forum13645_ac344/log_0036.bin")
    table, _ = read_input(InputSpec(path=path, imu_topic="IMU2", mag_topic="MAG2"))
    ref = _dfreader(path)
    assert counts(table)["imu"] == len(ref["IMU2"]) == 3755
    assert np.array_equal(sensor(table, "gyro").values[:, 2], [m.GyrZ for m in ref["IMU2"]])
    assert np.array_equal(sensor(table, "mag").values[:, 0], [m.MagX * 1e-7 for m in ref["MAG2"]])
    assert metadata(table)["instance"] == {"imu": 1, "mag": 1, "temperature": 1}


def test_inspect_lists_instances(synthetic):
    path, _ = synthetic
    proc = run_cli("inspect", path, "--json", "--imu-topic", "IMU_1")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["format"] == "dataflash"
    assert info["topics"]["IMU_1"]["instance"] == 1
    assert info["topics"]["IMU_1"]["count"] == 1200
    assert info["topics"]["IMU_1"]["rate_hz"] == pytest.approx(400, rel=1e-3)
    assert info["streams"]["imu"]["topic"] == "IMU_1"
    assert info["streams"]["imu"]["ardupilot_calibrated"] is True
    assert info["parameters"]["INS_GYROFFS_X"] == pytest.approx(0.0125)
    text = run_cli("inspect", path, "--imu-topic", "IMU").stdout
    assert "stream imu: IMU (1200 samples, already calibrated by ArduPilot)" in text


def test_run_and_convert(synthetic, tmp_path):
    path, truth = synthetic
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        f'[inputs.flight]\npath = "{path}"\nimu_topic = "IMU_1"\n\n[[stages]]\n'
        f'type = "gyro_bias"\n\n[output]\ndir = "{tmp_path / "out"}"\nrerun = false\n'
    )
    proc = run_cli("run", cfg)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
    bias = np.array(doc["chain"][0]["offset"])
    assert np.allclose(bias, truth["bias"][1], atol=2e-4)
    fitted = doc["results"]["gyro_bias"]["fitted_on"]
    assert fitted["format"] == "dataflash" and fitted["instance"]["imu"] == 1
    assert fitted["ardupilot"]["calibrated"]["imu"] is True
    written = decode_mcap(tmp_path / "out" / "flight.mcap")
    assert {t: len(m) for t, m in written.items()} == {
        "IMU_1": 1200,
        "MAG": 300,
        "IMU_1/temperature": 1200,
    }
    raw = np.array(truth["imu"][1], dtype=np.float64)[:, 1:4]
    assert np.allclose(vec(written["IMU_1"], "angular_velocity"), raw - bias)
    read = tmp_path / "read.toml"
    read.write_text('imu_topic = "IMU_1"\n')
    proc = run_cli(
        "convert",
        "--calibration",
        tmp_path / "out" / "calibration.json",
        "--config",
        read,
        "--out",
        tmp_path / "conv",
        path,
    )
    assert proc.returncode == 0, proc.stderr
    again = decode_mcap(tmp_path / "conv" / "synthetic.mcap")
    assert np.allclose(vec(again["IMU_1"], "angular_velocity"), raw - bias)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "not an ArduPilot DataFlash log"),
        (b"hello world" * 100, "not an ArduPilot DataFlash log"),
    ],
)
def test_bad_file_is_one_line(tmp_path, content, message):
    bad = tmp_path / "bad.bin"
    bad.write_bytes(content)
    proc = run_cli("inspect", bad)
    assert proc.returncode == 2
    assert message in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_truncated_log(synthetic, tmp_path):
    """Cut in its FMT header: one line, exit 2. Cut mid-flight: the records before the cut, as
    DFReader reads them, with a warning."""
    path, _ = synthetic
    data = path.read_bytes()
    head = tmp_path / "head.bin"
    head.write_bytes(data[:500])
    proc = run_cli("inspect", head, "--imu-topic", "IMU")
    assert proc.returncode == 0  # inspect lists what is there
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        f'[inputs.flight]\npath = "{head}"\nimu_topic = "IMU"\n\n[[stages]]\n'
        f'type = "gyro_bias"\n\n[output]\ndir = "{tmp_path / "out"}"\nrerun = false\n'
    )
    proc = run_cli("run", cfg)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    (line,) = [x for x in proc.stderr.splitlines() if "warning" not in x]
    assert "head.bin: imu_topic 'IMU' is not in the log" in line
    assert not (tmp_path / "out" / "calibration.json").exists()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[: len(data) // 2 + 17])
    table, warnings = read_input(InputSpec(path=cut, imu_topic="IMU"))
    ref = _dfreader(cut)
    assert counts(table)["imu"] == sum(1 for m in ref["IMU"] if m.I == 0)
    assert any("no whole record" in w for w in warnings)


def test_record_walk_skips_false_headers():
    """A header pattern inside a payload is not a record: only the chain from the start is."""
    payload = struct.pack("<QBB", 5, 0xA3, 0x95)  # a TimeUS then the header bytes as data
    fmt = bytes([0xA3, 0x95, 128]) + struct.pack(
        "<BB4s16s64s", 140, 3 + len(payload), b"TST", b"QBB", b"TimeUS,A,B"
    )
    log = fmt + (bytes([0xA3, 0x95, 140]) + payload) * 3
    offsets, types, _, end = record_offsets(np.frombuffer(log, dtype=np.uint8))
    assert types.tolist() == [128, 140, 140, 140]
    assert end == len(log)


@settings(
    max_examples=20,
    derandomize="IMUPIPE_FUZZ_EXAMPLES" not in os.environ,
    deadline=10000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    cut=st.floats(0.0, 1.0),
    flips=st.lists(st.tuples(st.floats(0.0, 0.2), st.integers(1, 255)), max_size=20),
)
def test_damaged_log_is_an_imupipe_error_or_reads(synthetic, cut, flips):
    """Truncations and byte flips (mostly in the FMT records at the start): read_input and
    inspect give a table or one ImupipeError."""
    path, _ = synthetic
    data = bytearray(path.read_bytes())
    for where, xor in flips:
        data[min(int(where * len(data)), len(data) - 1)] ^= xor
    if cut < 0.5:
        data = data[: int(cut * 2 * len(data))]
    damaged = path.with_name("damaged.bin")
    damaged.write_bytes(bytes(data))
    for spec in (InputSpec(path=damaged), InputSpec(path=damaged, imu_topic="IMU")):
        for read in (read_input, inspect):
            with contextlib.suppress(ImupipeError):
                read(spec)


def test_inspect_counts_messages_without_time():
    """Copter 3.3's PARM has no TimeMS: inspect still gives its count."""
    path = shared_path("logs", "ardupilot_flights", "erle_pxf_118/118.BIN")
    info = json.loads(run_cli("inspect", path, "--json").stdout)
    assert info["topics"]["PARM"]["count"] == 395 and info["topics"]["PARM"]["rate_hz"] is None
    assert info["topics"]["IMU"]["count"] == 12198
    assert info["streams"]["imu"]["topic"] == "IMU"


def test_header_scan_across_blocks(synthetic, monkeypatch):
    """The header scan runs in blocks: a header split by a block boundary is still found."""
    from imupipe.readers.dataflash import reader as dataflash_reader

    path, _ = synthetic
    buf = np.fromfile(path, dtype=np.uint8)
    whole = record_offsets(buf)
    monkeypatch.setattr(dataflash_reader, "SCAN_BLOCK", 997)
    blocks = record_offsets(buf)
    assert np.array_equal(whole[0], blocks[0]) and np.array_equal(whole[1], blocks[1])
    assert whole[3] == blocks[3]


def _both_walks(data: bytes, monkeypatch) -> None:
    """record_offsets with the compiled walk and with numpy's pointer doubling: the same."""
    from imupipe.readers.record_walk import PURE_PYTHON_ENV, compiled

    buf = np.frombuffer(data, dtype=np.uint8)
    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    assert compiled()
    fast = record_offsets(buf)
    monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    assert not compiled()
    slow = record_offsets(buf)
    monkeypatch.delenv(PURE_PYTHON_ENV)
    assert fast[0].tolist() == slow[0].tolist()
    assert fast[1].tolist() == slow[1].tolist() and fast[1].dtype == slow[1].dtype
    assert fast[2] == slow[2] and fast[3] == slow[3]


def test_compiled_walk_is_the_numpy_walk(synthetic, monkeypatch):
    """Issue 39: the DataFlash records walked in C (readers/_records.c) are the ones numpy's
    pointer doubling finds, on the real logs, the synthetic log and 40 damaged copies of it
    (bytes flipped, headers put inside payloads, cut)."""
    pytest.importorskip("imupipe.readers._records", reason="the compiled helper is not built")
    logs = [path for path in (shared_path_or_none(n) for n in FLIGHTS) if path is not None]
    path, _ = synthetic
    for log in [*logs, path]:
        _both_walks(log.read_bytes(), monkeypatch)
    rng = np.random.default_rng(39)
    data = path.read_bytes()
    for _ in range(40):
        damaged = bytearray(data)
        for at in rng.integers(0, len(data), rng.integers(1, 30)):
            damaged[at] = int(rng.choice([0xA3, 0x95, 128, int(rng.integers(0, 256))]))
        _both_walks(bytes(damaged[: int(rng.integers(len(data) // 2, len(data) + 1))]), monkeypatch)


def shared_path_or_none(name: str) -> Path | None:
    from conftest import SHARED

    path = SHARED / "logs" / "ardupilot_flights" / name
    return path if path.exists() else None
