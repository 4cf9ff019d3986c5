"""The fault campaign of issue 27 as tests: each group of cases that broke the contract, then a
property-based generator of hostile inputs and paths checked against the contract.

The contract (:mod:`faults`): exit 0, or 2 with one line on stderr (1 with one line per failed log
for a fleet); inputs byte for byte as they were; nothing written outside the output folder and no
temporary file left; on exit 2 no output at all. Beyond it, for what is converted: messages in
equal messages out, and NaN cells in equal NaN cells out under per-axis steps (the non-finite rule
of :func:`imupipe.stages.steps.axis_products`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from faults import check, cli, snapshot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.convert.settings import load_read_settings
from imupipe.pipeline.convert.verify import mcap_counts
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.stages.steps import LinearStep, axis_products

from conftest import TEST_DATA

AXES = [f"{s}_{a}" for s in ("gyro", "accel") for a in "xyz"]
READ_TOML = '[csv]\ntime = "t_ns"\ntime_unit = "ns"\ngyro = ["gyro_x", "gyro_y", "gyro_z"]\n' \
    'accel = ["accel_x", "accel_y", "accel_z"]\n'  # fmt: skip


def chain(scale: tuple[float, float, float] = (1.01, 0.99, 1.02), full: bool = False) -> dict:
    """A calibration of two linear steps, per axis (diagonal) unless ``full``."""
    m = np.diag(scale)
    if full:
        m = m + 0.01 * (1 - np.eye(3))
    return {
        "chain": [
            {"type": "g", "sensor": "gyro", "kind": "linear", "matrix": m.tolist(),
             "offset": [0.01, -0.02, 0.005]},
            {"type": "a", "sensor": "accel", "kind": "linear", "matrix": m.tolist(),
             "offset": [0.05, -0.03, 0.08]},
        ]
    }  # fmt: skip


def csv_text(n: int, cells: dict[tuple[int, str], str], seed: int = 0) -> str:
    """A CSV of ``n`` samples with the cells ``(row, column) -> text`` replaced."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 10_000_000
    vals = np.column_stack(
        [
            0.01 + 1e-3 * rng.standard_normal((n, 3)),
            [0, 0, 9.81] + 1e-2 * rng.standard_normal((n, 3)),
        ]
    )
    lines = ["t_ns," + ",".join(AXES)]
    for i in range(n):
        row = [f"{v:.9g}" for v in vals[i]]
        for j, col in enumerate(AXES):
            row[j] = cells.get((i, col), row[j])
        lines.append(f"{t[i]}," + ",".join(row))
    return "\n".join(lines) + "\n"


def cells_of(path: Path, spec: InputSpec | None = None) -> np.ndarray:
    """The (n, 6) gyro and accel cells of a log, read by imupipe's readers."""
    table, _ = read_input(spec or InputSpec(path=path))
    return np.column_stack([table.column(c).to_numpy(zero_copy_only=False) for c in AXES])


def csv_spec(path: Path, tmp: Path) -> InputSpec:
    """Writes ``tmp/read.toml`` (the ``--config`` of the CSV logs); the spec that reads ``path``."""
    (tmp / "read.toml").write_text(READ_TOML)
    return dataclasses.replace(load_read_settings(tmp / "read.toml"), path=path)


@pytest.fixture(scope="module")
def mcap_log(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("campaign")
    table, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 200.0}, seed=3)
    write_mcap(d / "s.mcap", table)
    return d / "s.mcap"


def fleet_with_cal(tmp_path: Path, mcap_log: Path, cal: dict | None = None) -> tuple[Path, Path]:
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    (fleet / "s.mcap").write_bytes(mcap_log.read_bytes())
    (tmp_path / "cal.json").write_text(json.dumps(cal or chain()))
    return fleet, tmp_path / "cal.json"


# -- 1. a symbolic link at DIR/manifest.jsonl ------------------------------------------------


@pytest.mark.parametrize("target", ["input", "outside", "output"])
def test_a_manifest_link_is_never_followed(tmp_path, mcap_log, target):
    fleet, cal = fleet_with_cal(tmp_path, mcap_log)
    out = tmp_path / "out"
    out.mkdir()
    link = {"input": "../fleet/s.mcap", "outside": str(tmp_path / "elsewhere.txt"),
            "output": "s.mcap"}[target]  # fmt: skip
    (out / "manifest.jsonl").symlink_to(link)
    before = snapshot(tmp_path)
    code, err = cli("convert", "--calibration", cal, "--out", out, "-q", fleet)
    check(f"manifest link to {target}", code, err, tmp_path, before, [])
    assert code == 2 and "manifest.jsonl" in err
    assert not (tmp_path / "elsewhere.txt").exists()


# -- 2. one NaN or Inf axis never reaches the others ------------------------------------------


def test_axis_products_keep_non_finite_cells_to_their_axes():
    diag = np.diag([2.0, 3.0, 4.0])
    v = np.array([[np.nan, 1, 2], [np.inf, 1, 2], [1, -np.inf, 2], [1e308, 1, 2], [1, 2, 3]])
    out = axis_products(diag, v)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(v))
    np.testing.assert_array_equal(np.isinf(out), np.isinf(v))
    assert out[3, 0] == np.finfo(np.float64).max  # finite in, finite out (held at the largest)
    np.testing.assert_array_equal(out[4], [2.0, 6.0, 12.0])
    # a full matrix: an output axis depends on the input axes with non-zero coefficients only
    m = np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.2, 1.0]])
    out = axis_products(m, np.array([[np.nan, 1.0, 2.0], [1.0, np.nan, 2.0]]))
    np.testing.assert_array_equal(np.isnan(out), [[True, False, False], [True, True, True]])
    # the same numbers as a matrix product where everything is finite
    rng = np.random.default_rng(0)
    x, full = rng.standard_normal((50, 3)), rng.standard_normal((3, 3))
    np.testing.assert_allclose(axis_products(full, x), x @ full.T, rtol=1e-14)
    step = LinearStep("t", "gyro", diag, [0.5, 0, 0])
    assert np.isinf(step.apply_values(np.array([[np.inf, 1.0, 1.0]]))).tolist() == [
        [True, False, False]
    ]


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_convert_keeps_nan_cells_to_their_axes(tmp_path, bad):
    """40 rows with ``gyro_x = nan``: 40 NaN cells in, 40 out (it was 120)."""
    (tmp_path / "logs").mkdir()
    log = tmp_path / "logs" / "a.csv"
    log.write_text(csv_text(200, {(i, "gyro_x"): bad for i in range(10, 50)}))
    (tmp_path / "cal.json").write_text(json.dumps(chain()))
    spec = csv_spec(log, tmp_path)
    before = snapshot(tmp_path)
    code, err = cli("convert", "--calibration", tmp_path / "cal.json", "--config",
                    tmp_path / "read.toml", "--out", tmp_path / "out", "-q", log)  # fmt: skip
    check("nan axis", code, err, tmp_path, before, [tmp_path / "out"])
    assert code == 0, err
    raw, done = cells_of(log, spec), cells_of(tmp_path / "out" / "a.mcap")
    assert np.isnan(raw).sum() + np.isinf(raw).sum() == 40
    np.testing.assert_array_equal(np.isnan(done), np.isnan(raw))
    np.testing.assert_array_equal(np.isinf(done), np.isinf(raw))


def test_run_apply_to_keeps_nan_cells_to_their_axes(tmp_path):
    log = tmp_path / "a.csv"
    log.write_text(csv_text(3000, {(i, "gyro_x"): "nan" for i in range(100, 140)}))
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.a]\npath = "{log}"\n[inputs.a.csv]\ntime = "t_ns"\ntime_unit = "ns"\n'
        'gyro = ["gyro_x", "gyro_y", "gyro_z"]\naccel = ["accel_x", "accel_y", "accel_z"]\n\n'
        '[[stages]]\ntype = "gyro_bias"\n\n[output]\ndir = "out"\nrerun = false\nreport = false\n'
        'apply_to = ["a"]\n'
    )
    code, err = cli("run", tmp_path / "cfg.toml", "-q")
    assert code == 0, err
    done = cells_of(tmp_path / "out" / "a.mcap")
    assert np.isnan(done).sum() == 40 and np.isnan(done[:, 0]).sum() == 40


# -- 3. every topic of a ULog carried or named, with its count --------------------------------


def test_ulog_topics_not_carried_are_named_with_their_counts(tmp_path):
    ulog = TEST_DATA / "px4_ulog" / "sample_log_small.ulg"
    (tmp_path / "cal.json").write_text(json.dumps(chain()))
    code, err = cli("convert", "--calibration", tmp_path / "cal.json", "--out",
                    tmp_path / "out", ulog)  # fmt: skip
    assert code == 0, err
    (line,) = [x for x in err.splitlines() if "not carried" in x]
    assert "67 of 70 ULog topics" in line and "12,981 of 14,604 messages" in line
    # issue 38: one readable line, the largest few named; every topic in the manifest
    assert "actuator_controls_0 (1,812)" in line and "(62 more)" in line
    assert "sensor_accel_1" not in line and len(line.replace(str(ulog), "")) < 360
    (rec,) = read_manifest(tmp_path / "out")
    assert len(rec["not_carried"]) == 67 and sum(rec["not_carried"].values()) == 12_981
    assert rec["not_carried"]["vehicle_attitude"] == 1_298
    assert rec["not_carried"]["sensor_accel_1"] == 6
    assert rec["messages"] == 14_604 - 12_981 == sum(mcap_counts(Path(rec["output"])).values())
    assert any("not carried" in w for w in rec["warnings"])


def test_mcap_topics_are_all_carried_without_a_warning(tmp_path, mcap_log):
    fleet, cal = fleet_with_cal(tmp_path, mcap_log)
    code, err = cli("convert", "--calibration", cal, "--out", tmp_path / "out", fleet)
    assert code == 0 and "not carried" not in err
    assert mcap_counts(tmp_path / "out" / "s.mcap") == mcap_counts(fleet / "s.mcap")


# -- 4. an input folder as --out; the sweep of stale temporaries -------------------------------


def test_an_input_folder_as_out_is_refused(tmp_path, mcap_log):
    fleet, cal = fleet_with_cal(tmp_path, mcap_log)
    before = snapshot(tmp_path)
    for _ in range(2):  # the same answer on a second try: nothing was written
        code, err = cli("convert", "--calibration", cal, "--out", fleet, "-q", fleet)
        check("--out = input folder", code, err, tmp_path, before, [])
        assert code == 2 and "searched for logs" in err
    # a folder inside it is fine (it is not searched), and resumes
    for status in ("converted", "skipped"):
        code, err = cli("convert", "--calibration", cal, "--out", fleet / "out", "-q", fleet)
        assert code == 0, err
        assert list(read_manifest(fleet / "out"))[-1]["status"] == status


def test_an_input_folder_under_out_is_never_written_or_swept(tmp_path, mcap_log):
    out = tmp_path / "out"
    (out / "fleet" / "sub").mkdir(parents=True)
    (out / "fleet" / "sub" / "s.mcap").write_bytes(mcap_log.read_bytes())
    (tmp_path / "cal.json").write_text(json.dumps(chain()))
    # names like imupipe's temporaries, of a process that is gone, in the input folder, and one
    # in DIR that is not imupipe's (its random part is not mkstemp's)
    users = [out / "fleet" / ".notes.1@00000000.keep.tmp",
             out / "fleet" / "sub" / ".s.mcap.1@00000000.abcdefgh.tmp", out / ".x.1@00000000.keep.tmp"]  # fmt: skip
    for f in users:
        f.write_text("mine")
    before = snapshot(tmp_path)
    code, err = cli("convert", "--calibration", tmp_path / "cal.json", "--out", out, "-q",
                    out / "fleet")  # fmt: skip
    assert code == 0, err
    after = snapshot(tmp_path)
    assert all(after[k] == v for k, v in before.items()), "an input or a user's file changed"
    assert (out / "sub" / "s.mcap").exists()
    # a stale temporary of imupipe's own in DIR is swept
    stale = out / ".s.mcap.1@00000000.abcdefgh.tmp"
    stale.write_text("")
    code, err = cli("convert", "--calibration", tmp_path / "cal.json", "--out", out, "-q",
                    out / "fleet")  # fmt: skip
    assert code == 0 and not stale.exists() and all(f.exists() for f in users)


def test_a_folder_link_into_an_input_folder_is_refused(tmp_path, mcap_log):
    fleet, cal = fleet_with_cal(tmp_path, mcap_log)
    out = tmp_path / "out"
    out.mkdir()
    (fleet / "robot1").mkdir()
    (fleet / "robot1" / "a.mcap").write_bytes(mcap_log.read_bytes())
    (out / "robot1").symlink_to(fleet / "robot1")  # DIR/robot1/a.mcap would land in the input
    before = snapshot(tmp_path)
    code, err = cli("convert", "--calibration", cal, "--out", out, "-q", fleet)
    check("folder link into the input", code, err, tmp_path, before, [])
    assert code == 2


# -- 5. the full uint64 time range --------------------------------------------------------------


def test_log_times_near_the_end_of_uint64(tmp_path, mcap_log):
    from mcap.reader import make_reader
    from mcap.writer import Writer

    top = 2**64 - 1
    src = tmp_path / "late.mcap"
    with open(mcap_log, "rb") as fh, open(src, "wb") as out:
        writer, ids = Writer(out), {}
        writer.start()
        for i, (schema, channel, msg) in enumerate(make_reader(fh).iter_messages()):
            if channel.id not in ids:
                sid = writer.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = writer.register_channel(channel.topic, "cdr", sid)
            t = top - 1000 + i if i < 300 else i  # both ends of the range in one log
            writer.add_message(ids[channel.id], log_time=t, publish_time=t, data=msg.data)
        writer.finish()
    (tmp_path / "cal.json").write_text(json.dumps(chain()))
    code, err = cli("convert", "--calibration", tmp_path / "cal.json", "--out", tmp_path / "o",
                    "-q", src)  # fmt: skip
    assert code == 0, err
    with open(tmp_path / "o" / "late.mcap", "rb") as fh:
        times = sorted(m.log_time for _, _, m in make_reader(fh).iter_messages())
    with open(src, "rb") as fh:
        assert times == sorted(m.log_time for _, _, m in make_reader(fh).iter_messages())
    assert times[-1] > 2**63


# -- 6. the error contract ----------------------------------------------------------------------


@pytest.mark.parametrize("what", ["README", "missing", "notes.md"])
def test_not_a_log_is_a_bad_command(tmp_path, mcap_log, what):
    _, cal = fleet_with_cal(tmp_path, mcap_log)
    (tmp_path / "README").write_text("hello\n")
    (tmp_path / "notes.md").write_text("# hello\n")
    before = snapshot(tmp_path)
    code, err = cli("convert", "--calibration", cal, "--out", tmp_path / "out", tmp_path / what)
    check(f"convert {what}", code, err, tmp_path, before, [])
    assert code == 2 and not (tmp_path / "out").exists()


def test_debug_keeps_the_exit_status(tmp_path, mcap_log):
    _, cal = fleet_with_cal(tmp_path, mcap_log)
    code, err = cli("--debug", "convert", "--calibration", cal, "--out", tmp_path / "o",
                    tmp_path / "missing")  # fmt: skip
    assert code == 2 and "Traceback" in err
    assert err.strip().splitlines()[-1].startswith("imupipe: error: ")


def test_rerun_max_points_past_int64_is_refused(tmp_path):
    (tmp_path / "a.csv").write_text(csv_text(100, {}))
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.a]\npath = "{tmp_path / "a.csv"}"\n\n[[stages]]\ntype = "gyro_bias"\n\n'
        f'[output]\ndir = "out"\nrerun_max_points = {10**30}\n'
    )
    before = snapshot(tmp_path)
    code, err = cli("run", tmp_path / "cfg.toml", "-q")
    check("rerun_max_points 1e30", code, err, tmp_path, before, [])
    assert code == 2 and "rerun_max_points" in err


def test_a_full_manifest_is_taken_back(tmp_path, monkeypatch):
    """A manifest line that cannot be written (ENOSPC) names the file and leaves the manifest as
    it was (no empty file)."""
    import errno

    from imupipe.pipeline.convert.manifest import Manifest

    m = Manifest(tmp_path)
    real_write = os.write

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OSError) as exc:
        m.append({"input": "a"})
    assert exc.value.filename == str(tmp_path / "manifest.jsonl")
    assert not (tmp_path / "manifest.jsonl").exists()
    monkeypatch.setattr(os, "write", real_write)
    m.append({"input": "a"})
    size = (tmp_path / "manifest.jsonl").stat().st_size
    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OSError):
        m.append({"input": "b"})
    assert (tmp_path / "manifest.jsonl").stat().st_size == size


@pytest.mark.slow
def test_sigterm_while_the_pool_starts(tmp_path, mcap_log):
    """SIGTERM in the first moments of ``convert --jobs 2``: 143 and one line, never a
    multiprocessing traceback (it was 4 tries in 5)."""
    fleet, cal = fleet_with_cal(tmp_path, mcap_log)
    for i in range(3):
        (fleet / f"c{i}.mcap").write_bytes(mcap_log.read_bytes())
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    for delay in (0.1, 0.2, 0.3, 0.35, 0.45):
        out = tmp_path / f"out{delay}"
        proc = subprocess.Popen(
            [sys.executable, "-m", "imupipe.pipeline.cli", "convert", "--calibration", str(cal),
             "--out", str(out), "-j", "2", "-q", str(fleet)],
            stderr=subprocess.PIPE, text=True, env=env,
        )  # fmt: skip
        time.sleep(delay)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        # -15: killed before the interpreter reached imupipe (a shell shows 143 too)
        assert proc.returncode in (0, 143, -15), err
        assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, err
        assert not list(out.rglob(".*.tmp")) if out.exists() else True


# -- 7. one log needs no pool -------------------------------------------------------------------


def test_one_log_is_converted_without_a_pool(tmp_path, mcap_log, monkeypatch):
    from imupipe.pipeline.convert import engines

    def no_pool(*args, **kwargs):
        raise AssertionError("a pool was started for one log")

    monkeypatch.setattr(engines, "run_local", no_pool)
    fleet, cal = fleet_with_cal(tmp_path, mcap_log)
    code, err = cli("convert", "--calibration", cal, "--out", tmp_path / "o", "-q", fleet)
    assert code == 0, err
    (rec,) = read_manifest(tmp_path / "o")
    assert rec["status"] == "converted" and rec["messages"] == sum(
        mcap_counts(fleet / "s.mcap").values()
    )


# -- the property: hostile inputs and paths against the contract --------------------------------

CELL = st.sampled_from(["nan", "inf", "-inf", "NaN", "1e308", "-1e308", "0", "1e-320"])
OUT = st.sampled_from(
    [
        "fresh",
        "the input folder",
        "inside the input folder",
        "containing the input folder",
        "a link to the input folder",
        "manifest links to the input",
        "manifest links outside",
        "a file",
    ]  # fmt: skip
)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    cells=st.dictionaries(st.tuples(st.integers(0, 59), st.sampled_from(AXES)), CELL, max_size=25),
    out_kind=OUT,
    scale=st.tuples(*[st.sampled_from([1.0, 2.0, 0.5, 1e3, -3.0])] * 3),
)
def test_hostile_inputs_and_paths_keep_the_contract(tmp_path_factory, cells, out_kind, scale):
    root = tmp_path_factory.mktemp("prop")
    fleet = root / "fleet"
    fleet.mkdir()
    log = fleet / "a.csv"
    log.write_text(csv_text(60, cells))
    (root / "cal.json").write_text(json.dumps(chain(scale)))
    spec = csv_spec(log, root)
    out = {
        "fresh": root / "out",
        "the input folder": fleet,
        "inside the input folder": fleet / "out",
        "containing the input folder": root,
        "a link to the input folder": root / "link",
        "manifest links to the input": root / "out",
        "manifest links outside": root / "out",
        "a file": root / "cal.json",
    }[out_kind]
    if out_kind == "a link to the input folder":
        out.symlink_to(fleet)
    if out_kind.startswith("manifest"):
        out.mkdir()
        target = log if out_kind.endswith("input") else root.parent / f"{root.name}.outside"
        (out / "manifest.jsonl").symlink_to(target)
    before = snapshot(root)
    code, err = cli("convert", "--calibration", root / "cal.json", "--config", root / "read.toml",
                    "--out", out, "-q", fleet)  # fmt: skip
    outs = [] if out_kind in ("a link to the input folder", "a file") else [out]
    if out_kind == "containing the input folder":
        outs = [root / "a.mcap", root / "manifest.jsonl"]
    check(f"{out_kind} {cells}", code, err, root, before, outs)
    assert not (root.parent / f"{root.name}.outside").exists()
    if code != 0:
        assert out_kind not in ("fresh", "inside the input folder", "containing the input folder")
        return
    raw = cells_of(log, spec)
    done = cells_of(out / "a.mcap")
    assert done.shape == raw.shape  # counts in = counts out
    np.testing.assert_array_equal(np.isnan(done), np.isnan(raw))  # NaN cells in = NaN cells out
    np.testing.assert_array_equal(np.isfinite(done), np.isfinite(raw))  # finite stays finite
