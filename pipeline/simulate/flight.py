"""Scenario ``flight``: a multicopter flight with a compass whose hard iron, soft iron and
motor interference are known, for the ``mag_inflight`` stage (written as DataFlash, ``.bin``).

- Attitude (body FRD -> NED): yaw turning ``yaw_turns`` full circles, roll and pitch
  sinusoids of amplitude ``roll_deg``/``pitch_deg`` (periods 17 s and 23 s), as a quaternion
  (``attitude`` flight stream, ``att_hz``).
- GPS track: a circle of ``radius_m`` about ``lat``, ``lon`` at ``alt_m`` (+-20 m), ``gps_hz``.
- Battery current (A): ``current_a`` mean, a 31 s sinusoid and a 13 s square wave of amplitudes
  ``current_swing_a`` and half of it; the ``BAT`` stream (``bat_hz``) logs it with 0.2 A noise
  (``current_sensor = false``: a vehicle without a current sensor, no ``BAT`` stream).
- Collective throttle (0..1): the throttle that draws that current, ``throttle_hover *
  (I / current_a)^(2/3)`` (a rotor's current grows as its throttle to the power 1.5, so the two
  are not proportional), logged as a copter's ``CTUN.ThO`` (``bat_hz``, exact: it is the value
  the firmware compensates with) when ``log_throttle`` is true or the interference follows the
  throttle.
- Compass (T, ``mag_hz``): the WMM field on ``year`` at the track (:mod:`imupipe.stages.magnetometer.wmm`)
  rotated into the body, distorted by the inverse of the correction
  ``corrected = M (raw - offset) + motor * P``: ``raw = M^-1 (B_body - motor P) + offset``,
  plus white noise ``mag_noise`` (T per axis); the DataFlash writer rounds it to milligauss.
  ``P`` is the current (``motor_source = "current"``, ``motor`` T/A) or the throttle
  (``motor_source = "throttle"``, ``motor_throttle`` T per unit of throttle).
- The vehicle's own compass calibration (``vehicle``: ArduPilot parameters, e.g.
  ``{"COMPASS_OFS_X": -120, "COMPASS_DIA_X": 1.02, "COMPASS_MOT_Z": 4.5, "COMPASS_MOTCT": 2}``;
  default none): applied to the logged field as ArduPilot's ``correct_field`` does
  (:func:`ardupilot_correct`) and written in the log's ``PARM``, so the log is what a calibrated
  vehicle records and an export must compose with it (DataFlash only: PX4 logs the raw field
  in ``sensor_mag``).

- A PX4 vehicle's mounting (``px4_parameters``, e.g. ``{"CAL_MAG0_ROT": 2}`` for an external
  compass turned 90 deg in yaw, or ``{"SENS_BOARD_ROT": 4, "SENS_BOARD_X_OFF": 1.5}`` with
  ``CAL_MAG0_ROT = -1`` for an internal one; ULog only): the compass reads in its own axes,
  ``raw_sensor = R^T raw`` with ``R`` the rotation PX4 turns it by
  (:func:`imupipe.readers.ulog.rotation.mag_rotation`); the parameters, with ``CAL_MAG0_ID``
  the compass's device id, are written in the log (``sensor_mag.is_external`` set when
  ``CAL_MAG0_ROT >= 0``). The truth stays in the body axes.

As a ULog (:func:`flight_ulog`): ``sensor_mag`` (raw, gauss), ``vehicle_attitude`` (``q``),
``vehicle_gps_position`` (1e-7 deg, mm, ``time_utc_usec``, ``fix_type`` 3), ``battery_status``
(``current_a``, with its 0.2 A noise), ``vehicle_thrust_setpoint`` (``xyz = (0, 0, -throttle)``,
a multicopter's, whose norm PX4's throttle compensation uses).

Truth: ``matrix`` M, ``offset`` (T), ``motor`` (T per unit of ``motor_source``),
``motor_source``, ``field_norm`` (T): the raw sensor's errors (before the vehicle's own
correction).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.exports.ardupilot import MILLIGAUSS_PER_TESLA, compass_terms, motor_kind
from imupipe.pipeline.writers.ulog import Topic, UlogData
from imupipe.readers.dataflash.reader import euler_quaternion
from imupipe.readers.table import (
    flight_stream,
    has_flight_stream,
    make_table,
    metadata,
    sensor,
    with_flight_stream,
    with_metadata,
)
from imupipe.readers.ulog.rotation import mag_rotation
from imupipe.stages.magnetometer.inflight import rotate
from imupipe.stages.magnetometer.wmm import earth_field

WRITES = (".bin", ".ulg")
"""The flight is written as DataFlash or as a PX4 ULog (:func:`flight_ulog`)."""
GAUSS_PER_TESLA = 1e4
MAG_DEVICE_ID = 396825
"""The simulated compass's PX4 device id (an external I2C HMC5883 on bus 1, address 0x1e)."""
DEFAULTS: dict[str, Any] = {
    "duration_s": 240.0,
    "mag_hz": 50.0,
    "att_hz": 25.0,
    "gps_hz": 5.0,
    "bat_hz": 10.0,
    "year": 2024.5,
    "lat": 52.038,
    "lon": 5.145,
    "alt_m": 100.0,
    "radius_m": 200.0,
    "yaw_turns": 6.0,
    "roll_deg": 35.0,
    "pitch_deg": 30.0,
    "current_a": 12.0,
    "current_swing_a": 8.0,
    "offset": [1.2e-5, -8.0e-6, 2.0e-5],
    "matrix": [[1.04, 0.02, -0.015], [0.02, 0.97, 0.01], [-0.015, 0.01, 1.02]],
    "motor": [6.0e-8, -4.0e-8, 1.2e-7],
    "motor_source": "current",
    "motor_throttle": [1.6e-6, -1.1e-6, 3.2e-6],
    "throttle_hover": 0.45,
    "current_sensor": True,
    "log_throttle": False,
    "mag_noise": 1.5e-7,
    "vehicle": {},
    "px4_parameters": {},
}


def _motor_power(p: dict[str, Any], amps: np.ndarray, throttle: np.ndarray | None) -> np.ndarray:
    """What ArduPilot multiplies ``COMPASS_MOT`` by under ``p``: the current (``COMPASS_MOTCT =
    2``), the throttle 0..1 (``= 1``; zeros when none is given)."""
    if motor_kind(p) == 1:
        return np.zeros(len(amps)) if throttle is None else np.asarray(throttle, dtype=np.float64)
    return amps


def ardupilot_correct(
    raw: np.ndarray, p: dict[str, Any], amps: np.ndarray, throttle: np.ndarray | None = None
) -> np.ndarray:
    """What ArduPilot logs (T) for the raw field ``raw`` (n, 3, T, body axes) under its
    parameters ``p`` (first compass), battery current ``amps`` (A) and throttle (0..1):
    ``AP_Compass_Backend``'s ``correct_field``: offsets added, scale and ``DIA``/``ODI``
    applied, then ``MOT`` times the current (``COMPASS_MOTCT = 2``) or the throttle (``= 1``),
    all in milligauss."""
    ofs, w, mot = compass_terms(p)
    power = _motor_power(p, amps, throttle)
    mg = (raw * MILLIGAUSS_PER_TESLA + ofs) @ w.T + power[:, None] * mot
    return mg / MILLIGAUSS_PER_TESLA


def ardupilot_raw(
    logged: np.ndarray, p: dict[str, Any], amps: np.ndarray, throttle: np.ndarray | None = None
) -> np.ndarray:
    """The inverse of :func:`ardupilot_correct`: the raw field (T) under a log's ``MAG``."""
    ofs, w, mot = compass_terms(p)
    power = _motor_power(p, amps, throttle)
    mg = np.linalg.solve(w, (logged * MILLIGAUSS_PER_TESLA - power[:, None] * mot).T).T - ofs
    return mg / MILLIGAUSS_PER_TESLA


M_PER_DEG = 111_320.0
"""Metres per degree of latitude (spherical earth: enough for a 200 m track)."""


def _times(hz: float, duration_s: float) -> np.ndarray:
    return (1_000_000_000 + np.arange(int(duration_s * hz)) * (1e9 / hz)).astype(np.int64)


def _attitude(t_s: np.ndarray, p: dict[str, Any]) -> np.ndarray:
    yaw = 2 * np.pi * p["yaw_turns"] * t_s / p["duration_s"]
    roll = np.radians(p["roll_deg"]) * np.sin(2 * np.pi * t_s / 17.0)
    pitch = np.radians(p["pitch_deg"]) * np.sin(2 * np.pi * t_s / 23.0 + 1.0)
    return euler_quaternion(roll, pitch, np.mod(yaw + np.pi, 2 * np.pi) - np.pi)


def _position(t_s: np.ndarray, p: dict[str, Any]) -> np.ndarray:
    a = 2 * np.pi * t_s / 60.0
    lat = p["lat"] + p["radius_m"] * np.cos(a) / M_PER_DEG
    lon = p["lon"] + p["radius_m"] * np.sin(a) / (M_PER_DEG * np.cos(np.radians(p["lat"])))
    return np.column_stack([lat, lon, p["alt_m"] + 20.0 * np.sin(a / 3)])


def _current(t_s: np.ndarray, p: dict[str, Any]) -> np.ndarray:
    """The true current (A); the ``BAT`` stream logs it with 0.2 A noise."""
    swing = p["current_swing_a"]
    square = np.sign(np.sin(2 * np.pi * t_s / 13.0))
    amps = p["current_a"] + swing * np.sin(2 * np.pi * t_s / 31.0) + 0.5 * swing * square
    return np.maximum(amps, 0.0)


def _throttle(amps: np.ndarray, p: dict[str, Any]) -> np.ndarray:
    """The collective throttle (0..1) that draws ``amps`` (module docstring)."""
    ratio = np.maximum(amps, 0.0) / float(p["current_a"])
    return np.clip(float(p["throttle_hover"]) * ratio ** (2.0 / 3.0), 0.0, 1.0)


def simulate(params: dict[str, Any], rng: np.random.Generator) -> tuple[pa.Table, dict[str, Any]]:
    p = params
    dur = float(p["duration_s"])
    t_mag = _times(p["mag_hz"], dur)
    t_att, t_gps, t_bat = (_times(p[k], dur) for k in ("att_hz", "gps_hz", "bat_hz"))
    s = lambda t: (t - 1_000_000_000) * 1e-9  # noqa: E731
    m = np.asarray(p["matrix"], dtype=np.float64)
    offset = np.asarray(p["offset"], dtype=np.float64)
    source = p["motor_source"]
    if source not in ("current", "throttle"):
        raise ConfigError(f"simulate flight: motor_source '{source}' (use current or throttle)")
    motor = np.asarray(p["motor" if source == "current" else "motor_throttle"], dtype=np.float64)
    lla = _position(s(t_mag), p)
    ned = earth_field(lla[:, 0], lla[:, 1], lla[:, 2], float(p["year"]))
    body = rotate(_attitude(s(t_mag), p), ned, inverse=True)
    amps = _current(s(t_mag), p)
    thr = _throttle(amps, p)
    power = amps if source == "current" else thr
    raw = np.linalg.solve(m, (body - power[:, None] * motor).T).T + offset
    raw += rng.normal(0.0, p["mag_noise"], raw.shape)
    vehicle = {k: float(v) for k, v in (p["vehicle"] or {}).items()}
    logged_mag = ardupilot_correct(raw, vehicle, amps, thr) if vehicle else raw
    px4 = dict(p["px4_parameters"] or {})
    if px4 and vehicle:
        raise ConfigError("simulate flight: give either vehicle (ArduPilot) or px4_parameters")
    turn = None
    if px4:
        px4 = {"CAL_MAG0_ID": MAG_DEVICE_ID, "CAL_MAG0_ROT": -1} | px4
        try:
            turn = mag_rotation(px4, 0)[0]
        except ValueError as exc:
            raise ConfigError(f"simulate flight: px4_parameters: {exc}") from None
        logged_mag = raw @ turn  # the compass's own axes: R^T raw, per row
    table = make_table(t_mag, mag=logged_mag)
    table = with_flight_stream(table, "attitude", t_att, _attitude(s(t_att), p))
    table = with_flight_stream(table, "position", t_gps, _position(s(t_gps), p))
    logged = _current(s(t_bat), p) + rng.normal(0.0, 0.2, len(t_bat))
    if p["current_sensor"]:
        table = with_flight_stream(table, "current", t_bat, logged)
    if p["log_throttle"] or source == "throttle":
        table = with_flight_stream(table, "throttle", t_bat, _throttle(_current(s(t_bat), p), p))
    meta = metadata(table) | {"source": "simulate flight", "gps_year": float(p["year"])}
    if vehicle:
        meta["ardupilot"] = {"parameters": vehicle, "calibrated": {"mag": True}}
    if turn is not None:  # as the ULog reader gives it
        meta["px4"] = {
            "parameters": px4,
            "calibrated": {"mag": False},
            "rotation": {"mag": {"matrix": turn.tolist(), "parameters": mag_rotation(px4, 0)[1]}},
        }
        meta["device_id"] = {"mag": MAG_DEVICE_ID}
    truth = {
        "matrix": m.tolist(),
        "offset": offset.tolist(),
        "motor": motor.tolist(),
        "motor_source": source,
        "field_norm": float(np.mean(np.linalg.norm(ned, axis=1))),
    }
    return with_metadata(table, meta), truth


def flight_ulog(table: pa.Table) -> UlogData:
    """The simulated flight (:func:`simulate`'s table) as a PX4 ULog's topics (module
    docstring); ConfigError for a flight with an ArduPilot vehicle calibration."""
    meta = metadata(table)
    if meta.get("ardupilot"):
        raise ConfigError(
            "simulate flight: 'vehicle' is an ArduPilot calibration (written as .bin); PX4 "
            "logs the raw field: leave vehicle unset for .ulg"
        )
    px4 = (meta.get("px4") or {}).get("parameters") or {}
    external = float(px4.get("CAL_MAG0_ROT", 0)) >= 0
    us = lambda t_ns: np.asarray(t_ns, dtype=np.int64) // 1000  # noqa: E731
    mag = sensor(table, "mag")
    att = flight_stream(table, "attitude")
    pos = flight_stream(table, "position")
    t0_utc_us = (float(meta["gps_year"]) - 1970.0) * 365.2425 * 86400.0 * 1e6
    f32, u64 = "float", "uint64_t"
    topics = [
        Topic(
            "sensor_mag",
            0,
            {
                "timestamp": us(mag.t_ns),
                "timestamp_sample": us(mag.t_ns),
                "device_id": np.full(len(mag), MAG_DEVICE_ID),
                **{a: mag.values[:, i] * GAUSS_PER_TESLA for i, a in enumerate("xyz")},
                "temperature": np.full(len(mag), 25.0),
                "is_external": np.full(len(mag), float(external)),
            },
            [(u64, "timestamp"), (u64, "timestamp_sample"), ("uint32_t", "device_id")]
            + [(f32, a) for a in "xyz"]
            + [(f32, "temperature"), ("uint32_t", "error_count"), ("bool", "is_external")],
        ),
        Topic(
            "vehicle_attitude",
            0,
            {"timestamp": us(att.t_ns), "timestamp_sample": us(att.t_ns), "q": att.values},
            [(u64, "timestamp"), (u64, "timestamp_sample"), ("float[4]", "q")],
        ),
        Topic(
            "vehicle_gps_position",
            0,
            {
                "timestamp": us(pos.t_ns),
                "time_utc_usec": (t0_utc_us + (pos.t_ns - pos.t_ns[0]) / 1e3).astype(np.int64),
                "lat": np.rint(pos.values[:, 0] * 1e7),
                "lon": np.rint(pos.values[:, 1] * 1e7),
                "alt": np.rint(pos.values[:, 2] * 1e3),
                "fix_type": np.full(len(pos), 3),
                "satellites_used": np.full(len(pos), 12),
            },
            [(u64, "timestamp"), (u64, "time_utc_usec")]
            + [("int32_t", k) for k in ("lat", "lon", "alt")]
            + [("uint8_t", "fix_type"), ("uint8_t", "satellites_used")],
        ),
    ]
    if has_flight_stream(table, "current"):
        cur = flight_stream(table, "current")
        topics.append(
            Topic(
                "battery_status",
                0,
                {"timestamp": us(cur.t_ns), "current_a": cur.values[:, 0]},
                [(u64, "timestamp"), (f32, "current_a")],
            )
        )
    if has_flight_stream(table, "throttle"):
        thr = flight_stream(table, "throttle")
        zero = np.zeros(len(thr))
        topics.append(
            Topic(
                "vehicle_thrust_setpoint",
                0,
                {
                    "timestamp": us(thr.t_ns),
                    "timestamp_sample": us(thr.t_ns),
                    "xyz": np.column_stack([zero, zero, -thr.values[:, 0]]),
                },
                [(u64, "timestamp"), (u64, "timestamp_sample"), ("float[3]", "xyz")],
            )
        )
    return UlogData(topics, dict(px4), {"sys_name": "PX4", "ver_hw": "SITL"})
