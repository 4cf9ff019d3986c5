"""Issue 16: PX4 ULog logs into the common table, checked field for field against pyulog's own
``ULog`` objects, on PX4/pyulog's test logs (BSD-3: ``tests/data/px4_ulog`` holds the small one,
``../shared/data/logs/px4_ulog`` the others).

The gyro bias imupipe finds is compared with the log's own calibration: PX4 subtracts
``CAL_GYROn_{X,Y,Z}OFF`` from the raw ``sensor_gyro`` of device ``CAL_GYROn_ID`` (PX4-Autopilot
``src/lib/sensor_calibration/Gyroscope.hpp``, ``Correct``: ``data - _thermal_offset -
_offset``), so a still stretch of a raw instance must average to that offset, and
``sensor_combined`` (already corrected) to a small residual.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyulog import ULog

from imupipe.pipeline.inspect_log import inspect
from imupipe.readers.dispatch import detect_format, read_input
from imupipe.readers.errors import ImupipeError, ReadError
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import counts, metadata, sensor
from imupipe.stages.base import StageContext
from imupipe.stages.gyro_bias import GyroBiasStage

from conftest import TEST_DATA, run_cli, shared_path
from helpers import decode_mcap, stamps_ns, vec

SMALL = TEST_DATA / "px4_ulog" / "sample_log_small.ulg"


def _read(path: Path, **kw) -> tuple:
    return read_input(InputSpec(path=path, **kw))


def _xyz(data: dict, fmt: str) -> np.ndarray:
    """(n, 3) float64 of fields ``fmt.format(i)``, i = 0, 1, 2 (``gyro_rad[{}]``), or of
    ``x, y, z`` when ``fmt`` is ``"xyz"``."""
    names = list("xyz") if fmt == "xyz" else [fmt.format(i) for i in range(3)]
    return np.column_stack([data[n] for n in names]).astype(np.float64)


def test_detect_format():
    assert detect_format(SMALL) == "ulog"


def test_sensor_combined_field_for_field():
    path = shared_path("logs", "px4_ulog", "sample.ulg")
    table, warnings = _read(path)
    ref = ULog(str(path)).get_dataset("sensor_combined").data
    imu = sensor(table, "gyro")
    assert len(imu) == 17070  # the folder's README
    assert np.array_equal(imu.t_ns, ref["timestamp"].astype(np.int64) * 1000)
    assert np.array_equal(imu.values, _xyz(ref, "gyro_rad[{}]"))
    assert np.array_equal(sensor(table, "accel").values, _xyz(ref, "accelerometer_m_s2[{}]"))
    # old firmware: the magnetometer rides in sensor_combined, each sample repeated until the
    # next; every distinct sample is read once, at timestamp + magnetometer_timestamp_relative
    rel = ref["magnetometer_timestamp_relative"].astype(np.int64)
    t_mag = ref["timestamp"].astype(np.int64) + rel
    distinct, first = np.unique(t_mag[rel != 2**31 - 1], return_index=True)
    mag = sensor(table, "mag")
    assert np.array_equal(mag.t_ns, distinct * 1000)
    rows = np.flatnonzero(rel != 2**31 - 1)[first]
    assert np.array_equal(mag.values, _xyz(ref, "magnetometer_ga[{}]")[rows] * 1e-4)
    meta = metadata(table)
    assert meta["format"] == "ulog"
    assert meta["topics"] == {"imu": "sensor_combined", "mag": "sensor_combined/magnetometer"}
    assert meta["px4"]["calibrated"] == {"imu": True, "mag": True}
    assert meta["device_id"]["imu"] == meta["px4"]["parameters"]["CAL_GYRO0_ID"] == 2162688
    assert meta["px4"]["parameters"]["CAL_GYRO0_YOFF"] == pytest.approx(-0.0188062135)
    (note,) = [w for w in warnings if "not carried" in w]
    assert "more)" in note and len(note) < 400  # a count and the first few, not every topic


def test_raw_instance_field_for_field():
    ulog = ULog(str(SMALL))
    for n in range(3):
        table, _ = _read(SMALL, imu_topic=f"sensor_gyro_{n}" if n else "sensor_gyro")
        gyro = ulog.get_dataset("sensor_gyro", n).data
        accel = ulog.get_dataset("sensor_accel", n).data
        imu = sensor(table, "gyro")
        assert np.array_equal(imu.t_ns, gyro["timestamp_sample"].astype(np.int64) * 1000)
        assert np.array_equal(imu.values, _xyz(gyro, "xyz"))
        # the FIFO driver stamps a device's accel and gyro samples identically: paired exactly
        assert np.array_equal(gyro["timestamp_sample"], accel["timestamp_sample"])
        assert np.array_equal(sensor(table, "accel").values, _xyz(accel, "xyz"))
        temp = sensor(table, "temperature")
        assert np.array_equal(temp.values[:, 0], gyro["temperature"].astype(np.float64))
        meta = metadata(table)
        assert meta["instance"] == {"imu": n, "temperature": n}
        assert meta["device_id"]["imu"] == int(gyro["device_id"][0])
        assert meta["px4"]["calibrated"] == {"imu": False}
        assert meta["topics"]["temperature"] == f"{meta['topics']['imu']}/temperature"
    # log time: the publication timestamp
    table, _ = _read(SMALL, imu_topic="sensor_gyro_1", time="log")
    ref = ulog.get_dataset("sensor_gyro", 1).data["timestamp"].astype(np.int64) * 1000
    assert np.array_equal(sensor(table, "gyro").t_ns, ref)


def test_default_streams_follow_px4():
    table, warnings = _read(SMALL)
    meta = metadata(table)
    # sensor_combined (corrected), the corrected vehicle_magnetometer, and the temperature of
    # the gyro PX4 selected (sensor_selection.gyro_device_id = sensor_gyro instance 0)
    assert meta["topics"] == {
        "imu": "sensor_combined",
        "mag": "vehicle_magnetometer",
        "temperature": "sensor_gyro/temperature",
    }
    assert counts(table) == {"imu": 1298, "mag": 319, "temperature": 6}
    assert meta["device_id"]["temperature"] == 2424842
    ref = ULog(str(SMALL)).get_dataset("vehicle_magnetometer").data
    assert np.array_equal(sensor(table, "mag").values, _xyz(ref, "magnetometer_ga[{}]") * 1e-4)


def test_unknown_topic_names_the_candidates():
    with pytest.raises(
        ReadError, match="imu_topic 'sensor_gyro_7' is not in the log.*sensor_gyro_2"
    ):
        _read(SMALL, imu_topic="sensor_gyro_7")
    with pytest.raises(ReadError, match="mag_topic 'sensor_baro' cannot fill it"):
        _read(SMALL, mag_topic="sensor_baro")


def _bias(table) -> np.ndarray:
    ctx = StageContext(name="gyro_bias", input_name="log", quiet=True)
    return np.array(GyroBiasStage(GyroBiasStage.Options()).fit(table, ctx).results["bias"])


def test_raw_gyro_bias_is_px4s_offset():
    """A raw instance at rest averages to PX4's CAL_GYROn_*OFF of its device (PX4 subtracts the
    offset): within 4 mrad/s on every axis of all three gyros, whose offsets span 70 mrad/s."""
    params = ULog(str(SMALL)).initial_parameters
    for n in range(3):
        table, _ = _read(SMALL, imu_topic=f"sensor_gyro_{n}" if n else "sensor_gyro")
        device = metadata(table)["device_id"]["imu"]
        slot = next(k for k in range(4) if params.get(f"CAL_GYRO{k}_ID") == device)
        px4 = np.array([params[f"CAL_GYRO{slot}_{a}OFF"] for a in "XYZ"])
        found = _bias(table)
        assert np.abs(found - px4).max() < 4e-3, (n, found, px4)
        assert np.abs(found + px4).max() > 8e-3  # the opposite sign would not fit


def test_sensor_combined_holds_px4s_correction():
    """sample.ulg's sensor_combined is already corrected by CAL_GYRO0: its still stretch (8 s to
    the end, before and after a hand wave) averages to a residual of a few mrad/s, far from the
    18.8 mrad/s the y offset removed."""
    path = shared_path("logs", "px4_ulog", "sample.ulg")
    table, _ = _read(path)
    stage = GyroBiasStage(GyroBiasStage.Options(interval=[8.0, 68.0]))
    ctx = StageContext(name="gyro_bias", input_name="log", quiet=True)
    found = np.array(stage.fit(table, ctx).results["bias"])
    params = metadata(table)["px4"]["parameters"]
    offsets = np.array([params[f"CAL_GYRO0_{a}OFF"] for a in "XYZ"])
    assert np.abs(found).max() < 3.5e-3
    assert abs(found[1] - offsets[1]) > 0.015


def test_run_and_convert_ulog(tmp_path):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        f'[inputs.flight]\npath = "{SMALL}"\n\n[[stages]]\ntype = "gyro_bias"\n\n'
        f'[output]\ndir = "{tmp_path / "out"}"\nrerun = false\n'
    )
    proc = run_cli("run", cfg)
    assert proc.returncode == 0, proc.stderr
    assert "not carried" in proc.stderr
    written = decode_mcap(tmp_path / "out" / "flight.mcap")
    assert {t: len(m) for t, m in written.items()} == {
        "sensor_combined": 1298,
        "vehicle_magnetometer": 319,
        "sensor_gyro/temperature": 6,
    }
    table, _ = _read(SMALL)
    assert np.array_equal(stamps_ns(written["sensor_combined"]), sensor(table, "gyro").t_ns)
    bias = np.array(
        json.loads((tmp_path / "out" / "calibration.json").read_text())["chain"][0]["offset"]
    )
    got = vec(written["sensor_combined"], "angular_velocity")
    assert np.allclose(got, sensor(table, "gyro").values - bias)
    proc = run_cli(
        "convert",
        "--calibration",
        tmp_path / "out" / "calibration.json",
        "--out",
        tmp_path / "conv",
        SMALL,
    )
    assert proc.returncode == 0, proc.stderr
    again = decode_mcap(tmp_path / "conv" / "sample_log_small.mcap")
    assert np.allclose(vec(again["sensor_combined"], "angular_velocity"), got)


def test_inspect_ulog():
    proc = run_cli("inspect", SMALL, "--json")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["format"] == "ulog"
    assert info["topics"]["sensor_gyro_2"]["instance"] == 2
    assert info["topics"]["sensor_gyro_2"]["device_id"] == 2621474
    assert info["topics"]["sensor_gyro_2"]["count"] == 6
    assert info["streams"]["imu"]["topic"] == "sensor_combined"
    assert info["streams"]["imu"]["px4_calibrated"] is True
    assert info["parameters"]["CAL_GYRO2_ID"] == 2621474
    text = run_cli("inspect", SMALL, "--imu-topic", "sensor_gyro_1").stdout
    assert "stream imu: sensor_gyro_1 (6 samples, device id 3670050, raw)" in text


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "not a readable ULog file"),
        (b"hello world" * 100, "not a readable ULog file"),
    ],
)
def test_bad_ulog_is_one_line(tmp_path, content, message):
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(content)
    proc = run_cli("inspect", bad)
    assert proc.returncode == 2
    assert message in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_truncated_ulog_reads_what_is_there(tmp_path):
    """A ULog has no index: a cut file gives the messages before the cut, none invented."""
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(SMALL.read_bytes()[: SMALL.stat().st_size // 2])
    table, _ = _read(cut)
    full, _ = _read(SMALL)
    n = counts(table)["imu"]
    assert 0 < n < counts(full)["imu"]
    assert np.array_equal(sensor(table, "gyro").values, sensor(full, "gyro").values[:n])


@settings(
    max_examples=int(os.environ.get("IMUPIPE_FUZZ_EXAMPLES", "20")),
    derandomize="IMUPIPE_FUZZ_EXAMPLES" not in os.environ,  # CI: the same 20; set it to explore
    deadline=10000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    cut=st.floats(0.0, 1.0),
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), max_size=20),
)
def test_damaged_ulog_is_an_imupipe_error_or_reads(tmp_path, cut, flips):
    """Truncations and byte flips: read_input and inspect give a table or one ImupipeError
    (pyulog's own complaints become a warning, nothing is printed)."""
    data = bytearray(SMALL.read_bytes())
    for where, xor in flips:
        data[min(int(where * len(data)), len(data) - 1)] ^= xor
    if cut < 0.5:
        data = data[: int(cut * 2 * len(data))]
    path = tmp_path / "damaged.ulg"
    path.write_bytes(bytes(data))
    for read in (lambda: read_input(InputSpec(path=path)), lambda: inspect(InputSpec(path=path))):
        with contextlib.suppress(ImupipeError):
            read()


PIXHAWK6C = TEST_DATA / "px4_ulog" / "pixhawk6c_bmi055.ulg"
"""A Pixhawk 6C log whose instance-0 gyro (0x42000a) and accel (0x41000a) are two devices of
one BMI055; the fixture's README."""


def test_two_device_chip_is_paired_as_px4_pairs_it():
    ulog = ULog(str(PIXHAWK6C))
    gyro = ulog.get_dataset("sensor_gyro", 0).data
    accel = ulog.get_dataset("sensor_accel", 0).data
    pair = ulog.get_dataset("vehicle_imu", 0).data
    assert int(gyro["device_id"][0]) != int(accel["device_id"][0])
    assert int(pair["accel_device_id"][0]) == int(accel["device_id"][0])
    table, warnings = _read(PIXHAWK6C, imu_topic="sensor_gyro")
    imu = sensor(table, "gyro")
    assert np.array_equal(imu.values, _xyz(gyro, "xyz"))
    # each gyro sample with the accel sample nearest in timestamp_sample (this log samples
    # the raw topics at about 1 Hz, the two devices at different instants: warned about)
    near = np.abs(
        gyro["timestamp_sample"].astype(np.int64)[:, None]
        - accel["timestamp_sample"].astype(np.int64)[None, :]
    ).argmin(axis=1)
    got = sensor(table, "accel").values
    paired = ~np.isnan(got[:, 0])
    assert paired.sum() >= 4
    assert np.array_equal(got[paired], _xyz(accel, "xyz")[near[paired]])
    assert any("paired by nearest timestamp_sample" in w for w in warnings)
    assert metadata(table)["device_id"]["imu"] == 0x42000A


def test_same_instance_without_vehicle_imu(monkeypatch):
    """Without vehicle_imu, PX4's own rule: accel instance i with gyro instance i."""
    from imupipe.readers.ulog import reader as ulog_reader

    monkeypatch.setattr(
        ulog_reader, "READ_TOPICS", tuple(t for t in ulog_reader.READ_TOPICS if t != "vehicle_imu")
    )
    table, _ = _read(PIXHAWK6C, imu_topic="sensor_gyro")
    accel = ULog(str(PIXHAWK6C)).get_dataset("sensor_accel", 0).data
    got = sensor(table, "accel").values
    assert np.isin(got[~np.isnan(got[:, 0]), 0], accel["x"].astype(np.float64)).all()


@pytest.mark.parametrize("path", [PIXHAWK6C, SMALL])
def test_every_vehicle_imu_instance_as_rates(path):
    ulog = ULog(str(path))
    instances = [d for d in ulog.data_list if d.name == "vehicle_imu"]
    assert len(instances) >= 2
    for d in instances:
        key = "vehicle_imu" if d.multi_id == 0 else f"vehicle_imu_{d.multi_id}"
        table, _ = _read(path, imu_topic=key)
        ref = d.data
        dt_a = ref["delta_angle_dt"].astype(np.float64) * 1e-6  # microseconds (VehicleImu.msg)
        dt_v = ref["delta_velocity_dt"].astype(np.float64) * 1e-6
        gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
        assert np.array_equal(gyro.t_ns, ref["timestamp_sample"].astype(np.int64) * 1000)
        assert np.allclose(gyro.values, _xyz(ref, "delta_angle[{}]") / dt_a[:, None], rtol=1e-12)
        assert np.allclose(
            accel.values, _xyz(ref, "delta_velocity[{}]") / dt_v[:, None], rtol=1e-12
        )
        # a corrected IMU at rest-ish on the ground: |a| near g
        assert 8.0 < np.median(np.linalg.norm(accel.values, axis=1)) < 11.5
        meta = metadata(table)
        assert meta["px4"]["calibrated"]["imu"] is True
        assert meta["device_id"]["imu"] == int(ref["gyro_device_id"][0])
        # the temperature of the gyro device vehicle_imu integrates
        gyros = {
            int(g.data["device_id"][0]): g.multi_id
            for g in ulog.data_list
            if g.name == "sensor_gyro"
        }
        want = gyros[int(ref["gyro_device_id"][0])]
        assert meta["topics"]["temperature"].startswith(
            "sensor_gyro" if want == 0 else f"sensor_gyro_{want}"
        )


def test_every_ulog_imu_is_a_candidate():
    info = json.loads(run_cli("inspect", PIXHAWK6C, "--json").stdout)
    for key in ("vehicle_imu", "vehicle_imu_1", "sensor_gyro", "sensor_gyro_1"):
        text = run_cli("inspect", PIXHAWK6C, "--imu-topic", key).stdout
        assert f"stream imu: {key} (" in text, text
    assert info["streams"]["imu"]["topic"] == "sensor_combined"


@pytest.mark.parametrize(
    "path, key, scale", [(SMALL, "sensor_baro_1", 100.0), (PIXHAWK6C, "sensor_baro", 1.0)]
)
def test_baro_pressure_and_temperature(path, key, scale):
    """A barometer as the temperature stream fills ``pressure`` (Pa) on the same rows: PX4
    v1.11 (SMALL) logged millibar, v1.13 (PIXHAWK6C) pascal."""
    multi = int(key.rsplit("_", 1)[1]) if key[-1].isdigit() else 0
    ref = ULog(str(path)).get_dataset("sensor_baro", multi).data
    table, _ = _read(path, temperature_topic=key)
    temp = sensor(table, "temperature")
    assert np.array_equal(temp.values[:, 0], ref["temperature"].astype(np.float64))
    rows = np.flatnonzero(~np.isnan(table.column("temperature").to_numpy(zero_copy_only=False)))
    pressure = table.column("pressure").to_numpy(zero_copy_only=False)
    assert np.array_equal(pressure[rows], ref["pressure"].astype(np.float64) * scale)
    assert table.column("pressure").null_count == len(table) - len(rows)
    assert 9e4 < np.median(pressure[rows]) < 1.1e5
    table, _ = _read(path, temperature_topic=key, time="log")  # rows at the publication time
    assert np.array_equal(
        table.column("pressure").drop_null().to_numpy(), ref["pressure"].astype(np.float64) * scale
    )


ULOGS = {
    "sample.ulg": lambda: shared_path("logs", "px4_ulog", "sample.ulg"),
    "sample_log_small.ulg": lambda: SMALL,
    "sample_logging_tagged_and_default_params.ulg": lambda: shared_path(
        "logs", "px4_ulog", "sample_logging_tagged_and_default_params.ulg"
    ),
    "pixhawk6c_bmi055.ulg": lambda: PIXHAWK6C,
}
"""pyulog's test logs (BSD-3) and the MCAP project's Pixhawk 6C fixture (MIT)."""


@pytest.mark.parametrize("name", list(ULOGS))
def test_every_imu_of_every_log_is_pyulogs(name):
    """Every IMU candidate of each log, value for value against pyulog: sensor_combined,
    vehicle_imu[_N] (delta over dt), sensor_gyro[_N] with its partner's accel samples."""
    from imupipe.readers.ulog.reader import UlogFile, accel_partner, candidates

    path = ULOGS[name]()
    f = UlogFile(path)
    imus = candidates(f)["imu"]
    assert imus
    for key in imus:
        inst = f.instances[key]
        table, _ = _read(path, imu_topic=key)
        gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
        ref = inst.data
        if inst.name == "sensor_combined":
            want_g, want_a = _xyz(ref, "gyro_rad[{}]"), _xyz(ref, "accelerometer_m_s2[{}]")
        elif inst.name == "vehicle_imu":
            want_g = _xyz(ref, "delta_angle[{}]") / (ref["delta_angle_dt"][:, None] * 1e-6)
            want_a = _xyz(ref, "delta_velocity[{}]") / (ref["delta_velocity_dt"][:, None] * 1e-6)
        else:
            partner = accel_partner(f, inst)
            want_g, want_a = _xyz(ref, "xyz"), _xyz(partner.data, "xyz")
        t = ref["timestamp_sample" if "timestamp_sample" in ref else "timestamp"]
        order = np.argsort(t, kind="stable")
        assert np.array_equal(gyro.t_ns, t[order].astype(np.int64) * 1000), key
        assert np.allclose(gyro.values, want_g[order], rtol=1e-12, atol=0), key
        if inst.name == "sensor_gyro":  # each paired accel sample is one of the partner's
            got = accel.values[~np.isnan(accel.values[:, 0])]
            assert len(got) and all(any(np.array_equal(g, w) for w in want_a) for g in got), key
        else:
            assert np.allclose(accel.values, want_a[order], rtol=1e-12, atol=0), key


def test_a_zero_timestamp_sample_means_unset():
    """PX4 v1.14's vehicle_gps_position leaves timestamp_sample 0 in every message: the header
    time is then the message's timestamp (before: 0 ns, so no compass sample lay within the GPS
    stream's span and mag_inflight refused the flight); a set one is kept."""
    from imupipe.readers.ulog.reader import Instance

    inst = Instance(
        "vehicle_gps_position",
        0,
        {
            "timestamp": np.array([1_000_000, 1_500_000, 2_000_000], dtype=np.uint64),
            "timestamp_sample": np.array([0, 1_499_000, 0], dtype=np.uint64),
        },
    )
    header, log = inst.stamps("header")
    assert header.tolist() == [1_000_000_000, 1_499_000_000, 2_000_000_000]
    assert log.tolist() == [1_000_000_000, 1_500_000_000, 2_000_000_000]


def test_px4_flights_with_two_compasses_name_them_and_calibrate(tmp_path):
    """A real PX4 v1.14 flight with two compasses: without mag_topic the compass stage names
    the compasses it saw; with instances every compass gets its CAL_MAGn_* (before: "0
    magnetometer samples lie within the attitude and GPS streams' time span")."""
    log = shared_path("logs", "px4_flights_flugdrohne", "log_20_2023-6-7-10-52-56.ulg")
    (tmp_path / "a.toml").write_text(
        f'[inputs.f]\npath = "{log}"\n[[stages]]\ntype = "mag_inflight"\n[output]\ndir = "a"\n'
    )
    proc = run_cli("run", "a.toml", cwd=tmp_path)
    assert proc.returncode == 2
    assert "several compasses (vehicle_magnetometer, vehicle_magnetometer_1, sensor_mag, " in (
        proc.stderr
    )
    (tmp_path / "b.toml").write_text(
        f'[inputs.f]\npath = "{log}"\ninstances = ["sensor_mag", "sensor_mag_1"]\n'
        '[[stages]]\ntype = "mag_inflight"\n[output]\ndir = "b"\n'
    )
    proc = run_cli("run", "b.toml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    text = (tmp_path / "b" / "px4_calibration.params").read_text()
    for n in (0, 1):
        assert f"CAL_MAG{n}_XOFF" in text and f"CAL_MAG{n}_ID" in text
