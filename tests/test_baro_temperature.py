"""Barometer thermal calibration (issue 26): the ``baro_temperature`` stage and PX4's ``TC_B*``.

On ``imupipe simulate board`` (a PX4 v1.11 warm-up ULog whose ``sensor_baro`` carries a known
thermal pressure error, ``baro_poly``, plus 1 Pa of noise):

- PX4's firmware formula (PX4-Autopilot ``TemperatureCompensation::calc_thermal_offsets_1D``:
  ``offset = sum X_k (clamp(T, TMIN, TMAX) - TREF)^k``; v1.11 ``VehicleAirData``: ``corrected =
  (100 * pressure_mbar - offset) * SCL``), in float32 with the exported file's numbers,
  reproduces imupipe's corrected pressure within 1 Pa, in the slot whose ``TC_Bn_ID`` the log
  holds;
- the curve agrees with an independent re-implementation of PX4's ``Tools/process_sensor_caldata
  .py`` fit (median filter of 31, pressure minus its median, 2000 temperature bins, 5th-order
  ``polyfit``) within 1 Pa over the logged range, and with the truth (up to the constant, which a
  room's unknown pressure leaves unobservable).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_exports import qgc_params

from imupipe.pipeline.calibration_file import on_device
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import make_table, with_stream_column
from imupipe.stages.base import StageContext
from imupipe.stages.errors import CalibrationError, FitError
from imupipe.stages.steps import apply_chain, steps_from_json
from imupipe.stages.thermal.baro import BaroTemperatureStage, baro_samples

from conftest import run_cli

BARO_ID = 6620441
SLOT = 1
"""The log's own TC_B1_ID holds the barometer: the file must use slot 1."""
PA_TOL = 1.0
"""Pa: the target of issue 26 (against PX4's formula, PX4's fit and the truth)."""


@pytest.fixture(scope="module")
def baro_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("baro")
    params = {"TC_B1_ID": BARO_ID, "TC_B1_SCL": 1.0}
    log, truth = simulate("board", {"rate_hz": 2.0, "parameters": params}, seed=7)
    write_log(d / "board.ulg", log)
    (d / "cfg.toml").write_text(
        '[inputs.baro]\npath = "board.ulg"\nimu_topic = "sensor_gyro"\n'
        'temperature_topic = "sensor_baro"\n'
        '[[stages]]\nname = "baro"\ntype = "baro_temperature"\ninput = "baro"\n'
        '[output]\ndir = "out"\napply_to = []\nrerun = false\nreport = false\n'
        'exports = ["px4", "ardupilot"]\n'
    )
    proc = run_cli("run", d / "cfg.toml", "--quiet", cwd=d)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((d / "out" / "calibration.json").read_text())
    px4 = qgc_params((d / "out" / "px4_calibration.params").read_text())
    return d, truth, doc, px4


def _raw_baro(path: Path) -> dict[str, np.ndarray]:
    from pyulog import ULog

    (data,) = [d.data for d in ULog(str(path), ["sensor_baro"]).data_list]
    return data


def _px4_offset(p: dict, k: int, temp: np.ndarray) -> np.ndarray:
    """PX4's calc_thermal_offsets_1D in float32, Pa."""
    f = np.float32
    lo, hi, ref = f(p[f"TC_B{k}_TMIN"]), f(p[f"TC_B{k}_TMAX"]), f(p[f"TC_B{k}_TREF"])
    d = np.clip(temp.astype(f), lo, hi) - ref
    out = np.zeros_like(d)
    for j in range(5, -1, -1):  # Horner's rule, in float32
        out = out * d + f(p[f"TC_B{k}_X{j}"])
    return out.astype(np.float64)


def _px4_script_fit(temp: np.ndarray, pressure_mbar: np.ndarray) -> tuple[float, np.ndarray]:
    """An independent re-implementation of process_sensor_caldata.py's barometer fit: (TREF,
    coefficients highest power first, Pa)."""
    from scipy.signal import medfilt

    tref = 0.5 * (temp.min() + temp.max())
    rel = temp - tref
    p = medfilt(pressure_mbar.astype(np.float64), 31)
    y = 100.0 * (p - np.median(p))
    n = 2000
    lo, hi = rel.min(), rel.max()
    idx = np.clip(((rel - lo) / ((hi - lo) / n)).astype(int), 0, n - 1)
    idx[rel >= hi] = n - 1
    count = np.bincount(idx, minlength=n)
    ok = count > 0
    x = np.bincount(idx, rel, n)[ok] / count[ok]
    yy = np.bincount(idx, y, n)[ok] / count[ok]
    return tref, np.polyfit(x, yy, 5)


def test_tc_b_in_the_logs_slot(baro_run):
    """TC_B_ENABLE, TC_B1_ID (the log's own slot for the device), TREF mid-range, SCL = 1
    because the log has it; nothing else (no CAL_*, no IMU TC_*); ArduPilot notes it has no
    place for it."""
    d, truth, doc, px4 = baro_run
    assert px4["TC_B_ENABLE"] == 1 and px4[f"TC_B{SLOT}_ID"] == BARO_ID
    assert "TC_B0_ID" not in px4 and px4[f"TC_B{SLOT}_SCL"] == 1.0
    lo, hi = truth["baro"]["temperature_range"]
    assert px4[f"TC_B{SLOT}_TMIN"] == pytest.approx(lo, abs=1e-5)
    assert px4[f"TC_B{SLOT}_TREF"] == pytest.approx((lo + hi) / 2, abs=1e-5)
    assert not [k for k in px4 if not k.startswith("TC_B")]
    notes = doc["exports"]["ardupilot_calibration.param"]["notes"]
    assert any("barometer" in n for n in notes)
    assert not (d / "out" / "ardupilot_calibration.param").exists()


def test_px4_formula_reproduces_imupipe(baro_run):
    """PX4's correction (float32, the file's numbers) on the logged raw pressure equals
    imupipe's corrected pressure within 1 Pa, over the whole warm-up."""
    d, _, doc, px4 = baro_run
    raw = _raw_baro(d / "board.ulg")
    temp = raw["temperature"].astype(np.float64)
    px4_out = (100.0 * raw["pressure"].astype(np.float64) - _px4_offset(px4, SLOT, temp)) * px4[
        f"TC_B{SLOT}_SCL"
    ]
    spec = InputSpec(path=d / "board.ulg", imu_topic="sensor_gyro", temperature_topic="sensor_baro")
    table, _ = read_input(spec)
    corrected = apply_chain(table, on_device(steps_from_json(doc["chain"]), doc["chain"]))
    rows, _, _, ours = baro_samples(corrected)
    _, _, _, before = baro_samples(table)
    assert len(ours) == len(px4_out)
    err = np.abs(px4_out - ours).max()
    assert err < PA_TOL, err
    assert np.abs(before - ours).max() > 50.0  # the correction did something


def test_agrees_with_px4s_script_fit_and_the_truth(baro_run):
    """The TC_B curve within 1 Pa of PX4's script fit (re-implemented) over the logged range,
    and of the true thermal error up to a constant."""
    d, truth, _, px4 = baro_run
    raw = _raw_baro(d / "board.ulg")
    temp = raw["temperature"].astype(np.float64)
    tref, coef = _px4_script_fit(temp, raw["pressure"])
    grid = np.linspace(temp.min(), temp.max(), 200)
    ours = _px4_offset(px4, SLOT, grid)
    theirs = np.polyval(coef, grid - tref)
    assert np.abs(ours - theirs).max() < PA_TOL, np.abs(ours - theirs).max()
    true = np.polynomial.polynomial.polyval(grid - truth["tref"], truth["baro"]["poly"])
    shape = (ours - true) - np.mean(ours - true)
    assert np.abs(shape).max() < PA_TOL, np.abs(shape).max()


def _table(temp: np.ndarray, pressure: np.ndarray):
    t = np.arange(len(temp), dtype=np.int64) * 10**8
    table = make_table(t, temperature=temp)
    return with_stream_column(table, "temperature", "pressure", t, pressure)


def test_flat_temperature_fails_its_check():
    """A barometer held at one temperature fixes no curve: the stage stops with one line."""
    rng = np.random.default_rng(1)
    temp = 25.0 + rng.normal(0, 0.1, 2000)
    table = _table(temp, 101325.0 + rng.normal(0, 1.0, 2000))
    stage = BaroTemperatureStage(BaroTemperatureStage.Options())
    with pytest.raises(FitError, match="min_span"):
        stage.fit(table, StageContext(name="b", input_name="x", quiet=True))


def test_no_pressure_is_one_line():
    table = make_table(np.arange(10, dtype=np.int64), temperature=np.linspace(0, 40, 10))
    stage = BaroTemperatureStage(BaroTemperatureStage.Options())
    with pytest.raises(FitError, match="sensor_baro"):
        stage.fit(table, StageContext(name="b", input_name="x", quiet=True))


def test_chain_entry_checks():
    """A damaged barometer entry is one line naming the field."""
    entry = {
        "type": "baro_temperature",
        "sensor": "temperature",
        "kind": "baro_temperature",
        "tref": 20.0,
        "coefficients": [1.0, 2.0],
        "range": [30.0, 10.0],
    }
    with pytest.raises(CalibrationError, match=r"chain\[0\]\.range"):
        steps_from_json([entry])
    (step,) = steps_from_json([{**entry, "range": [10.0, 30.0]}])
    temp = np.array([0.0, 20.0, 40.0])
    table = _table(temp, np.full(3, 1000.0))
    _, _, _, out = baro_samples(step.apply(table))
    np.testing.assert_allclose(out, 1000.0 - (1.0 + 2.0 * (np.clip(temp, 10, 30) - 20.0)))
