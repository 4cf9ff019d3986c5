"""CSV files as they come (issues 13 and 18): odd layouts read as the plain file does, empty and
NaN cells keep their rows, hostile files end in one line naming the file, line and column."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from imupipe.readers.csv.reader import read_csv
from imupipe.readers.errors import ReadError
from imupipe.readers.spec import CsvMapping, InputSpec
from imupipe.readers.table import counts, sensor

from conftest import run_cli

HEADER = "t_ns,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z"
ROWS = ["0,1,2,3,4,5,6", "10,1.5,2.5,3.5,4.5,5.5,6.5", "20,7,8,9,10,11,12"]
SPACED = "t ns\tgyro x\tgyro y\tgyro z\taccel x\taccel y\taccel z"


def _lines(rows: list[str], sep: str = "\n", header: str = HEADER) -> str:
    return header + sep + sep.join(rows) + sep


ODD = {
    "crlf": _lines(ROWS, "\r\n").encode(),
    "cr only": _lines(ROWS, "\r").encode(),
    "utf-8 bom": b"\xef\xbb\xbf" + _lines(ROWS).encode(),
    "quoted cells": _lines(
        ['"' + r.replace(",", '","') + '"' for r in ROWS],
        header='"' + HEADER.replace(",", '","') + '"',
    ).encode(),
    "trailing delimiter": _lines([r + "," for r in ROWS]).encode(),
    "trailing delimiter, header too": _lines([r + "," for r in ROWS], header=HEADER + ",").encode(),
    "no newline at the end": _lines(ROWS)[:-1].encode(),
    "semicolons, decimal commas": _lines(
        [r.replace(",", ";").replace(".", ",") for r in ROWS], header=HEADER.replace(",", ";")
    ).encode(),
    "blanks after commas": _lines(
        [r.replace(",", ", ") for r in ROWS], header=HEADER.replace(",", ", ")
    ).encode(),
    "tabs, header of spaces": _lines(
        [r.replace(",", "\t") for r in ROWS], header=" ".join(HEADER.split(","))
    ).encode(),
    "a line of blanks": (HEADER + "\n" + ROWS[0] + "\n   \n" + "\n".join(ROWS[1:]) + "\n").encode(),
    "blank lines and metadata": ("logger v2\n\nrate: 100 Hz\n" + _lines(ROWS)).encode(),
    "header written as a comment": _lines(ROWS, header="# " + HEADER).encode(),
    "latin-1 header": _lines([r + ",20" for r in ROWS], header=HEADER + ",temp (\xb0C)").encode(
        "latin-1"
    ),
}


@pytest.mark.parametrize("name", list(ODD))
def test_odd_layouts_read_like_the_plain_file(tmp_path, name):
    path = tmp_path / "odd.csv"
    path.write_bytes(ODD[name])
    table, _ = read_csv(InputSpec(path=path, csv=CsvMapping(temperature="temp (\xb0C)")))
    np.testing.assert_array_equal(table.column("t_ns").to_numpy(), [0, 10, 20])
    np.testing.assert_array_equal(sensor(table, "gyro").values[:, 0], [1, 1.5, 7])
    np.testing.assert_array_equal(sensor(table, "accel").values[:, 2], [6, 6.5, 12])
    assert counts(table) == ({"imu": 3, "temperature": 3} if "latin" in name else {"imu": 3})


def test_tab_separated_names_with_spaces(tmp_path):
    path = tmp_path / "t.tsv"
    path.write_text(_lines([r.replace(",", "\t") for r in ROWS], header=SPACED))
    m = CsvMapping(
        time="t ns", gyro=["gyro x", "gyro y", "gyro z"], accel=["accel x", "accel y", "accel z"]
    )
    table, _ = read_csv(InputSpec(path=path, csv=m))
    np.testing.assert_array_equal(sensor(table, "gyro").values[:, 2], [3, 3.5, 9])


def test_seconds_with_decimal_commas_are_exact(tmp_path):
    path = tmp_path / "s.csv"
    path.write_text("t;gx;gy;gz\n1700000000,0025;1,5;0;0\n1700000000,005;2,5;0;0\n")
    m = CsvMapping(time="t", time_unit="s", gyro=["gx", "gy", "gz"], accel=None)
    table, _ = read_csv(InputSpec(path=path, csv=m))
    np.testing.assert_array_equal(
        table.column("t_ns").to_numpy(), [1_700_000_000_002_500_000, 1_700_000_000_005_000_000]
    )
    np.testing.assert_array_equal(sensor(table, "gyro").values[:, 0], [1.5, 2.5])


# -- empty and NaN cells ---------------------------------------------------------------------


def _imu_csv(path: Path, n: int = 6000, edit=None) -> list[str]:
    t0 = 1_700_000_000_000_000_000
    rows = [f"{t0 + i * 10_000_000},0.01,0.02,0.03,0.1,0.2,9.81" for i in range(n)]
    if edit:
        edit(rows)
    path.write_text(_lines(rows))
    return rows


def test_an_empty_accel_cell_keeps_its_imu_sample_as_nan(tmp_path):
    """Issue 13: 6000 rows in, 6000 IMU samples out; the empty cell is NaN, counted once."""

    def edit(rows):
        rows[100] = rows[100].replace(",0.2,", ",,")
        rows[200] = rows[200].replace(",0.02,", ",nan,")

    path = tmp_path / "nan.csv"
    _imu_csv(path, edit=edit)
    table, warnings = read_csv(InputSpec(path=path))
    assert counts(table) == {"imu": 6000}
    accel = sensor(table, "accel").values
    gyro = sensor(table, "gyro").values
    assert np.isnan(accel[100, 1]) and np.isnan(gyro[200, 1])
    assert np.isfinite(accel[[99, 101]]).all() and accel[100, 0] == 0.1
    assert np.isfinite(np.delete(gyro, 200, axis=0)).all()
    assert [w for w in warnings if "NaN" in w] == [
        f"{path}: 2 of 6000 IMU samples have empty or NaN cells (gyro_y 1, accel_y 1); "
        "kept as NaN, left out of fits"
    ]


def test_a_row_of_nan_is_a_sample_a_row_of_empty_cells_is_not(tmp_path):
    path = tmp_path / "rates.csv"
    path.write_text(
        "t_ns,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z\n"
        "0,1,2,3,4,5,6,7,8,9\n"
        "1,nan,nan,nan,nan,nan,nan,,,\n"  # an IMU message whose values were NaN
        "2,,,,,,,nan,8,9\n"  # a magnetometer sample with a NaN field
        "3,,,,,,,,,\n"  # a row of no stream
    )
    table, warnings = read_csv(InputSpec(path=path))
    assert counts(table) == {"imu": 2, "mag": 2}
    np.testing.assert_array_equal(sensor(table, "gyro").t_ns, [0, 1])
    np.testing.assert_array_equal(sensor(table, "mag").t_ns, [0, 2])
    assert any("1 of 2 IMU samples" in w for w in warnings)
    assert any("1 of 2 magnetometer samples" in w and "mag_x 1" in w for w in warnings)


def test_run_writes_every_row_of_a_csv_with_an_empty_cell(tmp_path):
    """Through the CLI: the corrected MCAP holds one Imu message per row, NaN where empty."""
    from imupipe.readers.mcap.reader import read_mcap

    path = tmp_path / "a.csv"
    _imu_csv(path, edit=lambda rows: rows.__setitem__(100, rows[100].replace(",0.2,", ",,")))
    (tmp_path / "cfg.toml").write_text(
        '[inputs.a]\npath = "a.csv"\n\n[[stages]]\ntype = "gyro_bias"\n\n'
        '[output]\ndir = "out"\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 0, proc.stderr
    out, _ = read_mcap(InputSpec(path=tmp_path / "out" / "a.mcap"))
    assert counts(out) == {"imu": 6000}
    accel = sensor(out, "accel").values
    assert np.isnan(accel[100, 1]) and np.isfinite(np.delete(accel, 100, axis=0)).all()


# -- times -----------------------------------------------------------------------------------


def test_an_ns_cell_written_as_a_float_is_exact(tmp_path):
    """Issue 18: one `1.7e18` cell used to turn the column into floats and shift half the
    stamps by up to 128 ns; now every stamp is the exact integer."""
    path = tmp_path / "f.csv"
    rows = _imu_csv(path, edit=lambda r: r.__setitem__(0, "1.7e18" + r[0][19:]))
    table, _ = read_csv(InputSpec(path=path))
    expected = [1_700_000_000_000_000_000 + i * 10_000_000 for i in range(len(rows))]
    np.testing.assert_array_equal(table.column("t_ns").to_numpy(), expected)
    assert table.column("t_ns").type == pa.int64()


@pytest.mark.parametrize(
    "unit,cells,expected",
    [
        ("s", ["1700000000.0025", "1700000000.005"], [1700000000002500000, 1700000000005000000]),
        (
            "ms",
            ["1700000000002.5", "1.700000000005e12"],
            [1700000000002500000, 1700000000005000000],
        ),
        ("us", ["0.0015", "2"], [2, 2000]),  # 1.5 ns rounds half to even
        ("s", ["0.007500000000000001", "0.01"], [7_500_000, 10_000_000]),
    ],
)
def test_time_units_are_parsed_exactly(tmp_path, unit, cells, expected):
    path = tmp_path / "t.csv"
    path.write_text("t,gx,gy,gz\n" + "".join(f"{c},0,0,0\n" for c in cells))
    m = CsvMapping(time="t", time_unit=unit, gyro=["gx", "gy", "gz"], accel=None)
    table, _ = read_csv(InputSpec(path=path, csv=m))
    np.testing.assert_array_equal(table.column("t_ns").to_numpy(), expected)


BAD_TIMES = [
    ("-5", "line 3, column 't_ns': negative time '-5'"),
    ("99999999999999999999", "line 3, column 't_ns': '99999999999999999999' is out of range"),
    ("1000.5", "line 3, column 't_ns': '1000.5' is not a whole number of nanoseconds"),
    ("1e30", "line 3, column 't_ns': '1e30' is out of range"),
    ("nan", "line 3, column 't_ns': 'nan' is not a finite time"),
    ("12:00", "line 3, column 't_ns': '12:00' is not a number"),
    ("", "line 3, column 't_ns': empty time"),
    # beyond Decimal's exponent range (was decimal.Overflow, a traceback)
    ("10e999999", "line 3, column 't_ns': '10e999999' has an exponent of five digits or more"),
    # pyarrow 26's decimal cast crashes the process on this one (was a segmentation fault)
    ("1e-9999999", "line 3, column 't_ns': '1e-9999999' has an exponent of five digits or more"),
]


@pytest.mark.parametrize("cell,message", BAD_TIMES)
def test_bad_time_cells_name_line_and_column(tmp_path, cell, message):
    path = tmp_path / "b.csv"
    path.write_text(_lines(["0,1,2,3,4,5,6", cell + ",1,2,3,4,5,6", "20,1,2,3,4,5,6"]))
    with pytest.raises(ReadError) as info:
        read_csv(InputSpec(path=path))
    assert str(info.value).startswith(f"{path}: {message}")


def test_time_unit_overflow_is_an_error(tmp_path):
    path = tmp_path / "o.csv"
    path.write_text("t,gx,gy,gz\n0,0,0,0\n10000000000000,0,0,0\n")
    m = CsvMapping(time="t", time_unit="s", gyro=["gx", "gy", "gz"], accel=None)
    with pytest.raises(ReadError, match=r"line 3, column 't': '10000000000000' is out of range"):
        read_csv(InputSpec(path=path, csv=m))


# -- hostile files ---------------------------------------------------------------------------


def test_two_columns_of_one_name(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text(HEADER + ",gyro_x\n" + "\n".join(r + ",9" for r in ROWS) + "\n")
    with pytest.raises(ReadError, match=r"line 1: column 'gyro_x' \(csv.gyro\) appears 2 times"):
        read_csv(InputSpec(path=path))
    # a repeated name nobody maps is no problem
    path.write_text(HEADER + ",note,note\n" + "\n".join(r + ",a,b" for r in ROWS) + "\n")
    table, _ = read_csv(InputSpec(path=path))
    assert counts(table) == {"imu": 3}


def test_a_line_with_other_fields_is_named(tmp_path):
    path = tmp_path / "f.csv"
    lines = [f"{i},1,2,3,4,5,6" for i in range(50)]
    lines[30] += ",7"
    lines.insert(20, "")  # a blank line before it: still the right line number
    path.write_text(_lines(lines))
    with pytest.raises(ReadError, match=r"f.csv: line 33: 8 fields where the data have 7"):
        read_csv(InputSpec(path=path))


def test_a_commented_line_gets_a_hint(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text(_lines(["0,1,2,3,4,5,6", "# paused", "20,1,2,3,4,5,6"] * 10))
    with pytest.raises(ReadError, match=r"line 3: 1 field where .* set csv.comment"):
        read_csv(InputSpec(path=path))
    table, _ = read_csv(InputSpec(path=path, csv=CsvMapping(comment="#")))
    assert table.num_rows == 20


def test_a_bad_cell_is_named_after_blank_lines(tmp_path):
    path = tmp_path / "b.csv"
    lines = [f"{i},1,2,3,4,5,6" for i in range(20)]
    lines.insert(5, "")
    lines.insert(5, "")
    lines[15] = "13,1,2,x3,4,5,6"
    path.write_text(_lines(lines))
    with pytest.raises(ReadError, match=r"b.csv: line 17, column 'gyro_z': 'x3' is not a number"):
        read_csv(InputSpec(path=path))


def _dev_zero(tmp_path: Path) -> Path:
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero here")
    link = tmp_path / "zero.csv"
    link.symlink_to("/dev/zero")
    return link


def _folder(tmp_path: Path) -> Path:
    path = tmp_path / "folder.csv"
    path.mkdir()
    return path


def _bytes(data: bytes):
    def make(tmp_path: Path) -> Path:
        path = tmp_path / "x.csv"
        path.write_bytes(data)
        return path

    return make


@pytest.mark.parametrize(
    "make,message",
    [
        (_dev_zero, "zero.csv: not a regular file"),
        (_folder, "folder.csv: not a regular file"),
        (_bytes(b"\x89PNG\r\n\x1a\n\x00\x00" + bytes(range(256)) * 8), "x.csv: not a text file"),
        (_bytes(b"1," * 50_000), "no line break in the first 64 KiB"),
        (_bytes("t_ns,gyro_x\n".encode("utf-16")), "UTF-16 text"),
        (_bytes(b""), "the file is empty"),
        (_bytes(b"\n\n  \n"), "the file is empty"),
        (_bytes((HEADER + "\n").encode()), "the file has a header but no rows"),
    ],
)
def test_files_that_are_no_csv(tmp_path, make, message):
    with pytest.raises(ReadError, match=message):
        read_csv(InputSpec(path=make(tmp_path)))


HOSTILE = {
    "dup.csv": (HEADER + ",gyro_x\n0,1,2,3,4,5,6,7\n", "appears 2 times"),
    "neg.csv": (HEADER + "\n-5,1,2,3,4,5,6\n", "line 2, column 't_ns': negative time"),
    "ovf.csv": (HEADER + "\n99999999999999999999,1,2,3,4,5,6\n", "out of range"),
    "text.csv": (HEADER + "\n0,1,2,3,4,five,6\n", "line 2, column 'accel_y': 'five'"),
}


@pytest.mark.parametrize("name", list(HOSTILE))
def test_hostile_csv_through_the_cli_is_one_line_and_exit_2(tmp_path, name):
    text, needle = HOSTILE[name]
    (tmp_path / name).write_text(text)
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.a]\npath = "{name}"\n\n[[stages]]\ntype = "gyro_bias"\n\n[output]\ndir = "out"\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml", "--quiet")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and name in lines[0], proc.stderr
    assert not (tmp_path / "out").exists()


def test_is_number_answers_as_its_two_expressions():
    """Issue 39: ``is_number`` refuses cells by their commas before matching; the answer is the
    expressions' own for every cell: numbers with either decimal mark, blanks, signs,
    exponents, nan/inf in any case, whole lines as the sniff splits them by another delimiter,
    and random strings over the characters that matter."""
    import random

    from imupipe.readers.csv.layout import COMMA_NUMBER, NUMBER, is_number

    cells = [
        "0.01117506322170389", "-1,5", "1,5e-3", ",25", "1,", "1,,5", "1,5,6", " 2 ", "\t3\t",
        "NaN", "-INF", "Infinity", "+.5E+3", "1.", ".", ",", "", " ", "e5", "1e", "1_000",
        "1700000000000000000,0.0111,-0.0148,0.0030,0.0689,-0.028,9.84",
        "0,011;-0,014;9,8", "1.5,2.5", "1;5", "١٢٣", "1\u00a0",
    ]  # fmt: skip
    rng = random.Random(39)
    alphabet = "0123456789,.;eE+- \tnaiftyNAIFTY"
    cells += ["".join(rng.choices(alphabet, k=rng.randint(0, 12))) for _ in range(20_000)]
    for cell in cells:
        for decimal in (".", ","):
            expected = bool(NUMBER.match(cell) or (decimal == "," and COMMA_NUMBER.match(cell)))
            assert is_number(cell, decimal) == expected, (cell, decimal)
