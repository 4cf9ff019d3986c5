"""Issue 25, thermal: the ``temperature`` stage's default (``model = "auto"``) chooses its model by
held-out prediction and says why; only still samples enter the fit; a fit that does not beat no
compensation on its own held-out segments, or that spans orientations, is refused with the
figures; rate and direction warnings match the data (degC/min)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from imupipe.pipeline.errors import FitError
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.table import make_table
from imupipe.stages.base import StageContext
from imupipe.stages.thermal.temperature import TemperatureStage

from conftest import REPO, run_cli

sys.path.insert(0, str(REPO / "benchmarks"))

LAG = {"rate_hz": 2.0, "element_lag_s": 200.0, "gyro_rate_coef": [0.0] * 3, "ambient": False}


def fit(table, held_out=None, **options):
    stage = TemperatureStage(TemperatureStage.Options(**options))
    tables = {} if held_out is None else {"val": held_out}
    ctx = StageContext(name="temperature", input_name="fit", tables=tables, quiet=True)
    return stage.fit(table, ctx), ctx


@pytest.fixture(scope="module")
def family():
    from sweep_cases import thermal

    return thermal


@pytest.fixture(scope="module")
def lagging():
    """The issue's case: the sensing element lags the board sensor by 200 s; fitted on cycles at
    1 and 0.5 degC/min, held out a cycle at 2 degC/min."""
    fitted, truth = simulate("thermal", {"heating_rates": [1.0, 0.5], **LAG}, seed=11)
    val, _ = simulate("thermal", {"heating_rates": [2.0], **LAG}, seed=12)
    return fitted, val, truth


def test_default_chooses_the_lag_by_held_out_prediction(lagging):
    table, val, truth = lagging
    auto, _ = fit(table, val, validate="val")
    poly, _ = fit(table, val, validate="val", model="poly")
    assert auto.results["model"] == "lag" and poly.results["model"] == "poly"
    choice = auto.results["choice"]
    assert choice["model"] == "lag" and choice["reason"].startswith("lag predicts the 5 held-out")
    assert choice["scores"]["lag"] < 0.5 * choice["scores"]["poly"], choice["scores"]
    assert auto.results["lag"]["lag_s"] == pytest.approx(truth["element_lag_s"], rel=0.1)
    reduction = np.array([auto.results["metrics"]["validate"][a]["reduction"] for a in "xyz"])
    before = np.array([poly.results["metrics"]["validate"][a]["reduction"] for a in "xyz"])
    assert (reduction >= 25).all() and (before < 10).all(), (reduction, before)
    # applied to the faster cycle, the rates leave the fitted range: said in degC/min
    auto.step.apply(val)
    (note,) = [w for w in auto.step.warnings if "dTs (temperature rate) extrapolated beyond" in w]
    assert " degC/min at " in note and " degC/min)" in note, note
    # the stated remaining bias and its interval, per axis
    for axis in "xyz":
        m = auto.results["metrics"][axis]
        lo, hi = m["remaining_rms_95"]
        assert 0 <= lo <= m["remaining_rms"] <= hi
        assert m["held_out_rms"] < 0.1 * m["held_out_baseline"]


def test_default_keeps_poly_where_nothing_beats_it():
    table, _ = simulate("thermal", {"rate_hz": 1.0, "heating_rates": [2.0], "hold_s": 300.0})
    out, _ = fit(table)
    assert out.results["model"] == "poly", out.results["choice"]
    assert "another model replaces poly only when 10% lower" in out.results["choice"]["reason"]


def tag_log(family, seed=0):
    """The issue's tag log (simulated: the real one is not in ../shared/data): 1 Hz, three long
    still periods in three orientations, handled between them, slowly warming, a wandering
    bias."""
    case = next(c for c in family.CASES if c.name.startswith("tag day"))
    table, _ = simulate("thermal", case.params, seed=seed)
    return case.edit(table, np.random.default_rng(seed))


def test_orientation_changes_are_refused_with_the_cause(family):
    table = tag_log(family)
    with pytest.raises(FitError) as err:
        fit(table)
    message = str(err.value)
    assert "the IMU was turned between its still periods" in message
    assert (
        "held-out RMS x " in message
        and "record the thermal log in one fixed orientation" in message
    )
    # accepted on request: applied, with the failed check in the results
    stage = TemperatureStage(TemperatureStage.Options())
    ctx = StageContext(name="t", input_name="fit", quiet=True, accept_failed_checks=True)
    stage.fit(table, ctx)
    assert any("turned between" in c for c in ctx.failed_checks)


def test_handling_is_left_out_of_the_fit(family):
    case = next(c for c in family.CASES if c.name.startswith("handling between soaks"))
    table, _ = simulate("thermal", case.params, seed=3)
    handled = case.edit(table, np.random.default_rng(3))
    clean, _ = fit(table)
    out, ctx = fit(handled)
    assert out.results["moving_blocks"] >= 4 * 12  # four 2-minute handlings of 10 s blocks
    assert any("less than half their samples still (handling or motion" in w for w in ctx.warnings)
    for axis in "xyz":
        a, b = clean.results["metrics"][axis], out.results["metrics"][axis]
        assert b["rms_after"] < 1.2 * a["rms_after"], (axis, a["rms_after"], b["rms_after"])
    # without the still-sample detection the handling ruins the fit
    with pytest.raises(FitError, match="held-out segments no better than no compensation"):
        fit(handled, still_threshold=0)


def test_a_fit_that_does_not_beat_no_compensation_is_refused(family):
    case = next(c for c in family.CASES if c.name.startswith("bias random walk"))
    table, _ = simulate("thermal", case.params, seed=5)
    with pytest.raises(FitError) as err:
        fit(case.edit(table, np.random.default_rng(5)))
    message = str(err.value)
    assert "predicts held-out segments worse than no compensation on x, y" in message
    assert (
        "held-out RMS over 5 segments: x " in message and " rad/s without compensation" in message
    )
    assert "the fit is not applied" in message and "\n" not in message


def test_refused_run_writes_nothing(family, tmp_path):
    case = next(c for c in family.CASES if c.name.startswith("orientation changes"))
    table, _ = simulate("thermal", case.params, seed=1)
    write_log(tmp_path / "tag.csv", case.edit(table, np.random.default_rng(1)))
    (tmp_path / "cfg.toml").write_text(
        '[inputs.tag]\npath = "tag.csv"\n\n[[stages]]\ntype = "temperature"\n\n'
        '[output]\ndir = "out"\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 2, proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert "turned between its still periods" in line and "Traceback" not in proc.stderr
    assert not (tmp_path / "out" / "calibration.json").exists()
    assert not list(tmp_path.glob("out/*.mcap"))


def test_direction_warning_matches_the_data():
    """A slow warming with a few quick cooling blocks (a hand put down): not 'only rises', and
    the rates in degC/min, as in the results."""
    n = 6000
    t_ns = np.arange(n, dtype=np.int64) * 1_000_000_000
    temp = 5.0 + 19.0 * np.arange(n) / n
    temp[3000:3040] -= np.linspace(0, 2.0, 40)  # 40 s of cooling by 2 degC, then a step back
    rng = np.random.default_rng(0)
    gyro = np.outer(1e-4 * (temp - 15.0), [1.0, -2.0, 0.5]) + rng.normal(0, 1e-5, (n, 3))
    accel = np.array([0, 0, 9.80665]) + rng.normal(0, 1e-3, (n, 3))
    table = make_table(t_ns, gyro=gyro, accel=accel, temperature=temp)
    out, ctx = fit(table)
    lo, hi = out.results["rate_range"]
    assert lo < -2.0 and hi > 0.1, (lo, hi)  # degC/min
    (note,) = [w for w in ctx.warnings if "cannot be identified" in w]
    assert "only rises" not in note
    assert (
        "the temperature mostly rises (5.014 -> 23.95 degC; 3 of 597 blocks go the other way"
        in note
    )
    assert f"at {lo:.3g}..{hi:.3g} degC/min" in note, note


def test_an_axis_without_thermal_bias_does_not_refuse_the_fit(family):
    """z has no temperature dependence: its held-out error equals no compensation's (within the
    10 % margin), which is not a failure while x and y follow the temperature."""
    case = next(c for c in family.CASES if c.name.startswith("z axis without thermal bias"))
    table, _ = simulate("thermal", case.params, seed=7)
    out, _ = fit(table)
    m = out.results["metrics"]
    assert m["z"]["held_out_rms"] == pytest.approx(m["z"]["held_out_baseline"], rel=0.1)
    assert m["x"]["held_out_rms"] < 0.1 * m["x"]["held_out_baseline"]
