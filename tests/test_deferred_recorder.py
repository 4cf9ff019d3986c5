"""Issue 39: a run's stages start while Rerun still imports on the warm thread; their drawing
is kept and made on the real recorder once it exists (:mod:`imupipe.pipeline.report.deferred`).
The recording and the report must hold what they held, and a Rerun that cannot be imported must
still end the run with the same one line."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imupipe.pipeline.report.deferred import QUEUED, DeferredRecorder
from imupipe.pipeline.simulate import simulate, write_log


class Log:
    """A recorder that notes every call (and what its arrays held then)."""

    enabled = True

    def __init__(self) -> None:
        self.calls: list[tuple[str, list]] = []
        self.figures = "figures"

    def __getattr__(self, name: str):
        return lambda *a, **k: self.calls.append((name, [np.array(v) for v in a] + [k]))


def test_calls_are_kept_in_order_with_their_arrays_as_given_then_made():
    made: list[Log] = []
    ready = [False]
    rec = DeferredRecorder(lambda: made.append(Log()) or made[-1], lambda: ready[0])
    buf = np.arange(3.0)
    rec.start_at(5)
    rec.curve("/a", buf, label=("x",))
    buf[:] = -1.0  # the caller reuses its buffer: the kept call has what it was given
    rec.series("/b", buf)
    assert not made and not rec.made
    assert rec.figures == "figures"  # anything not a drawing call makes the real one first
    assert len(made) == 1 and rec.made
    names = [c[0] for c in made[0].calls]
    assert names == ["start_at", "curve", "series"]
    np.testing.assert_array_equal(made[0].calls[1][1][1], [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(made[0].calls[2][1][1], [-1.0, -1.0, -1.0])
    rec.document("s", "text")  # made: straight through
    assert made[0].calls[-1][0] == "document" and len(made) == 1


def test_the_first_call_once_ready_makes_it_and_goes_through():
    made: list[Log] = []
    ready = [False]
    rec = DeferredRecorder(lambda: made.append(Log()) or made[-1], lambda: ready[0])
    rec.sensors("stage", "table")
    ready[0] = True
    rec.ensure_stage("stage")
    assert [c[0] for c in made[0].calls] == ["sensors", "ensure_stage"]
    assert rec.enabled is True


def test_only_the_recorders_drawing_methods_are_kept():
    from imupipe.pipeline.report.recording import Recorder

    for name in QUEUED:
        assert callable(getattr(Recorder, name)), name
    assert not {"input_unit", "close", "blueprint", "figures"} & QUEUED


def _config(tmp_path: Path) -> Path:
    table, _ = simulate("static", {"duration_s": 60.0, "rate_hz": 100.0, "temperature": None}, 3)
    write_log(tmp_path / "static.csv", table)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\n\n'
        '[output]\ndir = "out"\n'
    )
    return cfg


def _figures(out: Path) -> str:
    """report.html without its time stamp (it holds every plot the recorder was given)."""
    text = (out / "report.html").read_text()
    return re.sub(r"\d{4}-\d\d-\d\d \d\d:\d\d(:\d\d)?", "T", text)


def test_a_run_deferred_to_the_end_of_its_stages_writes_the_same(tmp_path, monkeypatch):
    from imupipe.pipeline import run as run_module
    from imupipe.pipeline.warm_imports import WarmImports

    cfg = _config(tmp_path)
    run_module.run(cfg, quiet=True)
    direct = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    report = _figures(tmp_path / "out")
    made: list[DeferredRecorder] = []
    real = DeferredRecorder.real

    def noted(self):
        made.append(self)
        return real(self)

    monkeypatch.setattr(WarmImports, "ready", lambda self, name: False)  # Rerun "still" loading
    monkeypatch.setattr(DeferredRecorder, "real", noted)
    summary = run_module.run(cfg, quiet=True)
    assert made, "the run did not defer its recorder"
    assert summary.files and (tmp_path / "out" / "recording.rrd").stat().st_size > 0
    assert _figures(tmp_path / "out") == report
    for name, data in direct.items():
        if name not in ("report.html", "recording.rrd", "calibration.json"):
            assert (tmp_path / "out" / name).read_bytes() == data, name
    strip = re.compile(rb'"time_s": [0-9.e+-]+')
    after = (tmp_path / "out" / "calibration.json").read_bytes()
    assert strip.sub(b"", after) == strip.sub(b"", direct["calibration.json"])


NO_RERUN = """
import sys
sys.modules["rerun"] = None  # an install whose Rerun cannot be imported
from imupipe.pipeline.cli import main
sys.exit(main(["run", sys.argv[1], "--quiet"]))
"""


@pytest.mark.parametrize("report", [True, False])
def test_a_rerun_that_cannot_import_ends_the_run_with_its_one_line(tmp_path, report):
    cfg = _config(tmp_path)
    if not report:
        cfg.write_text(cfg.read_text() + "report = false\n")
    done = subprocess.run(
        [sys.executable, "-c", NO_RERUN, str(cfg)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        "imupipe: error: ModuleNotFoundError: import of rerun halted; None in sys.modules (run with "
        "--debug for the traceback)"
    ]
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())
