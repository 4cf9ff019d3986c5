"""The results summary: numbers with their units and uncertainties, on the terminal, in the
recording's documents and in the report; stages whose results lack a key still summarise."""

from __future__ import annotations

import io
import json

import pytest

from imupipe.pipeline.report.summary import (
    fmt,
    fmt_pm,
    print_summary,
    run_markdown,
    stage_markdown,
    summarise,
)
from imupipe.pipeline.simulate import simulate, write_log


def test_value_rounded_to_its_uncertainty():
    assert fmt_pm(0.0100598090, 2.0018e-6) == "0.0100598 ± 2.0e-6"
    assert fmt_pm(1.0199966606, 6.855e-6) == "1.0199967 ± 6.9e-6"
    assert fmt_pm(4.0609, 0.0117) == "4.061 ± 0.012"
    assert fmt_pm(-8.68e-5, 3.1e-6) == "-8.68e-5 ± 3.1e-6"
    assert fmt_pm(0.5, 0.0012) == "0.5000 ± 0.0012"  # four decimals: still written out
    assert fmt_pm(0.002413, 1.5e-7) == "0.00241300 ± 1.5e-7"
    assert fmt_pm(2.0e7, 3.0e5) == "2.000e7 ± 3.0e5"
    assert fmt_pm(5.0, None) == "5"  # no uncertainty: 5 significant digits
    assert fmt(1.7132e-4, 3) == "1.71e-4"
    assert fmt(None) == "-"


GYRO_BIAS = {
    "type": "gyro_bias",
    "input": "static",
    "bias": [0.0100598090, -0.0198317747, 0.0050605560],
    "metrics": {
        "samples": 720000,
        "duration_s": 7199.99,
        "std": [0.0016986, 0.0017007, 0.0017011],
        "bias_std_error": [2.0018e-6, 2.0043e-6, 2.0048e-6],
        "static": True,
    },
    "warnings": ["the IMU moved"],
}


def test_stage_summary_holds_values_units_uncertainty_and_warnings():
    (s,) = summarise({"gyro_bias": GYRO_BIAS})
    assert s.rows[0].name == "bias" and s.rows[0].unit == "rad/s"
    assert s.rows[0].cells == [
        "0.0100598 ± 2.0e-6",
        "-0.0198318 ± 2.0e-6",
        "0.0050606 ± 2.0e-6",
    ]
    assert s.warnings == ["the IMU moved"] and s.status == "ok, 1 warning"
    md = stage_markdown(s)
    assert "| bias (rad/s) | 0.0100598 ± 2.0e-6 |" in md
    assert "**Warnings**" in md and "- the IMU moved" in md
    assert "What to look at." in md


def test_missing_keys_and_unknown_stage_types_still_summarise():
    results = {
        "a": {"type": "accel_calibration", "input": "p", "warnings": []},  # nothing fitted
        "b": {
            "type": "future_stage",
            "input": "q",
            "gain": [1.0, 2.0, 3.0],
            "order": 4,
            "failed_checks": ["residual 4 mg > 3 mg"],
            "warnings": [],
        },  # fmt: skip
    }
    a, b = summarise(results)
    assert a.rows == [] and a.status == "ok"
    assert [r.name for r in b.rows] == ["gain"] and ("order", "4") in b.quality
    assert b.status.startswith("1 failed check accepted")
    md = run_markdown([a, b])
    assert md.startswith("# imupipe run")
    assert "| b | future_stage | q | - | 1 failed check accepted |" in md


def test_poses_and_samples_counted_as_the_metrics_count_them():
    """imu_tk's Xsens session: 40 still intervals make 38 poses (two intervals turned by less than
    2 deg), 14 distinct; the summary names each count for what it is. A magnetometer fit says
    where the samples it did not use went: thinned (over-sampled orientations) and outliers."""
    accel = {
        "type": "accel_calibration",
        "input": "xsens",
        "metrics": {
            "intervals": 40,
            "poses": 38,
            "distinct_poses": 14,
            "residual_mg": {"means_rms": 0.0988, "means_max": 0.21, "start_means_rms": 3.95},
        },
        "warnings": [],
    }
    mag = {
        "type": "mag_calibration",
        "input": "icm",
        "metrics": {
            "samples": 300,
            "samples_after_thinning": 293,
            "samples_used": 287,
            "outliers": 6,
        },
        "warnings": [],
    }
    a, m = summarise({"accel_calibration": accel, "mag_calibration": mag})
    quality = dict(a.quality)
    assert quality["still intervals"] == "40, grouped into 38 poses (14 distinct directions)"
    assert a.headline == "residual 0.0988 mg rms over 38 poses"
    assert dict(m.quality)["samples used"] == "287 of 300 (7 thinned, 6 outliers)"


def test_thermal_soak_summarised_as_values_at_tref_and_the_soaks_residual():
    """thermal_soak had no summariser: the terminal listed its temperature range as an x cell
    and nothing else. It shows each parameter at tref, the soaks and | |a| - g |."""
    poly = {
        a: {"terms": ["1", "T"], "coefficients": [c, 1e-4]}
        for a, c in zip("xyz", [1.02, 0.985, 1.01], strict=True)
    }
    bias = {
        a: {"terms": ["1", "T", "T^2"], "coefficients": [c, 1e-3, 2e-5]}
        for a, c in zip("xyz", [0.15, -0.1, 0.2], strict=True)
    }
    r = {
        "type": "thermal_soak",
        "input": "soaks",
        "tref": 24.97,
        "temperature_range": [-20.0, 69.94],
        "soaks": [{"temperature": t} for t in (-20.0, 24.93, 69.94)],
        "accel": {"parameters": {"scale": poly, "bias": bias}},
        "metrics": {
            "accel_norm_residual_mg": {
                "raw": 20.15, "thermal_model": 0.0183, "one_temperature": 5.22,
                "one_temperature_at": 24.93,
            },
        },
        "warnings": [],
    }  # fmt: skip
    (t,) = summarise({"thermal_soak": r})
    assert [row.label for row in t.rows] == [
        "accel scale at 24.97 degC",
        "accel bias at 24.97 degC (m/s^2)",
    ]
    assert t.rows[1].cells == ["0.15", "-0.1", "0.2"]
    quality = dict(t.quality)
    assert quality["soaks"] == "3, at -20, 24.9, 69.9 degC"
    assert quality["| |a| - g | at the soaks' poses"].startswith("0.0183 mg with the thermal model")
    assert t.headline == "| |a| - g | 0.0183 mg over 3 soaks"


def test_terminal_table():
    from rich.console import Console

    buf = io.StringIO()
    print_summary(summarise({"gyro_bias": GYRO_BIAS}), Console(file=buf, width=120))
    text = buf.getvalue()
    assert "gyro_bias (gyro_bias on static): ok, 1 warning" in text
    assert "bias (rad/s)" in text and "0.0100598 ± 2.0e-6" in text
    assert "warning: the IMU moved" in text


@pytest.fixture(scope="module")
def static_cfg(tmp_path_factory):
    d = tmp_path_factory.mktemp("summary")
    table, _ = simulate("static", {"duration_s": 20.0, "rate_hz": 100.0}, seed=4)
    write_log(d / "static.csv", table)
    (d / "cfg.toml").write_text(
        '[inputs.static]\npath = "static.csv"\n[[stages]]\ntype = "gyro_bias"\n'
        '[output]\ndir = "out"\nrerun = false\nreport = false\n'
    )
    return d / "cfg.toml"


def test_run_prints_the_summary_unless_quiet(static_cfg, cli):
    done = cli("run", static_cfg)
    assert done.returncode == 0, done.stderr
    cal = json.loads((static_cfg.parent / "out" / "calibration.json").read_text())
    r = cal["results"]["gyro_bias"]
    bias = fmt_pm(r["bias"][0], r["metrics"]["bias_std_error"][0])
    assert "gyro_bias (gyro_bias on static)" in done.stdout
    assert bias in done.stdout  # the same number as calibration.json, with its uncertainty
    assert str(static_cfg.parent / "out" / "calibration.json") in done.stdout
    quiet = cli("run", static_cfg, "--quiet")
    assert quiet.returncode == 0 and quiet.stdout == "" and quiet.stderr == ""


MAG_INFLIGHT = {  # results.mag_inflight of `imupipe simulate flight` calibrated (SI: tesla)
    "type": "mag_inflight",
    "input": "flight",
    "model": "soft_iron",
    "motor_term": True,
    "motor_source": "current",
    "matrix": [
        [1.04, 0.020038, -0.014836],
        [0.020038, 0.96993, 0.0099747],
        [-0.0148, 0.01, 1.0193],
    ],
    "offset_t": [1.2009e-5, -8.004e-6, 1.9974e-5],
    "motor_t_per_a": [6.0239e-8, -4.0263e-8, 1.1976e-7],
    "parameter_se": {"motor_x [uT/A]": 2.2e-4, "motor_y [uT/A]": 2.2e-4, "motor_z [uT/A]": 2.3e-4},
    "year": 2024.5,
    "coverage": {"yaw_coverage_deg": 360.0, "tilt_max_deg": 44.5},
    "metrics": {
        "residual_rms_ut_before": 22.817,
        "residual_rms_ut_after": 0.27598,
        "heading_rms_deg_before": 41.811,
        "heading_rms_deg_after": 0.46918,
        "held_out_rms_ut": {"offsets": 1.31, "soft_iron": 0.276},
        "samples": 11991,
        "outliers": 0,
        "field_ut": 49.432,
    },
}


def test_mag_inflight_in_microtesla_milligauss_and_degrees():
    """The compass fit reads like the other stages: labelled rows in uT, mG and deg, the
    soft-iron matrix, a headline and what to look at; no raw key in tesla."""
    (s,) = summarise({"mag_inflight": MAG_INFLIGHT})
    rows = {r.label: r.cells for r in s.rows}
    assert rows["hard iron, offset (uT)"] == ["12.009", "-8.004", "19.974"]
    assert rows["hard iron, offset (mG)"] == ["120.09", "-80.04", "199.74"]
    assert rows["soft iron, row x"] == ["1.0400", "0.0200", "-0.0148"]
    assert [r.name for r in s.rows].count("soft iron, row z") == 1
    assert rows["motor interference (uT/A)"][0] == "0.06024 ± 2.2e-4"
    assert rows["motor interference (mG/A)"] == ["0.60239", "-0.40263", "1.1976"]
    quality = dict(s.quality)
    assert quality["heading error"] == "0.469 deg rms; before 41.8 deg"
    assert quality["vector residual against the WMM"] == "0.276 uT rms; before 22.8 uT"
    assert s.headline == "heading error 41.8 -> 0.469 deg rms"
    assert "heading error" in s.look_at
    md = stage_markdown(s)
    assert "offset_t" not in md and "motor_t_per_a" not in md and "e-5" not in md
    assert "residual_rms_ut_before" not in md
