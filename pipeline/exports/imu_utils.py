"""imu_utils' result layout (``<stage>_imu_utils.yaml``), with honest meanings.

imu_utils (gaowenliang/imu_utils) writes, per sensor (``Gyr``, ``Acc``) and axis plus their
average, ``gyr_n``/``acc_n`` and ``gyr_w``/``acc_w``. Here, continuous-time SI per axis:
``*_n`` the white noise density N, ``*_w`` the random walk density K (the meaning VINS and Kalibr
expect; NOT what imu_utils writes there: the minimum of the Allan deviation, 0.664 B), and
``*_b`` the bias instability B itself. ``avg-axis`` is the mean of the three axes. The file
starts with OpenCV's ``%YAML:1.0`` directive as imu_utils' does. One file per ``allan`` stage.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imupipe.pipeline.exports.common import AXES, Export, allan_results, yaml_text

SECTIONS = (("gyro", "Gyr", "gyr", "rad/s"), ("accel", "Acc", "acc", "m/s^2"))
COMMENTS = [
    "imu_utils layout, written by imupipe's allan stage. Continuous-time SI, per axis:",
    "  gyr_n / acc_n: white noise density N (rad/s/sqrt(Hz), m/s^2/sqrt(Hz))",
    "  gyr_w / acc_w: random walk density K (rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz)), the",
    "    meaning VINS and Kalibr expect. NOT what imu_utils writes there (the minimum of the",
    "    Allan deviation, i.e. bias instability 0.664 B, in rad/s): that is gyr_b / acc_b",
    "    here, the bias instability B itself (rad/s, m/s^2).",
    "  avg-axis: the mean of the three axes (of the axes fitted: a dead axis has no entry).",
    "  gyr_n / acc_n: where the fit resolved no white noise, the upper bound from the shortest",
    "    taus (N_upper in calibration.json), never a zero.",
]


def imu_utils_doc(results: dict[str, Any]) -> dict[str, Any]:
    doc: dict[str, Any] = {"type": "IMU", "name": results.get("input", "")}
    for sensor, section, p, unit in SECTIONS:
        if sensor not in results:
            continue
        axes = [a for a in AXES if a in results[sensor]]  # a dead axis has no fit
        if not axes:
            continue
        values = {t: [float(results[sensor][a][t]) for a in axes] for t in ("N", "K", "B")}
        # a white noise the fit did not resolve is written as its upper bound, never a zero
        bounds = results.get("metrics", {}).get(sensor, {})
        values["N"] = [
            n if n > 0 else float(bounds.get(a, {}).get("N_upper", n))
            for n, a in zip(values["N"], axes, strict=True)
        ]
        block: dict[str, Any] = {"unit": f" {unit}"}
        rows = [("avg-axis", {t: float(np.mean(v)) for t, v in values.items()})]
        rows += [(f"{a}-axis", {t: v[i] for t, v in values.items()}) for i, a in enumerate(axes)]
        for label, vals in rows:
            block[label] = {f"{p}_n": vals["N"], f"{p}_w": vals["K"], f"{p}_b": vals["B"]}
        doc[section] = block
    return doc


def export(doc: dict[str, Any]) -> Export:
    out = Export()
    for name, res in allan_results(doc):
        out.files[f"{name}_imu_utils.yaml"] = yaml_text(imu_utils_doc(res), COMMENTS, opencv=True)
    return out
