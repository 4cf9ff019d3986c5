"""The compass in ``imupipe survey``: every flight log's in-flight compass fit, per compass, into
``DIR/compass.parquet``, and its fleet view (the rules are :mod:`imupipe.stages.survey.compass`'s).

**Per log** (:func:`survey_compass`, in the worker after the IMU figures): a PX4 ULog or
ArduPilot DataFlash log's compass instances (``sensor_mag`` instances; ``MAG``, ``MAG2``...) are
each read with the log's attitude, GPS position, battery current and throttle, and fitted by the
``mag_inflight`` stage's own code (:func:`imupipe.stages.magnetometer.inflight.flight_samples`
and :func:`~imupipe.stages.magnetometer.inflight.fit_flight`, the stage's default options): a
PX4 ``sensor_mag`` turned into the body by its rotation, offsets, soft iron, scale and the motor
term on the current or the throttle (the stage's source choice), the model chosen on held-out
segments, standard errors, residuals and heading errors, the attitudes flown. A flight that
cannot be fitted (no GPS date, no attitude or position, too few samples, nothing separable) is a
row with ``status = "refused"`` and ``why``, not a failed log. The rows go to
``DIR/parts/<log>.compass.parquet``; the driver joins them into ``DIR/compass.parquet``
(:func:`join_compass`; schema in ``docs/reference/survey.md``).

**Three calibrations side by side.** ArduPilot logs ``MAG`` after its own ``COMPASS_*``
correction, PX4 logs ``sensor_mag`` raw. Each row holds:

- the *vehicle's own* calibration (``vehicle_*``: the log's ``COMPASS_OFS*``/``DIA*``/``ODI*``/
  ``SCALE*``/``MOT*`` or ``CAL_MAGn_*OFF``/``SCALE``/``ODIAG``/``COMP`` of the slot holding the
  compass's device id, in imupipe's form ``corrected = M (raw - offset) + motor P``, ``P`` the
  current (``COMPASS_MOTCT`` 2, ``CAL_MAG_COMP_TYP`` 2, 3: ``vehicle_motor_*`` uT/A) or the
  throttle (both 1: ``vehicle_motor_throttle_*``, uT at full throttle));
- the flight's fit on the field as logged (``fit_offset_*``, ``fit_motor_*``: for ArduPilot the
  correction still missing on top of the vehicle's);
- the calibration the flight says the vehicle should use (``offset_*``, ``dia_*``, ``odi_*``,
  ``scale``, ``motor_*``: the fit composed with the log's own parameters by the ArduPilot
  export's :func:`~imupipe.pipeline.exports.ardupilot.compose_with_log`; for PX4 the fit itself,
  in the compass's axes: ``S = R^T M R``, ``OFF = R^T o``),
  which is what the fleet view tracks: it does not move when a user recalibrates, only when the
  compass's surroundings change.

``residual_vehicle_ut`` is the RMS vector residual against the World Magnetic Model under the
vehicle's own calibration, ``residual_after_ut`` under the flight's fit, and
``calibration_error_ut`` the RMS difference of the two corrected fields: "the compass
calibration in use is off by X uT".
"""

from __future__ import annotations

import dataclasses
import html
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

COMPASS_NAME = "compass.parquet"
COMPASS_FLEET_NAME = "compass.json"
PART_SUFFIX = ".compass.parquet"
FLIGHT_FORMATS = ("ulog", "dataflash")
UT = 1e6
"""uT per tesla (the dataset's field columns are in uT)."""
AXES = "xyz"
MOTOR_UNIT = {"current": "uT/A", "throttle": "uT"}
"""The motor term's unit per source: per ampere, or at full throttle (throttle 0..1)."""


def compass_part(part: Path) -> Path:
    """The compass part beside a log's survey part: ``<log>.compass.parquet``."""
    return part.with_name(part.name.removesuffix(".parquet") + PART_SUFFIX)


# -- the vehicle's own calibration -----------------------------------------------------------------


@dataclasses.dataclass
class VehicleCompass:
    """A vehicle's compass calibration in imupipe's form (``corrected = matrix (raw - offset) +
    motor P``; T, and T/A with ``source = "current"`` or T at full throttle with ``"throttle"``;
    None: no motor compensation), the parameters it came from, and whether it is ``known`` (a
    log without any compass parameter says nothing) and ``applied`` (ArduPilot: the logged field
    carries it). All in the compass's own axes (PX4 turns the result by ``R`` after it)."""

    offset: np.ndarray
    matrix: np.ndarray
    motor: np.ndarray
    parameters: dict[str, float]
    known: bool
    applied: bool
    notes: list[str]
    source: str | None = None


def _ardupilot_vehicle(p: dict[str, Any], instance: int) -> VehicleCompass:
    from imupipe.pipeline.exports.ardupilot import (
        MILLIGAUSS_PER_TESLA,
        MOTCT,
        compass_terms,
        motor_kind,
    )

    s = "" if instance == 0 else str(instance + 1)
    own = {
        k: float(v)
        for k, v in p.items()
        if k == "COMPASS_MOTCT"
        or any(
            k.startswith(f"COMPASS_{f}{s}_") or k == f"COMPASS_{f}{s}"
            for f in ("OFS", "DIA", "ODI", "SCALE", "MOT", "DEV_ID", "ORIENT")
        )
    }
    ofs, w, mot = compass_terms(p, s)  # MOT: mG/A (COMPASS_MOTCT 2) or mG at full throttle (1)
    source = {v: k for k, v in MOTCT.items()}.get(motor_kind(p)) if mot.any() else None
    return VehicleCompass(
        -ofs / MILLIGAUSS_PER_TESLA, w, mot / MILLIGAUSS_PER_TESLA, own, bool(p), True, [], source
    )


def _px4_vehicle(p: dict[str, Any], device_id: int | None) -> VehicleCompass:
    """PX4's ``Magnetometer::Correct``: ``R S (raw + COMP P - OFF)`` (gauss), for the
    ``CAL_MAGn`` slot whose ``CAL_MAGn_ID`` is the compass's device id
    (:func:`imupipe.stages.magnetometer.inflight.px4_vehicle_calibration`); ``P`` the battery
    current (``CAL_MAG_COMP_TYP`` 2, 3: ``COMP`` in G/kA) or the throttle 0..1 (1: G at full
    throttle); ``R`` (the slot's rotation, :func:`imupipe.stages.magnetometer.inflight.
    sensor_rotation`) is not part of this calibration."""
    from imupipe.stages.magnetometer.inflight import px4_vehicle_calibration

    cal = px4_vehicle_calibration(p, device_id)
    if cal is None:
        known = any(k.startswith("CAL_MAG") for k in p)
        notes = [f"no CAL_MAGn slot holds device id {device_id}"] if known else []
        return VehicleCompass(np.zeros(3), np.eye(3), np.zeros(3), {}, known, False, notes)
    off, s, comp, source = cal
    slot = next(n for n in range(8) if int(p.get(f"CAL_MAG{n}_ID") or 0) == int(device_id or 0))
    pre = f"CAL_MAG{slot}_"
    own = {k: float(v) for k, v in p.items() if k.startswith(pre) or k == "CAL_MAG_COMP_TYP"}
    motor = s @ comp  # added before S in PX4, after the matrix in imupipe's form
    return VehicleCompass(off, s, motor, own, True, False, [], source)


# -- one log --------------------------------------------------------------------------------------


def _instances(spec: Any) -> list[str]:
    from imupipe.readers import dispatch

    return list(dispatch.raw_instances(spec).get("mag") or [])


def survey_compass(task: Any) -> dict[str, Any] | None:
    """Fit every compass of ``task``'s log (a worker's :class:`~imupipe.pipeline.survey.scan.
    SurveyTask`) and write its compass part; None (no part) for a log that is not a flight
    log. Returns ``{"compasses": n, "fitted": n, "seconds": s, "warnings": [...]}``."""
    import pyarrow.parquet as pq

    from imupipe.pipeline.atomic import staged_outputs
    from imupipe.readers import dispatch
    from imupipe.readers.spec import InputSpec

    path = Path(task.path)
    if dispatch.detect_format(path) not in FLIGHT_FORMATS:
        return None
    start = time.perf_counter()
    spec = InputSpec(path=path, name=task.vehicle)
    rows: list[dict[str, Any]] = []
    warnings: list[str] = []
    keys: list[str | None] = list(_instances(spec))
    if not keys and dispatch.detect_format(path) == "ulog":
        keys = [None]  # no raw sensor_mag: the magnetometer PX4 corrected, if it is the only one
    for instance, key in enumerate(keys):
        one = dataclasses.replace(spec, imu_topic="", temperature_topic="", mag_topic=key)
        try:
            table, _ = dispatch.read_input(one)
        except Exception as exc:  # noqa: BLE001 - one compass that cannot be read: its row says why
            if key is not None:
                rows.append(_refused(task, key, instance, None, f"not read: {exc}"))
            continue
        if key is None:
            from imupipe.readers.table import has_stream, metadata

            if not has_stream(table, "mag"):
                continue
            key = str((metadata(table).get("topics") or {}).get("mag") or "mag")
        rows.append(fit_compass(task, key, instance, table))
    for r in rows:
        if r["status"] == "refused":
            warnings.append(f"{path}: compass {r['topic']}: not fitted: {r['why']}")
    table = rows_table(rows)
    out_path = compass_part(Path(task.part))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with staged_outputs() as out:
        pq.write_table(table, out.path(out_path), compression="zstd")
    return {
        "compasses": len(rows),
        "fitted": sum(r["status"] == "fitted" for r in rows),
        "seconds": round(time.perf_counter() - start, 4),
        "warnings": warnings,
    }


def _identity(task: Any, key: str, instance: int, meta: dict[str, Any] | None) -> dict[str, Any]:
    meta = meta or {}
    hw = (meta.get("device_id") or {}).get("mag")
    year = meta.get("gps_year")
    start_ns = None if year is None else int(round((float(year) - 1970.0) * 365.2425 * 86400e9))
    return {
        "log": task.log,
        "vehicle": task.vehicle,
        "format": meta.get("format"),
        "topic": key,
        "instance": int((meta.get("instance") or {}).get("mag", instance)),
        "device_id": f"{task.vehicle}:{key}",
        "hw_device_id": None if hw is None else int(hw),
        "start_ns": start_ns,
        "year": None if year is None else float(year),
    }


def _refused(
    task: Any, key: str, instance: int, meta: dict[str, Any] | None, why: str, **extra: Any
) -> dict[str, Any]:
    return {**_identity(task, key, instance, meta), "status": "refused", "why": why, **extra}


def fit_compass(task: Any, key: str, instance: int, table: pa.Table) -> dict[str, Any]:
    """One compass of one flight: the row of the dataset (refused with why when it cannot be
    fitted)."""
    from imupipe.pipeline.exports.ardupilot import compose_with_log
    from imupipe.pipeline.exports.common import Export, SensorModel
    from imupipe.readers.table import finite, has_flight_stream, has_stream, metadata, sensor
    from imupipe.stages.magnetometer.inflight import (
        STEP_BY_SOURCE,
        CannotSeparate,
        MagInflightStage,
        fit_flight,
        flight_samples,
        heading_deg,
        offset_covariance,
        wrap_deg,
    )

    meta = metadata(table)
    fmt = meta.get("format") or ("dataflash" if meta.get("ardupilot") else "ulog")
    meta = {**meta, "format": fmt}
    inst = int((meta.get("instance") or {}).get("mag", instance))
    if fmt == "dataflash":
        vehicle = _ardupilot_vehicle((meta.get("ardupilot") or {}).get("parameters") or {}, inst)
    else:
        hw = (meta.get("device_id") or {}).get("mag")
        vehicle = _px4_vehicle((meta.get("px4") or {}).get("parameters") or {}, hw)
        # vehicle_magnetometer (old sensor_combined): the field PX4 had corrected with CAL_MAG
        vehicle.applied = bool(((meta.get("px4") or {}).get("calibrated") or {}).get("mag"))
    common = {
        "vehicle_parameters": json.dumps(vehicle.parameters, sort_keys=True),
        "notes": "; ".join(vehicle.notes) or None,
    }
    missing = [s for s in ("attitude", "position") if not has_flight_stream(table, s)]
    if not has_stream(table, "mag"):
        missing.insert(0, "magnetometer")
    if missing:
        return _refused(task, key, instance, meta, "no " + ", ".join(missing), **common)
    if meta.get("gps_year") is None:
        why = "the flight's date is unknown (no GPS week and time): the WMM needs it"
        return _refused(task, key, instance, meta, why, **common)
    mag, _ = finite(sensor(table, "mag"))
    options = MagInflightStage.Options()
    try:
        if len(mag) < 50:
            raise ValueError(f"{len(mag)} finite magnetometer samples; the fit needs at least 50")
        fs = flight_samples(table, mag, float(meta["gps_year"]))
        flown = fit_flight(fs, options)
    except (CannotSeparate, ValueError, np.linalg.LinAlgError) as exc:
        return _refused(task, key, instance, meta, str(exc), **common)
    fit, source = flown.fit, flown.source
    corrected = fit.predict(fs.raw, fs.power(source))
    notes = list(vehicle.notes)
    # the field under the vehicle's own calibration (in the compass's axes, then turned by R
    # into the body as PX4 does: fs.raw is the logged field turned by R)
    turn = np.eye(3) if fs.rotation is None else fs.rotation
    own: np.ndarray | None = None
    if vehicle.applied:
        own = fs.raw
    elif vehicle.known:
        p_own = fs.power(vehicle.source)
        if vehicle.source is not None and p_own is None:
            notes.append(
                f"the vehicle compensates the motors by {vehicle.source}, which the log lacks: "
                "its own calibration is taken without that term"
            )
        p_own = np.zeros(len(fs.raw)) if p_own is None else p_own
        own = (
            (fs.raw @ turn - vehicle.offset) @ vehicle.matrix.T + p_own[:, None] * vehicle.motor
        ) @ turn.T
    # the calibration the flight says the vehicle should use (the raw sensor's)
    cov_off = offset_covariance(fit)
    se_motor = np.sqrt(np.diag(fit.cov)[-3:]) / UT if fit.motor_term else np.full(3, np.nan)
    if vehicle.applied and fmt != "dataflash":
        notes.append(
            "PX4 had corrected this field with its CAL_MAG parameters: the offsets for the raw "
            "sensor are not derived (fit_offset_* are tracked); survey the raw sensor_mag"
        )
        s_matrix, s_offset, s_motor = np.full((3, 3), np.nan), np.full(3, np.nan), None
        s_cov = np.full((3, 3), np.nan)
        s_source = None
    elif vehicle.applied:
        out = Export()
        model = SensorModel(
            "mag",
            fit.matrix,
            fit.offset,
            None,
            [
                {
                    "kind": STEP_BY_SOURCE[source or "current"].kind,
                    "fitted_on": {"ardupilot": {"parameters": meta["ardupilot"]["parameters"]}},
                }
            ],
            [],
            {},
            fit.motor if fit.motor_term else None,
            source or "current",
        )
        composed = compose_with_log(model, inst, out)
        notes += [n for ns in out.notes.values() for n in ns if "not written" not in n]
        if composed is None:
            notes.append(
                "the log rotates the compass (AHRS_ORIENTATION, COMPASS_ORIENT): the offsets "
                "for the raw sensor are not derived (fit_offset_* are tracked)"
            )
            s_matrix, s_offset, s_motor = np.full((3, 3), np.nan), np.full(3, np.nan), None
            s_cov = np.full((3, 3), np.nan)
            s_source = None
        else:
            s_matrix, s_offset, s_motor = composed.matrix, composed.offset, composed.motor
            s_source = composed.motor_source if s_motor is not None else None
            winv = np.linalg.inv(vehicle.matrix)
            s_cov = winv @ cov_off @ winv.T
    else:  # PX4 sensor_mag: M (R raw - o) + motor P = R (R^T M R (raw - R^T o) + R^T motor P)
        s_matrix, s_offset = turn.T @ fit.matrix @ turn, turn.T @ fit.offset
        s_cov = turn.T @ cov_off @ turn
        s_source = source
        s_motor = turn.T @ fit.motor if fit.motor_term else None
        s_se_motor = (
            np.sqrt(np.diag(turn.T @ fit.cov[-3:, -3:] @ turn)) / UT if fit.motor_term else None
        )
        se_motor = se_motor if s_se_motor is None else s_se_motor
    h_model = heading_deg(fs.q, fs.target)
    m = flown.metrics
    row: dict[str, Any] = {
        **_identity(task, key, instance, meta),
        "status": "fitted",
        "why": None,
        "not_fitted": "; ".join(flown.not_fitted) or None,
        "quality_ok": bool(m["residual_rms_ut_after"] <= options.max_residual_ut),
        "model": flown.model,
        "motor_term": bool(fit.motor_term),
        "motor_source": s_source,
        "fit_motor_source": source,
        "vehicle_motor_source": vehicle.source if vehicle.known else None,
        "duration_s": float((fs.t_ns[-1] - fs.t_ns[0]) * 1e-9),
        "samples": int(len(fs.t_ns)),
        "field_ut": m["field_ut"],
        "residual_before_ut": m["residual_rms_ut_before"],
        "residual_after_ut": m["residual_rms_ut_after"],
        "heading_before_deg": m["heading_rms_deg_before"],
        "heading_after_deg": m["heading_rms_deg_after"],
        "yaw_coverage_deg": flown.coverage["yaw_coverage_deg"],
        "tilt_max_deg": flown.coverage["tilt_max_deg"],
        "direction_spread": flown.coverage["direction_spread"][0],
        "current_span_a": (
            None if fs.current is None else float(np.subtract(*np.percentile(fs.current, [95, 5])))
        ),
        "throttle_span": (
            None
            if fs.throttle is None
            else float(np.subtract(*np.percentile(fs.throttle, [95, 5])))
        ),
        **common,
        "notes": "; ".join(notes) or None,
    }
    if own is not None:
        row["residual_vehicle_ut"] = float(np.sqrt(np.mean(np.sum((own - fs.target) ** 2, 1))) * UT)
        row["heading_vehicle_deg"] = float(
            np.sqrt(np.mean(wrap_deg(heading_deg(fs.q, own) - h_model) ** 2))
        )
        row["calibration_error_ut"] = float(
            np.sqrt(np.mean(np.sum((own - corrected) ** 2, 1))) * UT
        )
    s_se = np.sqrt(np.diag(s_cov))
    for i, a in enumerate(AXES):
        row[f"fit_offset_{a}"] = float(fit.offset[i] * UT)
        row[f"fit_offset_se_{a}"] = float(np.sqrt(cov_off[i, i]) * UT)
        # the motor terms: per ampere in motor_*, at full throttle in motor_throttle_*
        thr = {"current": "", "throttle": "throttle_"}
        if fit.motor_term:
            row[f"fit_motor_{thr[source]}{a}"] = float(fit.motor[i] * UT)
        row[f"offset_{a}"] = float(s_offset[i] * UT)
        row[f"offset_se_{a}"] = float(s_se[i] * UT)
        row[f"dia_{a}"] = float(s_matrix[i, i])
        if s_motor is not None:
            row[f"motor_{thr[s_source]}{a}"] = float(s_motor[i] * UT)
            if fit.motor_term and s_source == source:
                row[f"motor_{thr[s_source]}se_{a}"] = float(se_motor[i] * UT)
        if vehicle.known:
            row[f"vehicle_offset_{a}"] = float(vehicle.offset[i] * UT)
            row[f"vehicle_dia_{a}"] = float(vehicle.matrix[i, i])
            if vehicle.source is not None:
                row[f"vehicle_motor_{thr[vehicle.source]}{a}"] = float(vehicle.motor[i] * UT)
            else:  # no motor compensation
                row[f"vehicle_motor_{a}"] = 0.0
    for (i, j), a in zip(((0, 1), (0, 2), (1, 2)), AXES, strict=True):
        row[f"odi_{a}"] = float(s_matrix[i, j])
        if vehicle.known:
            row[f"vehicle_odi_{a}"] = float(vehicle.matrix[i, j])
    with np.errstate(invalid="ignore"):
        row["scale"] = float(np.cbrt(np.linalg.det(s_matrix)))
    return row


# -- the dataset ----------------------------------------------------------------------------------

_V3 = [f"{n}_{a}" for n in ("offset", "offset_se") for a in AXES]
COLUMNS: list[tuple[str, pa.DataType, str | None]] = [
    ("log", pa.string(), None),
    ("vehicle", pa.string(), None),
    ("format", pa.string(), None),
    ("topic", pa.string(), None),
    ("instance", pa.int32(), None),
    ("device_id", pa.string(), None),
    ("hw_device_id", pa.int64(), None),
    ("start_ns", pa.int64(), "ns"),
    ("start", pa.timestamp("us", "UTC"), None),
    ("year", pa.float64(), "year"),
    ("status", pa.string(), None),
    ("why", pa.string(), None),
    ("not_fitted", pa.string(), None),
    ("quality_ok", pa.bool_(), None),
    ("model", pa.string(), None),
    ("motor_term", pa.bool_(), None),
    ("motor_source", pa.string(), None),
    ("fit_motor_source", pa.string(), None),
    ("vehicle_motor_source", pa.string(), None),
    ("duration_s", pa.float64(), "s"),
    ("samples", pa.int64(), "1"),
    ("field_ut", pa.float64(), "uT"),
    *[(f"{n}_{a}", pa.float64(), "uT") for n in ("offset", "offset_se") for a in AXES],
    *[(f"{n}_{a}", pa.float64(), "1") for n in ("dia", "odi") for a in AXES],
    ("scale", pa.float64(), "1"),
    *[(f"{n}_{a}", pa.float64(), "uT/A") for n in ("motor", "motor_se") for a in AXES],
    *[
        (f"{n}_{a}", pa.float64(), "uT")
        for n in ("motor_throttle", "motor_throttle_se")
        for a in AXES
    ],
    *[(f"fit_{n}_{a}", pa.float64(), "uT") for n in ("offset", "offset_se") for a in AXES],
    *[(f"fit_motor_{a}", pa.float64(), "uT/A") for a in AXES],
    *[(f"fit_motor_throttle_{a}", pa.float64(), "uT") for a in AXES],
    *[(f"vehicle_offset_{a}", pa.float64(), "uT") for a in AXES],
    *[(f"vehicle_{n}_{a}", pa.float64(), "1") for n in ("dia", "odi") for a in AXES],
    *[(f"vehicle_motor_{a}", pa.float64(), "uT/A") for a in AXES],
    *[(f"vehicle_motor_throttle_{a}", pa.float64(), "uT") for a in AXES],
    ("vehicle_parameters", pa.string(), None),
    ("residual_before_ut", pa.float64(), "uT"),
    ("residual_vehicle_ut", pa.float64(), "uT"),
    ("residual_after_ut", pa.float64(), "uT"),
    ("calibration_error_ut", pa.float64(), "uT"),
    ("heading_before_deg", pa.float64(), "deg"),
    ("heading_vehicle_deg", pa.float64(), "deg"),
    ("heading_after_deg", pa.float64(), "deg"),
    ("yaw_coverage_deg", pa.float64(), "deg"),
    ("tilt_max_deg", pa.float64(), "deg"),
    ("direction_spread", pa.float64(), "1"),
    ("current_span_a", pa.float64(), "A"),
    ("throttle_span", pa.float64(), "1"),
    ("notes", pa.string(), None),
]
"""The dataset's columns: name, type, unit (its Parquet field's ``unit`` metadata; None for
identity and text)."""


def schema() -> pa.Schema:
    return pa.schema(
        [pa.field(n, t, metadata=None if u is None else {"unit": u}) for n, t, u in COLUMNS]
    )


def rows_table(rows: list[dict[str, Any]]) -> pa.Table:
    """The rows (dicts; absent keys are null) as a table of :func:`schema`."""
    data: dict[str, list[Any]] = {n: [r.get(n) for r in rows] for n, _, _ in COLUMNS}
    data["start"] = [None if s is None else s // 1000 for s in data["start_ns"]]
    arrays = []
    for n, t, _ in COLUMNS:
        if n == "start":
            arrays.append(pa.array(data[n], pa.int64()).cast(t))
        else:
            arrays.append(pa.array(data[n], t))
    return pa.Table.from_arrays(arrays, schema=schema())


# -- the driver: join, fleet view, summary, report --------------------------------------------------


def read_part(path: Path) -> pa.Table:
    """A survey's part file (one local Parquet file, no partition in its path) read whole:
    ``pyarrow.parquet.read_table``'s table, read through ``ParquetFile`` because ``read_table``
    goes through ``pyarrow.dataset``, whose import (with ``pyarrow.compute``) is 60-70 ms of a
    survey's fixed cost (issue 39); ``tests/test_survey.py`` checks the two tables equal."""
    import pyarrow.parquet as pq

    with pq.ParquetFile(path) as part:
        return part.read()


def join_compass(parts: list[Path], meta: dict[str, str]) -> pa.Table | None:
    """The compass parts that exist (flight logs) joined in the given order, with the survey's
    schema metadata; None when there is none."""
    tables = [read_part(p) for p in parts if p.exists()]
    if not tables:
        return None
    return pa.concat_tables(tables, promote_options="default").replace_schema_metadata(meta)


def _col(table: pa.Table, name: str) -> np.ndarray:
    return table.column(name).to_numpy(zero_copy_only=False)


def _f(table: pa.Table, name: str) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in table.column(name).to_pylist()], float)


def histories(table: pa.Table) -> list[Any]:
    """Each compass's :class:`~imupipe.stages.survey.compass.CompassHistory` from the dataset:
    its fitted flights' offsets in the sensor's domain where every flight has them, else as
    logged (``domain``), and its refused flights with why."""
    from imupipe.stages.survey.compass import compass_history

    devices = _col(table, "device_id").astype(str)
    status = _col(table, "status").astype(str)
    start = _f(table, "start_ns")
    t0 = int(np.nanmin(start)) if np.isfinite(start).any() else 0
    logs = _col(table, "log").astype(str)
    why = table.column("why").to_pylist()
    out = []
    for dev in sorted(set(devices)):
        rows = devices == dev
        ok = rows & (status == "fitted") & np.isfinite(start)
        refused = [(logs[i], str(why[i])) for i in np.flatnonzero(rows & ~ok)]
        sensor = np.isfinite(np.column_stack([_f(table, f"offset_{a}")[ok] for a in AXES])).all()
        pre = "" if sensor else "fit_"

        def vec(name: str, ok: np.ndarray = ok) -> np.ndarray:
            return np.column_stack([_f(table, f"{name}_{a}")[ok] for a in AXES])

        # the motor term in one unit per compass: per ampere where a flight has it, else at
        # full throttle (a vehicle without a current sensor)
        src_col = "motor_source" if sensor else "fit_motor_source"
        src = _col(table, src_col)[ok] if src_col in table.column_names else []
        source = "current" if "current" in set(src) or "throttle" not in set(src) else "throttle"
        thr = "" if source == "current" else "_throttle"
        motor = vec(("motor" if sensor else "fit_motor") + thr)
        motor_se = vec(f"motor{thr}_se")
        out.append(
            compass_history(
                dev,
                list(logs[ok]),
                start[ok],
                vec(f"{pre}offset"),
                vec(f"{pre}offset_se"),
                motor,
                np.where(np.isfinite(motor), motor_se, np.nan),
                _f(table, "calibration_error_ut")[ok],
                _f(table, "residual_after_ut")[ok],
                _f(table, "field_ut")[ok],
                t0,
                "sensor" if sensor else "logged",
                refused,
                source,
            )
        )
    return out


def compass_fleet(table: pa.Table, k: float) -> dict[str, Any]:
    """The compass fleet view as a JSON-ready dict (``DIR/compass.json``): ``k``, the fleet's
    scales, per compass its flights (``logs``, ``start_ns``: their start, ns since the epoch;
    ``day``) with their offsets and motor terms, drift, flags and refused flights, and the
    compasses to recalibrate."""
    from imupipe.stages.survey.compass import compass_flags

    hs = histories(table)
    fleet = compass_flags(hs, k)
    ids, logs, stamps = (table.column(c).to_pylist() for c in ("device_id", "log", "start_ns"))
    start = {(d, log): s for d, log, s in zip(ids, logs, stamps, strict=True)}  # one per flight
    devices = []
    for h in hs:
        devices.append(
            {
                "device_id": h.device_id,
                "domain": h.domain,
                "logs": h.logs,
                "start_ns": [start[(h.device_id, log)] for log in h.logs],
                "day": h.day.tolist(),
                "offset_ut": h.offset.tolist(),
                "offset_se_ut": h.offset_se.tolist(),
                "motor_source": h.motor_source,
                "motor_unit": MOTOR_UNIT[h.motor_source],
                "motor": h.motor.tolist(),
                "motor_se": h.motor_se.tolist(),
                "calibration_error_ut": h.calibration_error.tolist(),
                "residual_after_ut": h.residual_after.tolist(),
                "field_ut": h.field.tolist(),
                "mean_offset_ut": h.mean_offset,
                "drift_ut_per_day": h.drift,
                "moved_ut": h.moved,
                "refused": [{"log": log, "why": why} for log, why in h.refused],
                "flags": h.flags,
            }
        )
    devices.sort(key=lambda d: -d["moved_ut"])
    recal = [
        {"device_id": d["device_id"], "why": list(dict.fromkeys(f["why"] for f in d["flags"]))}
        for d in devices
        if d["flags"]
    ]
    return {**fleet, "devices": devices, "recalibrate": recal}


def summary_lines(fleet: dict[str, Any] | None) -> list[str]:
    """The terminal summary of the compasses: those to recalibrate and why (the first reason;
    the rest in report.html), and the refused flights' count."""
    if not fleet or not fleet.get("devices"):
        return []
    n = len(fleet["devices"])
    flights = sum(len(d["logs"]) for d in fleet["devices"])
    refused = sum(len(d["refused"]) for d in fleet["devices"])
    tail = f"; {refused} compass-flights refused (why: compass.parquet)" if refused else ""
    recal = fleet["recalibrate"]
    if not recal:
        return [
            f"imupipe survey: {n} compasses over {flights} compass-flights, none flagged "
            f"(k = {fleet['k']:g} robust sigmas){tail}"
        ]
    lines = [
        f"imupipe survey: recalibrate {len(recal)} of {n} compasses (k = {fleet['k']:g} "
        f"robust sigmas){tail}:"
    ]
    for r in recal:
        why = r["why"]
        more = f" (+{len(why) - 1} more in report.html)" if len(why) > 1 else ""
        lines.append(f"  {r['device_id']}: {why[0]}{more}")
    return lines


def _plots(d: dict[str, Any]) -> list[str]:
    from imupipe.pipeline.report.figures import Plot, Series, colors_for
    from imupipe.pipeline.report.svg_plot import svg

    day = np.asarray(d["day"], dtype=np.float64)
    if not len(day):
        return []
    out = []
    what = "offsets" if d["domain"] == "sensor" else "offsets (fitted on the field as logged)"
    for key, unit, title, vals, ses in (
        ("offset", "uT", f"compass {what}", d["offset_ut"], d["offset_se_ut"]),
        ("motor", d["motor_unit"], f"motor term ({d['motor_source']})", d["motor"], d["motor_se"]),
    ):
        v = np.asarray(vals, dtype=np.float64).reshape(-1, 3)
        se = np.asarray(ses, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(v).any():
            continue
        names = [f"{key} {a}" for a in AXES]
        colors = colors_for(names, None)
        p = Plot(
            "survey",
            f"{d['device_id']}/compass/{key}",
            "xy",
            f"{d['device_id']}: {title} per flight",
            unit,
            x_label="days since the fleet's first flight",
            x_unit="day",
        )
        for i in range(3):
            ok = np.isfinite(v[:, i])
            x, y, s = day[ok], v[ok, i], np.nan_to_num(se[ok, i])
            # the x axis ends at the last flight: the legend sits above the plot, not on it
            p.series.append(Series(f"compass/{key}/{AXES[i]}", [names[i]], [colors[i]], x,
                                   y[:, None], "points"))  # fmt: skip
            p.series.append(
                Series(f"compass/{key}/{AXES[i]}/band", [f"{names[i]} +-2 se"], [colors[i]], x,
                       np.column_stack([y - 2 * s, y + 2 * s]), "band")
            )  # fmt: skip
        out.append(svg(p))
    return [s for s in out if s]


def report_section(fleet: dict[str, Any] | None) -> str:
    """The compass section of the survey's ``report.html``: the compasses to recalibrate, a
    table (sorted by how far the offsets moved), per compass its flags, refused flights and
    plots of its offsets and motor term against the date."""
    if not fleet or not fleet.get("devices"):
        return ""
    esc = html.escape
    recal = (
        "".join(
            f"<li><b>{esc(r['device_id'])}</b>: {esc('; '.join(r['why']))}</li>"
            for r in fleet["recalibrate"]
        )
        or "<li>none</li>"
    )
    head = "".join(
        f"<th>{esc(h)}</th>"
        for h in (
            "compass",
            "flights fitted",
            "refused",
            "last offsets (uT)",
            "moved (uT)",
            "calibration in use off by (uT)",
            "flags",
        )
    )
    rows = []
    for d in fleet["devices"]:
        last = d["offset_ut"][-1] if d["offset_ut"] else [float("nan")] * 3
        err = d["calibration_error_ut"][-1] if d["calibration_error_ut"] else float("nan")
        anchor = "compass-" + d["device_id"]
        cells = (
            f"<a href='#{esc(anchor)}'>{esc(d['device_id'])}</a>",
            len(d["logs"]),
            len(d["refused"]),
            " ".join(f"{v:+.2f}" for v in last),
            f"{d['moved_ut']:.2f}",
            "unknown" if err is None or not np.isfinite(err) else f"{err:.2f}",
            len(d["flags"]),
        )
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    sections = []
    for d in fleet["devices"]:
        flags = "".join(f"<li>{esc(f['why'])}</li>" for f in d["flags"]) or "<li>no flag</li>"
        refused = "".join(
            f"<li>refused: {esc(r['log'])}: {esc(r['why'])}</li>" for r in d["refused"]
        )
        sections.append(
            f"<section id='{esc('compass-' + d['device_id'])}'><h3>compass {esc(d['device_id'])}"
            f"</h3><ul>{flags}{refused}</ul>" + "".join(_plots(d)) + "</section>"
        )
    return (
        "<h2>Compass</h2><p>Each flight log's in-flight compass fit (the mag_inflight stage's, "
        "against the World Magnetic Model): the offsets the flight says the vehicle should use, "
        f"per flight with +-2 standard errors. Flags: k = {fleet['k']:g} robust sigmas.</p>"
        f"<h3>Recalibrate</h3><ul>{recal}</ul>"
        f"<table><tr>{head}</tr>{''.join(rows)}</table>" + "".join(sections)
    )


def write_compass(out: Any, out_dir: Path, tasks: list[Any], k: float) -> dict[str, Any] | None:
    """Join the compass parts of ``tasks`` (in order) into ``DIR/compass.parquet`` and write
    the compass fleet view ``DIR/compass.json`` through ``out`` (the driver's staged outputs);
    returns the fleet view, None when no log had a compass part."""
    table = join_compass(
        [compass_part(Path(t.part)) for t in tasks],
        {"imupipe_survey_compass": json.dumps({"schema_version": 1, "k": k})},
    )
    if table is None:
        return None
    import pyarrow.parquet as pq

    pq.write_table(table, out.path(Path(out_dir) / COMPASS_NAME), compression="zstd")
    fleet = compass_fleet(table, k)
    out.write_text(
        Path(out_dir) / COMPASS_FLEET_NAME, json.dumps(fleet, indent=2, default=float) + "\n"
    )
    return fleet
