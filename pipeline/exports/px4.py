"""PX4 calibration parameters (``px4_calibration.params``, QGroundControl's parameter file).

PX4 corrects each sensor (PX4-Autopilot ``src/lib/sensor_calibration``, ``Correct``)::

    accel: R ((raw - thermal(T) - CAL_ACCn_{X,Y,Z}OFF) * CAL_ACCn_{X,Y,Z}SCALE)   m/s^2
    gyro:  R (raw - thermal(T) - CAL_GYROn_{X,Y,Z}OFF)                             rad/s
    mag:   R (S (raw - CAL_MAGn_{X,Y,Z}OFF)),  S symmetric: diagonal CAL_MAGn_*SCALE,
           off-diagonal CAL_MAGn_{X,Y,Z}ODIAG = S01, S02, S12                      gauss

``thermal(T)`` is the cubic ``TC_{A,G}n_X{0..3}_{axis}`` in ``T - TC_*n_TREF`` (T clamped to
``TC_*n_TMIN..TMAX``, ``src/modules/temperature_compensation``, ``calc_thermal_offsets_3D``),
enabled by ``TC_A_ENABLE``/``TC_G_ENABLE``. ``R`` is the board rotation; a magnetometer's is
``CAL_MAGn_ROT`` (external) or ``SENS_BOARD_ROT`` (internal) with the level adjustment
``SENS_BOARD_*_OFF`` (:mod:`imupipe.readers.ulog.rotation`), applied after ``S``: a
magnetometer model mapping the raw field to the body (``m``) is written ``S = R^T m``. A slot
``n`` applies to the device whose id ``CAL_*n_ID`` (``TC_*n_ID``) holds.

**One slot per device.** The chain of each device (:func:`imupipe.pipeline.exports.common.device_models`: steps of one device compose, of different devices never) goes to its own slot:
``CAL_*n`` is the slot whose ``CAL_*n_ID`` in the log holds the device's id, else the slot of the
device's instance when the log leaves it free, else the first free one; ``TC_*k`` likewise by
``TC_*k_ID``, else ``k = n``. PX4 applies a slot to the device whose id it holds, whatever ``n``
(``TemperatureCompensation::set_sensor_id``, ``Accelerometer::set_device_id``).

**Only what was estimated.** A device's ``CAL_*n_*OFF`` (and ``CAL_*n_ID``) are written when a
linear step (an offset) was fitted, ``*SCALE``/``ODIAG`` when a step fitted a matrix other than
the identity, ``TC_*k_*`` when a temperature step was fitted: a temperature-only run writes no
``CAL_ACC*`` line, so loading it keeps the vehicle's accelerometer calibration. The header lists
the families of the written slots that the file leaves alone. ``complete`` (``[output] params =
"complete"``) merges the estimated parameters over the log's own ``CAL_*``/``TC_*``/
``SENS_BOARD_*`` (a ULog carries them), a file that can replace the vehicle's calibration set.

Each device's composed chain maps as follows. Offsets map exactly (sign: PX4 subtracts them, as imupipe's ``offset``). The
accelerometer's scale maps from the diagonal; PX4 has no accelerometer misalignment, so the
off-diagonal part is left out (noted with its size). PX4 v1.11 and later have no gyro scale
(the ``CAL_GYROn_*SCALE`` of older firmware is written only when the log had it). The
magnetometer's soft iron maps to SCALE/ODIAG when symmetric (imupipe's ellipsoid fits are). A
temperature model maps to ``TC_*`` when it is a polynomial of order <= 3 in T; rate, ambient,
piecewise and scale-factor terms do not (noted, left out). A magnetometer temperature model maps
to ``TC_Mn_*`` in gauss (firmware with magnetometer thermal compensation, ``TC_M_ENABLE``).

**Data PX4 had already corrected.** ``sensor_combined`` and ``vehicle_magnetometer`` hold data
PX4 corrected with the log's own parameters (``fitted_on.px4.calibrated``). The chain fitted on
them is composed with those parameters (PX4's ``BiasCorrectedSensorOffset``: new offset = old
offset + bias / scale), so the file replaces the log's calibration; for the accelerometer and
gyroscope this needs no board rotation (``SENS_BOARD_ROT = 0``, ``CAL_*n_ROT`` -1 or 0), else
the sensor is left out with a note naming the parameter; a magnetometer's rotation is composed
(``vehicle_magnetometer = R S (raw - OFF)``). The slot is the one
whose ``CAL_*n_ID`` is the fitted device (``fitted_on.device_id``); for a log that names no PX4
device (CSV, ROS), the slots in the order of the devices without ``CAL_*_ID``/``TC_*_ID``,
noted (PX4 applies a slot only to the device whose id it holds).
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass
from typing import Any

import numpy as np

from imupipe.pipeline.calibration_file import same_device
from imupipe.pipeline.exports.common import (
    OFF_DIAGONAL,
    RELATIVE_TOLERANCE,
    Export,
    SensorModel,
    device_models,
    entry_device,
    left_alone,
    number,
    off_diagonal,
    params_text,
    soft_iron,
)
from imupipe.readers.ulog.rotation import mag_rotation

FNAME = "px4_calibration.params"
CAL = {"accel": "ACC", "gyro": "GYRO", "mag": "MAG"}
TC = {"accel": "A", "gyro": "G", "mag": "M"}
STREAM = {"accel": "imu", "gyro": "imu", "mag": "mag"}
INT32, REAL32 = 6, 9
"""MAVLink ``MAV_PARAM_TYPE`` of the rows (the last column)."""
GAUSS_PER_TESLA = 1e4


SLOTS = 4
"""PX4's slots per sensor kind (``CAL_ACC0..3``, ``TC_A0..3``)."""


@dataclass
class Target:
    """Where one device's sensor goes: PX4's ``CAL_*n`` slot ``n`` and ``TC_*n`` slot ``tc``,
    the device id (None: unknown), the log's parameters and whether PX4 had corrected the
    fitted data."""

    n: int
    tc: int
    device: int | None
    params: dict[str, Any]
    calibrated: bool


def _log_parameters(model: SensorModel) -> dict[str, Any]:
    return (model.fitted_on.get("px4") or {}).get("parameters") or {}


def _slot(
    prefix: str,
    suffix: str,
    device: int | None,
    params: dict[str, Any],
    taken: set[int],
    prefer: int | None,
) -> int | None:
    """The slot ``k`` whose ``<prefix>k<suffix>`` holds ``device``; else ``prefer`` when that slot
    is free, else the first free one (no id in the log, not taken by another device)."""
    if device is not None:
        for k in range(SLOTS):
            if k not in taken and params.get(f"{prefix}{k}{suffix}") == device:
                return k
    free = [k for k in range(SLOTS) if k not in taken and not params.get(f"{prefix}{k}{suffix}")]
    if prefer is not None and prefer in free:
        return prefer
    return free[0] if free else None


def targets(models: list[SensorModel], out: Export) -> list[Target | None]:
    """The slots of every device of one sensor (module docstring: slot rules); None: no slot
    left (noted)."""
    found: list[Target | None] = []
    taken: set[int] = set()
    taken_tc: set[int] = set()
    for model in models:
        stream = STREAM[model.sensor]
        px4 = model.fitted_on.get("px4") or {}
        params = _log_parameters(model)
        dev = model.device.get("device_id")
        dev = None if dev is None else int(dev)
        cal, tc = CAL[model.sensor], TC[model.sensor]
        instance = model.device.get("instance")
        n = _slot(f"CAL_{cal}", "_ID", dev, params, taken, instance)
        if n is None:
            out.note(FNAME, f"{model.sensor}: no CAL_{cal} slot left for device {dev}; not written")
            found.append(None)
            continue
        taken.add(n)
        k = _slot(f"TC_{tc}", "_ID", dev, params, taken_tc, n)
        k = n if k is None else k
        taken_tc.add(k)
        ids = [f"CAL_{cal}{n}_ID"] if model.linear else []
        ids += [f"TC_{tc}{k}_ID"] if model.thermal is not None else []
        if dev is None and ids:
            out.note(
                FNAME,
                f"{model.sensor}: the input names no PX4 device, so {' and '.join(ids)} "
                f"{'is' if len(ids) == 1 else 'are'} not written; PX4 applies a slot only to "
                "the device whose id it holds: set it",
            )
        found.append(Target(n, k, dev, params, bool((px4.get("calibrated") or {}).get(stream))))
    return found


def mag_turn(model: SensorModel, t: Target, out: Export) -> np.ndarray:
    """``R`` of PX4's magnetometer correction ``R (S (raw - OFF))`` for the model's slot
    (:mod:`imupipe.readers.ulog.rotation`): the one the reader found for the fitted device
    (``fitted_on.px4.rotation.mag``), else the slot's in the log's parameters, else the
    identity (a log without parameters). An undefined rotation: noted, the identity."""
    found = (((model.fitted_on.get("px4") or {}).get("rotation") or {}).get("mag") or {}).get(
        "matrix"
    )
    if found is not None:
        return np.asarray(found, dtype=np.float64).reshape(3, 3)
    if not t.params:
        return np.eye(3)
    try:
        return mag_rotation(t.params, t.n)[0]
    except ValueError as exc:
        out.note(FNAME, f"mag: {exc}; written as if none")
        return np.eye(3)


def _compose_with_log(model: SensorModel, t: Target, out: Export) -> SensorModel | None:
    """The model in PX4's raw domain when the fitted data held the log's CAL_* correction (a
    magnetometer's also its rotation: ``vehicle_magnetometer = R S (raw - OFF)``, so ``M (vm -
    o)`` is ``M R S (raw - (OFF + (R S)^-1 o))``)."""
    cal, p = CAL[model.sensor], t.params
    board, rot = p.get("SENS_BOARD_ROT", 0), p.get(f"CAL_{cal}{t.n}_ROT", -1)
    if model.sensor != "mag" and (board != 0 or rot not in (-1, 0)):
        turned = [f"SENS_BOARD_ROT = {board}"] if board != 0 else []
        turned += [f"CAL_{cal}{t.n}_ROT = {rot}"] if rot not in (-1, 0) else []
        out.note(
            FNAME,
            f"{model.sensor}: fitted on data PX4 had rotated ({', '.join(turned)}); not "
            "written: fit on the raw sensor topics instead",
        )
        return None
    old_off = np.array([p.get(f"CAL_{cal}{t.n}_{a}OFF", 0.0) for a in "XYZ"], dtype=np.float64)
    diag = [p.get(f"CAL_{cal}{t.n}_{a}SCALE", 1.0) for a in "XYZ"]
    s = np.diag(np.asarray(diag, dtype=np.float64))
    if model.sensor == "mag":
        od = [p.get(f"CAL_MAG{t.n}_{a}ODIAG", 0.0) for a in "XYZ"]
        for (i, j), value in zip(OFF_DIAGONAL, od, strict=True):
            s[i, j] = s[j, i] = value
        old_off = old_off / GAUSS_PER_TESLA
        s = mag_turn(model, t, out) @ s
    elif model.sensor == "gyro":
        s = np.diag([p.get(f"CAL_GYRO{t.n}_{a}SCALE", 1.0) for a in "XYZ"]).astype(np.float64)
    sinv = np.linalg.inv(s)
    thermal = model.thermal
    if thermal is not None:
        thermal = type(thermal)(thermal.tref, sinv @ thermal.coefficients, thermal.t_range)
    tc = TC[model.sensor]
    if p.get(f"TC_{tc}_ENABLE") == 1:
        out.note(
            FNAME,
            f"{model.sensor}: the log's data were also thermally compensated by PX4 "
            f"(TC_{tc}_ENABLE = 1): keep its TC_{tc}* parameters"
            + ("; the fitted temperature model is not written" if thermal is not None else ""),
        )
        thermal = None
    return SensorModel(
        model.sensor,
        model.matrix @ s,
        old_off + sinv @ model.offset,
        thermal,
        model.entries,
        model.issues,
        model.device,
    )


Row = tuple[str, float | int, int]


def rows_for(model: SensorModel, t: Target, out: Export) -> list[Row]:
    """(name, value, type) rows of one device's sensor: only what its steps estimated (module
    docstring)."""
    cal = CAL[model.sensor]
    linear, scaled = model.linear, model.scaled
    if t.calibrated:
        composed = _compose_with_log(model, t, out)
        if composed is None:
            return []
        model = composed
    for issue in model.issues:
        out.note(FNAME, f"{model.sensor}: {issue}")
    m, n = model.matrix, t.n
    rows: list[Row] = []
    if linear:
        if t.device is not None:
            rows.append((f"CAL_{cal}{n}_ID", int(t.device), INT32))
        offset = model.offset * (GAUSS_PER_TESLA if model.sensor == "mag" else 1.0)
        rows += [(f"CAL_{cal}{n}_{a}OFF", offset[i], REAL32) for i, a in enumerate("XYZ")]
    diag = np.diag(m)
    if scaled and model.sensor == "mag":
        # PX4 turns the corrected field into the body after S (R S = m): S = R^T m
        diag_s, off_s = soft_iron(mag_turn(model, t, out).T @ m, out, FNAME)
        rows += [(f"CAL_MAG{n}_{a}SCALE", diag_s[i], REAL32) for i, a in enumerate("XYZ")]
        rows += [(f"CAL_MAG{n}_{a}ODIAG", off_s[i], REAL32) for i, a in enumerate("XYZ")]
    elif scaled:
        off = off_diagonal(m)
        if off > RELATIVE_TOLERANCE:
            out.note(
                FNAME,
                f"{model.sensor}: PX4 has no misalignment terms; the off-diagonal "
                f"part of the matrix (up to {off:.2g} of its diagonal) is left out",
            )
        has_scale = model.sensor == "accel" or f"CAL_GYRO{n}_XSCALE" in t.params
        if has_scale:
            rows += [(f"CAL_{cal}{n}_{a}SCALE", diag[i], REAL32) for i, a in enumerate("XYZ")]
        elif np.abs(diag - 1.0).max() > RELATIVE_TOLERANCE:
            out.note(
                FNAME,
                f"gyro: PX4 (v1.11 and later) has no gyro scale; the scale "
                f"{np.round(diag, 6).tolist()} is left out",
            )
    if scaled and (np.abs(diag).mean() < 0.2 or np.abs(diag).mean() > 5):
        out.note(
            FNAME,
            f"{model.sensor}: scale about {np.abs(diag).mean():.3g}: PX4 expects "
            "data in SI units (were the data raw counts?)",
        )
    if model.thermal is not None:
        rows += thermal_rows(model, t, out)
    return rows


def thermal_rows(model: SensorModel, t: Target, out: Export) -> list[Row]:
    th = model.thermal
    assert th is not None
    letter = TC[model.sensor]
    unit = GAUSS_PER_TESLA if model.sensor == "mag" else 1.0
    if model.sensor == "mag":
        out.note(
            FNAME,
            "mag: TC_M* (gauss) is read by PX4 firmware that has magnetometer thermal "
            "compensation (TC_M_ENABLE); older firmware ignores these rows",
        )
    prefix = f"TC_{letter}{t.tc}"
    rows: list[Row] = [(f"TC_{letter}_ENABLE", 1, INT32)]
    if t.device is not None:
        rows.append((f"{prefix}_ID", int(t.device), INT32))
    rows += [(f"{prefix}_TREF", th.tref, REAL32)]
    rows += [(f"{prefix}_TMIN", th.t_range[0], REAL32), (f"{prefix}_TMAX", th.t_range[1], REAL32)]
    rows += [
        (f"{prefix}_X{k}_{i}", th.coefficients[i, k] * unit, REAL32)
        for k in range(4)
        for i in range(3)
    ]
    temp = model.fitted_on.get("topics", {}).get("temperature")
    devices = model.fitted_on.get("device_id") or {}
    own = devices.get(STREAM[model.sensor])
    if devices.get("temperature") is None or devices.get("temperature") != own:
        out.note(
            FNAME,
            f"{model.sensor}: the temperature model was fitted against {temp or 'a temperature'}"
            " not known to be the sensor's own; PX4 compensates against each sensor's own "
            "temperature",
        )
    return rows


FAMILIES = {
    "accel": (("CAL_ACC{n}_", "OFF"), ("CAL_ACC{n}_", "SCALE"), ("TC_A{k}_", "")),
    "gyro": (("CAL_GYRO{n}_", "OFF"), ("TC_G{k}_", "")),
    "mag": (
        ("CAL_MAG{n}_", "OFF"),
        ("CAL_MAG{n}_", "SCALE"),
        ("CAL_MAG{n}_", "ODIAG"),
        ("TC_M{k}_", ""),
    ),
}
"""(prefix, suffix) of the parameter families of a device's slots, for the header's list of
what the file leaves alone."""


COMP_TYP = {"throttle": 1, "current": 2}
"""``CAL_MAG_COMP_TYP`` of each motor source (``MagCompensationType::Throttle``,
``Current_inst0``)."""
POWER_UNIT = {"throttle": 1.0, "current": 1e3}
"""PX4's power signal per imupipe's: the throttle 0..1 as it is, the current in kA (per A x 1e3)."""


def stale_motor_terms(rows: list[Row], logged: dict[str, Any], out: Export) -> None:
    """Noted: a compass of the log this file leaves alone (its fit refused, or not fitted) whose
    ``CAL_MAGn_*COMP`` the log holds for another ``CAL_MAG_COMP_TYP`` than the one the file
    writes: the vehicle has one type for every compass, so PX4 would read that compass's terms
    as the other kind (per kA against at full throttle)."""
    kind = next((int(r[1]) for r in rows if r[0] == "CAL_MAG_COMP_TYP"), None)
    old = int(logged.get("CAL_MAG_COMP_TYP") or 0)
    source = {1: "throttle", 2: "current", 3: "current"}
    if kind is None or source.get(old) in (None, source.get(kind)):
        return
    written = {r[0] for r in rows}
    for n in range(SLOTS):
        comp = [float(logged.get(f"CAL_MAG{n}_{a}COMP") or 0.0) for a in "XYZ"]
        if logged.get(f"CAL_MAG{n}_ID") and f"CAL_MAG{n}_XCOMP" not in written and any(comp):
            out.note(
                FNAME,
                f"mag: CAL_MAG{n} (device {int(logged[f'CAL_MAG{n}_ID'])}) is not in this file "
                f"and keeps CAL_MAG{n}_*COMP of CAL_MAG_COMP_TYP = {old} ({source[old]}); this "
                f"file sets CAL_MAG_COMP_TYP = {kind}, under which PX4 reads them per "
                f"{source[kind]}: set them to 0, or fit that compass too",
            )


def motor_rows(model: SensorModel, t: Target) -> list[Row]:
    """A magnetometer's motor compensation (``mag_inflight``): PX4 adds ``CAL_MAGn_{X,Y,Z}COMP``
    times its power signal to the raw field before the offsets (``Magnetometer::Correct``,
    ``UpdatePower``): the battery current in kA with ``CAL_MAG_COMP_TYP = 2`` (``COMP = S^-1
    motor`` in G/kA), or the throttle 0..1 with ``CAL_MAG_COMP_TYP = 1`` (G at full throttle;
    ``VehicleMagnetometer`` takes the norm of ``vehicle_thrust_setpoint``, in PX4 up to v1.13
    ``actuator_controls_0[3]``, and zero while disarmed)."""
    if model.motor is None or model.sensor != "mag":
        return []
    per = POWER_UNIT[model.motor_source]
    comp = np.linalg.solve(model.matrix, model.motor) * GAUSS_PER_TESLA * per
    rows: list[Row] = [(f"CAL_MAG{t.n}_{a}COMP", comp[i], REAL32) for i, a in enumerate("XYZ")]
    return rows + [("CAL_MAG_COMP_TYP", COMP_TYP[model.motor_source], INT32)]


def families(sensor: str, t: Target) -> list[tuple[str, str]]:
    """The parameter families of the device's slots (for the header's list)."""
    return [(prefix.format(n=t.n, k=t.tc), suffix) for prefix, suffix in FAMILIES[sensor]]


BARO_KIND = "baro_temperature"
"""The chain entries of barometer temperature models (:mod:`imupipe.stages.thermal.baro`)."""


def baro_rows(doc: dict[str, Any], out: Export) -> tuple[list[Row], list[str], dict[str, Any]]:
    """(rows, families left alone, the log's parameters) of every barometer's ``TC_Bk_*``:
    ``offset = sum X_k (clamp(T) - TREF)^k``, Pa, one slot per device by ``TC_Bk_ID`` (module
    docstring: slot rules, as ``TC_*``); ``TC_Bk_SCL = 1`` where the log has that parameter
    (PX4 up to v1.11 multiplies the corrected pressure by it)."""
    rows: list[Row] = []
    alone: list[str] = []
    logged: dict[str, Any] = {}
    taken: set[int] = set()
    seen: list[dict[str, Any]] = []
    for entry in doc.get("chain", []):
        if entry.get("kind") != BARO_KIND:
            continue
        where = entry.get("fitted_on") or {}
        dev = entry_device(entry)
        if any(same_device(dev, other) for other in seen):
            out.note(FNAME, "baro: a second barometer temperature step of one device: not mapped")
            continue
        seen.append(dev)
        params = (where.get("px4") or {}).get("parameters") or {}
        device_id = dev.get("device_id")
        device_id = None if device_id is None else int(device_id)
        k = _slot("TC_B", "_ID", device_id, params, taken, dev.get("instance"))
        if k is None:
            out.note(FNAME, f"baro: no TC_B slot left for device {device_id}; not written")
            continue
        taken.add(k)
        prefix = f"TC_B{k}"
        mine: list[Row] = [("TC_B_ENABLE", 1, INT32)]
        if device_id is not None:
            mine.append((f"{prefix}_ID", device_id, INT32))
        else:
            out.note(
                FNAME,
                f"baro: the input names no PX4 device, so {prefix}_ID is not written; PX4 "
                "applies a slot only to the device whose id it holds: set it",
            )
        lo, hi = entry["range"]
        mine += [(f"{prefix}_TREF", float(entry["tref"]), REAL32)]
        mine += [(f"{prefix}_TMIN", float(lo), REAL32), (f"{prefix}_TMAX", float(hi), REAL32)]
        coef = list(entry["coefficients"]) + [0.0] * (6 - len(entry["coefficients"]))
        mine += [(f"{prefix}_X{j}", float(c), REAL32) for j, c in enumerate(coef)]
        if f"{prefix}_SCL" in params:
            mine.append((f"{prefix}_SCL", 1.0, REAL32))
        rows += mine
        alone += left_alone([r[0] for r in mine], [(f"{prefix}_", "")])
        logged.update(params)
    return rows, alone, logged


def export(doc: dict[str, Any], complete: bool = False) -> Export:
    """``px4_calibration.params``: the estimated parameters of every device in its own slot;
    ``complete``: merged over the log's own ``CAL_*``/``TC_*``/``SENS_BOARD_*`` parameters."""
    out = Export()
    rows: list[Row] = []
    alone: list[str] = []
    logged: dict[str, Any] = {}
    for sensor in CAL:
        models = []
        for model in device_models(doc, sensor):
            if ((model.fitted_on.get("ardupilot") or {}).get("calibrated") or {}).get(
                STREAM[sensor]
            ):
                out.note(
                    FNAME, f"{sensor}: fitted on data ArduPilot had already corrected; not written"
                )
                continue
            models.append(model)
        for model, t in zip(models, targets(models, out), strict=True):
            if t is None:
                continue
            mine = rows_for(model, t, out) + motor_rows(model, t)
            rows += mine
            alone += left_alone([r[0] for r in mine], families(sensor, t))
            logged.update(t.params)
    stale_motor_terms(rows, logged, out)
    baro, baro_alone, baro_logged = baro_rows(doc, out)
    rows += baro
    alone += baro_alone
    logged.update(baro_logged)
    if not rows:
        return out
    seen: dict[str, Row] = {}
    for row in rows:  # TC_*_ENABLE once
        seen.setdefault(row[0], row)
    rows = list(seen.values())
    comments = [
        "PX4 calibration parameters from imupipe (load in QGroundControl: Parameters, Tools,",
        "Load from file). corrected = (raw - thermal(T) - OFF) * SCALE, SI units (mag: gauss).",
    ]
    if complete and logged:
        ours = {r[0] for r in rows}
        rows += [
            (name, value, INT32 if isinstance(value, int) else REAL32)
            for name, value in sorted(logged.items())
            if name not in ours
        ]
        comments += [
            "Complete: the log's own CAL_*, TC_* and SENS_BOARD_* parameters, with the ones",
            "imupipe estimated in their place.",
        ]
    else:
        if complete:
            out.note(
                FNAME, "the input carries no PX4 parameters: only the estimated ones are written"
            )
        listed = ", ".join(alone) if alone else "(none in these slots)"
        comments += textwrap.wrap(
            "Only what imupipe estimated: loading it leaves every other parameter of the "
            f"vehicle as it is, among them {listed}.",
            width=92,
        )
    comments += ["", "Vehicle-Id Component-Id Name Value Type"]
    table = [
        (1, 1, name, number(value) if kind == REAL32 else int(value), kind)
        for name, value, kind in rows
    ]
    out.files[FNAME] = params_text(table, comments, delimiter="\t")
    return out
