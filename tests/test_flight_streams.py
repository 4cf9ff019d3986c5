"""Flight streams (attitude, position, current) of the common table, read from real DataFlash
and ULog flight logs and compared value for value with pymavlink's DFReader and pyulog."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink import DFReader

from imupipe.readers.dataflash.reader import euler_quaternion, read_dataflash
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import (
    counts,
    flight_stream,
    has_flight_stream,
    make_table,
    sensor,
    with_flight_stream,
    with_flight_streams,
)
from imupipe.readers.ulog.reader import read_ulog

from conftest import shared_path

FLIGHTS = {
    "erle_pxf_118/118.BIN": None,
    "erle_pxf_218/218.BIN": None,
    "forum13645_ac344/log_0036.bin": "MAG",
    "spark404_utrecht/log.bin": "MAG",
}


def _dfreader(path, names):
    """Every record of ``names`` as DFReader decodes it (its own scaling), in file order."""
    f = DFReader.DFReader_binary(str(path), zero_time_base=True)
    out: dict[str, list] = {n: [] for n in names}
    while True:
        m = f.recv_match(type=list(names))
        if m is None:
            return out
        out[m.get_type()].append(m.to_dict())


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Body -> NED: v' = q v q*, per row."""
    w, u = q[:, :1], q[:, 1:]
    return v + 2 * np.cross(u, np.cross(u, v) + w * v)


@pytest.mark.parametrize("name", sorted(FLIGHTS))
def test_dataflash_flight_streams_match_dfreader(name):
    path = shared_path("logs", "ardupilot_flights", *name.split("/"))
    table, _ = read_dataflash(
        InputSpec(path=path, imu_topic=FLIGHTS[name] and "IMU", mag_topic=FLIGHTS[name])
    )
    ref = _dfreader(path, ("ATT", "GPS", "BAT", "CURR"))
    att = flight_stream(table, "attitude")
    rec = [r for r in ref["ATT"] if r.get("I", 0) == 0]
    assert len(att) == len(rec) > 100
    roll, pitch, yaw = (np.radians([r[c] for r in rec]) for c in ("Roll", "Pitch", "Yaw"))
    tkey = "TimeUS" if "TimeUS" in rec[0] else "TimeMS"
    scale = 1000 if tkey == "TimeUS" else 1_000_000
    want_t = np.array([r[tkey] for r in rec], dtype=np.int64) * scale
    order = np.argsort(want_t, kind="stable")
    assert np.array_equal(att.t_ns, want_t[order])
    q = att.values
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    # the quaternion's body x axis (forward) points along yaw/pitch as the Euler angles say
    fwd = _rotate(q, np.tile([1.0, 0.0, 0.0], (len(q), 1)))
    exp = np.column_stack(
        [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)]
    )[order]
    assert np.allclose(fwd, exp, atol=1e-9)
    right = _rotate(q, np.tile([0.0, 1.0, 0.0], (len(q), 1)))
    assert np.allclose(right[:, 2], (np.sin(roll) * np.cos(pitch))[order], atol=1e-9)
    gps = [r for r in ref["GPS"] if r.get("I", 0) == 0 and r["Status"] >= 3]
    if gps:
        pos = flight_stream(table, "position")
        lla = np.array([[r["Lat"], r["Lng"], r["Alt"]] for r in gps])
        assert np.allclose(np.sort(pos.values, axis=0), np.sort(lla, axis=0), rtol=0, atol=1e-9)
    source = "BAT" if ref["BAT"] else "CURR"
    if ref[source]:
        cur = flight_stream(table, "current")
        amps = np.array([r["Curr"] for r in ref[source] if r.get("Inst", 0) == 0], dtype=float)
        if isinstance(ref[source][0]["Curr"], int):
            amps = amps / 100  # centiamperes of the old int16 field
        assert np.allclose(np.sort(cur.values[:, 0]), np.sort(amps), atol=1e-6)
    # the sensors' streams are unchanged by the flight rows
    assert counts(table)["mag"] == len(sensor(table, "mag"))


def test_ulog_attitude_matches_pyulog():
    from pyulog import ULog

    path = shared_path("logs", "px4_ulog", "sample.ulg")
    table, _ = read_ulog(InputSpec(path=path, time="log"))
    ref = ULog(str(path), ["vehicle_attitude"]).get_dataset("vehicle_attitude").data
    att = flight_stream(table, "attitude")
    q = np.column_stack([ref[f"q[{i}]"] for i in range(4)]).astype(float)
    assert np.array_equal(att.t_ns, ref["timestamp"].astype(np.int64) * 1000)
    assert np.array_equal(att.values, q)


def test_with_flight_stream_keeps_sensors_and_order():
    t = np.arange(0, 10, dtype=np.int64) * 10
    table = make_table(t, mag=np.ones((10, 3)))
    out = with_flight_stream(table, "current", np.array([5, 15, 200]), np.array([1.0, 2.0, 3.0]))
    assert len(out) == 13 and np.all(np.diff(out.column("t_ns").to_numpy()) >= 0)
    assert has_flight_stream(out, "current") and not has_flight_stream(out, "attitude")
    assert np.array_equal(flight_stream(out, "current").values[:, 0], [1.0, 2.0, 3.0])
    assert np.array_equal(sensor(out, "mag").t_ns, t)
    assert counts(out) == {"mag": 10}


def test_flight_streams_at_once_are_the_streams_one_by_one():
    """One merge of several streams gives the table of adding them one by one (issue 39: the
    table is sorted once): rows at equal stamps in the table's, then the streams' order, the
    new columns in the order given, unsorted stamps sorted in."""
    t = np.arange(0, 10, dtype=np.int64) * 10
    table = make_table(t, mag=np.ones((10, 3)))
    streams = {
        "current": (np.array([5, 20, 200]), np.array([1.0, 2.0, 3.0])),
        "attitude": (np.array([20, 3, 20]), np.arange(12.0).reshape(3, 4)),
        "throttle": (np.array([], dtype=np.int64), np.array([])),
        "position": (np.array([90, 20]), np.arange(6.0).reshape(2, 3)),
    }
    one_by_one = table
    for stream, (t_ns, values) in streams.items():
        one_by_one = with_flight_stream(one_by_one, stream, t_ns, values)
    at_once = with_flight_streams(table, streams)
    assert at_once.column_names == one_by_one.column_names
    assert at_once.schema.equals(one_by_one.schema, check_metadata=True)
    for name in at_once.column_names:
        assert at_once.column(name).to_pylist() == one_by_one.column(name).to_pylist(), name
    assert len(at_once) == 10 + 3 + 3 + 2 and not has_flight_stream(at_once, "throttle")


def test_euler_quaternion_identity_and_yaw():
    q = euler_quaternion(np.zeros(2), np.zeros(2), np.array([0.0, np.pi / 2]))
    assert np.allclose(q, [[1, 0, 0, 0], [np.sqrt(0.5), 0, 0, np.sqrt(0.5)]])


def test_ulog_position_and_current_match_pyulog():
    from pyulog import ULog

    path = shared_path("logs", "px4_ulog", "sample_log_small.ulg")
    table, _ = read_ulog(InputSpec(path=path, time="log"))
    ref = ULog(str(path), ["vehicle_gps_position", "battery_status"])
    gps = next(d for d in ref.data_list if d.name == "vehicle_gps_position").data
    keep = gps["fix_type"] >= 3
    pos = flight_stream(table, "position")
    want = np.column_stack([gps["lat"] * 1e-7, gps["lon"] * 1e-7, gps["alt"] * 1e-3])[keep]
    assert len(pos) == int(keep.sum()) > 10
    assert np.allclose(pos.values, want, rtol=0, atol=1e-12)
    assert np.array_equal(pos.t_ns, gps["timestamp"][keep].astype(np.int64) * 1000)
    bat = next(d for d in ref.data_list if d.name == "battery_status" and d.multi_id == 0).data
    ok = bat["current_a"] >= 0
    cur = flight_stream(table, "current")
    assert np.array_equal(cur.values[:, 0], bat["current_a"][ok].astype(float))


@pytest.mark.parametrize("name", sorted(FLIGHTS))
def test_dataflash_throttle_is_the_copters_ctun_thrust_out(name):
    """The throttle flight stream is CTUN.ThO (0..1, 4.x float) or ThrOut / 1000 (3.2-3.3
    int16), record for record as DFReader decodes it: what ArduCopter hands its compass."""
    path = shared_path("logs", "ardupilot_flights", *name.split("/"))
    table, _ = read_dataflash(
        InputSpec(path=path, imu_topic=FLIGHTS[name] and "IMU", mag_topic=FLIGHTS[name])
    )
    rec = _dfreader(path, ("CTUN",))["CTUN"]
    column, scale = ("ThO", 1.0) if "ThO" in rec[0] else ("ThrOut", 1e-3)
    want = np.array([r[column] for r in rec], dtype=float) * scale
    thr = flight_stream(table, "throttle")
    assert len(thr) == len(rec) > 100
    assert np.allclose(np.sort(thr.values[:, 0]), np.sort(want), rtol=0, atol=1e-6)
    assert thr.values.min() >= 0.0 and thr.values.max() <= 1.0 and thr.values.max() > 0.1


def _armed_by_pyulog(log, t_us):
    """vehicle_control_mode.flag_armed (what VehicleMagnetometer reads) step-held onto ``t_us``
    as pyulog decodes it; disarmed before its first message."""
    mode = log.get_dataset("vehicle_control_mode").data
    i = np.searchsorted(mode["timestamp"], t_us, side="right") - 1
    return np.where(i >= 0, mode["flag_armed"][np.maximum(i, 0)] == 1, False)


def test_ulog_throttle_is_the_thrust_setpoint_norm_or_actuator_controls():
    """PX4's throttle-based compass compensation input (VehicleMagnetometer::
    UpdatePowerCompensation): |vehicle_thrust_setpoint.xyz| of instance 0 (v1.14+,
    tests/data/px4_ulog/pixhawk6c_bmi055.ulg) or actuator_controls_0 control[3] (older), and 0
    while disarmed (both logs hold setpoints above 0 while disarmed: those read 0)."""
    from pyulog import ULog

    from conftest import REPO

    new = REPO / "tests" / "data" / "px4_ulog" / "pixhawk6c_bmi055.ulg"
    table, _ = read_ulog(InputSpec(path=new, time="log"))
    log = ULog(str(new), ["vehicle_thrust_setpoint", "vehicle_control_mode"])
    ref = log.get_dataset("vehicle_thrust_setpoint").data
    xyz = np.column_stack([ref[f"xyz[{i}]"] for i in range(3)]).astype(float)
    armed = _armed_by_pyulog(log, ref["timestamp"])
    thr = flight_stream(table, "throttle")
    assert np.array_equal(thr.t_ns, ref["timestamp"].astype(np.int64) * 1000)
    norm = np.linalg.norm(xyz, axis=1)
    assert np.allclose(thr.values[:, 0], norm * armed) and thr.values.max() > 0.1
    assert ((norm > 0) & ~armed).sum() > 10  # the disarmed setpoints are there, and read 0
    old = shared_path("logs", "px4_ulog", "sample_log_small.ulg")
    table, _ = read_ulog(InputSpec(path=old, time="log"))
    log = ULog(str(old), ["actuator_controls_0", "vehicle_control_mode"])
    ref = log.get_dataset("actuator_controls_0").data
    armed = _armed_by_pyulog(log, ref["timestamp"])
    thr = flight_stream(table, "throttle")
    assert np.array_equal(thr.values[:, 0], np.where(armed, ref["control[3]"].astype(float), 0.0))
    assert thr.values.max() > 0.1 and ((ref["control[3]"] > 0) & ~armed).sum() > 10
