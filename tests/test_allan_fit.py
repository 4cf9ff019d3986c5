"""Issue 4: the five-term fit against known truths and peer tools.

- units: white noise of discrete std 0.01 at 400 Hz is N = 0.01 / sqrt(400) = 5e-4;
- recovery on simulated Kalibr-model data (white + random walk, 400 Hz, 3 h) and, slow-marked,
  the 8-seed study;
- the allan_variance_ros simulated IMU (truth known, BSD, tests/data): better than that tool;
- imu_utils's own fits of 6 real IMUs' curves (MIT, ../shared): same curve values;
- each simulated noise process (flicker, quantisation, ramp) comes back as its own term.
- the random walk K under a bias instability: its single-run scatter against the Cramer-Rao
  bound (every term unknown, exact Gaussian likelihood) with and without B, and, slow-marked,
  against the maximum-likelihood estimate on the same runs.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy.linalg import cho_factor, cho_solve, toeplitz
from scipy.optimize import minimize

from imupipe.pipeline.simulate import noise, simulate
from imupipe.readers.table import sensor
from imupipe.stages.allan import estimators as est
from imupipe.stages.allan.fit import B_FLOOR, TERMS, fit_allan, slope_readings

from conftest import TEST_DATA, shared_path

ROS_SIM = TEST_DATA / "allan" / "allan_variance_ros_sim"


def curves(columns, rate_hz, grid="log", kind="oadev"):
    """(deviation, confidence) of rate columns, as the stage computes them."""
    x = est.rate_to_phase(columns, 1.0 / rate_hz)
    m = est.tau_grid(grid, est.max_af(kind, x.shape[1]), 10)
    dev = est.deviation_of_phase(x, 1.0 / rate_hz, kind, m)
    return dev, est.confidence(dev, x)


def fit_all(dev, conf, **kw):
    return [
        fit_allan(dev.taus, dev.dev[:, i], conf.edf[:, i], **kw) for i in range(dev.dev.shape[1])
    ]


def test_units_white_noise_density():
    rng = np.random.default_rng(7)
    y = rng.standard_normal((400 * 600, 6)) * 0.01  # 10 min at 400 Hz, discrete std 0.01
    dev, conf = curves(y, 400.0)
    fits = fit_all(dev, conf)
    for f in fits:
        assert f.params["N"] == pytest.approx(5.0e-4, rel=0.03)
        assert [t for t in TERMS if f.params[t] > 0 and t != "K"] == ["N"]  # nothing else
    # K is always fitted (Kalibr needs one) but white noise does not resolve it: its 68 %
    # interval reaches zero on most axes (a 68 % interval misses one time in three), and it
    # stays below a few times the K whose line meets the white noise at the longest tau
    k_meets_n = 5.0e-4 * np.sqrt(3.0) / dev.taus[-1]
    assert sum(f.ranges["K"][0] == 0.0 for f in fits) >= 4
    assert all(f.params["K"] <= f.ranges["K"][1] < 4 * k_meets_n for f in fits)
    reading = slope_readings(dev.taus, dev.dev[:, 0])
    assert reading["N"] == pytest.approx(5.0e-4, rel=0.03)


KALIBR_TRUTH = {  # allan_variance_ros's simulator (ori-drs imu_simulator.yaml)
    "gyro_N": [1.888339269965301e-4] * 3,
    "gyro_K": [2.5565313322052523e-6] * 3,
    "accel_N": [2.5019929573561175e-3] * 3,
    "accel_K": [6.972435158192731e-5] * 3,
}


def kalibr_run(seed: int, hours: float = 3.0):
    params = {"rate_hz": 400.0, "duration_s": hours * 3600.0, "temperature": None, **KALIBR_TRUTH}
    table, truth = simulate("static", params, seed=seed)
    columns = [sensor(table, s).values[:, i] for s in ("gyro", "accel") for i in range(3)]
    del table
    dev, conf = curves(columns, 400.0)
    fits = fit_all(dev, conf)
    n_true = np.array(truth["gyro"]["N"] + truth["accel"]["N"])
    k_true = np.array(truth["gyro"]["K"] + truth["accel"]["K"])
    n = np.array([f.params["N"] for f in fits])
    k = np.array([f.params["K"] for f in fits])
    return n / n_true - 1, k / k_true - 1, fits


def test_recovery_kalibr_model_3h():
    """One 3 h run (seed 0): N within 3 % and K within 35 % on every axis. (K from one 3 h run
    scatters by about 13 % (1 sigma); see the slow 8-seed study for the mean.)"""
    n_err, k_err, fits = kalibr_run(seed=0)
    assert np.abs(n_err).max() < 0.03, n_err
    assert np.abs(k_err).max() < 0.35, k_err
    for f in fits:  # the terms the simulation does not have are left out
        assert f.params["Q"] == f.params["B"] == f.params["R"] == 0.0


@pytest.mark.slow
def test_recovery_kalibr_model_8_runs():
    """The issue's study: 8 seeds x 3 h; the mean over seeds (and the three axes of a sensor,
    the value Kalibr takes) of the N error within 2 % and of the K error within 10 %. Per axis,
    an 8-run mean of K still scatters by about 5 % (1 sigma): printed, not asserted."""
    n_errs, k_errs = [], []
    for seed in range(8):
        n_err, k_err, _ = kalibr_run(seed)
        n_errs.append(n_err)
        k_errs.append(k_err)
        print(f"seed {seed}: N {np.round(n_err, 4)} K {np.round(k_err, 3)}")
    n_errs, k_errs = np.array(n_errs), np.array(k_errs)
    print("per-axis mean N error", np.round(n_errs.mean(axis=0), 4))
    print("per-axis mean K error", np.round(k_errs.mean(axis=0), 3))
    print("K std over runs", np.round(k_errs.std(axis=0, ddof=1), 3))
    print("K within 35 %:", int((np.abs(k_errs) < 0.35).sum()), "of", k_errs.size)
    for cols in (slice(0, 3), slice(3, 6)):  # gyro, accel
        print("sensor mean N, K error", n_errs[:, cols].mean(), k_errs[:, cols].mean())
        assert abs(n_errs[:, cols].mean()) < 0.02
        assert abs(k_errs[:, cols].mean()) < 0.10
    assert np.abs(n_errs.mean(axis=0)).max() < 0.02


def test_allan_variance_ros_simulated_truth():
    """Fit the curve allan_variance_ros computed on its simulated IMU; report like Kalibr (the
    largest axis) and beat that tool's own errors (+2.4 % / +30 % accel, +1.1 % / +61 % gyro)."""
    rows = np.loadtxt(ROS_SIM / "allan_variance_log20.csv")
    taus, dev = rows[:, 0], rows[:, 1:].copy()
    dev[:, 3:] *= np.pi / 180.0  # gyro columns are deg/s
    truth = yaml.safe_load((ROS_SIM / "imu_simulator_config_truth.yaml").read_text())
    tool = yaml.safe_load((ROS_SIM / "expected_imu.yaml").read_text())
    m = np.round(taus * 400.0).astype(np.int64)
    alpha = est.alpha_from_slope(taus, dev)
    edf = est.edf_of_curve("adev", m, alpha, int(11000 * 400) + 1)  # non-overlapping bins
    fits = [fit_allan(taus, dev[:, i], edf[:, i]) for i in range(6)]
    for sensor_cols, prefix in (((0, 1, 2), "accelerometer"), ((3, 4, 5), "gyroscope")):
        for term, key in (("N", "noise_density"), ("K", "random_walk")):
            true = truth[f"{prefix}_{key}"]
            ours = max(fits[i].params[term] for i in sensor_cols)
            theirs = tool[f"{prefix}_{key}"]
            assert abs(ours / true - 1) < abs(theirs / true - 1), (prefix, key, ours, theirs)
            for i in sensor_cols:  # and every axis within the single-run tolerances
                err = fits[i].params[term] / true - 1
                assert abs(err) < (0.03 if term == "N" else 0.35), (prefix, key, i, err)


def _imu_utils_yaml(path):
    return yaml.safe_load(path.read_text().replace("%YAML:1.0", ""))


@pytest.mark.parametrize("device", ["A3", "N3", "16448", "gx4", "xsens", "BMI160"])
def test_imu_utils_real_curves(device):
    """Same measured curves, same conventions (imu_utils: gyr_n = fitted ADEV at 1 s, gyr_w =
    minimum of the fitted ADEV; BMI160's yaml is x sqrt(fs)): our fitted curve agrees with
    imu_utils's at those two points within 15 % / 20 % on all 6 curves of each of 6 real IMUs."""
    params = _imu_utils_yaml(shared_path("allan", "imu_utils_curves", f"{device}_imu_param.yaml"))
    for short, section, scale in (("gyr", "Gyr", np.pi / 180 / 3600), ("acc", "Acc", 1.0)):
        taus = np.loadtxt(shared_path("allan", "imu_utils_curves", f"data_{device}_{short}_t.txt"))
        fs = 1.0 / taus[0]
        m = np.round(taus * fs).astype(np.int64)
        for axis in "xyz":
            name = f"data_{device}_{short}_{axis}.txt"
            dev = np.loadtxt(shared_path("allan", "imu_utils_curves", name)) * scale
            edf = est.edf_of_curve("oadev", m, est.alpha_from_slope(taus, dev), 2 * int(m[-1]) + 1)
            fit = fit_allan(taus, dev, edf[:, 0])
            ref = params[section][f"{axis}-axis"]
            at_1s = ref[f"{short}_n"] / (np.sqrt(fs) if device == "BMI160" else 1.0)
            dense = np.logspace(np.log10(taus[0]), np.log10(taus[-1]), 400)
            assert fit.deviation(np.array([1.0]))[0] == pytest.approx(at_1s, rel=0.15), name
            assert fit.deviation(dense).min() == pytest.approx(ref[f"{short}_w"], rel=0.20), name
            assert fit.rms_log10 < 0.25, name


def test_each_simulated_process_is_its_own_term():
    """noise.py's processes have the IEEE 952 Allan variances of the terms they stand for."""
    rng = np.random.default_rng(11)
    fs, n = 100.0, 100 * 3600
    b, q, r, white = 5e-5, 2e-5, 2e-7, 1e-4
    columns = [
        noise.flicker(rng, n, b, fs),
        noise.quantization(rng, n, q, fs) + noise.white(rng, n, white, fs),
        noise.rate_ramp(n, r, fs) + noise.white(rng, n, white, fs),
    ]
    dev, conf = curves(columns, fs)
    plateau = dev.dev[(dev.taus >= 0.1) & (dev.taus <= 30), 0] / (b * B_FLOOR)
    assert np.abs(plateau - 1).max() < 0.1  # flat at 0.664 B where the EDF is large
    flick, quant, ramp = fit_all(dev, conf)
    assert flick.params["B"] == pytest.approx(b, rel=0.1)
    assert quant.params["Q"] == pytest.approx(q, rel=0.1)
    assert quant.params["N"] == pytest.approx(white, rel=0.05)
    assert ramp.params["R"] == pytest.approx(r, rel=0.1)
    assert ramp.params["N"] == pytest.approx(white, rel=0.05)


K_TRUE, N_TRUE, B_TRUE = 2.0e-6, 1.7e-4, 5.0e-5
"""The random-walk study's gyro: white N (rad/s/sqrt(Hz)), random walk K (rad/s^2/sqrt(Hz)),
bias instability B (rad/s); 2 h at 20 Hz."""


def k_study_data(b: float, seed: int, hours: float = 2.0, rate_hz: float = 20.0) -> np.ndarray:
    """The three gyro columns (n, 3) of one simulated static run with N_TRUE, K_TRUE and bias
    instability ``b`` (simulated as a sum of Gauss-Markov processes, not the model's own form)."""
    params = {
        "rate_hz": rate_hz,
        "duration_s": hours * 3600.0,
        "temperature": None,
        "gyro_N": [N_TRUE] * 3,
        "gyro_B": [b] * 3,
        "gyro_K": [K_TRUE] * 3,
    }
    table, _ = simulate("static", params, seed=seed)
    return sensor(table, "gyro").values


def k_study(b: float, seeds: range, hours: float = 2.0, rate_hz: float = 20.0):
    """K/K_true - 1, whether the 68 % profile interval covers K_true, the fits and the gyro
    data, over ``seeds`` x 3 axes of :func:`k_study_data`."""
    errors, covered, fits, data = [], [], [], []
    for seed in seeds:
        y = k_study_data(b, seed, hours, rate_hz)
        dev, conf = est.curve(est.rate_to_phase(list(y.T), 1.0 / rate_hz), 1.0 / rate_hz)
        for i, f in enumerate(fit_all(dev, conf)):
            errors.append(f.params["K"] / K_TRUE - 1.0)
            low, high = f.ranges["K"]
            covered.append(low <= K_TRUE <= high)
            fits.append(f)
            data.append(y[:, i])
    return np.array(errors), np.array(covered), fits, data


def block_model(n: int, rate_hz: float, with_b: bool, block_s: float = 10.0) -> list[np.ndarray]:
    """Exact covariance matrices, per unit N^2, (B^2 when ``with_b``) and K^2, of the first
    differences of ``block_s`` block means of ``n`` samples of the simulator's gyro noise
    (:mod:`imupipe.pipeline.simulate.noise`): white rate noise of variance N^2 fs per sample,
    the sum of first-order Gauss-Markov processes standing for B (AR(1) block means in closed
    form), and a random walk with steps of variance K^2 / fs (its steps enter a difference of
    two neighbouring block means with triangular weights). The differences are stationary, so
    the covariance is Toeplitz; it is linear in (N^2, B^2, K^2). Block means of 10 s keep K's
    information (the random walk dominates only below a few mHz)."""
    fs, m = rate_hz, int(round(block_s * rate_hz))
    nb = n // m

    def of_differences(g: np.ndarray) -> np.ndarray:  # block means' autocovariance, lags 0..nb-1
        g = np.concatenate([g[1:2], g])  # g[-1] = g[1]
        return toeplitz(2.0 * g[1:-1] - g[2:] - g[:-2])

    white = np.zeros(nb)
    white[0] = fs / m
    mats = [of_differences(white)]
    if with_b:
        ratio = 10 ** (1 / 3)  # noise.flicker's defaults: times 1/fs .. n/fs, 3 per decade
        tc_min, tc_max = 1.0 / fs, max(n / fs, ratio / fs)
        count = int(np.ceil(np.log(tc_max / tc_min) / np.log(ratio))) + 1
        g, lag = np.zeros(nb), np.arange(1, nb)
        for tc in tc_min * ratio ** np.arange(count):  # a = exp(-1 / (fs tc)), variance 1
            one_a, one_am = -np.expm1(-1.0 / (fs * tc)), -np.expm1(-m / (fs * tc))
            a = 1.0 - one_a
            g[0] += m * (1.0 + a) / one_a - 2.0 * a * one_am / one_a**2
            g[1:] += np.exp(-((lag - 1) * m + 1) / (fs * tc)) * (one_am / one_a) ** 2
        mats.append(of_differences(g * np.log(ratio) / np.pi / m**2))
    u = np.arange(1, 2 * m)
    w = np.minimum(u, 2 * m - u) / m
    walk = np.zeros(nb - 1)
    walk[0], walk[1] = w @ w / fs, w[m:] @ w[:-m] / fs
    mats.append(toeplitz(walk))
    return mats


def k_bound(n: int, rate_hz: float, n_density: float, b: float, k: float) -> float:
    """Cramer-Rao bound on the relative standard deviation of K (rad/s^2/sqrt(Hz)) from one
    recording of ``n`` samples at ``rate_hz`` of white noise ``n_density``, bias instability
    ``b`` (absent when 0) and random walk ``k``, every term unknown: the scatter of an efficient
    estimator (maximum likelihood) on the exact Gaussian model of :func:`block_model`. Fisher
    information ``I_ij = tr(S^-1 A_i S^-1 A_j) / 2`` for ``S = sum theta_i A_i``; the bound on
    K^2 is ``(I^-1)_KK``, on K/K half its relative value."""
    mats = block_model(n, rate_hz, b > 0)
    theta = [n_density**2] + ([b * b] if b > 0 else []) + [k * k]
    chol = cho_factor(sum(t * a for t, a in zip(theta, mats, strict=True)))
    x = [cho_solve(chol, a) for a in mats]
    fisher = 0.5 * np.array([[np.sum(p * q.T) for q in x] for p in x])
    return float(np.sqrt(np.linalg.inv(fisher)[-1, -1]) / (2.0 * k * k))


def k_max_likelihood(y: np.ndarray, rate_hz: float, mats: list[np.ndarray], start) -> float:
    """The exact Gaussian maximum-likelihood K of one gyro column ``y`` on the model
    :func:`block_model` (``mats``), every term free (Nelder-Mead on the log of the variance
    parameters from ``start``, each held above ``start`` e^-25): the efficient estimator the
    Allan fit is compared with."""
    m = int(round(10.0 * rate_hz))
    nb = len(y) // m
    d = np.diff(y[: nb * m].reshape(nb, m).mean(axis=1))
    floor = np.log(np.asarray(start, dtype=np.float64)) - 25.0

    def nll(p: np.ndarray) -> float:
        theta = np.exp(np.maximum(p, floor))
        try:
            chol = cho_factor(sum(t * a for t, a in zip(theta, mats, strict=True)))
        except np.linalg.LinAlgError:
            return np.inf
        return float(np.sum(np.log(np.diag(chol[0]))) + 0.5 * d @ cho_solve(chol, d))

    opts = {"xatol": 1e-4, "fatol": 1e-6, "maxiter": 2000}
    res = minimize(nll, np.log(start), method="Nelder-Mead", options=opts)
    return float(np.sqrt(np.exp(max(res.x[-1], floor[-1]))))


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


STUDY_N = int(2 * 3600 * 20)
"""Samples of the study's 2 h at 20 Hz."""


def test_random_walk_kept_under_bias_instability():
    """2 h, B = 5e-5 and K = 2e-6 (gyro), 8 seeds x 3 axes, with and without B. Left to the
    information criterion, B absorbed the first rise of the random walk and K came out zero on
    every axis. K is now always fitted; "the same tolerance with B as without" is judged
    against what the data allow: the Cramer-Rao bound of K from one run (every term unknown,
    :func:`k_bound`) is 46 % with this B and 16 % without (a 2 h run holds about 8 times less
    information on K when B is present: the random walk rises above the bias-instability floor
    only past ~800 s). With and without B, the single-run RMS error of K is within the same
    1.35 x the bound (measured on 180 axis-runs: 1.03 x and 1.08 x), its mean within three
    standard errors of an efficient estimator, and the 68 % profile interval covers the truth
    on at least half of the axes."""
    bound_b = k_bound(STUDY_N, 20.0, N_TRUE, B_TRUE, K_TRUE)
    bound_0 = k_bound(STUDY_N, 20.0, N_TRUE, 0.0, K_TRUE)
    assert bound_b > 2.5 * bound_0  # the data's own limit: B makes K necessarily less certain
    with_b, covered, fits, _ = k_study(B_TRUE, range(8))
    without_b, covered_0, _, _ = k_study(0.0, range(8))
    print(f"K bound {bound_b:.3f} with B, {bound_0:.3f} without")
    print("K error with B", np.round(with_b, 2), "without", np.round(without_b, 2))
    print(f"RMS {rms(with_b):.3f} with B, {rms(without_b):.3f} without")
    assert np.count_nonzero(with_b > -1.0) >= 21  # K > 0 on all axes but at most 3 of 24
    assert np.all(without_b > -1.0)
    for errors, bound in ((with_b, bound_b), (without_b, bound_0)):
        assert rms(errors) <= 1.35 * bound
        assert abs(errors.mean()) <= 3.0 * bound / np.sqrt(len(errors))
    assert covered.sum() >= 12 and covered_0.sum() >= 12  # 68 % intervals: about 16 of 24
    for f in fits:  # B is found too, and nothing the simulation does not have
        assert f.params["B"] > 0 and f.params["Q"] == f.params["R"] == 0.0


@pytest.mark.slow
def test_random_walk_study_against_maximum_likelihood():
    """12 seeds x 3 axes (about 4 min on a shared 2-core machine): the Allan fit's K against
    the exact Gaussian maximum likelihood on the same runs (:func:`k_max_likelihood`, the
    efficient estimator, every term free) and the Cramer-Rao bound. Measured: with B the fit's
    RMS error is 42 %, ML's 50 %, the bound 46 %; without B 17 %, 17 %, 16 %. The fit is as
    efficient as ML: its RMS within 1.15 x ML's and 1.25 x the bound, with and without B; the
    ML's within 0.8 .. 1.35 x the bound (a check of the bound)."""
    for b in (B_TRUE, 0.0):
        errors, covered, _, data = k_study(b, range(12))
        mats = block_model(STUDY_N, 20.0, b > 0)
        start = [N_TRUE**2] + ([b * b] if b > 0 else []) + [K_TRUE**2]
        ml = np.array([k_max_likelihood(y, 20.0, mats, start) / K_TRUE - 1.0 for y in data])
        bound = k_bound(STUDY_N, 20.0, N_TRUE, b, K_TRUE)
        print(
            f"B = {b:g}: bound {bound:.3f}; fit RMS {rms(errors):.3f} mean {errors.mean():+.3f} "
            f"within 35 % {np.sum(np.abs(errors) < 0.35)}/{len(errors)} covered {covered.sum()}; "
            f"ML RMS {rms(ml):.3f} mean {ml.mean():+.3f}; "
            f"correlation {np.corrcoef(errors, ml)[0, 1]:.2f}"
        )
        assert rms(errors) <= 1.15 * rms(ml)
        assert rms(errors) <= 1.25 * bound
        assert 0.8 * bound <= rms(ml) <= 1.35 * bound
