"""Fault injection: a full and a read-only output folder (issue 18).

The folders are small tmpfs mounts made in a private user and mount namespace (``unshare
--user --map-root-user --mount``: no root needed where unprivileged user namespaces are allowed,
and nothing is mounted outside the namespace); the tests are skipped, with the reason, where
that is not possible. What the output folder held when the command ended is copied out before
the namespace goes away.
"""

from __future__ import annotations

import functools
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from faults import TALLY, temps

from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.convert.verify import mcap_counts
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap

UNSHARE = ["unshare", "--user", "--map-root-user", "--mount"]


@functools.cache
def can_mount() -> str | None:
    """None when a tmpfs can be mounted in a private namespace here, else why not."""
    if shutil.which("unshare") is None:
        return "no unshare command"
    probe = subprocess.run(
        [*UNSHARE, "sh", "-c", "d=$(mktemp -d) && mount -t tmpfs -o size=64k tmpfs $d"],
        capture_output=True,
        text=True,
    )
    return None if probe.returncode == 0 else f"cannot mount a tmpfs: {probe.stderr.strip()}"


def in_small_fs(tmp: Path, args: list[str], *, size: str, ro: bool = False) -> tuple[int, str]:
    """Run ``imupipe ARGS`` with ``tmp/out`` a tmpfs of ``size`` (read-only with ``ro``);
    the folder's content at the end is copied to ``tmp/saved``. (exit status, stderr)."""
    reason = can_mount()
    if reason is not None:
        pytest.skip(f"no private tmpfs here ({reason})")
    out, saved = tmp / "out", tmp / "saved"
    out.mkdir(exist_ok=True)
    saved.mkdir(exist_ok=True)
    opts = f"size={size}" + (",ro" if ro else "")
    cmd = " ".join(shlex.quote(a) for a in [sys.executable, "-m", "imupipe.pipeline.cli", *args])
    script = (
        f"mount -t tmpfs -o {opts} tmpfs {shlex.quote(str(out))} || exit 99\n"
        f"{cmd}\nrc=$?\ncp -a {shlex.quote(str(out))}/. {shlex.quote(str(saved))}/\nexit $rc\n"
    )
    proc = subprocess.run(
        [*UNSHARE, "sh", "-c", script], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode != 99, proc.stderr
    TALLY["cases"] += 1
    return proc.returncode, proc.stderr


def one_line(code: int, err: str, *needles: str) -> None:
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("imupipe: error: "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
    TALLY["clean"] += 1


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("fs") / "logs"
    d.mkdir()
    table, _ = simulate("static", {"duration_s": 4.0, "rate_hz": 200.0}, seed=1)
    for i in range(4):
        write_mcap(d / f"l{i}.mcap", table)
    cal = d.parent / "cal.json"
    cal.write_text(json.dumps({"chain": [{"type": "t", "sensor": "gyro", "kind": "linear",
                   "matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "offset": [0.1, 0, 0]}]}))  # fmt: skip
    return d, cal


def test_convert_into_a_full_folder(tmp_path, logs):
    folder, cal = logs
    size = (folder / "l0.mcap").stat().st_size
    code, err = in_small_fs(
        tmp_path,
        ["convert", "--calibration", str(cal), "--out", str(tmp_path / "out"), "-j", "2", "-q",
         str(folder)],
        size=str(int(size * 2.5)),
    )  # fmt: skip
    one_line(code, err, str(tmp_path / "out"), "no space left", "the same command resumes")
    saved = tmp_path / "saved"
    assert temps(saved) == []
    done = sorted(p.name for p in saved.glob("*.mcap"))
    assert 0 < len(done) < 4, done
    for p in saved.glob("*.mcap"):  # what is there is complete
        assert mcap_counts(p) is not None
    # a log whose output was committed while the run stopped may miss its manifest line (the
    # manifest is on the full disk too): the next run finds it done
    converted = {Path(r["output"]).name for r in read_manifest(saved) if r["status"] == "converted"}
    assert converted <= set(done)
    # the manifest is whole lines or absent: a line the full disk refused was taken back
    manifest = saved / "manifest.jsonl"
    if manifest.exists():
        text = manifest.read_text()
        assert text and text.endswith("\n"), repr(text[-80:])


def test_run_into_a_full_folder(tmp_path, logs):
    folder, _ = logs
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.a]\npath = "{folder / "l0.mcap"}"\n\n[[stages]]\ntype = "gyro_bias"\n\n'
        '[output]\ndir = "out"\nrerun = false\n'
    )
    code, err = in_small_fs(tmp_path, ["run", str(tmp_path / "cfg.toml"), "-q"], size="40k")
    one_line(code, err, str(tmp_path / "out"), "No space left")
    assert list((tmp_path / "saved").iterdir()) == []


@pytest.mark.parametrize("command", ["run", "convert"])
def test_read_only_folder(tmp_path, logs, command):
    folder, cal = logs
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.a]\npath = "{folder / "l0.mcap"}"\n\n[[stages]]\ntype = "gyro_bias"\n\n'
        '[output]\ndir = "out"\nrerun = false\n'
    )
    args = (
        ["run", str(tmp_path / "cfg.toml")]
        if command == "run"
        else [
            "convert",
            "--calibration",
            str(cal),
            "--out",
            str(tmp_path / "out"),
            "-q",
            str(folder),
        ]
    )
    code, err = in_small_fs(tmp_path, args, size="1m", ro=True)
    one_line(code, err, str(tmp_path / "out"), "Read-only file system")
    assert list((tmp_path / "saved").iterdir()) == []
