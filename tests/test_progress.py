"""Issue 38: no silent wait. Every command that can take more than two seconds shows how far it
is on a terminal (bytes of the log being read, rows being written; time elapsed where the total
is unknown) and nothing with ``--quiet`` or when stderr is not a terminal.

- the chunked readers (MCAP, ROS 1 bag) and the simulator's writers report how far they are
  through :mod:`imupipe.readers.progress` (the cause: a bar can only move if they do);
- ``imupipe run`` and ``imupipe simulate`` on a pseudo-terminal show the bar moving in bytes
  and rows; with ``--quiet``, or stderr a pipe, stderr stays empty.
"""

from __future__ import annotations

import os
import pty
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from imupipe.pipeline.progress import count_text
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.pipeline.writers.mcap import write_mcap
from imupipe.readers.dispatch import read_input
from imupipe.readers.progress import listening
from imupipe.readers.spec import InputSpec

from conftest import run_cli


@pytest.fixture(scope="module")
def static_table():
    table, _ = simulate("static", {"duration_s": 300.0}, seed=5)  # 60,000 rows
    return table


def _reports(action) -> list[tuple[int, int]]:
    seen: list[tuple[int, int]] = []
    with listening(lambda done, total: seen.append((done, total))):
        action()
    return seen


@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
def test_writers_and_readers_report_how_far_they_are(static_table, tmp_path: Path, suffix) -> None:
    path = tmp_path / f"static{suffix}"
    if suffix == ".mcap":  # a slice of rows at a time (here smaller than the default)
        written = _reports(lambda: write_mcap(path, static_table, slice_rows=10_000))
    else:
        written = _reports(lambda: write_log(path, static_table))
    assert len(written) >= 3, written  # moves while it writes, not once at the end
    dones = [d for d, _ in written]
    assert dones == sorted(dones) and all(0 <= d <= t for d, t in written)
    read = _reports(lambda: read_input(InputSpec(path=path)))
    size = path.stat().st_size
    assert len({d for d, _ in read}) >= 3, read  # one report per chunk, several chunks
    assert all(t == size and 0 <= d < size for d, t in read)
    assert [d for d, _ in read] == sorted(d for d, _ in read)


def test_nobody_listening_costs_nothing_visible(static_table, tmp_path: Path) -> None:
    path = tmp_path / "static.mcap"
    write_log(path, static_table)  # no listener: no error, no output
    gyro = read_input(InputSpec(path=path))[0]["gyro_x"]
    assert len(gyro) - gyro.null_count == static_table.num_rows


def test_count_text() -> None:
    assert count_text(12.3e6, 37.4e6, "bytes") == "12/37 MB"
    assert count_text(1.25e6, 8.0e6, "bytes") == "1.2/8.0 MB"
    assert count_text(2.5e9, 12e9, "bytes") == "2.5/12.0 GB"
    assert count_text(3, 7, "rows") == "3/7 rows" and count_text(1, 4, "") == "1/4"
    assert count_text(5, None, "bytes") == ""


def _on_a_terminal(args: list[str], cwd: Path) -> tuple[int, str]:
    """Run ``imupipe ARGS`` with stderr on a pseudo-terminal; returns (status, what it showed)."""
    master, slave = pty.openpty()
    env = {**os.environ, "TERM": "xterm", "COLUMNS": "120"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "imupipe.pipeline.cli", *args],
        cwd=cwd, stdout=subprocess.DEVNULL, stderr=slave, env=env,
    )  # fmt: skip
    os.close(slave)
    chunks: list[bytes] = []

    def drain() -> None:
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    status = proc.wait(timeout=600)
    reader.join(timeout=10)
    os.close(master)
    text = b"".join(chunks).decode("utf-8", "replace")
    return status, re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "\n", text.replace("\r", "\n"))


def test_simulate_and_run_show_progress_on_a_terminal(tmp_path: Path) -> None:
    status, shown = _on_a_terminal(
        ["simulate", "static", "--duration", "600", "--out", "static.mcap"], tmp_path
    )
    assert status == 0, shown
    assert "simulating static" in shown and "writing static.mcap" in shown
    rows = [int(m) for m in re.findall(r"\b(\d+)/120000 rows", shown)]
    assert rows and max(rows) > 0, shown
    (tmp_path / "run.toml").write_text(
        '[inputs.static]\npath = "static.mcap"\n[[stages]]\ntype = "gyro_bias"\n'
        '[output]\ndir = "out"\nrerun = false\nreport = false\n'
    )
    status, shown = _on_a_terminal(["run", "run.toml"], tmp_path)
    assert status == 0, shown
    size = (tmp_path / "static.mcap").stat().st_size / 1e6
    assert "reading static (static.mcap)" in shown
    done = [float(m) for m in re.findall(rf"([\d.]+)/{size:.0f} MB", shown)]
    assert done, shown  # the read counted in bytes of the file, not in steps
    # quiet, or not a terminal: nothing on stderr
    status, shown = _on_a_terminal(["run", "run.toml", "--quiet"], tmp_path)
    assert status == 0 and not shown.strip(), shown
    proc = run_cli("simulate", "static", "--duration", "60", "--out", "b.mcap", cwd=tmp_path)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def test_a_bar_of_logs_moves_within_the_log_under_way() -> None:
    """convert and survey count logs; a log read in this process moves the bar within it."""
    import io

    from rich.console import Console
    from rich.progress import Progress

    from imupipe.pipeline.progress import Bar
    from imupipe.readers.progress import report

    progress = Progress(console=Console(file=io.StringIO()))
    bar = Bar(progress, progress.add_task("logs", total=3, count=""))
    completed = lambda: progress.tasks[0].completed  # noqa: E731
    with bar.listen(within_items=True):
        report(50, 100)
        assert completed() == 0.5
        bar.advance()  # the first log done
        assert completed() == 1.0
        report(25, 100)
        assert completed() == 1.25
        report(100, 100)
        assert completed() < 2  # whole only when the log is counted done
    bar.phase("bytes", 1000, "bytes")
    with bar.listen():
        report(3, 4)
    assert progress.tasks[0].completed == 750


def test_a_phase_counts_only_once_its_reader_reports() -> None:
    """A reader that does not report (CSV) shows the time elapsed, not a count stuck at 0."""
    import io

    from rich.console import Console
    from rich.progress import Progress

    from imupipe.pipeline.progress import Bar
    from imupipe.readers.progress import report

    progress = Progress(console=Console(file=io.StringIO()))
    bar = Bar(progress, progress.add_task("run", total=None, count=""))
    bar.phase("reading static (static.csv)", 8e6, "bytes", when_reported=True)
    assert progress.tasks[0].total is None and progress.tasks[0].fields["count"] == ""
    with bar.listen():
        report(1, 4)
    assert progress.tasks[0].total == 8e6 and progress.tasks[0].completed == 2e6
    assert progress.tasks[0].fields["count"] == "2.0/8.0 MB"
