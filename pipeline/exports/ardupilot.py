"""ArduPilot calibration parameters (``ardupilot_calibration.param``, Mission Planner's
``NAME,VALUE`` file, also read by MAVProxy and pymavlink's ``MAVParmDict.load``).

ArduPilot corrects (ArduPilot ``libraries/AP_InertialSensor/AP_InertialSensor_Backend.cpp``,
``_rotate_and_correct_accel``/``_gyro``; ``AP_InertialSensor_tempcal.cpp``, ``correct_sensor``;
``libraries/AP_Compass/AP_Compass_Backend.cpp``, ``correct_field``)::

    accel: (raw - tcal(T) - INS_ACCOFFS_{X,Y,Z}) * INS_ACCSCAL_{X,Y,Z}                m/s^2
    gyro:  raw - tcal(T) - INS_GYROFFS_{X,Y,Z}                                        rad/s
    tcal(T) = p(T - 35) - p(INS_ACC1_CALTEMP - 35),  p(d) = 1e-6 (c1 d + c2 d^2 + c3 d^3),
             c_k = INS_TCAL1_ACC{k}_{X,Y,Z} (GYR for the gyro), T clamped to INS_TCAL1_TMIN..TMAX
    mag:   W (raw + COMPASS_OFS_{X,Y,Z}) + COMPASS_MOT_{X,Y,Z} P,  W = COMPASS_SCALE x the
           symmetric matrix of diagonal COMPASS_DIA_*, off-diagonal COMPASS_ODI_{X,Y,Z} = W01,
           W02, W12; P the battery current in A (COMPASS_MOTCT = 2) or the throttle 0..1
           (COMPASS_MOTCT = 1: Compass::set_throttle(motors->get_throttle()), the value a
           copter logs as CTUN.ThO)                                                     milligauss

``raw`` of the compass is the field already rotated into the body frame: ``AP_Compass_Backend``'s
``accumulate_sample`` rotates it (the driver's own rotation, then ``AHRS_ORIENTATION`` for an
internal compass or ``COMPASS_ORIENT*`` for an external one, ``rotate_field``) before
``correct_field`` adds the offsets; so the compass parameters are body-frame quantities and the
logged ``MAG`` is the corrected body-frame field whatever the orientation.

**One slot per device** (:func:`imupipe.pipeline.exports.common.device_models`): IMU ``i`` (1 to
3) is ``INS_ACC*``/``INS_GYR*`` (``INS_ACCOFFS_*``, ``INS_ACC2OFFS_*``, ``INS_ACC3OFFS_*``;
``INS_GYROFFS_*``, ``INS_GYR2OFFS_*``; ``INS_ACCi_CALTEMP``; ``INS_TCALi_*``), compass ``i`` is
``COMPASS_OFS*``/``DIA*``/``ODI*``/``SCALE*`` (``COMPASS_OFS_*``, ``COMPASS_OFS2_*``...). The
slot is the one whose ``INS_ACC*_ID``/``INS_GYR*_ID``/``COMPASS_DEV_ID*`` in the log's parameters
(``fitted_on.ardupilot.parameters``, a DataFlash log's) holds the device's id, else the device's
instance when free, else the first free one. ``INS_TCALi_TMIN``/``TMAX`` are shared by the
IMU's accel and gyro: written once, the intersection of both fitted ranges (noted when they
differ). A compass's soft iron ``W`` is written as ``COMPASS_SCALE*`` (its mean diagonal;
ArduPilot multiplies by it after the offsets, ``correct_field``, and only within 1/1.5..1.5)
times ``DIA``/``ODI`` (``W`` over the scale), as MagFit normalises them; a compass whose
``DIA`` leaves 0.8..1.2, ``ODI`` +-0.2 or scale 1/1.5..1.5 is not written (noted with the
figure: :func:`imupipe.stages.magnetometer.inflight.out_of_range`).

``INS_*_ID``/``COMPASS_DEV_ID*`` are written only from an ArduPilot log (PX4 numbers device
types differently).

**Only what was estimated**: offsets (and ``*_ID``) when a linear step was fitted, the accel
scale when a matrix was, ``INS_TCALi_*`` when a temperature step was. A temperature model
without a linear step writes only the ``INS_TCALi_*`` shape (``c1..c3``): ArduPilot corrects
relative to ``INS_*i_CALTEMP``, the temperature of the vehicle's own offsets, which stay.

imupipe's composed chain maps: offsets exactly (ArduPilot's compass offset is added, so ``COMPASS_OFS = -offset``, in
milligauss); the accelerometer scale from the diagonal (no misalignment in ArduPilot: the
off-diagonal part is left out, noted); no gyro scale in ArduPilot (noted); the soft iron when
symmetric. A temperature polynomial of order <= 3 in T maps exactly: it is re-expanded about
35 degC; with a linear step, its value at the calibration temperature (Tref clamped to the fitted
range) goes into the offset and ``INS_ACCi_CALTEMP``/``INS_GYRi_CALTEMP`` is that temperature. Models with
rate, ambient, piecewise or scale-factor terms do not map (noted, left out). A sensor fitted on
data PX4 had already corrected (a ULog's ``sensor_combined``) is left out.

**Data ArduPilot had already corrected** (a DataFlash log's ``IMU`` and ``MAG``): the chain is
composed with the log's own ``INS_*OFFS``/``INS_ACC*SCAL``/``COMPASS_*`` (:func:`compose_with_log`),
so the file holds the vehicle's new calibration, in the slot of the device (the reader gives
each instance the id of its ``INS_*_ID``/``COMPASS_DEV_ID*``).
"""

from __future__ import annotations

import textwrap
from typing import Any

import numpy as np

from imupipe.pipeline.exports.common import (
    RELATIVE_TOLERANCE,
    Export,
    SensorModel,
    device_models,
    left_alone,
    number,
    off_diagonal,
    params_text,
    soft_iron,
)
from imupipe.stages.magnetometer.inflight import out_of_range

FNAME = "ardupilot_calibration.param"
TCAL_REFERENCE = 35.0
"""degC: ArduPilot's fixed reference of the ``INS_TCAL`` polynomial (``TEMP_REFERENCE``)."""
TCAL_SCALE = 1e6
"""ArduPilot stores the ``INS_TCAL`` coefficients multiplied by this (``SCALE_FACTOR``)."""
MILLIGAUSS_PER_TESLA = 1e7
SCALE_RANGE = (1 / 1.5, 1.5)
"""``COMPASS_SCALE`` outside this range is ignored by ArduPilot (``Compass::have_scale_factor``,
``COMPASS_MIN/MAX_SCALE_FACTOR``)."""
SLOTS = 3
"""ArduPilot's IMUs (and compasses) with parameters of this form."""
SHORT = {"accel": "ACC", "gyro": "GYR", "mag": "COMPASS"}

Row = tuple[str, float]


def _s(i: int) -> str:
    """The parameter names' instance part: ``""`` for the first, ``"2"``, ``"3"``."""
    return "" if i == 0 else str(i + 1)


def id_name(sensor: str, i: int) -> str:
    return f"COMPASS_DEV_ID{_s(i)}" if sensor == "mag" else f"INS_{SHORT[sensor]}{_s(i)}_ID"


def log_parameters(model: SensorModel) -> dict[str, Any]:
    """The ArduPilot parameters of the log the model was fitted on (empty for other logs)."""
    return (model.fitted_on.get("ardupilot") or {}).get("parameters") or {}


def ardupilot_id(model: SensorModel) -> int | None:
    """The device's id as ArduPilot numbers it: only from an ArduPilot log (a PX4 device id
    differs in its device-type byte, so it is never written into ``INS_*_ID``)."""
    dev = model.device.get("device_id")
    return int(dev) if dev is not None and log_parameters(model) else None


def slots(models: list[SensorModel], out: Export) -> list[int | None]:
    """Each device's slot (module docstring); None when none is left (noted)."""
    found: list[int | None] = []
    taken: set[int] = set()
    for model in models:
        params = log_parameters(model)
        dev = ardupilot_id(model)
        ids = [params.get(id_name(model.sensor, i)) for i in range(SLOTS)]
        match = [i for i in range(SLOTS) if i not in taken and dev is not None and ids[i] == dev]
        free = [i for i in range(SLOTS) if i not in taken and not ids[i]]
        prefer = model.device.get("instance")
        slot = match[0] if match else (prefer if prefer in free else (free or [None])[0])
        if slot is None:
            out.note(FNAME, f"{model.sensor}: no slot left for device {dev}; not written")
        else:
            taken.add(slot)
        found.append(slot)
    return found


def imu_rows(
    model: SensorModel,
    i: int,
    out: Export,
    shared: tuple[float, float] | None,
    scaled: bool | None = None,
) -> list[Row]:
    """The rows of IMU slot ``i``'s accel or gyro; ``shared``: the slot's ``INS_TCALi_TMIN``/
    ``TMAX`` (ArduPilot clamps both the temperature and ``CALTEMP`` to it); ``scaled``: whether
    a stage estimated a matrix (default: the model's own)."""
    short = SHORT[model.sensor]
    offs = f"INS_{short}{_s(i)}OFFS" if model.sensor == "accel" or i else "INS_GYROFFS"
    m, offset = model.matrix, model.offset.copy()
    rows: list[Row] = []
    th = model.thermal
    if th is not None:
        coef = th.about(TCAL_REFERENCE)
        if model.linear:
            tcal = float(np.clip(th.tref, *(shared or th.t_range)))
            offset = offset + th.at(tcal)
            rows += [(f"INS_{short}{i + 1}_CALTEMP", tcal)]
        else:
            out.note(
                FNAME,
                f"{model.sensor}: a temperature model without offsets: INS_TCAL{i + 1} holds "
                f"its shape; the vehicle's own INS_{short}{i + 1}_CALTEMP and offsets stay",
            )
        rows += [
            (f"INS_TCAL{i + 1}_{short}{k}_{a}", coef[j, k] * TCAL_SCALE)
            for k in (1, 2, 3)
            for j, a in enumerate("XYZ")
        ]
        temp = model.fitted_on.get("topics", {}).get("temperature")
        out.note(
            FNAME,
            f"{model.sensor}: ArduPilot compensates against the IMU's own temperature; the "
            f"model was fitted against {temp or 'the temperature stream'}",
        )
    if model.linear:
        dev = ardupilot_id(model)
        if dev is not None:
            rows.append((id_name(model.sensor, i), dev))
        rows += [(f"{offs}_{a}", offset[j]) for j, a in enumerate("XYZ")]
    if not (model.scaled if scaled is None else scaled):
        return rows
    diag = np.diag(m)
    off = off_diagonal(m)
    if off > RELATIVE_TOLERANCE:
        out.note(
            FNAME,
            f"{model.sensor}: ArduPilot has no misalignment terms; the off-diagonal "
            f"part of the matrix (up to {off:.2g} of its diagonal) is left out",
        )
    if model.sensor == "accel":
        rows += [(f"INS_ACC{_s(i)}SCAL_{a}", diag[j]) for j, a in enumerate("XYZ")]
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


def families(sensor: str, i: int) -> list[tuple[str, str]]:
    """The parameter families of IMU or compass slot ``i`` (for the header's list)."""
    if sensor == "mag":
        return [(f"COMPASS_{k}{_s(i)}_", "") for k in ("OFS", "DIA", "ODI")]
    short = SHORT[sensor]
    offs = f"INS_{short}{_s(i)}OFFS_" if sensor == "accel" or i else "INS_GYROFFS_"
    out = [(offs, ""), (f"INS_{short}{i + 1}_CALTEMP", ""), (f"INS_TCAL{i + 1}_{short}", "")]
    return out + ([(f"INS_ACC{_s(i)}SCAL_", "")] if sensor == "accel" else [])


def mag_rows(model: SensorModel, i: int, out: Export, scaled: bool | None = None) -> list[Row]:
    if model.thermal is not None:
        out.note(FNAME, "mag: ArduPilot has no compass temperature model; left out")
    rows: list[Row] = []
    if not model.linear:
        return rows
    dev = ardupilot_id(model)
    if dev is not None:
        rows.append((id_name("mag", i), dev))
    ofs = -model.offset * MILLIGAUSS_PER_TESLA
    rows += [(f"COMPASS_OFS{_s(i)}_{a}", ofs[j]) for j, a in enumerate("XYZ")]
    if model.scaled if scaled is None else scaled:
        diag, off = soft_iron(model.matrix, out, FNAME)
        wrong = out_of_range(model.matrix)
        if wrong:
            out.note(FNAME, f"mag: compass {i + 1} not written: {wrong}")
            return []
        scale = float(diag.mean())  # COMPASS_SCALE x DIA/ODI, as MagFit normalises them
        rows += [(f"COMPASS_DIA{_s(i)}_{a}", diag[j] / scale) for j, a in enumerate("XYZ")]
        rows += [(f"COMPASS_ODI{_s(i)}_{a}", off[j] / scale) for j, a in enumerate("XYZ")]
        rows += [(f"COMPASS_SCALE{_s(i)}", scale)]
    return rows


def ardupilot_corrected(model: SensorModel) -> bool:
    """Whether the model was fitted on data ArduPilot had already corrected (a DataFlash log's
    ``IMU``/``MAG``: ``fitted_on.ardupilot.calibrated``)."""
    stream = "mag" if model.sensor == "mag" else "imu"
    return bool(((model.fitted_on.get("ardupilot") or {}).get("calibrated") or {}).get(stream))


def _vector(p: dict[str, Any], name: str, default: float) -> np.ndarray:
    values = [p.get(f"{name}_{a}", default) for a in "XYZ"]
    return np.array([default if v is None else float(v) for v in values])


def compass_terms(p: dict[str, Any], s: str = "") -> tuple[np.ndarray, ...]:
    """(OFS mG, W (scale x DIA/ODI), MOT mG/A or zeros) of compass ``s`` ("", "2", "3") as
    ArduPilot reads its parameters: an all-zero ``DIA`` is (1, 1, 1), ``COMPASS_SCALE``
    outside 1/1.5..1.5 (or unset) is not applied, ``MOT`` only with ``COMPASS_MOTCT`` 1 or 2
    (:func:`motor_kind` says whether it multiplies the throttle or the current)."""

    def vec(name: str, default: float) -> np.ndarray:
        return np.array([float(p.get(f"{name}_{a}", default) or 0.0) for a in "XYZ"])

    dia = vec(f"COMPASS_DIA{s}", 0.0)
    dia = np.ones(3) if not np.any(dia) else dia
    odi = vec(f"COMPASS_ODI{s}", 0.0)
    w = np.diag(dia)
    w[0, 1] = w[1, 0] = odi[0]
    w[0, 2] = w[2, 0] = odi[1]
    w[1, 2] = w[2, 1] = odi[2]
    scale = float(p.get(f"COMPASS_SCALE{s}") or 0.0)
    if SCALE_RANGE[0] <= scale <= SCALE_RANGE[1]:
        w = w * scale
    mot = vec(f"COMPASS_MOT{s}", 0.0) if motor_kind(p) else np.zeros(3)
    return vec(f"COMPASS_OFS{s}", 0.0), w, mot


MOTCT = {"throttle": 1, "current": 2}
"""``COMPASS_MOTCT`` of each motor source (``AP_COMPASS_MOT_COMP_THROTTLE``, ``_CURRENT``)."""


def motor_kind(p: dict[str, Any]) -> int:
    """The log's compass motor compensation as ArduPilot applies it (``correct_field``): 1
    throttle, 2 current, 0 none (disabled, per-motor ``COMPASS_MOTCT = 3`` or unset)."""
    kind = int(p.get("COMPASS_MOTCT") or 0)
    return kind if kind in MOTCT.values() else 0


def compose_with_log(model: SensorModel, i: int, out: Export) -> SensorModel | None:
    """The model in ArduPilot's raw (sensor-frame) domain when it was fitted on data ArduPilot
    had corrected with the log's own parameters (module docstring: the logged ``IMU`` is
    ``S (raw - tcal(T) - OFFS)``, the logged ``MAG`` is ``COMPASS_SCALE W (raw + OFS)``):
    ``M (logged - o - b(T))`` becomes ``M S (raw - (OFFS + S^-1 o) - S^-1 b(T))``, so the
    file replaces the log's calibration. A compass's parameters act on the field already turned
    into the body (``AHRS_ORIENTATION`` for an internal compass, ``COMPASS_ORIENT*`` for an
    external one: ``rotate_field`` before ``correct_field``, module docstring), as the logged
    ``MAG`` and the fit are: the composition holds whatever the orientation (the vehicle must
    keep it). An IMU's offsets and scales act before the board rotation
    (``_rotate_and_correct_accel``): with ``AHRS_ORIENTATION`` set, the IMU is left out with a
    note naming it. A thermal model on data the log had already compensated
    (``INS_TCALi_ENABLE = 1``) is left out."""
    p = log_parameters(model)
    sensor, s = model.sensor, _s(i)
    rot = p.get("AHRS_ORIENTATION", 0) or 0
    if rot and sensor != "mag":
        out.note(
            FNAME,
            f"{sensor}: fitted on data ArduPilot had rotated (AHRS_ORIENTATION = {rot:g}; its "
            f"INS_{SHORT[sensor]} offsets act before that rotation); not written",
        )
        return None
    thermal = model.thermal
    if sensor == "mag":
        ofs, w, mot = compass_terms(p, s)
        old = -ofs / MILLIGAUSS_PER_TESLA
        motor, source = log_motor(model, mot / MILLIGAUSS_PER_TESLA, p, s, out)
    else:
        short = SHORT[sensor]
        offs = f"INS_{short}{s}OFFS" if sensor == "accel" or i else "INS_GYROFFS"
        old = _vector(p, offs, 0.0)
        scale = _vector(p, f"INS_ACC{s}SCAL", 1.0) if sensor == "accel" else np.ones(3)
        w = np.diag(np.where(scale == 0.0, 1.0, scale))
        if thermal is not None and p.get(f"INS_TCAL{i + 1}_ENABLE") == 1:
            out.note(
                FNAME,
                f"{sensor}: the log's data were already thermally compensated by ArduPilot "
                f"(INS_TCAL{i + 1}_ENABLE = 1): keep its INS_TCAL{i + 1}; the fitted "
                "temperature model is not written",
            )
            thermal = None
        motor, source = model.motor, model.motor_source
    winv = np.linalg.inv(w)
    if thermal is not None:
        thermal = type(thermal)(thermal.tref, winv @ thermal.coefficients, thermal.t_range)
    return SensorModel(
        sensor,
        model.matrix @ w,
        old + winv @ model.offset,
        thermal,
        model.entries,
        model.issues,
        model.device,
        motor,
        source,
    )


def log_motor(
    model: SensorModel, mot: np.ndarray, p: dict[str, Any], s: str, out: Export
) -> tuple[np.ndarray | None, str]:
    """The compass's motor term composed with the log's own, and what it multiplies. ArduPilot
    adds ``COMPASS_MOT * P`` after ``DIA``/``ODI`` (``correct_field``; ``P`` the current with
    ``COMPASS_MOTCT = 2``, the throttle with ``= 1``), so the logged field is ``W (raw + OFS) +
    MOT_log P`` and imupipe's ``M (logged - o) + motor P`` holds ``(M MOT_log + motor) P``: the
    exported ``COMPASS_MOT`` replaces the log's. A log term of the other kind than the fitted
    one (current against throttle), or per-motor compensation (``COMPASS_PMOT_EN``), cannot be
    added to it: noted, its ``M MOT_log`` part left out."""
    kind = motor_kind(p)
    log_source = {v: k for k, v in MOTCT.items()}.get(kind)
    per_motor = s == "" and bool(p.get("COMPASS_PMOT_EN"))
    fitted = model.motor_source if model.motor is not None else log_source
    if log_source is not None and np.any(mot) and not per_motor and fitted == log_source:
        return model.matrix @ mot + (0.0 if model.motor is None else model.motor), log_source
    raw_mot = _vector(p, f"COMPASS_MOT{s}", 0.0)
    if (log_source is not None and np.any(raw_mot)) or per_motor:
        what = "per-motor (COMPASS_PMOT_EN = 1)" if per_motor else f"{log_source}-based"
        out.note(
            FNAME,
            f"mag: the log's data carry ArduPilot's {what} motor compensation "
            f"(COMPASS_MOTCT = {kind}), which has no {model.motor_source}-based form; "
            + (
                f"the fitted {model.motor_source}-based term replaces it (COMPASS_MOTCT = "
                f"{MOTCT[model.motor_source]})"
                if model.motor is not None
                else "it stays as it is"
            ),
        )
    return model.motor, model.motor_source


def motor_rows(model: SensorModel, i: int, written: list[Row], out: Export) -> list[Row]:
    """A compass's motor compensation (``mag_inflight``): ``COMPASS_MOT*_{X,Y,Z}`` added after
    ``DIA``/``ODI`` as imupipe's ``motor`` is (``correct_field``), in milligauss per ampere
    with ``COMPASS_MOTCT = 2`` (current-based) or in milligauss at full throttle with
    ``COMPASS_MOTCT = 1`` (throttle-based: ``motor_offset = MOT * throttle``, throttle 0..1);
    one ``COMPASS_MOTCT`` for every compass: a compass whose term is of another kind than an
    earlier compass's has it left out (noted)."""
    if model.motor is None:
        return []
    kind = dict(written).get("COMPASS_MOTCT")
    if kind is not None and kind != MOTCT[model.motor_source]:
        out.note(
            FNAME,
            f"mag: compass {i + 1}'s {model.motor_source}-based motor term is left out: the "
            f"vehicle has one COMPASS_MOTCT for its compasses, {kind:g} for an earlier one (fit "
            "every compass with one motor_source)",
        )
        return []
    mot = model.motor * MILLIGAUSS_PER_TESLA
    rows: list[Row] = [(f"COMPASS_MOT{_s(i)}_{a}", mot[j]) for j, a in enumerate("XYZ")]
    if not any(name == "COMPASS_MOTCT" for name, _ in written):
        rows.append(("COMPASS_MOTCT", MOTCT[model.motor_source]))
    return rows


def stale_motor_terms(rows: list[Row], logged: dict[str, Any], out: Export) -> None:
    """Noted: a compass of the log this file leaves alone (its fit refused, or not fitted) whose
    ``COMPASS_MOTn`` the log holds for another ``COMPASS_MOTCT`` than the one the file writes:
    the vehicle has one for every compass, so ArduPilot would read that compass's terms as the
    other kind (per ampere against at full throttle)."""
    kind = dict(rows).get("COMPASS_MOTCT")
    old = motor_kind(logged)
    if kind is None or old in (0, int(kind)):
        return
    source = {v: k for k, v in MOTCT.items()}
    written = {r[0] for r in rows}
    for i in range(3):
        s = _s(i)
        mot = _vector(logged, f"COMPASS_MOT{s}", 0.0)
        if f"COMPASS_OFS{s}_X" not in written and np.any(mot):
            out.note(
                FNAME,
                f"mag: compass {i + 1} is not in this file and keeps COMPASS_MOT{s}_* of "
                f"COMPASS_MOTCT = {old} ({source[old]}); this file sets COMPASS_MOTCT = "
                f"{kind:g}, under which ArduPilot reads them per {source[int(kind)]}: set them "
                "to 0, or fit that compass too",
            )


def shared_ranges(
    placed: list[tuple[SensorModel, int]], out: Export
) -> dict[int, tuple[float, float]]:
    """IMU slot -> its ``INS_TCALi_TMIN``/``TMAX``: the range every thermal model of the slot
    covers (noted when the accel's and the gyro's differ)."""
    found: dict[int, list[tuple[float, float]]] = {}
    for model, i in placed:
        if model.thermal is not None:
            found.setdefault(i, []).append(model.thermal.t_range)
    shared = {}
    for i, ranges in sorted(found.items()):
        lo, hi = max(r[0] for r in ranges), min(r[1] for r in ranges)
        if len(set(ranges)) > 1:
            out.note(
                FNAME,
                f"IMU {i + 1}: accel and gyro were fitted over different temperatures; "
                f"INS_TCAL{i + 1}_TMIN/TMAX hold the range both cover, {lo:.3g}..{hi:.3g} degC",
            )
        shared[i] = (lo, hi)
    return shared


def export(doc: dict[str, Any], complete: bool = False) -> Export:
    """``ardupilot_calibration.param``: the estimated parameters of every device in its own
    slot; ``complete``: merged over the log's own parameters (a DataFlash log's)."""
    out = Export()
    rows: list[Row] = []
    logged: dict[str, Any] = {}
    placed: list[tuple[SensorModel, int]] = []
    for sensor in ("accel", "gyro", "mag"):
        models = []
        for model in device_models(doc, sensor):
            stream = "mag" if sensor == "mag" else "imu"
            if ((model.fitted_on.get("px4") or {}).get("calibrated") or {}).get(stream):
                out.note(FNAME, f"{sensor}: fitted on data PX4 had already corrected; not written")
                continue
            models.append(model)
        placed += [(m, i) for m, i in zip(models, slots(models, out), strict=True) if i is not None]
    if any(e.get("kind") == "baro_temperature" for e in doc.get("chain", [])):
        out.note(
            FNAME,
            "baro: ArduPilot has no barometer temperature polynomial (PX4's TC_B*); the "
            "barometer model is not written",
        )
    composed: list[tuple[SensorModel, int, bool]] = []
    for model, i in placed:
        scaled = model.scaled  # what the stages estimated, before the log's own is composed
        if ardupilot_corrected(model):
            found = compose_with_log(model, i, out)
            if found is None:
                continue
            model = found
        composed.append((model, i, scaled))
    shared = shared_ranges([(m, i) for m, i, _ in composed if m.sensor != "mag"], out)
    alone: list[str] = []
    for model, i, scaled in composed:
        for issue in model.issues:
            out.note(FNAME, f"{model.sensor}: {issue}")
        logged.update(log_parameters(model))
        if model.sensor == "mag":
            mine = mag_rows(model, i, out, scaled)
            mine += motor_rows(model, i, rows, out) if mine else []
        else:
            mine = imu_rows(model, i, out, shared.get(i), scaled)
        rows += mine
        alone += left_alone([r[0] for r in mine], families(model.sensor, i))
    stale_motor_terms(rows, logged, out)
    for i, (lo, hi) in shared.items():
        rows += [(f"INS_TCAL{i + 1}_ENABLE", 1.0)]
        rows += [(f"INS_TCAL{i + 1}_TMIN", lo), (f"INS_TCAL{i + 1}_TMAX", hi)]
    if not rows:
        return out
    comments = [
        "ArduPilot calibration parameters from imupipe, one slot per IMU and compass (load in",
        "Mission Planner: Config, Full Parameter List, Load from file; or MAVProxy param load).",
    ]
    if complete and logged:
        ours = {r[0] for r in rows}
        rows += [(k, v) for k, v in sorted(logged.items()) if k not in ours]
        comments += ["Complete: the log's own parameters, with the ones imupipe estimated."]
    else:
        if complete:
            out.note(FNAME, "the input carries no ArduPilot parameters: only the estimated ones")
        listed = ", ".join(alone) if alone else "(none in these slots)"
        comments += textwrap.wrap(
            "Only what imupipe estimated: loading it leaves every other parameter of the "
            f"vehicle as it is, among them {listed}.",
            width=92,
        )
    out.files[FNAME] = params_text(
        [(name, number(value)) for name, value in rows], comments, delimiter=","
    )
    return out
