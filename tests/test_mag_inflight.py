"""mag_inflight: the compass fitted from a flight against the World Magnetic Model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.dataflash.reader import read_dataflash
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import (
    finite,
    flight_stream,
    has_flight_stream,
    make_table,
    metadata,
    sensor,
    with_flight_stream,
)
from imupipe.readers.ulog.rotation import euler_matrix
from imupipe.stages.base import StageContext
from imupipe.stages.errors import FitError
from imupipe.stages.magnetometer.inflight import (
    MagCurrentStep,
    MagInflightStage,
    MagThrottleStep,
    fit_model,
    flight_samples,
)
from imupipe.stages.steps import LinearStep, steps_from_json

from conftest import run_cli, shared_path


def fit(table, **options):
    stage = MagInflightStage(MagInflightStage.Options(**options))
    ctx = StageContext(name="compass", input_name="sim", quiet=True)
    return stage.fit(table, ctx), ctx


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """The default simulated flight, written as DataFlash and read back."""
    table, truth = simulate("flight", {"duration_s": 180.0}, seed=3)
    path = tmp_path_factory.mktemp("flight") / "flight.bin"
    write_log(path, table)
    back, _ = read_dataflash(InputSpec(path=path))
    return back, truth


def test_recovers_the_truth_from_dataflash(flight):
    table, truth = flight
    out, _ = fit(table)
    r = out.results
    assert r["model"] == "soft_iron" and r["motor_term"]
    field = truth["field_norm"]
    assert np.abs(np.array(r["offset_t"]) - truth["offset"]).max() < 0.01 * field
    assert np.abs(np.array(r["matrix"]) - truth["matrix"]).max() < 0.01
    motor = np.array(truth["motor"])
    assert np.linalg.norm(np.array(r["motor_t_per_a"]) - motor) < 0.05 * np.linalg.norm(motor)
    m = r["metrics"]
    assert m["residual_rms_ut_after"] < 0.1 * m["residual_rms_ut_before"]
    assert m["heading_rms_deg_after"] < 1.0 < m["heading_rms_deg_before"]
    assert m["held_out_rms_ut"]["soft_iron"] < m["held_out_rms_ut"]["offsets"]
    assert all(se > 0 for se in r["parameter_se"].values())
    assert r["coverage"]["yaw_coverage_deg"] == 360.0


def test_correction_step_applies_and_round_trips(flight):
    table, truth = flight
    out, _ = fit(table)
    step = steps_from_json([json.loads(json.dumps(out.step.to_json()))])[0]
    assert isinstance(step, MagCurrentStep) and step.kind == "mag_current"
    corrected = sensor(step.apply(table), "mag")
    assert len(corrected) == len(sensor(table, "mag"))
    # the corrected norm is the field's (1 % band), raw is not
    norms = np.linalg.norm(corrected.values, axis=1) / truth["field_norm"]
    assert np.percentile(np.abs(norms - 1), 95) < 0.01
    raw = np.linalg.norm(sensor(table, "mag").values, axis=1) / truth["field_norm"]
    assert np.percentile(np.abs(raw - 1), 95) > 0.05


def test_parameter_exports_reproduce_the_correction(flight):
    from imupipe.pipeline.exports import ardupilot, px4

    table, _ = flight
    out, _ = fit(table)
    doc = {"chain": [out.step.to_json()], "results": {}}
    ap = dict(
        line.split(",")
        for line in ardupilot.export(doc).files["ardupilot_calibration.param"].splitlines()
        if not line.startswith("#")
    )
    ap = {k: float(v) for k, v in ap.items()}
    raw = sensor(table, "mag").values[:50] * 1e7  # mG
    amps = np.linspace(0, 20, 50)
    m = np.array(out.results["matrix"])
    motor = np.array(out.results["motor_t_per_a"])
    want = ((raw * 1e-7 - out.results["offset_t"]) @ m.T + amps[:, None] * motor) * 1e7
    w = np.array(
        [
            [ap["COMPASS_DIA_X"], ap["COMPASS_ODI_X"], ap["COMPASS_ODI_Y"]],
            [ap["COMPASS_ODI_X"], ap["COMPASS_DIA_Y"], ap["COMPASS_ODI_Z"]],
            [ap["COMPASS_ODI_Y"], ap["COMPASS_ODI_Z"], ap["COMPASS_DIA_Z"]],
        ]
    )
    ofs = np.array([ap[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    mot = np.array([ap[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    # AP_Compass_Backend::correct_field: offsets added, scale, DIA/ODI, then MOT x current
    got = ((raw + ofs) * ap["COMPASS_SCALE"]) @ w.T + amps[:, None] * mot
    assert np.allclose(got, want, atol=1e-6) and ap["COMPASS_MOTCT"] == 2
    rows = [
        line.split("\t")
        for line in px4.export(doc).files["px4_calibration.params"].splitlines()
        if not line.startswith("#")
    ]
    p = {r[2]: float(r[3]) for r in rows}
    assert p["CAL_MAG_COMP_TYP"] == 2
    s = np.array(
        [
            [p["CAL_MAG0_XSCALE"], p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YODIAG"]],
            [p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YSCALE"], p["CAL_MAG0_ZODIAG"]],
            [p["CAL_MAG0_YODIAG"], p["CAL_MAG0_ZODIAG"], p["CAL_MAG0_ZSCALE"]],
        ]
    )
    off = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])  # G
    comp = np.array([p[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])  # G/kA
    # PX4 Magnetometer::Correct: S ((raw + COMP * I[kA]) - OFF), gauss
    got = ((raw * 1e-3 + amps[:, None] / 1e3 * comp) - off) @ s.T
    assert np.allclose(got * 1e3, want, atol=1e-6)


def test_refuses_what_the_flight_cannot_separate():
    level, truth = simulate(
        "flight",
        {"duration_s": 60.0, "roll_deg": 0.0, "pitch_deg": 0.0, "current_swing_a": 0.0},
        seed=1,
    )
    truth_offset = truth["offset"]
    with pytest.raises(FitError, match="soft iron.*spread"):
        fit(level, model="soft_iron")
    with pytest.raises(FitError, match="motor.*current spans"):
        fit(level, motor="on")
    out, ctx = fit(level)  # auto: what the flight can separate, the rest named in warnings
    assert not out.results["motor_term"]
    assert any("motor" in w for w in ctx.warnings)
    # a level flight turns the horizontal soft iron (fitted, the truth recovered) but not the
    # vertical row, which trades with the vertical offset: kept at the scale model's by the
    # few-directions ridge (without it, M_zz 0.87 and the offset 9 uT off in z)
    r, truth = out.results, np.asarray(truth["matrix"])
    assert r["model"] == "soft_iron"
    assert any("soft iron fitted on few directions" in w for w in ctx.warnings)
    m = np.asarray(r["matrix"])
    assert np.allclose(m[:2, :2], truth[:2, :2], atol=0.005)
    assert abs(m[2, 2] - np.mean(np.diag(m)[:2])) < 0.02
    assert abs(r["offset_t"][2] - truth_offset[2]) < 4e-6


def test_refuses_a_log_without_attitude_or_gps():
    t = np.arange(200, dtype=np.int64) * 20_000_000
    table = make_table(t, mag=np.tile([2e-5, 0, 4e-5], (200, 1)))
    with pytest.raises(FitError, match="no attitude, position"):
        fit(table)
    table = with_flight_stream(table, "attitude", t, np.tile([1.0, 0, 0, 0], (200, 1)))
    table = with_flight_stream(table, "position", t, np.tile([52.0, 5.0, 0.0], (200, 1)))
    with pytest.raises(FitError, match="date is unknown"):
        fit(table)


def test_robust_fit_rejects_outliers():
    rng = np.random.default_rng(4)
    target = rng.normal(0, 3e-5, (2000, 3))
    raw = target + [1e-5, -2e-5, 5e-6] + rng.normal(0, 1e-7, target.shape)
    raw[::50] += 5e-5  # spikes, 2 %
    f = fit_model(raw, target, None, "soft_iron")
    assert np.allclose(f.offset, [1e-5, -2e-5, 5e-6], atol=3e-8)
    assert np.count_nonzero(~f.used) >= 40


def test_simulate_flight_cli(tmp_path):
    out = tmp_path / "f.bin"
    run_cli("simulate", "flight", "--out", str(out), "--duration", "20")
    truth = json.loads((tmp_path / "f.bin.truth.json").read_text())
    assert truth["scenario"] == "flight"
    table, _ = read_dataflash(InputSpec(path=out))
    assert len(flight_stream(table, "attitude")) == 500
    assert len(flight_stream(table, "current")) == 200
    bad = run_cli("simulate", "flight", "--out", str(tmp_path / "f.csv"), "--duration", "5")
    assert bad.returncode == 2 and ".bin" in bad.stderr


REAL = {
    "erle_pxf_118/118.BIN": {},
    "erle_pxf_218/218.BIN": {},
    "forum13645_ac344/log_0036.bin": {"imu_topic": "IMU", "mag_topic": "MAG"},
    "spark404_utrecht/log.bin": {"imu_topic": "IMU", "mag_topic": "MAG"},
}


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_flights_improve(name):
    """Every real flight's fit lowers the residual and the heading error. erle_pxf_118 (two
    crashes) was refused: its free soft iron lay outside ArduPilot's form (diagonal 0.70 over a
    scale of 1.28: in 0.3 exported as COMPASS_DIA 1.53 with no note) and without it the heading
    error rose (5.2 -> 6.1 deg); held at the firmware's ranges as MagFit bounds it (DIA_Y 0.8,
    ODI_Z -0.2, said in a warning) it wins on held-out segments and lowers the heading error to
    3.6 deg (MagFit has no trustworthy fit of this log)."""
    from imupipe.stages.magnetometer.inflight import out_of_range

    path = shared_path("logs", "ardupilot_flights", *name.split("/"))
    table, _ = read_dataflash(InputSpec(path=path, **REAL[name]))
    out, ctx = fit(table)
    assert (
        out.results["metrics"]["heading_rms_deg_after"]
        < out.results["metrics"]["heading_rms_deg_before"]
    )
    m = out.results["metrics"]
    assert m["residual_rms_ut_after"] < 0.5 * m["residual_rms_ut_before"]
    assert 40 < m["field_ut"] < 52
    assert out_of_range(np.asarray(out.results["matrix"])) == ""
    if name.startswith("erle_pxf_118"):
        assert out.results["model"] == "soft_iron"
        assert any("held at ArduPilot's ranges: DIA_Y 0.800" in w for w in ctx.warnings)


@pytest.mark.slow
def test_no_worse_than_magfit_on_the_simulated_flight(tmp_path):
    """pymavlink's magfit_WMM.py (minutes: pure Python) and mag_inflight on one simulated log,
    scored the same way (benchmarks/bench_magfit.py)."""
    import importlib.util

    from conftest import REPO

    spec = importlib.util.spec_from_file_location("bench", REPO / "benchmarks" / "bench_magfit.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    if not bench.magfit_script().exists():
        pytest.skip("pymavlink's tools/magfit_WMM.py is not installed")
    path = tmp_path / "flight.bin"
    table, _ = simulate("flight", {"duration_s": 60.0}, seed=5)
    write_log(path, table)
    table, _ = read_dataflash(InputSpec(path=path))
    out, _ = fit(table)
    mag, _ = finite(sensor(table, "mag"))
    fs = flight_samples(table, mag, float(metadata(table)["gps_year"]))
    ours = out.step.apply_values(fs.raw) + fs.power(out.results["motor_source"])[:, None] * (
        out.step.motor
    )
    theirs = bench.run_magfit(path, True, 10, 100, None)
    assert isinstance(theirs, dict), theirs
    mf = bench.magfit_corrected(path, fs.t_ns, fs.raw, fs.current, theirs)
    assert bench.score(fs, ours)[0] <= bench.score(fs, mf)[0]


VEHICLE = {
    "COMPASS_OFS_X": -150.0,
    "COMPASS_OFS_Y": 80.0,
    "COMPASS_OFS_Z": -40.0,
    "COMPASS_DIA_X": 1.03,
    "COMPASS_DIA_Y": 0.98,
    "COMPASS_DIA_Z": 1.01,
    "COMPASS_ODI_X": 0.012,
    "COMPASS_ODI_Y": -0.008,
    "COMPASS_ODI_Z": 0.005,
    "COMPASS_SCALE": 1.02,
    "COMPASS_MOT_X": 0.3,
    "COMPASS_MOT_Y": -0.2,
    "COMPASS_MOT_Z": 0.5,
    "COMPASS_MOTCT": 2.0,
}
"""A vehicle's own compass calibration in force while it logged (mG, mG/A), none zero."""


def exported_reproduces_imupipe(
    tmp_path, log, inputs: str = "", stage: str = ""
) -> tuple[float, dict]:
    """Run mag_inflight on ``log`` (a DataFlash file) with the CLI; undo the log's own
    correction on its MAG (the raw field), apply ArduPilot's correct_field with the exported
    parameters over the log's (what the vehicle holds after loading the file), and compare with
    imupipe's corrected field: (max difference in mG, the exported parameters)."""
    from imupipe.pipeline.simulate.flight import ardupilot_correct, ardupilot_raw
    from imupipe.readers.table import interpolate

    (tmp_path / "c.toml").write_text(
        f'[inputs.f]\npath = "{log}"\n{inputs}\n[[stages]]\ntype = "mag_inflight"\n{stage}\n'
        '[output]\ndir = "out"\n'
    )
    proc = run_cli("run", "c.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
    text = (tmp_path / "out" / "ardupilot_calibration.param").read_text()
    exported = {
        k: float(v) for k, v in (ln.split(",") for ln in text.splitlines() if ln[:1] != "#")
    }
    kw = dict(line.split(" = ") for line in inputs.splitlines() if line)
    table, _ = read_dataflash(InputSpec(path=log, **{k: v.strip('"') for k, v in kw.items()}))
    logged = sensor(table, "mag")
    amps = np.zeros(len(logged))
    if has_flight_stream(table, "current"):
        cur = flight_stream(table, "current")
        amps = interpolate(cur.t_ns, cur.values[:, 0], logged.t_ns)
    thr = None
    if has_flight_stream(table, "throttle"):  # CTUN.ThO: what COMPASS_MOTCT = 1 multiplies
        sig = flight_stream(table, "throttle")
        thr = interpolate(sig.t_ns, sig.values[:, 0], logged.t_ns)
    before = metadata(table)["ardupilot"]["parameters"]
    raw = ardupilot_raw(logged.values, before, amps, thr)
    vehicle = ardupilot_correct(raw, before | exported, amps, thr)
    ours = sensor(steps_from_json(doc["chain"])[0].apply(table), "mag").values
    assert np.allclose(ardupilot_correct(raw, before, amps, thr), logged.values, atol=1e-12)
    return float(np.abs(vehicle - ours).max() * 1e7), exported


def test_export_composes_with_the_vehicles_own_calibration(tmp_path):
    """The simulated vehicle logged MAG corrected by its own COMPASS_OFS/DIA/ODI/SCALE/MOT:
    the exported file, loaded on it, gives imupipe's corrected field from the raw one, and its
    parameters are the truth (the raw sensor's errors) in ArduPilot's form."""
    table, truth = simulate("flight", {"duration_s": 120.0, "vehicle": VEHICLE}, seed=6)
    path = tmp_path / "flight.bin"
    write_log(path, table)
    diff, p = exported_reproduces_imupipe(tmp_path, path)
    # mG (the field is ~500 mG, the log's resolution 1 mG): ArduPilot's DIA/ODI is symmetric,
    # the composed M W is not quite (the product of two symmetric matrices): 1e-4 of the field
    assert diff < 0.1
    assert p["COMPASS_MOTCT"] == 2
    # the truth: corrected = M (raw - offset) + motor I  =>  OFS = -offset, W = M, MOT = motor
    field = truth["field_norm"] * 1e7
    ofs = np.array([p[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    assert np.abs(ofs + np.array(truth["offset"]) * 1e7).max() < 0.01 * field
    dia = np.array([p[f"COMPASS_DIA_{a}"] for a in "XYZ"])
    assert dia.mean() == pytest.approx(1.0)  # the common scale is in COMPASS_SCALE
    assert np.abs(dia * p["COMPASS_SCALE"] - np.diag(truth["matrix"])).max() < 0.01
    mot = np.array([p[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    want = np.array(truth["motor"]) * 1e7
    assert np.linalg.norm(mot - want) < 0.05 * np.linalg.norm(want)
    # without composing, the file would hold a correction on top of the vehicle's: far off
    assert np.abs(ofs - [VEHICLE[f"COMPASS_OFS_{a}"] for a in "XYZ"]).max() > 50


def test_export_composes_with_a_real_logs_calibration(tmp_path):
    """spark404_utrecht: ArduPilot logged MAG with its COMPASS_OFS and DIA/ODI in force."""
    path = shared_path("logs", "ardupilot_flights", "spark404_utrecht", "log.bin")
    diff, p = exported_reproduces_imupipe(tmp_path, path, 'imu_topic = "IMU"\nmag_topic = "MAG"')
    assert diff < 0.1
    assert {"COMPASS_OFS_X", "COMPASS_DIA_X"} <= set(p)
    assert ("COMPASS_MOT_X" in p) == ("COMPASS_MOTCT" in p)  # switched on only when fitted


def test_flights_of_one_vehicle_fitted_together():
    """Two flights, one compass (the default truth), other tracks and attitudes: the joint fit
    has smaller standard errors than either alone and recovers the truth; a flight logged under
    other compass parameters is refused."""
    a, truth = simulate("flight", {"duration_s": 90.0}, seed=7)
    b, _ = simulate(
        "flight",
        {
            "duration_s": 90.0,
            "yaw_turns": 3.0,
            "roll_deg": 25.0,
            "pitch_deg": 40.0,
            "lat": 46.5,
            "lon": 7.9,
            "current_a": 18.0,
        },
        seed=8,
    )
    alone = [fit(t)[0].results for t in (a, b)]
    stage = MagInflightStage(MagInflightStage.Options(flights=["b"]))
    ctx = StageContext(name="compass", input_name="a", quiet=True, tables={"a": a, "b": b})
    r = stage.fit(a, ctx).results
    assert r["model"] == "soft_iron" and r["motor_term"]
    for name, se in r["parameter_se"].items():
        assert se < min(x["parameter_se"][name] for x in alone), name
    field = truth["field_norm"]
    assert np.abs(np.array(r["offset_t"]) - truth["offset"]).max() < 0.01 * field
    assert np.abs(np.array(r["matrix"]) - truth["matrix"]).max() < 0.01
    motor = np.array(truth["motor"])
    assert np.linalg.norm(np.array(r["motor_t_per_a"]) - motor) < 0.05 * np.linalg.norm(motor)
    flights = r["metrics"]["flights"]
    assert set(flights) == {"a", "b"} and flights["b"]["samples"] > 4400
    # the model is chosen on held-out flights (each fitted on the other, scored on itself),
    # not on time segments cutting across both
    from imupipe.stages.magnetometer.inflight import held_out_rms

    assert r["metrics"]["held_out_on"] == "flights"
    joined, counts = stage._joint(a, ctx)
    each = [np.arange(counts[0]), np.arange(counts[0], sum(counts))]
    for model, got in r["metrics"]["held_out_rms_ut"].items():
        want = held_out_rms(joined.raw, joined.target, joined.current, model, each, stage.options)
        assert got == pytest.approx(want * 1e6, rel=1e-9), model
    assert all(f["residual_rms_ut_after"] < 0.5 for f in flights.values())
    other, _ = simulate("flight", {"duration_s": 30.0, "vehicle": VEHICLE}, seed=9)
    ctx = StageContext(name="compass", input_name="a", quiet=True, tables={"a": a, "b": other})
    with pytest.raises(FitError, match="other compass parameters"):
        stage.fit(a, ctx)
    ctx = StageContext(name="compass", input_name="a", quiet=True, tables={"a": a})
    with pytest.raises(FitError, match="'b' is not another input"):
        stage.fit(a, ctx)


def test_flights_whose_offsets_stepped_are_named_not_fitted_together():
    """Three flights of one vehicle; between the first and the second the compass's hard iron
    moved by 15 uT (30 % of the field: a part or wiring moved near it). Fitted together they
    are refused by a check naming the two flights, their dates and the step (uT and mG): one
    calibration cannot serve both sides (before: refused as "residual 7.34 uT >
    max_residual_ut", which blames the fit; with accept_failed_checks, applied silently). The
    two flights after the step agree and are fitted together; a step of 2 uT (attitude and
    model errors move a fitted offset as much between real flights) is not one."""
    base = {"duration_s": 60.0, "mag_hz": 10.0, "year": 2024.40}
    turns = {"yaw_turns": 3.0, "roll_deg": 25.0, "pitch_deg": 40.0, "current_a": 18.0}
    a, truth = simulate("flight", base, seed=7)
    moved = (np.asarray(truth["offset"]) + [0.0, 0.0, 1.5e-5]).tolist()
    b, _ = simulate("flight", {**base, **turns, "year": 2024.45, "offset": moved}, seed=8)
    c, _ = simulate("flight", {**base, "year": 2024.46, "offset": moved}, seed=9)
    nudged = (np.asarray(truth["offset"]) + [0.0, 2e-6, 0.0]).tolist()
    d, _ = simulate("flight", {**base, **turns, "year": 2024.45, "offset": nudged}, seed=8)
    tables = {"a": a, "b": b, "c": c, "d": d}

    def joint(first: str, *others: str, accept: bool = False):
        stage = MagInflightStage(MagInflightStage.Options(flights=list(others)))
        ctx = StageContext(
            name="compass", input_name=first, quiet=True, tables=tables, accept_failed_checks=accept
        )
        return stage.fit(tables[first], ctx), ctx

    with pytest.raises(FitError, match="offsets moved by") as err:
        joint("c", "a", "b")  # in any order: the step is between consecutive dates
    said = str(err.value)
    assert "between 'a' (2024-05-26) and 'b' (2024-06-13)" in said, said
    step = float(said.split("in the body axes (")[1].split(" uT")[0])
    assert step == pytest.approx(15.0, abs=1.5)
    assert f"{step * 10:.0f} mG" in said
    out, ctx = joint("c", "a", "b", accept=True)
    flights = out.results["metrics"]["flights"]
    assert flights["b"]["offset_ut"][2] - flights["a"]["offset_ut"][2] == pytest.approx(15, abs=1.5)
    assert [c for c in ctx.failed_checks if "offsets moved" in c]
    out, ctx = joint("b", "c")
    assert not ctx.failed_checks
    assert np.abs(np.asarray(out.results["offset_t"]) - moved).max() < 0.3e-6
    out, ctx = joint("a", "d")
    assert not ctx.failed_checks
    flights = out.results["metrics"]["flights"]
    assert flights["d"]["offset_ut"][1] - flights["a"]["offset_ut"][1] == pytest.approx(2, abs=0.3)


def test_flights_whose_own_offsets_cannot_be_fitted_are_not_compared(monkeypatch):
    """A flight left with no sample the grouped fit keeps makes its own offsets singular: the
    joint fit stands, with a warning that the flights were not compared (no traceback)."""
    import imupipe.stages.magnetometer.inflight as inflight

    base = {"duration_s": 40.0, "mag_hz": 10.0}
    a, _ = simulate("flight", base, seed=7)
    b, _ = simulate("flight", {**base, "yaw_turns": 3.0, "current_a": 18.0}, seed=8)

    def singular(*args, **kwargs):
        raise np.linalg.LinAlgError("singular")

    monkeypatch.setattr(inflight, "flight_offsets", singular)
    stage = MagInflightStage(MagInflightStage.Options(flights=["b"]))
    ctx = StageContext(name="compass", input_name="a", quiet=True, tables={"a": a, "b": b})
    r = stage.fit(a, ctx).results
    assert "offset_ut" not in r["metrics"]["flights"]["b"]
    assert any("own offsets could not be fitted" in w for w in ctx.warnings), ctx.warnings


@pytest.fixture(scope="module")
def px4_flights():
    """The three real PX4 flights (../shared/data/logs/px4_flights_flugdrohne), each compass's
    table per flight: {key: {"log_20": table, ...}}."""
    from imupipe.readers.dispatch import read_input

    folder = shared_path("logs", "px4_flights_flugdrohne")
    return {
        key: {
            p.name[:6]: read_input(InputSpec(path=p, mag_topic=key, imu_topic=""))[0]
            for p in sorted(folder.glob("*.ulg"))
        }
        for key in ("sensor_mag", "sensor_mag_1")
    }


def test_real_px4_flights_across_a_hard_iron_change_are_refused_by_name(px4_flights):
    """px4_flights_flugdrohne: the internal compass (sensor_mag) reads 200-300 mG of hard iron
    that moved between 7 June (log_20, log_30) and 21 June (log_86; the vehicle rewired: motors
    moved from the MAIN to the AUX outputs, new AUX functions), at any current (the ground
    samples before take-off, 0-3 A, show it too; its per-ampere term is 2-3 mG/A). Fitted
    together the three are refused naming log_30 -> log_86 and a step near 24 uT (before:
    "offsets 53.2 uT exceed the Earth's field", blaming the attitude or the GPS); the two of
    7 June are fitted together. The external compass's offsets agree across the three flights
    (steps under 4 uT): no such refusal."""

    def joint(key: str, first: str, *others: str):
        stage = MagInflightStage(MagInflightStage.Options(flights=list(others)))
        ctx = StageContext(
            name="compass",
            input_name=first,
            quiet=True,
            tables=px4_flights[key],
            accept_failed_checks=True,
        )
        return stage.fit(px4_flights[key][first], ctx), ctx

    out, ctx = joint("sensor_mag", "log_20", "log_30", "log_86")
    moved = [c for c in ctx.failed_checks if "offsets moved" in c]
    assert len(moved) == 1 and ctx.failed_checks[0] == moved[0], ctx.failed_checks
    assert "between 'log_30' (2023-06-07) and 'log_86' (2023-06-21)" in moved[0]
    step = float(moved[0].split("in the body axes (")[1].split(" uT")[0])
    assert 20.0 < step < 30.0
    flights = out.results["metrics"]["flights"]
    same_day = np.subtract(flights["log_30"]["offset_ut"], flights["log_20"]["offset_ut"])
    assert np.linalg.norm(same_day) < 8.0
    _, ctx = joint("sensor_mag", "log_20", "log_30")
    assert not [c for c in ctx.failed_checks if "offsets moved" in c], ctx.failed_checks
    out, ctx = joint("sensor_mag_1", "log_20", "log_30", "log_86")
    assert not [c for c in ctx.failed_checks if "offsets moved" in c], ctx.failed_checks
    off = np.array([f["offset_ut"] for f in out.results["metrics"]["flights"].values()])
    assert np.linalg.norm(np.diff(off, axis=0), axis=1).max() < 5.0


def simulated_ulog_run(tmp_path, *settings: str) -> tuple[dict, dict]:
    """``imupipe simulate flight --out flight.ulg --duration 120 --set S...`` then ``imupipe
    run`` of mag_inflight on it (CLI, in ``tmp_path``): (the truth, calibration.json)."""
    sets = [x for setting in settings for x in ("--set", setting)]
    proc = run_cli(
        "simulate", "flight", "--out", "flight.ulg", "--duration", "120", *sets, cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    truth = json.loads((tmp_path / "flight.ulg.truth.json").read_text())
    (tmp_path / "c.toml").write_text(
        '[inputs.f]\npath = "flight.ulg"\n[[stages]]\ntype = "mag_inflight"\n[output]\ndir = "out"\n'
    )
    proc = run_cli("run", "c.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    return truth, json.loads((tmp_path / "out" / "calibration.json").read_text())


def test_px4_path_end_to_end(tmp_path):
    """imupipe simulate flight --out flight.ulg: sensor_mag (raw), vehicle_attitude,
    vehicle_gps_position (its UTC time gives the date), battery_status; the fit recovers the
    truth and the exported CAL_MAG0_*, CAL_MAG0_{X,Y,Z}COMP with CAL_MAG_COMP_TYP = 2, applied
    as PX4 does, give imupipe's corrected field."""
    from imupipe.readers.table import interpolate
    from imupipe.readers.ulog.reader import read_ulog

    truth, doc = simulated_ulog_run(tmp_path)
    r = doc["results"]["mag_inflight"]
    assert r["model"] == "soft_iron" and r["motor_term"] and abs(r["year"] - 2024.5) < 1e-3
    rows = (tmp_path / "out" / "px4_calibration.params").read_text().splitlines()
    p = {x[2]: float(x[3]) for x in (ln.split("\t") for ln in rows if ln[:1] != "#")}
    assert p["CAL_MAG_COMP_TYP"] == 2 and p["CAL_MAG0_ID"] == 396825
    field = truth["field_norm"] * 1e4  # G
    off = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    assert np.abs(off - np.array(truth["offset"]) * 1e4).max() < 0.01 * field
    s = np.array(
        [
            [p["CAL_MAG0_XSCALE"], p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YODIAG"]],
            [p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YSCALE"], p["CAL_MAG0_ZODIAG"]],
            [p["CAL_MAG0_YODIAG"], p["CAL_MAG0_ZODIAG"], p["CAL_MAG0_ZSCALE"]],
        ]
    )
    assert np.abs(s - truth["matrix"]).max() < 0.01
    comp = np.array([p[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])  # G/kA, added before S
    want = np.linalg.solve(truth["matrix"], truth["motor"]) * 1e4 * 1e3
    assert np.linalg.norm(comp - want) < 0.05 * np.linalg.norm(want)
    table, _ = read_ulog(InputSpec(path=tmp_path / "flight.ulg"))
    raw = sensor(table, "mag")
    cur = flight_stream(table, "current")
    amps = interpolate(cur.t_ns, cur.values[:, 0], raw.t_ns)
    px4 = ((raw.values * 1e4 + amps[:, None] / 1e3 * comp) - off) @ s.T  # G
    ours = sensor(steps_from_json(doc["chain"])[0].apply(table), "mag").values * 1e4
    assert np.abs(px4 - ours).max() < 1e-6
    bad = run_cli(
        "simulate",
        "flight",
        "--out",
        "v.ulg",
        "--set",
        'vehicle={"COMPASS_OFS_X": 5}',
        cwd=tmp_path,
    )
    assert bad.returncode == 2 and "vehicle" in bad.stderr and not (tmp_path / "v.ulg").exists()


def test_throttle_compensated_log_is_noted(tmp_path):
    """A log recorded with throttle-based (COMPASS_MOTCT = 1) compensation: the term has no
    per-ampere form; the export says so and writes the fitted current-based term."""
    from imupipe.pipeline.exports import ardupilot

    table, _ = simulate("flight", {"duration_s": 60.0}, seed=10)
    path = tmp_path / "flight.bin"
    write_log(path, table)
    (tmp_path / "c.toml").write_text(
        '[inputs.f]\npath = "flight.bin"\n[[stages]]\ntype = "mag_inflight"\n[output]\ndir = "o"\n'
    )
    assert run_cli("run", "c.toml", cwd=tmp_path).returncode == 0
    doc = json.loads((tmp_path / "o" / "calibration.json").read_text())
    params = doc["chain"][0]["fitted_on"]["ardupilot"]["parameters"]
    params.update({"COMPASS_MOTCT": 1.0, "COMPASS_MOT_X": 0.4})
    out = ardupilot.export(doc)
    assert any("throttle-based" in n for n in out.notes[ardupilot.FNAME])
    assert "COMPASS_MOTCT,2" in out.files[ardupilot.FNAME]


# -- throttle-based motor compensation (COMPASS_MOTCT = 1, CAL_MAG_COMP_TYP = 1) -----------------


@pytest.fixture(scope="module")
def throttle_flight(tmp_path_factory):
    """A vehicle without a current sensor whose motors' interference follows the throttle,
    written as DataFlash (CTUN.ThO, no BAT) and read back."""
    table, truth = simulate(
        "flight",
        {"duration_s": 180.0, "motor_source": "throttle", "current_sensor": False},
        seed=3,
    )
    path = tmp_path_factory.mktemp("thr") / "flight.bin"
    write_log(path, table)
    back, _ = read_dataflash(InputSpec(path=path))
    return back, truth


def _params(text: str, sep: str) -> dict[str, float]:
    """name -> value of a Mission Planner (``,``) or QGroundControl (tab) parameter file."""
    rows = [ln.split(sep) for ln in text.splitlines() if ln[:1] not in ("#", "")]
    return {r[0]: float(r[1]) for r in rows} if sep == "," else {r[2]: float(r[3]) for r in rows}


def _soft(p: dict[str, float], diag: str, off: str) -> np.ndarray:
    """The symmetric matrix of a parameter file's diagonal/off-diagonal names (``{a}`` = X, Y,
    Z)."""
    d = [p[diag.format(a=a)] for a in "XYZ"]
    o = [p[off.format(a=a)] for a in "XYZ"]
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


def test_throttle_term_recovers_the_truth_without_a_current_sensor(throttle_flight):
    """No BAT: the motor term is fitted against CTUN.ThO and recovers the truth (targets:
    offsets 1 % of the field, soft iron 1 %, motor 5 %)."""
    table, truth = throttle_flight
    assert not has_flight_stream(table, "current") and has_flight_stream(table, "throttle")
    out, ctx = fit(table)
    r = out.results
    assert r["model"] == "soft_iron" and r["motor_term"] and r["motor_source"] == "throttle"
    field = truth["field_norm"]
    assert np.abs(np.array(r["offset_t"]) - truth["offset"]).max() < 0.01 * field
    assert np.abs(np.array(r["matrix"]) - truth["matrix"]).max() < 0.01
    motor = np.array(truth["motor"])  # T at full throttle
    got = np.array(r["motor_t_per_throttle"])
    assert np.linalg.norm(got - motor) < 0.05 * np.linalg.norm(motor)
    assert r["motor_t_per_a"] == [0.0, 0.0, 0.0]
    assert "motor_z [uT/throttle]" in r["parameter_se"]
    assert r["metrics"]["residual_rms_ut_after"] < 0.5
    assert not any("motor" in w for w in ctx.warnings)
    # without the throttle term the same flight fits worse: the term is real
    off, _ = fit(table, motor="off")
    assert (
        off.results["metrics"]["residual_rms_ut_after"] > 2 * r["metrics"]["residual_rms_ut_after"]
    )


def test_throttle_step_round_trips_and_applies_the_throttle(throttle_flight):
    table, truth = throttle_flight
    out, _ = fit(table)
    step = steps_from_json([json.loads(json.dumps(out.step.to_json()))])[0]
    assert isinstance(step, MagThrottleStep) and step.kind == "mag_throttle"
    corrected = sensor(step.apply(table), "mag").values
    norms = np.linalg.norm(corrected, axis=1) / truth["field_norm"]
    assert np.percentile(np.abs(norms - 1), 95) < 0.01
    static = sensor(LinearStep("x", "mag", step.matrix, step.offset).apply(table), "mag").values
    moved = np.linalg.norm(corrected - static, axis=1)  # the motor term, ~uT with the throttle
    assert moved.max() > 1e-6


def test_throttle_exports_reproduce_the_correction_with_the_firmware_formulas(throttle_flight):
    """ArduPilot (AP_Compass_Backend::correct_field with COMPASS_MOTCT = 1: motor_offset = MOT x
    throttle, throttle 0..1 from motors->get_throttle(), i.e. CTUN.ThO) and PX4
    (Magnetometer::Correct with CAL_MAG_COMP_TYP = 1: S ((raw + COMP x thrust) - OFF), thrust
    the norm of vehicle_thrust_setpoint) give imupipe's corrected field from the exported
    parameters."""
    from imupipe.pipeline.exports import ardupilot, px4
    from imupipe.readers.table import interpolate

    table, _ = throttle_flight
    out, _ = fit(table)
    doc = {"chain": [out.step.to_json()], "results": {}}
    mag = sensor(table, "mag")
    sig = flight_stream(table, "throttle")
    thr = interpolate(sig.t_ns, sig.values[:, 0], mag.t_ns)
    ours = sensor(out.step.apply(table), "mag").values
    ap = _params(ardupilot.export(doc).files[ardupilot.FNAME], ",")
    assert ap["COMPASS_MOTCT"] == 1
    w = _soft(ap, "COMPASS_DIA_{a}", "COMPASS_ODI_{a}") * ap["COMPASS_SCALE"]
    ofs = np.array([ap[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    mot = np.array([ap[f"COMPASS_MOT_{a}"] for a in "XYZ"])  # mG at full throttle
    got = (mag.values * 1e7 + ofs) @ w.T + thr[:, None] * mot
    assert np.abs(got - ours * 1e7).max() < 1e-6
    p = _params(px4.export(doc).files[px4.FNAME], "\t")
    assert p["CAL_MAG_COMP_TYP"] == 1
    s = _soft(p, "CAL_MAG0_{a}SCALE", "CAL_MAG0_{a}ODIAG")
    off = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    comp = np.array([p[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])  # G at full throttle
    got = ((mag.values * 1e4 + thr[:, None] * comp) - off) @ s.T
    assert np.abs(got - ours * 1e4).max() < 1e-6


def test_motor_source_is_one_per_vehicle():
    """Both a current and a throttle logged: the current (the physical cause) is the motor
    source whatever the compass, so that every compass of a vehicle has the kind of its one
    COMPASS_MOTCT (before, each compass's held-out segments chose, and one log's MAG took the
    throttle, its MAG2 the current); the throttle when asked for; the motor term scored against
    none on held-out segments; a forced source that is not logged is refused with motor = "on"."""
    for source in ("current", "throttle"):
        table, truth = simulate(
            "flight", {"duration_s": 120.0, "motor_source": source, "log_throttle": True}, seed=11
        )
        assert has_flight_stream(table, "current") and has_flight_stream(table, "throttle")
        r = fit(table)[0].results
        assert r["motor_source"] == "current" and r["motor_term"]
        held = r["metrics"]["held_out_rms_ut_motor_source"]
        assert set(held) == {"current", "none"} and held["current"] < 0.98 * held["none"]
        asked = fit(table, motor_source=source)[0].results
        assert asked["motor_source"] == source
        key = "motor_t_per_a" if source == "current" else "motor_t_per_throttle"
        motor = np.array(truth["motor"])
        assert np.linalg.norm(np.array(asked[key]) - motor) < 0.05 * np.linalg.norm(motor)
    table, _ = simulate("flight", {"duration_s": 30.0, "current_sensor": False}, seed=12)
    with pytest.raises(FitError, match="no battery current"):
        fit(table, motor="on", motor_source="current")


def test_px4_throttle_path_end_to_end(tmp_path):
    """imupipe simulate flight --out flight.ulg with the interference on the throttle and no
    battery_status: vehicle_thrust_setpoint is read, CAL_MAG_COMP_TYP = 1 and CAL_MAG0_*COMP
    (G at full throttle) applied as PX4 does give imupipe's corrected field."""
    from imupipe.readers.table import interpolate
    from imupipe.readers.ulog.reader import read_ulog

    truth, doc = simulated_ulog_run(tmp_path, "motor_source=throttle", "current_sensor=false")
    assert doc["results"]["mag_inflight"]["motor_source"] == "throttle"
    p = _params((tmp_path / "out" / "px4_calibration.params").read_text(), "\t")
    assert p["CAL_MAG_COMP_TYP"] == 1
    s = _soft(p, "CAL_MAG0_{a}SCALE", "CAL_MAG0_{a}ODIAG")
    comp = np.array([p[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])
    want = np.linalg.solve(truth["matrix"], truth["motor"]) * 1e4  # COMP = S^-1 motor, G
    assert np.linalg.norm(comp - want) < 0.05 * np.linalg.norm(want)
    off = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    table, _ = read_ulog(InputSpec(path=tmp_path / "flight.ulg"))
    assert not has_flight_stream(table, "current")
    raw = sensor(table, "mag")
    sig = flight_stream(table, "throttle")
    thrust = interpolate(sig.t_ns, sig.values[:, 0], raw.t_ns)
    px4 = ((raw.values * 1e4 + thrust[:, None] * comp) - off) @ s.T
    ours = sensor(steps_from_json(doc["chain"])[0].apply(table), "mag").values * 1e4
    assert np.abs(px4 - ours).max() < 1e-6


def test_export_composes_with_a_throttle_compensating_vehicle(tmp_path):
    """The vehicle logged MAG with its own COMPASS_MOTCT = 1 term (MOT x CTUN.ThO) on top of
    OFS/DIA/ODI: the exported file, loaded on it, gives imupipe's corrected field from the raw
    one, and its COMPASS_MOT is the truth in mG at full throttle."""
    vehicle = VEHICLE | {"COMPASS_MOTCT": 1.0, "COMPASS_MOT_X": 6.0, "COMPASS_MOT_Y": -4.0}
    table, truth = simulate(
        "flight",
        {"duration_s": 120.0, "vehicle": vehicle, "motor_source": "throttle"},
        seed=6,
    )
    path = tmp_path / "flight.bin"
    write_log(path, table)
    diff, p = exported_reproduces_imupipe(tmp_path, path, stage='motor_source = "throttle"')
    assert diff < 0.1 and p["COMPASS_MOTCT"] == 1
    mot = np.array([p[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    want = np.array(truth["motor"]) * 1e7
    assert np.linalg.norm(mot - want) < 0.05 * np.linalg.norm(want)


def test_a_throttle_the_compass_does_not_follow_is_left_out():
    """No current sensor, a logged throttle, no motor interference: the throttle term does not
    lower the held-out residual by 2 %, so it is left out (warned), the fit is the static one."""
    table, truth = simulate(
        "flight",
        {
            "duration_s": 60.0,
            "motor": [0.0, 0.0, 0.0],
            "current_sensor": False,
            "log_throttle": True,
        },
        seed=13,
    )
    out, ctx = fit(table)
    r = out.results
    assert not r["motor_term"] and r["motor_source"] is None
    held = r["metrics"]["held_out_rms_ut_motor_source"]
    assert held["throttle"] > 0.98 * held["none"]
    assert any("throttle term does not lower" in w for w in ctx.warnings)
    assert type(out.step) is MagCurrentStep and not np.any(out.step.motor)
    assert np.abs(np.array(r["offset_t"]) - truth["offset"]).max() < 0.01 * truth["field_norm"]
    forced = fit(table, motor="on")[0].results  # asked for: fitted, and near zero
    assert forced["motor_source"] == "throttle"
    assert np.abs(forced["motor_t_per_throttle"]).max() < 0.05 * np.abs(truth["offset"]).max()


# -- board and compass orientation ----------------------------------------------------------------


@pytest.mark.parametrize(
    "px4_parameters",
    [
        {"CAL_MAG0_ROT": 2, "SENS_BOARD_X_OFF": 1.5},  # external, turned 90 deg in yaw
        {"SENS_BOARD_ROT": 10, "SENS_BOARD_Y_OFF": -2.0},  # internal: the board's roll 180 yaw 90
    ],
)
def test_px4_rotated_compass_exports_reproduce_the_correction(tmp_path, px4_parameters):
    """A PX4 compass read in its own axes (sensor_mag) and turned into the body by PX4 after its
    calibration (Magnetometer::Correct: R (S ((raw + COMP P) - OFF)), R = Euler(SENS_BOARD_*_OFF)
    rot(CAL_MAG0_ROT, or SENS_BOARD_ROT for an internal one)): the fit runs in the body axes
    (the truth), and the exported S = R^T M R, OFF = R^T offset, COMP applied with that R give
    imupipe's corrected field."""
    from imupipe.readers.table import interpolate
    from imupipe.readers.ulog.reader import read_ulog

    truth, doc = simulated_ulog_run(tmp_path, "px4_parameters=" + json.dumps(px4_parameters))
    r = doc["results"]["mag_inflight"]
    # R as PX4 builds it: the level adjustment (degrees) times the enum's Euler angles
    rot = {2: (0, 0, 90), 10: (180, 0, 90)}[
        px4_parameters.get("CAL_MAG0_ROT", px4_parameters.get("SENS_BOARD_ROT"))
    ]
    level = [px4_parameters.get(f"SENS_BOARD_{a}_OFF", 0.0) for a in "XYZ"]
    turn = euler_matrix(*np.radians(level)) @ euler_matrix(*np.radians(rot))
    assert np.allclose(r["sensor_rotation"], turn, atol=1e-6)
    field = truth["field_norm"]
    assert np.abs(np.array(r["offset_t"]) - truth["offset"]).max() < 0.01 * field
    assert np.abs(np.array(r["matrix"]) - truth["matrix"]).max() < 0.01
    p = _params((tmp_path / "out" / "px4_calibration.params").read_text(), "\t")
    s = _soft(p, "CAL_MAG0_{a}SCALE", "CAL_MAG0_{a}ODIAG")
    off = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])  # G, sensor axes
    comp = np.array([p[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])  # G/kA
    assert np.abs(s - turn.T @ np.array(truth["matrix"]) @ turn).max() < 0.01
    assert np.abs(off - turn.T @ np.array(truth["offset"]) * 1e4).max() < 0.01 * field * 1e4
    table, _ = read_ulog(InputSpec(path=tmp_path / "flight.ulg"))
    raw = sensor(table, "mag")
    cur = flight_stream(table, "current")
    amps = interpolate(cur.t_ns, cur.values[:, 0], raw.t_ns)
    px4 = (((raw.values * 1e4 + amps[:, None] / 1e3 * comp) - off) @ s.T) @ turn.T  # G, body
    ours = sensor(steps_from_json(doc["chain"])[0].apply(table), "mag").values * 1e4
    # S is written symmetric (R^T M R is, for a symmetric M); the fitted M's own asymmetry: 0
    assert np.abs(px4 - ours).max() < 1e-6
    # without the rotation the file would be wrong by the turn itself
    unturned = ((raw.values * 1e4 + amps[:, None] / 1e3 * comp) - off) @ s.T
    assert np.abs(unturned - ours).max() > 0.1


@pytest.mark.parametrize(
    "orientation",
    [
        {"COMPASS_ORIENT": 8.0, "COMPASS_EXTERNAL": 1.0},  # external, roll 180 (the erle logs')
        {"AHRS_ORIENTATION": 2.0, "COMPASS_EXTERNAL": 0.0},  # internal, the board yawed 90
    ],
)
def test_ardupilot_orientation_composes(tmp_path, orientation):
    """ArduPilot turns the raw field into the body (rotate_field: COMPASS_ORIENT for an external
    compass, AHRS_ORIENTATION for an internal one) before correct_field applies the offsets,
    DIA/ODI and MOT, and logs MAG after both: the exported file is written (no longer refused)
    and, loaded on the vehicle, turns the compass's own readings into imupipe's corrected
    field."""
    from imupipe.pipeline.simulate.flight import ardupilot_correct, ardupilot_raw
    from imupipe.readers.ulog.rotation import rotation_matrix

    vehicle = VEHICLE | orientation
    table, truth = simulate("flight", {"duration_s": 120.0, "vehicle": vehicle}, seed=6)
    path = tmp_path / "flight.bin"
    write_log(path, table)
    diff, p = exported_reproduces_imupipe(tmp_path, path)
    assert diff < 0.1 and {"COMPASS_OFS_X", "COMPASS_DIA_X", "COMPASS_MOT_X"} <= set(p)
    # the firmware path from the compass's own axes: rotate_field, then correct_field
    back, _ = read_dataflash(InputSpec(path=path))
    logged = sensor(back, "mag")
    cur = flight_stream(back, "current")
    from imupipe.readers.table import interpolate

    amps = interpolate(cur.t_ns, cur.values[:, 0], logged.t_ns)
    turn = rotation_matrix(
        int(orientation.get("COMPASS_ORIENT", orientation.get("AHRS_ORIENTATION")))
    )
    body = ardupilot_raw(logged.values, vehicle, amps)  # the raw field turned into the body
    own_axes = body @ turn  # what the chip read: R^T body
    firmware = ardupilot_correct(own_axes @ turn.T, vehicle | p, amps)
    doc = json.loads((tmp_path / "out" / "calibration.json").read_text())
    ours = sensor(steps_from_json(doc["chain"])[0].apply(back), "mag").values
    assert np.abs(firmware - ours).max() * 1e7 < 0.1
    mot = np.array([p[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    want = np.array(truth["motor"]) * 1e7
    assert np.linalg.norm(mot - want) < 0.05 * np.linalg.norm(want)


def test_export_composes_with_a_real_rotated_compass(tmp_path):
    """erle_pxf_218 flew with COMPASS_ORIENT = 8 (roll 180): its export was refused before; the
    composition holds since ArduPilot's compass parameters act after the rotation."""
    path = shared_path("logs", "ardupilot_flights", "erle_pxf_218", "218.BIN")
    diff, p = exported_reproduces_imupipe(tmp_path, path)
    assert diff < 0.1 and {"COMPASS_OFS_X", "COMPASS_DIA_X"} <= set(p)


def _trimmed(table, trim: tuple[float, float]):
    """``table`` as ArduPilot would log it with ``AHRS_TRIM_X/Y = trim`` (rad): ATT is the
    vehicle body's attitude, ``R_board from_euler(trim.x, trim.y, 0)^T`` (``AP_AHRS``), the
    compass stays in the board's frame; the trim goes into the log's parameters."""
    import pyarrow as pa
    from scipy.spatial.transform import Rotation

    from imupipe.readers.table import FLIGHT_COLUMNS, with_metadata

    att = flight_stream(table, "attitude")
    board = Rotation.from_quat(att.values[:, [1, 2, 3, 0]])
    turn = Rotation.from_euler("ZYX", [0.0, trim[1], trim[0]])
    vehicle = (board * turn.inv()).as_quat()[:, [3, 0, 1, 2]]
    for j, name in enumerate(FLIGHT_COLUMNS["attitude"]):
        col = table.column(name).to_numpy(zero_copy_only=False).astype(float)
        col[att.rows] = vehicle[:, j]
        i = table.schema.get_field_index(name)
        table = table.set_column(i, table.schema.field(i), pa.array(col, mask=np.isnan(col)))
    meta = metadata(table)
    params = meta.setdefault("ardupilot", {}).setdefault("parameters", {})
    params.update({"AHRS_TRIM_X": trim[0], "AHRS_TRIM_Y": trim[1]})
    return with_metadata(table, meta)


def test_ahrs_trim_turns_the_logged_attitude_into_the_boards():
    """ArduPilot logs the trimmed vehicle attitude; the compass is in the board's frame. With
    AHRS_TRIM_X/Y of 2-3 deg the fit recovers the truth as on the untrimmed flight (before the
    trim was applied: the offsets came out 3.2 uT off)."""
    table, truth = simulate("flight", {"duration_s": 120.0}, seed=3)
    trimmed = _trimmed(table, (np.radians(2.0), np.radians(-3.0)))
    r = fit(trimmed)[0].results
    field = truth["field_norm"]
    assert np.abs(np.array(r["offset_t"]) - truth["offset"]).max() < 0.01 * field
    assert np.abs(np.array(r["matrix"]) - truth["matrix"]).max() < 0.01
    plain = fit(table)[0].results["metrics"]["residual_rms_ut_after"]
    assert r["metrics"]["residual_rms_ut_after"] < 1.2 * plain


def _narrow_flight(tilt_deg: float, matrix: list[list[float]]):
    """A 40 s simulated flight banking to ``tilt_deg`` with the compass's soft iron ``matrix``."""
    table, _ = simulate(
        "flight",
        {
            "duration_s": 40.0,
            "roll_deg": tilt_deg,
            "pitch_deg": tilt_deg,
            "matrix": matrix,
            "current_swing_a": 0.0,
        },
        seed=2,
    )
    return table


def test_soft_iron_on_few_directions_is_chosen_on_held_out_segments():
    """A flight banking to 8 deg only (spread below min_spread, as erle_pxf_218's and
    forum13645's first 60 %): the soft iron was refused outright, the scale kept (held out ~1.9
    uT); it is now a bounded candidate and wins on the held-out segments, the truth recovered.
    Asked for explicitly it is still refused (the user gets what the flight cannot separate)."""
    truth = [[1.10, 0.03, 0.0], [0.03, 0.92, 0.0], [0.0, 0.0, 1.0]]
    table = _narrow_flight(8.0, truth)
    out, ctx = fit(table)
    r = out.results
    assert r["coverage"]["direction_spread"][0] < MagInflightStage.Options().min_spread
    assert r["model"] == "soft_iron", r["metrics"]["held_out_rms_ut"]
    held = r["metrics"]["held_out_rms_ut"]
    assert held["soft_iron"] < 0.5 * held["scale"]
    assert np.allclose(r["matrix"], truth, atol=0.01)
    assert any("few directions" in w and "held-out" in w for w in ctx.warnings)
    with pytest.raises(FitError, match="soft iron.*spread"):
        fit(table, model="soft_iron")


def test_soft_iron_outside_the_firmware_ranges_is_bounded_not_dropped():
    """A compass whose diagonal over its scale is 1.27 (beyond ArduPilot's and MagFit's 0.8..1.2):
    the soft iron was dropped (scale kept, held out 6.2 uT); it is now fitted held at the range,
    as MagFit bounds it (DIA_X 1.2, the file written, a warning naming the term), and that
    bounded fit still wins on held-out segments."""
    from imupipe.stages.magnetometer.inflight import out_of_range

    table = _narrow_flight(35.0, [[1.40, 0.02, 0.0], [0.02, 0.95, 0.0], [0.0, 0.0, 0.95]])
    out, ctx = fit(table)
    r = out.results
    held = r["metrics"]["held_out_rms_ut"]
    assert r["model"] == "soft_iron" and held["soft_iron"] < 0.5 * held["scale"], held
    m = np.asarray(r["matrix"])
    assert out_of_range(m) == ""
    assert m[0, 0] / np.mean(np.diag(m)) == pytest.approx(1.2, abs=1e-3)
    assert any("held at ArduPilot's ranges: DIA_X 1.2" in w for w in ctx.warnings)


def test_px4_raw_compass_is_judged_against_the_vehicles_own_calibration(tmp_path):
    """A raw PX4 sensor_mag is logged before PX4's CAL_MAGn correction: "as flown" is that
    correction applied (as the judge and PX4's Magnetometer::Correct apply it), not the raw
    field. A vehicle whose CAL_MAG0 already holds the truth flies at the noise (before: its
    raw field, 20+ uT off, was the baseline, so any fit "helped"); a fit cannot beat it on
    held-out segments and is refused, the vehicle keeping its calibration."""
    from imupipe.pipeline.simulate.flight import MAG_DEVICE_ID, flight_ulog
    from imupipe.pipeline.writers.ulog import write_ulog
    from imupipe.readers.dispatch import read_input

    table, truth = simulate("flight", {"duration_s": 60.0, "mag_hz": 25.0}, seed=5)
    data = flight_ulog(table)
    m, off, mot = (np.asarray(truth[k]) for k in ("matrix", "offset", "motor"))
    comp = np.linalg.solve(m, mot) * 1e4 * 1e3  # G/kA, added before S
    params = {"CAL_MAG_COMP_TYP": 2, "CAL_MAG0_ID": MAG_DEVICE_ID}
    for i, a in enumerate("XYZ"):
        params |= {f"CAL_MAG0_{a}OFF": off[i] * 1e4, f"CAL_MAG0_{a}SCALE": m[i, i]}
        params[f"CAL_MAG0_{a}COMP"] = comp[i]
    for (i, j), a in zip(((0, 1), (0, 2), (1, 2)), "XYZ", strict=True):
        params[f"CAL_MAG0_{a}ODIAG"] = m[i, j]
    data.parameters.update(params)
    path = tmp_path / "f.ulg"
    write_ulog(path, data)
    back, _ = read_input(InputSpec(path=path, mag_topic="sensor_mag"))
    stage = MagInflightStage(MagInflightStage.Options())
    ctx = StageContext(name="compass", input_name="f", quiet=True, accept_failed_checks=True)
    m_ = stage.fit(back, ctx).results["metrics"]
    assert m_["residual_rms_ut_before"] > 10.0  # the raw field
    assert m_["residual_rms_ut_as_flown"] < 0.5 and m_["heading_rms_deg_as_flown"] < 1.0
    assert m_["held_out_rms_ut_as_flown"] < 0.5
    assert any("not below as flown" in c for c in ctx.failed_checks), ctx.failed_checks


def _truth_slot(n: int, device: int, truth: dict) -> dict[str, float]:
    """``CAL_MAG<n>_*`` holding the simulated compass's truth (PX4's form: OFF, S, COMP in
    G/kA added before S), so that the vehicle flies it calibrated."""
    m, off, mot = (np.asarray(truth[k]) for k in ("matrix", "offset", "motor"))
    comp = np.linalg.solve(m, mot) * 1e4 * 1e3
    p: dict[str, float] = {f"CAL_MAG{n}_ID": device}
    for i, a in enumerate("XYZ"):
        p |= {f"CAL_MAG{n}_{a}OFF": off[i] * 1e4, f"CAL_MAG{n}_{a}SCALE": m[i, i]}
        p[f"CAL_MAG{n}_{a}COMP"] = comp[i]
    for (i, j), a in zip(((0, 1), (0, 2), (1, 2)), "XYZ", strict=True):
        p[f"CAL_MAG{n}_{a}ODIAG"] = m[i, j]
    return p


@pytest.fixture(scope="module")
def two_compasses(tmp_path_factory):
    """A simulated PX4 flight logging two compasses (``sensor_mag``, ``sensor_mag_1``; devices
    A and B, the same raw field): folder, truth, device ids and a writer of the log under
    given parameters."""
    from imupipe.pipeline.simulate.flight import MAG_DEVICE_ID, flight_ulog
    from imupipe.pipeline.writers.ulog import Topic, write_ulog

    d = tmp_path_factory.mktemp("two_compasses")
    table, truth = simulate("flight", {"duration_s": 60.0, "mag_hz": 10.0}, seed=5)
    data = flight_ulog(table)
    first = next(t for t in data.topics if t.name == "sensor_mag")
    other = MAG_DEVICE_ID + 256
    ids = np.full(len(first.data["x"]), other)
    second = Topic("sensor_mag", 1, {**first.data, "device_id": ids}, first.fields)
    data.topics.append(second)

    def write(name: str, params: dict[str, float]) -> None:
        data.parameters.clear()
        data.parameters.update({"CAL_MAG_COMP_TYP": 2, **params})
        write_ulog(d / name, data)

    return d, truth, (MAG_DEVICE_ID, other), write


def _run_two(d, log: str, out: str, accept: str = ""):
    (d / f"{out}.toml").write_text(
        f'[inputs.f]\npath = "{log}"\ninstances = ["sensor_mag", "sensor_mag_1"]\n'
        f'[[stages]]\ntype = "mag_inflight"\n{accept}'
        f'[output]\ndir = "{out}"\napply_to = []\nrerun = false\nexports = ["px4"]\n'
    )
    return run_cli("run", d / f"{out}.toml", cwd=d)


def test_one_refused_compass_leaves_the_others_fit(two_compasses):
    """instances = [sensor_mag, sensor_mag_1]: compass A flew with its truth in CAL_MAG0 (a fit
    cannot beat it and is refused), compass B with no calibration (its fit is accepted). The
    run goes on: B's CAL_MAGn_* are written, A is left out of the file (the vehicle keeps its
    calibration of it) with one warning naming it and the failed figure, and its results say
    refused. accept_failed_checks = ["sensor_mag"] keeps A's fit too; both refused: the run
    stops on the first refusal, as before, with nothing written."""
    from test_exports import qgc_params

    d, truth, (a, b), write = two_compasses
    write("one.ulg", _truth_slot(0, a, truth))
    proc = _run_two(d, "one.ulg", "one")
    assert proc.returncode == 0, proc.stderr
    refused = [ln for ln in proc.stderr.splitlines() if "sensor_mag refused:" in ln]
    assert len(refused) == 1 and "not below as flown" in refused[0], proc.stderr
    doc = json.loads((d / "one" / "calibration.json").read_text())
    ra, rb = (doc["results"][f"mag_inflight_sensor_mag{k}"] for k in ("", "_1"))
    assert any("not below as flown" in c for c in ra["refused"]) and "refused" not in rb
    assert [e["device"]["device_id"] for e in doc["chain"]] == [b]
    p = qgc_params((d / "one" / "px4_calibration.params").read_text())
    slots = [k for k in p if k.endswith("_ID") and k.startswith("CAL_MAG")]
    assert [p[k] for k in slots] == [b], p
    n = slots[0][7]
    off = np.array([p[f"CAL_MAG{n}_{x}OFF"] for x in "XYZ"])
    assert np.abs(off - np.array(truth["offset"]) * 1e4).max() < 0.01 * truth["field_norm"] * 1e4
    report = (d / "one" / "report.html").read_text()
    assert "refused" in report and "not below as flown" in report

    proc = _run_two(d, "one.ulg", "kept", 'accept_failed_checks = ["sensor_mag"]\n')
    assert proc.returncode == 0, proc.stderr
    p = qgc_params((d / "kept" / "px4_calibration.params").read_text())
    assert sorted(v for k, v in p.items() if k.startswith("CAL_MAG") and k.endswith("_ID")) == [
        a,
        b,
    ]
    doc = json.loads((d / "kept" / "calibration.json").read_text())
    assert doc["results"]["mag_inflight_sensor_mag"]["failed_checks"]

    write("both.ulg", _truth_slot(0, a, truth) | _truth_slot(1, b, truth))
    proc = _run_two(d, "both.ulg", "both")
    assert proc.returncode == 2 and not (d / "both").exists()
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("imupipe: error: stage 'mag_inflight_sensor_mag' ") and (
        "not below as flown" in last and "the fit is not applied" in last
    ), proc.stderr
    bad = _run_two(d, "one.ulg", "bad", 'accept_failed_checks = ["sensor_mag_9"]\n')
    assert bad.returncode == 2 and "sensor_mag_9 not among the instances" in bad.stderr


def test_heading_check_judges_the_samples_the_fit_kept():
    """PX4 log_30's external compass: for 7 s after take-off (8-14 s) the primary EKF (instance
    2) held a yaw ~35 deg off until the selector switched to instance 0; the fit rejects those
    seven samples as outliers. The heading check judged them all the same (12.76 -> 13.44 deg:
    the reference's transient, refused); judged, like the residual checks, on the samples the
    fit kept it passes (6.9 -> 3.9 deg), and PX4's EKF-GSF yaw, which uses no compass, agrees
    the fit helps (benchmarks/magfit_judge.py: 8.95 -> 5.93 deg)."""
    from imupipe.readers.dispatch import read_input

    path = shared_path("logs", "px4_flights_flugdrohne", "log_30_2023-6-7-12-11-06.ulg")
    table, _ = read_input(InputSpec(path=path, mag_topic="sensor_mag_1", imu_topic=""))
    out, ctx = fit(table)
    m = out.results["metrics"]
    assert m["outliers"] == 7 and m["heading_rms_deg_after"] > m["heading_rms_deg_as_flown"]
    assert m["heading_rms_deg_after_inliers"] < 0.7 * m["heading_rms_deg_as_flown_inliers"]


def test_accept_failed_checks_list_needs_instances(tmp_path):
    """A list of instances in accept_failed_checks is for an input with ``instances``; on any
    other it is a config error naming the key (true/false as before)."""
    from imupipe.pipeline.config import load_config
    from imupipe.pipeline.errors import ConfigError

    (tmp_path / "f.ulg").write_bytes(b"")
    (tmp_path / "c.toml").write_text(
        '[inputs.f]\npath = "f.ulg"\n[[stages]]\ntype = "mag_inflight"\n'
        'accept_failed_checks = ["sensor_mag"]\n'
    )
    with pytest.raises(
        ConfigError, match=r"stages\[0\]\.accept_failed_checks: must be true or false$"
    ):
        load_config(tmp_path / "c.toml")


def test_a_compass_left_alone_keeps_a_motor_term_of_another_kind_noted(two_compasses):
    """The vehicle compensates throttle (CAL_MAG_COMP_TYP = 1, compass A's CAL_MAG0_*COMP set);
    only compass B is fitted, with the current, so the file sets CAL_MAG_COMP_TYP = 2 and leaves
    CAL_MAG0 alone: PX4 would read A's throttle terms per kA. The export says so (one type per
    vehicle), naming the slot, the device and both types."""
    d, _, (a, _), write = two_compasses
    write("thr.ulg", {"CAL_MAG_COMP_TYP": 1, "CAL_MAG0_ID": a, "CAL_MAG0_XCOMP": 0.05})
    (d / "thr.toml").write_text(
        '[inputs.f]\npath = "thr.ulg"\ninstances = ["sensor_mag_1"]\n'
        '[[stages]]\ntype = "mag_inflight"\nmotor_source = "current"\n'
        '[output]\ndir = "thr"\napply_to = []\nrerun = false\nexports = ["px4"]\n'
    )
    proc = run_cli("run", d / "thr.toml", cwd=d)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((d / "thr" / "calibration.json").read_text())
    notes = " ".join(doc["exports"]["px4_calibration.params"]["notes"])
    assert f"CAL_MAG0 (device {a}) is not in this file" in notes, notes
    assert "CAL_MAG_COMP_TYP = 1 (throttle)" in notes and "reads them per current" in notes


def test_ardupilot_compass_left_alone_with_a_motor_term_of_another_kind_is_noted():
    """ArduPilot: the file sets COMPASS_MOTCT = 2 for compass 1 while the log's compass 2 (not
    in the file) holds COMPASS_MOT2 for COMPASS_MOTCT = 1: noted; the same kind, or a compass in
    the file, is not."""
    from imupipe.pipeline.exports.ardupilot import stale_motor_terms
    from imupipe.pipeline.exports.common import Export

    logged = {"COMPASS_MOTCT": 1, "COMPASS_MOT2_X": 12.0, "COMPASS_MOT_Z": 3.0}
    rows = [("COMPASS_OFS_X", 1.0), ("COMPASS_MOT_X", 2.0), ("COMPASS_MOTCT", 2)]
    out = Export()
    stale_motor_terms(rows, logged, out)
    notes = [n for ns in out.notes.values() for n in ns]
    assert len(notes) == 1 and "compass 2 is not in this file" in notes[0], notes
    assert "COMPASS_MOTCT = 1 (throttle)" in notes[0] and "per current" in notes[0]
    same = Export()
    stale_motor_terms(rows, logged | {"COMPASS_MOTCT": 2}, same)
    assert not same.notes
