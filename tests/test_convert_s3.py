"""Issue 27 item 4: ``imupipe convert`` with logs, ``--out`` and the manifest on object storage.

Against a local S3-compatible server the module starts itself (moto's, bound to 127.0.0.1 on a
free port, reached through ``AWS_ENDPOINT_URL`` as a user would): a small fleet converted from
``s3://`` to ``s3://`` holds, log for log, the same messages as the same fleet converted locally
(counts in = counts out); a second run skips every log through the published outputs and the
manifest on S3; a missing bucket or key is one line naming the URL, exit 2, nothing written; an
upload interrupted half-way publishes nothing and leaves no temporary key.
"""

from __future__ import annotations

import json
import logging
import os
import socket
from pathlib import Path

import pytest
from mcap.reader import make_reader
from test_convert import CHAIN, _status_messages, write_bag_with_rosbags

from imupipe.pipeline.convert import remote
from imupipe.pipeline.convert.fleet import convert
from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.convert.plan import plan
from imupipe.pipeline.convert.settings import load_read_settings
from imupipe.pipeline.convert.worker import convert_log
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.pipeline.writers.mcap import write_mcap

from conftest import run_cli

moto_server = pytest.importorskip("moto.server", reason="moto[server] (the test extras) is needed")
boto3 = pytest.importorskip("boto3")

BUCKET_IN, BUCKET_OUT = "fleet-logs", "fleet-out"


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    """A moto S3 server on 127.0.0.1 (a free port), the AWS variables pointing at it, the two
    buckets, and a small fleet uploaded under ``s3://fleet-logs/logs/``."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # the server's request lines
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    env = {
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}",
    }
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    remote._FILESYSTEMS.clear()
    try:
        client = boto3.client("s3", endpoint_url=env["AWS_ENDPOINT_URL"])
        client.create_bucket(Bucket=BUCKET_IN)
        client.create_bucket(Bucket=BUCKET_OUT)
        d = tmp_path_factory.mktemp("s3fleet")
        logs = d / "logs"
        (logs / "site1").mkdir(parents=True)
        (logs / "site2").mkdir()
        static, _ = simulate("static", {"duration_s": 2.0, "rate_hz": 200.0}, seed=1)
        write_mcap(
            logs / "a.mcap", static, carry_over=_status_messages(7, int(static["t_ns"][0].as_py()))
        )
        mag, _ = simulate("mag", {"duration_s": 3.0, "rate_hz": 50.0}, seed=2)
        write_log(logs / "site1" / "m.mcap", mag)
        ros, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 100.0, "temperature": None}, 3)
        write_bag_with_rosbags(logs / "site2" / "r1.bag", ros, 1, status=5)
        (logs / "notes.md").write_text("not a log")  # not found in a folder: no log suffix
        for f in sorted(p for p in logs.rglob("*") if p.is_file()):
            client.upload_file(str(f), BUCKET_IN, "logs/" + f.relative_to(logs).as_posix())
        cal = d / "calibration.json"
        cal.write_text(json.dumps({"imupipe_version": "test", "chain": CHAIN, "results": {}}))
        yield client, d, logs, cal
    finally:
        server.stop()
        remote._FILESYSTEMS.clear()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _keys(client, bucket: str, prefix: str) -> dict[str, object]:
    """Key -> last-modified of every object under ``prefix`` (pyarrow's empty folder markers,
    keys ending in ``/``, left out)."""
    out = {}
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix):
        out.update(
            {o["Key"]: o["LastModified"] for o in page.get("Contents", []) if o["Key"][-1] != "/"}
        )
    return out


def _messages(data: bytes) -> list[tuple[str, int, bytes]]:
    import io

    reader = make_reader(io.BytesIO(data))
    return sorted((c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages())


def _manifest(client, key: str) -> list[dict]:
    body = client.get_object(Bucket=BUCKET_OUT, Key=key)["Body"].read().decode()
    return [json.loads(line) for line in body.splitlines()]


def test_fleet_s3_to_s3_matches_local_then_resumes(s3, tmp_path):
    client, _, logs, cal = s3
    src, out = f"s3://{BUCKET_IN}/logs", f"s3://{BUCKET_OUT}/run1"
    proc = run_cli("convert", "--calibration", cal, "--out", out, "--jobs", "2", "--parquet", src)
    assert proc.returncode == 0, proc.stderr
    local = convert([logs], cal, tmp_path / "local", jobs=1, parquet=True)
    assert len(local.converted) == 3 and not local.failed

    keys = _keys(client, BUCKET_OUT, "run1/")
    names = {"a", "site1/m", "site2/r1"}
    assert set(keys) == (
        {f"run1/{n}.mcap" for n in names}
        | {f"run1/parquet/{n}.parquet" for n in names}
        | {"run1/manifest.jsonl"}
    )  # no temporary key left, no probe
    for n in names:  # counts in = counts out, message for message as a local conversion
        got = client.get_object(Bucket=BUCKET_OUT, Key=f"run1/{n}.mcap")["Body"].read()
        assert _messages(got) == _messages((tmp_path / "local" / f"{n}.mcap").read_bytes())
    lines = _manifest(client, "run1/manifest.jsonl")
    assert sorted(r["input"] for r in lines) == sorted(
        f"{src}/{n}" for n in ("a.mcap", "site1/m.mcap", "site2/r1.bag")
    )
    assert {r["status"] for r in lines} == {"converted"}
    by_input = {Path(r["input"]).name: r for r in read_manifest(tmp_path / "local")}
    for r in lines:
        assert r["output"].startswith(out + "/")
        assert r["counts"] == by_input[r["input"].rpartition("/")[2]]["counts"]
    attached = json.loads(
        next(
            a.data
            for a in make_reader(
                __import__("io").BytesIO(
                    client.get_object(Bucket=BUCKET_OUT, Key="run1/a.mcap")["Body"].read()
                )
            ).iter_attachments()
            if a.name == "calibration.json"
        )
    )
    assert attached["conversion"]["input"] == f"{src}/a.mcap"  # the URL, not a local copy

    # resume: every log skipped through its published output, nothing rewritten
    again = run_cli("convert", "--calibration", cal, "--out", out, "--parquet", "-q", src)
    assert again.returncode == 0, again.stderr
    after = _keys(client, BUCKET_OUT, "run1/")
    assert {k: v for k, v in after.items() if "manifest" not in k} == {
        k: v for k, v in keys.items() if "manifest" not in k
    }
    lines = _manifest(client, "run1/manifest.jsonl")
    assert [r["status"] for r in lines] == ["converted"] * 3 + ["skipped"] * 3


def test_s3_logs_to_a_local_folder_and_local_logs_to_s3(s3, tmp_path):
    client, _, logs, cal = s3
    summary = convert([f"s3://{BUCKET_IN}/logs/a.mcap"], cal, tmp_path / "out", jobs=1)
    assert [s.status for s in summary.converted] == ["converted"]
    assert (tmp_path / "out" / "a.mcap").is_file()
    assert next(read_manifest(tmp_path / "out"))["input"] == f"s3://{BUCKET_IN}/logs/a.mcap"
    up = convert([logs / "site1"], cal, f"s3://{BUCKET_OUT}/run2", jobs=1)
    assert [s.output for s in up.converted] == [f"s3://{BUCKET_OUT}/run2/m.mcap"]
    assert set(_keys(client, BUCKET_OUT, "run2/")) == {"run2/m.mcap", "run2/manifest.jsonl"}


@pytest.mark.parametrize(
    ("log", "out", "says"),
    [
        ("s3://no-such-bucket/logs", f"s3://{BUCKET_OUT}/bad", "no such bucket 'no-such-bucket'"),
        (f"s3://{BUCKET_IN}/logs/missing.mcap", f"s3://{BUCKET_OUT}/bad", "no such object"),
        (f"s3://{BUCKET_IN}/logs/notes.md", f"s3://{BUCKET_OUT}/bad", "unknown log format"),
        (f"s3://{BUCKET_IN}/logs/a.mcap", "s3://no-such-bucket/out", "no such bucket"),
    ],
)
def test_bad_url_is_one_line_exit_2_nothing_written(s3, log, out, says):
    client, _, _, cal = s3
    proc = run_cli("convert", "--calibration", cal, "--out", out, log)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0], proc.stderr
    assert (log if "no-such-bucket" in log or "missing" in log or "notes" in log else out) in lines[
        0
    ]
    assert _keys(client, BUCKET_OUT, "bad/") == {}


class _CutStream:
    """An output stream that fails after ``limit`` writes (a connection lost, a signal)."""

    def __init__(self, stream, limit: int, exc: BaseException) -> None:
        self.stream, self.left, self.exc = stream, limit, exc

    def write(self, data):
        if self.left == 0:
            raise self.exc
        self.left -= 1
        return self.stream.write(data)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stream.close()  # as pyarrow's own stream does: what was written is sent


class _CutFS:
    def __init__(self, fs, exc: BaseException) -> None:
        self.fs, self.exc = fs, exc

    def open_output_stream(self, path):
        return _CutStream(self.fs.open_output_stream(path), 2, self.exc)

    def __getattr__(self, name):
        return getattr(self.fs, name)


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), OSError("connection reset by peer")])
def test_an_interrupted_upload_publishes_nothing(s3, monkeypatch, exc):
    client, _, _, cal = s3
    doc = json.loads(cal.read_text())
    cut = f"cut-{type(exc).__name__}"
    out = f"s3://{BUCKET_OUT}/{cut}"
    tasks = plan([f"s3://{BUCKET_IN}/logs/a.mcap"], out, doc, load_read_settings(None)).tasks
    real = remote.filesystem
    monkeypatch.setattr(remote, "CHUNK", 4096)  # several writes per object
    monkeypatch.setattr(remote, "filesystem", lambda url: (_CutFS(real(url)[0], exc), real(url)[1]))
    with pytest.raises(
        remote.ObjectStoreError if isinstance(exc, OSError) else type(exc)
    ) as raised:
        convert_log(tasks[0])
    if isinstance(exc, OSError):  # one line naming the output object
        assert f"{out}/a.mcap: cannot write" in str(raised.value)
    assert _keys(client, BUCKET_OUT, cut + "/") == {}  # no final object, no temporary key
    monkeypatch.setattr(remote, "filesystem", real)
    stats = convert_log(tasks[0])  # the same task again: complete
    assert stats.status == "converted"
    assert set(_keys(client, BUCKET_OUT, cut + "/")) == {cut + "/a.mcap"}


def test_a_size_mismatch_is_not_published(s3, monkeypatch, tmp_path):
    client, _, _, _ = s3
    local = tmp_path / "x.bin"
    local.write_bytes(b"x" * 1000)
    real_stat = Path.stat

    def short(self, *a, **k):  # the store holding other bytes than the file: seen as a mismatch
        st = real_stat(self, *a, **k)
        return os.stat_result((*st[:6], st.st_size + 1, *st[7:])) if self == local else st

    monkeypatch.setattr(Path, "stat", short)
    with pytest.raises(Exception, match="uploaded 1000 bytes of 1001; not published"):
        remote.publish([(local, f"s3://{BUCKET_OUT}/size/x.bin")])
    assert _keys(client, BUCKET_OUT, "size/") == {}


def test_a_corrupt_object_is_named_by_its_url_and_has_no_output(s3):
    client, _, logs, cal = s3
    data = (logs / "a.mcap").read_bytes()
    client.put_object(Bucket=BUCKET_IN, Key="bad/corrupt.mcap", Body=data[: len(data) // 2])
    out = f"s3://{BUCKET_OUT}/corrupt"
    proc = run_cli("convert", "--calibration", cal, "--out", out, "-q", f"s3://{BUCKET_IN}/bad")
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"imupipe: error: s3://{BUCKET_IN}/bad/corrupt.mcap: truncated or corrupt"
    ), proc.stderr
    assert "imupipe-convert-" not in lines[0]  # the local copy is not named
    assert set(_keys(client, BUCKET_OUT, "corrupt/")) == {"corrupt/manifest.jsonl"}
    (line,) = _manifest(client, "corrupt/manifest.jsonl")
    assert line["status"] == "failed" and line["input"] == f"s3://{BUCKET_IN}/bad/corrupt.mcap"


def test_sigterm_mid_run_leaves_only_complete_objects_and_resumes(s3):
    import signal
    import subprocess
    import sys
    import time

    client, _, _, cal = s3
    src, out = f"s3://{BUCKET_IN}/logs", f"s3://{BUCKET_OUT}/term"
    args = ["convert", "--calibration", str(cal), "--out", out, "--jobs", "2", "-q", src]
    proc = subprocess.Popen(
        [sys.executable, "-m", "imupipe.pipeline.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:  # until the first upload
        listed = client.list_objects_v2(Bucket=BUCKET_OUT, Prefix="term/").get("Contents", [])
        if any(".mcap" in o["Key"] or ".parquet" in o["Key"] for o in listed):
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)  # mid-run: other logs converting, this one publishing
    _, err = proc.communicate(timeout=60)
    assert proc.returncode in (0, 143), err
    keys = _keys(client, BUCKET_OUT, "term/")
    assert not [k for k in keys if k.endswith(".tmp")]  # no temporary key left
    lines = _manifest(client, "term/manifest.jsonl") if "term/manifest.jsonl" in keys else []
    for line in lines:  # every line's output is published, and complete
        assert line["output"].removeprefix(f"s3://{BUCKET_OUT}/") in keys
    for key in (k for k in keys if k.endswith(".mcap")):
        got = _messages(client.get_object(Bucket=BUCKET_OUT, Key=key)["Body"].read())
        assert got  # a whole MCAP: its summary and every message read back
    again = run_cli(*args)
    assert again.returncode == 0, again.stderr
    assert {k for k in _keys(client, BUCKET_OUT, "term/") if k.endswith(".mcap")} == {
        f"term/{n}.mcap" for n in ("a", "site1/m", "site2/r1")
    }
