"""Issue 4: the ``allan`` stage end to end (``imupipe run`` on a simulated static CSV) and its
input checks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.table import make_table, sensor
from imupipe.stages.allan.stage import AllanStage
from imupipe.stages.base import StageContext

from helpers import rrd_static

TRUTH = {
    "gyro_N": [1.7e-4, 2.0e-4, 1.5e-4],
    "gyro_K": [0.0, 0.0, 0.0],
    "accel_N": [2.0e-3, 1.5e-3, 2.5e-3],
    "accel_K": [0.0, 0.0, 0.0],
}


@pytest.fixture(scope="module")
def allan_run(tmp_path_factory):
    from conftest import run_cli

    d = tmp_path_factory.mktemp("allan")
    table, truth = simulate("static", {"duration_s": 1200.0, "rate_hz": 100.0, **TRUTH}, seed=5)
    write_log(d / "static.csv", table)
    (d / "cfg.toml").write_text(
        '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\n\n'
        '[output]\ndir = "out"\napply_to = []\n'
    )
    proc = run_cli("run", d / "cfg.toml")
    assert proc.returncode == 0, proc.stderr
    return d, truth, proc


def test_results_in_calibration_json(allan_run):
    d, truth, _ = allan_run
    res = json.loads((d / "out" / "calibration.json").read_text())["results"]["allan"]
    for s in ("gyro", "accel"):
        for i, axis in enumerate("xyz"):
            got = res[s][axis]
            assert set(got) == {"N", "B", "K", "Q", "R"}
            assert got["N"] == pytest.approx(truth[s]["N"][i], rel=0.03)
    assert res["metrics"]["rate_hz"] == pytest.approx(100.0)
    assert res["metrics"]["kind"] == "oadev"
    assert any("two hours" in w for w in res["warnings"])


def test_kalibr_yaml_is_the_largest_axis(allan_run):
    d, _, _ = allan_run
    res = json.loads((d / "out" / "calibration.json").read_text())["results"]["allan"]
    text = (d / "out" / "imu.yaml").read_text()
    kalibr = yaml.safe_load(text)
    for prefix, s in (("gyroscope", "gyro"), ("accelerometer", "accel")):
        assert kalibr[f"{prefix}_noise_density"] == pytest.approx(
            max(res[s][a]["N"] for a in "xyz"), rel=1e-6
        )
        k_fit = max(res[s][a]["K"] for a in "xyz")
        if k_fit == 0.0:  # the simulation has no random walk: Kalibr gets the 68 % upper bound
            k_fit = max(res["metrics"][s][a]["K_upper_68"] for a in "xyz")
            assert f"{prefix}_random_walk" in text and "upper bound" in text
        assert kalibr[f"{prefix}_random_walk"] == pytest.approx(k_fit, rel=1e-6)
    assert kalibr["rostopic"] == "/imu/data"
    assert kalibr["update_rate"] == pytest.approx(100.0)
    assert "LARGEST" in text and "axis y" in text  # gyro N: y is the largest in TRUTH


def test_imu_utils_yaml_and_curves(allan_run):
    d, truth, _ = allan_run
    text = (d / "out" / "allan_imu_utils.yaml").read_text()
    assert text.startswith("%YAML:1.0") and "random walk density K" in text
    doc = yaml.safe_load(text.replace("%YAML:1.0", ""))
    assert doc["Gyr"]["y-axis"]["gyr_n"] == pytest.approx(truth["gyro"]["N"][1], rel=0.03)
    assert doc["Acc"]["z-axis"]["acc_n"] == pytest.approx(truth["accel"]["N"][2], rel=0.03)
    csv = np.genfromtxt(d / "out" / "allan_curves.csv", delimiter=",", names=True)
    assert csv["tau_s"][0] == pytest.approx(0.01)
    n_true = truth["gyro"]["N"][0]
    np.testing.assert_allclose(
        csv["gyro_x_oadev"][:5], n_true / np.sqrt(csv["tau_s"][:5]), rtol=0.05
    )
    assert np.all(csv["gyro_x_lo68"] < csv["gyro_x_oadev"])
    assert np.all(csv["gyro_x_oadev"] < csv["gyro_x_hi68"])


def test_rerun_curves(allan_run):
    d, _, _ = allan_run
    plots = rrd_static(d / "out" / "recording.rrd")  # static 2D plots, no time axis
    for s in ("gyro", "accel"):
        for axis in "xyz":
            assert len(plots[f"/allan/{s}/{axis}/measured"]["Points2D:positions"]) > 10
            assert len(plots[f"/allan/{s}/{axis}/model"]["LineStrips2D:strips"]) == 1  # the fit
            assert len(plots[f"/allan/{s}/{axis}/terms"]["LineStrips2D:strips"]) >= 1


# -- input checks (in-process: the messages) ---------------------------------------------------
def static_table(n=20_000, fs=100.0, seed=0):
    rng = np.random.default_rng(seed)
    t_ns = 1_700_000_000_000_000_000 + np.round(np.arange(n) * 1e9 / fs).astype(np.int64)
    gyro = rng.standard_normal((n, 3)) * 1e-3
    accel = rng.standard_normal((n, 3)) * 1e-2 + [0.0, 0.0, 9.81]
    return t_ns, gyro, accel


def fit(t_ns, gyro, accel, **options):
    ctx = StageContext(name="allan", input_name="static", quiet=True)
    stage = AllanStage(AllanStage.Options(**options))
    return stage.fit(make_table(t_ns, gyro=gyro, accel=accel), ctx), ctx


def test_nan_samples_are_excluded_and_counted():
    t_ns, gyro, accel = static_table()
    gyro[1234, 1] = np.nan
    accel[5000:5003, 0] = np.inf
    out, ctx = fit(t_ns, gyro, accel, taus="octave")
    assert "4 of 20000 IMU (gyro and accel) samples are NaN or Inf; fitted on 19996" in (
        ctx.warnings
    )
    # their slots on the sample clock are filled, not closed up: the rate stays 100 Hz
    assert any("4 IMU samples missing in 2 gap(s)" in w for w in ctx.warnings)
    m = out.results["metrics"]
    assert m["samples"] == 19996 and m["missing_samples"] == 4
    assert m["rate_hz"] == pytest.approx(100.0, rel=1e-9)
    assert out.results["gyro"]["y"]["N"] == pytest.approx(1e-4, rel=0.05)


def test_too_few_finite_samples_refused():
    from imupipe.pipeline.errors import FitError

    t_ns, gyro, accel = static_table(n=100)
    gyro[2:] = np.nan
    with pytest.raises(FitError, match="2 finite IMU .* samples of 100; the fit needs at least 3"):
        fit(t_ns, gyro, accel)


def jittered(t_ns, rng, late=0.45, spikes=True):
    """Stamps taken on arrival: each late by up to ``late`` periods (uniform), and with
    ``spikes`` every 50th sample 0.66 periods late (steps of 1.66 and 0.34 periods, as in the
    Phidgets bag)."""
    period = float(np.median(np.diff(t_ns)))
    delay = rng.uniform(0.0, late, len(t_ns))
    if spikes:
        delay[::50] = 0.66
    return t_ns + np.round(delay * period).astype(np.int64)


def test_jitter_is_not_a_gap():
    """Stamps late by up to 0.66 periods: steps from 0.34 to 1.66 periods; nothing missing,
    nothing filled, no gap, the rate and the noise as without jitter."""
    t_ns, gyro, accel = static_table()
    stamps = jittered(t_ns, np.random.default_rng(1))
    assert np.diff(stamps).max() > 1.6 * 10_000_000
    out, ctx = fit(stamps, gyro, accel, taus="octave")
    m = out.results["metrics"]
    assert m["missing_samples"] == 0 and m["samples"] == 20_000
    assert 0.1 < m["timestamp_jitter"] < 0.3
    assert not any("gap" in w or "missing" in w for w in ctx.warnings)
    assert m["rate_hz"] == pytest.approx(100.0, rel=1e-4)
    plain, _ = fit(t_ns, gyro, accel, taus="octave")
    for axis in "xyz":  # the same samples; the mean rate differs by the end stamps' jitter
        assert out.results["gyro"][axis]["N"] == pytest.approx(
            plain.results["gyro"][axis]["N"], rel=1e-4
        )


def test_lost_samples_are_filled_and_counted():
    """50 single samples lost (steps of two periods) among stamps late by up to 0.3 periods:
    counted, filled by interpolation on the nominal clock, the noise density unchanged within
    2 %. (A stamp more than half a period late next to a lost sample is ambiguous from its
    neighbours alone: such a loss may go uncounted.)"""
    t_ns, gyro, accel = static_table()
    stamps = jittered(t_ns, np.random.default_rng(2), late=0.3, spikes=False)
    lost = np.arange(200, 20_000, 397)[:50]
    keep = np.setdiff1d(np.arange(len(t_ns)), lost)
    out, ctx = fit(stamps[keep], gyro[keep], accel[keep], taus="octave")
    m = out.results["metrics"]
    assert m["missing_samples"] == 50 and m["gaps_filled"] == 50
    (warning,) = [w for w in ctx.warnings if "missing" in w]
    assert warning.startswith("50 IMU samples missing in 50 gap(s) (0.25 % of the 100 Hz clock")
    assert m["rate_hz"] == pytest.approx(100.0, rel=1e-4)
    plain, _ = fit(t_ns, gyro, accel, taus="octave")
    for axis in "xyz":
        assert out.results["gyro"][axis]["N"] == pytest.approx(
            plain.results["gyro"][axis]["N"], rel=0.02
        )


def test_long_gap_uses_the_longest_stretch():
    t_ns, gyro, accel = static_table()
    t_ns[5000:] += 2_000_000_000  # 2 s missing after sample 4999
    out, ctx = fit(t_ns, gyro, accel, taus="octave")
    (warning,) = [w for w in ctx.warnings if "gap(s) longer" in w]
    assert warning.startswith(
        "1 gap(s) longer than max_gap = 10 sample periods (the longest: 2.010 s, 200 samples "
        "missing, after IMU sample 4999 at t = 49.990 s); the deviations use the longest stretch "
        "without one: IMU samples 5000 to 19999, 150.0 s of 202.0 s"
    )
    assert out.results["metrics"]["samples"] == 15_000
    assert out.results["metrics"]["missing_samples"] == 0


def test_time_not_increasing_is_an_error_naming_it():
    from imupipe.pipeline.errors import FitError

    t_ns, gyro, accel = static_table()
    t_ns[700] = t_ns[699]
    with pytest.raises(FitError, match=r"time does not increase at IMU sample 700 \(step 0 ns\)"):
        fit(t_ns, gyro, accel)


def test_too_short_for_the_fit():
    from imupipe.pipeline.errors import FitError

    t_ns, gyro, accel = static_table(n=60)
    with pytest.raises(FitError, match="taus on the 'octave' grid; fitting 5 terms needs"):
        fit(t_ns, gyro, accel, taus="octave")


def test_motion_is_a_failed_check():
    from imupipe.pipeline.errors import FitError

    t_ns, gyro, accel = static_table()
    gyro[8000:9000, 2] += 0.5  # 10 s of turning
    with pytest.raises(FitError, match=r"1 s gyro means depart 0\.\d+ rad/s from the mean"):
        fit(t_ns, gyro, accel, taus="octave")
    ctx = StageContext(name="allan", input_name="static", quiet=True, accept_failed_checks=True)
    stage = AllanStage(AllanStage.Options(taus="octave"))
    out = stage.fit(make_table(t_ns, gyro=gyro, accel=accel), ctx)
    assert out.results["metrics"]["static"] is False
    assert any("does not look static" in w and "accepted" in w for w in ctx.warnings)
    assert "measures it, not the noise" in ctx.failed_checks[0]


def test_cli_error_is_one_line(tmp_path):
    from conftest import run_cli

    table, _ = simulate("static", {"duration_s": 2.0, "rate_hz": 20.0}, seed=1)
    write_log(tmp_path / "short.csv", table)
    (tmp_path / "cfg.toml").write_text(
        '[inputs.s]\npath = "short.csv"\n\n[[stages]]\ntype = "allan"\ntaus = "octave"\n\n'
        '[output]\ndir = "out"\napply_to = []\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    assert "stage 'allan' on input 's'" in proc.stderr
    assert not (tmp_path / "out" / "imu.yaml").exists()


@pytest.mark.parametrize("kind", ["mdev", "hdev", "totdev"])
def test_other_kinds_are_shown_and_the_fit_uses_oadev(kind):
    t_ns, gyro, accel = static_table()  # white noise, std 1e-3 at 100 Hz: N = 1e-4
    out, _ = fit(t_ns, gyro, accel, kind=kind, taus="octave")
    assert out.results["metrics"]["kind"] == kind
    assert out.results["metrics"]["fit_kind"] == "oadev"
    assert out.results["gyro"]["x"]["N"] == pytest.approx(1e-4, rel=0.05)
    header = out.artifacts["allan_curves.csv"].splitlines()[0].split(",")
    assert f"gyro_x_{kind}" in header and "gyro_x_oadev" in header


def test_interval_selects_samples():
    t_ns, gyro, accel = static_table()
    gyro[15_000:] += 1.0  # the IMU turns after 150 s: outside the interval
    out, ctx = fit(t_ns, gyro, accel, interval=[0.0, 100.0], taus="octave")
    assert out.results["metrics"]["samples"] == 10_001
    assert out.results["metrics"]["static"] is True
    assert out.results["gyro"]["x"]["N"] == pytest.approx(1e-4, rel=0.05)


def test_analysis_only_run_writes_no_corrected_copy(tmp_path):
    """``[output] apply_to`` left out: a run whose stages only analyse (allan) writes no
    corrected MCAP (nothing was corrected); an explicit list still writes its inputs."""
    from conftest import run_cli

    table, _ = simulate("static", {"duration_s": 120.0, "rate_hz": 50.0}, seed=2)
    write_log(tmp_path / "static.csv", table)
    base = '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\ntaus = "octave"\n\n'
    for out, extra in (("default", ""), ("listed", 'apply_to = ["static"]\n')):
        (tmp_path / f"{out}.toml").write_text(
            base + f'[output]\ndir = "{out}"\nrerun = false\n' + extra
        )
        proc = run_cli("run", tmp_path / f"{out}.toml", "--quiet")
        assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (tmp_path / "default").iterdir()) == [
        "allan_curves.csv",
        "allan_imu_utils.yaml",
        "calibration.json",
        "imu.yaml",
        "kalibr_imu_chain.yaml",
        "report.html",
        "vins_imu.yaml",
    ]
    assert (tmp_path / "listed" / "static.mcap").stat().st_size > 0


def test_white_noise_not_resolved_is_exported_as_its_upper_bound_never_zero():
    """Issue 25: a recording at 10 Hz whose shortest tau is already dominated by bias instability
    (a phone's decimated log): the fit resolves no N; imu.yaml and the imu_utils layout get the
    upper bound sigma(tau) sqrt(tau) from the shortest taus (at or above the truth), never 0.0,
    with a warning and a comment saying so."""
    from imupipe.pipeline.exports.imu_utils import imu_utils_doc
    from imupipe.pipeline.exports.kalibr import noise_yaml

    p = {
        "rate_hz": 10.0,
        "duration_s": 3600.0,
        "gyro_N": [1e-4] * 3,
        "gyro_B": [1e-3] * 3,
        "gyro_K": [0.0] * 3,
        "accel_N": [1e-3] * 3,
        "accel_B": [1e-2] * 3,
        "accel_K": [0.0] * 3,
    }
    table, _ = simulate("static", p, seed=1)
    ctx = StageContext(name="allan", input_name="s", quiet=True)
    results = AllanStage(AllanStage.Options()).fit(table, ctx).results
    results["type"] = "allan"
    assert any(w.startswith("white noise not resolved") for w in ctx.warnings)
    text = noise_yaml("allan", results)
    doc = yaml.safe_load(text)
    for prefix, truth in (("gyroscope", 1e-4), ("accelerometer", 1e-3)):
        assert truth <= doc[f"{prefix}_noise_density"] <= 5 * truth
    assert "UPPER BOUND from the shortest taus" in text
    layout = imu_utils_doc(results)
    assert all(row["gyr_n"] > 0 for row in layout["Gyr"].values() if isinstance(row, dict))


def test_a_jump_of_the_bias_is_refused_not_read_as_a_random_walk():
    """Issue 25's sweep: a gyro bias step of one sample's noise (2.5e-3 rad/s at 100 Hz, below
    the motion threshold) at half time made K ten times the truth; it is a failed check naming
    the jump, where it is and what to do. Without the step the same recording passes."""
    from imupipe.pipeline.errors import FitError

    p = {"duration_s": 1200.0, "rate_hz": 100.0, "gyro_N": [2.5e-4] * 3}
    table, _ = simulate("static", p, seed=3)
    gyro = sensor(table, "gyro").values.copy()
    t_ns = sensor(table, "gyro").t_ns
    accel = sensor(table, "accel").values
    ctx = StageContext(name="allan", input_name="s", quiet=True)
    AllanStage(AllanStage.Options()).fit(table, ctx)  # no jump: no failed check
    gyro[len(gyro) // 2 :, 0] += 2.5e-3
    stepped = make_table(t_ns, gyro=gyro, accel=accel)
    with pytest.raises(FitError, match=r"the gyro bias jumps by 0\.002[4-7]\d* rad/s about 600 s"):
        AllanStage(AllanStage.Options()).fit(stepped, ctx)
