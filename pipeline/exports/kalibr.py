"""Kalibr's IMU files: the noise model ``imu.yaml`` and the ``scale-misalignment`` intrinsics.

``imu.yaml`` (read by Kalibr's camera-IMU calibration, ethz-asl/kalibr
``aslam_offline_calibration/kalibr/python/kalibr_common/ConfigReader.py``, ``ImuParameters``):
``accelerometer_noise_density``, ``accelerometer_random_walk``, ``gyroscope_noise_density``,
``gyroscope_random_walk`` (continuous time: m/s^2/sqrt(Hz), m/s^3/sqrt(Hz), rad/s/sqrt(Hz),
rad/s^2/sqrt(Hz)), ``rostopic``, ``update_rate`` (Hz). Kalibr takes one value per sensor: each is
the largest of the three axes (named in the file's comments); when the fit resolved no random
walk, K is the upper end of its 68 % band. Written for each ``allan`` stage (``imu.yaml`` for
the first, ``<stage>_imu.yaml`` for any other).

``kalibr_imu_intrinsics.yaml``: the ``imu0`` block Kalibr writes for an IMU calibrated with
``--imu-models scale-misalignment`` (``IccScaledMisalignedImu.ImuParameters``: ``model``,
``accelerometers: {M}``, ``gyroscopes: {M, A, C_gyro_i}``, plus ``T_i_b``, ``time_offset``, the
noise and the topic), from the accel and gyro steps of the chain (see
:mod:`imupipe.pipeline.exports.common` for the decomposition). Kalibr's model has no biases
(it estimates them online) and no thermal terms: the chain's offsets and temperature steps are
not in it. ``A`` (the gyro's g-sensitivity) is zero: imupipe's chain applies none. Written when
an ``accel_calibration`` or ``gyro_calibration`` step is in the chain.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imupipe.pipeline.exports.common import (
    Export,
    allan_results,
    imu_topic,
    kalibr_intrinsics,
    noise,
    rate_hz,
    single_device,
    yaml_text,
)

NOISE_KEYS = (("accel", "accelerometer"), ("gyro", "gyroscope"))
INTRINSIC_TYPES = ("accel_calibration", "gyro_calibration")


def noise_block(results: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """Kalibr's four noise keys of an allan stage's results, and comments saying which axis
    each value is."""
    data: dict[str, Any] = {}
    comments: list[str] = []
    for sensor, prefix in NOISE_KEYS:
        n = noise(results, sensor)
        if n is None:
            continue
        data[f"{prefix}_noise_density"] = n.density
        data[f"{prefix}_random_walk"] = n.random_walk
        how = (
            "the fit resolved no random walk; upper bound from the 68 % band"
            if n.k_bound
            else "the largest"
        )
        density_how = (
            "white noise not resolved: UPPER BOUND from the shortest taus"
            if n.n_bound
            else "the largest"
        )
        comments.append(
            f"{prefix}_noise_density: axis {n.density_axis} ({density_how}); "
            f"{prefix}_random_walk: axis {n.random_walk_axis} ({how})"
        )
    return data, comments


def noise_yaml(name: str, results: dict[str, Any]) -> str:
    data, comments = noise_block(results)
    data["rostopic"] = imu_topic(results)
    data["update_rate"] = rate_hz(results)
    kind = results["metrics"].get("fit_kind", "oadev")
    head = [
        f"Kalibr IMU noise model from imupipe's {kind} fit (stage {name}).",
        "Continuous-time SI: noise densities per sqrt(Hz), random walks per second per sqrt(Hz);",
        "update_rate in Hz, measured from the timestamps.",
        "Kalibr takes one value per sensor: each value is the LARGEST of the three axes.",
    ]
    topics = (results.get("fitted_on") or {}).get("topics", {})
    if "gyro" in topics and "accel" in topics:
        head.append(
            f"The gyro ({topics['gyro']}) and accelerometer ({topics['accel']}) came on topics "
            "of their own; Kalibr reads one Imu topic with both (realsense-ros: "
            "unite_imu_method): set rostopic to it. update_rate is the gyro's."
        )
    return yaml_text(data, head + comments)


def intrinsics_yaml(doc: dict[str, Any], out: Export, fname: str) -> str | None:
    accel = single_device(doc, "accel", out, fname)
    gyro = single_device(doc, "gyro", out, fname)
    if not any(m is not None and any(m.fitted(t) for t in INTRINSIC_TYPES) for m in (accel, gyro)):
        return None
    k = kalibr_intrinsics(
        None if accel is None else accel.matrix, None if gyro is None else gyro.matrix
    )
    for m in (accel, gyro):
        if m is not None and (np.any(m.offset) or m.thermal is not None):
            out.note(
                fname,
                f"the {m.sensor} offset and temperature terms are not in Kalibr's model (it "
                "estimates biases online)",
            )
    imu: dict[str, Any] = {
        "T_i_b": np.eye(4),
        "model": "scale-misalignment",
        "accelerometers": {"M": k.m_accel},
        "gyroscopes": {"M": k.m_gyro, "A": np.zeros((3, 3)), "C_gyro_i": k.c_gyro_i},
        "time_offset": 0.0,
    }
    allan = allan_results(doc)
    if allan:
        name, res = allan[0]
        imu.update(noise_block(res)[0])
        imu["rostopic"] = imu_topic(res)
        imu["update_rate"] = rate_hz(res)
    else:
        topic = (accel or gyro).fitted_on.get("topics", {}).get("imu")  # type: ignore[union-attr]
        imu["rostopic"] = topic or "/imu/data"
        out.note(fname, "no allan stage ran: the noise keys are not written")
    head = [
        "Kalibr scale-misalignment IMU model (imu0) from imupipe's calibration chain:",
        "a_m = M_a a + b_a;  w_m = M_g C_gyro_i w + A a + b_g  (Kalibr's IccScaledMisalignedImu).",
        "Kalibr's IMU frame has the accelerometer's x axis; the rotation R from imupipe's",
        "corrected frame to it (a_kalibr = R a_imupipe) is in calibration.json, exports.",
    ]
    out.info[fname] = {"R_kalibr_from_imupipe": k.frame.tolist()}
    return yaml_text({"imu0": imu}, head)


def export(doc: dict[str, Any]) -> Export:
    out = Export()
    for i, (name, res) in enumerate(allan_results(doc)):
        out.files["imu.yaml" if i == 0 else f"{name}_imu.yaml"] = noise_yaml(name, res)
    fname = "kalibr_imu_intrinsics.yaml"
    text = intrinsics_yaml(doc, out, fname)
    if text is not None:
        out.files[fname] = text
    return out
