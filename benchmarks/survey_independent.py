"""``imupipe survey`` on fleets it was not designed for (issue #36): an independent generator.

This generator shares no code with ``imupipe simulate`` (its own motion, sensor and fleet model,
written from the issue's description) so that the survey's rules are not tuned to the project's
own simulator. A fleet (:func:`make_fleet`): 6-8 vehicles x 8 logs over five weeks; each vehicle
one IMU at 100-400 Hz; a log alternates still periods of 20-120 s with 1-3 min of motion
(rotation, and on flights vibration of the airframe: a rotor line and broadband shaking, a
constant-rate yaw turn at times, which keeps the windowed variance low); the sensor is a MEMS
model:

- white noise (gyro 1.5-4e-4 rad/s/sqrt(Hz), accel 1-2.5e-3 m/s^2/sqrt(Hz));
- in-log bias instability: a first-order Gauss-Markov process (time constant 300 s, gyro
  0.03 mrad/s, accel 0.2 mg);
- turn-on bias: a device's base bias (gyro 5 mrad/s, accel 30 mg per axis) plus a per-log
  repeatability (gyro 0.05 mrad/s, accel 0.3 mg) and a slow random walk over days;
- a thermal slope (gyro 0.01 mrad/s/K per axis) and a per-log temperature (ambient 5-35 degC
  and a warm-up of 3-8 K with a 200 s time constant);
- an accelerometer scale error per axis (0.3 % standard deviation);
- a first-order low-pass at a quarter of the rate (the sensor's digital filter), then
  quantisation (gyro 1/16.4 deg/s... 61 urad/s LSB; accel 2.4e-3 m/s^2 LSB).

Per fleet: one log in motion throughout (a flight logged from arming), one vehicle with a second,
1 Hz gyro topic (a decimated ``sensor_gyro_1``), one truncated log (cut inside a still period),
one vehicle whose temperature is not logged, and two vehicles set down on any of their six
faces when still (a handheld rig; the others rest level, a few degrees off). Plants (issue #36's table), each on its own
vehicle: ``drift`` (gyro z 0.3 mrad/s per week), ``crash`` (a 2 mrad/s gyro x step inside a
log that goes on after it), ``step`` (the same between two logs), ``noise`` (both noise
densities x2.5 from a log on), ``accel_z`` (+30 mg on accel z from a log on), ``thermal`` (gyro
bias following temperature at 0.05 mrad/s/K: not a fault, nothing to flag), ``accel_x`` (+30
mg on accel x from a log on, on a vehicle set down on its faces; judged only where some log of
it lay on both x faces, which parts the x offset from the x scale). A planted fleet has at least
one vehicle per plant and one more.

:func:`truncated_check` writes a log as an MCAP with the ``mcap`` library's ROS 2 writer, cuts
the file (a recording stopped part-way) and surveys it from the file with and without
``--read-truncated``, against what the ``mcap`` library recovers.

:func:`survey_fleet` runs each log's IMU through the survey's own detector and figures and the
fleet view, in memory (as ``benchmarks/survey_false_flags.py``). ``main`` prints the false-alarm
rate over clean fleets, the detection of each plant and the bias errors in stated standard
errors. Usage: ``python benchmarks/survey_independent.py [--clean 20] [--planted 6]``.
"""

from __future__ import annotations

import argparse
import collections
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

G0 = 9.80665
DAY_NS = 86_400 * 10**9
T0_NS = 1_780_000_000 * 10**9
PLANTS = ("drift", "crash", "step", "noise", "accel_z", "thermal", "accel_x")


@dataclass
class Stream:
    """One IMU topic of one log: samples and the truth of its still periods."""

    topic: str
    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    temperature: tuple[np.ndarray, np.ndarray] | None
    still: list[tuple[int, int, np.ndarray, np.ndarray]] = field(default_factory=list)
    """(start_ns, stop_ns, true mean gyro bias (3,), true mean accel bias (3,)) per still period."""
    up: list[np.ndarray] = field(default_factory=list)
    """The true direction of gravity's reaction (body frame, unit) in each still period."""


@dataclass
class Log:
    vehicle: str
    name: str
    streams: list[Stream]


@dataclass
class Device:
    rate: float
    gyro_n: float
    accel_n: float
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    gyro_thermal: np.ndarray
    temperature_logged: bool = True
    poses: bool = False
    """Set down on any of its faces when still (a handheld rig), not resting level."""
    accel_scale: np.ndarray = field(default_factory=lambda: np.zeros(3))


def _gauss_markov(rng: np.random.Generator, n: int, dt: float, tau: float, sd: float) -> np.ndarray:
    """(n, 3) first-order Gauss-Markov process, stationary with standard deviation ``sd``
    (computed on a 1 s grid and held: its time constant is minutes)."""
    from scipy.signal import lfilter

    per = max(int(round(1.0 / dt)), 1)
    m = n // per + 1
    a = np.exp(-1.0 / tau)
    w = rng.normal(0.0, sd * np.sqrt(1 - a * a), (m, 3))
    w[0] = rng.normal(0.0, sd, 3)
    return np.repeat(lfilter([1.0], [1.0, -a], w, axis=0), per, axis=0)[:n]


def _segments(rng: np.random.Generator, moving_throughout: bool) -> list[tuple[str, float]]:
    """(kind, seconds): still periods of 20-120 s between 1-3 min of motion."""
    if moving_throughout:
        return [("flight", rng.uniform(300, 480))]
    out: list[tuple[str, float]] = []
    for _ in range(int(rng.integers(2, 4))):
        out.append(("still", rng.uniform(20, 120)))
        out.append(("flight" if rng.random() < 0.5 else "handle", rng.uniform(60, 180)))
    out.append(("still", rng.uniform(20, 60)))
    return out


def _motion(
    rng: np.random.Generator, kind: str, n: int, rate: float
) -> tuple[np.ndarray, np.ndarray]:
    """(true rate (n,3) rad/s, specific force (n,3) m/s^2) of a motion segment."""
    t = np.arange(n) / rate
    w = np.zeros((n, 3))
    tilt = np.zeros((n, 2))
    for ax in range(3):
        for _ in range(3):
            f, amp = rng.uniform(0.05, 0.6), rng.uniform(0.05, 0.4)
            w[:, ax] += amp * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    for ax in range(2):
        tilt[:, ax] = rng.uniform(0.02, 0.2) * np.sin(
            2 * np.pi * rng.uniform(0.05, 0.3) * t + rng.uniform(0, 6.3)
        )
    f = np.column_stack(
        [
            -G0 * np.sin(tilt[:, 1]),
            G0 * np.sin(tilt[:, 0]) * np.cos(tilt[:, 1]),
            G0 * np.cos(tilt[:, 0]) * np.cos(tilt[:, 1]),
        ]
    )
    if kind == "flight":  # slow attitude, constant-rate turns, airframe vibration
        w *= 0.15
        turns = np.repeat(rng.uniform(-0.4, 0.4, n // int(20 * rate) + 1), int(20 * rate))[:n]
        w[:, 2] += turns * (rng.random(len(turns)) < 2)  # yaw held at a rate for 20 s
        throttle = 0.6 + 0.4 * np.sin(2 * np.pi * rng.uniform(0.005, 0.03) * t) ** 2
        rotor = rng.uniform(0.3, 0.45) * rate  # aliased rotor line
        vib_g = rng.uniform(0.01, 0.08)
        vib_a = rng.uniform(0.5, 3.0)
        line = np.sin(2 * np.pi * rotor * t)[:, None] * rng.normal(0, 1, 3)[None, :]
        w += throttle[:, None] * vib_g * (0.7 * line + 0.3 * rng.normal(0, 1, (n, 3)))
        f += throttle[:, None] * vib_a * (0.7 * line + 0.3 * rng.normal(0, 1, (n, 3)))
    else:  # carried by hand
        f += rng.normal(0, 0.3, (n, 3)) * 0.2 + 0.5 * np.sin(2 * np.pi * 0.7 * t)[:, None]
    return w, f


def _log(
    rng: np.random.Generator,
    dev: Device,
    start_ns: int,
    ambient: float,
    moving_throughout: bool,
    turn_on: tuple[np.ndarray, np.ndarray],
    plant: dict[str, Any],
    topic: str = "/imu/data",
    cut: bool = False,
) -> Stream:
    from scipy.signal import lfilter

    rate = dev.rate
    dt = 1.0 / rate
    segs = _segments(rng, moving_throughout)
    n_seg = [int(s * rate) for _, s in segs]
    n = sum(n_seg)
    w = np.zeros((n, 3))
    f = np.zeros((n, 3))
    edges = np.r_[0, np.cumsum(n_seg)]
    still_idx = []
    for (kind, _), i0, i1 in zip(segs, edges[:-1], edges[1:], strict=True):
        if kind == "still" and dev.poses:  # set down on any of its six faces
            up = np.eye(3)[rng.integers(3)] * rng.choice([-1.0, 1.0]) + rng.normal(0, 0.05, 3)
            f[i0:i1] = G0 * up / np.linalg.norm(up)
            still_idx.append((i0, i1))
        elif kind == "still":
            # resting on the ground: a few degrees off level, Earth rate ignored
            tilt = rng.normal(0, 0.03, 2)
            f[i0:i1] = [
                -G0 * np.sin(tilt[1]),
                G0 * np.sin(tilt[0]) * np.cos(tilt[1]),
                G0 * np.cos(tilt[0]) * np.cos(tilt[1]),
            ]
            still_idx.append((i0, i1))
        else:
            w[i0:i1], f[i0:i1] = _motion(rng, kind, i1 - i0, rate)
    t = np.arange(n) * dt
    temp = ambient + rng.uniform(3, 8) * (1 - np.exp(-t / 200.0))
    gbias = (
        dev.gyro_bias
        + turn_on[0]
        + dev.gyro_thermal * (temp[:, None] - 25.0)
        + _gauss_markov(rng, n, dt, 300.0, 3e-5)
    )
    abias = dev.accel_bias + turn_on[1] + _gauss_markov(rng, n, dt, 300.0, 2e-3)
    if "crash_at" in plant:  # a step inside the log, in the middle of a motion segment
        moving = [
            (i0, i1)
            for (kind, _), i0, i1 in zip(segs, edges[:-1], edges[1:], strict=True)
            if kind != "still"
        ]
        i0, i1 = moving[min(int(plant["crash_at"] * len(moving)), len(moving) - 1)]
        k = (i0 + i1) // 2
        plant["crash_index"] = k
        gbias[k:, 0] += 2e-3
    scale = plant.get("noise_scale", 1.0)
    gyro = w + gbias + rng.normal(0, dev.gyro_n * scale * np.sqrt(rate), (n, 3))
    accel = (
        f * (1 + dev.accel_scale)
        + abias
        + rng.normal(0, dev.accel_n * scale * np.sqrt(rate), (n, 3))
    )
    a = np.exp(-2 * np.pi * (rate / 4) * dt)  # the sensor's low-pass at rate / 4
    gyro = lfilter([1 - a], [1, -a], gyro, axis=0, zi=(gyro[0] * a)[None, :])[0]
    accel = lfilter([1 - a], [1, -a], accel, axis=0, zi=(accel[0] * a)[None, :])[0]
    gyro = np.round(gyro / 6.1e-5) * 6.1e-5
    accel = np.round(accel / 2.4e-3) * 2.4e-3
    t_ns = start_ns + (t * 1e9).astype(np.int64)
    if cut:  # truncated inside its second still period (or at 60 %)
        stop = (still_idx[1][0] + still_idx[1][1]) // 2 if len(still_idx) > 1 else int(0.6 * n)
        t_ns, gyro, accel, temp = t_ns[:stop], gyro[:stop], accel[:stop], temp[:stop]
        still_idx = [(i0, min(i1, stop)) for i0, i1 in still_idx if i0 < stop]
    s = Stream(
        topic,
        t_ns,
        gyro,
        accel,
        (t_ns[:: int(rate)], np.round(temp[:: int(rate)], 2)) if dev.temperature_logged else None,
    )
    for i0, i1 in still_idx:
        s.up.append(f[i0] / np.linalg.norm(f[i0]))
        s.still.append(
            (int(t_ns[i0]), int(t_ns[i1 - 1]), gbias[i0:i1].mean(axis=0), abias[i0:i1].mean(axis=0))
        )
    return s


def make_fleet(seed: int, plants: tuple[str, ...] = ()) -> tuple[list[Log], list[dict[str, Any]]]:
    """One fleet (see the module docstring) and its planted events (device, kind, figure, log,
    and for an in-log step its time)."""
    rng = np.random.default_rng(seed)
    n_veh = max(int(rng.integers(6, 9)), len(plants) + 1)
    logs: list[Log] = []
    events: list[dict[str, Any]] = []
    flight_veh, lowrate_veh, cut_veh, notemp_veh, *posed = rng.choice(n_veh, 6, replace=False)
    # accel_x on a vehicle set down on its faces (a level one sees its x offset only through
    # its lean); the others on vehicles that log their temperature (the thermal plant needs it)
    planted = {posed[0]: "accel_x"} if "accel_x" in plants else {}
    hosts = [v for v in rng.permutation(n_veh) if v != notemp_veh and v not in planted]
    others = [p for p in plants if p != "accel_x"]
    planted.update(zip(hosts[: len(others)], others, strict=True))
    for v in range(n_veh):
        name = f"veh{v:02d}"
        dev = Device(
            float(rng.choice([100.0, 200.0, 250.0, 400.0])),
            rng.uniform(1.5e-4, 4e-4),
            rng.uniform(1e-3, 2.5e-3),
            rng.normal(0, 5e-3, 3),
            rng.normal(0, 0.3, 3),
            rng.normal(0, 1e-5, 3),
            temperature_logged=v != notemp_veh,
            poses=v in posed,
            accel_scale=rng.normal(0, 3e-3, 3),
        )
        plant = planted.get(v)
        if plant == "thermal":
            dev.gyro_thermal = dev.gyro_thermal + np.array([0.0, 0.0, 5e-5])
        days = np.sort(np.r_[rng.uniform(0, 1), rng.uniform(1, 34, 6), rng.uniform(34, 35)])
        walk_g = np.cumsum(
            rng.normal(0, 2e-5, (8, 3)) * np.sqrt(np.diff(np.r_[0, days]))[:, None], 0
        )
        j_plant = int(rng.integers(3, 6))
        flight_log = int(rng.integers(1, 7)) if v == flight_veh else -1
        cut_log = int(rng.integers(0, 8)) if v == cut_veh else -1
        both_x = False
        for j in range(8):
            start = T0_NS + int(days[j] * DAY_NS) + int(rng.uniform(8, 10) * 3600e9)
            g_on = rng.normal(0, 5e-5, 3) + walk_g[j]
            a_on = rng.normal(0, 3e-3, 3)
            p: dict[str, Any] = {}
            if plant == "drift":
                g_on = g_on + np.array([0, 0, 0.3e-3 / 7 * days[j]])
            if plant == "step" and j >= j_plant:
                g_on = g_on + np.array([2e-3, 0, 0])
            if plant == "accel_z" and j >= j_plant:
                a_on = a_on + np.array([0, 0, 0.03 * G0])
            if plant == "accel_x" and j >= j_plant:
                a_on = a_on + np.array([0.03 * G0, 0, 0])
            if plant == "noise" and j >= j_plant:
                p["noise_scale"] = 2.5
            if plant == "crash" and j == j_plant:
                p["crash_at"] = rng.uniform(0.35, 0.65)
            if plant == "crash" and j > j_plant:
                g_on = g_on + np.array([2e-3, 0, 0])
            ambient = rng.uniform(5, 35)
            log = f"{name}/log_{j:02d}"
            stream = _log(
                rng,
                dev,
                start,
                ambient,
                j == flight_log and not (plant and j == j_plant),
                (g_on, a_on),
                p,
                cut=j == cut_log and "crash_at" not in p,
            )
            streams = [stream]
            if v == lowrate_veh:  # a decimated 1 Hz copy of the gyro (PX4 sensor_gyro_1)
                step = int(dev.rate)
                streams.append(
                    Stream(
                        "/imu1/data",
                        stream.t_ns[::step],
                        stream.gyro[::step],
                        stream.accel[::step],
                        None,
                    )
                )
            logs.append(Log(name, log, streams))
            if plant and j == j_plant and plant not in ("thermal", "drift"):
                ev: dict[str, Any] = {"device_id": f"{name}:/imu/data", "kind": plant, "log": log}
                if plant == "crash":
                    ev["t_ns"] = int(stream.t_ns[p["crash_index"]])
                events.append(ev)
            ups = [u[0] for u in stream.up]  # x's offset apart from its scale: both x faces
            both_x = both_x or (any(u > 0.9 for u in ups) and any(u < -0.9 for u in ups))
            if plant == "drift" and j == 0:
                events.append({"device_id": f"{name}:/imu/data", "kind": "drift", "log": log})
            if plant == "thermal" and j == 0:
                events.append({"device_id": f"{name}:/imu/data", "kind": "thermal", "log": log})
        if plant == "accel_x":  # judged only where a log lay on both x faces
            next(e for e in events if e["kind"] == "accel_x")["observable"] = both_x
    return logs, events


IMU_MSGDEF = """std_msgs/Header header
geometry_msgs/Quaternion orientation
float64[9] orientation_covariance
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
"""
"""``sensor_msgs/msg/Imu`` (ROS 2 Humble) with its dependencies, as ``ros2 bag`` writes it."""


def write_mcap(stream: Stream, path: Path, chunk_size: int = 256 * 1024) -> None:
    """``stream`` as a ROS 2 MCAP written by the ``mcap`` library's own ROS 2 writer
    (``mcap_ros2.writer``, not imupipe's), one ``sensor_msgs/msg/Imu`` per sample."""
    from mcap_ros2.writer import Writer

    with open(path, "wb") as fh:
        writer = Writer(fh, chunk_size=chunk_size)
        schema = writer.register_msgdef("sensor_msgs/msg/Imu", IMU_MSGDEF)
        zero9 = [0.0] * 9
        rows = zip(stream.t_ns.tolist(), stream.gyro.tolist(), stream.accel.tolist(), strict=True)
        for t, w, a in rows:
            msg = {
                "header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "imu"},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                "orientation_covariance": [-1.0] + zero9[1:],
                "angular_velocity": dict(zip("xyz", w, strict=True)),
                "angular_velocity_covariance": zero9,
                "linear_acceleration": dict(zip("xyz", a, strict=True)),
                "linear_acceleration_covariance": zero9,
            }
            writer.write_message(stream.topic, schema, msg, log_time=t, publish_time=t)
        writer.finish()


def recovered(path: Path) -> int:
    """Messages the ``mcap`` library's ``StreamReader`` reads from a cut MCAP before the record
    that runs past the end (what a tool can recover; imupipe's reader is not asked)."""
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    n = 0
    with open(path, "rb") as fh:
        try:
            for record in StreamReader(fh).records:
                n += isinstance(record, Message)
        except Exception:  # noqa: BLE001 - the damaged record: the stream ends there
            pass
    return n


def truncated_check(folder: Path, seed: int = 0, keep: float = 0.7) -> dict[str, Any]:
    """A log cut off part-way through writing (its MCAP file's first ``keep`` of its bytes:
    no summary, the last chunk broken) surveyed from the file by ``imupipe survey`` without
    and with ``--read-truncated``. Returns the samples written and recovered (by the ``mcap``
    library), whether the plain survey failed it, the still periods surveyed from the cut file
    and those the survey's own code finds in memory on the recovered samples (equal when the
    cut log is read up to its cut), the true still periods before the cut."""
    from imupipe.pipeline.survey.scan import survey
    from imupipe.stages.survey.stats import StillOptions, period_stats, still_periods

    rng = np.random.default_rng(seed)
    dev = Device(100.0, 2e-4, 1.5e-3, rng.normal(0, 5e-3, 3), rng.normal(0, 0.3, 3), np.zeros(3))
    stream = _log(rng, dev, T0_NS, 20.0, False, (np.zeros(3), np.zeros(3)), {})
    stop = int(np.searchsorted(stream.t_ns, stream.still[1][1])) + 2000  # two still periods
    stream.t_ns, stream.gyro, stream.accel = (
        stream.t_ns[:stop],
        stream.gyro[:stop],
        stream.accel[:stop],
    )
    stream.still = [p for p in stream.still if p[1] <= stream.t_ns[-1]]
    logs = folder / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    full = folder / "full.mcap"
    write_mcap(stream, full)
    data = full.read_bytes()
    cut = logs / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * keep)])
    n = recovered(cut)
    plain = survey([logs], folder / "plain", jobs=1, quiet=True, rerun=False)
    read = survey([logs], folder / "cut", jobs=1, quiet=True, rerun=False, read_truncated=True)
    import pyarrow.parquet as pq

    rows = pq.read_table(folder / "cut" / "survey.parquet").to_pylist()
    opts = StillOptions()
    t, g, a = stream.t_ns[:n], stream.gyro[:n], stream.accel[:n]
    memory = period_stats(t, g, a, still_periods(t, g, a, opts), opts, None)
    return {
        "samples": len(stream.t_ns),
        "recovered": n,
        "plain_failed": len(plain["failed"]),
        "read_failed": len(read["failed"]),
        "file": [(r["start_ns"], r["stop_ns"], r["gyro_bias_x"]) for r in rows if r["samples"]],
        "memory": list(
            zip(
                memory["start_ns"].tolist(),
                memory["stop_ns"].tolist(),
                memory["gyro_bias"][:, 0].tolist(),
                strict=True,
            )
        ),
        "true_before_cut": sum(b <= stream.t_ns[n - 1] for _, b, _, _ in stream.still),
    }


def survey_fleet(logs: list[Log], k: float = 5.0) -> tuple[Any, dict[str, Any]]:
    """The survey dataset and fleet view of ``logs``, in memory (the survey's own per-log code:
    :func:`~imupipe.stages.survey.stats.still_periods` and
    :func:`~imupipe.stages.survey.stats.period_stats`, as a worker runs a log held whole)."""
    import pyarrow as pa

    from imupipe.pipeline.survey.report import fleet_view, still_column
    from imupipe.pipeline.survey.scan import SurveyTask, _rows
    from imupipe.stages.survey.stats import StillOptions, period_stats, still_periods

    opts = StillOptions()
    parts = []
    for log in logs:
        task = SurveyTask(Path(log.name), log.name, log.vehicle, Path("-"), None, None, {}, "")
        for i, s in enumerate(log.streams):
            found = still_periods(s.t_ns, s.gyro, s.accel, opts)
            stats = period_stats(s.t_ns, s.gyro, s.accel, found, opts, s.temperature)
            m = len(stats["start_ns"])
            parts.append(_rows(task, s.topic, i, None, stats, None, m))
    table = pa.concat_tables(parts)
    view = fleet_view(table, k)
    return still_column(table, view), view


def caught(event: dict[str, Any], flags: list[dict[str, Any]]) -> bool:
    """The plant flagged with the right kind, figure and log (and time, for an in-log step:
    within 3 min: the step lies between two still periods); a step between logs may be named
    between the last log before the plant that has the figure and the first from it that has
    it (:func:`_bracketed`)."""
    got = [(f["kind"], f["figure"], f["log"]) for f in flags]
    kind, log = event["kind"], event["log"]
    if kind == "drift":
        return any(f[0] == "drift" and f[1] == "gyro_bias_z" for f in got)
    if kind == "crash":
        return any(
            f["kind"] == "step"
            and f["figure"] == "gyro_bias_x"
            and f["log"] == log
            and f.get("t_ns") is not None
            and abs(f["t_ns"] - event["t_ns"]) < 200e9
            for f in flags
        )
    if kind == "step":
        return any(_bracketed(f, "gyro_bias_x", log) for f in flags)
    if kind == "noise":
        return ("noise", "gyro_noise", log) in got and ("noise", "accel_noise", log) in got
    if kind == "accel_z":
        return any(
            _bracketed(f, z, log) for f in flags for z in ("accel_norm_error", "accel_bias_z")
        )
    if kind == "accel_x":
        return any(_bracketed(f, "accel_bias_x", log) for f in flags)
    if kind == "thermal":
        return not flags
    raise ValueError(kind)


def _bracketed(flag: dict[str, Any], figure: str, log: str) -> bool:
    """A step of ``figure`` flagged at ``log``, or between two logs that ``log`` lies between
    (the log before it and ``log`` lack the figure: no level still period, no pose that tells
    the axis): after the last log that had it, at or before the flag's."""
    if flag["kind"] != "step" or flag["figure"] != figure:
        return False
    return flag["log"] == log or flag.get("after_log", log) < log <= flag["log"]


def bias_z(table: Any, logs: list[Log]) -> np.ndarray:
    """(gyro bias error / stated se) of every surveyed period matched to a true one."""
    rows = [r for r in table.to_pylist() if r["still"]]
    truth: dict[tuple[str, str], list[tuple[int, int, np.ndarray]]] = {}
    for log in logs:
        for s in log.streams[:1]:
            truth[(log.name, s.topic)] = [(a, b, g) for a, b, g, _ in s.still]
    z = []
    for r in rows:
        for a, b, g in truth.get((r["log"], r["topic"]), []):
            if r["start_ns"] >= a - 1e9 and r["stop_ns"] <= b + 1e9:
                for i, ax in enumerate("xyz"):
                    z.append((r[f"gyro_bias_{ax}"] - g[i]) / r[f"gyro_bias_se_{ax}"])
    return np.array(z)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clean", type=int, default=20, help="clean fleets (default 20)")
    ap.add_argument("--planted", type=int, default=6, help="planted fleets (default 6)")
    ap.add_argument("--first", type=int, default=0)
    args = ap.parse_args()
    t = time.perf_counter()
    flagged = collections.Counter()
    examples = []
    devices = 0
    zs = []
    fake = 0
    judged_out = 0
    for seed in range(args.first, args.first + args.clean):
        logs, _ = make_fleet(seed)
        table, view = survey_fleet(logs)
        zs.append(bias_z(table, logs))
        fake += _unmatched(table, logs)
        judged_out += sum(not x for x in table.column("still").to_pylist())
        for d in view["devices"]:
            devices += 1
            for f in d["flags"]:
                flagged[(f["kind"], f["figure"])] += 1
                if len(examples) < 8:
                    examples.append(f"seed {seed} {d['device_id']}: {f['why']}")
    n_false = sum(flagged.values())
    print(
        f"clean fleets {args.clean}: {devices} devices, {n_false} flags, {time.perf_counter() - t:.0f} s"
    )
    for key, n in sorted(flagged.items()):
        print(f"   {key}: {n}")
    for e in examples:
        print("   e.g.", e)
    z = np.concatenate(zs) if zs else np.zeros(0)
    print(f"   gyro bias within 3 stated se: {np.mean(np.abs(z) < 3):.3f} of {len(z)} period-axes")
    print(f"   still periods with no true still period under them: {fake}")
    print(f"   candidates judged not still (vibration): {judged_out}")
    hits = collections.Counter()
    tried = collections.Counter()
    other = copies = 0
    power: list[float] = []
    unobservable = 0
    for seed in range(1000 + args.first, 1000 + args.first + args.planted):
        logs, events = make_fleet(seed, PLANTS)
        _, view = survey_fleet(logs)
        flags = {d["device_id"]: d["flags"] for d in view["devices"]}
        planted = {e["device_id"] for e in events}
        # the 1 Hz copy (/imu1/data) is the same sensor as its vehicle's /imu/data: a plant's
        # flag on it is right, counted apart
        host = {dev.split(":")[0] for dev in planted}
        for dev, v in flags.items():
            if dev not in planted:
                copy = dev.split(":")[0] in host and dev.endswith("/imu1/data")
                copies += len(v) if copy else 0
                other += 0 if copy else len(v)
        for e in events:
            if e.get("observable") is False:  # its poses never tell x: not a test
                unobservable += 1
                continue
            tried[e["kind"]] += 1
            ok = caught(e, flags.get(e["device_id"], []))
            hits[e["kind"]] += ok
            if not ok:
                got = [(f["kind"], f["figure"], f["log"]) for f in flags.get(e["device_id"], [])]
                print(f"   missed seed {seed} {e['kind']} at {e['log']}: {got}")
        for d in view["devices"]:
            power.extend(
                v for f, v in d["drift_detectable_per_week"].items() if f.startswith("gyro")
            )
    print(
        f"planted fleets {args.planted}: flags on unplanted devices {other} (and {copies} on the "
        "1 Hz copy of a planted sensor)"
    )
    for kind in PLANTS:
        print(f"   {kind:8s} {hits[kind]} of {tried[kind]}")
    print(
        f"   accel_x plants on a vehicle never set down on both x faces (not judged): {unobservable}"
    )
    if power:
        q = np.nanpercentile(power, [10, 50, 90])
        print(
            f"   gyro drift found with 90 % probability: {q[1]:.3g} rad/s per week (median; "
            f"10-90 %: {q[0]:.3g}-{q[2]:.3g})"
        )
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        r = truncated_check(Path(tmp))
    same = r["file"] == r["memory"]
    print(
        f"cut-off log (MCAP, 70 % of its bytes): {r['recovered']} of {r['samples']} samples "
        f"recovered by the mcap library; plain survey failed it: {bool(r['plain_failed'])}; with "
        f"--read-truncated {len(r['file'])} still periods (in memory on those samples: "
        f"{len(r['memory'])}, {'the same' if same else 'DIFFERENT'}; true before the cut: "
        f"{r['true_before_cut']})"
    )
    print(f"total {time.perf_counter() - t:.0f} s")


def _unmatched(table: Any, logs: list[Log]) -> int:
    """Still periods (the fleet view's judgement) of the main IMU topic that lie in no true
    still period."""
    spans = {
        (log.name, s.topic): [(a, b) for a, b, _, _ in s.still] for log in logs for s in log.streams
    }
    n = 0
    for r in table.to_pylist():
        if r["topic"] != "/imu/data" or not r["still"]:
            continue
        if not any(
            r["start_ns"] >= a - 1.5e9 and r["stop_ns"] <= b + 1.5e9
            for a, b in spans[(r["log"], r["topic"])]
        ):
            n += 1
    return n


if __name__ == "__main__":
    main()
