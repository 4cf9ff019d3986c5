"""Issue 16: the files other tools read, each read back with the consumer's own parser where one
installs (PyYAML for Kalibr, OpenCV's FileStorage for OpenVINS and VINS, pymavlink's
``MAVParmDict`` for ArduPilot; PX4's ``.params`` with the rules of QGroundControl's parameter
file: ``#`` comments, tab-separated ``vehicle component name value type``), and each checked
numerically: the consumer's own correction equation, applied to raw samples with the numbers
read back, must give imupipe's corrected samples.

Equations (cited in each exporter's docstring): Kalibr ``a_m = M_a a + b``, ``w_m = M_g C_gyro_i
w + b``; OpenVINS ``w = R_IMUtoGYRO^T Tw^-1 (w_m - b)``, ``a = R_IMUtoACC^T Ta^-1 (a_m - b)``;
PX4 ``(raw - thermal(T) - OFF) * SCALE`` with a clamped cubic about ``TC_*_TREF``; ArduPilot
``(raw - (p(T - 35) - p(CALTEMP - 35)) - OFFS) * SCAL`` with ``p`` the ``INS_TCAL`` cubic /
1e6, compass ``W (raw + OFS)`` in milligauss.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from imupipe.pipeline.exports import export_all
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.table import make_table, sensor
from imupipe.stages.steps import LinearStep, steps_from_json
from imupipe.stages.thermal.step import TemperatureStep

from conftest import TEST_DATA, run_cli

RNG = np.random.default_rng(16)


def qgc_params(text: str) -> dict[str, float]:
    """A QGroundControl ``.params`` file: ``#`` lines are comments, rows are tab-separated
    ``vehicle-id component-id name value type`` (type 6 INT32, 9 REAL32)."""
    out = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        vid, cid, name, value, kind = line.split("\t")
        assert (vid, cid) == ("1", "1") and kind in ("6", "9") and len(name) <= 16
        out[name] = int(value) if kind == "6" else float(value)
    return out


def mavparm(path) -> dict[str, float]:
    from pymavlink.mavparm import MAVParmDict

    params = MAVParmDict()
    assert params.load(str(path))
    assert all(len(k) <= 16 for k in params)  # MAVLink parameter ids
    return dict(params)


def opencv_yaml(path, keys: list[str], node: str | None = None) -> dict[str, np.ndarray]:
    cv2 = pytest.importorskip("cv2")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    root = fs.getNode(node) if node else fs.root()
    out = {}
    for k in keys:
        n = root.getNode(k)
        assert not n.empty(), k
        if n.isSeq():  # OpenVINS writes matrices as a sequence of rows
            out[k] = np.array(
                [[n.at(i).at(j).real() for j in range(n.at(i).size())] for i in range(n.size())]
            )
        elif n.isString():
            out[k] = n.string()
        else:
            out[k] = n.real()
    fs.release()
    return out


# -- one run end to end: allan + accel_calibration + gyro_calibration on simulated logs ----------


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    d = tmp_path_factory.mktemp("exports")
    static, _ = simulate("static", {"duration_s": 400.0, "rate_hz": 100.0}, seed=3)
    write_log(d / "static.csv", static)
    poses, truth = simulate("poses", seed=11)
    write_log(d / "poses.csv", poses)
    (d / "cfg.toml").write_text(
        '[inputs.static]\npath = "static.csv"\n[inputs.poses]\npath = "poses.csv"\n\n'
        '[[stages]]\ntype = "allan"\ninput = "static"\ntaus = "octave"\n\n'
        '[[stages]]\ntype = "accel_calibration"\ninput = "poses"\n\n'
        '[[stages]]\ntype = "gyro_calibration"\ninput = "poses"\n\n'
        '[output]\ndir = "out"\napply_to = []\nrerun = false\nreport = false\n'
        'exports = ["kalibr", "imu_utils", "vins", "openvins", "px4", "ardupilot"]\n'
    )
    proc = run_cli("run", d / "cfg.toml")
    assert proc.returncode == 0, proc.stderr
    out = d / "out"
    doc = json.loads((out / "calibration.json").read_text())
    return out, doc, poses, proc.stderr


def _chain(doc, s):
    return [e for e in doc["chain"] if e["sensor"] == s]


def test_files_written_when_their_stages_ran(calibrated):
    out, doc, _, _ = calibrated
    names = {p.name for p in out.iterdir()}
    assert {
        "imu.yaml",
        "allan_imu_utils.yaml",
        "vins_imu.yaml",
        "kalibr_imu_intrinsics.yaml",
        "kalibr_imu_chain.yaml",
        "px4_calibration.params",
        "ardupilot_calibration.param",
    } <= names
    # provenance: every chain entry and stage says where it was fitted
    for entry in doc["chain"]:
        where = entry["fitted_on"]
        assert where["input"] == "poses" and where["format"] == "csv"
        assert where["path"].endswith("poses.csv")
        assert where["rate_hz"]["imu"] == pytest.approx(100.0, rel=1e-3)
        assert where["t_end_ns"] > where["t_start_ns"]
    assert doc["results"]["allan"]["fitted_on"]["input"] == "static"
    assert "kalibr_imu_intrinsics.yaml" in doc["exports"]


def test_autopilot_files_only_when_asked_or_fitted_on_a_px4_log(calibrated, tmp_path):
    """By default the ROS and VIO tools' files are written; PX4's only for a step fitted on a
    PX4 log, ArduPilot's only when asked; Kalibr's imu.yaml whenever an allan stage ran."""
    out, *_ = calibrated
    cfg = (out.parent / "cfg.toml").read_text()
    default = cfg.replace(
        'exports = ["kalibr", "imu_utils", "vins", "openvins", "px4", "ardupilot"]\n', ""
    )
    (out.parent / "default.toml").write_text(default.replace('dir = "out"', 'dir = "out_default"'))
    none = cfg.replace(
        'exports = ["kalibr", "imu_utils", "vins", "openvins", "px4", "ardupilot"]', "exports = []"
    )
    (out.parent / "none.toml").write_text(none.replace('dir = "out"', 'dir = "out_none"'))
    for name in ("default", "none"):
        proc = run_cli("run", out.parent / f"{name}.toml", "--quiet")
        assert proc.returncode == 0, proc.stderr
    names = {p.name for p in (out.parent / "out_default").iterdir()}
    assert {"imu.yaml", "kalibr_imu_chain.yaml", "vins_imu.yaml"} <= names
    assert not names & {"px4_calibration.params", "ardupilot_calibration.param"}
    names = {p.name for p in (out.parent / "out_none").iterdir()}
    assert "imu.yaml" in names and "vins_imu.yaml" not in names
    doc, px4_out = _run(tmp_path, SMALL, imu_topic="sensor_gyro_2")
    assert (px4_out / "px4_calibration.params").exists()
    assert not (px4_out / "ardupilot_calibration.param").exists()


def test_kalibr_intrinsics_reproduce_the_chain(calibrated):
    out, doc, poses, _ = calibrated
    imu = yaml.safe_load((out / "kalibr_imu_intrinsics.yaml").read_text())["imu0"]
    assert imu["model"] == "scale-misalignment"
    m_a = np.array(imu["accelerometers"]["M"])
    m_g = np.array(imu["gyroscopes"]["M"])
    c = np.array(imu["gyroscopes"]["C_gyro_i"])
    assert np.allclose(np.triu(m_a, 1), 0) and np.allclose(np.triu(m_g, 1), 0)  # Kalibr's masks
    assert np.allclose(c @ c.T, np.eye(3)) and np.linalg.det(c) == pytest.approx(1.0)
    r = np.array(doc["exports"]["kalibr_imu_intrinsics.yaml"]["R_kalibr_from_imupipe"])
    steps = steps_from_json(doc["chain"])
    from imupipe.stages.steps import apply_chain

    corrected = apply_chain(poses, steps)
    for s, m in (("accel", m_a), ("gyro", m_g @ c)):
        offset = sum(np.asarray(e["offset"]) for e in _chain(doc, s)) if s == "gyro" else None
        raw = sensor(poses, s).values
        ours = sensor(corrected, s).values @ r.T  # imupipe's corrected frame -> Kalibr's
        bias = raw - ours @ m.T  # Kalibr: raw = M x + b, b constant (the fitted offset)
        assert np.ptp(bias, axis=0).max() < 1e-9 * np.abs(raw).max()
        if offset is not None:
            assert np.allclose(bias[0], _chain(doc, s)[0]["offset"])
    assert imu["accelerometer_noise_density"] > 0 and imu["rostopic"] == "/imu/data"


def test_openvins_file_reads_in_opencv_and_matches_kalibr(calibrated):
    out, _, _, _ = calibrated
    keys = ["Tw", "R_IMUtoGYRO", "Ta", "R_IMUtoACC", "Tg", "model", "gyroscope_noise_density"]
    ov = opencv_yaml(out / "kalibr_imu_chain.yaml", keys, node="imu0")
    kalibr = yaml.safe_load((out / "kalibr_imu_intrinsics.yaml").read_text())["imu0"]
    # OpenVINS 'kalibr' model: Tw = M_g, R_IMUtoGYRO = C_gyro_i, Ta = M_a, R_IMUtoACC = I
    assert ov["model"] == "kalibr"
    assert np.allclose(ov["Tw"], kalibr["gyroscopes"]["M"])
    assert np.allclose(ov["R_IMUtoGYRO"], kalibr["gyroscopes"]["C_gyro_i"])
    assert np.allclose(ov["Ta"], kalibr["accelerometers"]["M"])
    assert np.allclose(ov["R_IMUtoACC"], np.eye(3)) and np.allclose(ov["Tg"], 0)
    # OpenVINS keeps the lower triangle of Dw = Tw^-1: nothing above it may be lost
    assert np.allclose(np.triu(np.linalg.inv(ov["Tw"]), 1), 0)
    assert ov["gyroscope_noise_density"] == pytest.approx(kalibr["gyroscope_noise_density"])


def test_vins_and_imu_yaml_read_back(calibrated):
    out, doc, _, _ = calibrated
    vins = opencv_yaml(
        out / "vins_imu.yaml", ["acc_n", "gyr_n", "acc_w", "gyr_w", "g_norm", "imu_topic"]
    )
    kalibr = yaml.safe_load((out / "imu.yaml").read_text())
    assert vins["gyr_n"] == pytest.approx(kalibr["gyroscope_noise_density"])
    assert vins["acc_w"] == pytest.approx(kalibr["accelerometer_random_walk"])
    assert vins["g_norm"] == pytest.approx(9.80665)
    res = doc["results"]["allan"]
    assert kalibr["gyroscope_noise_density"] == max(res["gyro"][a]["N"] for a in "xyz")
    assert set(kalibr) == {
        "accelerometer_noise_density",
        "accelerometer_random_walk",
        "gyroscope_noise_density",
        "gyroscope_random_walk",
        "rostopic",
        "update_rate",
    }
    utils = opencv_yaml(out / "allan_imu_utils.yaml", ["type"])
    assert utils["type"] == "IMU"


def test_autopilot_files_drop_misalignment_with_a_note(calibrated):
    out, doc, _, stderr = calibrated
    px4 = qgc_params((out / "px4_calibration.params").read_text())
    accel = _chain(doc, "accel")[0]
    assert [px4[f"CAL_ACC0_{a}OFF"] for a in "XYZ"] == pytest.approx(accel["offset"])
    assert [px4[f"CAL_ACC0_{a}SCALE"] for a in "XYZ"] == pytest.approx(np.diag(accel["matrix"]))
    assert "CAL_ACC0_ID" not in px4  # a CSV names no PX4 device
    notes = " ".join(doc["exports"]["px4_calibration.params"]["notes"])
    assert "no misalignment terms" in notes and "CAL_ACC0_ID is not written" in notes
    assert "no gyro scale" in notes
    assert "[exports] " in stderr and "px4_calibration.params" in stderr
    ap = mavparm(out / "ardupilot_calibration.param")
    assert [ap[f"INS_ACCOFFS_{a}"] for a in "XYZ"] == pytest.approx(accel["offset"])
    assert [ap[f"INS_GYROFFS_{a}"] for a in "XYZ"] == pytest.approx(
        _chain(doc, "gyro")[0]["offset"]
    )


# -- thermal and magnetometer mappings, checked against the consumers' equations ----------------


def _thermal_doc(linear_first: bool):
    coef = [[0.05, 2e-3, -4e-5, 3e-7], [-0.08, -1e-3, 2e-5, 1e-7], [0.12, 3e-3, 1e-5, -2e-7]]
    temp = TemperatureStep(
        type="temperature",
        sensor="accel",
        model="poly",
        tref=25.0,
        window=None,
        window_s=10.0,
        axes=[{"terms": ["1", "T", "T^2", "T^3"], "coefficients": np.array(c)} for c in coef],
        ranges={"T": [5.0, 60.0], "dT": [-1.0, 1.0]},
    )
    lin = LinearStep("accel_calibration", "accel", np.diag([1.01, 0.98, 1.02]), [0.1, -0.2, 0.05])
    chain = [lin, temp] if linear_first else [temp, lin]
    return {"chain": [s.to_json() for s in chain], "results": {}}


def _table(n=400):
    t = np.arange(n, dtype=np.int64) * 10_000_000
    temp = np.linspace(0.0, 70.0, n)  # past both ends of the fitted range: clamped alike
    accel = RNG.normal(size=(n, 3)) + [0, 0, 9.8]
    return make_table(t, gyro=np.zeros((n, 3)), accel=accel, temperature=temp), accel, temp


@pytest.mark.parametrize("linear_first", [False, True])
def test_px4_and_ardupilot_thermal_equations(tmp_path, linear_first):
    doc = _thermal_doc(linear_first)
    table, raw, temp = _table()
    from imupipe.stages.steps import apply_chain

    ours = sensor(apply_chain(table, steps_from_json(doc["chain"])), "accel").values
    files, report = export_all(doc)
    p = qgc_params(files["px4_calibration.params"])
    assert p["TC_A_ENABLE"] == 1
    d = np.clip(temp, p["TC_A0_TMIN"], p["TC_A0_TMAX"]) - p["TC_A0_TREF"]
    x = np.array([[p[f"TC_A0_X{k}_{i}"] for k in range(4)] for i in range(3)])
    thermal = (d[:, None] ** np.arange(4)) @ x.T
    off = np.array([p[f"CAL_ACC0_{a}OFF"] for a in "XYZ"])
    scale = np.array([p[f"CAL_ACC0_{a}SCALE"] for a in "XYZ"])
    np.testing.assert_allclose((raw - thermal - off) * scale, ours, atol=1e-9)
    (tmp_path / "ap.param").write_text(files["ardupilot_calibration.param"])
    a = mavparm(tmp_path / "ap.param")
    lo, hi = a["INS_TCAL1_TMIN"], a["INS_TCAL1_TMAX"]
    c = np.array([[a[f"INS_TCAL1_ACC{k}_{ax}"] for k in (1, 2, 3)] for ax in "XYZ"]) * 1e-6

    def poly(t):
        dd = np.clip(t, lo, hi) - 35.0
        return (np.atleast_1d(dd)[:, None] ** np.arange(1, 4)) @ c.T

    tcal = poly(temp) - poly(np.array([a["INS_ACC1_CALTEMP"]]))
    off = np.array([a[f"INS_ACCOFFS_{ax}"] for ax in "XYZ"])
    scal = np.array([a[f"INS_ACCSCAL_{ax}"] for ax in "XYZ"])
    np.testing.assert_allclose((raw - tcal - off) * scal, ours, atol=1e-6)
    assert "ardupilot_calibration.param" in report  # the temperature source is noted


def test_rate_terms_do_not_map():
    doc = _thermal_doc(False)
    doc["chain"][0]["axes"][0]["terms"][3] = "dT"
    files, report = export_all(doc)
    assert "TC_A0_TREF" not in files["px4_calibration.params"]
    assert any("dT" in n for n in report["px4_calibration.params"]["notes"])


def test_mag_soft_iron_both_autopilots(tmp_path):
    w = np.array([[1.1, 0.02, -0.01], [0.02, 0.95, 0.03], [-0.01, 0.03, 1.05]])
    hard = np.array([12e-6, -30e-6, 8e-6])  # tesla
    doc = {"chain": [LinearStep("mag_calibration", "mag", w, hard).to_json()], "results": {}}
    files, _ = export_all(doc)
    raw = RNG.normal(size=(50, 3)) * 40e-6
    ours = (raw - hard) @ w.T
    p = qgc_params(files["px4_calibration.params"])
    s = np.diag([p[f"CAL_MAG0_{a}SCALE"] for a in "XYZ"])
    for (i, j), a in zip(((0, 1), (0, 2), (1, 2)), "XYZ", strict=True):
        s[i, j] = s[j, i] = p[f"CAL_MAG0_{a}ODIAG"]
    off_gauss = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    np.testing.assert_allclose((raw * 1e4 - off_gauss) @ s.T, ours * 1e4, atol=1e-12)
    (tmp_path / "ap.param").write_text(files["ardupilot_calibration.param"])
    a = mavparm(tmp_path / "ap.param")
    ofs = np.array([a[f"COMPASS_OFS_{x}"] for x in "XYZ"])
    dia = [a[f"COMPASS_DIA_{x}"] for x in "XYZ"]
    odi = [a[f"COMPASS_ODI_{x}"] for x in "XYZ"]
    m = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    m = m * a["COMPASS_SCALE"]  # correct_field: (raw + OFS) x COMPASS_SCALE, then DIA/ODI
    np.testing.assert_allclose((raw * 1e7 + ofs) @ m.T, ours * 1e7, atol=1e-9)


def test_topic_with_a_newline_injects_no_key():
    """imu.yaml's rostopic comes from the log; a hostile topic name stays one string."""
    res = {
        "type": "allan",
        "input": "x",
        "gyro": {a: {"N": 1e-4, "K": 1e-6, "B": 1e-5, "Q": 0, "R": 0} for a in "xyz"},
        "accel": {a: {"N": 1e-3, "K": 1e-5, "B": 1e-4, "Q": 0, "R": 0} for a in "xyz"},
        "metrics": {"rate_hz": 200.0, "fit_kind": "oadev"},
        "fitted_on": {"topics": {"imu": '/imu\nupdate_rate: 1\n"evil": [1'}},
    }
    files, _ = export_all({"chain": [], "results": {"allan": res}})
    for name in ("imu.yaml", "vins_imu.yaml", "kalibr_imu_chain.yaml"):
        text = files[name].replace("%YAML:1.0", "")
        doc = yaml.safe_load(text)
        block = doc.get("imu0", doc)
        topic = block.get("rostopic", block.get("imu_topic"))
        assert topic == '/imu\nupdate_rate: 1\n"evil": [1'
        assert "evil" not in block
    assert yaml.safe_load(files["imu.yaml"])["update_rate"] == 200.0


# -- PX4 logs ----------------------------------------------------------------------------------


SMALL = TEST_DATA / "px4_ulog" / "sample_log_small.ulg"


def _run(tmp_path, path, stage="", **inputs):
    keys = "".join(f'{k} = "{v}"\n' for k, v in inputs.items())
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.log]\npath = "{path}"\n{keys}\n[[stages]]\ntype = "gyro_bias"\n{stage}\n'
        f'[output]\ndir = "{tmp_path / "out"}"\napply_to = []\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
    return doc, tmp_path / "out"


def test_px4_raw_instance_goes_to_its_devices_slot(tmp_path):
    """sensor_gyro_2 is device 2621474 = CAL_GYRO2_ID: the bias fitted on it is CAL_GYRO2_*OFF."""
    doc, out = _run(tmp_path, SMALL, imu_topic="sensor_gyro_2")
    p = qgc_params((out / "px4_calibration.params").read_text())
    bias = doc["chain"][0]["offset"]
    assert p["CAL_GYRO2_ID"] == 2621474
    assert [p[f"CAL_GYRO2_{a}OFF"] for a in "XYZ"] == pytest.approx(bias)
    assert doc["chain"][0]["fitted_on"]["instance"] == {"imu": 2, "temperature": 2}


def test_px4_composes_with_the_logs_calibration(tmp_path):
    """sample.ulg's sensor_combined held CAL_GYRO0 already: the exported offset is the log's
    plus the residual bias (PX4's BiasCorrectedSensorOffset), ArduPilot's file is not written."""
    from conftest import shared_path

    path = shared_path("logs", "px4_ulog", "sample.ulg")
    doc, out = _run(tmp_path, path, stage="interval = [8.0, 68.0]\n")
    p = qgc_params((out / "px4_calibration.params").read_text())
    params = doc["chain"][0]["fitted_on"]["px4"]["parameters"]
    bias = np.array(doc["chain"][0]["offset"])
    old = np.array([params[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"])
    assert [p[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"] == pytest.approx(old + bias)
    assert p["CAL_GYRO0_ID"] == params["CAL_GYRO0_ID"]
    assert not (out / "ardupilot_calibration.param").exists()


def test_kalibr_intrinsics_import_back(calibrated, tmp_path):
    """imupipe import kalibr of the exported intrinsics: the same correction, in Kalibr's frame
    (accel and gyro matrices R A and R G), with zero offsets (Kalibr keeps no biases)."""
    out, doc, _, _ = calibrated
    proc = run_cli(
        "import", "kalibr", out / "kalibr_imu_intrinsics.yaml", "--out", tmp_path / "k.json"
    )
    assert proc.returncode == 0, proc.stderr
    assert "biases online" in proc.stderr
    back = json.loads((tmp_path / "k.json").read_text())["chain"]
    r = np.array(doc["exports"]["kalibr_imu_intrinsics.yaml"]["R_kalibr_from_imupipe"])
    for entry in back:
        (ours,) = (np.array(e["matrix"]) for e in _chain(doc, entry["sensor"]))  # one step each
        np.testing.assert_allclose(entry["matrix"], r @ ours, atol=1e-9)
        assert entry["offset"] == [0.0, 0.0, 0.0]


def test_exports_note_agrees_with_its_files():
    from imupipe.pipeline.run import exports_note

    assert exports_note(["kalibr_imu_intrinsics.yaml"]) == (
        "imupipe: note: [exports] kalibr_imu_intrinsics.yaml leaves out what its format has no "
        'place for: see "exports" in calibration.json'
    )
    assert exports_note(["imu.yaml", "px4_calibration.params"]).startswith(
        "imupipe: note: [exports] imu.yaml, px4_calibration.params leave out what their formats "
        "have no place for"
    )


def test_a_compass_without_a_fitted_motor_term_switches_nothing_on():
    """mag_inflight's step of a fit without a motor term (zeros): no COMPASS_MOTCT, no
    COMPASS_MOT, no CAL_MAG_COMP_TYP (before: COMPASS_MOTCT = 2 with MOT 0, also on vehicles
    without a current sensor); with one, COMPASS_MOTCT = 2."""
    from imupipe.stages.magnetometer.inflight import MagCurrentStep

    for motor in ([0.0, 0.0, 0.0], [3e-8, -2e-8, 1e-8]):
        step = MagCurrentStep("mag_inflight", "mag", np.eye(3), [1e-6, 2e-6, 3e-6], motor=motor)
        files, _ = export_all({"chain": [step.to_json()], "results": {}})
        ap = files["ardupilot_calibration.param"]
        px4 = files["px4_calibration.params"]
        fitted = any(motor)
        assert ("COMPASS_MOTCT,2" in ap) == fitted and ("COMPASS_MOT_X" in ap) == fitted
        assert ("CAL_MAG_COMP_TYP" in px4) == fitted
