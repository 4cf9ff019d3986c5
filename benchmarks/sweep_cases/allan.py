"""Static recordings (``imupipe simulate static``, then filtered, decimated or stepped where the
case says) through ``allan`` with default options: 0.5 to 12 h, 10 to 1000 Hz, low-pass filtered
and decimated data, bias-instability bumps, a bias step.

Judged on what ``imu.yaml`` gets (:func:`imupipe.pipeline.exports.common.noise`: Kalibr's one
value per sensor, the largest axis):

- N (white noise density): a fitted N is within tolerance within +-10 % of the truth (the
  stage states no interval for N: ``covered`` is None); an unresolved N is written as the upper
  bound from the shortest taus: within tolerance when it bounds the truth and is at most 10 times
  it, covered when it bounds the truth. Never a zero.
- K (random walk density): the stage states a 68 % profile interval per axis (asymmetric); its
  95 % interval is taken as the fitted K times ``exp(-1.96 s_lo)`` to ``exp(+1.96 s_hi)`` with
  ``s_lo``, ``s_hi`` the 68 % interval's log half-widths below and above K; the truth is judged
  against the side it lies on: within tolerance inside ``exp(+-3.3 s)`` (99.9 %). The largest
  of three axes' estimates of one K reads high by about 0.85 of their scatter (the expected
  largest of three normals): the K rows are mostly high for that reason, not the fit's. A K the fit did not resolve is written as
  the upper end of its 68 % interval: within tolerance when that is at least a third of the
  truth (a random walk too weak to resolve), covered when it bounds the truth.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.signal import butter, sosfiltfilt

from imupipe.pipeline.exports.common import noise
from imupipe.pipeline.simulate import simulate
from imupipe.readers.table import make_table, sensor
from imupipe.stages.allan.stage import AllanStage
from imupipe.stages.base import StageContext
from sweep_cases import judge

FAMILY = "allan"
N_TOLERANCE = 0.10
HOUR = 3600.0
MEMS = {  # a consumer MEMS IMU (BMI088-like), continuous-time SI
    "gyro_N": [2.5e-4] * 3,
    "gyro_K": [3.0e-6] * 3,
    "gyro_B": [0.0] * 3,
    "accel_N": [1.5e-3] * 3,
    "accel_K": [4.0e-5] * 3,
    "accel_B": [0.0] * 3,
}
BUMP = {"gyro_B": [3.0e-5] * 3, "accel_B": [2.0e-4] * 3}
"""Bias instability (flicker) well above the white noise's floor at minutes."""

CASES: list[tuple[str, dict[str, Any], dict[str, Any], bool]] = [
    # (case, simulation parameters over MEMS, post-processing, in the quick subset)
    (
        "1 h at 10 Hz, white noise under the bias instability (a phone's stream)",
        {
            "duration_s": HOUR,
            "rate_hz": 10.0,
            "gyro_N": [1e-4] * 3,
            "gyro_B": [1e-3] * 3,
            "gyro_K": [1e-6] * 3,
            "accel_N": [1e-3] * 3,
            "accel_B": [1e-2] * 3,
            "accel_K": [1e-5] * 3,
        },
        {},
        True,
    ),
    ("0.5 h at 100 Hz", {"duration_s": 0.5 * HOUR, "rate_hz": 100.0}, {}, True),
    ("0.5 h at 1000 Hz", {"duration_s": 0.5 * HOUR, "rate_hz": 1000.0}, {}, False),
    ("2 h at 400 Hz", {"duration_s": 2 * HOUR, "rate_hz": 400.0}, {}, False),
    ("12 h at 10 Hz", {"duration_s": 12 * HOUR, "rate_hz": 10.0}, {}, False),
    (
        "1 h at 100 Hz, bias-instability bump",
        {"duration_s": HOUR, "rate_hz": 100.0, **BUMP},
        {},
        True,
    ),
    (
        "6 h at 50 Hz, bias-instability bump",
        {"duration_s": 6 * HOUR, "rate_hz": 50.0, **BUMP},
        {},
        False,
    ),
    (
        "1 h at 100 Hz averaged and decimated to 10 Hz",
        {"duration_s": HOUR, "rate_hz": 100.0},
        {"decimate": 10, "filter": "mean"},
        True,
    ),
    (
        "6 h at 100 Hz low-passed at 2 Hz, decimated to 10 Hz (a phone)",
        {"duration_s": 6 * HOUR, "rate_hz": 100.0, **BUMP},
        {"decimate": 10, "filter": 2.0},
        False,
    ),
    (
        "1 h at 100 Hz low-passed at 2 Hz, decimated to 10 Hz",
        {"duration_s": HOUR, "rate_hz": 100.0, **BUMP},
        {"decimate": 10, "filter": 2.0},
        True,
    ),
    (
        "2 h at 100 Hz, a bias step of 20 sample sigmas at half time",
        {"duration_s": 2 * HOUR, "rate_hz": 100.0},
        {"step": 20.0},
        False,
    ),
    (
        "2 h at 100 Hz, a bias step of 1 sample sigma at half time",
        {"duration_s": 2 * HOUR, "rate_hz": 100.0},
        {"step": 1.0},
        False,
    ),
]


def recording(params: dict[str, Any], post: dict[str, Any], seed: int):
    """The simulated table after the case's post-processing, and the truth."""
    table, truth = simulate("static", params, seed=seed)
    gyro, accel = sensor(table, "gyro"), sensor(table, "accel")
    t_ns, g, a = gyro.t_ns, gyro.values, accel.values
    fs = float(params["rate_hz"])
    if "step" in post:  # a bias step (a knock, a power event) at half time
        half = len(t_ns) // 2
        g = g.copy()
        a = a.copy()
        g[half:] += post["step"] * np.asarray(params["gyro_N"]) * np.sqrt(fs)
        a[half:] += post["step"] * np.asarray(params["accel_N"]) * np.sqrt(fs)
    if "decimate" in post:
        q = int(post["decimate"])
        if post["filter"] == "mean":  # block means: a decimating driver
            m = len(t_ns) // q * q
            g = g[:m].reshape(-1, q, 3).mean(axis=1)
            a = a[:m].reshape(-1, q, 3).mean(axis=1)
            t_ns = t_ns[:m:q]
        else:  # a phone's low-pass filter, then every q-th sample
            sos = butter(4, float(post["filter"]), fs=fs, output="sos")
            g, a = sosfiltfilt(sos, g, axis=0)[::q], sosfiltfilt(sos, a, axis=0)[::q]
            t_ns = t_ns[::q]
    return make_table(t_ns, gyro=g, accel=a, metadata={}), truth


def rows_for(case: str, params: dict[str, Any], post: dict[str, Any], seed: int) -> list[dict]:
    state: dict[str, Any] = {}

    def fit() -> dict[str, Any]:
        table, truth = recording(params, post, seed)
        ctx = StageContext(name="allan", input_name="sweep", quiet=True)
        state["results"] = AllanStage(AllanStage.Options()).fit(table, ctx).results
        state["truth"] = truth
        return judge_n("gyro")

    def judge_n(name: str) -> dict[str, Any]:
        n = noise(state["results"], name)
        true_n = max(state["truth"][name]["N"])
        if n.n_bound:
            ok = true_n <= n.density <= 10 * true_n
            return {
                "ok": ok,
                "error": f"N upper bound {n.density / true_n:.3g} x truth",
                "stated": "upper bound",
                "covered": n.density >= true_n,
            }
        err = n.density / true_n - 1
        return {
            "ok": n.density > 0 and abs(err) <= N_TOLERANCE,
            "error": f"N {100 * err:+.3g} %",
            "stated": f"+-{100 * N_TOLERANCE:g} % (no interval)",
            "covered": None,
        }

    def judge_k(name: str) -> dict[str, Any]:
        res, truth = state["results"], state["truth"]
        n = noise(res, name)
        true_k = float(np.asarray(truth[name]["K"])[0])
        if n.k_bound:
            return {
                "ok": n.random_walk >= true_k / 3,
                "error": f"K upper bound {n.random_walk / true_k:.3g} x truth",
                "stated": "68 % upper bound",
                "covered": n.random_walk >= true_k,
            }
        axis = n.random_walk_axis
        lo, hi = res["metrics"][name][axis]["K_range_68"] or (0.0, np.inf)
        k = n.random_walk
        # the interval is asymmetric (a profile): each side's log half-width s, and the
        # truth judged against the side it lies on
        s_lo = np.log(k / lo) if lo > 0 else np.inf
        s_hi = np.log(hi / k) if np.isfinite(hi) and hi > 0 else np.inf
        s = s_lo if true_k < k else s_hi
        z = abs(np.log(true_k / k)) / s if s > 0 else np.inf
        stated = "/".join(
            f"{sign}{100 * abs(np.exp(f * 1.96 * side) - 1):.3g} %"
            if np.isfinite(side)
            else f"{sign}inf"
            for sign, f, side in (("-", -1, s_lo), ("+", 1, s_hi))
        )
        return {
            "ok": bool(z <= 3.3),
            "error": f"K {100 * (k / true_k - 1):+.3g} %",
            "stated": stated,
            "covered": bool(z <= 1.96),
        }

    label = f"{case} (seed {seed})"
    causes = (r"jump of the bias", r"gyro bias jumps") if "step" in post else ()
    rows = [judge(FAMILY, f"gyro N: {label}", fit, causes)]
    if "results" in state:
        rows.append(judge(FAMILY, f"accel N: {label}", lambda: judge_n("accel")))
        rows.append(judge(FAMILY, f"gyro K: {label}", lambda: judge_k("gyro")))
        rows.append(judge(FAMILY, f"accel K: {label}", lambda: judge_k("accel")))
    return rows


def run(quick: bool) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for index, (case, over, post, in_quick) in enumerate(CASES):
        if quick and not in_quick:
            continue
        rows += rows_for(case, {**MEMS, **over}, post, seed=21 + index)  # one realisation each
    return rows
