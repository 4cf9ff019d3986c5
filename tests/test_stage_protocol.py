"""The shared stage protocol: quality checks that stop a fit unless accepted, NaN samples
excluded from fits with one warning, and streamed steps equal to whole-table steps."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from imupipe.readers.table import make_table, sensor
from imupipe.stages.base import StageContext
from imupipe.stages.errors import FitError
from imupipe.stages.steps import LinearStep, apply_chain, apply_chain_stream


def test_failed_check_stops_unless_accepted() -> None:
    ctx = StageContext(name="s", input_name="i", quiet=True)
    ctx.check(True, "never shown")
    with pytest.raises(FitError, match="residual 5 mg > 1 mg; the fit is not applied"):
        ctx.check(False, "residual 5 mg > 1 mg")
    ctx = StageContext(name="s", input_name="i", quiet=True, accept_failed_checks=True)
    ctx.check(False, "residual 5 mg > 1 mg")
    assert ctx.failed_checks == ["residual 5 mg > 1 mg"]
    assert "accepted" in ctx.warnings[0]


def test_finite_drops_and_counts_nan() -> None:
    t = np.arange(10, dtype=np.int64) * 10_000_000
    mag = np.ones((10, 3))
    mag[[2, 5], 1] = np.nan
    data = sensor(make_table(t, mag=mag), "mag")
    ctx = StageContext(name="s", input_name="i", quiet=True)
    kept = ctx.finite(data, "magnetometer")
    assert len(kept) == 8 and list(kept.rows) == [0, 1, 3, 4, 6, 7, 8, 9]
    assert ctx.warnings == ["2 of 10 magnetometer samples are NaN or Inf; fitted on 8"]
    with pytest.raises(FitError, match="8 finite magnetometer samples of 10"):
        ctx.finite(data, "magnetometer", minimum=9)


def test_stream_equals_whole() -> None:
    rng = np.random.default_rng(0)
    n = 1000
    t = np.arange(n, dtype=np.int64) * 1_000_000
    table = make_table(t, gyro=rng.normal(size=(n, 3)), accel=rng.normal(size=(n, 3)))
    steps = [LinearStep("x", "gyro", np.eye(3) * 2, np.ones(3))]
    whole = apply_chain(table, steps)
    parts = [table.slice(i, 137) for i in range(0, n, 137)]
    streamed = pa.concat_tables(apply_chain_stream(iter(parts), steps))
    assert streamed.equals(whole)
