"""The two tutorials of docs/tutorials run as written: their commands, their configs (taken from
the pages), and the figures and messages they quote."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
import yaml

from conftest import REPO, run_cli

TUTORIALS = REPO / "docs" / "tutorials"


def blocks(page: str, language: str) -> list[str]:
    text = (TUTORIALS / page).read_text()
    return re.findall(rf"```{language}[^\n]*\n(.*?)```", text, flags=re.S)


def run_commands(block: str, cwd: Path) -> None:
    for line in block.strip().splitlines():
        args = shlex.split(line)
        assert args[0] == "imupipe", line
        proc = run_cli(*args[1:], cwd=cwd)
        assert proc.returncode == 0, (line, proc.stderr)


def test_ros_bag_to_imu_yaml(tmp_path):
    page = "ros-bag-to-imu-yaml.md"
    run_commands(blocks(page, "bash")[0], tmp_path)
    config = blocks(page, "toml")[0]
    (tmp_path / "allan.toml").write_text(config)
    proc = run_cli("run", "allan.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    shown = blocks(page, "text")[0].splitlines()
    assert proc.stderr.strip() == shown[0]
    written = proc.stdout.split()[-len(shown[1:]) :]  # the files, after the summary table
    assert written == [str(tmp_path / line) for line in shown[1:]]
    quoted = yaml.safe_load(blocks(page, "yaml")[0])
    written = yaml.safe_load((tmp_path / "out" / "imu.yaml").read_text())
    for key, value in quoted.items():
        assert written[key] == (pytest.approx(value, rel=1e-6) if key != "rostopic" else value)
    metrics = json.loads((tmp_path / "out" / "calibration.json").read_text())["results"]["allan"]
    low, high = metrics["metrics"]["gyro"]["x"]["K_range_68"]
    assert low == 0.0 and high == pytest.approx(1.15e-6, rel=0.01)


def test_magnetometer_tumble(tmp_path):
    page = "magnetometer-tumble.md"
    commands = blocks(page, "bash")
    run_commands(commands[0], tmp_path)
    tumble, qmc = blocks(page, "toml")
    (tmp_path / "mag.toml").write_text(tumble)
    proc = run_cli("run", "mag.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    m = cal["results"]["mag_calibration"]["metrics"]
    assert round(m["norm_std_pct"], 1) == 6.1 and round(m["noise_pct"], 1) == 6.2
    assert m["noise"] == pytest.approx(3.0e-6, abs=0.05e-6) and m["unexplained_pct"] < 0.05
    # the planar rotation is refused with the quoted line, nothing written
    run_commands(commands[2], tmp_path)
    (tmp_path / "planar.toml").write_text(tumble.replace("tumble.bag", "planar.bag"))
    proc = run_cli("run", "planar.toml", cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == blocks(page, "text")[0].strip()
    # the real noisy QMC5883L, from the repository root (tests/ reached through a link)
    (tmp_path / "tests").symlink_to(REPO / "tests")
    (tmp_path / "qmc.toml").write_text(qmc)
    proc = run_cli("run", "qmc.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    shown = blocks(page, "text")[1].strip().splitlines()
    assert [line.split(": ", 1)[1] for line in proc.stderr.strip().splitlines()][2] == (
        shown[2].split(": ", 1)[1]
    )
    m = json.loads((tmp_path / "out_qmc" / "calibration.json").read_text())["results"]
    m = m["mag_calibration"]["metrics"]
    assert round(m["norm_std_pct"], 2) == 6.19 and round(m["unexplained_pct"], 1) == 1.7
    assert round(m["noise"]) == 64


def test_multi_position_session(tmp_path):
    """The figures the multi-position tutorial quotes (imu_tk's Xsens session, then a simulated
    session against its truth)."""
    page = "multi-position-session.md"
    (tmp_path / "tests").symlink_to(REPO / "tests")
    xsens, poses = blocks(page, "toml")
    (tmp_path / "xsens.toml").write_text(xsens)
    proc = run_cli("run", "xsens.toml", "--quiet", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out_xsens" / "calibration.json").read_text())
    accel, gyro = doc["results"]["accel_calibration"], doc["results"]["gyro_calibration"]
    m = accel["metrics"]
    assert (m["intervals"], m["poses"], m["threshold"]["k"]) == (40, 38, 4.0)
    assert round(m["predicted_error_mg"], 3) == 0.143
    assert round(m["residual_mg"]["means_rms"], 3) == 0.099
    assert round(m["residual_mg"]["samples_rms"], 2) == 0.82
    assert round(m["residual_mg"]["noise_per_sample"], 2) == 0.75
    assert "9-parameter: leave-one-pose-out 0.1469 mg" in accel["model"]["reason"]
    assert "6-parameter: leave-one-pose-out 3.984 mg" in accel["model"]["reason"]
    assert m["residual_mg"]["raw_means_rms"] is None  # raw counts: no "before calibration"
    assert round(m["error_95_mg"], 3) == 0.266
    assert round(1e3 * accel["misalignment_rad"]["zx"], 2) == 21.23
    g = gyro["metrics"]
    assert gyro["model"]["chosen"] == "9-parameter" and g["transitions"] == 37
    assert round(g["gravity_direction_residual_deg"]["rms"], 2) == 0.48
    assert round(g["gravity_direction_residual_deg"]["start_rms"], 2) == 3.25
    assert all(2.09e-4 <= s < 2.10e-4 for s in gyro["scale"])
    # the simulated session against its truth, to the digits of the table
    run_commands(blocks(page, "bash")[3], tmp_path)
    (tmp_path / "poses.toml").write_text(poses)
    proc = run_cli("run", "poses.toml", "--quiet", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    truth = json.loads((tmp_path / "poses.csv.truth.json").read_text())
    doc = json.loads((tmp_path / "out_poses" / "calibration.json").read_text())
    accel, gyro = doc["results"]["accel_calibration"], doc["results"]["gyro_calibration"]
    assert truth["accel"]["scale"] == [1.02, 0.985, 1.01]
    assert [round(v, 5) for v in accel["scale"]] == [1.02001, 0.98501, 1.00999]
    assert [round(v, 5) for v in accel["misalignment_rad"].values()] == [0.00402, -0.00601, 0.008]
    assert [round(v, 5) for v in accel["bias"]] == [0.14995, -0.10016, 0.19991]
    assert [round(v, 5) for v in gyro["scale"]] == [1.00999, 0.98994, 1.00496]
    assert [round(v, 5) for v in gyro["bias"]] == [0.01, -0.02001, 0.00499]


def test_px4_ulog(tmp_path):
    """The PX4 tutorial's run writes the files it lists (both autopilots' parameter files, as its
    introduction says), warns as shown, and fits the offsets its table quotes."""
    page = "px4-ulog.md"
    (tmp_path / "sample_log_small.ulg").symlink_to(
        REPO / "tests/data/px4_ulog/sample_log_small.ulg"
    )
    (tmp_path / "px4.toml").write_text(blocks(page, "toml")[0])
    proc = run_cli("run", "px4.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    shown = blocks(page, "text")[1].strip().splitlines()
    warnings = [line for line in shown if line.startswith("imupipe: warning:")]
    files = [line for line in shown if not line.startswith("imupipe:")]
    got = proc.stderr.strip().splitlines()
    assert len(got) == len(warnings)
    for line, quoted in zip(got, warnings, strict=True):
        assert line.startswith(quoted.removesuffix(" ..."))
    assert proc.stdout.split()[-len(files) :] == [str(tmp_path / f) for f in files]
    bias = json.loads((tmp_path / "out_px4" / "calibration.json").read_text())
    bias = bias["results"]["gyro_bias"]["bias"]
    assert [round(b, 5) for b in bias] == [0.01737, -0.00013, -0.00556]


def test_px4_thermal_calibration(tmp_path):
    """The PX4 thermal tutorial (one input with instances = "all"): both IMUs' TC_G/TC_A and the
    barometer's TC_B0 in their devices' slots with the quoted figures, the quoted fit of the
    second gyro, the quoted header, no CAL_ACC/CAL_GYRO line, the quoted barometer figures."""
    page = "px4-thermal-calibration.md"
    run_commands(blocks(page, "bash")[0], tmp_path)
    (tmp_path / "thermal.toml").write_text(blocks(page, "toml")[0])
    proc = run_cli("run", "thermal.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    quoted_fit = blocks(page, "text")[1].strip().splitlines()
    printed = [line.rstrip() for line in proc.stdout.splitlines()]
    start = printed.index(next(p for p in printed if p.startswith(quoted_fit[0])))
    assert printed[start + 1 : start + len(quoted_fit)] == quoted_fit[1:]
    text = (tmp_path / "out_thermal" / "px4_calibration.params").read_text()
    quoted = blocks(page, "text")[2].strip().splitlines()
    header = [line for line in quoted if line.startswith("#")]
    assert "\n".join(header) in text
    rows = {}
    for line in text.splitlines():
        if not line.startswith("#") and line.strip():
            _, _, name, value, _ = line.split("\t")
            rows[name] = float(value)
    for line in quoted:
        if line.startswith("#"):
            continue
        _, _, name, value, _ = line.split("\t")
        digits = len(value.split(".")[1]) if "." in value else 0
        assert round(rows[name], digits) == float(value), name
    assert not [n for n in rows if n.startswith(("CAL_ACC", "CAL_GYRO"))]
    assert {n for n in rows if n.endswith("_ID")} == {
        "TC_A0_ID",
        "TC_A1_ID",
        "TC_G0_ID",
        "TC_G1_ID",
        "TC_B0_ID",
    }
    doc = json.loads((tmp_path / "out_thermal" / "calibration.json").read_text())
    baro = doc["results"]["baro_sensor_baro"]["metrics"]
    assert round(baro["correction_span_pa"]) == 196
    assert round(baro["residual_rms_pa"]) == 1
    # 5. the magnetometer: the quoted TC_M0 rows
    run_commands(blocks(page, "bash")[2], tmp_path)
    (tmp_path / "mag.toml").write_text(blocks(page, "toml")[2])
    proc = run_cli("run", "mag.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    text = (tmp_path / "out_mag" / "px4_calibration.params").read_text()
    rows = {}
    for line in text.splitlines():
        if not line.startswith("#") and line.strip():
            _, _, name, value, _ = line.split("\t")
            rows[name] = float(value)
    for line in blocks(page, "text")[3].strip().splitlines():
        _, _, name, value, _ = line.split("\t")
        digits = len(value.split(".")[1]) if "." in value else 0
        assert round(rows[name], digits) == float(value), name
