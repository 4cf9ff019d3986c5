"""Issue 26: drone boards as they are. Every IMU instance in its own parameter slot, files that
write only what was estimated, and the thermal calibration of every IMU of a board in one run,
checked with the firmware's own correction formulas:

- PX4 (PX4-Autopilot ``src/lib/sensor_calibration``, ``Correct``; ``src/modules/
  temperature_compensation``, ``calc_thermal_offsets_3D``): per device, ``corrected = (raw -
  TC(T) - CAL_*OFF) * CAL_ACC*SCALE``, ``TC(T) = sum_k X{k} (clamp(T, TMIN, TMAX) - TREF)^k``,
  the slot chosen by ``TC_*n_ID``/``CAL_*n_ID`` = the device id;
- ArduPilot (``AP_InertialSensor_Backend.cpp`` ``_rotate_and_correct_accel``/``_gyro``;
  ``AP_InertialSensor_tempcal.cpp`` ``correct_sensor``): ``corrected = (raw - tcal(T) -
  INS_ACC{,2,3}OFFS) * INS_ACC{,2,3}SCAL``, ``tcal(T) = p(T - 35) - p(CALTEMP - 35)``, ``p`` the
  ``INS_TCALi_{ACC,GYR}{1,2,3}`` cubic / 1e6, T clamped to ``INS_TCALi_TMIN..TMAX``.

Logs: ``imupipe simulate board`` (a two-IMU PX4 v1.11 warm-up, written as a ULog). PX4's own
``Tools/process_sensor_caldata.py`` (BSD-3, not vendored) is run when the environment variable
``PX4_PROCESS_SENSOR_CALDATA`` names it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_exports import mavparm, qgc_params

from imupipe.pipeline.calibration_file import on_device
from imupipe.pipeline.exports import export_all
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import make_table, sensor
from imupipe.stages.steps import LinearStep, apply_chain, steps_from_json
from imupipe.stages.thermal.step import TemperatureStep

from conftest import run_cli

SWAPPED = [1, 0]
"""The log's slots in the opposite order of the instances: CAL_*0_ID is instance 1's device."""
WARM_UP = {"rate_hz": 5.0, "cal_order": SWAPPED}
"""A 45 min warm-up at 5 Hz (the fits' precision depends on the duration, not the rate)."""
GYRO_TOL = 0.05e-3
"""rad/s: the TC curves of imupipe and PX4's script agree within this over the logged range."""
ACCEL_TOL = 0.2e-3
"""m/s^2: the same for the accelerometer's temperature-driven part (both remove a constant)."""


BARO_INPUT = (
    '[inputs.baro]\npath = "board.ulg"\nimu_topic = ""\ntemperature_topic = "sensor_baro"\n'
)
BARO_STAGE = '[[stages]]\nname = "baro"\ntype = "baro_temperature"\ninput = "baro"\n'
BARO_TOL = 1.0
"""Pa: the TC_B curves of imupipe and PX4's script over the logged range."""


def _stages(stype: str, sensors: list[str], extra: str = "") -> str:
    text = ""
    for i in (0, 1):
        topic = "sensor_gyro" if i == 0 else "sensor_gyro_1"
        text += f'[inputs.imu{i}]\npath = "board.ulg"\nimu_topic = "{topic}"\n'
    for i in (0, 1):
        for s in sensors:
            text += f'[[stages]]\nname = "{s}{i}"\ntype = "{stype}"\ninput = "imu{i}"\n'
            text += f'sensor = "{s}"\n{extra}' if stype == "temperature" else extra
    return text


def _run(
    d: Path, body: str, params: str = "estimated", ardupilot: bool = True
) -> tuple[dict, dict, dict]:
    exports = '["px4", "ardupilot"]' if ardupilot else '["px4"]'
    (d / "cfg.toml").write_text(
        body + f'[output]\ndir = "out"\napply_to = []\nrerun = false\nreport = false\n'
        f'exports = {exports}\nparams = "{params}"\n'
    )
    proc = run_cli("run", d / "cfg.toml", "--quiet", cwd=d)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((d / "out" / "calibration.json").read_text())
    px4 = (d / "out" / "px4_calibration.params").read_text()
    ardu = mavparm(d / "out" / "ardupilot_calibration.param") if ardupilot else {}
    return doc, qgc_params(px4), ardu


@pytest.fixture(scope="module")
def warm_up(tmp_path_factory):
    """Both IMUs' gyro and accel fitted against temperature in one run."""
    d = tmp_path_factory.mktemp("board")
    log, truth = simulate("board", WARM_UP, seed=26)
    write_log(d / "board.ulg", log)
    body = _stages("temperature", ["gyro", "accel"], "order = 3\nrate_terms = []\n")
    body = BARO_INPUT + body + BARO_STAGE
    doc, px4, ardu = _run(d, body)
    return d, truth, doc, px4, ardu, (d / "out" / "px4_calibration.params").read_text()


def _slot(p: dict, prefix: str, device: int) -> int:
    (n,) = [k for k in range(4) if p.get(f"{prefix}{k}_ID") == device]
    return n


def _px4_tc(p: dict, prefix: str, n: int, temp: np.ndarray) -> np.ndarray:
    """PX4's thermal offset (calc_thermal_offsets_3D): the clamped cubic about TREF, (m, 3)."""
    d = np.clip(temp, p[f"{prefix}{n}_TMIN"], p[f"{prefix}{n}_TMAX"]) - p[f"{prefix}{n}_TREF"]
    x = np.array([[p[f"{prefix}{n}_X{k}_{i}"] for k in range(4)] for i in range(3)])
    return (d[:, None] ** np.arange(4)) @ x.T


def _raw(path: Path, topic: str, instance: int) -> dict[str, np.ndarray]:
    from pyulog import ULog

    (data,) = [d.data for d in ULog(str(path), [topic]).data_list if d.multi_id == instance]
    return data


def _ours(path: Path, doc: dict, instance: int) -> tuple:
    """imupipe's corrected output of one instance: its table through the chain (each step on
    its own device)."""
    topic = "sensor_gyro" if instance == 0 else f"sensor_gyro_{instance}"
    table, _ = read_input(InputSpec(path=path, imu_topic=topic))
    chain = doc["chain"]
    corrected = apply_chain(table, on_device(steps_from_json(chain), chain))
    return table, corrected


def test_board_ulog_reads_back(tmp_path):
    """The simulated ULog: PX4 v1.11's formats, each instance with its device id, the log's
    CAL_* parameters in the slot order asked for."""
    from pyulog import ULog

    log, truth = simulate("board", {"duration_s": 30.0, "cal_order": SWAPPED}, seed=1)
    write_log(tmp_path / "b.ulg", log)
    u = ULog(str(tmp_path / "b.ulg"))
    found = {(d.name, d.multi_id): d.data for d in u.data_list}
    assert set(found) == {
        ("sensor_gyro", 0),
        ("sensor_gyro", 1),
        ("sensor_accel", 0),
        ("sensor_accel", 1),
        ("sensor_baro", 0),
    }
    ids = [imu["device_id"] for imu in truth["imus"]]
    assert found[("sensor_accel", 1)]["device_id"][0] == ids[1]
    assert u.initial_parameters["CAL_GYRO0_ID"] == ids[1]
    assert u.initial_parameters["CAL_ACC1_ZSCALE"] == pytest.approx(0.975)
    table, _ = read_input(InputSpec(path=tmp_path / "b.ulg", imu_topic="sensor_gyro_1"))
    from imupipe.readers.table import metadata

    assert metadata(table)["device_id"]["imu"] == ids[1]
    np.testing.assert_allclose(
        sensor(table, "gyro").values[:, 0], found[("sensor_gyro", 1)]["x"], rtol=1e-6
    )
    with pytest.raises(Exception, match="ulg"):
        write_log(tmp_path / "b.csv", log)


def test_every_imu_in_its_own_tc_slot(warm_up):
    """TC_G and TC_A of both devices, in the slots of the log's own CAL_*n_ID (the slots run
    opposite to the instances); the TC curves match the true thermal bias."""
    d, truth, _, px4, _, _ = warm_up
    assert px4["TC_G_ENABLE"] == 1 and px4["TC_A_ENABLE"] == 1
    for slot, imu in zip((1, 0), truth["imus"], strict=True):  # cal_order [1, 0]
        for prefix, key, tol in (("TC_G", "gyro_poly", GYRO_TOL), ("TC_A", "accel_poly", 1e-3)):
            assert _slot(px4, prefix, imu["device_id"]) == slot
            # TMIN/TMAX: the logged range of raw samples (PX4's script takes the same), not
            # the block means' narrower one, over which the curve would be flat at the ends
            np.testing.assert_allclose(
                px4_range(px4, prefix, slot), imu["temperature_range"], rtol=1e-6
            )
            temp = np.linspace(*px4_range(px4, prefix, slot), 50)
            true = np.array([np.polynomial.polynomial.polyval(temp - 25.0, c) for c in imu[key]])
            err = _px4_tc(px4, prefix, slot, temp) - true.T
            if prefix == "TC_A":  # the accel's constant is gravity's share: compare the shape
                err -= err.mean(axis=0)
            assert np.abs(err).max() < tol, (prefix, imu["device_id"], np.abs(err).max())


def px4_range(p: dict, prefix: str, n: int) -> tuple[float, float]:
    return p[f"{prefix}{n}_TMIN"], p[f"{prefix}{n}_TMAX"]


def test_temperature_only_file_keeps_the_vehicles_calibration(warm_up):
    """No stage fitted an offset or a scale: no CAL_ACC*/CAL_GYRO* line (the log's
    CAL_ACC1_ZSCALE = 0.975 survives loading), and the header names them as left alone."""
    _, _, _, px4, ardu, text = warm_up
    assert not [k for k in px4 if k.startswith(("CAL_ACC", "CAL_GYRO"))]
    assert "CAL_ACC1_*SCALE" in text and "leaves every other parameter" in text
    assert not [k for k in ardu if "OFFS" in k or "SCAL" in k or "CALTEMP" in k]
    assert {"INS_TCAL1_TMIN", "INS_TCAL2_TMIN", "INS_TCAL1_TMAX", "INS_TCAL2_TMAX"} <= set(ardu)
    header = (warm_up[0] / "out" / "ardupilot_calibration.param").read_text()
    assert "INS_ACC2SCAL_*" in header and "INS_ACC1_CALTEMP," in header


def test_px4_formula_reproduces_imupipe_for_both_devices(warm_up):
    """PX4's correction with the file, on each instance's raw samples, equals imupipe's
    corrected output of that instance (float32 parameters: 1e-6 relative)."""
    d, truth, doc, px4, _, _ = warm_up
    for instance, imu in enumerate(truth["imus"]):
        table, corrected = _ours(d / "board.ulg", doc, instance)
        temp = sensor(table, "temperature")
        for s, prefix in (("gyro", "TC_G"), ("accel", "TC_A")):
            raw = sensor(table, s)
            t = np.interp(raw.t_ns, temp.t_ns, temp.values[:, 0])
            n = _slot(px4, prefix, imu["device_id"])
            px4_out = raw.values - _px4_tc(px4, prefix, n, t)
            ours = sensor(corrected, s).values
            scale = 1e-4 if s == "gyro" else 1e-3
            np.testing.assert_allclose(px4_out, ours, atol=scale * 1e-2)


def test_ardupilot_formula_reproduces_imupipe_for_both_devices(warm_up):
    """ArduPilot's correct_sensor with INS_TCAL1 and INS_TCAL2 reproduces imupipe's correction
    of each IMU up to a constant (the vehicle's own offsets at its INS_*_CALTEMP, left alone)."""
    d, truth, doc, _, ardu, _ = warm_up
    for instance in range(2):
        table, corrected = _ours(d / "board.ulg", doc, instance)
        temp = sensor(table, "temperature")
        slot = instance + 1  # no ArduPilot ids in a PX4 log: IMU i is instance i - 1
        for s, short in (("gyro", "GYR"), ("accel", "ACC")):
            raw = sensor(table, s)
            t = np.interp(raw.t_ns, temp.t_ns, temp.values[:, 0])
            lo, hi = ardu[f"INS_TCAL{slot}_TMIN"], ardu[f"INS_TCAL{slot}_TMAX"]
            c = [[ardu[f"INS_TCAL{slot}_{short}{k}_{a}"] for k in (1, 2, 3)] for a in "XYZ"]
            dd = np.clip(t, lo, hi) - 35.0
            p = (dd[:, None] ** np.arange(1, 4)) @ (np.array(c) * 1e-6).T
            diff = (raw.values - p) - sensor(corrected, s).values
            assert np.abs(diff - diff.mean(axis=0)).max() < (1e-6 if s == "gyro" else 1e-5)


def test_px4s_script_agrees(warm_up, tmp_path):
    """PX4's Tools/process_sensor_caldata.py on the same log: the same TMIN/TMAX (the logged
    range of raw samples), and every TC curve of both devices within 0.05 mrad/s (gyro) and
    0.2 mm/s^2 (accel, temperature-driven part), the barometer's TC_B within 1 Pa, over PX4's
    whole TMIN..TMAX (each file applied with its own clamping, as the firmware does)."""
    script = os.environ.get("PX4_PROCESS_SENSOR_CALDATA")
    if not script or not Path(script).is_file():
        pytest.skip(
            "PX4's Tools/process_sensor_caldata.py not available: set "
            "PX4_PROCESS_SENSOR_CALDATA to its path (PX4-Autopilot, BSD-3)"
        )
    d, _, _, px4, _, _ = warm_up
    shutil.copy(d / "board.ulg", tmp_path / "board.ulg")
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, script, str(tmp_path / "board.ulg")],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    theirs = qgc_params((tmp_path / "board.ulg.params").read_text())
    for prefix, tol in (("TC_G", GYRO_TOL), ("TC_A", ACCEL_TOL)):
        for n in range(2):
            dev = theirs[f"{prefix}{n}_ID"]
            k = _slot(px4, prefix, dev)
            np.testing.assert_allclose(
                px4_range(px4, prefix, k), px4_range(theirs, prefix, n), rtol=1e-6
            )
            temp = np.linspace(*px4_range(theirs, prefix, n), 200)
            err = _px4_tc(px4, prefix, k, temp) - _px4_tc(theirs, prefix, n, temp)
            if prefix == "TC_A":
                err -= err.mean(axis=0)
            assert np.abs(err).max() < tol, (prefix, dev, np.abs(err).max())
    k = _slot(px4, "TC_B", theirs["TC_B0_ID"])
    np.testing.assert_allclose(px4_range(px4, "TC_B", k), px4_range(theirs, "TC_B", 0), rtol=1e-6)
    temp = np.linspace(*px4_range(theirs, "TC_B", 0), 200)

    def tc_b(p: dict, n: int) -> np.ndarray:
        x = np.clip(temp, p[f"TC_B{n}_TMIN"], p[f"TC_B{n}_TMAX"]) - p[f"TC_B{n}_TREF"]
        return np.polynomial.polynomial.polyval(x, [p[f"TC_B{n}_X{j}"] for j in range(6)])

    err = np.abs(tc_b(px4, k) - tc_b(theirs, 0)).max()
    assert err < BARO_TOL, err


# -- offsets of two devices ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def two_biases(tmp_path_factory):
    """Two gyro_bias stages, one per instance, on a board held at 30 degC."""
    d = tmp_path_factory.mktemp("biases")
    opts = {"duration_s": 120.0, "rate_hz": 50.0, "t_start": 30.0, "t_end": [30.0, 30.0]}
    log, truth = simulate("board", {**opts, "cal_order": SWAPPED}, seed=2)
    write_log(d / "board.ulg", log)
    doc, px4, ardu = _run(d, _stages("gyro_bias", ["gyro"]))
    return d, truth, doc, px4, ardu


def _true_bias(imu: dict, temp: float = 30.0) -> np.ndarray:
    return np.array([np.polynomial.polynomial.polyval(temp - 25.0, c) for c in imu["gyro_poly"]])


def test_each_cal_gyro_is_its_own_devices_bias(two_biases):
    """CAL_GYROn_*OFF is the bias of the device whose id CAL_GYROn_ID holds (not the sum of
    both, not fitted on data corrected by the other device's bias); ArduPilot's INS_GYROFFS and
    INS_GYR2OFFS likewise; no accelerometer line."""
    _, truth, doc, px4, ardu = two_biases
    assert [e["device"]["device_id"] for e in doc["chain"]] == [
        imu["device_id"] for imu in truth["imus"]
    ]
    for entry, imu in zip(doc["chain"], truth["imus"], strict=True):
        n = _slot(px4, "CAL_GYRO", imu["device_id"])
        assert n == SWAPPED[truth["imus"].index(imu)]
        off = [px4[f"CAL_GYRO{n}_{a}OFF"] for a in "XYZ"]
        assert off == pytest.approx(entry["offset"], rel=1e-12)
        np.testing.assert_allclose(off, _true_bias(imu), atol=2e-5)
        i = truth["imus"].index(imu)  # no ArduPilot ids in a PX4 log: slot = instance
        name = "INS_GYROFFS" if i == 0 else f"INS_GYR{i + 1}OFFS"
        assert [ardu[f"{name}_{a}"] for a in "XYZ"] == pytest.approx(entry["offset"])
    assert not [k for k in ardu if k.endswith("_ID")]  # PX4 ids are not ArduPilot's
    assert not [k for k in px4 if k.startswith(("CAL_ACC", "TC_"))]
    assert not [k for k in ardu if k.startswith(("INS_ACC", "INS_TCAL"))]


def test_complete_file_merges_the_logs_parameters(two_biases):
    """params = "complete": the log's CAL_* (CAL_ACC0_ZSCALE = 0.9795 of device 3670050 in
    slot 0) with the estimated gyro offsets in place."""
    d, truth, doc, _, _ = two_biases
    text = (d / "cfg.toml").read_text().replace('params = "estimated"', 'params = "complete"')
    (d / "complete").mkdir()
    (d / "complete" / "cfg.toml").write_text(text)
    shutil.copy(d / "board.ulg", d / "complete" / "board.ulg")
    _, px4, _ = _run(d / "complete", text.split("[output]")[0], params="complete")
    assert px4["CAL_ACC0_ZSCALE"] == pytest.approx(0.9795)
    assert px4["CAL_ACC0_ID"] == truth["imus"][1]["device_id"]
    assert px4["TC_G_ENABLE"] == 0  # the log's own, kept
    offset = doc["chain"][1]["offset"]
    assert [px4[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"] == pytest.approx(offset, rel=1e-6)


# -- exports from hand-made chains ---------------------------------------------------------------


def _dev(device_id: int | None, instance: int | None = None) -> dict:
    where: dict = {"format": "ulog" if instance is not None else "csv"}
    if device_id is not None:
        where["device_id"] = {"imu": device_id}
    if instance is not None:
        where["instance"] = {"imu": instance}
    return where


def _temperature(sensor_name: str, coef, lo: float, hi: float) -> TemperatureStep:
    return TemperatureStep(
        type="temperature",
        sensor=sensor_name,
        model="poly",
        tref=25.0,
        window=None,
        window_s=10.0,
        axes=[{"terms": ["1", "T", "T^2", "T^3"], "coefficients": np.array(c)} for c in coef],
        ranges={"T": [lo, hi], "dT": [-1.0, 1.0]},
    )


def _doc(steps_and_devices) -> dict:
    chain = []
    for step, where in steps_and_devices:
        chain.append({**step.to_json(), "fitted_on": where})
    return {"chain": chain, "results": {}}


COEF_A = [[0.05, 2e-3, -4e-5, 3e-7], [-0.08, -1e-3, 2e-5, 1e-7], [0.12, 3e-3, 1e-5, -2e-7]]
COEF_B = [[-0.02, 1e-3, 3e-5, -1e-7], [0.03, -2e-3, 1e-5, 2e-7], [0.01, 1e-3, -2e-5, 1e-7]]


def test_steps_of_two_devices_never_compose(tmp_path):
    """Accel calibration and temperature model on two devices: each device's file slot
    reproduces its own chain under PX4's and ArduPilot's formulas, the other device's steps
    play no part."""
    lin_a = LinearStep("accel_calibration", "accel", np.diag([1.01, 0.98, 1.02]), [0.1, -0.2, 0.05])
    lin_b = LinearStep("accel_calibration", "accel", np.diag([0.99, 1.03, 0.97]), [-0.3, 0.1, 0.2])
    a, b = _dev(111, 0), _dev(222, 1)
    for where in (a, b):  # an ArduPilot log's own ids: IMU 1 is device 222, IMU 2 is 111
        where["ardupilot"] = {"parameters": {"INS_ACC_ID": 222, "INS_ACC2_ID": 111}}
    doc = _doc(
        [
            (lin_a, a),
            (_temperature("accel", COEF_A, 5.0, 60.0), a),
            (_temperature("accel", COEF_B, 10.0, 50.0), b),
            (lin_b, b),
        ]
    )
    files, _ = export_all(doc, ["px4", "ardupilot"])
    px4 = qgc_params(files["px4_calibration.params"])
    (tmp_path / "ap.param").write_text(files["ardupilot_calibration.param"])
    ardu = mavparm(tmp_path / "ap.param")
    n = 400
    temp = np.linspace(0.0, 70.0, n)
    raw = np.random.default_rng(26).normal(size=(n, 3)) + [0, 0, 9.8]
    table = make_table(np.arange(n, dtype=np.int64) * 10**7, accel=raw, temperature=temp)
    for k, (dev, steps) in enumerate(((111, [0, 1]), (222, [2, 3]))):
        chain = [doc["chain"][i] for i in steps]
        ours = sensor(apply_chain(table, steps_from_json(chain)), "accel").values
        p = px4
        assert p[f"CAL_ACC{k}_ID"] == dev and p[f"TC_A{k}_ID"] == dev
        off = np.array([p[f"CAL_ACC{k}_{x}OFF"] for x in "XYZ"])
        scale = np.array([p[f"CAL_ACC{k}_{x}SCALE"] for x in "XYZ"])
        np.testing.assert_allclose(
            (raw - _px4_tc(p, "TC_A", k, temp) - off) * scale, ours, atol=1e-9
        )
        i = 2 - k  # the ArduPilot slots follow the log's INS_ACC*_ID
        s = "" if i == 1 else str(i)
        c = np.array([[ardu[f"INS_TCAL{i}_ACC{j}_{x}"] for j in (1, 2, 3)] for x in "XYZ"]) * 1e-6

        def poly(t, i=i, c=c):
            dd = np.clip(t, ardu[f"INS_TCAL{i}_TMIN"], ardu[f"INS_TCAL{i}_TMAX"]) - 35.0
            return (np.atleast_1d(dd)[:, None] ** np.arange(1, 4)) @ c.T

        tcal = poly(temp) - poly(np.array([ardu[f"INS_ACC{i}_CALTEMP"]]))
        off = np.array([ardu[f"INS_ACC{s}OFFS_{x}"] for x in "XYZ"])
        scal = np.array([ardu[f"INS_ACC{s}SCAL_{x}"] for x in "XYZ"])
        np.testing.assert_allclose((raw - tcal - off) * scal, ours, atol=1e-6)
        assert ardu[f"INS_ACC{s}_ID"] == dev


def test_shared_tcal_range_written_once_and_noted(tmp_path):
    """Accel and gyro of one IMU fitted over different ranges: INS_TCAL1_TMIN/TMAX once, the
    range both cover, with a note; ArduPilot's formula (temperature and CALTEMP clamped to it)
    reproduces imupipe's accel correction over that range."""
    d = _dev(111, 0)
    lin = LinearStep("accel_calibration", "accel", np.diag([1.01, 0.98, 1.02]), [0.1, -0.2, 0.05])
    doc = _doc(
        [
            (_temperature("accel", COEF_A, 5.0, 60.0), d),
            (lin, d),
            (_temperature("gyro", np.array(COEF_B) * 1e-2, 30.0, 55.0), d),
        ]
    )
    files, report = export_all(doc, ["ardupilot"])
    text = files["ardupilot_calibration.param"]
    lines = text.splitlines()
    assert [ln for ln in lines if ln.startswith("INS_TCAL1_TMIN")] == ["INS_TCAL1_TMIN,30.0"]
    assert [ln for ln in lines if ln.startswith("INS_TCAL1_TMAX")] == ["INS_TCAL1_TMAX,55.0"]
    notes = " ".join(report["ardupilot_calibration.param"]["notes"])
    assert "different temperatures" in notes
    (tmp_path / "ap.param").write_text(text)
    a = mavparm(tmp_path / "ap.param")
    assert 30.0 <= a["INS_ACC1_CALTEMP"] <= 55.0  # the accel's Tref, 25, clamped to the range
    n = 100
    temp = np.linspace(30.0, 55.0, n)
    raw = np.random.default_rng(3).normal(size=(n, 3)) + [0, 0, 9.8]
    table = make_table(np.arange(n, dtype=np.int64) * 10**7, accel=raw, temperature=temp)
    ours = sensor(apply_chain(table, steps_from_json(doc["chain"][:2])), "accel").values
    c = np.array([[a[f"INS_TCAL1_ACC{j}_{x}"] for j in (1, 2, 3)] for x in "XYZ"]) * 1e-6

    def poly(t):
        dd = np.clip(t, a["INS_TCAL1_TMIN"], a["INS_TCAL1_TMAX"]) - 35.0
        return (np.atleast_1d(dd)[:, None] ** np.arange(1, 4)) @ c.T

    tcal = poly(temp) - poly(np.array([a["INS_ACC1_CALTEMP"]]))
    off = np.array([a[f"INS_ACCOFFS_{x}"] for x in "XYZ"])
    scal = np.array([a[f"INS_ACCSCAL_{x}"] for x in "XYZ"])
    np.testing.assert_allclose((raw - tcal - off) * scal, ours, atol=1e-6)


def test_no_device_named_notes_the_tc_id():
    """A CSV input names no device: TC_A0_ID is not written, and the note says so."""
    doc = _doc([(_temperature("accel", COEF_A, 5.0, 60.0), _dev(None))])
    files, report = export_all(doc, ["px4"])
    p = qgc_params(files["px4_calibration.params"])
    assert "TC_A0_ID" not in p and "TC_A0_TREF" in p
    assert not [k for k in p if k.startswith("CAL_")]
    notes = " ".join(report["px4_calibration.params"]["notes"])
    assert "TC_A0_ID is not written" in notes


def test_compass_scale_and_second_compass():
    """Two magnetometers of an ArduPilot log: COMPASS_OFS/DIA/ODI and COMPASS_OFS2/DIA2/ODI2 by
    the log's COMPASS_DEV_ID*, each soft iron as COMPASS_SCALE* (its mean diagonal: ArduPilot
    multiplies by it) times DIA/ODI, as MagFit normalises them (before: SCALE 1, all in DIA)."""
    w = np.array([[1.1, 0.02, -0.01], [0.02, 0.95, 0.03], [-0.01, 0.03, 1.05]])
    m1 = LinearStep("mag_calibration", "mag", w, [12e-6, -30e-6, 8e-6])
    m2 = LinearStep("mag_calibration", "mag", np.eye(3) * 1.02, [1e-6, 2e-6, 3e-6])
    logged = {"parameters": {"COMPASS_DEV_ID": 666, "COMPASS_DEV_ID2": 555}}
    doc = _doc(
        [
            (m1, {"device_id": {"mag": 555}, "instance": {"mag": 0}, "ardupilot": logged}),
            (m2, {"device_id": {"mag": 666}, "instance": {"mag": 1}, "ardupilot": logged}),
        ]
    )
    files, _ = export_all(doc, ["ardupilot", "px4"])
    text = files["ardupilot_calibration.param"]
    rows = dict(line.split(",") for line in text.splitlines() if not line.startswith("#"))
    rows = {k: float(v) for k, v in rows.items()}
    scale2 = float(np.mean(np.diag(w)))
    assert rows["COMPASS_SCALE"] == pytest.approx(1.02) and rows["COMPASS_DIA_X"] == 1.0
    assert rows["COMPASS_SCALE2"] == pytest.approx(scale2)
    assert rows["COMPASS_DEV_ID"] == 666 and rows["COMPASS_DEV_ID2"] == 555
    assert rows["COMPASS_OFS_Z"] == pytest.approx(-3e-6 * 1e7)
    assert rows["COMPASS_DIA2_X"] == pytest.approx(1.1 / scale2)
    assert rows["COMPASS_ODI2_Z"] == pytest.approx(0.03 / scale2)
    p = qgc_params(files["px4_calibration.params"])
    assert p["CAL_MAG1_ID"] == 666 and p["CAL_MAG1_XSCALE"] == pytest.approx(1.02)


def test_convert_applies_each_devices_own_steps(two_biases, tmp_path):
    """imupipe convert of instance 1 with the two-device calibration: only device 1's bias is
    subtracted, and the provenance check (refuse) compares it only with device 1's entry."""
    d, truth, doc, _, _ = two_biases
    (tmp_path / "read.toml").write_text('imu_topic = "sensor_gyro_1"\n')
    proc = run_cli(
        "convert",
        d / "board.ulg",
        "--calibration",
        d / "out" / "calibration.json",
        "--config",
        tmp_path / "read.toml",
        "--out",
        tmp_path / "conv",
        "--on-mismatch",
        "refuse",
        "--jobs",
        "1",
        "--quiet",
    )
    assert proc.returncode == 0, proc.stderr
    raw, _ = read_input(InputSpec(path=d / "board.ulg", imu_topic="sensor_gyro_1"))
    out, _ = read_input(InputSpec(path=tmp_path / "conv" / "board.mcap"))
    (entry,) = [
        e for e in doc["chain"] if e["device"]["device_id"] == truth["imus"][1]["device_id"]
    ]
    np.testing.assert_allclose(
        sensor(out, "gyro").values, sensor(raw, "gyro").values - entry["offset"], atol=1e-12
    )


def test_mag_thermal_model_maps_to_tc_m():
    """A magnetometer temperature model: TC_M0_* in gauss (PX4's Magnetometer: raw - thermal
    - OFF, then the soft iron), with its id."""
    coef = np.array(COEF_B) * 1e-6  # tesla
    doc = _doc([(_temperature("mag", coef, 0.0, 40.0), {"device_id": {"mag": 777}})])
    files, report = export_all(doc, ["px4"])
    p = qgc_params(files["px4_calibration.params"])
    assert p["TC_M_ENABLE"] == 1 and p["TC_M0_ID"] == 777
    temp = np.linspace(-5.0, 45.0, 20)
    true = np.array(
        [np.polynomial.polynomial.polyval(np.clip(temp, 0, 40) - 25.0, c) for c in coef]
    )
    np.testing.assert_allclose(_px4_tc(p, "TC_M", 0, temp), true.T * 1e4, atol=1e-12)
    assert not [k for k in p if k.startswith("CAL_MAG")]


def test_a_step_naming_no_device_composes_with_every_device():
    """A step without a device (imported from another tool) applies to every device in run and
    convert, so each device's slot composes it: CAL_GYROn_*OFF = own bias + the common one."""
    common = LinearStep("import", "gyro", np.eye(3), [1e-3, 2e-3, 3e-3])
    b0 = LinearStep("gyro_bias", "gyro", np.eye(3), [1e-4, 0.0, 0.0])
    b1 = LinearStep("gyro_bias", "gyro", np.eye(3), [0.0, 1e-4, 0.0])
    doc = _doc([(b0, _dev(111, 0)), (common, {"format": "kalibr"}), (b1, _dev(222, 1))])
    files, _ = export_all(doc, ["px4"])
    p = qgc_params(files["px4_calibration.params"])
    assert [p[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"] == pytest.approx([1.1e-3, 2e-3, 3e-3])
    assert [p[f"CAL_GYRO1_{a}OFF"] for a in "XYZ"] == pytest.approx([1e-3, 2.1e-3, 3e-3])
    assert (p["CAL_GYRO0_ID"], p["CAL_GYRO1_ID"]) == (111, 222)


# -- magnetometers ------------------------------------------------------------------------------

MAGS = [396825, 396826]
"""Two magnetometers (``sensor_mag`` instances 0 and 1) on the board, each with its own thermal
offset and its own temperature, held in one orientation as in a thermal chamber."""
MAG_TOL = 2e-8
"""T: the TC_M curve against the simulated thermal offset (0.2 mG; the offsets drift by 1 to
2 uT over the warm-up, the noise is 0.1 uT per sample)."""
MAG_BODY = (
    '[inputs.board]\npath = "board.ulg"\ninstances = "all"\n'
    '[[stages]]\nname = "mag"\ntype = "temperature"\nsensor = "mag"\norder = 3\nrate_terms = []\n'
)


@pytest.fixture(scope="module")
def mag_board(tmp_path_factory):
    """The magnetometers' thermal calibration in one run (``instances = "all"``)."""
    d = tmp_path_factory.mktemp("mags")
    opts = {**WARM_UP, "mag_device_ids": MAGS, "mag_rate_hz": 5.0, "baro": False}
    log, truth = simulate("board", opts, seed=27)
    write_log(d / "board.ulg", log)
    doc, px4, _ = _run(d, MAG_BODY, ardupilot=False)  # ArduPilot has no compass thermal model
    return d, truth, doc, px4


def test_every_magnetometer_in_its_own_tc_m_slot(mag_board):
    """One ``temperature`` stage with sensor = "mag" runs on each magnetometer instance; its
    TC_M slot holds the device's id, TMIN/TMAX the logged range, X0 = 0 (zero at TREF, as PX4's
    own magnetometer calibration normalises it) and a curve that matches the simulated thermal
    offset relative to TREF, in gauss; no CAL_MAG line (nothing else was estimated)."""
    _, truth, doc, px4 = mag_board
    assert set(doc["results"]) == {"mag_sensor_mag", "mag_sensor_mag_1"}
    assert px4["TC_M_ENABLE"] == 1
    assert not [k for k in px4 if k.startswith(("CAL_", "TC_A", "TC_G"))]
    for mag in truth["mags"]:
        k = _slot(px4, "TC_M", mag["device_id"])
        assert k == mag["instance"]  # the log's CAL_MAGk_ID
        np.testing.assert_allclose(px4_range(px4, "TC_M", k), mag["temperature_range"], rtol=1e-6)
        assert [px4[f"TC_M{k}_X0_{i}"] for i in range(3)] == [0.0, 0.0, 0.0]
        temp = np.linspace(*px4_range(px4, "TC_M", k), 60)
        tref = px4[f"TC_M{k}_TREF"]

        def true(t, mag=mag):
            return np.array([np.polynomial.polynomial.polyval(t - 25.0, c) for c in mag["poly"]])

        expected = (true(temp) - true(np.array([tref]))).T * 1e4  # gauss
        err = np.abs(_px4_tc(px4, "TC_M", k, temp) - expected).max() * 1e-4
        assert err < MAG_TOL, (mag["device_id"], err)


def test_px4_formula_reproduces_imupipe_for_each_magnetometer(mag_board):
    """PX4's firmware (``TemperatureCompensation::update_offsets_mag``, calc_thermal_offsets_3D,
    subtracted from the raw field before the CAL_MAG offsets) with the file's TC_M, on each
    sensor_mag instance's raw gauss, equals imupipe's corrected output of that instance."""
    d, truth, doc, px4 = mag_board
    chain = doc["chain"]
    for mag in truth["mags"]:
        topic = "sensor_mag" if mag["instance"] == 0 else f"sensor_mag_{mag['instance']}"
        raw = _raw(d / "board.ulg", "sensor_mag", mag["instance"])
        gauss = np.column_stack([raw[a] for a in "xyz"]).astype(np.float64)
        k = _slot(px4, "TC_M", mag["device_id"])
        firmware = gauss - _px4_tc(px4, "TC_M", k, raw["temperature"].astype(np.float64))
        spec = InputSpec(
            path=d / "board.ulg", imu_topic="", mag_topic=topic, temperature_topic=topic
        )
        table, _ = read_input(spec)
        ours = sensor(apply_chain(table, on_device(steps_from_json(chain), chain)), "mag").values
        np.testing.assert_allclose(ours * 1e4, firmware, atol=1e-6)  # gauss, float32 params
        assert np.abs(ours * 1e4 - gauss).max() > 5e-3  # a correction of 0.5 uT or more


def test_a_turned_magnetometer_is_refused():
    """The field in the sensor's frame turns with it: a magnetometer turned by 30 degrees
    between its still periods fails the orientation check (its corrected field's direction),
    named as such; the same log held still fits."""
    from imupipe.pipeline.errors import FitError
    from imupipe.stages.base import StageContext
    from imupipe.stages.thermal.temperature import TemperatureStage

    rng = np.random.default_rng(5)
    t = np.arange(0.0, 2700.0, 0.5)
    temp = 48.0 - 43.0 * np.exp(-t / 700.0)
    field = np.array([2.0e-5, 3.0e-6, 4.5e-5])
    drift = np.outer(temp - 25.0, [3e-8, -2e-8, 5e-8])
    noise = rng.normal(size=(len(t), 3)) * 1e-7
    a = np.radians(30.0) * np.clip((t - 1350.0) / 10.0, 0.0, 1.0)  # turned by hand in 10 s
    turned = np.column_stack(
        [np.cos(a) * field[0] - np.sin(a) * field[1], np.sin(a) * field[0] + np.cos(a) * field[1]]
    )
    turned = np.column_stack([turned, np.full(len(t), field[2])])
    stamps = (t * 1e9).astype(np.int64)

    def fit(values):
        table = make_table(stamps, mag=values, temperature=temp)
        stage = TemperatureStage(TemperatureStage.Options(sensor="mag", order=3, rate_terms=[]))
        ctx = StageContext(name="mag", input_name="fit", tables={}, quiet=True)
        return stage.fit(table, ctx)

    out = fit(field + drift + noise)
    assert out.step.sensor == "mag" and out.results["unit"] == "T"
    with pytest.raises(FitError, match="the magnetometer was turned between its still periods"):
        fit(turned + drift + noise)
