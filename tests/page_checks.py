"""The figures and messages the tutorial pages quote, checked on the page's own run.

``tests/test_docs_examples.py::test_tutorial_runs_as_written`` runs every page once, as
written, in a fresh folder; then, for a page named in ``CHECKS``, it calls the page's check with
that folder, the page's text and the completed process of each ```bash block (in order; the
page's ```python blocks, run as one script, last). A check asserts that the run printed and
wrote what the page quotes, and, for a figure the check knows (the run's answer, held to its
digits), that the page quotes that figure: a wrong number on the page or in the run fails.

A command the page describes but does not run (a refused run the page only quotes) runs here,
in the same folder.
"""

from __future__ import annotations

import json
import re
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from conftest import run_cli

Results = list[subprocess.CompletedProcess]


def fenced(page: str, language: str) -> list[str]:
    """The bodies of the page's fenced blocks of ``language``."""
    return re.findall(rf"```{language}[^\n]*\n(.*?)```", page, flags=re.S)


def ran(results: Results, command: str) -> subprocess.CompletedProcess:
    """The run of the one block that holds the line ``command``."""
    found = [r for r in results if command in r.args[-1].splitlines()]
    assert len(found) == 1, f"{len(found)} blocks run {command!r}"
    return found[0]


def quoted(page: str, *snippets: str) -> None:
    """The page quotes each snippet (a figure in its words)."""
    for snippet in snippets:
        assert snippet in page, f"the page does not quote {snippet!r}"


def run(folder: Path, *args: str) -> subprocess.CompletedProcess:
    """``imupipe ARGS`` in the page's folder (a command the page does not run itself)."""
    return run_cli(*args, cwd=folder)


def params(path: Path) -> dict[str, float]:
    """A PX4 parameter file's values by name."""
    rows = {}
    for line in path.read_text().splitlines():
        if not line.startswith("#") and line.strip():
            _, _, name, value, _ = line.split("\t")
            rows[name] = float(value)
    return rows


def same_digits(rows: dict[str, float], quoted_rows: list[str]) -> None:
    """Every quoted parameter row holds the written value to the digits shown."""
    for line in quoted_rows:
        if line.startswith("#"):
            continue
        _, _, name, value, _ = line.split("\t")
        digits = len(value.split(".")[1]) if "." in value else 0
        assert round(rows[name], digits) == float(value), name


def check_ros_bag_to_imu_yaml(folder: Path, page: str, results: Results) -> None:
    proc = ran(results, "imupipe run allan.toml")
    shown = fenced(page, "text")[0].splitlines()
    assert proc.stderr.strip() == shown[0]
    written = proc.stdout.split()[-len(shown[1:]) :]  # the files, after the summary table
    assert written == [str(folder / line) for line in shown[1:]]
    quoted_yaml = yaml.safe_load(fenced(page, "yaml")[0])
    written = yaml.safe_load((folder / "out" / "imu.yaml").read_text())
    for key, value in quoted_yaml.items():
        assert written[key] == (pytest.approx(value, rel=1e-6) if key != "rostopic" else value)
    metrics = json.loads((folder / "out" / "calibration.json").read_text())["results"]["allan"]
    low, high = metrics["metrics"]["gyro"]["x"]["K_range_68"]
    assert low == 0.0 and high == pytest.approx(1.15e-6, rel=0.01)
    quoted(page, f"`[0.0, {high:.2e}]`")


def check_magnetometer_tumble(folder: Path, page: str, results: Results) -> None:
    cal = json.loads((folder / "out" / "calibration.json").read_text())
    m = cal["results"]["mag_calibration"]["metrics"]
    assert round(m["norm_std_pct"], 1) == 6.1 and round(m["noise_pct"], 1) == 6.2
    assert m["noise"] == pytest.approx(3.0e-6, abs=0.05e-6) and m["unexplained_pct"] < 0.05
    quoted(page, f"| `norm_std_pct` | {m['norm_std_pct']:.1f} |")
    quoted(page, f"| {m['noise_pct']:.1f}, {m['noise']:.1e} |")
    # the planar rotation (simulated by the page) is refused with the quoted line, nothing written
    (folder / "planar.toml").write_text(fenced(page, "toml")[0].replace("tumble.bag", "planar.bag"))
    proc = run(folder, "run", "planar.toml")
    assert proc.returncode == 2
    assert proc.stderr.strip() == fenced(page, "text")[0].strip()
    # the real noisy QMC5883L, from the repository root (tests/ reached through a link)
    proc = ran(results, "imupipe run qmc.toml")
    shown = fenced(page, "text")[1].strip().splitlines()
    assert [line.split(": ", 1)[1] for line in proc.stderr.strip().splitlines()][2] == (
        shown[2].split(": ", 1)[1]
    )
    m = json.loads((folder / "out_qmc" / "calibration.json").read_text())["results"]
    m = m["mag_calibration"]["metrics"]
    assert round(m["norm_std_pct"], 2) == 6.19 and round(m["unexplained_pct"], 1) == 1.7
    assert round(m["noise"]) == 64
    quoted(
        page,
        f"spreads by {m['norm_std_pct']:.2f} %",
        f"the per-sample noise ({m['noise']:.0f} counts",
    )
    quoted(page, f"explains all but {m['unexplained_pct']:.1f} %")


def check_multi_position_session(folder: Path, page: str, results: Results) -> None:
    """imu_tk's Xsens session, then a simulated session against its truth (the table)."""
    proc = ran(results, "imupipe run xsens.toml")
    printed = [line.rstrip() for line in proc.stdout.splitlines()]
    for line in fenced(page, "text")[1].rstrip().splitlines():
        assert line in printed, (line, proc.stdout)
    doc = json.loads((folder / "out_xsens" / "calibration.json").read_text())
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
    r = m["residual_mg"]
    quoted(page, f"(`predicted_error_mg` {m['predicted_error_mg']:.3f}:")
    quoted(page, f"is {r['means_rms']:.3f} mg RMS over the {m['poses']} pose means and")
    quoted(page, f"{r['samples_rms']:.2f} mg over", f"noise is {r['noise_per_sample']:.2f} mg")
    quoted(page, "`9-parameter: leave-one-pose-out 0.1469 mg", "`6-parameter: leave-one-pose-out")
    quoted(page, "6-parameter: leave-one-pose-out 3.984 mg")
    quoted(page, f"{1e3 * accel['misalignment_rad']['zx']:.2f} ± ")
    g = gyro["metrics"]
    assert gyro["model"]["chosen"] == "9-parameter" and g["transitions"] == 37
    assert round(g["gravity_direction_residual_deg"]["rms"], 2) == 0.48
    assert round(g["gravity_direction_residual_deg"]["start_rms"], 2) == 3.25
    assert all(2.09e-4 <= s < 2.10e-4 for s in gyro["scale"])
    d = g["gravity_direction_residual_deg"]
    quoted(page, f"within {d['rms']:.2f} deg RMS over {g['transitions']} motions")
    quoted(page, f"({d['start_rms']:.2f} deg before)", "2.09e-4 to 2.10e-4 (rad/s) per count")
    # the simulated session against its truth, to the digits of the table
    truth = json.loads((folder / "poses.csv.truth.json").read_text())
    doc = json.loads((folder / "out_poses" / "calibration.json").read_text())
    accel, gyro = doc["results"]["accel_calibration"], doc["results"]["gyro_calibration"]
    assert truth["accel"]["scale"] == [1.02, 0.985, 1.01]
    assert [round(v, 5) for v in accel["scale"]] == [1.02001, 0.98501, 1.00999]
    assert [round(v, 5) for v in accel["misalignment_rad"].values()] == [0.00402, -0.00601, 0.008]
    assert [round(v, 5) for v in accel["bias"]] == [0.14995, -0.10016, 0.19991]
    assert [round(v, 5) for v in gyro["scale"]] == [1.00999, 0.98994, 1.00496]
    assert [round(v, 5) for v in gyro["bias"]] == [0.01, -0.02001, 0.00499]
    for name, values in [
        ("accelerometer scale x, y, z", accel["scale"]),
        ("accelerometer angles yz, zy, zx (rad)", accel["misalignment_rad"].values()),
        ("accelerometer bias (m/s^2)", accel["bias"]),
        ("gyroscope scale x, y, z", gyro["scale"]),
        ("gyroscope bias (rad/s)", gyro["bias"]),
    ]:
        row = rf"\| {re.escape(name)} \|[^\n]*\| {', '.join(f'{v:.5f}' for v in values)} \|"
        assert re.search(row, page), f"the page's table does not quote {name} as run: {values}"


def check_px4_ulog(folder: Path, page: str, results: Results) -> None:
    """The run writes the files the page lists (both autopilots' parameter files), warns as
    shown, and fits the offsets its table quotes."""
    proc = ran(results, "imupipe run px4.toml")
    shown = fenced(page, "text")[1].strip().splitlines()
    warnings = [line for line in shown if line.startswith("imupipe: warning:")]
    files = [line for line in shown if not line.startswith("imupipe:")]
    got = proc.stderr.strip().splitlines()
    assert len(got) == len(warnings)
    for line, quoted_line in zip(got, warnings, strict=True):
        assert line.startswith(quoted_line.removesuffix(" ..."))
    assert proc.stdout.split()[-len(files) :] == [str(folder / f) for f in files]
    bias = json.loads((folder / "out_px4" / "calibration.json").read_text())
    bias = bias["results"]["gyro_bias"]["bias"]
    assert [round(b, 5) for b in bias] == [0.01737, -0.00013, -0.00556]
    quoted(
        page, "| imupipe `gyro_bias` on `sensor_gyro_1` | " + " | ".join(f"{b:.5f}" for b in bias)
    )


def check_px4_thermal_calibration(folder: Path, page: str, results: Results) -> None:
    """One input with instances = "all": both IMUs' TC_G/TC_A and the barometer's TC_B0 in their
    devices' slots with the quoted figures, the quoted fit of the second gyro, the quoted header,
    no CAL_ACC/CAL_GYRO line, the quoted barometer figures; then the magnetometer's TC_M0 rows
    (``imupipe run mag.toml``, which the page names in its text and does not run)."""
    proc = ran(results, "imupipe run thermal.toml")
    quoted_fit = fenced(page, "text")[1].strip().splitlines()
    printed = [line.rstrip() for line in proc.stdout.splitlines()]
    start = printed.index(next(p for p in printed if p.startswith(quoted_fit[0])))
    assert printed[start + 1 : start + len(quoted_fit)] == quoted_fit[1:]
    text = (folder / "out_thermal" / "px4_calibration.params").read_text()
    shown = fenced(page, "text")[2].strip().splitlines()
    header = [line for line in shown if line.startswith("#")]
    assert "\n".join(header) in text
    rows = params(folder / "out_thermal" / "px4_calibration.params")
    same_digits(rows, shown)
    assert not [n for n in rows if n.startswith(("CAL_ACC", "CAL_GYRO"))]
    assert {n for n in rows if n.endswith("_ID")} == {
        "TC_A0_ID",
        "TC_A1_ID",
        "TC_G0_ID",
        "TC_G1_ID",
        "TC_B0_ID",
    }
    doc = json.loads((folder / "out_thermal" / "calibration.json").read_text())
    baro = doc["results"]["baro_sensor_baro"]["metrics"]
    assert round(baro["correction_span_pa"]) == 196
    assert round(baro["residual_rms_pa"]) == 1
    quoted(
        page,
        f"about {baro['correction_span_pa']:.0f} Pa)",
        f"the sensor's {baro['residual_rms_pa']:.0f} Pa noise",
    )
    # 5. the magnetometer: the quoted TC_M0 rows
    proc = run(folder, "run", "mag.toml")
    assert proc.returncode == 0, proc.stderr
    same_digits(
        params(folder / "out_mag" / "px4_calibration.params"),
        fenced(page, "text")[3].strip().splitlines(),
    )


def check_compass_from_flight(folder: Path, page: str, results: Results) -> None:
    """Sections 1, 2 and 5 (the fit, the level flight refused, the throttle), then section 6 (the
    survey of four flights prints the lines the page quotes)."""
    bash, toml, text = fenced(page, "bash"), fenced(page, "toml")[0], fenced(page, "text")[0]
    assert len(bash) == 5 and bash[1].strip() == "imupipe run compass.toml"
    r = json.loads((folder / "out" / "calibration.json").read_text())["results"]
    r = r["mag_inflight"]
    m = r["metrics"]
    assert r["model"] == "soft_iron" and r["motor_term"]
    assert round(m["residual_rms_ut_before"], 1) == 22.8
    assert round(m["residual_rms_ut_after"], 2) == 0.28
    assert round(m["heading_rms_deg_before"], 1) == 41.8
    assert round(m["heading_rms_deg_after"], 2) == 0.47
    quoted(page, f"| {m['residual_rms_ut_before']:.1f} / {m['residual_rms_ut_after']:.2f} |")
    quoted(page, f"| {m['heading_rms_deg_before']:.1f} / {m['heading_rms_deg_after']:.2f} |")
    report = (folder / "out" / "report.html").read_text()
    for shown in ("heading error before", "heading error after", "vector residual"):
        assert shown in report  # the heading along the flight, the residual against current
    # labelled rows in uT, mG and deg like every stage, not the raw keys in tesla
    for shown in ("hard iron, offset (uT)", "hard iron, offset (mG)", "soft iron, row x"):
        assert shown in report
    assert "offset_t" not in report and "What to look at." in report
    assert "COMPASS_MOTCT,2" in (folder / "out" / "ardupilot_calibration.param").read_text()
    thr = json.loads((folder / "out_throttle" / "calibration.json").read_text())["results"]
    thr = thr["mag_inflight"]
    t = thr["metrics"]
    assert thr["motor_source"] == "throttle" and thr["model"] == "soft_iron"
    assert round(t["residual_rms_ut_before"], 1) == 22.9
    assert round(t["residual_rms_ut_after"], 2) == 0.27
    assert round(t["heading_rms_deg_after"], 2) == 0.46
    held = t["held_out_rms_ut_motor_source"]
    assert (round(held["throttle"], 2), round(held["none"], 2)) == (0.27, 0.79)
    quoted(
        page,
        f"from {t['residual_rms_ut_before']:.1f} to {t['residual_rms_ut_after']:.2f} uT, the heading"
        f" error from {t['heading_rms_deg_before']:.1f} to {t['heading_rms_deg_after']:.2f} deg.",
        f"{held['throttle']:.2f} uT on the held-out\nsegments with it, {held['none']:.2f} uT without",
    )
    params_text = (folder / "out_throttle" / "ardupilot_calibration.param").read_text()
    assert "COMPASS_MOTCT,1" in params_text
    assert not (folder / "out" / "px4_calibration.params").exists()  # an ArduPilot log
    # the level flight (simulated by the page) with model = "soft_iron": the quoted refusal
    level = toml.replace("flight.bin", "level.bin").replace(
        'type = "mag_inflight"', 'type = "mag_inflight"\nmodel = "soft_iron"'
    )
    (folder / "level.toml").write_text(level)
    proc = run(folder, "run", "level.toml")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == text.strip()
    assert not (folder / "out" / "level.mcap").exists()
    # 6. the survey of four flights: the lines the page quotes, the other reason in compass.json
    section = page.split("## 6. Track the compass across flights", 1)[1]
    (script,) = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    (shown,) = re.findall(r"```text\n(.*?)```", section, flags=re.S)
    done = ran(results, "imupipe survey fleet --out survey --no-rerun")
    assert script.strip().splitlines()[-1] in done.args[-1]
    for line in shown.strip().splitlines():
        assert line in done.stdout.splitlines(), (line, done.stdout)
    fleet = json.loads((folder / "survey" / "compass.json").read_text())
    (dev,) = fleet["devices"]
    why = re.search(r"off by\s+(\S+ uT in \S+?)\*", section)
    assert why and f"off by {why.group(1)}" in dev["flags"][-1]["why"]
    assert "off by 5.1 uT in drone/flight_3" in dev["flags"][-1]["why"]


def check_fleet_survey(folder: Path, page: str, results: Results) -> None:
    """The survey of the simulated fleet (section 1) and of the chamber fleet (section 5) print
    the summaries the page quotes."""
    runs = [r for r in results if "imupipe survey fleet --out survey" in r.args[-1].splitlines()]
    assert len(runs) == 2, "the page surveys the fleet, then again (nothing left to do)"
    chamber = ran(
        results, "imupipe survey chamber_fleet --out chamber_survey --chamber chamber_fleet.chamber"
    )
    for done, shown in [
        (runs[0], fenced(page, "text")[0]),
        (chamber, next(b for b in fenced(page, "text") if "chamber curve" in b)),
    ]:
        printed = (done.stdout + done.stderr).splitlines()
        lines = shown.strip().splitlines()
        assert lines and all(line in printed for line in lines), (lines, printed)
        assert printed[printed.index(lines[0]) :][: len(lines)] == lines


def check_readme(folder: Path, page: str, results: Results) -> None:
    """The walk-through writes only the files it names, and warns about nothing (it says "this
    run has none")."""
    done = ran(results, "imupipe run cfg.toml")
    section = page.split("## Calibrate the IMU in your bag", 1)[1].split("\n## ", 1)[0]
    written = sorted(p.name for p in (folder / "out").iterdir())
    assert written and all(f"`{name}`" in section for name in written), written
    assert "warning" not in done.stderr, done.stderr


CHECKS: dict[str, Callable[[Path, str, Results], None]] = {
    "README.md": check_readme,
    "docs/tutorials/ros-bag-to-imu-yaml.md": check_ros_bag_to_imu_yaml,
    "docs/tutorials/magnetometer-tumble.md": check_magnetometer_tumble,
    "docs/tutorials/multi-position-session.md": check_multi_position_session,
    "docs/tutorials/px4-ulog.md": check_px4_ulog,
    "docs/tutorials/px4-thermal-calibration.md": check_px4_thermal_calibration,
    "docs/tutorials/compass-from-flight.md": check_compass_from_flight,
    "docs/tutorials/fleet-survey.md": check_fleet_survey,
}
"""Each page's check, by its path in the repository."""
