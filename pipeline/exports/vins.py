"""The IMU noise block of VINS-Mono / VINS-Fusion configs (``vins_imu.yaml``).

VINS reads ``acc_n``, ``gyr_n``, ``acc_w``, ``gyr_w`` (and ``imu_topic``, ``g_norm``) with
OpenCV's ``FileStorage`` from a ``%YAML:1.0`` file (HKUST-Aerial-Robotics/VINS-Fusion
``vins_estimator/src/estimator/parameters.cpp``, ``readParameters``). Written here: the
continuous-time densities of the first ``allan`` stage (N and K, the largest axis, as in Kalibr's
``imu.yaml``; VINS's shipped configs inflate them several times for unmodelled effects: that
choice is left to the user), ``imu_topic`` and, when an ``accel_calibration`` stage ran,
``g_norm`` (its gravity). Copy the keys into the VINS config.
"""

from __future__ import annotations

from typing import Any

from imupipe.pipeline.exports.common import Export, first_allan, imu_topic, noise, yaml_text

FNAME = "vins_imu.yaml"


def export(doc: dict[str, Any]) -> Export:
    out = Export()
    first = first_allan(doc)
    if first is None:
        return out
    name, res = first
    data: dict[str, Any] = {"imu_topic": imu_topic(res)}
    for sensor, p in (("accel", "acc"), ("gyro", "gyr")):
        n = noise(res, sensor)
        if n is not None:
            data[f"{p}_n"] = n.density
            data[f"{p}_w"] = n.random_walk
    gravity = [
        r["gravity"]
        for r in doc["results"].values()
        if r.get("type") == "accel_calibration" and "gravity" in r
    ]
    if gravity:
        data["g_norm"] = float(gravity[0])
    comments = [
        f"VINS IMU noise from imupipe's allan stage {name}: continuous-time densities, the",
        "largest axis (acc_n m/s^2/sqrt(Hz), gyr_n rad/s/sqrt(Hz), acc_w m/s^3/sqrt(Hz),",
        "gyr_w rad/s^2/sqrt(Hz)). Copy the keys into the VINS config file.",
    ]
    out.files[FNAME] = yaml_text(data, comments, opencv=True)
    return out
