"""Scenario ``fleet``: a fleet of vehicles, each with IMU instances, logging for weeks, with a known
bias history per device and planted events: the truth ``imupipe survey`` is tested against.

Model (SI; one device = one IMU instance of one vehicle):

- **Logs.** Each vehicle records ``logs`` logs ``days_between_logs`` days apart (+- 30 %
  jitter), each ``log_s`` seconds at ``rate_hz``: alternating still moments (``still_s``
  [min, max], uniform: waiting on the pad, parked, at a crossing) and motion (``motion_s``
  [min, max]: rates of ~0.5 rad/s and 1 m/s^2 of vibration), starting and ending still. The
  vehicle's IMUs share its motion. Each still moment has its own attitude, tilted by up to
  ``tilt_deg`` (a slope), half of them level (tilt 0).
- **Gyro and accelerometer** of a device: ``true + bias + white noise`` (densities ``gyro_N``,
  ``accel_N``, unit/sqrt(Hz)). The bias of each axis is ``b0 + w(day) + c (T - 25 degC)``:
  ``b0`` drawn once per device (std ``gyro_bias_spread`` / ``accel_bias_spread``), ``w`` a random
  walk over calendar days (``gyro_rw_per_day`` / ``accel_rw_per_day``, unit/sqrt(day)),
  ``c`` a per-device thermal coefficient (std ``gyro_thermal``, ``accel_thermal``, unit/K).
- **Temperature** of a device in a log: ``ambient + warm_c * (1 - exp(-t / warm_tau_s))`` (self-heating
  after power-on), ``ambient``
  uniform in ``ambient_c`` per log, plus a per-device offset of up to 3 K; sampled at 1 Hz on
  its own topic.
- **Planted events** (``events = true``), from log ``logs // 2`` of a vehicle on:
  ``crash`` (vehicle 2, imu 0: accel bias steps by ``crash_accel`` and gyro bias by
  ``crash_gyro``), ``noise`` (vehicle 3, last imu: noise densities times ``noise_factor``:
  a loosened mount) and ``failing`` (vehicle 4, imu 0: the gyro z bias runs away at
  ``fail_rate`` rad/s per day). Events whose vehicle does not exist are left out.
- **Chamber calibrations** (``chamber = true``): every device went through a thermal chamber
  ``chamber_days`` days before its vehicle's first log, over ``chamber_range_c`` degC; its
  chamber calibration is the true curve then (a ``temperature`` step, model ``poly``, terms
  ``1, T`` about Tref = 25 degC, for the gyro and the accelerometer): ``b0 - w_pre + c (T - 25)``,
  ``w_pre`` the bias random walk over those days (so the bias has moved since the chamber by
  ``w_pre + w(day)``). Planted changes of the curve after the chamber (``chamber_events``, from
  the first log on), both on vehicle 1: its last IMU's gyro bias moves by ``chamber_offset``
  (rad/s, per axis), its first IMU's gyro thermal slope by ``chamber_slope`` (rad/s/K).

Written as a folder ``OUT/<vehicle>/log_<k>.mcap``, one MCAP per log holding each IMU instance
on ``/imu<i>/data`` (frame ``<vehicle>_imu<i>``) and ``/imu<i>/temperature``; the truth is
``OUT.truth.json``: per device and log, every still moment's bounds and its true mean gyro bias,
accelerometer bias, ``|a| - g``, the direction of gravity in the body (unit), noise densities and
temperature, and the planted events. With
``chamber``, each vehicle's chamber calibration (one ``calibration.json`` with a gyro and an
accelerometer step per IMU, each naming its topic) is ``OUT.chamber/<vehicle>.json`` and the truth
gives per device ``chamber``: the change of the curve since the chamber, per log the offset at
Tref (``gyro_offset``, ``accel_offset``, unit) and the slope change (``gyro_slope``,
``accel_slope``, unit/K), and ``planted`` (``offset``, ``slope`` or null).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.simulate.clock import sample_times
from imupipe.pipeline.simulate.noise import white
from imupipe.readers.table import make_table

WRITES = ("",)
"""A folder of MCAP logs (no suffix)."""

DEFAULTS: dict[str, Any] = {
    "vehicles": 4,
    "imus": 2,
    "logs": 6,
    "rate_hz": 100.0,
    "log_s": 150.0,
    "days_between_logs": 7.0,
    "t0_s": 1_767_225_600.0,
    "gravity": 9.80665,
    "still_s": [8.0, 30.0],
    "motion_s": [10.0, 30.0],
    "tilt_deg": 8.0,
    "gyro_N": 1.5e-4,
    "accel_N": 2.0e-3,
    "gyro_bias_spread": 3e-3,
    "accel_bias_spread": 0.03,
    "gyro_rw_per_day": 3e-5,
    "accel_rw_per_day": 3e-4,
    "gyro_thermal": 5e-5,
    "accel_thermal": 5e-4,
    "ambient_c": [5.0, 35.0],
    "warm_c": 10.0,
    "warm_tau_s": 60.0,
    "events": True,
    "crash_gyro": 4e-3,
    "crash_accel": [0.12, -0.08, 0.15],
    "noise_factor": 3.0,
    "fail_rate": 1.5e-3,
    "chamber": False,
    "chamber_days": 20.0,
    "chamber_range_c": [0.0, 40.0],
    "chamber_events": True,
    "chamber_offset": [0.0, 0.0, 2e-3],
    "chamber_slope": [0.0, 0.0, 6e-5],
}
CHAMBER_TREF = 25.0
"""degC: the reference temperature of the simulated thermal coefficients and chamber curves."""


@dataclass
class LogRecipe:
    """What makes one log (small): its samples are drawn again from ``seed`` when written, so a
    fleet of thousands of logs is never held in memory."""

    rel: str
    vehicle: str
    t0_s: float
    day: float
    ambient: float
    seed: int
    imus: list[dict[str, Any]]
    """Per IMU: gyro/accel bias at this log and thermal coefficients, temperature offset, noise
    densities and the planted additions (SI)."""


@dataclass
class FleetLogs:
    """The fleet's logs (recipes) and the scenario's parameters."""

    params: dict[str, Any]
    logs: list[LogRecipe] = field(default_factory=list)
    chambers: dict[str, dict[str, Any]] = field(default_factory=dict)
    """vehicle -> its chamber calibration document (with ``chamber``)."""

    def tables(self, recipe: LogRecipe) -> list[pa.Table]:
        """The common tables of one log's IMU instances (one per topic)."""
        return _log(recipe, self.params, tables=True)[0]

    def write(self, out: Path) -> None:
        """Write every log as ``out/<relative path>`` (MCAP; each written atomically) and each
        vehicle's chamber calibration as ``out.chamber/<vehicle>.json``."""
        from imupipe.pipeline.atomic import staged_outputs
        from imupipe.pipeline.calibration_file import calibration_json
        from imupipe.pipeline.writers.mcap import McapTableWriter

        if self.chambers:
            folder = out.with_name(out.name + ".chamber")
            folder.mkdir(parents=True, exist_ok=True)
            with staged_outputs() as staged:
                for vehicle, doc in self.chambers.items():
                    staged.write_text(folder / f"{vehicle}.json", calibration_json(doc))

        for recipe in self.logs:
            path = out / recipe.rel
            path.parent.mkdir(parents=True, exist_ok=True)
            with staged_outputs() as staged, McapTableWriter(staged.path(path)) as writer:
                for table in self.tables(recipe):
                    writer.write_table(table)


def _rotation(tilt: float, azimuth: float) -> np.ndarray:
    """The gravity direction in the body frame for a tilt (rad) towards ``azimuth`` (rad)."""
    return np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])


def _activity(
    rng: np.random.Generator, n: int, fs: float, p: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """A vehicle's activity in one log: (true rate (n,3), gravity direction (n,3), vibration
    (n,3), still sample ranges)."""
    still: list[tuple[int, int]] = []
    rate = np.zeros((n, 3))
    up = np.zeros((n, 3))
    vib = np.zeros((n, 3))
    i, is_still = 0, True
    last_up = _rotation(0.0, 0.0)
    while i < n:
        lo, hi = p["still_s"] if is_still else p["motion_s"]
        m = min(n - i, int(rng.uniform(lo, hi) * fs))
        if n - i - m < int(p["still_s"][0] * fs):  # too little left: finish with this segment
            m = n - i
        if is_still:
            tilt = 0.0 if rng.random() < 0.5 else np.radians(rng.uniform(1.0, p["tilt_deg"]))
            last_up = _rotation(tilt, rng.uniform(0, 2 * np.pi))
            up[i : i + m] = last_up
            still.append((i, i + m))
        else:
            t = np.arange(m) / fs
            f = rng.uniform(0.05, 0.3, 3)
            rate[i : i + m] = 0.5 * np.sin(2 * np.pi * f * t[:, None] + rng.uniform(0, 6, 3))
            up[i : i + m] = last_up
            vib[i : i + m] = rng.standard_normal((m, 3))
        i += m
        is_still = not is_still
    return rate, up, vib, still


def _log(
    r: LogRecipe, p: dict[str, Any], tables: bool
) -> tuple[list[pa.Table], list[list[dict[str, Any]]]]:
    """One log from its recipe: (its tables when ``tables``, else none; per IMU the truth of
    each still moment). The activity is drawn from ``seed``, the noise from a second stream."""
    fs = float(p["rate_hz"])
    n = int(round(float(p["log_s"]) * fs))
    g = float(p["gravity"])
    rate, up, vib, still = _activity(np.random.default_rng(r.seed), n, fs, p)
    noise = np.random.default_rng([r.seed, 1])
    t_ns = sample_times(r.t0_s, n, fs)
    ts = np.arange(n) / fs
    out, truth = [], []
    for imu in r.imus:
        k = imu["k"]
        temp = r.ambient + imu["t_off"] + p["warm_c"] * (1 - np.exp(-ts / p["warm_tau_s"]))
        gb = imu["gyro_b"] + imu["gyro_c"] * (temp[:, None] - 25.0)
        ab = imu["accel_b"] + imu["accel_c"] * (temp[:, None] - 25.0)
        periods = []
        for a, b in still:
            mean_a = up[a] * g + ab[a:b].mean(axis=0)
            periods.append(
                {
                    "start_ns": int(t_ns[a]),
                    "stop_ns": int(t_ns[b - 1]),
                    "gyro_bias": gb[a:b].mean(axis=0).tolist(),
                    "accel_bias": ab[a:b].mean(axis=0).tolist(),
                    "accel_norm_error": float(np.linalg.norm(mean_a) - g),
                    "level": bool(up[a][2] == 1.0),
                    "gravity_direction": up[a].tolist(),
                    "gyro_N": imu["gyro_N"],
                    "accel_N": imu["accel_N"],
                    "temperature": float(temp[a:b].mean()),
                }
            )
        truth.append(periods)
        if not tables:
            continue
        gyro = rate + gb + np.column_stack([white(noise, n, imu["gyro_N"], fs) for _ in range(3)])
        accel = up * g + vib + ab
        accel += np.column_stack([white(noise, n, imu["accel_N"], fs) for _ in range(3)])
        temp_rows = np.zeros(n, dtype=bool)
        temp_rows[:: max(int(fs), 1)] = True
        frame = f"{r.vehicle}_imu{k}"
        out.append(
            make_table(
                t_ns,
                gyro=gyro,
                accel=accel,
                temperature=temp,
                valid={"imu": np.ones(n, dtype=bool), "temperature": temp_rows},
                metadata={
                    "source": "imupipe simulate fleet",
                    "format": "simulated",
                    "topics": {"imu": f"/imu{k}/data", "temperature": f"/imu{k}/temperature"},
                    "frame_id": {"imu": frame, "temperature": frame},
                },
            )
        )
    return out, truth


def chamber_entries(
    vehicle: str, k: int, imu: dict[str, Any], p: dict[str, Any], t_ns: int
) -> list[dict[str, Any]]:
    """The chain entries of IMU ``k``'s chamber calibration: a ``temperature`` step (poly,
    ``1, T`` about :data:`CHAMBER_TREF`) for the gyro and one for the accelerometer, fitted on a
    chamber log of its topic that ended at ``t_ns``."""
    from imupipe.stages.thermal.step import TemperatureStep

    out = []
    lo, hi = (float(v) for v in p["chamber_range_c"])
    for sensor in ("gyro", "accel"):
        b, c = imu[f"{sensor}_b0"], imu[f"{sensor}_c"]
        step = TemperatureStep(
            type="temperature",
            sensor=sensor,
            model="poly",
            tref=CHAMBER_TREF,
            window=None,
            window_s=10.0,
            axes=[
                {"terms": ["1", "T"], "coefficients": [float(b[i]), float(c[i])]} for i in range(3)
            ],
            ranges={"T": [lo, hi]},
        )
        topic = f"/imu{k}"
        out.append(
            {
                **step.to_json(),
                "fitted_on": {
                    "input": "chamber",
                    "path": f"chamber/{vehicle}_imu{k}.mcap",
                    "format": "mcap",
                    "topics": {"imu": f"{topic}/data", "temperature": f"{topic}/temperature"},
                    "frame_id": {"imu": f"{vehicle}_imu{k}"},
                    "t_start_ns": t_ns - int(4 * 3600e9),
                    "t_end_ns": t_ns,
                },
            }
        )
    return out


def simulate(p: dict[str, Any], rng: np.random.Generator) -> tuple[FleetLogs, dict[str, Any]]:
    nv, ni, nl = int(p["vehicles"]), int(p["imus"]), int(p["logs"])
    event_log = nl // 2
    planted: dict[tuple[int, int], str] = {}
    if p["events"]:
        for kind, (v, k) in {"crash": (1, 0), "noise": (2, ni - 1), "failing": (3, 0)}.items():
            if v < nv:
                planted[(v, k)] = kind
    chamber_planted: dict[tuple[int, int], str] = {}
    if p["chamber"] and p["chamber_events"]:
        chamber_planted = {(0, 0): "slope", (0, ni - 1): "offset"}
        if ni == 1:
            chamber_planted = {(0, 0): "offset and slope"}
    fleet = FleetLogs(dict(p))
    devices: dict[str, dict[str, Any]] = {}
    events: list[dict[str, Any]] = []
    for v in range(nv):
        vehicle = f"veh{v + 1:02d}"
        gaps = p["days_between_logs"] * rng.uniform(0.7, 1.3, nl)
        days = np.cumsum(gaps) - gaps[0]
        state = []
        for k in range(ni):
            topic = f"/imu{k}/data"
            dev = f"{vehicle}:{topic}"
            steps_g = rng.standard_normal((nl, 3)) * p["gyro_rw_per_day"] * np.sqrt(gaps)[:, None]
            steps_a = rng.standard_normal((nl, 3)) * p["accel_rw_per_day"] * np.sqrt(gaps)[:, None]
            steps_g[0] = steps_a[0] = 0.0
            state.append(
                {
                    "gyro_b": rng.standard_normal(3) * p["gyro_bias_spread"]
                    + np.cumsum(steps_g, axis=0),
                    "accel_b": rng.standard_normal(3) * p["accel_bias_spread"]
                    + np.cumsum(steps_a, axis=0),
                    "gyro_c": rng.standard_normal(3) * p["gyro_thermal"],
                    "accel_c": rng.standard_normal(3) * p["accel_thermal"],
                    "t_off": rng.uniform(0.0, 3.0),
                }
            )
            kind = planted.get((v, k))
            if kind is not None:
                events.append(
                    {"device_id": dev, "kind": kind, "log": f"{vehicle}/log_{event_log:02d}.mcap"}
                )
            chamber = None
            if p["chamber"]:  # the walk from the chamber to the first log
                st = state[-1]
                pre = np.sqrt(float(p["chamber_days"]))
                st["gyro_b0"] = (
                    st["gyro_b"][0] - rng.standard_normal(3) * p["gyro_rw_per_day"] * pre
                )
                st["accel_b0"] = (
                    st["accel_b"][0] - rng.standard_normal(3) * p["accel_rw_per_day"] * pre
                )
                change = chamber_planted.get((v, k))
                st["chamber_offset"] = np.zeros(3)
                st["chamber_slope"] = np.zeros(3)
                if change and "offset" in change:
                    st["chamber_offset"] = np.asarray(p["chamber_offset"], dtype=np.float64)
                if change and "slope" in change:
                    st["chamber_slope"] = np.asarray(p["chamber_slope"], dtype=np.float64)
                chamber = {
                    "file": f"{vehicle}.json",
                    "planted": change,
                    "tref": CHAMBER_TREF,
                    "gyro_offset": (st["gyro_b"] - st["gyro_b0"] + st["chamber_offset"]).tolist(),
                    "accel_offset": (st["accel_b"] - st["accel_b0"]).tolist(),
                    "gyro_slope": st["chamber_slope"].tolist(),
                    "accel_slope": [0.0, 0.0, 0.0],
                }
            devices[dev] = {
                "vehicle": vehicle,
                "topic": topic,
                "instance": k,
                "frame_id": f"{vehicle}_imu{k}",
                "gyro_thermal": state[-1]["gyro_c"].tolist(),
                "accel_thermal": state[-1]["accel_c"].tolist(),
                "event": kind,
                "chamber": chamber,
                "logs": [],
            }
        for j in range(nl):
            rel = f"{vehicle}/log_{j:02d}.mcap"
            imus = []
            for k in range(ni):
                st = state[k]
                kind = planted.get((v, k)) if j >= event_log else None
                imu = {
                    "k": k,
                    "gyro_b": st["gyro_b"][j].copy(),
                    "accel_b": st["accel_b"][j].copy(),
                    "gyro_c": st["gyro_c"] + st.get("chamber_slope", 0.0),
                    "accel_c": st["accel_c"],
                    "t_off": st["t_off"],
                    "gyro_N": float(p["gyro_N"]),
                    "accel_N": float(p["accel_N"]),
                }
                if p["chamber"]:
                    imu["gyro_b"] += st["chamber_offset"]
                if kind == "crash":
                    imu["gyro_b"] += p["crash_gyro"]
                    imu["accel_b"] += np.asarray(p["crash_accel"], dtype=np.float64)
                elif kind == "noise":
                    imu["gyro_N"] *= p["noise_factor"]
                    imu["accel_N"] *= p["noise_factor"]
                elif kind == "failing":
                    imu["gyro_b"][2] += p["fail_rate"] * (days[j] - days[event_log] + 1)
                imus.append(imu)
            if p["chamber"] and j == 0:
                t_ch = int((float(p["t0_s"]) + (days[0] - p["chamber_days"]) * 86400.0) * 1e9)
                chain = [
                    e
                    for k in range(ni)
                    for e in chamber_entries(
                        vehicle,
                        k,
                        {
                            "gyro_b0": state[k]["gyro_b0"],
                            "accel_b0": state[k]["accel_b0"],
                            "gyro_c": state[k]["gyro_c"],
                            "accel_c": state[k]["accel_c"],
                        },
                        p,
                        t_ch,
                    )
                ]
                fleet.chambers[vehicle] = {
                    "chain": chain,
                    "simulated": {"scenario": "fleet", "vehicle": vehicle},
                }
            recipe = LogRecipe(
                rel,
                vehicle,
                float(p["t0_s"]) + days[j] * 86400.0 + rng.uniform(8, 18) * 3600.0,
                float(days[j]),
                float(rng.uniform(*p["ambient_c"])),
                int(rng.integers(2**62)),
                imus,
            )
            fleet.logs.append(recipe)
            for k, periods in enumerate(_log(recipe, p, tables=False)[1]):
                devices[f"{vehicle}:/imu{k}/data"]["logs"].append(
                    {"log": rel, "day": float(days[j]), "periods": periods}
                )
    return fleet, {"devices": devices, "events": events}
