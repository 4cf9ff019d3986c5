"""Issue 2, bad input as SPEC says: one line on stderr, non-zero exit, no traceback, no output."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import run_cli

GOOD_CSV = "t_ns,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + "".join(
    f"{i * 10_000_000},0.01,0.02,0.03,0,0,9.81\n" for i in range(50)
)
GOOD_CFG = '[inputs.a]\npath = "a.csv"\n\n[[stages]]\ntype = "gyro_bias"\n\n[output]\ndir = "out"\n'


def check_one_line_error(proc, *needles: str) -> str:
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def run_case(tmp_path: Path, csv: str | None, cfg: str, *needles: str) -> str:
    if csv is not None:
        (tmp_path / "a.csv").write_text(csv)
    (tmp_path / "cfg.toml").write_text(cfg)
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    line = check_one_line_error(proc, *needles)
    assert not (tmp_path / "out").exists(), list((tmp_path / "out").iterdir())
    return line


def test_good_case_runs(tmp_path):
    (tmp_path / "a.csv").write_text(GOOD_CSV)
    (tmp_path / "cfg.toml").write_text(GOOD_CFG)
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "a.mcap").exists()


def test_missing_config(tmp_path):
    proc = run_cli("run", tmp_path / "nope.toml")
    check_one_line_error(proc, "nope.toml", "no such config file")


def test_missing_input_file(tmp_path):
    run_case(tmp_path, None, GOOD_CFG, "[inputs.a].path", "no such file")


def test_empty_csv(tmp_path):
    run_case(tmp_path, "", GOOD_CFG, "a.csv", "empty")


def test_header_only_csv(tmp_path):
    run_case(tmp_path, GOOD_CSV.splitlines()[0] + "\n", GOOD_CFG, "a.csv", "no rows")


def test_non_numeric_cell_names_row_and_column(tmp_path):
    lines = GOOD_CSV.splitlines()
    lines[7] = lines[7].replace("0.02", "abc")
    line = run_case(tmp_path, "\n".join(lines) + "\n", GOOD_CFG, "a.csv", "line 8", "gyro_y", "abc")
    assert "not a number" in line


def test_missing_mapped_column(tmp_path):
    cfg = GOOD_CFG.replace("[[stages]]", '[inputs.a.csv]\ngyro = ["gx", "gy", "gz"]\n\n[[stages]]')
    run_case(tmp_path, GOOD_CSV, cfg, "a.csv", "'gx'", "not found")


def test_unknown_stage_type(tmp_path):
    run_case(
        tmp_path,
        GOOD_CSV,
        GOOD_CFG.replace('"gyro_bias"', '"gyro_bais"'),
        "stages[0].type",
        "gyro_bais",
    )


def test_unknown_stage_key(tmp_path):
    cfg = GOOD_CFG.replace('type = "gyro_bias"', 'type = "gyro_bias"\nwindow = 3')
    run_case(tmp_path, GOOD_CSV, cfg, "stages[0]", "unknown key 'window'")


def test_wrong_option_type(tmp_path):
    cfg = GOOD_CFG.replace('type = "gyro_bias"', 'type = "gyro_bias"\nmotion_threshold = "high"')
    run_case(tmp_path, GOOD_CSV, cfg, "motion_threshold", "not of type")


@pytest.mark.parametrize(
    "cfg,needles",
    [
        ("[inputs.a\npath = 1", ("cfg.toml", "not valid TOML")),
        (GOOD_CFG + "[extra]\n", ("unknown key 'extra'",)),
        (
            GOOD_CFG.replace('path = "a.csv"', 'path = "a.csv"\nimu_topicc = "/x"'),
            ("[inputs.a]", "unknown key 'imu_topicc'"),
        ),
        (
            GOOD_CFG.replace('dir = "out"', 'dir = "out"\napply_to = ["b"]'),
            ("apply_to", "unknown input 'b'"),
        ),
        (
            GOOD_CFG.replace('type = "gyro_bias"', 'type = "gyro_bias"\ninput = "zz"'),
            ("stages[0].input", "unknown input 'zz'"),
        ),
        (
            GOOD_CFG.replace('path = "a.csv"', 'path = "a.csv"\n[inputs.a.csv]\ngyro_unit = "rpm"'),
            ("gyro_unit", "rpm"),
        ),
    ],
)
def test_config_errors(tmp_path, cfg, needles):
    run_case(tmp_path, GOOD_CSV, cfg, *needles)


def test_unsupported_format(tmp_path):
    (tmp_path / "a.xyz").write_text("hello")
    run_case(tmp_path, None, GOOD_CFG.replace("a.csv", "a.xyz"), "a.xyz", "unknown log format")


def test_fit_error_leaves_no_output(tmp_path):
    # a stage failing after others ran: nothing is left in the output folder
    cfg = GOOD_CFG.replace('type = "gyro_bias"', 'type = "gyro_bias"\ninterval = [100.0, 200.0]')
    run_case(tmp_path, GOOD_CSV, cfg, "gyro_bias", "samples in interval")


def test_debug_shows_traceback(tmp_path):
    (tmp_path / "cfg.toml").write_text("[inputs.a\n")
    proc = run_cli("--debug", "run", tmp_path / "cfg.toml")
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_huge_finite_values_are_left_out_with_one_warning(tmp_path):
    """Cells of 1e308 are numbers no gyro reports: left out of the bias with one counted warning
    (the recording is shorter than the motion check's 1 s blocks, so nothing else would catch
    them), no numpy RuntimeWarning beside it, the report's plots of the raw input drawn."""
    rows = GOOD_CSV.splitlines()
    rows[20] = rows[20].replace("0.01,", "1e308,", 1)
    rows[30] = rows[30].replace("0.02,", "-1e308,", 1)
    (tmp_path / "a.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "cfg.toml").write_text(GOOD_CFG)
    proc = run_cli("run", tmp_path / "cfg.toml")
    assert proc.returncode == 0, proc.stderr
    warned = [line for line in proc.stderr.splitlines() if line.startswith("imupipe: ")]
    assert warned[0] == (
        "imupipe: warning: [gyro_bias] 2 of 50 IMU (gyroscope and accelerometer) samples are "
        "NaN, Inf or beyond 1e+100; fitted on 48"
    ), proc.stderr
    # the only other warning: the recording is under a minute (issue 38)
    assert len(warned) == 2 and "[gyro_bias] only " in warned[1], proc.stderr
    assert "RuntimeWarning" not in proc.stderr
    assert "<svg" in (tmp_path / "out" / "report.html").read_text()
