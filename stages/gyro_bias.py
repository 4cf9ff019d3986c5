"""``gyro_bias`` stage: gyroscope bias from a static recording (the turn-on bias of the
basic calibration: the mean of N samples at rest after power-up, subtracted from every sample).

Model: ``bias = mean(gyro)`` over the static samples (all of them, or those in ``interval =
[start_s, end_s]`` seconds after the input's first sample); ``corrected = gyro - bias`` (rad/s).
Added to the chain as ``matrix = I``, ``offset = bias``.

Quality check (``ctx.check``): the data must be static (:mod:`imupipe.stages.stillness`): no
1-second gyro mean further than ``motion_threshold`` rad/s from the overall mean, and the
accelerometer norm's 1-second means within 0.05 g. A recording that moved stops the run with one
line (a bias that includes motion is not applied) unless ``accept_failed_checks = true``. A
recording shorter than :data:`SHORT_S` (a minute) is used with a warning that gives its length,
its number of 1 s means and the bias's standard error; its stillness is not judged (metric
``static_judged`` false: a few 1 s means that agree do not show the IMU at rest), though motion
seen in them still fails the check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from imupipe.readers.table import SensorData, has_stream, imu_pairs
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.steps import LinearStep
from imupipe.stages.stillness import stillness

SHORT_S = 60.0
"""Seconds of data under which the stage warns that the recording is short (the README: "the
IMU at rest, a minute or more")."""


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
        gyro, accel, note = imu_pairs(table)
        if note:
            ctx.warn(note)
        interval = self.options.interval
        if interval is not None and (len(interval) != 2 or interval[1] <= interval[0]):
            raise ctx.fail("'interval' must be [start_s, end_s] with end_s > start_s")
        mask = select_interval(gyro, interval)
        n = int(mask.sum())
        if n < 2:
            raise ctx.fail(f"only {n} gyroscope samples in interval {interval}")
        both = ctx.finite(
            SensorData(
                gyro.t_ns[mask],
                np.hstack([gyro.values[mask], accel.values[mask]]),
                gyro.rows[mask],
            ),
            "IMU (gyroscope and accelerometer)",
            minimum=2,
            axes=[f"{s} {a}" for s in ("gyro", "accel") for a in "xyz"],
        )
        values, t_ns = both.values[:, :3], both.t_ns
        n = len(both)
        # a constant axis is its own bias (a quantised gyro at rest may read one count
        # throughout); an axis with no finite value is named by ctx.finite above
        bias = values.mean(axis=0)
        std = values.std(axis=0, ddof=1)

        still = stillness(t_ns, values, both.values[:, 3:])
        static = still.static(self.options.motion_threshold)
        ctx.recorder.series(
            f"/{ctx.name}/gyro_1s_means",
            still.gyro_1s.t_ns,
            still.gyro_1s.means,
            ("gyro x 1 s mean", "gyro y 1 s mean", "gyro z 1 s mean"),
            unit="rad/s",
            title="gyro, 1 s means of the input",
        )
        step = LinearStep(
            type=self.type,
            sensor="gyro",
            matrix=np.eye(3),
            offset=bias,
            params={"bias": bias.tolist()},
        )
        duration_s = float((t_ns[-1] - t_ns[0]) * 1e-9)
        judged = duration_s * n / (n - 1) >= SHORT_S  # n sample periods: 60 s at 100 Hz is a minute
        results = {
            "bias": bias.tolist(),
            "metrics": {
                "samples": n,
                "duration_s": duration_s,
                "std": std.tolist(),
                "bias_std_error": (std / np.sqrt(n)).tolist(),
                "max_1s_excursion": still.excursion,
                "accel_norm_1s_spread": still.accel_spread,
                "static": bool(static),
                "static_judged": bool(judged) or not static,
            },
        }
        if not judged:
            ctx.warn(
                f"only {duration_s:.3g} s of data ({n} samples; the at-rest check had "
                f"{len(still.gyro_1s.t_ns)} one-second means, too few to judge whether the IMU "
                "was at rest): a gyro bias wants the IMU at rest for a minute or more; this one "
                f"is uncertain by up to {float(np.max(std / np.sqrt(n))):.2g} rad/s (one standard "
                "error) and says nothing of the drift over minutes"
            )
        ctx.check(
            static,
            f"motion in the bias recording: {still.describe(self.options.motion_threshold)}: the "
            "bias would include the motion; give a still interval",
        )
        return StageOutput(results=results, step=step)
