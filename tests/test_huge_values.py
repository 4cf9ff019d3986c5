"""Cells of 1e308 are numbers, not samples any sensor reports: every fitting stage leaves them
out with one counted warning (as NaN and Inf; ``readers.table.MAX_MAGNITUDE``), fits the rest
and prints no numpy RuntimeWarning; the corrected log keeps them as they came."""

from __future__ import annotations

import numpy as np
import pytest

from imupipe.pipeline.simulate import simulate, write_log

from conftest import run_cli

CASES = {
    # stage, scenario, its parameters, columns damaged
    "allan": ("allan", "static", {"rate_hz": 100.0, "duration_s": 300.0, "temperature": None}),
    "accel_calibration": ("accel_calibration", "poses", {}),
    "gyro_calibration": ("gyro_calibration", "poses", {}),
    "mag_calibration": ("mag_calibration", "mag", {}),
    "temperature": ("temperature", "thermal", {}),
}
DAMAGED = {
    "allan": ("gyro_x", "accel_z"),
    "accel_calibration": ("accel_x", "accel_y"),
    "gyro_calibration": ("gyro_y", "accel_x"),
    "mag_calibration": ("mag_x", "mag_y"),
    "temperature": ("gyro_x", "temperature"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_huge_cells_are_left_out_with_one_warning(tmp_path, case):
    stage, scenario, params = CASES[case]
    table, _ = simulate(scenario, params, 3)
    path = tmp_path / "a.csv"
    write_log(path, table)
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    for k, column in enumerate(DAMAGED[case]):
        col = header.index(column)
        row = next(  # a row that holds this column, a third and two thirds in
            r
            for r in range(len(lines) * (k + 1) // 3, len(lines))
            if lines[r].split(",")[col] not in ("", "nan")
        )
        cells = lines[row].split(",")
        cells[col] = "1e308" if k == 0 else "-1e308"
        lines[row] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    (tmp_path / "cfg.toml").write_text(
        f'[inputs.a]\npath = "a.csv"\n\n[[stages]]\ntype = "{stage}"\n\n'
        '[output]\ndir = "out"\nrerun = false\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml")
    assert proc.returncode == 0, proc.stderr
    assert "RuntimeWarning" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    warned = [line for line in proc.stderr.splitlines() if "beyond 1e+100" in line]
    assert len(warned) == 1, proc.stderr
    assert f"[{stage}]" in warned[0]
    if (tmp_path / "out" / "a.mcap").exists():  # the correction keeps every sample
        from imupipe.readers.mcap.reader import read_mcap
        from imupipe.readers.spec import InputSpec

        out, _ = read_mcap(InputSpec(path=tmp_path / "out" / "a.mcap"))
        values = np.concatenate(
            [out.column(c).to_numpy(zero_copy_only=False) for c in DAMAGED[case]]
        )
        assert np.isinf(values).any() or (np.abs(values[np.isfinite(values)]) > 1e300).any()
