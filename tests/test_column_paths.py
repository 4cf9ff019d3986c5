"""Issue 17 item 2: the Allan run works column by column on views of the table (no (n, 3) copy
of a long input). The column-wise paths give what the (n, 3) ones give."""

from __future__ import annotations

import numpy as np

from imupipe.pipeline.report.figures import decimate, decimate_columns
from imupipe.readers.table import make_table, sensor, sensor_columns
from imupipe.stages.stillness import stillness


def _table(n: int = 5000, mag_every: int = 0):
    rng = np.random.default_rng(3)
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 2_500_000
    gyro, accel = rng.normal(0, 0.01, (n, 3)), rng.normal(0, 0.1, (n, 3)) + [0, 0, 9.81]
    if not mag_every:
        return make_table(t, gyro=gyro, accel=accel)
    mag_rows = np.arange(n) % mag_every == 0
    return make_table(
        t,
        gyro=gyro,
        accel=accel,
        mag=rng.normal(0, 5e-5, (n, 3)),
        valid={"imu": ~mag_rows, "mag": mag_rows},
    )


def test_sensor_columns_are_views_of_the_table_and_equal_sensor():
    table = _table()
    t_ns, columns = sensor_columns(table, "gyro")
    assert not any(c.flags.owndata for c in columns)  # the table's own buffers
    data = sensor(table, "gyro")
    np.testing.assert_array_equal(t_ns, data.t_ns)
    np.testing.assert_array_equal(np.column_stack(columns), data.values)


def test_sensor_columns_of_a_stream_that_does_not_hold_every_row():
    table = _table(mag_every=7)
    for name in ("accel", "mag"):
        t_ns, columns = sensor_columns(table, name)
        data = sensor(table, name)
        np.testing.assert_array_equal(t_ns, data.t_ns)
        np.testing.assert_array_equal(np.column_stack(columns), data.values)
        assert np.isfinite(data.values).all()


def test_stillness_by_columns_equals_by_arrays():
    table = _table(n=40_000)
    gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
    whole = stillness(gyro.t_ns, gyro.values, accel.values)
    cols = stillness(gyro.t_ns, sensor_columns(table, "gyro")[1], sensor_columns(table, "accel")[1])
    assert whole.excursion == cols.excursion and whole.accel_spread == cols.accel_spread
    np.testing.assert_array_equal(whole.gyro_1s.means, cols.gyro_1s.means)
    np.testing.assert_array_equal(whole.gyro_1s.t_ns, cols.gyro_1s.t_ns)


def test_decimate_columns_equals_decimate():
    table = _table(n=10_007)
    t_ns, columns = sensor_columns(table, "accel")
    for points in (100, 999, 20_000):
        a_t, a_v = decimate(t_ns, np.column_stack(columns), points)
        b_t, b_v = decimate_columns(t_ns, columns, points)
        np.testing.assert_array_equal(a_t, b_t)
        np.testing.assert_array_equal(a_v, b_v)
