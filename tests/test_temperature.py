"""Issue 7: temperature compensation, checked against simulated truth and scipy's curve_fit.

Done-when: thermal cycles -40..80 degC (cubic bias + rate term), fitted on cycles at 1 and
0.5 degC/min and validated on a 2 degC/min cycle through ``imupipe convert``: the 10 s-mean bias
RMS drops >= 20x on every axis; the rate model beats the plain polynomial; the cubic is recovered
to 1e-6 on noiseless data; the MATLAB example's six-term model equals curve_fit to 1e-9; a constant
temperature is refused with one line.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from scipy.optimize import curve_fit

from imupipe.pipeline.errors import FitError
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import make_table, metadata, sensor, with_metadata
from imupipe.stages.base import StageContext
from imupipe.stages.blocks import block_means
from imupipe.stages.steps import apply_chain, steps_from_json
from imupipe.stages.thermal.step import TemperatureStep
from imupipe.stages.thermal.stepwise import candidate_terms
from imupipe.stages.thermal.temperature import TemperatureStage

from conftest import run_cli

FIT = {"heating_rates": [1.0, 0.5], "rate_hz": 2.0}
VALIDATE = {"heating_rates": [2.0], "rate_hz": 2.0}
REFERENCE = {"gyro": [0.0, 0.0, 0.0], "accel": [0.0, 0.0, 9.80665]}


def fit_stage(table, held_out=None, **options):
    stage = TemperatureStage(TemperatureStage.Options(**options))
    tables = {} if held_out is None else {"val": held_out}
    ctx = StageContext(name="temperature", input_name="fit", tables=tables, quiet=True)
    return stage.fit(table, ctx)


@pytest.fixture(scope="module")
def cycles():
    fit, truth = simulate("thermal", FIT, seed=11)
    val, _ = simulate("thermal", VALIDATE, seed=12)
    return fit, val, truth


def block_std(table, name, reference):
    """Std over the complete 10 s blocks (the trailing partial one left out) of the bias: the
    temperature-driven variation, the quantity of the stage's rms_before / rms_after."""
    data = sensor(table, name)
    blocks = block_means(data.t_ns, data.values - reference, window_s=10.0)
    return blocks.means[:-1].std(axis=0)


@pytest.fixture(scope="module")
def converted(tmp_path_factory, cycles):
    """`imupipe run` fits gyro and accel on the 1 and 0.5 degC/min cycles; `imupipe convert`
    applies calibration.json to the 2 degC/min cycle."""
    fit, val, _ = cycles
    d = tmp_path_factory.mktemp("thermal")
    write_log(d / "fit.csv", fit)
    write_log(d / "val.csv", val)
    (d / "cfg.toml").write_text(
        '[inputs.fit]\npath = "fit.csv"\n[inputs.val]\npath = "val.csv"\n\n'
        '[[stages]]\ntype = "temperature"\nname = "temp_gyro"\ninput = "fit"\nsensor = "gyro"\n'
        'validate = "val"\n\n'
        '[[stages]]\ntype = "temperature"\nname = "temp_accel"\ninput = "fit"\nsensor = "accel"\n'
        'reference = [0.0, 0.0, 9.80665]\nvalidate = "val"\n\n'
        '[output]\ndir = "out"\napply_to = []\n'
    )
    proc = run_cli("run", d / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    proc = run_cli(
        "convert", "--calibration", d / "out" / "calibration.json", "--out", d / "conv",
        d / "val.csv", "--jobs", "1", "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    corrected, _ = read_input(InputSpec(path=d / "conv" / "val.mcap"))
    calibration = json.loads((d / "out" / "calibration.json").read_text())
    return d, val, corrected, calibration


@pytest.mark.parametrize("name", ["gyro", "accel"])
def test_convert_reduces_bias_20x_on_held_out_cycle(converted, name):
    _, val, corrected, calibration = converted
    before = block_std(val, name, REFERENCE[name])
    after = block_std(corrected, name, REFERENCE[name])
    ratio = before / after
    assert (ratio >= 20).all(), ratio
    # the stage's own held-out metrics agree with what convert wrote (same blocks, same quantity)
    metrics = calibration["results"][f"temp_{name}"]["metrics"]["validate"]
    np.testing.assert_allclose([metrics[a]["rms_before"] for a in "xyz"], before, rtol=1e-9)
    np.testing.assert_allclose([metrics[a]["rms_after"] for a in "xyz"], after, rtol=1e-9)


def test_chain_entry_round_trips(converted, cycles):
    _, val, _, calibration = converted
    steps = steps_from_json(calibration["chain"])
    assert [type(s) for s in steps] == [TemperatureStep, TemperatureStep]
    again = steps_from_json([s.to_json() for s in steps])
    a = sensor(apply_chain(val, steps), "gyro").values
    b = sensor(apply_chain(val, again), "gyro").values
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ["gyro", "accel"])
def test_rate_term_beats_plain_polynomial(cycles, name):
    fit, val, _ = cycles
    ref = REFERENCE[name]
    with_rate = fit_stage(fit, val, sensor=name, reference=ref, validate="val")
    plain = fit_stage(fit, val, sensor=name, reference=ref, validate="val", rate_terms=[])
    for axis in "xyz":
        a = with_rate.results["metrics"]["validate"][axis]["rms_after"]
        b = plain.results["metrics"]["validate"][axis]["rms_after"]
        assert a < 0.5 * b, (axis, a, b)


def test_cubic_recovered_on_noiseless_data():
    params = {
        "heating_rates": [2.0, 1.0],
        "hold_s": 900.0,
        "rate_hz": 1.0,
        "gyro_N": [0.0] * 3,
        "accel_N": [0.0] * 3,
        "temperature_noise": 0.0,
    }
    table, truth = simulate("thermal", params, seed=0)
    for name in ("gyro", "accel"):
        out = fit_stage(
            table, sensor=name, window=1, bin_width=0.0, tref=truth["poly_tref"],
            reference=REFERENCE[name],
        )  # fmt: skip
        for i, axis in enumerate("xyz"):
            assert out.results["terms"][axis] == ["1", "T", "T^2", "T^3", "dT"]
            got = np.array(out.results["coefficients"][axis])
            want = np.r_[truth[name]["poly"][i], truth[name]["rate_coef"][i]]
            np.testing.assert_allclose(got, want, rtol=1e-6, err_msg=f"{name} {axis}")


def test_six_term_model_equals_curve_fit(cycles):
    fit, _, _ = cycles
    for bin_width in (0.0, 1.0):
        out = fit_stage(fit, model="six_term", window=500, bin_width=bin_width, write_blocks=True)
        (text,) = out.artifacts.values()
        blocks = np.genfromtxt(io.StringIO(text), delimiter=",", names=True)
        x = np.vstack([blocks["T"], blocks["dT"]])
        sigma = 1.0 / np.sqrt(blocks["weight"])

        def t_fun(x, a1, a2, a3, a4, a5, a6):  # the MATLAB example's tFun
            return a1 * x[0] ** 2 + a2 * x[0] + a3 * x[1] ** 2 + a4 * x[1] + a5 * x[1] * x[0] + a6

        def t_jac(x, *a):  # its derivatives; finite differences would limit curve_fit to ~1e-7
            return np.column_stack(
                [x[0] ** 2, x[0], x[1] ** 2, x[1], x[1] * x[0], np.ones_like(x[0])]
            )

        for axis in "xyz":
            assert out.results["terms"][axis] == ["T^2", "T", "dT^2", "dT", "T*dT", "1"]
            ref, _ = curve_fit(
                t_fun, x, blocks[f"bias_{axis}"], p0=np.zeros(6), sigma=sigma, jac=t_jac,
                xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm",
            )  # fmt: skip
            got = np.array(out.results["coefficients"][axis])
            np.testing.assert_allclose(got, ref, rtol=1e-9, err_msg=f"{axis} bins {bin_width}")


def test_piecewise_hysteresis_term_matches_truth(cycles):
    fit, val, truth = cycles
    out = fit_stage(fit, val, model="piecewise", validate="val")
    for i, axis in enumerate("xyz"):
        terms = out.results["terms"][axis]
        k_dt = out.results["coefficients"][axis][terms.index("dT")]
        assert k_dt == pytest.approx(truth["gyro"]["rate_coef"][i], rel=0.05)
        assert out.results["metrics"]["validate"][axis]["reduction"] >= 20


@pytest.mark.parametrize(
    ("ambient", "criterion"), [(False, "f_test"), (True, "f_test"), (False, "adj_r2")]
)
def test_stepwise_selects_temperature_and_rate_terms(cycles, ambient, criterion):
    fit, val, _ = cycles
    if not ambient:
        fit, val = (
            fit.drop_columns(["ambient_temperature"]),
            val.drop_columns(["ambient_temperature"]),
        )
    out = fit_stage(fit, val, model="stepwise", validate="val", criterion=criterion)
    for axis in "xyz":
        terms = set(out.results["terms"][axis])
        assert {"T^2", "T^3"} <= terms
        # with an ambient column, Ta = T + lag * dT stands in for the rate
        assert terms & ({"dT", "Ta", "T*dT"} if ambient else {"dT", "T*dT"})
        assert out.results["metrics"]["validate"][axis]["reduction"] >= 20


def test_stepwise_candidates_count():
    assert len(candidate_terms(["T", "dT", "Ta", "dTa"], order=2)) == 15
    assert len(candidate_terms(["T", "dT"], order=2)) == 6


def test_soak_steps_work(cycles):
    _, val, _ = cycles
    soak, _ = simulate("thermal", {**FIT, "heating_rates": [1.0], "soak_step": 20.0}, seed=5)
    out = fit_stage(soak, val, validate="val")
    for axis in "xyz":
        assert out.results["metrics"]["validate"][axis]["reduction"] >= 20


def test_narrow_span_refused_and_clamped():
    n = 2000
    t_ns = np.arange(n, dtype=np.int64) * 1_000_000_000
    temp = np.full(n, 25.0)
    table = make_table(t_ns, gyro=np.zeros((n, 3)), accel=np.zeros((n, 3)), temperature=temp)
    with pytest.raises(FitError, match="spans only 0 degC"):
        fit_stage(table)
    # a 12 degC ramp fits (with a warning); outside it the correction is clamped
    ramp = 20.0 + 12.0 * np.arange(n) / n
    gyro = np.outer(1e-3 * (ramp - 20.0), [1.0, 2.0, 3.0])
    table = make_table(t_ns, gyro=gyro, accel=np.zeros((n, 3)), temperature=ramp)
    out = fit_stage(table, order=1, rate_terms=[])
    hot = make_table(t_ns[:10], gyro=np.zeros((10, 3)), accel=np.zeros((10, 3)),
                     temperature=np.full(10, 60.0))  # fmt: skip
    corrected = sensor(out.step.apply(hot), "gyro").values
    hi = out.step.ranges["T"][1]  # the warmest block mean
    want = -1e-3 * (hi - 20.0) * np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(corrected, np.tile(want, (10, 1)), rtol=1e-9)
    assert "T clamped to the fitted range" in out.step.warnings[0]
    # the warning names the log it is about (run and convert correct several)
    named = with_metadata(hot, {**metadata(hot), "source": "hot.mcap"})
    out.step.apply(named)
    assert out.step.warnings[-1].startswith("hot.mcap: T clamped to the fitted range")
    with pytest.raises(FitError, match="'window' must be >= 1"):
        fit_stage(table, window=0)


def test_constant_temperature_refused_by_cli(tmp_path):
    table, _ = simulate("static", {"duration_s": 60.0, "rate_hz": 50.0}, seed=1)
    write_log(tmp_path / "static.csv", table)
    (tmp_path / "cfg.toml").write_text(
        '[inputs.s]\npath = "static.csv"\n[[stages]]\ntype = "temperature"\n[output]\ndir = "out"\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "temperature spans only 0 degC" in lines[0] and "'temperature'" in lines[0]
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_recording_has_the_figures(converted):
    import rerun.chunk as rc

    d, _, _, _ = converted
    entities = {
        c.entity_path for c in rc.RrdReader(str(d / "out" / "recording.rrd")).stream().to_chunks()
    }
    for axis in "xyz":
        for part in ("heating", "cooling", "fit"):
            assert f"/temp_gyro/bias_vs_temperature/{axis}/{part}" in entities
        assert f"/temp_gyro/surface/{axis}/mesh" in entities
        assert f"/temp_gyro/surface/{axis}/data" in entities
    assert any(e.startswith("/temp_accel/residual/") for e in entities)  # one per line


def test_turntable_scale_factor_against_temperature(tmp_path):
    """The gyro patent: +/-rate turntable runs in the chamber give sf(T) = (out+ - out-) / (2 rate)."""
    turn = {"turntable_rate": 10.0}
    fit, truth = simulate("thermal", {**FIT, **turn}, seed=21)
    val, _ = simulate("thermal", {**VALIDATE, **turn}, seed=22)
    rate = float(np.deg2rad(10.0))
    out = fit_stage(fit, val, validate="val", turntable_rate=rate, tref=truth["poly_tref"])
    assert list(out.step.scale) == ["z"]  # the table turns about z only
    s1, s2 = truth["gyro"]["scale_poly"][2]
    sf0, got1, got2 = out.step.scale["z"]["coefficients"]
    assert abs(sf0 - 1.0) < 3e-4 and got1 == pytest.approx(s1, rel=0.02)
    assert got2 == pytest.approx(s2, rel=0.1)
    metrics = out.results["metrics"]["validate"]
    assert metrics["z"]["scale_error_after"] < 0.1 * metrics["z"]["scale_error_before"]
    for axis in "xyz":  # the turning blocks stay out of the bias fit
        assert metrics[axis]["reduction"] >= 20
    # the scale travels through calibration.json
    (again,) = steps_from_json([out.step.to_json()])
    a = sensor(out.step.apply(val), "gyro").values
    np.testing.assert_array_equal(a, sensor(again.apply(val), "gyro").values)


LAG = {"rate_hz": 2.0, "element_lag_s": 200.0, "gyro_rate_coef": [0.0] * 3, "ambient": False}


@pytest.fixture(scope="module")
def lagging():
    """The sensing element lags the board sensor by 200 s (the bias follows the element): fit on
    cycles at 1 and 0.5 degC/min, held-out cycle at 2 degC/min."""
    fit, truth = simulate("thermal", {"heating_rates": [1.0, 0.5], **LAG}, seed=11)
    val, _ = simulate("thermal", {"heating_rates": [2.0], **LAG}, seed=12)
    return fit, val, truth


def test_lag_model_beats_piecewise_and_stepwise_on_held_out_cycle(lagging):
    fit, val, truth = lagging
    rms = {}
    for model in ("lag", "piecewise", "stepwise"):
        out = fit_stage(fit, val, model=model, validate="val")
        rms[model] = np.array([out.results["metrics"]["validate"][a]["rms_after"] for a in "xyz"])
        if model == "lag":
            tau = out.results["lag"]["lag_s"]
            assert tau == pytest.approx(truth["element_lag_s"], rel=0.10)
            assert out.step.lag_s == tau and "Ts" in out.results["terms"]["x"]
    assert (2 * rms["lag"] <= rms["piecewise"]).all(), rms
    assert (2 * rms["lag"] <= rms["stepwise"]).all(), rms


def test_lag_model_round_trips_and_streams(lagging):
    fit, val, _ = lagging
    out = fit_stage(fit, model="lag")
    (again,) = steps_from_json([out.step.to_json()])
    np.testing.assert_array_equal(
        sensor(out.step.apply(val), "gyro").values, sensor(again.apply(val), "gyro").values
    )


def test_one_way_narrow_ramp_falls_back_with_warnings():
    """An 8 degC cooling ramp: the span is a warning, the rate term and the lag cannot be
    identified (one direction), so the fit falls back to a polynomial in T and says so."""
    n = 4000
    t_ns = np.arange(n, dtype=np.int64) * 1_000_000_000
    temp = 24.0 - 8.0 * np.arange(n) / n
    gyro = np.outer(1e-4 * (temp - 20.0), [1.0, -2.0, 0.5])
    table = make_table(t_ns, gyro=gyro, accel=np.zeros((n, 3)), temperature=temp)
    for model in ("poly", "lag"):
        stage = TemperatureStage(TemperatureStage.Options(model=model))
        ctx = StageContext(name="t", input_name="ramp", quiet=True)
        out = stage.fit(table, ctx)
        assert any("spans only 7.9" in w for w in ctx.warnings), ctx.warnings
        (note,) = out.results["fallback"]
        assert "cannot be identified: the temperature only falls (23.99 -> 16" in note, note
        assert out.results["model"] == "poly" and out.step.lag_s is None
        for axis in "xyz":
            assert not {"dT", "Ts", "dTs"} & set(out.results["terms"][axis])
        assert (
            out.results["metrics"]["x"]["rms_after"]
            < 1e-3 * out.results["metrics"]["x"]["rms_before"]
        )


def test_partial_last_block_is_left_out():
    """A trailing 1-sample block does not enter the fit or the metrics (it used to weigh like a
    full block): an outlier there changes nothing but the neighbouring block's temperature
    rate (the partial block's temperature still counts there)."""
    table, _ = simulate("thermal", {"heating_rates": [2.0], "rate_hz": 1.0, "hold_s": 300.0})
    n = len(table) - len(table) % 50
    # still_threshold = 0: the spike is motion to the still-sample detection, which would
    # (rightly) leave out its neighbours in the last complete block; this test is about the block
    full = fit_stage(table.slice(0, n), window=50, still_threshold=0)
    data = sensor(table.slice(0, n + 1), "gyro")
    spiked = data.values.copy()
    spiked[-1] += 0.5  # rad/s, 10^4 x the noise
    extra = fit_stage(
        make_table(data.t_ns, gyro=spiked, accel=np.zeros_like(spiked),
                   temperature=sensor(table.slice(0, n + 1), "temperature").values[:, 0]),
        window=50, still_threshold=0,
    )  # fmt: skip
    assert full.results["blocks"] == extra.results["blocks"]
    for axis in "xyz":
        a, b = full.results["metrics"][axis], extra.results["metrics"][axis]
        assert b["rms_after"] == pytest.approx(a["rms_after"], rel=0.01)
        assert b["rms_before"] == pytest.approx(a["rms_before"], rel=1e-9)


def test_lag_model_recording(lagging, tmp_path):
    """Rerun: lagged vs measured temperature, the bias against the element's temperature, the
    lag fit's cost profile."""
    import rerun.chunk as rc

    from imupipe.pipeline.report.recording import Recorder

    fit, _, _ = lagging
    recorder = Recorder(tmp_path / "lag.rrd")
    stage = TemperatureStage(TemperatureStage.Options(model="lag"))
    stage.fit(
        fit, StageContext(name="temperature_gyro", input_name="fit", recorder=recorder, quiet=True)
    )
    recorder.close()
    chunks = list(rc.RrdReader(str(tmp_path / "lag.rrd")).stream().to_chunks())
    entities = {c.entity_path for c in chunks}
    for axis in "xyz":
        assert f"/temperature_gyro/bias_vs_temperature/{axis}/fit" in entities
    assert "/temperature_gyro/lag_fit" in entities
    lines = "/temperature_gyro/temperature/"  # one entity per line
    assert any(e.startswith(lines) for e in entities)
    names = str([c.to_record_batch() for c in chunks if c.entity_path.startswith(lines)])
    assert "sensing element Ts (lag 199.7 s)" in names and "measured T" in names
