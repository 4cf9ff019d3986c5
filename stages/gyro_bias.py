"""``gyro_bias`` stage: gyroscope bias from a static recording (seed 002).

Model: ``bias = mean(gyro)`` over the static samples (all of them, or those in ``interval =
[start_s, end_s]`` seconds after the input's first sample); ``corrected = gyro - bias`` (rad/s).
Added to the chain as ``matrix = I``, ``offset = bias``. Warns when the data is not static: when
any 1-second mean of the gyro departs from the overall mean by more than ``motion_threshold``
rad/s, or the accelerometer norm's 1-second means spread by more than 0.05 g.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from imupipe.pipeline.table import SensorData, has_stream, sensor
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.blocks import block_means
from imupipe.stages.steps import LinearStep

G0 = 9.80665


def select_interval(data: SensorData, interval: list[float] | None) -> np.ndarray:
    """Boolean mask of the samples within ``interval`` seconds of the first sample (all if None)."""
    if interval is None:
        return np.ones(len(data), dtype=bool)
    t = data.t_s
    return (t >= interval[0]) & (t <= interval[1])


class GyroBiasStage(Stage):
    type = "gyro_bias"
    sensors = ("gyro",)
    corrects = True

    @dataclass
    class Options:
        interval: list[float] | None = None
        """[start_s, end_s], seconds from the input's first sample; default the whole input."""
        motion_threshold: float = 0.02
        """rad/s: a 1 s mean further than this from the overall mean means the IMU moved."""

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        if not has_stream(table, "imu"):
            raise ctx.fail("the input has no gyroscope samples")
        gyro = sensor(table, "gyro")
        interval = self.options.interval
        if interval is not None and (len(interval) != 2 or interval[1] <= interval[0]):
            raise ctx.fail("'interval' must be [start_s, end_s] with end_s > start_s")
        mask = select_interval(gyro, interval)
        n = int(mask.sum())
        if n < 2:
            raise ctx.fail(f"only {n} gyroscope samples in interval {interval}")
        values = gyro.values[mask]
        t_ns = gyro.t_ns[mask]
        if not np.isfinite(values).all():
            bad = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
            raise ctx.fail(f"non-finite gyroscope sample at sample {bad}")
        bias = values.mean(axis=0)
        std = values.std(axis=0, ddof=1)

        second = block_means(t_ns, values, window_s=1.0)
        excursion = float(np.abs(second.means - bias).max()) if len(second.counts) else 0.0
        accel = sensor(table, "accel").values[mask]
        norm_means = block_means(t_ns, np.linalg.norm(accel, axis=1), window_s=1.0).means
        accel_spread = float(np.ptp(norm_means)) if len(norm_means) else 0.0
        static = excursion <= self.options.motion_threshold and accel_spread <= 0.05 * G0
        if not static:
            ctx.warn(
                f"the data does not look static: 1 s gyro means depart {excursion:.3g} rad/s from "
                f"the mean (threshold {self.options.motion_threshold}), accel norm 1 s means spread "
                f"{accel_spread:.3g} m/s^2; the bias will include motion"
            )
        ctx.recorder.series(
            f"/{ctx.name}/gyro_1s_means", second.t_ns, second.means, ("x", "y", "z")
        )
        step = LinearStep(
            type=self.type,
            sensor="gyro",
            matrix=np.eye(3),
            offset=bias,
            params={"bias": bias.tolist()},
        )
        results = {
            "bias": bias.tolist(),
            "metrics": {
                "samples": n,
                "duration_s": float((t_ns[-1] - t_ns[0]) * 1e-9),
                "std": std.tolist(),
                "bias_std_error": (std / np.sqrt(n)).tolist(),
                "max_1s_excursion": excursion,
                "accel_norm_1s_spread": accel_spread,
                "static": bool(static),
            },
        }
        return StageOutput(results=results, step=step)
