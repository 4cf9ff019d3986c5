"""OpenVINS' IMU file ``kalibr_imu_chain.yaml``: the noise and the IMU intrinsics of ``imu0``.

OpenVINS (rpng/open_vins ``ov_msckf/src/core/VioManagerOptions.h``) reads ``Tw``, ``Ta``,
``R_IMUtoACC``, ``R_IMUtoGYRO`` and ``Tg`` from this file (all five are required) with OpenCV's
``FileStorage``, and corrects (``docs/propagation-analytical.dox``)::

    w = R_GYROtoIMU Dw (w_m - Tg a - b_g),   a = R_ACCtoIMU Da (a_m - b_a),
    Dw = Tw^-1, Da = Ta^-1, R_GYROtoIMU = R_IMUtoGYRO^T, R_ACCtoIMU = R_IMUtoACC^T

With ``model: kalibr`` (written here) OpenVINS keeps the lower triangle of ``Dw`` and ``Da`` and
calibrates only the gyro's rotation. imupipe's chain maps exactly onto that form: ``Ta`` and
``Tw`` are Kalibr's ``M_a`` and ``M_g``, ``R_IMUtoGYRO`` is Kalibr's ``C_gyro_i``,
``R_IMUtoACC = I`` (the IMU frame is the accelerometer-anchored frame of Kalibr's model, see
:mod:`imupipe.pipeline.exports.common`), ``Tg = 0`` (imupipe's chain applies no g-sensitivity).
The biases are left to OpenVINS' online estimate; temperature terms are not in its model. The
noise is the first ``allan`` stage's (as in ``imu.yaml``). Written when an ``allan`` stage ran
(identity intrinsics when no accel or gyro calibration is in the chain).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imupipe.pipeline.exports.common import (
    Export,
    first_allan,
    imu_topic,
    kalibr_intrinsics,
    rate_hz,
    single_device,
    yaml_text,
)
from imupipe.pipeline.exports.kalibr import noise_block

FNAME = "kalibr_imu_chain.yaml"


def export(doc: dict[str, Any]) -> Export:
    out = Export()
    first = first_allan(doc)
    if first is None:
        return out
    name, res = first
    accel = single_device(doc, "accel", out, FNAME)
    gyro = single_device(doc, "gyro", out, FNAME)
    k = kalibr_intrinsics(
        None if accel is None else accel.matrix, None if gyro is None else gyro.matrix
    )
    for m in (accel, gyro):
        if m is not None and m.thermal is not None:
            out.note(FNAME, f"the {m.sensor} temperature terms are not in OpenVINS' model")
    imu: dict[str, Any] = {"T_i_b": np.eye(4)}
    imu.update(noise_block(res)[0])
    imu.update(
        {
            "rostopic": imu_topic(res),
            "time_offset": 0.0,
            "update_rate": rate_hz(res),
            "model": "kalibr",
            "Tw": k.m_gyro,
            "R_IMUtoGYRO": k.c_gyro_i,
            "Ta": k.m_accel,
            "R_IMUtoACC": np.eye(3),
            "Tg": np.zeros((3, 3)),
        }
    )
    comments = [
        f"OpenVINS imu0 from imupipe: noise of allan stage {name} (continuous time, largest",
        "axis), intrinsics from the calibration chain in OpenVINS' 'kalibr' model",
        "(w = R_IMUtoGYRO^T Tw^-1 (w_m - Tg a - b_g), a = R_IMUtoACC^T Ta^-1 (a_m - b_a)).",
    ]
    if accel is not None or gyro is not None:
        out.info[FNAME] = {"R_kalibr_from_imupipe": k.frame.tolist()}
    out.files[FNAME] = yaml_text({"imu0": imu}, comments, opencv=True)
    return out
