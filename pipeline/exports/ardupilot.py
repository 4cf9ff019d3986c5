"""ArduPilot calibration parameters (``ardupilot_calibration.param``, Mission Planner's
``NAME,VALUE`` file, also read by MAVProxy and pymavlink's ``MAVParmDict.load``).

ArduPilot corrects (ArduPilot ``libraries/AP_InertialSensor/AP_InertialSensor_Backend.cpp``,
``_rotate_and_correct_accel``/``_gyro``; ``AP_InertialSensor_tempcal.cpp``, ``correct_sensor``;
``libraries/AP_Compass/AP_Compass_Backend.cpp``, ``correct_field``)::

    accel: (raw - tcal(T) - INS_ACCOFFS_{X,Y,Z}) * INS_ACCSCAL_{X,Y,Z}                m/s^2
    gyro:  raw - tcal(T) - INS_GYROFFS_{X,Y,Z}                                        rad/s
    tcal(T) = p(T - 35) - p(INS_ACC1_CALTEMP - 35),  p(d) = 1e-6 (c1 d + c2 d^2 + c3 d^3),
             c_k = INS_TCAL1_ACC{k}_{X,Y,Z} (GYR for the gyro), T clamped to INS_TCAL1_TMIN..TMAX
    mag:   W (raw + COMPASS_OFS_{X,Y,Z}),  W symmetric: diagonal COMPASS_DIA_*,
           off-diagonal COMPASS_ODI_{X,Y,Z} = W01, W02, W12                            milligauss

(the second and third IMU/compass use ``INS_ACC2OFFS_*``, ``COMPASS_OFS2_*``, ...; this file
writes the first). imupipe's composed chain (:func:`imupipe.pipeline.exports.common.sensor_model`)
maps: offsets exactly (ArduPilot's compass offset is added, so ``COMPASS_OFS = -offset``, in
milligauss); the accelerometer scale from the diagonal (no misalignment in ArduPilot: the
off-diagonal part is left out, noted); no gyro scale in ArduPilot (noted); the soft iron when
symmetric. A temperature polynomial of order <= 3 in T maps exactly: it is re-expanded about
35 degC, its value at the calibration temperature (Tref clamped to the fitted range) goes into
the offset and ``INS_ACC1_CALTEMP``/``INS_GYR1_CALTEMP`` is that temperature. Models with
rate, ambient, piecewise or scale-factor terms do not map (noted, left out). A sensor fitted on
data PX4 had already corrected (a ULog's ``sensor_combined``) is left out.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imupipe.pipeline.exports.common import (
    RELATIVE_TOLERANCE,
    Export,
    SensorModel,
    number,
    off_diagonal,
    params_text,
    sensor_model,
    soft_iron,
)

FNAME = "ardupilot_calibration.param"
TCAL_REFERENCE = 35.0
"""degC: ArduPilot's fixed reference of the ``INS_TCAL`` polynomial (``TEMP_REFERENCE``)."""
TCAL_SCALE = 1e6
"""ArduPilot stores the ``INS_TCAL`` coefficients multiplied by this (``SCALE_FACTOR``)."""
MILLIGAUSS_PER_TESLA = 1e7
NAMES = {"accel": ("INS_ACCOFFS", "INS_ACCSCAL", "ACC"), "gyro": ("INS_GYROFFS", None, "GYR")}


def imu_rows(model: SensorModel, out: Export) -> list[tuple[str, float]]:
    offs, scal, short = NAMES[model.sensor]
    m, offset = model.matrix, model.offset.copy()
    rows: list[tuple[str, float]] = []
    th = model.thermal
    if th is not None:
        tcal = float(np.clip(th.tref, *th.t_range))
        offset = offset + th.at(tcal)
        coef = th.about(TCAL_REFERENCE)
        rows += [("INS_TCAL1_ENABLE", 1.0)]
        rows += [("INS_TCAL1_TMIN", th.t_range[0]), ("INS_TCAL1_TMAX", th.t_range[1])]
        rows += [(f"INS_{short}1_CALTEMP", tcal)]
        rows += [
            (f"INS_TCAL1_{short}{k}_{a}", coef[i, k] * TCAL_SCALE)
            for k in (1, 2, 3)
            for i, a in enumerate("XYZ")
        ]
        temp = model.fitted_on.get("topics", {}).get("temperature")
        out.note(
            FNAME,
            f"{model.sensor}: ArduPilot compensates against the IMU's own temperature; the "
            f"model was fitted against {temp or 'the temperature stream'}",
        )
    rows += [(f"{offs}_{a}", offset[i]) for i, a in enumerate("XYZ")]
    diag = np.diag(m)
    off = off_diagonal(m)
    if off > RELATIVE_TOLERANCE:
        out.note(
            FNAME,
            f"{model.sensor}: ArduPilot has no misalignment terms; the off-diagonal "
            f"part of the matrix (up to {off:.2g} of its diagonal) is left out",
        )
    if scal is not None:
        rows += [(f"{scal}_{a}", diag[i]) for i, a in enumerate("XYZ")]
        if np.any(np.abs(diag - 1.0) > 0.2):
            out.note(
                FNAME,
                f"accel: scale {np.round(diag, 6).tolist()} outside ArduPilot's "
                "accepted 0.8..1.2 (were the data in SI units?)",
            )
    elif np.abs(diag - 1.0).max() > RELATIVE_TOLERANCE:
        out.note(
            FNAME,
            f"gyro: ArduPilot has no gyro scale; the scale "
            f"{np.round(diag, 6).tolist()} is left out",
        )
    return rows


def mag_rows(model: SensorModel, out: Export) -> list[tuple[str, float]]:
    if model.thermal is not None:
        out.note(FNAME, "mag: ArduPilot has no compass temperature model; left out")
    diag, off = soft_iron(model.matrix, out, FNAME)
    ofs = -model.offset * MILLIGAUSS_PER_TESLA
    rows = [(f"COMPASS_OFS_{a}", ofs[i]) for i, a in enumerate("XYZ")]
    rows += [(f"COMPASS_DIA_{a}", diag[i]) for i, a in enumerate("XYZ")]
    rows += [(f"COMPASS_ODI_{a}", off[i]) for i, a in enumerate("XYZ")]
    return rows


def export(doc: dict[str, Any]) -> Export:
    out = Export()
    rows: list[tuple[str, float]] = []
    for sensor in ("accel", "gyro", "mag"):
        model = sensor_model(doc, sensor)
        if model is None:
            continue
        stream = "mag" if sensor == "mag" else "imu"
        if ((model.fitted_on.get("px4") or {}).get("calibrated") or {}).get(stream):
            out.note(FNAME, f"{sensor}: fitted on data PX4 had already corrected; not written")
            continue
        for issue in model.issues:
            out.note(FNAME, f"{sensor}: {issue}")
        rows += mag_rows(model, out) if sensor == "mag" else imu_rows(model, out)
    if not rows:
        return out
    tcal = [r for r in rows if r[0] == "INS_TCAL1_ENABLE"]
    rows = [r for r in rows if r[0] != "INS_TCAL1_ENABLE"] + tcal[:1]
    comments = [
        "ArduPilot calibration parameters from imupipe, for IMU 1 and compass 1 (load in",
        "Mission Planner: Config, Full Parameter List, Load from file; or MAVProxy param load).",
    ]
    out.files[FNAME] = params_text(
        [(name, number(value)) for name, value in rows], comments, delimiter=","
    )
    return out
