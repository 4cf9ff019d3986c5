"""``imupipe run --spawn``: streams to a Rerun viewer where one can start; where none can, one
line says so and every output is still written. A viewer failure never loses the run's files."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from imupipe.pipeline.report.recording import Recorder
from imupipe.pipeline.simulate import simulate, write_log

from helpers import rrd_rows, screenshot_tool

OUTPUTS = ["calibration.json", "recording.rrd", "static.mcap"]


@pytest.fixture(scope="module")
def cfg(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("spawn")
    table, _ = simulate(
        "static", {"duration_s": 60.0, "rate_hz": 100.0}, seed=5
    )  # a minute: no short-recording warning
    write_log(d / "static.csv", table)
    (d / "cfg.toml").write_text(
        '[inputs.static]\npath = "static.csv"\n[[stages]]\ntype = "gyro_bias"\n'
        '[output]\ndir = "out"\nreport = false\n'
    )
    return d / "cfg.toml"


def run_with_path(cfg: Path, out: str, path: Path) -> subprocess.CompletedProcess:
    """``imupipe run --spawn`` with ``PATH`` set to the folder ``path`` only."""
    text = cfg.read_text().replace('dir = "out"', f'dir = "{out}"')
    (cfg.parent / f"{out}.toml").write_text(text)
    env = {k: v for k, v in os.environ.items() if k != "PATH"} | {"PATH": str(path)}
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "imupipe.pipeline.cli",
            "run",
            "--spawn",
            str(cfg.parent / f"{out}.toml"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


def script(folder: Path, body: str) -> Path:
    folder.mkdir(exist_ok=True)
    exe = folder / "rerun"
    exe.write_text("#!/bin/sh\n" + body)
    exe.chmod(0o755)
    return folder


def test_no_viewer_on_path_says_so_and_writes_everything(cfg, tmp_path):
    (tmp_path / "empty").mkdir()
    done = run_with_path(cfg, "out_none", tmp_path / "empty")
    assert done.returncode == 0, done.stderr
    out = cfg.parent / "out_none"
    assert done.stderr.splitlines() == [
        "imupipe: warning: --spawn: no Rerun viewer on PATH (the 'rerun' command comes with "
        f"rerun-sdk); the recording is written to {out / 'recording.rrd'}: without a display, "
        f"open it with `rerun --web-viewer {out / 'recording.rrd'}`, or see report.html"
    ]
    assert sorted(p.name for p in out.iterdir()) == OUTPUTS
    assert rrd_rows(out / "recording.rrd")["/gyro_bias/corrected/gyro/gyro_x_corrected"] > 0


def test_viewer_that_cannot_start_says_why_in_one_line(cfg, tmp_path):
    # what the viewer does on a machine without a display: it listens, then exits with an error
    folder = script(
        tmp_path / "bin",
        'echo "Error: winit EventLoopError: neither WAYLAND_DISPLAY nor DISPLAY is set." >&2\n'
        "exit 1\n",
    )
    done = run_with_path(cfg, "out_fail", folder)
    assert done.returncode == 0, done.stderr
    out = cfg.parent / "out_fail"
    assert done.stderr.splitlines() == [
        "imupipe: warning: --spawn: the Rerun viewer could not start (Error: winit "
        "EventLoopError: neither WAYLAND_DISPLAY nor DISPLAY is set.); the recording is "
        f"written to {out / 'recording.rrd'}: without a display, open it with "
        f"`rerun --web-viewer {out / 'recording.rrd'}`, or see report.html"
    ]
    assert sorted(p.name for p in out.iterdir()) == OUTPUTS


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # a file the viewer still writes
def test_spawned_viewer_receives_the_whole_recording(cfg, tmp_path):
    real = screenshot_tool().rerun_binary()
    if real is None:
        pytest.skip("no Rerun viewer binary (rerun-sdk's rerun_cli) to stand in for the viewer")
    # there is no display here: the stand-in runs the real viewer binary as a headless gRPC
    # server (what the viewer runs inside) that saves what it receives
    saved, pidfile = tmp_path / "received.rrd", tmp_path / "viewer.pid"
    folder = script(
        tmp_path / "bin",
        "port=9876\n"
        'while [ $# -gt 0 ]; do [ "$1" = "--port" ] && port="$2"; shift; done\n'
        f'echo $$ > "{pidfile}"\n'
        f'exec "{real}" --serve-grpc --port "$port" --save "{saved}"\n',
    )
    done = run_with_path(cfg, "out_live", folder)
    try:
        assert done.returncode == 0, done.stderr
        assert done.stderr == ""
        out = cfg.parent / "out_live"
        assert sorted(p.name for p in out.iterdir()) == OUTPUTS
        expected = rrd_rows(out / "recording.rrd")
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            received = rrd_rows(saved) if saved.exists() else {}
            if received == expected:
                break
            time.sleep(0.5)
        assert received == expected
        import rerun.chunk as rc

        assert len(rc.RrdReader(str(saved)).blueprints()) == 1  # the layout came along
    finally:
        if pidfile.exists():
            os.kill(int(pidfile.read_text()), signal.SIGTERM)


def test_viewer_dying_mid_run_leaves_the_file_whole(tmp_path):
    real = screenshot_tool().rerun_binary()
    if real is None:
        pytest.skip("no Rerun viewer binary (rerun-sdk's rerun_cli) to stand in for the viewer")
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen(
        [real, "--serve-grpc", "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=os.environ | {"RERUN_APP_ONLY": "true"},
    )
    warnings: list[str] = []
    try:
        for _ in range(100):
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.1)
        rec = Recorder(
            tmp_path / "r.rrd", viewer=f"rerun+http://127.0.0.1:{port}/proxy", warn=warnings.append
        )
        t = np.arange(1000, dtype=np.int64) * 10_000_000
        rec.series("/s/a", t, np.zeros(1000), ("a",), unit="rad/s")
        rec._live.flush()
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait()
    rec.series("/s/b", t, np.ones(1000), ("b",), unit="rad/s")
    rec.close()
    assert rrd_rows(tmp_path / "r.rrd") == {"/s/a/a": 1000, "/s/b/b": 1000}  # one per line
    assert len(warnings) == 1 and warnings[0].startswith("the Rerun viewer stopped receiving (")
