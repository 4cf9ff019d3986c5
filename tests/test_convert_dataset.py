"""Issue 16: ``convert --parquet`` writes a dataset that pyarrow, polars and DuckDB each open
with one call; units as field metadata, times as timestamps, the calibration in the file; and
``convert`` checks each log against the sensor the calibration was fitted on (``fitted_on``)."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from test_convert import CHAIN, expected

from imupipe.pipeline.convert.fleet import convert
from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap

from conftest import run_cli


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    d = tmp_path_factory.mktemp("dataset")
    (d / "logs" / "robot2").mkdir(parents=True)
    a, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 100.0}, seed=1)
    m, _ = simulate("mag", {"duration_s": 1.0, "rate_hz": 50.0}, seed=2)
    write_mcap(d / "logs" / "a.mcap", a)
    write_mcap(d / "logs" / "robot2" / "m.mcap", m)
    cal = d / "cal.json"
    cal.write_text(json.dumps({"chain": CHAIN}))
    summary = convert([d / "logs"], cal, d / "out", jobs=1, parquet=True)
    assert not summary.failed and len(summary.converted) == 2
    rows = a.num_rows * 2 + m.num_rows * 2  # Imu + Temperature / Imu + MagneticField
    return d / "out" / "parquet", rows, a


def test_pyarrow_dataset_opens_the_folder(dataset):
    import pyarrow.dataset as ds

    folder, rows, a = dataset
    assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")) == [
        "a.parquet", "robot2", "robot2/m.parquet"
    ]  # fmt: skip
    table = ds.dataset(folder, format="parquet").to_table()
    assert table.num_rows == rows
    assert set(table.column("log").to_pylist()) == {"a", "robot2/m"}
    assert table.schema.field("t_ns").type == pa.timestamp("ns", tz="UTC")
    assert table.schema.field("gyro_x").metadata == {b"unit": b"rad/s"}
    assert table.schema.field("accel_cov").metadata == {b"unit": b"(m/s^2)^2"}
    imu = table.filter(pc.and_(pc.equal(table.column("log"), "a"), table["gyro_x"].is_valid()))
    np.testing.assert_array_equal(imu.column("t_ns").cast("int64"), a.column("t_ns"))
    got = np.column_stack([imu.column(f"accel_{x}").to_numpy() for x in "xyz"])
    np.testing.assert_allclose(got, expected(a, "accel"), rtol=0, atol=1e-9)
    meta = json.loads(pq.read_schema(folder / "a.parquet").metadata[b"imupipe"])
    assert meta["calibration"]["chain"] == CHAIN and meta["topics"]["imu"] == "/imu/data"


def test_polars_opens_the_folder(dataset):
    pl = pytest.importorskip("polars", reason="polars is not installed (pip install polars)")
    folder, rows, _ = dataset
    frame = pl.scan_parquet(folder / "**" / "*.parquet").collect()
    assert frame.height == rows
    assert str(frame.schema["t_ns"]) == "Datetime(time_unit='ns', time_zone='UTC')"
    assert sorted(frame["log"].unique().to_list()) == ["a", "robot2/m"]


def test_duckdb_opens_the_folder(dataset):
    duckdb = pytest.importorskip("duckdb", reason="duckdb is not installed (pip install duckdb)")
    folder, rows, _ = dataset
    ((n, logs),) = duckdb.sql(
        f"select count(*), count(distinct log) from read_parquet('{folder}/**/*.parquet')"
    ).fetchall()
    assert (n, logs) == (rows, 2)


def _fitted(chain, **fitted_on):
    return [dict(step, fitted_on=fitted_on) for step in chain]


def test_provenance_warn_refuse_unknown(tmp_path):
    a, _ = simulate("static", {"duration_s": 0.5, "rate_hz": 100.0}, seed=3)
    write_mcap(tmp_path / "a.mcap", a)  # topics /imu/data, /imu/temperature; frame "imu"
    same = {"topics": {"imu": "/imu/data"}, "frame_id": {"imu": "imu"}, "instance": {"imu": 0}}
    other = {"topics": {"imu": "/robot1/imu"}, "frame_id": {"imu": "imu"}}
    cases = {"same": _fitted(CHAIN, **same), "other": _fitted(CHAIN[:1], **other), "old": CHAIN}
    for name, chain in cases.items():
        (tmp_path / f"{name}.json").write_text(json.dumps({"chain": chain}))

    lines = {}
    for name in cases:
        proc = run_cli("convert", "--calibration", tmp_path / f"{name}.json", "--out",
                       tmp_path / name, tmp_path / "a.mcap")  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        (lines[name],) = read_manifest(tmp_path / name)
        if name == "old":  # one note, once
            assert proc.stderr.count("does not record which sensor") == 1, proc.stderr
        if name == "other":
            assert "imupipe: warning:" in proc.stderr and "/robot1/imu" in proc.stderr
    assert lines["same"]["provenance"] == "match"
    assert lines["old"]["provenance"] == "unknown"
    assert lines["other"]["provenance"].startswith("mismatch: chain[0] (accel_calibration)")
    assert "'/robot1/imu' for imu, this log has '/imu/data'" in lines["other"]["provenance"]

    proc = run_cli("convert", "--calibration", tmp_path / "other.json", "--out",
                   tmp_path / "refused", "--on-mismatch", "refuse", tmp_path / "a.mcap")  # fmt: skip
    assert proc.returncode == 1
    (error,) = proc.stderr.strip().splitlines()
    assert "not the sensor of the calibration" in error and "/robot1/imu" in error
    assert not (tmp_path / "refused" / "a.mcap").exists()
    (line,) = read_manifest(tmp_path / "refused")
    assert line["status"] == "failed" and "not the sensor" in line["error"]
