"""The run imports what it needs next on a second thread while it reads its inputs
(:mod:`imupipe.pipeline.warm_imports`): the list must cover what the stages import on first use,
and a failed import must still fail, with its own message, where the run makes it."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from imupipe.pipeline.config import load_config
from imupipe.pipeline.run import warm_modules
from imupipe.pipeline.warm_imports import WarmImports
from imupipe.stages.registry import STAGE_TYPES, stage_modules

FIT_AFTER_WARMING = """
import sys
import numpy as np
from imupipe.stages.registry import stage_modules
import importlib
for name in stage_modules("allan"):
    importlib.import_module(name)
before = {m for m in sys.modules if m.startswith("scipy")}
from imupipe.readers.table import make_table
from imupipe.stages.allan.stage import AllanStage
from imupipe.stages.base import StageContext
rng = np.random.default_rng(0)
n = 20_000
t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 10_000_000
table = make_table(t, gyro=rng.standard_normal((n, 3)) * 1e-3,
                   accel=rng.standard_normal((n, 3)) * 1e-2 + [0, 0, 9.81])
AllanStage(AllanStage.Options()).fit(table, StageContext(name="a", input_name="s", quiet=True))
print(sorted({m for m in sys.modules if m.startswith("scipy")} - before))
"""


def test_the_allan_stage_imports_nothing_of_scipy_the_warm_list_left_out():
    """Run in a fresh interpreter: after importing ``stage_modules("allan")`` a whole fit loads
    no further scipy module (one it did would be imported on the main thread, not warmed)."""
    done = subprocess.run(
        [sys.executable, "-c", FIT_AFTER_WARMING], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_every_stage_type_names_its_module_first():
    for type_name, target in STAGE_TYPES.items():
        assert stage_modules(type_name)[0] == target.split(":")[0]


def test_a_run_warms_its_stages_recorder_report_and_exporters(tmp_path):
    (tmp_path / "s.csv").write_text("t,gx\n0,0\n")
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[inputs.s]\npath = "s.csv"\n[[stages]]\ntype = "allan"\n[[stages]]\ntype = "average"\n'
        '[[stages]]\ntype = "allan"\nname = "again"\n[output]\ndir = "out"\n'
    )
    assert warm_modules(load_config(cfg)) == [
        "imupipe.stages.allan.stage",
        "imupipe.stages.special",
        "imupipe.stages.average",
        "imupipe.pipeline.report.recording",
        "imupipe.pipeline.report.page",
        "imupipe.pipeline.exports.kalibr",
        "imupipe.pipeline.exports.imu_utils",
        "imupipe.pipeline.exports.vins",
        "imupipe.pipeline.exports.openvins",
        "yaml",
    ]
    cfg.write_text(cfg.read_text() + 'report = false\nexports = ["px4"]\n')
    assert warm_modules(load_config(cfg))[-4:] == [
        "imupipe.pipeline.report.recording",
        "imupipe.pipeline.exports.kalibr",
        "imupipe.pipeline.exports.px4",
        "yaml",  # Kalibr's imu.yaml is written whenever an allan stage ran
    ]


def test_the_yaml_writers_are_the_exporters_that_write_yaml():
    """PyYAML is warmed for a run when one of its exporters writes YAML (``yaml_text``)."""
    import importlib
    import inspect

    from imupipe.pipeline.exports import EXPORTERS, YAML_WRITERS

    for name in EXPORTERS:
        source = inspect.getsource(importlib.import_module(f"imupipe.pipeline.exports.{name}"))
        assert ("yaml_text(" in source) == (name in YAML_WRITERS), name


def test_a_module_that_fails_on_the_thread_fails_again_where_it_is_imported():
    with WarmImports(["json", "imupipe_no_such_module"]) as warm:
        pass
    assert warm.failed == ["imupipe_no_such_module"]
    with pytest.raises(ModuleNotFoundError, match="imupipe_no_such_module"):
        import imupipe_no_such_module  # noqa: F401


def test_the_block_waits_for_the_thread_even_when_it_ends_on_an_error():
    with pytest.raises(RuntimeError), WarmImports(["json"]):
        raise RuntimeError("a read failed")
    assert not [t for t in threading.enumerate() if t.name == "imupipe-warm-imports"]


def test_a_one_shot_process_freezes_what_it_imported_and_collects_again():
    import gc

    assert gc.isenabled()
    before = gc.get_freeze_count()
    try:
        with WarmImports(["json"], freeze=True):
            pass
        assert gc.isenabled()
        assert gc.get_freeze_count() > before
    finally:
        gc.unfreeze()
    with WarmImports(["json"]):
        pass
    assert gc.get_freeze_count() == 0


def _csv_config(tmp_path, rows=2_000, name="s.csv"):
    import numpy as np
    import pyarrow as pa
    import pyarrow.csv as pacsv

    values = np.random.default_rng(1).standard_normal((6, rows))
    names = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    columns = {"t_ns": pa.array(np.arange(rows, dtype=np.int64) * 2_500_000)}
    columns.update({n: pa.array(v) for n, v in zip(names, values, strict=True)})
    pacsv.write_csv(pa.table(columns), tmp_path / name)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        f'[inputs.s]\npath = "{name}"\n[[stages]]\ntype = "allan"\n[output]\ndir = "out"\n'
    )
    return load_config(cfg)


def test_a_small_csv_is_parsed_on_one_thread_while_rerun_imports(tmp_path, monkeypatch):
    """Issue 39: CSV inputs under ONE_THREAD_CSV_BYTES, while Rerun's import is still to come,
    leave it a core (one thread on two cores); pyarrow's own count otherwise."""
    import pyarrow as pa

    import imupipe.pipeline.run as run_module
    from imupipe.pipeline.run import parse_threads, pyarrow_threads

    cfg = _csv_config(tmp_path)
    monkeypatch.delitem(sys.modules, "rerun", raising=False)
    with pyarrow_threads(2):
        assert parse_threads(cfg, ["s"]) == 1
    with pyarrow_threads(8):
        assert parse_threads(cfg, ["s"]) == 7
    with pyarrow_threads(1):
        assert parse_threads(cfg, ["s"]) is None
    assert parse_threads(cfg, ["s"]) == (pa.cpu_count() - 1 or None)
    assert parse_threads(cfg, []) is None
    monkeypatch.setattr(run_module, "ONE_THREAD_CSV_BYTES", (tmp_path / "s.csv").stat().st_size)
    assert parse_threads(cfg, ["s"]) is None  # not under the limit
    monkeypatch.undo()
    monkeypatch.setitem(sys.modules, "rerun", sys)  # already imported: nothing to make room for
    assert parse_threads(cfg, ["s"]) is None
    monkeypatch.undo()
    mcap = tmp_path / "s.mcap"
    mcap.write_bytes(b"")
    cfg.inputs["s"].path = mcap
    monkeypatch.delitem(sys.modules, "rerun", raising=False)
    assert parse_threads(cfg, ["s"]) is None  # not a CSV


def test_one_parse_thread_reads_the_same_table_and_restores_the_pool(tmp_path):
    import pyarrow as pa

    from imupipe.pipeline.run import pyarrow_threads
    from imupipe.readers.dispatch import read_input

    cfg = _csv_config(tmp_path, rows=80_000)  # 11 MB: three of the reader's 4 MiB blocks
    before = pa.cpu_count()
    with pyarrow_threads(1):
        assert pa.cpu_count() == 1
        one, _ = read_input(cfg.inputs["s"])
    assert pa.cpu_count() == before
    every, _ = read_input(cfg.inputs["s"])
    assert one.equals(every)
    with pytest.raises(RuntimeError), pyarrow_threads(1):
        raise RuntimeError("a read failed")
    assert pa.cpu_count() == before
