"""ArduPilot from DataFlash logs (issue 26): the ArduPilot parameter file by default, slots by
the log's own ``INS_*_ID``, and ``INS_TCAL*`` from a DataFlash thermal log within ArduPilot's
model.

ArduPilot logs its IMUs *corrected* (``AP_InertialSensor_Backend.cpp``,
``_rotate_and_correct_accel``/``_gyro``): ``IMU = S (raw - tcal(T) - OFFS)`` with ``S`` the
``INS_ACC*SCAL`` (identity for the gyro), ``tcal`` zero while ``INS_TCALi_ENABLE = 0``, and
the board rotation (``AHRS_ORIENTATION = 0`` here). ``AP_InertialSensor_tempcal.cpp``
``correct_sensor``: ``tcal(T) = p(T - 35) - p(CALTEMP - 35)``, ``p(d) = 1e-6 (c1 d + c2 d^2 +
c3 d^3)``, T clamped to ``INS_TCALi_TMIN..TMAX``.

The log is written here with ``struct`` in ArduPilot 4.x's formats (``IMU`` with an instance
field ``I``, ``PARM``; :mod:`test_dataflash_reader`): two IMUs warming up at rest for 45 min
(2 Hz), each with its own thermal bias (the ``board`` scenario's), offsets and an accelerometer
scale in the log's parameters, and ids ``INS_ACC_ID`` ... ``INS_GYR2_ID``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_dataflash_reader import MESSAGES, _record
from test_exports import mavparm

from imupipe.pipeline.calibration_file import on_device
from imupipe.pipeline.simulate.board import DEFAULTS, warm_up
from imupipe.readers.dispatch import read_input
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import sensor
from imupipe.stages.steps import apply_chain, steps_from_json

from conftest import run_cli

IDS = {"INS_ACC_ID": 1442082, "INS_ACC2_ID": 1114634, "INS_GYR_ID": 2163722, "INS_GYR2_ID": 2228490}
PARAMS = {
    **IDS,
    "INS_GYROFFS_X": 0.01,
    "INS_GYROFFS_Y": -0.02,
    "INS_GYROFFS_Z": 0.005,
    "INS_GYR2OFFS_X": -0.004,
    "INS_GYR2OFFS_Y": 0.003,
    "INS_GYR2OFFS_Z": 0.002,
    "INS_ACCOFFS_X": 0.1,
    "INS_ACCOFFS_Y": -0.05,
    "INS_ACCOFFS_Z": 0.2,
    "INS_ACCSCAL_X": 1.0,
    "INS_ACCSCAL_Y": 1.01,
    "INS_ACCSCAL_Z": 0.98,
    "INS_ACC2OFFS_X": 0.0,
    "INS_ACC2OFFS_Y": 0.0,
    "INS_ACC2OFFS_Z": 0.0,
    "INS_ACC2SCAL_X": 1.0,
    "INS_ACC2SCAL_Y": 1.0,
    "INS_ACC2SCAL_Z": 1.0,
    "INS_TCAL1_ENABLE": 0.0,
    "INS_TCAL2_ENABLE": 0.0,
    "AHRS_ORIENTATION": 0.0,
}
RATE_HZ, DURATION_S = 2.0, 2700.0
GYRO_TOL = 0.05e-3
"""rad/s: the INS_TCAL curves against the true thermal bias (shape), as the PX4 test's."""
ACCEL_TOL = 1e-3


def _poly(coefs, x: np.ndarray) -> np.ndarray:
    c = np.asarray(coefs, dtype=np.float64).reshape(3, 4)
    return (x[:, None] ** np.arange(4)) @ c.T


def write_warm_up(path: Path, seed: int = 3) -> dict:
    """Two IMUs warming up (the board scenario's temperatures and thermal biases), logged as
    ArduPilot logs them (corrected with PARAMS); returns the truth in the sensor's raw domain."""
    rng = np.random.default_rng(seed)
    fmts = {name: (t, f) for t, name, f, _ in MESSAGES}
    out = bytearray()
    out += _record(128, "BBnNZ", (128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns"))
    for t, name, f, cols in MESSAGES:
        length = 3 + len(_record(0, f, _zeros(f))) - 3
        out += _record(128, "BBnNZ", (t, length, name.encode(), f.encode(), cols.encode()))
    for name, value in PARAMS.items():
        out += _record(fmts["PARM"][0], "QNf", (1_000_000, name.encode(), float(value)))
    t_s = np.arange(int(DURATION_S * RATE_HZ) + 1) / RATE_HZ
    n = len(t_s)
    truth = {"imus": []}
    logged = []
    for i in (0, 1):
        temp = warm_up(t_s, DEFAULTS["t_start"], DEFAULTS["t_end"][i], DEFAULTS["tau_s"][i])
        x = temp - DEFAULTS["tref"]
        gyro_raw = _poly(DEFAULTS["gyro_poly"][i], x) + rng.normal(0, 2e-4, (n, 3))
        accel_raw = _poly(DEFAULTS["accel_poly"][i], x) + [0.0, 0.0, -9.80665]
        accel_raw = accel_raw + rng.normal(0, 3e-3, (n, 3))
        s = "" if i == 0 else "2"
        g_off = np.array(
            [PARAMS[f"INS_GYR{s}OFFS_{a}" if i else f"INS_GYROFFS_{a}"] for a in "XYZ"]
        )
        a_off = np.array([PARAMS[f"INS_ACC{s}OFFS_{a}"] for a in "XYZ"])
        scale = np.array([PARAMS[f"INS_ACC{s}SCAL_{a}"] for a in "XYZ"])
        logged.append((gyro_raw - g_off, (accel_raw - a_off) * scale, temp))
        truth["imus"].append(
            {"gyro_poly": DEFAULTS["gyro_poly"][i], "accel_poly": DEFAULTS["accel_poly"][i]}
        )
    stamps = 2_000_000 + np.round(t_s * 1e6).astype(np.int64)
    for k in range(n):
        for i in (0, 1):
            g, a, temp = (v[k] for v in logged[i])
            vals = (int(stamps[k]) + 100 * i, i, *g, *a, 0, 0, float(temp), 1, 1, 400, 400)
            out += _record(fmts["IMU"][0], MESSAGES[0][2], vals)
    path.write_bytes(bytes(out))
    truth["t_s"] = t_s
    return truth


def _zeros(fmt: str) -> tuple:
    return tuple(b"" if c in "nNZ" else 0 for c in fmt)


def _run(d: Path, name: str, stages: str) -> tuple[dict, Path]:
    (d / f"{name}.toml").write_text(
        '[inputs.fc]\npath = "warm.bin"\ninstances = "all"\n'
        + stages
        + f'[output]\ndir = "{name}"\napply_to = []\nrerun = false\nreport = false\n'
    )
    proc = run_cli("run", d / f"{name}.toml", "--quiet", cwd=d)
    assert proc.returncode == 0, proc.stderr
    return json.loads((d / name / "calibration.json").read_text()), d / name


@pytest.fixture(scope="module")
def thermal(tmp_path_factory):
    d = tmp_path_factory.mktemp("apwarm")
    truth = write_warm_up(d / "warm.bin")
    stages = ""
    for s in ("gyro", "accel"):
        stages += f'[[stages]]\ntype = "temperature"\nsensor = "{s}"\norder = 3\nrate_terms = []\n'
    doc, out = _run(d, "thermal", stages)
    return d, truth, doc, out


def _tcal(p: dict, i: int, short: str, temp: np.ndarray, caltemp: float) -> np.ndarray:
    """ArduPilot's correct_sensor offset (m, 3)."""
    c = np.array([[p[f"INS_TCAL{i}_{short}{k}_{a}"] for k in (1, 2, 3)] for a in "XYZ"]) * 1e-6

    def poly(t):
        d = np.clip(np.atleast_1d(t), p[f"INS_TCAL{i}_TMIN"], p[f"INS_TCAL{i}_TMAX"]) - 35.0
        return (d[:, None] ** np.arange(1, 4)) @ c.T

    return poly(temp) - poly(caltemp)


def test_ardupilot_file_by_default_not_px4(thermal):
    """A chain fitted on a DataFlash log: the ArduPilot file is written without being asked
    for, PX4's is not."""
    _, _, doc, out = thermal
    assert (out / "ardupilot_calibration.param").is_file()
    assert not (out / "px4_calibration.params").exists()
    devices = sorted(e["device"]["device_id"] for e in doc["chain"])
    assert devices == sorted(IDS.values())  # each entry names its ArduPilot device


def test_ins_tcal_reproduces_imupipe_and_the_truth(thermal):
    """ArduPilot's correct_sensor with INS_TCAL1/2, on the raw sensor data (the vehicle's own
    offsets and scale, left alone), reproduces imupipe's correction of the logged data up to a
    constant, and the curves match the true raw-domain thermal bias's shape."""
    d, truth, doc, out = thermal
    p = mavparm(out / "ardupilot_calibration.param")
    assert not [k for k in p if "OFFS" in k or "SCAL" in k or k.endswith("_ID")]
    for inst, key in enumerate(("IMU", "IMU_1")):
        table, _ = read_input(InputSpec(path=d / "warm.bin", imu_topic=key, mag_topic=""))
        ours = apply_chain(table, on_device(steps_from_json(doc["chain"]), doc["chain"]))
        temp = sensor(table, "temperature").values[:, 0]
        i, s = inst + 1, "" if inst == 0 else "2"
        lo, hi = p[f"INS_TCAL{i}_TMIN"], p[f"INS_TCAL{i}_TMAX"]
        grid = np.linspace(lo, hi, 60)
        for name, short, tol in (("gyro", "GYR", GYRO_TOL), ("accel", "ACC", ACCEL_TOL)):
            logged = sensor(table, name).values
            if name == "gyro":
                off = np.array(
                    [PARAMS[f"INS_GYR{s}OFFS_{a}" if inst else f"INS_GYROFFS_{a}"] for a in "XYZ"]
                )
                scale = np.ones(3)
            else:
                off = np.array([PARAMS[f"INS_ACC{s}OFFS_{a}"] for a in "XYZ"])
                scale = np.array([PARAMS[f"INS_ACC{s}SCAL_{a}"] for a in "XYZ"])
            raw = logged / scale + off  # the sensor's raw data (float32 in the log)
            ap = (raw - _tcal(p, i, short, temp, 25.0) - off) * scale
            diff = ap - sensor(ours, name).values
            assert np.abs(diff - diff.mean(axis=0)).max() < tol / 10, (name, inst)
            true = _poly(truth["imus"][inst][f"{name}_poly"], grid - DEFAULTS["tref"])
            err = _tcal(p, i, short, grid, 25.0) - true
            err -= err.mean(axis=0)
            assert np.abs(err).max() < tol, (name, inst, np.abs(err).max())


def test_offsets_compose_with_the_logs_in_their_id_slots(thermal):
    """gyro_bias over the first minute of each IMU: INS_GYROFFS/INS_GYR2OFFS are the log's own
    offsets plus the bias fitted on ArduPilot's corrected data (the raw bias), each in the slot
    of its INS_GYR*_ID, with the id written."""
    d, truth, _, _ = thermal
    doc, out = _run(d, "bias", '[[stages]]\ntype = "gyro_bias"\ninterval = [0.0, 60.0]\n')
    p = mavparm(out / "ardupilot_calibration.param")
    assert (p["INS_GYR_ID"], p["INS_GYR2_ID"]) == (IDS["INS_GYR_ID"], IDS["INS_GYR2_ID"])
    t = truth["t_s"]
    for inst, name in enumerate(("INS_GYROFFS", "INS_GYR2OFFS")):
        temp = warm_up(t, DEFAULTS["t_start"], DEFAULTS["t_end"][inst], DEFAULTS["tau_s"][inst])
        first = temp[t <= 60.0] - DEFAULTS["tref"]
        raw_bias = _poly(truth["imus"][inst]["gyro_poly"], first).mean(axis=0)
        got = np.array([p[f"{name}_{a}"] for a in "XYZ"])
        np.testing.assert_allclose(got, raw_bias, atol=6e-5)
    assert not [k for k in p if k.startswith("INS_ACC")]
