"""Every real multi-position session through ``imupipe run`` with default options, against the
answers published for it (or an independent re-implementation), and on held-out recordings.

- imu_tk's Xsens session (raw counts; tests/data): the re-implementation in the data's README.
- the RealSense T265 session (../shared only): imu_tk's published calibration, cggos/imu_tk @
  d07e762b3c0f1526418058694a84a1164ddded92, bin/test_data/t265_test_imu_acc.calib and
  t265_test_imu_gyro.calib (the same figures as its scripts/data/t265.log).
- the MPU-6050 session (tests/data, MIT): its authors' calibration (tomisuarez2/ImuCalibration,
  ImuCalibrationModules/imu_calibration.py @ 1bc11c96dc629f1f2816f4d236e67606254c88e1, the
  parameters quoted in calibrate_imu_from_data, which reproduce that repository's
  "optmization result data/calibrated_accel_avg_data.csv" and params_gyro.csv @
  1c30280f5537226b3644c6274f43ec1b30c13fb5), judged on three held-out recordings of the same sensor.
- imucal's Ferraris sessions: in tests/test_accel_calibration.py (snapshot and calibrated output).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from imupipe.pipeline.config import load_config
from imupipe.readers.dispatch import read_input
from imupipe.readers.table import sensor
from imupipe.stages.multiposition import accel_models as am
from imupipe.stages.multiposition import gyro_models as gm
from imupipe.stages.multiposition.accel_calibration import AccelCalibrationStage, detect_intervals
from imupipe.stages.static_detector import make_detector, sample_clock
from imupipe.stages.steps import apply_chain, steps_from_json
from imupipe.stages.stillness import stillness

from conftest import TEST_DATA, run_cli, shared_path

G = 9.80665
MG = 9.80665e-3


def run_default(tmp_path: Path, inputs: str, gravity: float = G) -> dict:
    """``imupipe run`` with accel_calibration then gyro_calibration, default options."""
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        inputs
        + f"""
[[stages]]
type = "accel_calibration"
gravity = {gravity}

[[stages]]
type = "gyro_calibration"
gravity = {gravity}

[output]
dir = "out"
rerun = false
apply_to = []
"""
    )
    done = run_cli("run", cfg, "--quiet")
    assert done.returncode == 0, done.stderr
    return json.loads((tmp_path / "out" / "calibration.json").read_text())


# -- imu_tk's Xsens session -------------------------------------------------------------------


def test_xsens(tmp_path):
    """Raw counts, no initial rest given: the 9-parameter model is chosen; the figures agree
    with (or beat) the independent re-implementation of imu_tk in the data's README (38
    intervals, 0.11 mg on means, 0.82 mg per sample; gyro 0.52 deg RMS, scale ~2.09e-4)."""
    data = TEST_DATA / "imu_tk_xsens"
    doc = run_default(
        tmp_path,
        f"""[inputs.xsens]
path = "{data / "xsens_acc.mat"}"
[inputs.xsens.csv]
time = 0
time_unit = "s"
accel = [1, 2, 3]
accel_unit = "raw"
gyro_file = "{data / "xsens_gyro.mat"}"
gyro = [1, 2, 3]
gyro_unit = "raw"
""",
        gravity=9.81744,
    )
    accel = doc["results"]["accel_calibration"]
    assert accel["model"]["chosen"] == "9-parameter"
    metrics = accel["metrics"]
    assert metrics["poses"] >= 38
    assert metrics["threshold"]["reference"].startswith("noise floor")
    assert metrics["residual_mg"]["means_rms"] <= 0.11
    assert metrics["residual_mg"]["samples_rms"] <= 0.83
    assert metrics["residual_mg"]["start_means_rms"] > 1.0  # the start alone is not the answer
    assert all(s > 0 for s in accel["standard_errors"]["misalignment_rad"])
    gyro = doc["results"]["gyro_calibration"]
    assert gyro["model"]["chosen"] == "9-parameter"
    assert gyro["metrics"]["gravity_direction_residual_deg"]["rms"] <= 0.52
    # imu_tk's nominal 1/6258 (rad/s)/count is 25 % off; the data says ~2.09e-4
    np.testing.assert_allclose(gyro["scale"], 2.09e-4, rtol=0.02)


# -- the T265 session -------------------------------------------------------------------------

T265_ACC_T = np.array([[1, 0.0194692, -0.0574956], [0, 1, -0.00366816], [0, 0, 1]])
T265_ACC_K = np.diag([1.00773, 1.01848, 1.01499])
T265_ACC_B = np.array([-0.19119, 0.57394, -0.231325])
T265_GYR_T = np.array(
    [[1, 0.0141865, -0.0365638], [-0.0195891, 1, -0.00691532], [0.0386539, 0.0134009, 1]]
)
T265_GYR_K = np.diag([1.00051, 0.999542, 0.99792])
T265_GYR_B = np.array([0.00335198, -0.00136361, -0.00353717])
"""imu_tk's published calibration of the T265 session: calibrated = T K (raw - b)."""


def test_t265(tmp_path):
    """The poses are the six faces: the 9-parameter model is not supported, so the 6-parameter
    model is chosen and said (main refused to fit); at least as many intervals as imu_tk's
    detector (41); scale and bias agree with imu_tk's published 9-parameter answer, and on the
    same pose means and motions both our accelerometer and our gyroscope calibration leave a
    smaller residual than that answer."""
    acc_file = shared_path("calib", "imu_tk_t265_cggos", "t265_acc.mat")
    doc = run_default(
        tmp_path,
        f"""[inputs.t265]
path = "{acc_file}"
[inputs.t265.csv]
time = 0
time_unit = "s"
accel = [1, 2, 3]
gyro_file = "{acc_file.with_name("t265_gyr.mat")}"
gyro = [1, 2, 3]
""",
        gravity=9.8016,
    )
    accel = doc["results"]["accel_calibration"]
    assert accel["model"]["chosen"] == "6-parameter"
    assert any(w.startswith("misalignment not fitted") for w in accel["warnings"])
    metrics = accel["metrics"]
    assert metrics["intervals"] >= 41
    assert metrics["residual_mg"]["means_rms"] < 0.6
    assert metrics["residual_mg"]["start_means_rms"] > 5.0
    np.testing.assert_allclose(accel["scale"], np.diag(T265_ACC_K), atol=2e-3)
    np.testing.assert_allclose(accel["bias"], T265_ACC_B, atol=5e-3)

    table = read_input(load_config(tmp_path / "cfg.toml").inputs["t265"])[0]
    acc, gyr = sensor(table, "accel"), sensor(table, "gyro")
    ours = apply_chain(table, steps_from_json(doc["chain"]))
    ours_acc, ours_gyr = sensor(ours, "accel").values, sensor(ours, "gyro").values
    published_acc = (acc.values - T265_ACC_B) @ (T265_ACC_T @ T265_ACC_K).T
    poses = detect_intervals(
        acc.t_ns, acc.values, AccelCalibrationStage.Options(), 9.8016, ["6-parameter"]
    ).poses

    def accel_rms_mg(values):
        norms = np.linalg.norm(poses.means(values), axis=1)
        return float(np.sqrt(np.mean(((norms - 9.8016) / MG) ** 2)))

    assert accel_rms_mg(ours_acc) < accel_rms_mg(published_acc) < 0.7
    t_s = sample_clock(acc.t_ns)[0]
    ours_moves = gm.PoseTransitions.build(t_s, ours_gyr, ours_acc, poses)
    published_moves = gm.PoseTransitions.build(t_s, gyr.values, published_acc, poses)
    ours_deg = ours_moves.angles_deg(np.eye(3), np.zeros(3))
    published_deg = published_moves.angles_deg(T265_GYR_T @ T265_GYR_K, T265_GYR_B)
    gyro = doc["results"]["gyro_calibration"]
    assert "quantised to 10 ms" in gyro["metrics"]["clock"]
    assert np.sqrt(np.mean(ours_deg**2)) < 1.1 < 1.5 < np.sqrt(np.mean(published_deg**2))


# -- the MPU-6050 session and its held-out recordings -------------------------------------------

MPU = TEST_DATA / "mpu6050_tomisuarez"
MPU_CSV = """[inputs.{name}]
path = "{path}"
[inputs.{name}.csv]
accel = ["ax", "ay", "az"]
accel_unit = "raw"
gyro = ["gx", "gy", "gz"]
gyro_unit = "raw"
"""
HELD_OUT = ("imu_static_test.csv", "example_data_tinit_calc.csv", "imu_90_x_rot.csv")
# the authors' calibration (raw counts): calibrated = T K (raw + b) for the accelerometer
# (misalignment yz, zy, zx; scale; bias) and T K (raw - b) for the gyroscope (misalignment yz, zy,
# xz, zx, xy, yx; scale; bias)
PUBLISHED_ACC = [1.043860522409845042e-05, 2.098452816658057195e-06, 2.005985606930172646e-06,
                 6.020083400010406817e-04, 5.968449488725015338e-04, 5.859241382355084718e-04,
                 -7.115163422327075295e+02, 3.585054836108664063e+02, 1.840128451085784491e+03]  # fmt: skip
PUBLISHED_GYRO = [-9.967394130262499652e-03, 9.183836411500549690e-03, -2.912198601931083493e-03,
                  7.234881652289322680e-03, -9.841957371310869340e-03, 5.795923574753897821e-03,
                  1.373743743438648286e-04, 1.329249743689399734e-04, 1.339443406342994032e-04,
                  -4.274617614746093750e+02, 1.479479370117187500e+02, -8.072266387939453125e+01]  # fmt: skip
NOMINAL_GYRO = np.radians(1.0) / 131.0
"""The datasheet's 131 LSB/(deg/s), in (rad/s)/LSB."""
AUTHORS_STARTS = [150, 4297, 4934, 5585, 6205, 7018, 7570, 8297, 9094, 9662]
AUTHORS_ENDS = [3613, 4299, 4946, 5690, 6368, 7046, 7765, 8457, 9158, 10095]
"""The authors' ten static intervals (sample indices, end exclusive): their
"optmization result data/static_intervals.csv" @ 1c30280f5537226b3644c6274f43ec1b30c13fb5."""


def published_accel(raw: np.ndarray) -> np.ndarray:
    m, s, b = np.split(np.asarray(PUBLISHED_ACC), [3, 6])
    t = np.array([[1, -m[0], m[1]], [0, 1, -m[2]], [0, 0, 1]])
    return (raw + b) @ (t @ np.diag(s)).T


def published_gyro_matrix() -> tuple[np.ndarray, np.ndarray]:
    m, s, b = np.split(np.asarray(PUBLISHED_GYRO), [6, 9])
    t = np.array([[1, -m[0], m[1]], [m[2], 1, -m[3]], [-m[4], m[5], 1]])
    return t @ np.diag(s), b


AUTHORS_INIT_S, AUTHORS_WAIT_S = 36.5, 3.0
"""The session file's header ``Initialization time,36.5`` and ``Waiting time,3``: the authors'
t_init (the initial rest whose variance is the threshold's reference) and t_wait (their variance
window), s."""


def authors_detection(raw: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The authors' static detector at threshold ``k`` (find_static_imu_intervals with the
    threshold of calibrate_accel_from_data, imu_calibration.py @ 1bc11c96): sample i (100 Hz) is
    static when the sum of the squared per-axis variances (ddof 0, counts^4) over the 300 samples
    [i - 150, i + 150) is below k times that of the first int(36.5 * 100) - 1 samples; every run of
    static samples is an interval, however short. Returns (starts, ends), ends exclusive."""
    n, half = len(raw), int(AUTHORS_WAIT_S * 100 / 2)
    x = raw - raw.mean(axis=0)  # the variances do not change; the running sums stay small
    c1 = np.vstack([np.zeros((1, 3)), np.cumsum(x, axis=0)])
    c2 = np.vstack([np.zeros((1, 3)), np.cumsum(x * x, axis=0)])
    centre = np.arange(half, n - half)
    s1, s2 = c1[centre + half] - c1[centre - half], c2[centre + half] - c2[centre - half]
    var = s2 / (2 * half) - (s1 / (2 * half)) ** 2
    reference = np.sum(np.var(raw[: int(AUTHORS_INIT_S * 100) - 1], axis=0) ** 2)
    static = np.zeros(n, dtype=np.int8)
    static[centre] = np.sum(var**2, axis=1) < k * reference
    edges = np.diff(static, prepend=0, append=0)
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def authors_accept(means: np.ndarray) -> bool:
    """The authors' test of a threshold's intervals: more than nine, and no two consecutive means
    within 1 % of each other on every axis."""
    if len(means) <= 9:
        return False
    close = np.abs(np.diff(means, axis=0)) / np.linalg.norm(means[1:], axis=1)[:, None] < 1e-2
    return not bool(np.any(np.all(close, axis=1)))


def authors_means(tmp_path: Path) -> np.ndarray:
    """(10, 3) raw means of the session over the authors' static intervals."""
    raw = sensor(read_mpu("example_data_calibration.csv", tmp_path), "accel").values
    pairs = zip(AUTHORS_STARTS, AUTHORS_ENDS, strict=True)
    return np.array([raw[a:b].mean(axis=0) for a, b in pairs])


def read_mpu(name: str, tmp_path: Path):
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(MPU_CSV.format(name="x", path=MPU / name))
    return read_input(load_config(cfg).inputs["x"])[0]


def held_out_blocks_mg(
    table, accel_values: np.ndarray, gyro_rad_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The 10 s block means (k, 3) of a held-out recording's calibrated accelerometer and their
    signed |a| - g (k,) mg, blocks in which the IMU moved left out (the shared motion check)."""
    t_ns = sensor(table, "accel").t_ns
    n = len(t_ns) // 1000 * 1000
    means = []
    for i in range(0, n, 1000):  # ten-second blocks (tens per file)
        block = slice(i, i + 1000)
        rate = gyro_rad_s[block] - gyro_rad_s[:1000].mean(axis=0)
        if stillness(t_ns[block], rate, accel_values[block]).static(0.02):
            means.append(accel_values[block].mean(axis=0))
    means_array = np.array(means)
    return means_array, (np.linalg.norm(means_array, axis=1) - G) / MG


def held_out_rms_mg(table, accel_values: np.ndarray, gyro_rad_s: np.ndarray) -> float:
    """| |a| - g | RMS (mg) over the still 10 s block means of a held-out recording."""
    residuals = held_out_blocks_mg(table, accel_values, gyro_rad_s)[1]
    return float(np.sqrt(np.mean(np.square(residuals))))


def rotation_error_deg(table, accel_values: np.ndarray, matrix: np.ndarray) -> float:
    """imu_90_x_rot: at rest (0-13 s), a turn of about 90 deg about x, at rest (25 s - end). The
    gravity direction measured before, carried by the calibrated gyro (bias: the file's own first
    rest, as a user's gyro_bias would take it) to the second rest, against the one measured
    there: the angle between them, deg."""
    acc, gyr = sensor(table, "accel"), sensor(table, "gyro")
    first, second = acc.t_s <= 13.0, acc.t_s >= 25.0
    u = [accel_values[m].mean(axis=0) for m in (first, second)]
    u = [v / np.linalg.norm(v) for v in u]
    start, stop = np.flatnonzero(first)[-1], np.flatnonzero(second)[0]
    bias = gyr.values[first].mean(axis=0)
    w = (gyr.values[start : stop + 1] - bias) @ matrix.T
    phi = 0.5 * (w[1:] + w[:-1]) * np.diff(acc.t_s[start : stop + 1])[:, None]
    q = gm.compose(gm.rotvec_to_quat(phi[None]))
    predicted = gm.rotate_inverse(q, u[0][None])[0]
    return float(np.degrees(np.arccos(np.clip(predicted @ u[1], -1.0, 1.0))))


@pytest.fixture(scope="module")
def mpu(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("mpu")
    doc = run_default(
        tmp_path, MPU_CSV.format(name="session", path=MPU / "example_data_calibration.csv")
    )
    return doc, steps_from_json(doc["chain"]), tmp_path


def test_mpu6050_model_choice(mpu):
    """Ten hand-held poses: the 9-parameter accelerometer model (1 degree of freedom) and the
    six gyro angles are not supported; both choices are stated with their standard errors
    (main fitted a 5.6 deg accelerometer misalignment from one degree of freedom)."""
    doc, _, _ = mpu
    accel, gyro = doc["results"]["accel_calibration"], doc["results"]["gyro_calibration"]
    assert accel["metrics"]["poses"] == 10
    assert accel["model"]["chosen"] == "6-parameter"
    assert accel["model"]["candidates"]["9-parameter"]["aicc"] is None  # n - K - 1 < 1
    assert gyro["model"]["chosen"] == "scale-only"
    assert any(w.startswith("gyro misalignment not fitted") for w in gyro["warnings"])
    assert all(
        se > 0 for se in accel["standard_errors"]["scale"] + gyro["standard_errors"]["scale"]
    )


def test_mpu6050_published_figures_reproduce(tmp_path):
    """The authors' parameters reproduce their own calibrated pose means, and give the held-out
    figures we compare against (mean 1.03 mg; rotation 1.52 deg; nominal 131 LSB/(deg/s) with the
    same accelerometer calibration: 1.67 deg)."""
    means = authors_means(tmp_path)
    # their calibrated_accel_avg_data.csv @ 1c30280, first and last rows
    np.testing.assert_allclose(
        published_accel(means)[[0, -1]],
        [[-0.5253836034, -0.2664464290, 9.7867752986], [4.7615917210, 0.0223525863, 8.5792817779]],
        atol=1e-6,
    )
    figures = []
    for name in HELD_OUT:
        table = read_mpu(name, tmp_path)
        gyro = sensor(table, "gyro").values * NOMINAL_GYRO
        figures.append(held_out_rms_mg(table, published_accel(sensor(table, "accel").values), gyro))
    np.testing.assert_allclose(figures, [1.385, 0.911, 0.782], atol=2e-3)
    table = read_mpu("imu_90_x_rot.csv", tmp_path)
    acc = published_accel(sensor(table, "accel").values)
    assert rotation_error_deg(table, acc, published_gyro_matrix()[0]) == pytest.approx(
        1.52, abs=0.01
    )
    assert rotation_error_deg(table, acc, NOMINAL_GYRO * np.eye(3)) == pytest.approx(1.67, abs=0.01)


def test_mpu6050_published_is_the_six_parameter_model_on_its_intervals(tmp_path):
    """The authors' code fits nine parameters, but their published answer is the 6-parameter
    model fitted on their ten interval means (equal weights, g = 9.80665, the g of the held-out
    figure): our 6-parameter fit on those means gives their parameters and their held-out figures.
    The 9-parameter optimum on the same means has a 0.12 rad angle (one degree of freedom) and a
    cost 270 times lower: not what they published. So the method is ours; the held-out gap comes
    from which samples make the pose means (their intervals hold 2 to 3463 samples, ours 101 to
    3661)."""
    means = authors_means(tmp_path)
    six = am.fit_model(means, G, "6-parameter")
    angles, scale, bias = np.split(np.asarray(PUBLISHED_ACC), [3, 6])
    assert np.abs(angles).max() < 2e-5
    np.testing.assert_allclose(six.params.scale, scale, rtol=1e-5)
    np.testing.assert_allclose(six.params.bias, -bias, atol=0.02)  # counts (1 count = 0.06 mg)
    nine = am.fit_model(means, G, "9-parameter")
    assert abs(nine.params.angles[0]) > 0.1
    published_rss = np.sum(((np.linalg.norm(published_accel(means), axis=1) - G) / G) ** 2)
    assert nine.rss * 200 < published_rss < six.rss * 1.01
    figures = []
    for name in HELD_OUT:
        table = read_mpu(name, tmp_path)
        gyro = sensor(table, "gyro").values * NOMINAL_GYRO
        figures.append(
            held_out_rms_mg(table, six.params.apply(sensor(table, "accel").values), gyro)
        )
    np.testing.assert_allclose(figures, [1.385, 0.911, 0.782], atol=2e-3)


def test_mpu6050_held_out_gap_is_a_power_up_shift(mpu):
    """What the held-out figure measures. 54 of its 60 still blocks hold the IMU z up; on every
    one of them both calibrations read at least 0.5 mg above what the same calibration reads on
    the session's own z-up rest (-0.2 mg, flat over its 36 s): a z-axis zero-g shift between
    power-ups (the datasheet allows +-60 mg over 0-70 degC on z), which no calibration of the
    session can see. On the 6 blocks a z shift cannot touch (y up, after the turn) the two
    calibrations tie (0.195 mg RMS each). A calibration reading lower everywhere gains on this
    figure: the authors' reads 0.10-0.23 mg below ours, within our standard error there (0.46-0.64
    mg)."""
    doc, chain, tmp_path = mpu
    session = read_mpu("example_data_calibration.csv", tmp_path)
    raw_rest = sensor(session, "accel").values[50:3600]  # the initial rest, z up
    ours_acc = sensor(apply_chain(session, chain[:1]), "accel").values[50:3600]
    rest = {
        "ours": (np.linalg.norm(ours_acc.mean(axis=0)) - G) / MG,
        "authors'": (np.linalg.norm(published_accel(raw_rest).mean(axis=0)) - G) / MG,
    }
    z_up: dict[str, list] = {"ours": [], "authors'": []}
    y_up: dict[str, list] = {"ours": [], "authors'": []}
    for name in HELD_OUT:
        table = read_mpu(name, tmp_path)
        corrected = apply_chain(table, chain)
        gyro = sensor(corrected, "gyro").values
        calibrated = {
            "ours": sensor(corrected, "accel").values,
            "authors'": published_accel(sensor(table, "accel").values),
        }
        for label, acc in calibrated.items():
            means, residual = held_out_blocks_mg(table, acc, gyro)
            up = np.abs(means[:, 2]) > np.abs(means[:, 1])
            z_up[label].extend(residual[up])
            y_up[label].extend(residual[~up])
    for label in ("ours", "authors'"):
        assert -0.5 < rest[label] < 0.0
        assert len(z_up[label]) == 54 and len(y_up[label]) == 6
        assert min(z_up[label]) > rest[label] + 0.5
    rms = {label: float(np.sqrt(np.mean(np.square(v)))) for label, v in y_up.items()}
    assert max(rms.values()) < 0.25
    assert abs(rms["ours"] - rms["authors'"]) < 0.02


def test_mpu6050_published_figure_is_the_best_of_its_own_thresholds(mpu):
    """Where the authors' intervals come from, and how much of their figure is the threshold's.
    Their detector (a 3 s window: the header's waiting time; reference: the first 36.5 s, the
    header's initialization time; k x the sum of squared variances, every run kept) gives their
    ten intervals at k = 13, the first k its test accepts (their rule keeps the lowest cost of
    their LM fit; rerun, it is k = 13 of the 53 thresholds it evaluates, 13 to 70). The
    6-parameter fit on the intervals of the next accepted thresholds scores 1.04 to 1.28 mg: 1.026
    is the luck of one threshold (over all 53: 1.026 to 1.277, median 1.129), and ours lies
    inside that spread. Honouring the declared initialization time would not reproduce their
    intervals: its variance is 1.1 times our noise floor, and their intervals of 2 to 64 samples
    are shorter than min_interval_s (a 2-sample mean carries 2.6 mg of noise, 5 times the
    residual of the fit)."""
    doc, chain, tmp_path = mpu
    session = sensor(read_mpu("example_data_calibration.csv", tmp_path), "accel")
    raw = session.values
    held_out = []
    for name in HELD_OUT:
        table = read_mpu(name, tmp_path)
        acc = sensor(table, "accel").values
        held_out.append((table, acc, sensor(table, "gyro").values * NOMINAL_GYRO))

    def figure(apply) -> float:
        return float(np.mean([held_out_rms_mg(t, apply(a), g) for t, a, g in held_out]))

    figures = {}
    for k in range(2, 25):
        starts, ends = authors_detection(raw, k)
        means = np.array([raw[a:b].mean(axis=0) for a, b in zip(starts, ends, strict=True)])
        if not authors_accept(means):
            continue
        if not figures:
            assert k == 13
            assert starts.tolist() == AUTHORS_STARTS and ends.tolist() == AUTHORS_ENDS
        figures[k] = figure(am.fit_model(means, G, "6-parameter").params.apply)
    assert figures[13] == pytest.approx(1.026, abs=2e-3)
    others = [v for k, v in figures.items() if k != 13]
    assert len(others) >= 8
    ours = figure(chain[0].apply_values)
    assert 1.04 < min(others) < ours < 1.25 < max(others)
    floor = make_detector(session.t_ns, raw).reference
    declared = make_detector(session.t_ns, raw, init_static_s=AUTHORS_INIT_S).reference
    assert 1.0 < declared / floor < 1.2


def test_mpu6050_held_out(mpu):
    """Accelerometer: mean held-out | |a| - g | RMS 1.12 mg (main 1.43; the authors' 1.03). The
    figure is dominated by a z-axis shift of the later power-ups (+0.6 to +2.1 mg on z-up blocks,
    test above) that rewards a calibration reading low; ours reads 0.1 mg above the authors' there,
    less than its own predicted error (0.56 mg), and ties with it where the shift does not act.
    Gyroscope: the held-out ~90 deg turn is predicted within 1.35 deg: better than the authors'
    calibration (1.52 deg) and than the datasheet's nominal scale (1.68 deg with this accelerometer
    calibration; main 2.16 deg)."""
    doc, chain, tmp_path = mpu
    figures = []
    for name in HELD_OUT:
        corrected = apply_chain(read_mpu(name, tmp_path), chain)
        acc, gyr = sensor(corrected, "accel").values, sensor(corrected, "gyro").values
        figures.append(held_out_rms_mg(corrected, acc, gyr))
    assert np.mean(figures) < 1.13
    assert doc["results"]["accel_calibration"]["metrics"]["predicted_error_mg"] > abs(
        np.mean(figures) - 1.026
    )
    table = read_mpu("imu_90_x_rot.csv", tmp_path)
    acc = sensor(apply_chain(table, chain[:1]), "accel").values
    gyro_matrix = np.asarray(doc["chain"][1]["matrix"])
    ours = rotation_error_deg(table, acc, gyro_matrix)
    nominal = rotation_error_deg(table, acc, NOMINAL_GYRO * np.eye(3))
    assert ours < 1.4 < 1.52 < nominal


# -- imucal's sessions with the default (static-pose) methods -----------------------------------


def test_imucal_sessions_with_default_options(tmp_path):
    """imucal's annotated session holds only its six labelled faces (and three turns): the
    default fit calibrates them with the 6-parameter model (exact: nothing checks it, which a
    warning says), as six_position does. Its continuous example session
    (../shared) calibrates with the static-pose methods: the 6-parameter model, and the three
    gyro scales, each chosen and said; the calibrated |a| at imucal's six static regions is within
    1 mg of g."""
    annotated = TEST_DATA / "imucal" / "annotated_session.csv"
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        f"""[inputs.s]
path = "{annotated}"
[inputs.s.csv]
rate_hz = 204.8
accel = ["acc_x", "acc_y", "acc_z"]
accel_unit = "raw"
gyro = ["gyr_x", "gyr_y", "gyr_z"]
gyro_unit = "raw"
[[stages]]
type = "accel_calibration"
gravity = 9.81
[output]
dir = "out"
"""
    )
    done = run_cli("run", cfg, "--quiet")
    assert done.returncode == 0, done.stderr
    default = json.loads((tmp_path / "out" / "calibration.json").read_text())
    fitted = default["results"]["accel_calibration"]
    assert fitted["model"]["chosen"] == "6-parameter"
    assert any("the six faces determine scale and bias exactly" in w for w in fitted["warnings"])
    cfg.write_text(
        cfg.read_text().replace("gravity = 9.81", 'gravity = 9.81\nmethod = "six_position"')
    )
    done = run_cli("run", cfg, "--quiet")
    assert done.returncode == 0, done.stderr
    six = json.loads((tmp_path / "out" / "calibration.json").read_text())
    # the 6-parameter fit of the six faces is the six-position answer (to second order in the
    # faces' tilt)
    np.testing.assert_allclose(
        fitted["scale"], six["results"]["accel_calibration"]["scale"], rtol=2e-3
    )
    assert six["results"]["accel_calibration"]["metrics"]["residual_mg"]["means_rms"] < 0.5

    folder = shared_path("calib", "imucal_ferraris")
    out = tmp_path / "example"
    out.mkdir()
    doc = run_default(
        out,
        f"""[inputs.s]
path = "{folder / "example_ferraris_session.csv"}"
[inputs.s.csv]
rate_hz = 102.4
accel = ["acc_x", "acc_y", "acc_z"]
gyro = ["gyr_x", "gyr_y", "gyr_z"]
gyro_unit = "deg/s"
""",
        gravity=9.81,
    )
    accel, gyro = doc["results"]["accel_calibration"], doc["results"]["gyro_calibration"]
    assert accel["model"]["chosen"] == "6-parameter"
    assert gyro["model"]["chosen"] == "scale-only"
    assert gyro["metrics"]["gravity_direction_residual_deg"]["rms"] < 1.1
    regions = json.loads((folder / "example_ferraris_session_list.json").read_text())
    table = read_input(load_config(out / "cfg.toml").inputs["s"])[0]
    corrected = sensor(apply_chain(table, steps_from_json(doc["chain"])), "accel").values
    for part in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a"):
        r = regions[part]
        norm = np.linalg.norm(corrected[r["start"] : r["end"]].mean(axis=0))
        assert abs(norm - 9.81) / MG < 1.0, part


# -- GetOverMassif/imu_tk's short-hold session (../shared) -----------------------------------

IMU_TK_DATA1 = {  # GetOverMassif/imu_tk @ 92022128, data/data1/test_imu_acc.calib (imu_tk)
    "scale": [1.00069, 1.00011, 1.00229],
    "bias": [-0.00837744, -0.0227623, -0.121363],
}


def test_short_holds_session_calibrates_as_imu_tk_does():
    """Issue 25: a hand session at 100 Hz whose holds last 1 to 1.5 s was refused ('too few
    static poses: ... 3 intervals' at every k): a 1 s window leaves no 1 s run of quiet window
    centres in such a hold. With every sample of a quiet window static it calibrates, within
    0.1 % (scale) and 20 mg (bias) of imu_tk's published calibration of the same session."""
    folder = shared_path("calib", "imutk_ros2_getovermassif", "data1")
    acc = np.loadtxt(folder / "acc_data.txt")
    gyro = np.loadtxt(folder / "gyro_data.txt")
    from imupipe.readers.table import make_table
    from imupipe.stages.base import StageContext

    table = make_table(
        (acc[:, 0] * 1e9).astype(np.int64), gyro=gyro[:, 1:], accel=acc[:, 1:], metadata={}
    )
    ctx = StageContext(name="accel", input_name="data1", quiet=True)
    out = AccelCalibrationStage(AccelCalibrationStage.Options()).fit(table, ctx)
    metrics = out.results["metrics"]
    assert metrics["threshold"]["whole_windows"] is True
    assert metrics["poses"] >= 20
    np.testing.assert_allclose(out.results["scale"], IMU_TK_DATA1["scale"], atol=1e-3)
    np.testing.assert_allclose(out.results["bias"], IMU_TK_DATA1["bias"], atol=0.02 * G / 9.8)
    # 'before calibration' is the raw pose means' | |a| - g |, not the data-derived start's
    raw = metrics["residual_mg"]["raw_means_rms"]
    assert raw > 5.0 and raw > 2 * metrics["residual_mg"]["start_means_rms"]
