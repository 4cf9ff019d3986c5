"""``mag_inflight`` stage: the compass calibrated from a flight log against the World Magnetic
Model, as ArduPilot's MagFit (pymavlink ``tools/magfit_WMM.py``) does.

Model (tesla; ``P`` the motor power signal interpolated onto the magnetometer's stamps: the
battery current ``I`` in A, or the collective throttle 0..1 when the motor term follows the
throttle)::

    R(q)^T B_wmm(lat, lon, alt)  =  M (raw - offset) + motor * P

``B_wmm`` is the earth field in NED (:mod:`imupipe.stages.magnetometer.wmm`), ``R(q)`` the attitude
(body FRD -> NED) of the table's ``attitude`` flight stream, so the left side is the field the
compass should read in the body frame. ``offset`` is the hard iron, ``M`` a symmetric matrix
(soft iron and scale: ArduPilot's ``COMPASS_SCALE`` x ``DIA``/``ODI``), ``motor`` the field per
ampere (``COMPASS_MOT`` with ``COMPASS_MOTCT = 2``) or per unit of throttle (``COMPASS_MOTCT =
1``, PX4 ``CAL_MAG_COMP_TYP = 1``). The model is linear in ``(M, -M offset, motor)``:
it is fitted by iteratively reweighted least squares with Huber weights on the vector
residual (``huber_k`` robust sigmas), samples beyond ``outlier_k`` robust sigmas rejected.

Model choice (``model = "auto"``): ``offsets`` (M = I), ``scale`` (M = s I), ``soft_iron``
(symmetric M), each with the motor term when the current varies; the flight is cut into
``folds`` segments in time (several flights of one vehicle, ``flights``: each flight is a
segment), each candidate fitted on the others and scored on the one held out, and the simplest
candidate within 2 % of the best held-out RMS residual is kept. The soft iron is fitted within
ArduPilot's ranges (``COMPASS_SCALE`` 1/1.5..1.5, ``DIA`` 0.8..1.2, ``ODI`` +-0.2 of the
scale; :func:`solve_bounded`), as MagFit bounds its fit, and is a candidate also on a flight
whose field directions spread less than ``min_spread`` (little tilt): there its terms the
attitudes did not turn are held at the scale model's by a ridge (:func:`toward_scale`), and
the held-out segments decide.

Motor source (``motor_source = "auto"``): the battery current when it is logged and
separable, else the throttle (the table's ``throttle`` flight stream: ArduCopter ``CTUN.ThO``,
PX4's thrust setpoint). The choice depends only on the vehicle's current and attitude, not on
the compass, so every compass of one log gets the same kind: a vehicle has one
``COMPASS_MOTCT`` (one ``CAL_MAG_COMP_TYP``) for all its compasses, and a per-ampere
``COMPASS_MOT2`` under a throttle ``COMPASS_MOTCT`` is wrong by the ratio of the two signals
(the current is the physical cause; ask for ``motor_source = "throttle"`` for a current sensor
that does not see the motors' wiring). With ``motor = "auto"`` the motor term is then scored
against none on the same held-out segments and kept only when it lowers the held-out residual
(the throttle, a proxy, by more than 2 %: a flying copter's throttle always varies, so its
range alone does not show that the compass follows it); a compass left without it gets no
``MOT``. A term of the kind the vehicle already had switched on (``COMPASS_MOTCT``,
``CAL_MAG_COMP_TYP``: :attr:`FlightSamples.compensated`) is kept without that test: the file
replaces the vehicle's term, which stays on either way.

Frames: the fit runs in the body frame. A raw PX4 ``sensor_mag`` is in the compass's own axes,
which PX4 turns into the body after its calibration (``R``: ``CAL_MAGn_ROT`` or
``SENS_BOARD_ROT`` with ``SENS_BOARD_*_OFF``, read by the ULog reader into the table's metadata:
:func:`sensor_rotation`): the field is turned by ``R`` before the fit, and the correction step
holds ``M R`` and ``R^T offset`` (results: ``matrix``/``offset_t`` in the body frame,
``sensor_rotation`` ``R``). ArduPilot's ``MAG`` is logged already turned (``AHRS_ORIENTATION``,
``COMPASS_ORIENT``), as PX4's ``vehicle_magnetometer`` is.

Separation (refused with ``ctx.fail`` naming what is missing): the expected body-field
directions must span the sphere enough for soft iron (``min_spread``, the smallest eigenvalue
of their covariance; a flight that only yawed level leaves the vertical unseen) and the current
must vary (``min_current_a``; the throttle ``min_throttle``) and not follow the field direction
(correlation < 0.95) for the motor term. Standard errors are the least-squares ones inflated by the residual's lag-1
autocorrelation (the residual of a flight is slow: attitude and model errors). Heading error:
the heading of the corrected field rotated into NED minus the model's (deg).

Quality checks (a fit failing one is not applied unless ``accept_failed_checks``): offsets no
larger than the Earth's field; the held-out residual below the flight's as flown; the heading
error no larger than as flown; the residual below ``max_residual_ut``. The residual checks leave
out samples beyond 5 medians on both sides, and the heading check compares over the samples the
fit kept (not its outliers), as flown and after: a sample the fit rejects is most often one
whose attitude is wrong (PX4 log_30: the primary EKF's yaw 35 deg off for 7 s after take-off),
and the heading error there measures the reference, not the compass.

The fit itself is :func:`fit_flight` (on :func:`flight_samples`): the stage calls it on its
input (and the flights joined to it), ``imupipe survey`` on every compass of every flight log
(:mod:`imupipe.pipeline.survey.compass`), so both give the same answer on the same flight.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import (
    SensorData,
    flight_stream,
    has_flight_stream,
    has_stream,
    interpolate,
    metadata,
    sensor,
)
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.magnetometer.wmm import date_of, earth_field
from imupipe.stages.steps import EntryError, LinearStep, _numbers, _short

MODELS = ("offsets", "scale", "soft_iron")
"""Candidate static models, simplest first."""
POWER_SOURCES = ("current", "throttle")
"""The motor term's power signals (flight streams), preferred first."""
POWER_UNIT = {"current": "A", "throttle": "throttle"}
"""What the motor term is per (``motor`` is T per A, or T per unit of throttle 0..1)."""
UT = 1e6
"""uT per tesla: the fit works in uT (and A), which keeps its normal equations well scaled."""


def rotate(q: np.ndarray, v: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Rotate rows of ``v`` by unit quaternions ``q`` (w, x, y, z): ``q v q*`` (body -> NED),
    or ``q* v q`` with ``inverse`` (NED -> body)."""
    w, u = q[:, :1], q[:, 1:]
    if inverse:
        u = -u
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _design(
    raw: np.ndarray, current: np.ndarray | None, model: str, groups: np.ndarray | None = None
) -> np.ndarray:
    """(3n, p) design of the stacked body-axis equations ``target = A theta``; theta is
    (M terms, b (3), motor (3) when current is given); ``M raw + b + motor I``. ``groups``
    (n,) ints 0..k-1: one ``b`` per group (per flight: ``b`` (3k), ``b_0`` first)."""
    n = len(raw)
    x, y, z = raw[:, 0], raw[:, 1], raw[:, 2]
    zero = np.zeros(n)
    one = np.ones(n)
    cols: list[list[np.ndarray]] = []  # each column: its 3 axis blocks
    if model == "scale":
        cols.append([x, y, z])
    elif model == "soft_iron":
        cols += [[x, zero, zero], [zero, y, zero], [zero, zero, z]]
        cols += [[y, x, zero], [z, zero, x], [zero, z, y]]
    for g in range(1 if groups is None else int(groups.max()) + 1):
        ind = one if groups is None else (groups == g).astype(np.float64)
        cols += [[ind, zero, zero], [zero, ind, zero], [zero, zero, ind]]
    if current is not None:
        cols += [[current, zero, zero], [zero, current, zero], [zero, zero, current]]
    return np.column_stack([np.concatenate(c) for c in cols])


@dataclass
class Fit:
    """A fitted model: ``matrix`` M, ``offset`` (T; (k, 3), one per group, when fitted with
    ``groups``), ``motor`` (T/A; zeros without); the parameter vector ``theta`` (M terms, ``b =
    -M offset`` in uT, motor in uT/A: see :func:`parameter_names`), its covariance, the samples
    used and the residual sigma (uT)."""

    model: str
    motor_term: bool
    matrix: np.ndarray
    offset: np.ndarray
    motor: np.ndarray
    theta: np.ndarray
    cov: np.ndarray
    used: np.ndarray
    sigma: float

    def predict(self, raw: np.ndarray, current: np.ndarray | None) -> np.ndarray:
        """The corrected field (n, 3), T."""
        out = (raw - self.offset) @ self.matrix.T
        if current is not None:
            out = out + current[:, None] * self.motor
        return out


def parameter_names(model: str, motor_term: bool, source: str = "current") -> list[str]:
    """What each entry of :attr:`Fit.theta` is (units in brackets; the motor term per ampere, or
    per unit of throttle with ``source = "throttle"``)."""
    names = {
        "offsets": [],
        "scale": ["scale [1]"],
        "soft_iron": [f"M{ij} [1]" for ij in ("xx", "yy", "zz", "xy", "xz", "yz")],
    }[model]
    names += [f"b_{a} [uT]" for a in "xyz"]
    if motor_term:
        names += [f"motor_{a} [uT/{POWER_UNIT[source]}]" for a in "xyz"]
    return names


def _unpack(
    theta: np.ndarray, model: str, motor_term: bool, groups: int = 1
) -> tuple[np.ndarray, ...]:
    """(M, offset, motor) of ``theta``; with ``groups`` > 1 (:func:`_design`'s) the offsets
    (groups, 3)."""
    k = {"offsets": 0, "scale": 1, "soft_iron": 6}[model]
    if model == "offsets":
        m = np.eye(3)
    elif model == "scale":
        m = np.eye(3) * theta[0]
    else:
        d, o = theta[:3], theta[3:6]
        m = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    b = theta[k : k + 3 * groups].reshape(groups, 3)
    end = k + 3 * groups
    motor = theta[end : end + 3] if motor_term else np.zeros(3)
    offset = -np.linalg.solve(m, b.T).T
    return m, offset[0] if groups == 1 else offset, motor


SCALE_RANGE = (1 / 1.5, 1.5)
"""The common scale of the soft iron ArduPilot applies (``COMPASS_SCALE``:
``Compass::have_scale_factor``, ``COMPASS_MIN/MAX_SCALE_FACTOR``; MagFit bounds it 0.6..1.5)."""
DIAGONAL_RANGE = (0.8, 1.2)
"""The soft iron's diagonal over its common scale (``COMPASS_DIA``): MagFit's bounds
(``magfit_WMM.py --min-diag/--max-diag``); ArduPilot's own calibrator refuses beyond 0.2..5
(``CompassCalibrator::fit_acceptable``), a physical compass stays well inside 0.8..1.2."""
OFF_DIAGONAL_MAX = 0.2
"""The soft iron's off-diagonal over its common scale (``COMPASS_ODI``): MagFit's bound
(``--min-offdiag/--max-offdiag``; the calibrator's is 1)."""
BOUND_MARGIN = 1e-4
"""How far inside the firmware's ranges a bounded fit stays (relative)."""


def bound_constraints(model: str, p: int) -> tuple[np.ndarray, np.ndarray]:
    """``(G, h)``: the firmware's ranges of ``model``'s matrix as linear inequalities ``G theta >=
    h`` on :attr:`Fit.theta` (``p`` entries): the scale ``s`` (the mean diagonal) inside
    :data:`SCALE_RANGE`, each diagonal inside :data:`DIAGONAL_RANGE` times ``s``, each
    off-diagonal within +-:data:`OFF_DIAGONAL_MAX` times ``s`` (``COMPASS_SCALE`` x ``DIA``/
    ``ODI``, as MagFit bounds them: ``magfit_WMM.py --min-scale/--max-diag/--max-offdiag``),
    each bound moved inward by :data:`BOUND_MARGIN` so that a bounded fit is written, not
    refused, by :func:`out_of_range`. No rows for ``offsets``."""
    rows: list[np.ndarray] = []
    low: list[float] = []
    lo_s, hi_s = SCALE_RANGE[0] * (1 + BOUND_MARGIN), SCALE_RANGE[1] * (1 - BOUND_MARGIN)
    if model == "scale":
        rows += [np.eye(p)[0], -np.eye(p)[0]]
        low += [lo_s, -hi_s]
    elif model == "soft_iron":
        mean = np.zeros(p)
        mean[:3] = 1.0 / 3.0
        lo_d, hi_d = DIAGONAL_RANGE[0] + BOUND_MARGIN, DIAGONAL_RANGE[1] - BOUND_MARGIN
        off = OFF_DIAGONAL_MAX - BOUND_MARGIN
        for i in range(3):
            rows += [np.eye(p)[i] - lo_d * mean, hi_d * mean - np.eye(p)[i]]
            rows += [off * mean - np.eye(p)[3 + i], off * mean + np.eye(p)[3 + i]]
            low += [0.0, 0.0, 0.0, 0.0]
        rows += [mean, -mean]
        low += [lo_s, -hi_s]
    return np.array(rows).reshape(-1, p), np.array(low)


def solve_bounded(h: np.ndarray, g: np.ndarray, model: str) -> np.ndarray:
    """The ``theta`` minimising ``theta^T h theta / 2 - g^T theta`` (normal equations ``h theta
    = g`` of one weighted least-squares step) within the firmware's ranges of ``model``
    (:func:`bound_constraints`): the unconstrained solution when it lies inside them, else the
    constrained minimum (SLSQP, as MagFit fits with bounds). Raises ``np.linalg.LinAlgError``
    when ``h`` is singular."""
    theta = np.linalg.solve(h, g)
    if model == "offsets":
        return theta
    gm, low = bound_constraints(model, len(theta))
    if np.all(gm @ theta >= low):
        return theta
    from scipy.optimize import minimize  # loaded only when a fit leaves the ranges

    norm = float(np.trace(h)) / len(theta)  # keeps the objective of order 1
    hn, gn = h / norm, g / norm
    start = theta.copy()
    if model == "scale":
        start[0] = np.clip(start[0], *SCALE_RANGE)
    else:
        d = start[:3]
        s = float(np.clip(np.mean(d), *SCALE_RANGE))
        start[:3] = np.clip(d, DIAGONAL_RANGE[0] * s, DIAGONAL_RANGE[1] * s)
        start[3:6] = np.clip(start[3:6], -OFF_DIAGONAL_MAX * s, OFF_DIAGONAL_MAX * s)
    res = minimize(
        lambda x: 0.5 * x @ hn @ x - gn @ x,
        start,
        jac=lambda x: hn @ x - gn,
        constraints=[{"type": "ineq", "fun": lambda x: gm @ x - low, "jac": lambda x: gm}],
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 500},
    )
    return np.asarray(res.x, dtype=np.float64)


FEW_DIRECTIONS_RIDGE = 1e-3
"""Weight of :func:`toward_scale` (relative to the data's mean weight on a matrix term) on a
flight whose field directions spread less than ``min_spread``."""


def toward_scale(h: np.ndarray, model: str, ridge: float) -> np.ndarray:
    """A ridge on a soft-iron fit's normal matrix ``h``: ``ridge`` times its mean diagonal over
    the matrix terms, on the matrix's departure from its scale (each diagonal minus their mean,
    each off-diagonal). On a flight of few directions (:data:`FEW_DIRECTIONS_RIDGE`) a term the
    attitudes turned is determined by the data ~100 to 1, while one they did not turn (the
    vertical row of a flight that stayed level: ``M_zz`` trades with the vertical offset, and
    least squares shrinks it by the noise) stays at the scale model's. Zeros for the other
    models or ``ridge`` 0."""
    out = np.zeros_like(h)
    if model != "soft_iron" or ridge <= 0:
        return out
    lam = ridge * float(np.mean(np.diag(h)[:6]))
    out[:3, :3] = lam * (np.eye(3) - 1.0 / 3.0)  # (d - mean d)^T (d - mean d)
    out[3:6, 3:6] = lam * 2.0 * np.eye(3)  # each off-diagonal is in M twice
    return out


def fit_model(
    raw: np.ndarray,
    target: np.ndarray,
    current: np.ndarray | None,
    model: str,
    huber_k: float = 1.5,
    outlier_k: float = 5.0,
    iterations: int = 20,
    ridge: float = 0.0,
    groups: np.ndarray | None = None,
) -> Fit:
    """Robust (Huber IRLS, outliers beyond ``outlier_k`` robust sigmas rejected) linear fit of
    ``target ~ M raw + b + motor I`` (normal equations: fields in uT and current in A keep them
    well scaled), each step within the firmware's ranges (:func:`solve_bounded`) with the
    ``ridge`` of :func:`toward_scale`; raises ``np.linalg.LinAlgError`` when singular.
    ``groups`` (:func:`_design`): one offset per group (``Fit.offset`` (k, 3)), M and the motor
    term shared."""
    n = len(raw)
    raw, target = raw * UT, target * UT
    a = _design(raw, current, model, groups)
    rhs = target.T.reshape(-1) if model != "offsets" else (target - raw).T.reshape(-1)
    w = np.ones(n)
    keep = np.ones(n, dtype=bool)
    theta = np.zeros(a.shape[1])
    sigma = 0.0
    for _ in range(iterations):
        ww = np.tile(w * keep, 3)
        aw = a * ww[:, None]
        h = aw.T @ a
        theta_new = solve_bounded(h + toward_scale(h, model, ridge), aw.T @ rhs, model)
        r = (rhs - a @ theta_new).reshape(3, n).T
        e = np.linalg.norm(r, axis=1)
        sigma = float(1.4826 * np.median(e[keep])) / np.sqrt(3) * 1.0 + 1e-300
        per_axis = e / np.sqrt(3)
        keep = per_axis <= outlier_k * sigma
        w = np.minimum(1.0, huber_k * sigma / np.maximum(per_axis, 1e-300))
        done = np.allclose(theta_new, theta, rtol=1e-9, atol=1e-9)
        theta = theta_new
        if done:
            break
    ww = np.tile(w * keep, 3)
    r = rhs - a @ theta
    dof = max(int(ww.astype(bool).sum()) - a.shape[1], 1)
    s2 = float(np.sum(ww * r**2) / dof)
    rr = r.reshape(3, n).T[keep]
    rho = 0.0
    if len(rr) > 3:
        num = float(np.sum(rr[1:] * rr[:-1]))
        den = float(np.sum(rr * rr)) or 1.0
        rho = min(max(num / den, 0.0), 0.99)
    inflate = (1 + rho) / (1 - rho)
    h = (a * ww[:, None]).T @ a
    cov = np.linalg.inv(h + toward_scale(h, model, ridge)) * s2 * inflate
    k = 1 if groups is None else int(groups.max()) + 1
    m, offset, motor = _unpack(theta, model, current is not None, k)
    return Fit(
        model, current is not None, m, offset / UT, motor / UT, theta, cov, keep, np.sqrt(s2)
    )


def held_out_rms(
    raw: np.ndarray,
    target: np.ndarray,
    power: np.ndarray | None,
    model: str,
    segments: list[np.ndarray],
    options: Any,
    ridge: float = 0.0,
) -> float:
    """RMS vector residual (T) of ``model`` (with the motor term on ``power`` when given) over
    the held-out ``segments``: each fitted on the others (``options.huber_k``/``outlier_k``),
    scored on itself, beyond 5 medians left out (``ridge``: :func:`toward_scale`). Raises
    ``np.linalg.LinAlgError`` when a fit is singular."""
    sq, cnt = 0.0, 0
    for seg in segments:
        train = np.ones(len(raw), dtype=bool)
        train[seg] = False
        f = fit_model(
            raw[train],
            target[train],
            None if power is None else power[train],
            model,
            options.huber_k,
            options.outlier_k,
            ridge=ridge,
        )
        r = np.linalg.norm(
            f.predict(raw[seg], None if power is None else power[seg]) - target[seg], axis=1
        )
        r = r[r <= np.median(r) * 5 + 1e-300]
        sq += float(np.sum(r**2))
        cnt += len(r)
    return float(np.sqrt(sq / max(cnt, 1)))


def as_flown(before: np.ndarray) -> float:
    """RMS of the vector residuals ``before`` (as flown: no fit, nothing held out), beyond 5
    medians left out as :func:`held_out_rms` leaves them out: the figure a held-out residual
    must be below for the fit to help."""
    r = before[before <= np.median(before) * 5 + 1e-300]
    return float(np.sqrt(np.mean(r**2)))


def heading_deg(q: np.ndarray, body: np.ndarray) -> np.ndarray:
    """Heading (deg from north, NED) of body-frame fields rotated into NED by ``q``."""
    ned = rotate(q, body)
    return np.degrees(np.arctan2(ned[:, 1], ned[:, 0]))


def wrap_deg(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


@dataclass
class FlightSamples:
    """The magnetometer samples within the attitude and GPS streams' span, with what they
    should read: ``raw`` (n, 3) T in the body frame, attitude ``q`` (n, 4), WMM ``ned`` and
    body-frame ``target`` (n, 3) T, ``current`` (n,) A or None, ``throttle`` (n,) 0..1 or None;
    all on the magnetometer's stamps ``t_ns``. ``rotation`` (3x3, body <- sensor) is the turn
    :func:`flight_samples` applied to the logged field (:func:`sensor_rotation`; None: logged
    in the body frame): the logged field is ``raw @ rotation``."""

    t_ns: np.ndarray
    raw: np.ndarray
    q: np.ndarray
    ned: np.ndarray
    target: np.ndarray
    current: np.ndarray | None
    throttle: np.ndarray | None = None
    rotation: np.ndarray | None = None
    compensated: str | None = None
    """The motor compensation the vehicle had switched on while logging (``"current"``,
    ``"throttle"``: ArduPilot ``COMPASS_MOTCT`` 2/1, PX4 ``CAL_MAG_COMP_TYP`` 2/1), None."""
    flown: np.ndarray | None = None
    """(n, 3) T, body frame: the field as the vehicle corrected it while flying, where ``raw``
    is not that (a raw PX4 ``sensor_mag``: its ``CAL_MAGn`` calibration applied as PX4 does,
    :func:`px4_vehicle_calibration`); None: ``raw`` is it (ArduPilot's ``MAG``, PX4's
    ``vehicle_magnetometer``). The baseline of the "as flown" figures and quality checks
    (``metrics.*_as_flown``); the ``*_before`` figures stay those of ``raw``."""

    def as_flown(self) -> np.ndarray:
        """The field as flown (:attr:`flown`, else ``raw``)."""
        return self.raw if self.flown is None else self.flown

    def power(self, source: str | None) -> np.ndarray | None:
        """The motor power signal of ``source`` (``"current"``, ``"throttle"``; None: none)."""
        return None if source is None else getattr(self, source)


def continuous(q: np.ndarray) -> np.ndarray:
    """Quaternions (n, 4) with their signs chosen so that neighbours lie in one hemisphere
    (``q`` and ``-q`` are one rotation; a log's yaw wrapping at +-180 deg flips the sign), so
    that interpolating between neighbours stays near both."""
    if len(q) < 2:
        return q
    flips = np.sign(np.einsum("ij,ij->i", q[1:], q[:-1]))
    flips[flips == 0] = 1.0
    return q * np.concatenate([[1.0], np.cumprod(flips)])[:, None]


def flight_samples(table: pa.Table, mag: SensorData, year: float) -> FlightSamples:
    """:class:`FlightSamples` of ``mag`` (finite magnetometer samples of ``table``, as logged):
    the field turned into the body frame by the table's :func:`sensor_rotation` (as the firmware
    turns it after its calibration), attitude, position, current and throttle interpolated onto
    its stamps, the WMM field of ``year`` at the position, rotated into the body. ValueError (one
    line) when fewer than 50 samples lie within the flight streams or the date precedes the
    model."""
    att = flight_stream(table, "attitude")
    pos = flight_stream(table, "position")
    inside = (mag.t_ns >= max(att.t_ns[0], pos.t_ns[0])) & (
        mag.t_ns <= min(att.t_ns[-1], pos.t_ns[-1])
    )
    if inside.sum() < 50:
        raise ValueError(
            f"{int(inside.sum())} magnetometer samples lie within the attitude and GPS "
            "streams' time span; the fit needs at least 50"
        )
    t_ns, raw = mag.t_ns[inside], mag.values[inside]
    turn = sensor_rotation(table)
    if turn is not None:  # the raw field into the body frame, as the firmware turns it
        raw = raw @ turn.T
    q = interpolate(att.t_ns, continuous(att.values), t_ns)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    trim = attitude_trim(table)
    if trim is not None:  # the vehicle body's attitude -> the board's, where MAG is
        q = turn_by(q, trim)
    lla = interpolate(pos.t_ns, pos.values, t_ns)
    ned = earth_field(lla[:, 0], lla[:, 1], lla[:, 2], year)
    power: dict[str, np.ndarray | None] = {}
    for stream in POWER_SOURCES:
        power[stream] = None
        if has_flight_stream(table, stream):
            sig = flight_stream(table, stream)
            power[stream] = interpolate(sig.t_ns, sig.values[:, 0], t_ns)
    return FlightSamples(
        t_ns,
        raw,
        q,
        ned,
        rotate(q, ned, inverse=True),
        power["current"],
        power["throttle"],
        turn,
        vehicle_compensation(table),
        _px4_flown(table, mag.values[inside], turn, power),
    )


def px4_vehicle_calibration(
    params: dict[str, Any], device_id: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str | None] | None:
    """PX4's calibration of compass ``device_id`` in ``params`` (the ``CAL_MAGn`` slot whose
    ``CAL_MAGn_ID`` it is; None when none is): ``(OFF, S, COMP, source)`` of
    ``sensor_calibration::Magnetometer::Correct``, ``S (raw + COMP P - OFF)`` in the sensor's
    axes, turned into the body after it; ``OFF`` in T, ``S`` symmetric (``SCALE`` diagonal,
    ``ODIAG``), ``COMP`` in T per A (``CAL_MAG_COMP_TYP`` 2/3: ``COMP`` is G/kA) or in T at full
    throttle (1), ``source`` ``"current"``/``"throttle"`` or None (no compensation)."""
    if device_id is None:
        return None
    slot = next(
        (
            n
            for n in range(8)
            if params.get(f"CAL_MAG{n}_ID") not in (None, 0)
            and int(params[f"CAL_MAG{n}_ID"]) == int(device_id)
        ),
        None,
    )
    if slot is None:
        return None
    pre = f"CAL_MAG{slot}_"
    off = np.array([params.get(f"{pre}{a}OFF", 0.0) for a in "XYZ"], dtype=np.float64) * 1e-4
    sm = np.diag([params.get(f"{pre}{a}SCALE", 1.0) or 1.0 for a in "XYZ"]).astype(np.float64)
    od = [params.get(f"{pre}{a}ODIAG", 0.0) for a in "XYZ"]
    sm[0, 1] = sm[1, 0] = od[0]
    sm[0, 2] = sm[2, 0] = od[1]
    sm[1, 2] = sm[2, 1] = od[2]
    comp = np.array([params.get(f"{pre}{a}COMP", 0.0) for a in "XYZ"], dtype=np.float64) * 1e-4
    typ = int(params.get("CAL_MAG_COMP_TYP") or 0)
    source = {1: "throttle", 2: "current", 3: "current"}.get(typ) if comp.any() else None
    if source == "current":
        comp = comp / 1e3  # per kA -> per A
    return off, sm, comp if source else np.zeros(3), source


def _px4_flown(
    table: pa.Table,
    logged: np.ndarray,
    turn: np.ndarray | None,
    power: dict[str, np.ndarray | None],
) -> np.ndarray | None:
    """:attr:`FlightSamples.flown` of a raw PX4 compass (``logged``, T, its own axes): the
    vehicle's ``CAL_MAGn`` calibration applied as PX4 applies it, turned into the body by
    ``turn``; None when the table's field is not a raw PX4 one or no slot holds its device."""
    meta = metadata(table)
    px4 = meta.get("px4") or {}
    if not px4 or (px4.get("calibrated") or {}).get("mag", True):
        return None
    cal = px4_vehicle_calibration(
        px4.get("parameters") or {}, (meta.get("device_id") or {}).get("mag")
    )
    if cal is None:
        return None
    off, sm, comp, source = cal
    signal = power.get(source) if source else None
    x = logged - off if signal is None else logged + signal[:, None] * comp - off
    out = x @ sm.T
    return out if turn is None else out @ turn.T


def vehicle_compensation(table: pa.Table) -> str | None:
    """The motor compensation switched on in the log's parameters (:attr:`FlightSamples.
    compensated`)."""
    meta = metadata(table)
    ap = (meta.get("ardupilot") or {}).get("parameters") or {}
    px4 = (meta.get("px4") or {}).get("parameters") or {}
    kind = ap.get("COMPASS_MOTCT") if ap else px4.get("CAL_MAG_COMP_TYP")
    return {1: "throttle", 2: "current"}.get(int(kind or 0))


class CannotSeparate(ValueError):
    """The flight cannot separate what was asked (the message names what is missing)."""


@dataclass
class FlownFit:
    """What :func:`fit_flight` found on one flight (or on several joined): the chosen ``model``
    and its :class:`Fit`, the motor ``source``, the held-out RMS per candidate (uT), the ``coverage`` of attitudes,
    the terms ``not_fitted`` and why, the ``warnings`` a stage shows, the ``metrics`` (uT, deg),
    each parameter's standard error, and per sample the vector residual (T) and heading error
    (deg) before and after."""

    model: str
    fit: Fit
    source: str | None
    """What the motor term multiplies (``"current"``, ``"throttle"``; None: no motor term)."""
    held_out: dict[str, float]
    coverage: dict[str, Any]
    not_fitted: list[str]
    warnings: list[str]
    metrics: dict[str, Any]
    parameter_se: dict[str, float]
    before: np.ndarray
    after: np.ndarray
    h_before: np.ndarray
    h_after: np.ndarray


def out_of_range(matrix: np.ndarray) -> str:
    """Why the soft-iron ``matrix`` M has no plausible ArduPilot form (empty when it has): M
    as ``COMPASS_SCALE`` (its mean diagonal) times ``DIA``/``ODI`` (as MagFit normalises it),
    each inside :data:`SCALE_RANGE`, :data:`DIAGONAL_RANGE`, :data:`OFF_DIAGONAL_MAX`."""
    scale = float(np.mean(np.diag(matrix)))
    if not SCALE_RANGE[0] <= scale <= SCALE_RANGE[1]:
        return (
            f"scale {scale:.3f} outside {SCALE_RANGE[0]:.3f}..{SCALE_RANGE[1]:g} "
            "(COMPASS_SCALE; a compass this far off is broken or mis-configured)"
        )
    rel = matrix / scale
    diag = np.diag(rel)
    off = rel[np.triu_indices(3, 1)]
    if np.any(diag < DIAGONAL_RANGE[0]) or np.any(diag > DIAGONAL_RANGE[1]):
        return (
            f"soft-iron diagonal {np.round(diag, 3).tolist()} outside "
            f"{DIAGONAL_RANGE[0]:g}..{DIAGONAL_RANGE[1]:g} (COMPASS_DIA over COMPASS_SCALE "
            f"{scale:.3f})"
        )
    if np.any(np.abs(off) > OFF_DIAGONAL_MAX):
        return (
            f"soft-iron off-diagonal {np.round(off, 3).tolist()} outside +-{OFF_DIAGONAL_MAX:g} "
            f"(COMPASS_ODI over COMPASS_SCALE {scale:.3f})"
        )
    return ""


def at_bounds(matrix: np.ndarray) -> str:
    """Which terms of a bounded fit's ``matrix`` sit at the firmware's ranges
    (:func:`bound_constraints`; within twice :data:`BOUND_MARGIN`), empty when none do."""
    scale = float(np.mean(np.diag(matrix)))
    rel = matrix / scale
    tol = 2 * BOUND_MARGIN
    said = []
    if scale <= SCALE_RANGE[0] * (1 + tol) or scale >= SCALE_RANGE[1] * (1 - tol):
        said.append(f"COMPASS_SCALE {scale:.3f}")
    for i, a in enumerate("XYZ"):
        d = rel[i, i]
        if d <= DIAGONAL_RANGE[0] + tol or d >= DIAGONAL_RANGE[1] - tol:
            said.append(f"DIA_{a} {d:.3f}")
    for (i, k), a in zip(((0, 1), (0, 2), (1, 2)), "XYZ", strict=True):
        if abs(rel[i, k]) >= OFF_DIAGONAL_MAX - tol:
            said.append(f"ODI_{a} {rel[i, k]:.3f}")
    return ", ".join(said)


def coverage_of(q: np.ndarray, target: np.ndarray) -> dict[str, Any]:
    """The attitudes a flight covered: the eigenvalues of the covariance of the expected field's
    body directions (``direction_spread``, ascending), the yaw covered in 10 deg bins (deg) and
    the 99th percentile of the tilt (deg)."""
    dirs = target / np.linalg.norm(target, axis=1, keepdims=True)
    spread = np.linalg.eigvalsh(np.cov(dirs.T))
    tilt = np.degrees(np.arccos(np.clip(rotate(q, np.tile([0, 0, 1.0], (len(q), 1)))[:, 2], -1, 1)))
    yaw = heading_deg(q, np.tile([1.0, 0, 0], (len(q), 1)))
    yaw_cover = float(np.count_nonzero(np.histogram(yaw, bins=36, range=(-180, 180))[0])) * 10
    return {
        "direction_spread": [float(v) for v in spread],
        "yaw_coverage_deg": yaw_cover,
        "tilt_max_deg": float(np.percentile(tilt, 99)),
    }


def fit_flight(  # noqa: C901
    fs: FlightSamples, o: Any, flights: list[int] | None = None
) -> FlownFit:
    """The in-flight compass fit of the module docstring on ``fs``, under ``o`` (the stage's
    :class:`MagInflightStage.Options` or any object with its fields): what the flight can
    separate, the model chosen on held-out segments, the motor source (current or throttle,
    held-out 2 % rule), the final robust fit and its figures. ``fs`` is in the body frame
    (:func:`flight_samples` turns a raw PX4 field by :func:`sensor_rotation`).
    :class:`CannotSeparate` when the model or motor term asked for cannot be separated, or every
    candidate is singular. One implementation for the stage and for ``imupipe survey``.

    ``flights``: the sample counts of the flights ``fs`` joins, in order (several flights of
    one vehicle fitted together): the held-out segments are then the flights themselves, each
    candidate fitted on the others and scored on the one left out, so that the model and the
    motor term chosen are those that carry from one flight to another (time segments of one
    flight share its attitude errors and its pattern of turns); None or one flight:
    ``o.folds`` time segments."""
    raw, q, ned, target = fs.raw, fs.q, fs.ned, fs.target

    # -- what the flight can separate ----------------------------------------------------
    coverage = coverage_of(q, target)
    spread = coverage["direction_spread"]
    yaw_cover = coverage["yaw_coverage_deg"]
    reasons: list[str] = []
    can_soft = bool(spread[0] >= o.min_spread)
    if not can_soft:
        reasons.append(
            f"soft iron: the field's body directions spread {spread[0]:.3g} < min_spread "
            f"{o.min_spread:g} (yaw covered {yaw_cover:.0f} deg, tilt to "
            f"{coverage['tilt_max_deg']:.0f} deg): fly full turns and steeper banks"
        )
    separable: dict[str, bool] = {}
    minimum = {
        "current": (o.min_current_a, "A", "min_current_a"),
        "throttle": (o.min_throttle, "", "min_throttle"),
    }
    wanted = POWER_SOURCES if o.motor_source == "auto" else (o.motor_source,)
    for src in wanted:
        sig = fs.power(src)
        if sig is None:
            continue
        lo, hi = np.percentile(sig, [5, 95])
        corr = max(abs(np.corrcoef(sig, target[:, i])[0, 1]) for i in range(3)) if hi > lo else 1.0
        least, unit, key = minimum[src]
        separable[src] = bool(hi - lo >= least and corr < 0.95)
        if not separable[src]:
            reasons.append(
                f"motor: the {src} spans {hi - lo:.2g}{unit} ({key} {least:g}) or follows "
                f"the field direction (|r| {corr:.2f})"
            )
    if not separable:
        what = {
            "auto": "no battery current and no throttle",
            "current": "no battery current",
            "throttle": "no throttle (CTUN.ThO, vehicle_thrust_setpoint)",
        }[o.motor_source]
        reasons.append(f"motor: the log has {what}")
    motor_reasons = [r for r in reasons if r.startswith("motor")]
    usable = [src for src, ok in separable.items() if ok]
    if o.model == "soft_iron" and not can_soft:
        raise CannotSeparate("cannot separate " + reasons[0])
    if o.motor == "on" and not usable:
        raise CannotSeparate("cannot separate " + "; ".join(motor_reasons))
    if usable:  # a source that could not be used while another is: not worth a warning
        reasons = [r for r in reasons if r not in motor_reasons]
    warnings = ["not fitted: " + r for r in reasons]
    source = usable[0] if usable and o.motor != "off" else None
    power = fs.power(source)
    can_scale = bool(spread[-1] >= o.min_spread)
    if not can_scale:
        reasons.append(
            f"scale: the field's body direction hardly changed (largest spread "
            f"{spread[-1]:.3g} < min_spread {o.min_spread:g}): only offsets are fitted"
        )
    if o.model == "scale" and not can_scale:
        raise CannotSeparate("cannot separate " + reasons[-1])
    if o.model == "auto":
        # soft iron on few directions too: held to the firmware's ranges (as MagFit bounds it)
        # and kept only when it wins on held-out segments (erle_pxf_218's and forum13645's
        # first 60 %: tilt to 10-12 deg; refused before, their held-out residual lost to MagFit)
        candidates = ["offsets"] + ["scale"] * can_scale + ["soft_iron"] * can_scale
    else:
        candidates = [o.model]

    # -- model choice on held-out segments -----------------------------------------------
    held: dict[str, float] = {}
    ridge = 0.0 if can_soft else FEW_DIRECTIONS_RIDGE  # unturned terms kept at the scale's
    if flights is not None and len(flights) > 1:
        cuts = np.cumsum([0, *flights])
        segments = [np.arange(a, b) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    else:
        segments = np.array_split(np.arange(len(raw)), o.folds)
    for model in candidates:
        try:
            whole = fit_model(raw, target, power, model, o.huber_k, o.outlier_k, ridge=ridge)
            held[model] = held_out_rms(raw, target, power, model, segments, o, ridge)
        except np.linalg.LinAlgError:
            continue
        wrong = out_of_range(whole.matrix)
        if wrong:
            del held[model]
            reasons.append(f"{model}: {wrong}")
            if o.model != "auto":
                raise CannotSeparate(f"{model}: {wrong}")
            warnings.append(f"not fitted: {model}: {wrong}")
    if not held:
        raise CannotSeparate("every candidate model is singular on this flight")
    best = min(held.values())
    chosen = next(m for m in candidates if m in held and held[m] <= best * 1.02)
    if chosen == "soft_iron" and not can_soft:  # not refused after all: say on what it stands
        gone = next(r for r in reasons if r.startswith("soft iron"))
        reasons.remove(gone)
        warnings.remove("not fitted: " + gone)
        warnings.append(
            f"soft iron fitted on few directions (spread {spread[0]:.3g} < min_spread "
            f"{o.min_spread:g}, yaw covered {yaw_cover:.0f} deg, tilt to "
            f"{coverage['tilt_max_deg']:.0f} deg): held to ArduPilot's ranges and chosen on "
            f"held-out segments ({held['soft_iron'] * UT:.3g} uT against "
            + ", ".join(f"{m} {v * UT:.3g}" for m, v in held.items() if m != "soft_iron")
            + ")"
        )

    # -- the motor term: kept only when it lowers the held-out residual ---------------------
    held_source: dict[str, float] = {}
    if source is not None and o.motor == "auto" and source != fs.compensated:
        held_source[source] = held[chosen]
        try:
            held_source["none"] = held_out_rms(raw, target, None, chosen, segments, o, ridge)
        except np.linalg.LinAlgError:
            held_source["none"] = np.inf
        margin = 0.02 if source == "throttle" else 0.0  # the throttle is a proxy: 2 %
        if held_source[source] >= held_source["none"] * (1 - margin):
            reasons.append(
                f"motor: a {source} term does not lower the held-out residual"
                + (" by 2 %" if margin else "")
                + " "
                f"({held_source[source] * UT:.3g} uT with it, "
                f"{held_source['none'] * UT:.3g} uT without)"
            )
            warnings.append("not fitted: " + reasons[-1])
            source, power = None, None
    fit = fit_model(raw, target, power, chosen, o.huber_k, o.outlier_k, ridge=ridge)
    bounded = at_bounds(fit.matrix) if chosen != "offsets" else ""
    if bounded:
        warnings.append(f"{chosen} held at ArduPilot's ranges: {bounded}")

    before = np.linalg.norm(raw - target, axis=1)
    flown = fs.as_flown()  # the vehicle's own calibration (a raw PX4 compass's CAL_MAGn)
    r_flown = before if fs.flown is None else np.linalg.norm(flown - target, axis=1)
    corrected = fit.predict(raw, power)
    after = np.linalg.norm(corrected - target, axis=1)
    h_model = heading_deg(q, target)
    h_before = wrap_deg(heading_deg(q, raw) - h_model)
    h_flown = h_before if fs.flown is None else wrap_deg(heading_deg(q, flown) - h_model)
    h_after = wrap_deg(heading_deg(q, corrected) - h_model)
    se = np.sqrt(np.diag(fit.cov))
    ut = UT
    metrics = {
        "residual_rms_ut_before": float(np.sqrt(np.mean(before**2)) * ut),
        "residual_rms_ut_after": float(np.sqrt(np.mean(after**2)) * ut),
        "residual_rms_ut_after_inliers": float(np.sqrt(np.mean(after[fit.used] ** 2)) * ut),
        "heading_rms_deg_before": float(np.sqrt(np.mean(h_before**2))),
        "heading_rms_deg_after": float(np.sqrt(np.mean(h_after**2))),
        "held_out_rms_ut": {m: v * ut for m, v in held.items()},
        "held_out_rms_ut_as_flown": as_flown(r_flown) * ut,
        "residual_rms_ut_as_flown": float(np.sqrt(np.mean(r_flown**2)) * ut),
        "heading_rms_deg_as_flown": float(np.sqrt(np.mean(h_flown**2))),
        "heading_rms_deg_after_inliers": float(np.sqrt(np.mean(h_after[fit.used] ** 2))),
        "heading_rms_deg_as_flown_inliers": float(np.sqrt(np.mean(h_flown[fit.used] ** 2))),
        "held_out_on": "flights" if flights is not None and len(flights) > 1 else "time",
        **(
            {"held_out_rms_ut_motor_source": {k: v * ut for k, v in held_source.items()}}
            if held_source
            else {}
        ),
        "outliers": int(len(raw) - fit.used.sum()),
        "samples": len(raw),
        "field_ut": float(np.mean(np.linalg.norm(ned, axis=1)) * ut),
    }
    names = parameter_names(chosen, fit.motor_term, source or "current")
    return FlownFit(
        chosen,
        fit,
        source if fit.motor_term else None,
        held,
        coverage,
        reasons,
        warnings,
        metrics,
        dict(zip(names, se.tolist(), strict=True)),
        before,
        after,
        h_before,
        h_after,
    )


def offset_covariance(fit: Fit) -> np.ndarray:
    """(3, 3) covariance of ``fit.offset`` (T^2): ``offset = -M^-1 b`` propagated from the
    covariance of ``theta`` through its Jacobian (central differences on ``theta``)."""
    k = {"offsets": 0, "scale": 1, "soft_iron": 6}[fit.model]
    if k == 0:
        return fit.cov[:3, :3] / UT**2
    jac = np.zeros((3, len(fit.theta)))
    for j in range(k + 3):  # the offset depends on the M terms and on b only
        h = 1e-6 * max(abs(fit.theta[j]), 1.0)
        up, down = fit.theta.copy(), fit.theta.copy()
        up[j] += h
        down[j] -= h
        jac[:, j] = (
            _unpack(up, fit.model, fit.motor_term)[1] - _unpack(down, fit.model, fit.motor_term)[1]
        ) / (2 * h)
    return jac @ fit.cov @ jac.T / UT**2


OFFSET_STEP_K = 5.0
"""Flights fitted together disagree when their offsets differ by more than this many standard
errors on some axis (:func:`offset_steps`; the survey's default ``k``)..."""
OFFSET_STEP_FRACTION = 0.2
"""... and by more than this fraction of the earth field in all. Flights of one calibration
differ by the attitude and model errors of each: the three real PX4 flights of
``px4_flights_flugdrohne`` (48.8 uT), fitted in pairs (:func:`flight_offsets`), 1.7 to 5.0 uT
(4 to 10 % of the field) between flights of one day and the external compass's 2.1 to 3.5 uT
across two weeks, but 24 to 26 uT (49 to 53 %) across the internal compass's change between
7 and 21 June. An offset error of a fifth of the field turns the heading by up to ``asin(0.2
F / H)`` (28 deg at that site's 64 deg inclination): no calibration serves both sides."""


def flight_offsets(
    fs: FlightSamples, flown: FlownFit, counts: list[int], o: Any
) -> tuple[np.ndarray, np.ndarray]:
    """Each joined flight's own offset (T, (k, 3), body frame) and their covariance (T^2,
    (3k, 3k)): the chosen model refitted (:func:`fit_model`, options ``o``, the motor term
    of ``flown``) with one soft-iron matrix and motor term for all and one offset per flight
    (``groups``), the covariance of the ``b`` terms carried through ``M^-1`` (the matrix
    shared: its own uncertainty moves every flight's offset alike)."""
    groups = np.repeat(np.arange(len(counts)), counts)
    can_soft = flown.coverage["direction_spread"][0] >= o.min_spread
    fit = fit_model(
        fs.raw,
        fs.target,
        fs.power(flown.source),
        flown.model,
        o.huber_k,
        o.outlier_k,
        ridge=0.0 if can_soft else FEW_DIRECTIONS_RIDGE,
        groups=groups,
    )
    k = {"offsets": 0, "scale": 1, "soft_iron": 6}[flown.model]
    nb = 3 * len(counts)
    m_inv = np.kron(np.eye(len(counts)), np.linalg.inv(fit.matrix))
    cov = m_inv @ fit.cov[k : k + nb, k : k + nb] @ m_inv.T / UT**2
    return fit.offset, cov


def offset_steps(
    offsets: np.ndarray, cov: np.ndarray, field_t: float, order: list[int]
) -> list[tuple[int, int, np.ndarray, float]]:
    """``(i, j, d, limit)`` for each pair of flights consecutive in ``order`` (their dates)
    whose offsets (:func:`flight_offsets`, T) differ by ``d = o_j - o_i`` beyond what attitude
    and model errors move a fitted offset: more than :data:`OFFSET_STEP_K` standard errors of
    ``d`` on some axis and ``|d|`` above :data:`OFFSET_STEP_FRACTION` of the earth field
    ``field_t`` (``limit``, T). A step in the compass's hard iron between them (a part, wiring
    or payload moved near the compass, or magnetised)."""
    out = []
    for i, j in zip(order[:-1], order[1:], strict=True):
        d = offsets[j] - offsets[i]
        si, sj = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
        var = np.diag(cov[si, si] + cov[sj, sj] - cov[si, sj] - cov[sj, si])
        if hard_iron_stepped(d, np.sqrt(np.maximum(var, 0.0)), field_t):
            out.append((i, j, d, OFFSET_STEP_FRACTION * field_t))
    return out


def hard_iron_stepped(d: np.ndarray, se: np.ndarray, field: float) -> bool:
    """Whether an offset change ``d`` (3,) with standard errors ``se`` (3,) is a step of the
    hard iron no one calibration can serve across: beyond :data:`OFFSET_STEP_K` standard errors
    on some axis and above :data:`OFFSET_STEP_FRACTION` of the earth field ``field`` in all
    (any one unit for the three)."""
    d, se = np.asarray(d, dtype=np.float64), np.asarray(se, dtype=np.float64)
    beyond = np.abs(d) > OFFSET_STEP_K * se
    return bool(np.any(beyond)) and float(np.linalg.norm(d)) > OFFSET_STEP_FRACTION * field


@dataclass
class MagCurrentStep(LinearStep):
    """``corrected = matrix @ (raw - offset) + motor * I(t)``: a linear step plus a field per
    ampere of battery current (``motor``, T/A), the current being the table's ``current``
    flight stream interpolated onto the magnetometer's stamps (no current stream: the term is
    left out)."""

    kind: ClassVar[str] = "mag_current"
    arrays: ClassVar[tuple[str, ...]] = ("matrix", "offset", "motor")
    stream: ClassVar[str] = "current"
    """The flight stream the motor term multiplies."""
    motor: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        super().__post_init__()
        self.motor = np.asarray(self.motor, dtype=np.float64).reshape(3)

    def apply(self, table: pa.Table) -> pa.Table:
        from imupipe.readers.table import replace_sensor

        if not has_stream(table, "mag"):
            return table
        data = sensor(table, "mag")
        out = self.apply_values(data.values)
        if has_flight_stream(table, self.stream):
            sig = flight_stream(table, self.stream)
            out = out + interpolate(sig.t_ns, sig.values[:, 0], data.t_ns)[:, None] * self.motor
        return replace_sensor(table, "mag", data.rows, out)

    def to_json(self) -> dict[str, Any]:
        return {**super().to_json(), "motor": self.motor.tolist()}

    @classmethod
    def check_entry(cls, entry: dict[str, Any]) -> None:
        super().check_entry(entry)
        if _numbers(entry.get("motor"), (3,)) is None:
            raise EntryError("motor", f"3 numbers expected, got {_short(entry.get('motor'))}")


@dataclass
class MagThrottleStep(MagCurrentStep):
    """``corrected = matrix @ (raw - offset) + motor * thr(t)``: as :class:`MagCurrentStep`, the
    motor term per unit of collective throttle (``motor``, T at full throttle), the throttle
    being the table's ``throttle`` flight stream (0..1; none: the term is left out)."""

    kind: ClassVar[str] = "mag_throttle"
    stream: ClassVar[str] = "throttle"


STEP_BY_SOURCE: dict[str, type[MagCurrentStep]] = {
    "current": MagCurrentStep,
    "throttle": MagThrottleStep,
}
"""The correction step of each motor source."""


def sensor_rotation(table: pa.Table) -> np.ndarray | None:
    """The rotation (3x3, body <- sensor) the firmware applies to the table's raw magnetometer
    after its calibration, as the reader found it in the log (a PX4 ``sensor_mag``:
    ``CAL_MAGn_ROT`` or ``SENS_BOARD_ROT`` with ``SENS_BOARD_*_OFF``); None when the field is
    already in the body frame (an ArduPilot ``MAG``, a PX4 ``vehicle_magnetometer``) or the log
    declares none. The fit runs on the field turned by it, and the correction step includes it."""
    px4 = metadata(table).get("px4") or {}
    turn = ((px4.get("rotation") or {}).get("mag") or {}).get("matrix")
    if turn is None:
        return None
    m = np.asarray(turn, dtype=np.float64).reshape(3, 3)
    return None if np.allclose(m, np.eye(3), atol=1e-12) else m


def turn_by(q: np.ndarray, trim: tuple[float, float]) -> np.ndarray:
    """``q (x) q_y(trim[1]) q_x(trim[0])``: attitudes (n, 4; w, x, y, z; body -> NED) followed
    by the body-fixed turn of roll ``trim[0]`` and pitch ``trim[1]`` (rad), yaw 0."""
    cr, sr = np.cos(trim[0] / 2), np.sin(trim[0] / 2)
    cp, sp = np.cos(trim[1] / 2), np.sin(trim[1] / 2)
    bw, bx, by, bz = cr * cp, sr * cp, cr * sp, -sr * sp
    aw, ax, ay, az = q.T
    return np.column_stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def attitude_trim(table: pa.Table) -> tuple[float, float] | None:
    """ArduPilot's ``AHRS_TRIM_X``/``_Y`` (rad) of the log, or None when absent or zero.

    ArduPilot logs the vehicle body's attitude (``ATT``; the EKFs' ``NKF1``/``XKF1`` Euler
    angles have the trim subtracted too), while its compass and IMU are in the autopilot
    board's frame (already turned by ``AHRS_ORIENTATION`` and ``COMPASS_ORIENT``, so those
    need nothing more): ``AP_AHRS`` builds ``_rotation_autopilot_body_to_vehicle_body =
    from_euler(trim.x, trim.y, 0)`` and ``body_dcm = dcm * (that)^T``, so the board's attitude
    is ``R_board = R_att from_euler(trim.x, trim.y, 0)`` (``AHRS_TRIM_Z`` is not used). MagFit
    (``magfit_WMM.py``) adds the trims to the logged roll and pitch for the same reason. A
    trim of 2 deg left out tilts the expected field by 2 deg: ~17 mG of a 500 mG field."""
    params = (metadata(table).get("ardupilot") or {}).get("parameters") or {}
    trim = (float(params.get("AHRS_TRIM_X") or 0.0), float(params.get("AHRS_TRIM_Y") or 0.0))
    return trim if any(trim) else None


def _compass_parameters(table: pa.Table) -> dict[str, float]:
    """The compass parameters (``COMPASS_*``) a log was recorded under (an ArduPilot log's)."""
    params = (metadata(table).get("ardupilot") or {}).get("parameters") or {}
    return {k: v for k, v in params.items() if k.startswith("COMPASS_")}


class MagInflightStage(Stage):
    type = "mag_inflight"
    sensors = ("mag",)
    corrects = True

    @dataclass
    class Options:
        model: Literal["auto", "offsets", "scale", "soft_iron"] = "auto"
        """``auto`` (chosen on held-out flight segments) or one model."""
        motor: Literal["auto", "on", "off"] = "auto"
        """The motor term: ``auto`` (fitted when the current or the throttle varies), ``on``
        (refused when the flight cannot separate it) or ``off``."""
        motor_source: Literal["auto", "current", "throttle"] = "auto"
        """What the motor term multiplies: the battery current (per ampere: ArduPilot
        ``COMPASS_MOTCT = 2``, PX4 ``CAL_MAG_COMP_TYP = 2``), the collective throttle (per unit
        of throttle 0..1: ``COMPASS_MOTCT = 1``, ``CAL_MAG_COMP_TYP = 1``; for vehicles without
        a current sensor), or ``auto``: the one logged, and when both are, the current unless the
        throttle's held-out residual is more than 2 % lower (module docstring)."""
        year: float | None = None
        """The flight's date as a decimal year (WMM epoch); default: the log's GPS date."""
        folds: int = field(default=5, metadata={"min": 2, "max": 50})
        """Held-out time segments for the model choice (with ``flights``: the flights are the
        segments)."""
        huber_k: float = field(default=1.5, metadata={"min": 0.1})
        """Huber weights beyond this many robust sigmas of the per-axis residual."""
        outlier_k: float = field(default=5.0, metadata={"min": 1.0})
        """Samples beyond this many robust sigmas are rejected (left out of the fit)."""
        min_spread: float = field(default=0.002, metadata={"min": 0.0})
        """Smallest eigenvalue of the expected field directions' covariance for a free soft
        iron; below it, ``model = "soft_iron"`` is refused and ``auto`` holds the terms the
        flight did not turn at the scale model's (module docstring)."""
        min_current_a: float = field(default=2.0, metadata={"min": 0.0})
        """Current range (A, 5-95 %) below which the motor term cannot be fitted."""
        min_throttle: float = field(default=0.1, metadata={"min": 0.0, "max": 1.0})
        """Throttle range (0..1, 5-95 %) below which a throttle-based motor term cannot be
        fitted."""
        max_residual_ut: float = field(default=5.0, metadata={"min": 0.0})
        """Quality check: RMS vector residual after the fit, uT."""
        flights: list[str] = field(default_factory=list)
        """Other inputs: flights of the same vehicle (same compass, same mounting, and the same
        compass parameters in force when logged) fitted together with this stage's input, one
        calibration for all; each flight at its own position and date. The model and the
        motor term are then chosen on held-out flights (each fitted on the others, scored on
        itself), not on time segments, and flights whose own offsets stepped between their
        dates (the hard iron changed) are refused by name (:func:`offset_steps`)."""

    def _samples(self, table: pa.Table, name: str, ctx: StageContext) -> FlightSamples:
        """The :class:`FlightSamples` of input ``name`` (``table``); refused (one line naming
        the input) when a stream or the date is missing."""
        o: MagInflightStage.Options = self.options
        where = "the log" if name == ctx.input_name else f"input '{name}'"
        missing = [s for s in ("attitude", "position") if not has_flight_stream(table, s)]
        if not has_stream(table, "mag"):
            missing.insert(0, "magnetometer")
        if missing:
            seen = metadata(table).get("mag_candidates") or []
            which = (
                f"; it has several compasses ({', '.join(seen)}) and read none: set mag_topic, "
                'or instances = "all" on the input to fit each'
                if seen and missing[0] == "magnetometer"
                else ""
            )
            raise ctx.fail(
                f"{where} has no " + ", ".join(missing) + " (an in-flight compass fit needs the "
                "magnetometer, the attitude and a GPS position: DataFlash MAG, ATT, GPS; ULog "
                f"sensor_mag, vehicle_attitude, vehicle_gps_position){which}"
            )
        mag = ctx.finite(sensor(table, "mag"), f"magnetometer of {where}", minimum=50)
        year = o.year if o.year is not None else metadata(table).get("gps_year")
        if year is None:
            raise ctx.fail(
                f"the flight's date is unknown ({where} has no GPS week and time): set year "
                "(decimal, e.g. 2016.4) in this stage"
            )
        try:
            return flight_samples(table, mag, float(year))
        except ValueError as exc:
            raise ctx.fail(f"{where}: {exc}") from None

    def _joint(self, table: pa.Table, ctx: StageContext) -> tuple[FlightSamples, list[int]]:
        """This input's samples followed by those of every input in ``flights`` (one fit), and
        each flight's sample count. Refused when an input is unknown or was logged under other
        compass parameters than this one (its field is not the same function of the raw one)."""
        o: MagInflightStage.Options = self.options
        parts = [self._samples(table, ctx.input_name, ctx)]
        mine = _compass_parameters(table)
        turn = sensor_rotation(table)
        for name in o.flights:
            if name == ctx.input_name or name not in ctx.tables:
                raise ctx.fail(
                    f"flights: '{name}' is not another input (inputs: {', '.join(ctx.tables)})"
                )
            other = ctx.tables[name]
            theirs = _compass_parameters(other)
            differ = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            if differ:
                raise ctx.fail(
                    f"flights: input '{name}' was logged under other compass parameters "
                    f"({', '.join(differ[:4])}{'...' if len(differ) > 4 else ''} differ): fit "
                    "flights of one calibration together"
                )
            theirs_turn = sensor_rotation(other)
            if (turn is None) != (theirs_turn is None) or (
                turn is not None and not np.allclose(turn, theirs_turn, atol=1e-9)
            ):
                raise ctx.fail(
                    f"flights: input '{name}' turns its magnetometer into the body otherwise "
                    "(CAL_MAGn_ROT, SENS_BOARD_ROT, SENS_BOARD_*_OFF differ): fit flights of one "
                    "mounting together"
                )
            parts.append(self._samples(other, name, ctx))
        counts = [len(p.t_ns) for p in parts]
        if len(parts) == 1:
            return parts[0], counts
        power: dict[str, np.ndarray | None] = {}
        for source in POWER_SOURCES:
            signals = [p.power(source) for p in parts]
            power[source] = None if any(c is None for c in signals) else np.concatenate(signals)
        if all(v is None for v in power.values()):
            ctx.warn(
                "flights: not every flight has a battery current or a throttle; the motor term "
                "is left out"
            )
        joined = FlightSamples(
            *(np.concatenate([getattr(p, k) for p in parts]) for k in ("t_ns", "raw", "q")),
            *(np.concatenate([getattr(p, k) for p in parts]) for k in ("ned", "target")),
            power["current"],
            power["throttle"],
            turn,
            parts[0].compensated,  # one calibration: the flights' compass parameters agree
            None
            if all(p.flown is None for p in parts)
            else np.concatenate([p.as_flown() for p in parts]),
        )
        return joined, counts

    def _flights_agree(
        self,
        table: pa.Table,
        ctx: StageContext,
        fs: FlightSamples,
        flown: FlownFit,
        counts: list[int],
    ) -> None:
        """Each joined flight's own offsets under the joint calibration into
        ``metrics.flights.<name>`` (``offset_ut``, ``offset_se_ut``: :func:`flight_offsets`),
        and the quality check that they agree: flights whose offsets stepped between their dates
        (:func:`offset_steps`) are named with the step (uT and mG), since one calibration
        cannot serve both (the joint fit's other checks would blame its size or its held-out
        residual)."""
        o: MagInflightStage.Options = self.options
        names = [ctx.input_name, *o.flights]
        try:
            offsets, cov = flight_offsets(fs, flown, counts, o)
        except np.linalg.LinAlgError:  # a flight left with no sample the fit keeps
            ctx.warn("flights: each flight's own offsets could not be fitted; not compared")
            return
        se = np.sqrt(np.diag(cov)).reshape(-1, 3)
        flights = flown.metrics["flights"]
        for name, off, s in zip(names, offsets, se, strict=True):
            flights[name]["offset_ut"] = (off * UT).tolist()
            flights[name]["offset_se_ut"] = (s * UT).tolist()
        years = [
            o.year
            if o.year is not None
            else metadata(table if n == ctx.input_name else ctx.tables[n]).get("gps_year")
            for n in names
        ]
        order = sorted(range(len(names)), key=lambda i: (years[i] is None, years[i] or 0.0))
        field_t = flown.metrics["field_ut"] / UT
        said = []
        for i, j, d, limit in offset_steps(offsets, cov, field_t, order):
            when = [
                f"'{names[k]}'" + ("" if years[k] is None else f" ({date_of(years[k])})")
                for k in (i, j)
            ]
            size = float(np.linalg.norm(d))
            said.append(
                "("
                + ", ".join(f"{v * UT:+.1f}" for v in d)
                + f") uT in the body axes ({size * UT:.1f} uT = "
                f"{size * 1e7:.0f} mG, {100 * size / field_t:.0f} % of the field) between "
                f"{when[0]} and {when[1]}; limit {limit * UT:.1f} uT "
                f"({100 * OFFSET_STEP_FRACTION:.0f} % of the field) and "
                f"{OFFSET_STEP_K:g} standard errors"
            )
        ctx.check(
            not said,
            "flights: the compass's offsets moved by "
            + "; by ".join(said)
            + ": its hard iron changed (a part, wiring or payload moved near the compass, or "
            "something magnetised), and one calibration cannot serve flights on both sides: "
            "fit together only the flights since the change",
        )

    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        o: MagInflightStage.Options = self.options
        fs, counts = self._joint(table, ctx)
        try:
            flown = fit_flight(fs, o, counts)
        except CannotSeparate as exc:
            raise ctx.fail(str(exc)) from None
        for w in flown.warnings:
            ctx.warn(w)
        t_ns, current, source = fs.t_ns, fs.current, flown.source
        fit, chosen, metrics = flown.fit, flown.model, flown.metrics
        before, after, h_before, h_after = flown.before, flown.after, flown.h_before, flown.h_after
        ut = UT
        if o.flights:  # each flight's residual under the one joint calibration
            names = [ctx.input_name, *o.flights]
            cuts = np.cumsum([0, *counts])
            metrics["flights"] = {
                name: {
                    "samples": int(b - a),
                    "residual_rms_ut_before": float(np.sqrt(np.mean(before[a:b] ** 2)) * ut),
                    "residual_rms_ut_after": float(np.sqrt(np.mean(after[a:b] ** 2)) * ut),
                    "heading_rms_deg_after": float(np.sqrt(np.mean(h_after[a:b] ** 2))),
                }
                for name, a, b in zip(names, cuts[:-1], cuts[1:], strict=True)
            }
            self._flights_agree(table, ctx, fs, flown, counts)
        field_ut = metrics["field_ut"]
        ctx.check(
            float(np.linalg.norm(fit.offset)) * ut <= field_ut,
            f"offsets {np.linalg.norm(fit.offset) * ut:.1f} uT exceed the Earth's field "
            f"{field_ut:.1f} uT (a compass's own hard iron is smaller; is the attitude, the "
            "compass or the flight's GPS span wrong?)",
        )
        held_fit = metrics["held_out_rms_ut"][chosen]
        ctx.check(
            held_fit < metrics["held_out_rms_ut_as_flown"],
            f"held-out residual {held_fit:.2f} uT not below as flown "
            f"{metrics['held_out_rms_ut_as_flown']:.2f} uT (the fit does not help on data it "
            "did not see)",
        )
        kept = f" (the {metrics['samples'] - metrics['outliers']} samples the fit kept)"
        ctx.check(
            metrics["heading_rms_deg_after_inliers"] <= metrics["heading_rms_deg_as_flown_inliers"],
            f"heading error {metrics['heading_rms_deg_after_inliers']:.2f} deg RMS after, above "
            f"{metrics['heading_rms_deg_as_flown_inliers']:.2f} deg as flown"
            + (kept if metrics["outliers"] else ""),
        )
        ctx.check(
            metrics["residual_rms_ut_after"] <= o.max_residual_ut,
            f"residual {metrics['residual_rms_ut_after']:.2f} uT > max_residual_ut "
            f"{o.max_residual_ut:g} uT",
        )
        results: dict[str, Any] = {
            "model": chosen,
            "motor_term": fit.motor_term,
            "motor_source": source if fit.motor_term else None,
            "matrix": fit.matrix.tolist(),
            "offset_t": fit.offset.tolist(),
            "motor_t_per_a": (fit.motor if source == "current" else np.zeros(3)).tolist(),
            **(
                {"motor_t_per_throttle": fit.motor.tolist()}
                if fit.motor_term and source == "throttle"
                else {}
            ),
            "parameter_se": flown.parameter_se,
            "year": float(o.year if o.year is not None else metadata(table)["gps_year"]),
            "coverage": flown.coverage,
            "not_fitted": flown.not_fitted,
            "metrics": metrics,
        }
        if ctx.recorder.enabled:
            rec = ctx.recorder
            own = slice(0, counts[0])  # along this input's flight (others: their own times)
            rec.series(
                f"/{ctx.name}/heading_error",
                t_ns[own],
                np.column_stack([h_before[own], h_after[own]]),
                ["heading error before", "heading error after"],
                unit="deg",
                title="heading error against the WMM",
            )
            shown = source or ("current" if current is not None else None)
            if shown is not None:
                rec.curve(
                    f"/{ctx.name}/residual_vs_{shown}",
                    fs.power(shown),
                    np.column_stack([before, after]),
                    ["residual before", "residual after"],
                    unit="T",
                    x_label=shown,
                    x_unit="A" if shown == "current" else "1",
                    points=True,
                    title="vector residual",
                )
        turn = fs.rotation
        if turn is not None:  # corrected = M (R raw - o) + motor P = (M R) (raw - R^T o) + ...
            results["sensor_rotation"] = turn.tolist()
        step = STEP_BY_SOURCE[source or "current"](
            type=self.type,
            sensor="mag",
            matrix=fit.matrix if turn is None else fit.matrix @ turn,
            offset=fit.offset if turn is None else turn.T @ fit.offset,
            motor=fit.motor,
            params={"model": chosen},
        )
        return StageOutput(results=results, step=step)
