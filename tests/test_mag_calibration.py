"""Issue 6, done-when: the ``mag_calibration`` stage on simulated tumbling with known hard and soft
iron (held-out data), on the ICM-20948 set against Magneto 1.4, and refusals through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_mag_ellipsoid import MAGNETO_AINV, MAGNETO_B

from imupipe.pipeline.config import build_options
from imupipe.pipeline.errors import FitError
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.pipeline.simulate.mag import DEFAULTS as MAG_DEFAULTS
from imupipe.readers.table import make_table, sensor
from imupipe.stages.base import StageContext
from imupipe.stages.magnetometer.calibration import MagCalibrationStage

from conftest import run_cli, shared_path
from helpers import decode_mcap, vec


def fit(table, **options):
    stage = MagCalibrationStage(build_options(MagCalibrationStage.Options, options, "test"))
    return stage.fit(table, StageContext(name="mag", input_name="sim", quiet=True))


def held_out_std_pct(step, table, field_norm) -> float:
    """|h| std of another recording corrected by ``step``, in % of the true field."""
    norms = np.linalg.norm(step.apply_values(sensor(table, "mag").values), axis=1)
    return float(100 * norms.std() / field_norm)


@pytest.fixture(scope="module")
def tumbles():
    """Two tumbling sessions of the same sensor (same hard and rotated soft iron)."""
    fit_table, truth = simulate("mag", {}, seed=11)
    held_out, _ = simulate("mag", {}, seed=12)
    return fit_table, held_out, truth["mag"]


def test_general_recovers_hard_and_soft_iron(tumbles):
    fit_table, held_out, truth = tumbles
    out = fit(fit_table, model="general", field_ut=truth["field_norm"] * 1e6)
    step = out.step
    assert held_out_std_pct(step, held_out, truth["field_norm"]) < 0.45
    assert np.linalg.norm(step.offset - truth["hard_iron"]) < 0.3e-6
    np.testing.assert_allclose(step.matrix, truth["matrix"], atol=2e-3)
    np.testing.assert_allclose(step.matrix, step.matrix.T)  # no rotation added
    # native parameters: the raw ellipsoid's semi-axes are the field times the soft-iron scales
    scales = np.sort(MAG_DEFAULTS["soft_iron_scale"])[::-1]
    np.testing.assert_allclose(step.params["radii"], truth["field_norm"] * scales, rtol=2e-3)
    axes, radii = np.array(step.params["axes"]), np.array(step.params["radii"])
    ellipsoid = axes @ np.diag(radii) @ axes.T / truth["field_norm"]
    np.testing.assert_allclose(ellipsoid, truth["soft_iron"], atol=2e-3)
    m = out.results["metrics"]
    assert m["norm_std_pct"] < 0.45 and m["direction_spread"][0] > 0.2
    # the corrected norm is the local field, not the data's radius
    assert m["corrected_norm_mean"] == pytest.approx(truth["field_norm"], rel=1e-3)


def test_axis_aligned_is_worse_on_rotated_soft_iron(tumbles):
    fit_table, held_out, truth = tumbles
    general = held_out_std_pct(fit(fit_table, model="general").step, held_out, truth["field_norm"])
    loose = {"max_unexplained_pct": None}  # the default 5 % bound refuses these fits
    aligned = held_out_std_pct(
        fit(fit_table, model="axis_aligned", **loose).step, held_out, truth["field_norm"]
    )
    sphere = held_out_std_pct(
        fit(fit_table, model="sphere", **loose).step, held_out, truth["field_norm"]
    )
    assert aligned > 0.45 and aligned > 5 * general
    assert sphere > aligned


def test_axis_aligned_suffices_when_the_soft_iron_is_aligned():
    over = {"soft_iron_euler_deg": [0.0, 0.0, 0.0]}
    fit_table, truth = simulate("mag", over, seed=21)
    held_out, _ = simulate("mag", over, seed=22)
    out = fit(fit_table, model="axis_aligned")
    truth = truth["mag"]
    assert held_out_std_pct(out.step, held_out, truth["field_norm"]) < 0.45
    assert np.linalg.norm(out.step.offset - truth["hard_iron"]) < 0.3e-6


def test_thinning_resists_an_oversampled_disturbed_orientation():
    """Tumbling for 30 s, then 3 minutes on a desk whose steel adds 3 uT: without thinning the
    still samples pull the hard iron; with it they weigh like any other orientation."""
    table, truth = simulate("mag", {"duration_s": 30.0}, seed=31)
    truth = truth["mag"]
    tumble = sensor(table, "mag")
    soft, hard = np.array(truth["soft_iron"]), np.array(truth["hard_iron"])
    rng = np.random.default_rng(0)
    desk = (np.array(truth["field"]) + [3e-6, 0, 0]) @ soft.T + hard
    still = desk + 1e-7 * rng.standard_normal((18000, 3))
    t_ns = tumble.t_ns[-1] + 10_000_000 * np.arange(1, 18001)
    both = make_table(np.r_[tumble.t_ns, t_ns], mag=np.vstack([tumble.values, still]))
    err = {}
    for thinning in (False, True):
        out = fit(both, thinning=thinning, outlier_k=None)
        err[thinning] = np.linalg.norm(out.step.offset - hard)
    assert err[True] < 0.1e-6
    assert err[False] > 3 * err[True]


def test_outliers_rejected():
    table, truth = simulate("mag", {"duration_s": 30.0}, seed=41)
    values = sensor(table, "mag").values.copy()
    spikes = np.arange(100, 3000, 100)
    values[spikes] += 20e-6  # a motor switching on
    spiky = make_table(table.column("t_ns").to_numpy(), mag=values)
    out = fit(spiky)
    # a spike across the field changes its norm little: 27 of the 29 are beyond 4 robust sigmas
    # (the two left weigh nothing: the hard iron is as close as with none), and no sample else
    assert len(spikes) - 3 <= out.results["metrics"]["outliers"] <= len(spikes)
    err = np.linalg.norm(out.step.offset - truth["mag"]["hard_iron"])
    assert err < 0.05e-6
    kept = fit(spiky, outlier_k=None)
    assert np.linalg.norm(kept.step.offset - truth["mag"]["hard_iron"]) > 10 * err
    assert kept.results["metrics"]["outliers"] == 0


@pytest.mark.parametrize(
    "options,match",
    [
        ({"max_offset": 0.1}, "> max_offset = 0.1; the fit is not applied"),
        ({"soft_iron_range": [0.97, 1.03]}, "outside soft_iron_range"),
        ({"min_samples": 10_000}, "at least 10000"),
    ],
)
def test_acceptance_bounds_refuse(tumbles, options, match):
    with pytest.raises(FitError, match=match):
        fit(tumbles[0], **options)


def test_failed_check_accepted_on_request(tumbles):
    stage = MagCalibrationStage(build_options(MagCalibrationStage.Options, {"max_offset": 0.1}, ""))
    ctx = StageContext(name="mag", input_name="sim", quiet=True, accept_failed_checks=True)
    out = stage.fit(tumbles[0], ctx)
    assert out.step is not None and "max_offset" in ctx.failed_checks[0]


def test_normalised_field_directions_are_refused(tumbles):
    """A driver that publishes the field normalised (every sample scaled to one length, as the
    SparkFun Razor of imu_tools' bag does at 100 uT) has thrown hard and soft iron away: the fit
    would be the identity and say nothing. Refused with the figure; accepted on request."""
    values = sensor(tumbles[0], "mag").values
    unit = 1e-4 * values / np.linalg.norm(values, axis=1)[:, None]
    table = make_table(sensor(tumbles[0], "mag").t_ns, mag=unit)
    with pytest.raises(FitError, match=r"the magnetometer norm is constant: .* normalised"):
        fit(table)
    stage = MagCalibrationStage(MagCalibrationStage.Options())
    ctx = StageContext(name="mag", input_name="sim", quiet=True, accept_failed_checks=True)
    stage.fit(table, ctx)
    assert ctx.failed_checks[0].startswith("the magnetometer norm is constant")


@pytest.mark.parametrize("noise_ut", [0.15, 0.7])
def test_a_sensor_that_did_not_turn_is_refused_for_it(noise_ut):
    """A magnetometer at rest (a drone on the ground: PX4's test logs) gives a cluster of noise;
    the sphere through it is as small as the noise, so its directions look spread. The stage says
    the sensor did not turn, with the cone its raw field spans, instead of failing the ellipsoid
    fit ('the refined fit is not an ellipsoid') or passing the coverage check."""
    rng = np.random.default_rng(3)
    field = np.array([21.5, 1.0, 43.0]) * 1e-6
    values = field + rng.normal(scale=noise_ut * 1e-6, size=(600, 3))
    table = make_table(np.arange(600, dtype=np.int64) * 100_000_000, mag=values)
    with pytest.raises(
        FitError, match=r"stays within [\d.]+ deg of one direction: the sensor did not turn"
    ):
        fit(table)


def test_px4_log_at_rest_is_refused_for_not_turning():
    """PX4's sample_log_small.ulg (tests/data, BSD-3): vehicle_magnetometer on the ground."""
    from imupipe.readers.dispatch import read_input
    from imupipe.readers.spec import InputSpec

    from conftest import TEST_DATA

    table, _ = read_input(InputSpec(path=TEST_DATA / "px4_ulog" / "sample_log_small.ulg"))
    with pytest.raises(
        FitError, match=r"stays within 2\.8 deg of one direction: the sensor did not turn"
    ):
        fit(table)


def test_narrow_cone_refused():
    """Tilting by at most ~35 degrees: a cap of directions, refused by the spread check."""
    table, truth = simulate("mag", {"duration_s": 20.0}, seed=51)
    values = sensor(table, "mag").values
    soft, hard = np.array(truth["mag"]["soft_iron"]), np.array(truth["mag"]["hard_iron"])
    body = (values - hard) @ np.linalg.inv(soft).T
    axis = np.array(truth["mag"]["field"]) / truth["mag"]["field_norm"]
    near = body @ axis > 0.8 * truth["mag"]["field_norm"]
    assert near.sum() > 50
    cap = make_table(table.column("t_ns").to_numpy()[near], mag=values[near])
    with pytest.raises(FitError, match="covers too few orientations"):
        fit(cap)


ICM_CFG = """
[inputs.icm]
path = "{path}"
[inputs.icm.csv]
mag = [0, 1, 2]
mag_unit = "raw"
rate_hz = 5.0

[[stages]]
type = "mag_calibration"
model = "general"

[output]
dir = "out"
"""


def test_icm20948_through_cli_against_magneto(tmp_path):
    """``imupipe run`` on the header-less raw-count CSV: |h| std no worse than Magneto + 0.05 pp
    on all 300 samples, centre within 0.5 % of the field radius of Magneto's B."""
    path = shared_path("calib", "magneto_icm20948_jremington", "icm_20948_cal_mag.csv")
    (tmp_path / "cfg.toml").write_text(ICM_CFG.format(path=path))
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    (step,) = cal["chain"]
    assert step["type"] == "mag_calibration" and step["sensor"] == "mag"
    h = np.loadtxt(path, delimiter=",")

    def std_pct(matrix, offset):
        norms = np.linalg.norm((h - offset) @ np.asarray(matrix).T, axis=1)
        return 100 * norms.std() / norms.mean()

    magneto = std_pct(MAGNETO_AINV, MAGNETO_B)
    ours = std_pct(step["matrix"], step["offset"])
    assert ours <= magneto + 0.05
    radius = step["field"]
    assert np.linalg.norm(np.array(step["offset"]) - MAGNETO_B) < 0.005 * radius
    metrics = cal["results"]["mag_calibration"]["metrics"]
    assert metrics["norm_std_pct"] == pytest.approx(ours, rel=1e-9)
    # the corrected MCAP carries every sample, corrected by the fitted matrix and offset
    mag = vec(decode_mcap(tmp_path / "out" / "icm.mcap")["/imu/mag"], "magnetic_field")
    expected = (h - step["offset"]) @ np.asarray(step["matrix"]).T
    np.testing.assert_allclose(mag, expected, rtol=1e-12, atol=1e-9)

    import rerun.chunk as rc

    entities = {
        c.entity_path
        for c in rc.RrdReader(str(tmp_path / "out" / "recording.rrd")).stream().to_chunks()
    }
    for entity in ("raw/points", "raw/ellipsoid", "corrected/points", "corrected/sphere"):
        assert f"/mag_calibration/{entity}" in entities
    assert any(e.startswith("/mag_calibration/norm/") for e in entities)  # one per line


REFUSE_CFG = """
[inputs.log]
path = "{name}"

[[stages]]
type = "mag_calibration"

[output]
dir = "out"
"""


@pytest.mark.parametrize(
    "scenario,overrides,message",
    [
        ("mag", {"motion": "planar", "duration_s": 20.0}, "covers too few orientations"),
        ("static", {"duration_s": 5.0}, "has no magnetometer samples"),
    ],
)
def test_cli_refuses_planar_and_magless_data(tmp_path, scenario, overrides, message):
    table, _ = simulate(scenario, overrides, seed=1)
    write_log(tmp_path / "log.csv", table)
    (tmp_path / "cfg.toml").write_text(REFUSE_CFG.format(name="log.csv"))
    proc = run_cli("run", tmp_path / "cfg.toml")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("imupipe: error: stage 'mag_calibration'")
    assert message in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_noisy_tumble_judged_against_its_noise():
    """White noise of 3 uT per axis (6 % of the field): the corrected norm spreads by ~6 % (the
    old 5 % bound refused it), all of it per-sample noise; the fit is kept and its hard and soft
    iron, judged on a clean held-out tumble, are as good as the noise allows."""
    noisy, truth = simulate("mag", {"mag_noise": 3e-6}, seed=61)
    held_out, _ = simulate("mag", {}, seed=62)
    out = fit(noisy)
    m = out.results["metrics"]
    assert m["norm_std_pct"] > 5.5 and m["unexplained_pct"] < 0.6
    assert m["noise"] == pytest.approx(3e-6, rel=0.1)  # T: along the field, per sample
    field = truth["mag"]["field_norm"]
    assert held_out_std_pct(out.step, held_out, field) < 0.5
    assert np.linalg.norm(out.step.offset - truth["mag"]["hard_iron"]) < 0.02 * field


@pytest.mark.parametrize("noise", [1e-7, 2e-6])
def test_a_second_field_is_refused_whatever_the_noise(noise):
    """A magnet fixed to the sensor halfway (the hard iron moves by 20 % of the field): two
    ellipsoids. What the noise does not explain is 6 % at either noise level: refused with the
    figures; a shift of 5 % (1.5 % unexplained, like a real sensor's model error) is kept."""
    field = 4.9e-5
    first, _ = simulate("mag", {"duration_s": 60.0, "mag_noise": noise}, seed=3)
    second, _ = simulate("mag", {"duration_s": 60.0, "mag_noise": noise}, seed=4)
    direction = np.array([1.0, 0.5, -0.3]) / np.linalg.norm([1.0, 0.5, -0.3])

    def joined(shift):
        h = np.vstack([sensor(first, "mag").values, sensor(second, "mag").values])
        h[len(h) // 2 :] += shift * field * direction
        return make_table(np.arange(len(h)) * 10_000_000, mag=h)

    with pytest.raises(FitError, match=r"explains all but 6\.\d+ % > max_unexplained_pct = 5"):
        fit(joined(0.2))
    kept = fit(joined(0.05)).results["metrics"]
    assert 1.2 < kept["unexplained_pct"] < 2.0
