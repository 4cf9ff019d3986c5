"""The CSV reader: mapping, units, delimiters, header or none, rate_hz, streams at other rates."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.pipeline.errors import ReadError
from imupipe.readers.csv.reader import read_csv
from imupipe.readers.spec import G0, CsvMapping, InputSpec
from imupipe.readers.table import counts, sensor


def read(path, **mapping):
    table, warnings = read_csv(InputSpec(path=path, csv=CsvMapping(**mapping)))
    return table, warnings


def test_units_are_converted_to_si(tmp_path):
    p = tmp_path / "u.csv"
    p.write_text(
        "time_ms,gx,gy,gz,ax,ay,az,mx,my,mz,temp_c\n"
        "0,180,0,-90,1,0,0,10,20,30,21.5\n"
        "10,0,0,0,0,0,-1,0,0,0,22\n"
    )
    table, _ = read(
        p,
        time="time_ms",
        time_unit="ms",
        gyro=["gx", "gy", "gz"],
        gyro_unit="deg/s",
        accel=["ax", "ay", "az"],
        accel_unit="g",
        mag=["mx", "my", "mz"],
        mag_unit="uT",
        temperature="temp_c",
    )
    np.testing.assert_array_equal(table.column("t_ns").to_numpy(), [0, 10_000_000])
    np.testing.assert_allclose(sensor(table, "gyro").values[0], [np.pi, 0, -np.pi / 2], rtol=1e-15)
    np.testing.assert_allclose(sensor(table, "accel").values[:, 0], [G0, 0])
    np.testing.assert_allclose(sensor(table, "mag").values[0], [1e-5, 2e-5, 3e-5], rtol=1e-15)
    np.testing.assert_allclose(sensor(table, "temperature").values[:, 0], [21.5, 22.0])


@pytest.mark.parametrize(
    "unit,factor", [("T", 1.0), ("nT", 1e-9), ("gauss", 1e-4), ("mgauss", 1e-7)]
)
def test_mag_units(tmp_path, unit, factor):
    p = tmp_path / "m.csv"
    p.write_text("t,mx,my,mz\n0,1.5,2,3\n")
    table, _ = read(
        p,
        time="t",
        time_unit="s",
        gyro=None,
        accel=None,
        mag=["mx", "my", "mz"],
        mag_unit=unit,
        temperature=None,
    )
    np.testing.assert_allclose(sensor(table, "mag").values[0], np.array([1.5, 2, 3]) * factor)


def test_whitespace_no_header_columns_by_index(tmp_path):
    # imu_tk's .mat layout: leading spaces, runs of spaces, no header
    p = tmp_path / "x.mat"
    p.write_text(
        "   2.9840000e-02   3.3108000e+04   3.3329000e+04   3.6429000e+04\n"
        "   3.9857000e-02   3.3096000e+04   3.3336000e+04   3.6437000e+04\n"
    )
    table, _ = read(
        p,
        time=0,
        time_unit="s",
        accel=[1, 2, 3],
        accel_unit="raw",
        gyro=None,
        mag=None,
        temperature=None,
    )
    assert table.num_rows == 2
    np.testing.assert_array_equal(table.column("t_ns").to_numpy(), [29_840_000, 39_857_000])
    np.testing.assert_array_equal(sensor(table, "accel").values[1], [33096, 33336, 36437])


def test_rate_hz_without_time_column(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text("gyro_x;gyro_y;gyro_z;accel_x;accel_y;accel_z\n" + "0;0;0;0;0;9.8\n" * 4)
    table, _ = read(p, time=None, rate_hz=400.0)
    np.testing.assert_array_equal(
        table.column("t_ns").to_numpy(), [0, 2_500_000, 5_000_000, 7_500_000]
    )


def test_streams_at_different_rates_keep_their_rows(tmp_path):
    # the magnetometer at a quarter of the IMU rate: empty cells mean "no sample"
    rows = []
    for i in range(8):
        mag = "1e-5,2e-5,3e-5" if i % 4 == 0 else ",,"
        rows.append(f"{i * 1000},0,0,0,0,0,9.8,{mag}")
    p = tmp_path / "multi.csv"
    p.write_text(
        "t_ns,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z\n"
        + "\n".join(rows)
        + "\n"
    )
    table, _ = read(p)
    assert counts(table) == {"imu": 8, "mag": 2}
    np.testing.assert_array_equal(sensor(table, "mag").t_ns, [0, 4000])


def test_out_of_order_rows_are_sorted_stably_and_counted(tmp_path):
    p = tmp_path / "o.csv"
    p.write_text(
        "t_ns,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n"
        "30,3,0,0,0,0,0\n10,1,0,0,0,0,0\n10,2,0,0,0,0,0\n20,4,0,0,0,0,0\n"
    )
    table, warnings = read(p)
    np.testing.assert_array_equal(table.column("t_ns").to_numpy(), [10, 10, 20, 30])
    np.testing.assert_array_equal(sensor(table, "gyro").values[:, 0], [1, 2, 4, 3])
    assert any("out of time order" in w for w in warnings)


def test_bad_time_unit_is_an_error(tmp_path):
    p = tmp_path / "b.csv"
    p.write_text("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0,0,0,0,0,0,0\n")
    with pytest.raises(ReadError, match="time_unit"):
        read(p, time="t", time_unit="h")


DATA = __import__("pathlib").Path(__file__).resolve().parent / "data"


def test_metadata_lines_are_skipped_and_give_the_rate():
    """The MPU-6050 files (tomisuarez2/ImuCalibration) start with `Fs,100`, `Logging Type,0`,
    `Initialization time,36.5`, `Waiting time,3`, then the header: read as they are."""
    path = DATA / "mpu6050_tomisuarez" / "example_data_calibration.csv"
    table, warnings = read(
        path,
        gyro=["gx", "gy", "gz"],
        gyro_unit="raw",
        accel=["ax", "ay", "az"],
        accel_unit="raw",
    )
    lines = path.read_text().splitlines()
    assert table.num_rows == len(lines) - 5
    assert any(
        "skipped 4 line(s) before the header: Fs,100 | Logging Type,0" in w for w in warnings
    )
    assert any("rate 100 Hz" in w for w in warnings)
    t = table.column("t_ns").to_numpy()
    assert t[1] - t[0] == 10_000_000
    first = [float(v) for v in lines[5].split(",")]
    np.testing.assert_array_equal(sensor(table, "accel").values[0], first[:3])
    np.testing.assert_array_equal(sensor(table, "gyro").values[0], first[3:])


def test_metadata_rate_with_decimals_and_mag_only():
    path = DATA / "qmc5883l_tomisuarez" / "noisy_raw_data.csv"
    table, warnings = read(path, mag=["mx", "my", "mz"], mag_unit="raw")
    assert any("rate 50 Hz" in w for w in warnings)
    assert counts(table) == {"mag": len(path.read_text().splitlines()) - 3}


def test_scale_and_offset_convert_raw_registers():
    """The PAN thermal log's `temp` is a raw register: degC = raw / 256 - 231 (25 degC at
    65536 counts, 256 LSB/degC); its gyro columns are logged 2x too large."""
    path = DATA / "pan_tvc_gyro" / "TVCtest3_7_20.csv"
    gyro = ["gyrox rad/s", "gyroy rad/s", "gyroz rad/s"]
    table, _ = read(
        path,
        time="time (ms)",
        time_unit="ms",
        gyro=gyro,
        accel=None,
        mag=None,
        temperature="temp",
        scale={"temp": 1 / 256, **{g: 0.5 for g in gyro}},
        offset={"temp": -231.0},
    )
    temp = sensor(table, "temperature").values[:, 0]
    assert temp[0] == pytest.approx(25 + (65236 - 65536) / 256)
    assert 15.0 < temp.min() < 16.5 and 23.0 < temp.max() < 24.5
    assert sensor(table, "gyro").values[0, 0] == pytest.approx(-6.53e-2 * 0.5)


def test_scale_must_name_a_mapped_column(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("t_ns,gyro_x,gyro_y,gyro_z\n0,1,2,3\n")
    with pytest.raises(ReadError, match=r"csv.scale.gx: not a mapped column"):
        read(p, scale={"gx": 2.0})


def test_comment_lines_and_explicit_skip_rows(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text(
        "logger v2\nsome words here\n"
        "t_ns,gyro_x,gyro_y,gyro_z\n# paused\n0,1,2,3\n  # resumed\n10,4,5,6\n"
    )
    table, _ = read(p, skip_rows=2, comment="#")
    np.testing.assert_array_equal(sensor(table, "gyro").values, [[1, 2, 3], [4, 5, 6]])


def test_metadata_without_rate_needs_a_time(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("device,abc\nax,ay,az\n1,2,3\n4,5,6\n")
    with pytest.raises(ReadError, match="column 't_ns' .csv.time. not found"):
        read(p, gyro=None, accel=["ax", "ay", "az"])
