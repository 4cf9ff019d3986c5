"""``average`` stage: block means of every sensor (``ImuDataSum`` of the MATLAB example in the
Chinese article "【IMU】温度零偏标定" on IMU temperature bias calibration).

Model: each block of ``window`` samples (or ``window_s`` seconds) is replaced by its mean; the
trailing partial block is averaged too; block times are block centres. Units are those of the
input (SI). An analysis stage: it adds nothing to the calibration chain. The block means of each
sensor go to Rerun under ``/<name>/<sensor>`` and, with ``write_csv``, to
``<name>_<input>_<sensor>.csv``.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from imupipe.readers.table import SENSOR_COLUMNS, SENSOR_UNITS, STREAM_OF_SENSOR, has_stream, sensor
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.blocks import block_means


class AverageStage(Stage):
    type = "average"
    sensors = ("gyro", "accel", "mag", "temperature")

    @dataclass
    class Options:
        window: int | None = None
        """Samples per block (500 when neither ``window`` nor ``window_s`` is given, as the
        MATLAB example of the temperature-calibration method)."""
        window_s: float | None = None
        """Seconds per block (instead of ``window``)."""
        write_csv: bool = False
        """Also write each sensor's block means as ``<name>_<input>_<sensor>.csv`` (t_ns + SI
        columns)."""

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        opts = self.options
        if opts.window is None and opts.window_s is None:
            opts.window = 500
        if opts.window is not None and opts.window_s is not None:
            raise ctx.fail("give 'window' or 'window_s', not both")
        if (opts.window is not None and opts.window < 1) or (
            opts.window_s is not None and opts.window_s <= 0
        ):
            raise ctx.fail("'window' must be >= 1 and 'window_s' > 0")
        results: dict = {"window": opts.window, "window_s": opts.window_s, "metrics": {}}
        artifacts: dict[str, str] = {}
        for name in self.sensors:
            if not has_stream(table, STREAM_OF_SENSOR[name]):
                continue
            data = sensor(table, name)
            blocks = block_means(data.t_ns, data.values, opts.window, opts.window_s)
            ctx.recorder.series(
                f"/{ctx.name}/means/{name}",
                blocks.t_ns,
                blocks.means,
                [f"{c.replace('_', ' ')} block mean" for c in SENSOR_COLUMNS[name]],
                unit=SENSOR_UNITS[name],
                plot=name,
            )
            results["metrics"][name] = {
                "samples": len(data),
                "blocks": len(blocks.counts),
                "last_block_samples": int(blocks.counts[-1]) if len(blocks.counts) else 0,
            }
            if opts.write_csv:
                buf = io.StringIO()
                header = "t_ns," + ",".join(SENSOR_COLUMNS[name])
                np.savetxt(
                    buf,
                    np.column_stack([blocks.t_ns.astype(np.float64), blocks.means]),
                    delimiter=",",
                    header=header,
                    comments="",
                    fmt=["%.0f"] + ["%.17g"] * blocks.means.shape[1],
                )
                artifacts[f"{ctx.name}_{ctx.input_name}_{name}.csv"] = buf.getvalue()
        return StageOutput(results=results, artifacts=artifacts)
