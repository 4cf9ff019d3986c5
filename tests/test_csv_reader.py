"""The CSV reader: mapping, units, delimiters, header or none, rate_hz, streams at other rates."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.pipeline.errors import ReadError
from imupipe.readers.csv_reader import read_csv
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
