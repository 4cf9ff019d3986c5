"""``mag_calibration`` on real tumbling sets against the fits their authors published, with
default options: the QMC5883L sets of tomisuarez2/MagnetometerCalibration (MIT, tests/data),
Magneto's answer for Michael Wrona's FXOS8700 set (no licence: read from ../shared), and the
Phidgets bag of imu_tools (GPL, ../shared) whose magnetometer stream is half NaN.

Figures are |h| std in % of the mean |h| of the corrected samples (what both authors show)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.pipeline.config import build_options
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import CsvMapping, InputSpec
from imupipe.stages.base import StageContext
from imupipe.stages.errors import FitError
from imupipe.stages.magnetometer.calibration import MagCalibrationStage

from conftest import TEST_DATA, run_cli, shared_path

QMC = TEST_DATA / "qmc5883l_tomisuarez"
QMC_INIT = 3000
"""The first 60 s at 50 Hz: the sensor at rest before the tumbling; the authors' fit skips it
(``t_init`` in their ``calibrate_mag_from_data``)."""

# tomisuarez2/MagnetometerCalibration, "optimization result data/paramters_mag.csv":
# [a11 .. a33, b1 b2 b3], calibrated = A @ raw + b (their apply_mag_calibration). The fit of
# noisy_raw_data.csv is the version at commit b57130f1a34b0148acc33834a14e4071474c112a (whose
# CalibrationTests/test_mag_calibration.py reads that file); the fit of filtered_raw_data.csv the
# version at 9590433598f12d58c009d0680fa0c171e05e7d77 (whose test reads that one).
QMC_PUBLISHED = {
    "noisy": (
        [9.245237182442075019e-04, -3.688388709191654053e-06, 3.453668566727742089e-06],
        [-5.322591438996653507e-05, 1.348658099253034585e-03, -4.036562569472319637e-05],
        [-1.267906109846512230e-05, -4.913899879534819570e-05, 6.250403675176544310e-04],
        [-5.704757833872988293e00, 1.260117523397376038e-01, -2.063140195611369521e00],
    ),
    "filtered": (
        [9.239633019853381877e-04, -2.282760375277355860e-05, -1.264915698714182454e-05],
        [-3.264636888055812386e-05, 1.394196009755322742e-03, -8.316408758871346853e-05],
        [9.246626792836116709e-07, 5.043424401002268953e-05, 6.255306542452643108e-04],
        [-5.674257299474922966e00, 1.399525040268657095e-01, -2.193756343933045638e00],
    ),
}
QMC_PUBLISHED_STD = {"noisy": 5.95, "filtered": 2.90}
"""Their fits' |h| std on the tumbling samples, rounded as the issue quotes them."""

# Magneto's answer for michaelwro/mag-cal-example examples/mag-readings.txt, as published in
# plot-calibration-data.py @ 2f0decaeb5606851d5d93fea604873f167efb7f0: h_calib = A (h - b), uT
WRONA_A = np.array(
    [
        [0.989575, -0.022220, 0.005152],
        [-0.022220, 0.989327, 0.022216],
        [0.005152, 0.022216, 1.045404],
    ]
)
WRONA_B = np.array([28.557458, -39.981060, -27.428035])
WRONA_STILL = 24
"""The first 24 samples (2.4 s at 10 Hz): the sensor still before the tumbling."""


def std_pct(calibrated: np.ndarray) -> float:
    norms = np.linalg.norm(calibrated, axis=1)
    return float(100 * norms.std() / norms.mean())


def qmc_raw(name: str) -> np.ndarray:
    return np.loadtxt(QMC / f"{name}_raw_data.csv", delimiter=",", skiprows=3)


def published_qmc(name: str, h: np.ndarray) -> np.ndarray:
    *rows, b = QMC_PUBLISHED[name]
    return h @ np.array(rows).T + np.array(b)


@pytest.mark.parametrize("name", ["noisy", "filtered"])
def test_published_qmc_figures_reproduced(name):
    """The authors' parameters leave 5.95 % (noisy) and 2.90 % (filtered) on the tumbling
    samples (6.19 % and 2.81 % on every sample)."""
    h = qmc_raw(name)
    assert len(h) == {"noisy": 22743, "filtered": 22745}[name]
    tumbling = std_pct(published_qmc(name, h[QMC_INIT:]))
    assert tumbling == pytest.approx(QMC_PUBLISHED_STD[name], abs=0.005)


def qmc_stage(name: str, **options):
    mapping = CsvMapping(mag=["mx", "my", "mz"], mag_unit="raw", gyro=None, accel=None)
    table, _ = read_input(InputSpec(path=QMC / f"{name}_raw_data.csv", csv=mapping))
    stage = MagCalibrationStage(build_options(MagCalibrationStage.Options, options, "test"))
    ctx = StageContext(name="mag_calibration", input_name=name, quiet=True)
    return stage.fit(table, ctx), ctx


def test_qmc_noisy_through_the_cli(tmp_path):
    """The noisy set (sample-to-sample std ~90 counts on a radius of ~1090) was refused at
    6.19 % > 5 %. Judged against its noise it is as clean an ellipsoid as the filtered set:
    fitted with default options, no worse than the authors' 5.95 % + 0.05 pp on the same
    samples, its warnings in counts."""
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.qmc]\npath = "{QMC / "noisy_raw_data.csv"}"\n[inputs.qmc.csv]\n'
        'mag = ["mx", "my", "mz"]\nmag_unit = "raw"\n\n[[stages]]\ntype = "mag_calibration"\n\n'
        '[output]\ndir = "out"\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml")
    assert proc.returncode == 0, proc.stderr
    assert "'T'" not in proc.stderr and "radius 1087 counts" in proc.stderr
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    (step,) = cal["chain"]
    h = qmc_raw("noisy")
    ours = std_pct((h[QMC_INIT:] - step["offset"]) @ np.array(step["matrix"]).T)
    assert ours <= QMC_PUBLISHED_STD["noisy"] + 0.05
    m = cal["results"]["mag_calibration"]["metrics"]
    assert m["unit"] == "counts"
    assert 60 < m["noise"] < 70  # counts, per sample along the field (5.9 % of the radius)
    assert m["unexplained_pct"] < 2.0 < 5.0 < m["norm_std_pct"]


def test_qmc_noisy_and_filtered_leave_the_same_unexplained_spread():
    """The two recordings of one sensor: 6.2 % and 2.8 % of spread, of which the noise leaves
    1.7 % and 1.8 %: the noisy one is no worse an ellipsoid. The filtered set is fitted no worse
    than the authors' 2.90 % + 0.05 pp."""
    noisy, _ = qmc_stage("noisy")
    filtered, _ = qmc_stage("filtered")
    unexplained = [r.results["metrics"]["unexplained_pct"] for r in (noisy, filtered)]
    assert unexplained == pytest.approx([1.7, 1.8], abs=0.15)
    h = qmc_raw("filtered")
    ours = std_pct((h[QMC_INIT:] - filtered.step.offset) @ filtered.step.matrix.T)
    assert ours <= QMC_PUBLISHED_STD["filtered"] + 0.05


def wrona_fit(**options):
    path = shared_path("calib", "magneto_wrona", "mag-readings.txt")
    mapping = CsvMapping(mag=[0, 1, 2], mag_unit="uT", gyro=None, accel=None, rate_hz=10.0)
    table, _ = read_input(InputSpec(path=path, csv=mapping))
    stage = MagCalibrationStage(build_options(MagCalibrationStage.Options, options, "test"))
    out = stage.fit(table, StageContext(name="mag", input_name="wrona", quiet=True))
    return np.loadtxt(path), out


def test_wrona_against_magneto():
    """Magneto leaves 2.17 % on all 324 samples. The first 2.4 s (24 samples, the sensor still)
    lie off the ellipsoid of the tumbling (+6 % against -1 % for later samples in the same
    direction): thinning caps their weight like any over-sampled orientation, so the default
    fit leaves 2.21 % on all (no worse than Magneto + 0.05 pp) and 1.79 % on the tumbling samples,
    where Magneto leaves 1.94 %. Without thinning (every sample weighs alike, as in Magneto) it
    leaves 2.17 % on all, the geometric optimum of (|M (h - b)| - F)^2. With 0.1's 3-sigma
    rejection 7 of the still samples were dropped and the fit turned away from them: 2.29 % on
    all."""
    h, out = wrona_fit()
    magneto_all = std_pct((h - WRONA_B) @ WRONA_A.T)
    assert magneto_all == pytest.approx(2.17, abs=0.005)
    uT = 1e-6

    def ours(fitted, rows=slice(None)):
        return std_pct((h[rows] * uT - fitted.step.offset) @ fitted.step.matrix.T)

    tumbling = slice(WRONA_STILL, None)
    magneto_tumbling = std_pct((h[tumbling] - WRONA_B) @ WRONA_A.T)
    assert ours(out) <= magneto_all + 0.05
    assert ours(out, tumbling) <= magneto_tumbling - 0.1  # 1.79 % against 1.94 %
    _, unthinned = wrona_fit(thinning=False)
    assert ours(unthinned) <= magneto_all + 0.005
    assert ours(out) > ours(unthinned)  # thinning trades a little of the all-sample figure
    _, three_sigma = wrona_fit(outlier_k=3.0)
    assert three_sigma.results["metrics"]["outliers"] >= 5 and ours(three_sigma) > ours(out) + 0.05
    # the hard iron agrees with Magneto's within 1 % of the field
    assert np.linalg.norm(out.step.offset / uT - WRONA_B) < 0.01 * out.step.params["field"] / uT


def test_phidgets_bag_half_nan_refused_for_coverage_not_nan():
    """6,990 of the 13,964 MagneticField messages are NaN: left out with one counted warning;
    the rest (an IMU turning on a table) is refused for its coverage, with the figure."""
    table, _ = read_input(
        InputSpec(path=shared_path("logs", "madgwick_phidgets_imu_upside_down.bag"))
    )
    stage = MagCalibrationStage(MagCalibrationStage.Options())
    ctx = StageContext(name="mag_calibration", input_name="log", quiet=True)
    with pytest.raises(
        FitError, match=r"covers too few orientations: .* is 0\.019\d* < min_spread"
    ):
        stage.fit(table, ctx)
    assert ctx.warnings == ["6990 of 13964 magnetometer samples are NaN or Inf; fitted on 6974"]


def test_razor_bag_publishes_normalised_directions_refused():
    """imu_tools' SparkFun Razor bag publishes the field as directions of length 100 uT (|h| equal
    to 1e-14 %): no hard or soft iron can be fitted, and the stage says so instead of returning
    the identity as "ok"."""
    table, _ = read_input(InputSpec(path=shared_path("logs", "madgwick_sparkfun_razor.bag")))
    stage = MagCalibrationStage(MagCalibrationStage.Options())
    ctx = StageContext(name="mag_calibration", input_name="log", quiet=True)
    with pytest.raises(FitError, match=r"norm is constant: .* 100 uT .* normalised"):
        stage.fit(table, ctx)
