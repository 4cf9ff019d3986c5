"""Issue 17 item 1 for the temperature step: applied batch by batch, it equals ``apply`` on the
whole log bit for bit, yields every row once in order, and holds a bounded number of rows.

The log is bag-like (IMU and temperature in rows of their own, the temperature at 1 Hz beside a
20 Hz IMU), with a gap of 5 minutes, a NaN gyro sample, a NaN temperature sample and an ambient
column; it is cut at random places and at awkward ones: a batch without a temperature sample, a
batch of one row, an empty batch.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from imupipe.readers.table import make_table
from imupipe.stages.steps import apply_chain, apply_chain_stream
from imupipe.stages.thermal.step import TemperatureStep, ThermalMatrixStep

IMU_HZ, TEMP_HZ = 20, 1


@pytest.fixture(scope="module")
def log() -> pa.Table:
    rng = np.random.default_rng(3)
    t_imu = np.arange(0, 1800, 1 / IMU_HZ)
    t_imu = t_imu[(t_imu < 700) | (t_imu > 1000)]  # a 5-minute gap
    t_temp = np.arange(0.37, 1800, 1 / TEMP_HZ)
    t = np.r_[t_imu, t_temp]
    is_temp = np.r_[np.zeros(len(t_imu), bool), np.ones(len(t_temp), bool)]
    order = np.argsort(t, kind="stable")
    t, is_temp = t[order], is_temp[order]
    n = len(t)
    temp = 20 + 15 * np.sin(t / 300) + rng.normal(0, 0.02, n)
    temp[np.flatnonzero(is_temp)[40]] = np.nan
    gyro = rng.normal(0, 1e-3, (n, 3))
    gyro[np.flatnonzero(~is_temp)[500]] = np.nan
    ambient = 20 + 15 * np.sin((t + 100) / 300)
    t_ns = 1_700_000_000_000_000_000 + np.round(t * 1e9).astype(np.int64)
    return make_table(
        t_ns,
        gyro=gyro,
        accel=rng.normal(0, 1e-2, (n, 3)) + [0, 0, 9.8],
        temperature=temp,
        valid={"imu": ~is_temp, "temperature": is_temp},
        extra={"ambient_temperature": np.where(is_temp, ambient, np.nan)},
    )


def step(
    terms: list[str], lag_s: float | None = None, window: int | None = None
) -> TemperatureStep:
    coefficients = [np.linspace(1e-3, 2e-3, len(terms)) * (i + 1) for i in range(3)]
    ranges = {
        "T": [8.0, 32.0], "dT": [-0.05, 0.05], "Ta": [8.0, 32.0], "dTa": [-0.05, 0.05],
        "Ts": [9.0, 31.0], "dTs": [-0.04, 0.04],
    }  # fmt: skip
    return TemperatureStep(
        type="temperature",
        sensor="gyro",
        model="lag" if lag_s else "poly",
        tref=20.0,
        window=window,
        window_s=None if window else 10.0,
        axes=[{"terms": terms, "coefficients": c} for c in coefficients],
        ranges=ranges,
        lag_s=lag_s,
        quiet=True,
    )


def matrix_step() -> ThermalMatrixStep:
    def comps(k: int, base: float) -> list[dict]:
        return [
            {"terms": ["1", "T", "T^2"], "coefficients": [base, 1e-4 * (i + 1), -2e-6]}
            for i in range(k)
        ]

    return ThermalMatrixStep(
        type="thermal_soak",
        sensor="gyro",
        form="gyro",
        tref=25.0,
        range=[10.0, 30.0],
        parameters={
            "scale": comps(3, 1.01),
            "misalignment": comps(6, 1e-3),
            "bias": comps(3, 0.01),
        },
        quiet=True,
    )


STEPS = {
    "T only": step(["1", "T", "T^2"]),
    "T and dT": step(["1", "T", "T^2", "T^3", "dT"]),
    "ambient": step(["1", "T", "Ta", "dTa", "T*dT"]),
    "lag": step(["1", "Ts", "Ts^2", "dTs"], lag_s=150.0),
    "lag, sample blocks": step(["1", "Ts", "dTs", "dT"], lag_s=40.0, window=37),
    "soak matrix": matrix_step(),
}


def cuts(table: pa.Table, rng: np.random.Generator) -> list[int]:
    """Random cut points plus awkward ones: a one-row batch, an empty batch, and a batch lying
    between two temperature rows (no temperature sample in it)."""
    n = len(table)
    temp_rows = np.flatnonzero(
        table.column("temperature").is_valid().to_numpy(zero_copy_only=False)
    )
    k = temp_rows[100]
    awkward = [k + 1, k + 5, k + 6, k + 6, 20_000, 20_001]
    return sorted({*rng.integers(1, n, 25).tolist(), *awkward}) + [k + 6]


def batches(table: pa.Table, points: list[int]) -> list[pa.Table]:
    edges = [0, *sorted(points), len(table)]
    return [table.slice(a, b - a) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def bits(table: pa.Table) -> dict[str, np.ndarray]:
    return {
        name: np.asarray(table.column(name).to_numpy(zero_copy_only=False)).view(np.uint64)
        if pa.types.is_floating(table.column(name).type)
        else table.column(name).to_numpy(zero_copy_only=False)
        for name in table.column_names
    }


@pytest.mark.parametrize("name", list(STEPS))
def test_stream_equals_whole_bit_for_bit(log, name):
    s = STEPS[name]
    whole = s.apply(log)
    assert not np.array_equal(
        whole.column("gyro_x").to_numpy(zero_copy_only=False),
        log.column("gyro_x").to_numpy(zero_copy_only=False),
        equal_nan=True,
    )
    rng = np.random.default_rng(7)
    for _ in range(3):
        parts = list(s.apply_stream(batches(log, cuts(log, rng))))
        streamed = pa.concat_tables(parts)
        assert len(streamed) == len(log)
        got, want = bits(streamed), bits(whole)
        for column, values in want.items():
            np.testing.assert_array_equal(got[column], values, err_msg=f"{name}: {column}")


def test_stream_holds_a_bounded_window(log):
    """Rows held = rows read - rows yielded stays under one batch plus about three 10 s blocks
    (200 IMU rows each) and the temperature samples around them, whatever the log's length."""
    s = STEPS["lag"]
    size = 1000
    read = 0
    held = []

    def source():
        nonlocal read
        for b in batches(log, list(range(size, len(log), size))):
            read += len(b)
            yield b

    written = 0
    for part in s.apply_stream(source()):
        held.append(read - written)
        written += len(part)
    assert written == len(log)
    window = 3 * 10 * (IMU_HZ + TEMP_HZ)
    assert max(held) <= size + window + 2 * IMU_HZ * 10, max(held)


def test_chain_of_steps_streams_like_the_whole_chain(log):
    chain = [STEPS["soak matrix"], STEPS["T and dT"], STEPS["lag"]]
    whole = apply_chain(log, chain)
    streamed = pa.concat_tables(list(apply_chain_stream(batches(log, [1, 2, 5000, 5001]), chain)))
    for column, values in bits(whole).items():
        np.testing.assert_array_equal(bits(streamed)[column], values, err_msg=column)


def test_stream_without_temperature_fails_with_one_line(log):
    imu_only = log.filter(log.column("temperature").is_null())
    with pytest.raises(Exception, match="no temperature samples"):
        list(STEPS["T only"].apply_stream(batches(imu_only, [100, 2000])))
