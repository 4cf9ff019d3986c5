"""Issue 16: calibrations from other tools as chain steps (``imupipe import``).

Magneto: its own published result for the ICM-20948 tumbling set (``../shared/data/calib/
magneto_icm20948_jremington``, ``cal_mag_1.lis``), applied by imupipe, gives the norm spread the
folder's README reports for Magneto's B/Ainv (2.75 % of the mean). imu_tk: a ``.calib`` written
as ``CalibratedTriad_::save`` prints it. Kalibr: the intrinsics imupipe exports come back as the
same correction (in Kalibr's frame).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.pipeline.calibration_file import load_calibration
from imupipe.pipeline.errors import ImupipeError
from imupipe.pipeline.imports import import_calibration
from imupipe.readers.table import make_table, sensor
from imupipe.stages.steps import apply_chain

from conftest import run_cli, shared_path

T = np.array([[1.0, -0.0033, 0.0092], [0.0, 1.0, -0.0213], [0.0, 0.0, 1.0]])
K = np.diag([2.413e-3, 2.4269e-3, 2.412e-3])
B = np.array([33123.6, 33275.1, 32364.7])


def _eigen(m: np.ndarray) -> str:
    """A matrix as Eigen's ``operator<<`` prints it (space-padded columns)."""
    rows = np.atleast_2d(m)
    return "\n".join(" ".join(f"{v:>12.6g}" for v in row) for row in rows)


def test_magneto_result_reproduces_its_published_spread(tmp_path):
    lis = shared_path("calib", "magneto_icm20948_jremington", "cal_mag_1.lis")
    raw = np.loadtxt(
        shared_path("calib", "magneto_icm20948_jremington", "icm_20948_cal_mag.csv"), delimiter=","
    )
    proc = run_cli("import", "magneto", lis, "--out", tmp_path / "cal.json")
    assert proc.returncode == 0, proc.stderr
    doc, steps = load_calibration(tmp_path / "cal.json")
    entry = doc["chain"][0]
    assert entry["offset"] == [-156.70, -52.79, -141.07]
    assert entry["matrix"][1] == [-0.01142, 1.09539, 0.00927]
    assert entry["fitted_on"] == {"input": None, "path": str(lis), "format": "magneto"}
    table = make_table(np.arange(len(raw), dtype=np.int64), mag=raw)
    norm = np.linalg.norm(sensor(apply_chain(table, steps), "mag").values, axis=1)
    assert 100 * norm.std() / norm.mean() == pytest.approx(2.75, abs=0.01)


def test_imu_tk_pair_and_units(tmp_path):
    acc = tmp_path / "acc.calib"
    acc.write_text(f"{_eigen(T)}\n\n{_eigen(K)}\n\n{_eigen(B[:, None])}\n\n")
    gyro = tmp_path / "gyro.calib"
    gyro.write_text(
        f"{_eigen(np.eye(3))}\n\n{_eigen(np.eye(3) * 2e-4)}\n\n{_eigen(np.ones((3, 1)))}\n"
    )
    proc = run_cli("import", "imu_tk", acc, gyro, "--out", tmp_path / "cal.json")
    assert proc.returncode == 0, proc.stderr
    doc, _ = load_calibration(tmp_path / "cal.json")
    a, g = doc["chain"]
    assert (a["sensor"], g["sensor"]) == ("accel", "gyro")
    np.testing.assert_allclose(a["matrix"], T @ K, rtol=1e-5)
    np.testing.assert_allclose(a["offset"], B, rtol=1e-5)
    # numbers given in g: the offset becomes m/s^2, the dimensionless matrix stays
    proc = run_cli("import", "imu_tk", acc, "--unit", "g", "--out", tmp_path / "g.json")
    assert proc.returncode == 0, proc.stderr
    doc, _ = load_calibration(tmp_path / "g.json")
    np.testing.assert_allclose(doc["chain"][0]["offset"], B * 9.80665, rtol=1e-5)


def test_into_appends_and_bad_files_are_one_line(tmp_path):
    acc = tmp_path / "acc.calib"
    acc.write_text(f"{_eigen(T)}\n{_eigen(K)}\n{_eigen(B[:, None])}\n")
    run_cli("import", "imu_tk", acc, "--out", tmp_path / "first.json")
    proc = run_cli(
        "import",
        "imu_tk",
        acc,
        "--sensor",
        "gyro",
        "--into",
        tmp_path / "first.json",
        "--out",
        tmp_path / "both.json",
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "both.json").read_text())
    assert [e["sensor"] for e in doc["chain"]] == ["accel", "gyro"]
    (tmp_path / "short.calib").write_text("1 2 3\n")
    for tool, files, kw, message in (
        ("imu_tk", [tmp_path / "short.calib"], {}, "holds 21 numbers"),
        ("magneto", [acc], {}, "Combined bias vector B"),
        ("kalibr", [acc], {}, "no Kalibr IMU block"),
        ("imu_tk", [acc], {"unit": "furlong"}, "--unit furlong: not a accel unit"),
        ("imu_tk", [tmp_path / "none.calib"], {}, "no such file"),
    ):
        with pytest.raises(ImupipeError, match=message):
            import_calibration(tool, files, tmp_path / "x.json", **kw)
    proc = run_cli("import", "imu_tk", tmp_path / "short.calib", "--out", tmp_path / "x.json")
    assert proc.returncode == 2 and "holds 21 numbers" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.json").exists()
