"""Issue 40: damaged logs say what they lost; the survey, s3 and the Python API keep the error
contract (``tests/faults.py``).

- ULog: a data record of size 0 (``sample_log_small.ulg``, byte 142397) and an ``add_logged``
  ``msg_id`` set to 0: read past, with a warning naming offsets, records and bytes;
- DataFlash (``118.BIN``): a ``FMT`` length changed, a field format changed, ``GPS.TimeMS``
  renamed: counts as pymavlink's or more, the vanished stream named, never an exception;
- the survey: a FIFO in a fleet folder, given as a log, to ``inspect`` or as ``--calibration``;
  a README; ``--out`` the input folder; a name with a line break; ``--min-still inf``; a 2 GiB
  sparse ``.bin``; stale temporary files; ``--out`` inside the fleet folder;
- SIGTERM before ``main`` and after the outputs: status 143, one line, no "Exception ignored";
- URLs: ``--out s3://``, ``s3:///x.mcap``, ``hdfs://``: one line, exit 2, nothing written;
- the Python API: wrong types, missing columns, bad arguments: ``ImupipeError`` in one line.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow as pa
import pytest
from faults import check, cli, snapshot

from imupipe.pipeline.atomic import HOST_KEY
from imupipe.pipeline.convert.worker import COPY_PREFIX, remove_stale_copies
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import counts

from conftest import REPO, SHARED
from conftest import shared_path as shared

SMALL_ULOG = REPO / "tests" / "data" / "px4_ulog" / "sample_log_small.ulg"
IDENTITY = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def _cal(path: Path) -> Path:
    entry = {"type": "gyro_bias", "sensor": "gyro", "kind": "linear", "matrix": IDENTITY,
             "offset": [0.01, 0.0, 0.0]}  # fmt: skip
    path.write_text(json.dumps({"imupipe_version": "test", "chain": [entry], "results": {}}))
    return path


# -- ULog ------------------------------------------------------------------------------------


def test_ulog_record_of_size_0_is_read_past_and_named(tmp_path):
    from pyulog import ULog

    data = bytearray(SMALL_ULOG.read_bytes())
    assert data[142397 + 2] == ord("D")  # a data record
    data[142397:142399] = b"\0\0"
    bad = tmp_path / "size0.ulg"
    bad.write_bytes(bytes(data))
    stock = {d.name: len(d.data["timestamp"]) for d in ULog(str(bad)).data_list}
    clean, _ = read_input(InputSpec(path=SMALL_ULOG))
    table, warnings = read_input(InputSpec(path=bad))
    # stock pyulog 1.3 ends its parse at the record (117 of 1,298 sensor_combined)
    assert counts(table)["imu"] > stock["sensor_combined"]
    assert counts(table)["imu"] > 0.9 * counts(clean)["imu"]
    said = [w for w in warnings if "damaged" in w]
    assert len(said) == 1 and "at byte 142397" in said[0] and "a data record of 0 bytes" in said[0]


@pytest.mark.parametrize("fmt_id_at", [103238])
def test_ulog_msg_id_0_is_named(tmp_path, fmt_id_at):
    src = shared("logs", "peer_fixtures", "mcap_fixture_test_ulog.ulg")
    data = bytearray(src.read_bytes())
    assert data[fmt_id_at + 6 : fmt_id_at + 21] == b"sensor_combined"
    data[fmt_id_at + 4 : fmt_id_at + 6] = b"\0\0"  # its msg_id: the id of action_request
    bad = tmp_path / "msgid0.ulg"
    bad.write_bytes(bytes(data))
    code, err = cli("inspect", bad)
    assert code in (0, 2) and "Traceback" not in err
    from imupipe.readers.ulog.reader import UlogFile

    said = UlogFile(bad).damage_warning()
    assert said is not None and "1298 records skipped" in said and "sensor_combined" in said


# -- DataFlash -------------------------------------------------------------------------------


def _edited_118(tmp_path: Path, at: int, value: bytes, name: str) -> Path:
    data = bytearray(shared("logs", "ardupilot_flights", "erle_pxf_118", "118.BIN").read_bytes())
    data[at : at + len(value)] = value
    path = tmp_path / name
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("length", [23, 27])
def test_dataflash_fmt_length_changed_keeps_every_count(tmp_path, length):
    path = _edited_118(tmp_path, 2759 + 4, bytes([length]), "len.BIN")  # MAG's FMT length
    table, warnings = read_input(InputSpec(path=path))
    assert counts(table) == {"imu": 12198, "mag": 2439}  # the clean log's
    assert any(f"says {length} bytes a record" in w and "read as 25" in w for w in warnings)


@pytest.mark.parametrize(
    ("at", "value", "stream", "n"),
    [(276, b"h", "imu", 12198), (2776, b"f", "mag", 2439)],  # IMU's and MAG's field formats
)
def test_dataflash_stream_vanished_by_fmt_edit_is_named(tmp_path, at, value, stream, n):
    path = _edited_118(tmp_path, at, value, "fmt.BIN")
    table, warnings = read_input(InputSpec(path=path))
    assert stream not in counts(table)
    assert any(f"{n} records of message {stream.upper()}" in w for w in warnings), warnings


def test_dataflash_gps_timems_renamed_is_read(tmp_path):
    path = _edited_118(tmp_path, 178 + 25 + 7, b"TimeMX", "gps.BIN")
    before = snapshot(tmp_path)
    code, err = cli("convert", "--calibration", _cal(tmp_path / "c.json"), "--out",
                    tmp_path / "out", "-q", path)  # fmt: skip
    check(
        "GPS TimeMS renamed", code, err, tmp_path, before, [tmp_path / "out", tmp_path / "c.json"]
    )
    assert code == 0, err


# -- the survey and the files it opens ----------------------------------------------------------


@pytest.fixture
def fleet(tmp_path):
    fleet = tmp_path / "fleet"
    (fleet / "veh01").mkdir(parents=True)
    (fleet / "veh01" / "a.ulg").write_bytes(SMALL_ULOG.read_bytes())
    os.mkfifo(fleet / "veh01" / "pipe.mcap")
    return fleet


def _alarm(seconds: int):
    def fail(*_):
        raise TimeoutError("blocked")

    signal.signal(signal.SIGALRM, fail)
    signal.alarm(seconds)


def test_a_fifo_never_blocks(tmp_path, fleet):
    os.mkfifo(tmp_path / "cal.json")
    _alarm(120)
    try:
        before = snapshot(tmp_path)
        code, err = cli("survey", fleet, "--out", tmp_path / "out", "--no-rerun", "--quiet",
                        "--jobs", "1")  # fmt: skip
        check("FIFO in the fleet", code, err, tmp_path, before, [tmp_path / "out"])
        assert code == 0, err
        for argv in (
            ("inspect", fleet / "veh01" / "pipe.mcap"),
            ("survey", fleet / "veh01" / "pipe.mcap", "--out", tmp_path / "o2"),
            ("survey", fleet, "--out", tmp_path / "o3", "--calibration", tmp_path / "cal.json"),
        ):
            before = snapshot(tmp_path)
            code, err = cli(*argv)
            check(str(argv), code, err, tmp_path, before, [])
            assert code == 2 and "not a regular file" in err, err
    finally:
        signal.alarm(0)


def test_survey_refuses_as_convert_refuses(tmp_path, fleet):
    (tmp_path / "README.md").write_text("not a log\n")
    odd = tmp_path / "bad\nname.ulg"
    odd.write_bytes(b"garbage")
    cases = [
        (("survey", tmp_path / "README.md", "--out", tmp_path / "o1"), 2, "unknown log format"),
        (("survey", fleet, "--out", fleet), 2, "searched for logs"),
        (("survey", fleet, "--out", tmp_path / "o2", "--min-still", "inf"), 2, "--min-still inf"),
        (("survey", odd, "--out", tmp_path / "o3", "--no-rerun"), 1, "name.ulg: not a readable"),
    ]
    for argv, want, says in cases:
        before = snapshot(tmp_path)
        code, err = cli(*argv)
        check(str(argv), code, err, tmp_path, before, [tmp_path / "o3"], fleet=want == 1)
        assert code == want and says in err, err
        assert len([line for line in err.splitlines() if "error" in line]) == 1


def test_a_huge_file_that_is_no_log_is_refused_without_reading_it(tmp_path):
    huge = tmp_path / "huge.bin"
    with open(huge, "wb") as fh:
        fh.truncate(2 << 30)  # 2 GiB of zeros, sparse
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    code, err = cli("inspect", huge)
    assert code == 2 and "no FMT record in its first" in err, err
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss < 200_000  # kB


def test_stale_survey_temporaries_are_removed_and_out_in_the_fleet_is_said(tmp_path, fleet):
    out = tmp_path / "out"
    (out / "parts").mkdir(parents=True)
    stale = [out / f".survey.parquet.999999@{HOST_KEY}.abcdefgh.tmp",
             out / "parts" / f".a.parquet.999998@{HOST_KEY}.abcdefgh.tmp"]  # fmt: skip
    for f in stale:
        f.write_bytes(b"")
    code, err = cli("survey", fleet / "veh01" / "a.ulg", "--out", out, "--no-rerun", "--quiet")
    assert code == 0, err
    assert not any(f.exists() for f in stale)
    (fleet / "veh02").mkdir()
    (fleet / "veh02" / "b.ulg").write_bytes(SMALL_ULOG.read_bytes())
    code, err = cli("survey", fleet, "--out", fleet / "veh01", "--no-rerun")
    assert code == 0, err
    assert "veh01 is the output folder: the logs in it are not surveyed" in err


# -- SIGTERM ------------------------------------------------------------------------------------

_SCRIPT = """
import os, signal, sys, time
from imupipe.pipeline.cli import main
if sys.argv[1] == "early":
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(5)
code = main(sys.argv[2:])
os.kill(os.getpid(), signal.SIGTERM)  # the outputs are in place
time.sleep(5)
sys.exit(code)
"""


@pytest.mark.parametrize("when", ["early", "after"])
def test_sigterm_before_main_or_after_the_outputs_exits_143(tmp_path, when):
    proc = subprocess.run(
        [sys.executable, "-c", _SCRIPT, when, "inspect", str(SMALL_ULOG)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 143, proc
    assert proc.stderr.strip().splitlines()[-1] == "imupipe: terminated", proc.stderr
    assert "Exception ignored" not in proc.stderr and "Traceback" not in proc.stderr


# -- URLs ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("log", "out", "says"),
    [
        (None, "s3://", "--out s3://: names no bucket"),
        ("s3:///x.mcap", "o", "s3:///x.mcap: names no bucket"),
        (None, "hdfs://x/y", "the scheme 'hdfs://' is not supported"),
        ("abfs://x/y.mcap", "o", "the scheme 'abfs://' is not supported"),
    ],
)
def test_urls_without_bucket_or_scheme_are_one_line(tmp_path, log, out, says):
    cal = _cal(tmp_path / "c.json")
    log = log or str(tmp_path / "a.ulg")
    if not log.startswith(("s3:", "abfs:")):
        Path(log).write_bytes(SMALL_ULOG.read_bytes())
    before = snapshot(tmp_path)
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "imupipe.pipeline.cli", "convert", "--calibration", str(cal),
         "--out", out, log],
        capture_output=True, text=True, cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert time.monotonic() - t0 < 60
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and says in proc.stderr, proc
    assert snapshot(tmp_path) == before  # no folder named 's3:' or 'hdfs:'


def test_local_copies_of_dead_workers_are_removed(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead = tmp_path / f"{COPY_PREFIX}999999@{HOST_KEY}-abc_1234"
    mine = tmp_path / f"{COPY_PREFIX}{os.getpid()}@{HOST_KEY}-abc_1234"
    other = tmp_path / f"{COPY_PREFIX}999999@00000000-abc_1234"  # another machine's
    for d in (dead, mine, other):
        (d / "x").mkdir(parents=True)
    assert remove_stale_copies() == [dead]
    assert mine.exists() and other.exists()


# -- the Python API ------------------------------------------------------------------------------


def test_python_api_wrong_arguments_are_one_line_imupipe_errors(tmp_path):
    import imupipe

    table = imupipe.read(SMALL_ULOG)
    bias = imupipe.gyro_bias(table, accept_failed_checks=True)
    cal = imupipe.Calibration.from_results(bias)
    cases = [
        (lambda: imupipe.gyro_bias(pa.table({})), "has no column t_ns"),
        (lambda: imupipe.gyro_bias("x"), "must be a pyarrow.Table"),
        (lambda: imupipe.Calibration.from_results("x"), "must be a stage result"),
        (lambda: cal.apply("x"), "must be a pyarrow.Table"),
        (lambda: cal.apply(table.drop(["gyro_y"])), "has no column gyro_y"),
        (lambda: cal.apply(table, on_mismatch="maybe"), "on_mismatch must be"),
        (lambda: cal.save(tmp_path), "is a folder"),
        (lambda: imupipe.convert([SMALL_ULOG], tmp_path / "c.json", tmp_path / "o", jobs=0),
         "--jobs 0: must be at least 1"),
        (lambda: imupipe.convert([SMALL_ULOG], tmp_path / "c.json", tmp_path / "o", retries=-1),
         "--retries -1"),
    ]  # fmt: skip
    for call, says in cases:
        with pytest.raises(imupipe.ImupipeError, match=None) as info:
            call()
        assert says in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "o").exists()


def test_calibration_apply_checks_the_device(tmp_path):
    import imupipe

    px4 = imupipe.read(SMALL_ULOG)
    cal = imupipe.Calibration.from_results(imupipe.gyro_bias(px4, accept_failed_checks=True))
    flight = SHARED / "logs" / "ardupilot_flights" / "erle_pxf_118" / "118.BIN"
    if not flight.is_file():
        pytest.skip(f"{flight} is absent (../shared/data)")
    other = imupipe.read(flight, imu_topic="IMU")
    with pytest.warns(imupipe.ImupipeWarning, match="was fitted on topics 'sensor_combined'"):
        cal.apply(other)
    with pytest.raises(imupipe.ImupipeError, match="not the sensor of the calibration"):
        cal.apply(other, on_mismatch="refuse")


def test_an_object_store_gone_is_one_line(tmp_path):
    """A moto server stopped after the log was uploaded: the conversion ends in one line
    naming the URL (no raw OSError, no traceback), nothing written outside ``--out``."""
    import logging
    import socket

    moto_server = pytest.importorskip("moto.server", reason="moto[server] is needed")
    boto3 = pytest.importorskip("boto3")
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    env = {**os.environ, "AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
           "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}"}  # fmt: skip
    try:
        client = boto3.client(
            "s3", endpoint_url=env["AWS_ENDPOINT_URL"], region_name="us-east-1",
            aws_access_key_id="testing", aws_secret_access_key="testing",
        )  # fmt: skip
        client.create_bucket(Bucket="logs")
        client.upload_file(str(SMALL_ULOG), "logs", "a.ulg")
    finally:
        server.stop()
    cal = _cal(tmp_path / "c.json")
    before = snapshot(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", "imupipe.pipeline.cli", "convert", "--calibration", str(cal),
         "--out", str(tmp_path / "out"), "s3://logs/a.ulg"],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    check("object store gone", proc.returncode, proc.stderr, tmp_path, before, [tmp_path / "out"],
          fleet=True)  # fmt: skip
    assert proc.returncode in (1, 2) and "s3://logs/a.ulg" in proc.stderr, proc.stderr
