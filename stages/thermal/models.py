"""Temperature error models: every model is linear in named terms, ``bias = sum_j c_j term_j``.

Variables (degC, degC/s): ``T`` = measured temperature - Tref, ``dT`` = its rate dT/dt,
``Ta`` = ambient temperature - Tref, ``dTa`` = its rate, ``Ts`` = the sensing element's
temperature (a first-order lag of the measured one, :mod:`imupipe.stages.thermal.track`) - Tref,
``dTs`` = its rate. A term is ``1``, a variable, or a product of powers of variables written
``T^2``, ``T*dT``, ``Ta^2*dT`` ...; ``hat<i>`` is the i-th piecewise-linear "hat" function of
``T`` on the knots of the piecewise model (1 at knot i, 0 at its neighbours), so a sum of hats is
a continuous function linear between knots.

Models (the ``temperature`` stage's ``model`` option):

- ``poly``: ``1, T, ..., T^order`` plus optional rate terms ``dT``, ``dT^2``, ``T*dT`` (PX4's
  cubic about a reference temperature when order = 3 and no rate term);
- ``lag``: ``1, Ts, ..., Ts^order`` plus optionally ``dTs``, with the lag's time constant fitted
  (:func:`fit_lag`): the gyro patent "陀螺仪的温度标定补偿方法、装置、设备及介质" (2023) names the
  mechanism, a sensing element whose temperature lags the board's temperature sensor, so that
  heating and cooling read differently at the same measured temperature;
- ``six_term``: the six-term model ``a1 T^2 + a2 T + a3 dT^2 + a4 dT + a5 T dT + a6`` of the
  MATLAB ``lsqcurvefit`` example in "MEMS 惯性测量组件的温度误差补偿模型研究" (the Chinese
  paper on temperature error compensation models of MEMS IMUs);
- ``piecewise``: the gyro patent's model: hats on knots every ``segment_width`` degC across the
  fitted range (bias linear in T within each temperature segment, continuous at the knots),
  fitted first; then the hysteresis term ``k_dt * dT + constant`` fitted on the residual (the
  patent's ``k_dt = polyfit(gy_dt, gy_shift, 1)``, with dT as a rate in degC/s);
- ``stepwise``: see :mod:`imupipe.stages.thermal.stepwise`.

Least squares is weighted (the temperature-bin weights of the stage) and column-scaled so that
terms of very different sizes (T^3 ~ 1e5, dT ~ 1e-2) are solved to full precision. Where the
terms are chosen by the data, the small-sample Akaike criterion decides (:func:`aicc`, Hurvich
and Tsai, Biometrika 76, 1989): ``n ln(RSS/n) + 2k + 2k(k+1)/(n-k-1)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from imupipe.stages.thermal.track import first_order_lag

VARIABLES: tuple[str, ...] = ("T", "dT", "Ta", "dTa", "Ts", "dTs")
TEMPERATURES: tuple[str, ...] = ("T", "Ta", "Ts")
"""The variables that are temperatures (relative to Tref, clamped to the fitted range)."""
SIX_TERMS: tuple[str, ...] = ("T^2", "T", "dT^2", "dT", "T*dT", "1")
"""The MATLAB example's ``tFun``: a(1) T^2 + a(2) T + a(3) dT^2 + a(4) dT + a(5) dT T + a(6)."""
RATE_TERMS: tuple[str, ...] = ("dT", "dT^2", "T*dT")
MAX_ORDER = 5


def parse_term(term: str) -> tuple[tuple[str, int], ...]:
    """``"T^2*dT"`` -> (("T", 2), ("dT", 1)); ``"1"`` -> (); ``"hat3"`` -> (("hat3", 1),)."""
    if term == "1":
        return ()
    factors = []
    for factor in term.split("*"):
        name, _, power = factor.partition("^")
        if not (name in VARIABLES or (name.startswith("hat") and name[3:].isdigit())):
            raise ValueError(f"unknown variable '{name}' in term '{term}'")
        p = int(power) if power else 1
        if p < 1:
            raise ValueError(f"bad power in term '{term}'")
        factors.append((name, p))
    return tuple(factors)


def term_variables(terms: Sequence[str]) -> set[str]:
    """The variables (not hats) the terms use."""
    return {name for t in terms for name, _ in parse_term(t) if not name.startswith("hat")}


def hat_basis(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(n, len(knots)) hat functions of ``x`` on increasing ``knots`` (x clamped to the knots)."""
    x = np.clip(np.asarray(x, dtype=np.float64), knots[0], knots[-1])
    k = len(knots)
    seg = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, k - 2)
    frac = (x - knots[seg]) / (knots[seg + 1] - knots[seg])
    out = np.zeros((len(x), k))
    rows = np.arange(len(x))
    out[rows, seg] = 1.0 - frac
    out[rows, seg + 1] += frac
    return out


def design(
    terms: Sequence[str], variables: Mapping[str, np.ndarray], knots: np.ndarray | None = None
) -> np.ndarray:
    """(n, len(terms)) design matrix; ``variables`` maps T, dT (Ta, dTa) to (n,) arrays,
    ``knots`` (relative to Tref, like T) is needed by hat terms."""
    n = len(next(iter(variables.values())))
    hats = None
    cols = []
    for term in terms:
        col = np.ones(n)
        for name, power in parse_term(term):
            if name.startswith("hat"):
                if knots is None:
                    raise ValueError(f"term '{term}' needs the piecewise model's knots")
                if hats is None:
                    hats = hat_basis(variables["T"], knots)
                col = col * hats[:, int(name[3:])]
            else:
                col = col * variables[name] ** power
        cols.append(col)
    return np.column_stack(cols) if cols else np.zeros((n, 0))


def weighted_lstsq(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """argmin sum w (y - x c)^2, with columns scaled to unit norm for conditioning."""
    sw = np.ones(len(y)) if w is None else np.sqrt(np.asarray(w, dtype=np.float64))
    xw = x * sw[:, None]
    scale = np.linalg.norm(xw, axis=0)
    scale[scale == 0] = 1.0
    coef, *_ = np.linalg.lstsq(xw / scale, y * sw, rcond=None)
    return coef / scale


def poly_terms(order: int, rate_terms: Sequence[str] = ()) -> list[str]:
    """``1, T, ..., T^order`` followed by the chosen rate terms."""
    if not 0 <= order <= MAX_ORDER:
        raise ValueError(f"order must be 0..{MAX_ORDER}")
    bad = [t for t in rate_terms if t not in RATE_TERMS]
    if bad:
        raise ValueError(f"unknown rate term(s) {bad} (known: {', '.join(RATE_TERMS)})")
    return ["1"] + [("T" if p == 1 else f"T^{p}") for p in range(1, order + 1)] + list(rate_terms)


def aicc(rss: float, n: float, k: int) -> float:
    """The small-sample Akaike criterion of a least-squares fit with ``k`` coefficients on ``n``
    points (Hurvich and Tsai 1989); inf when ``n <= k + 1``."""
    if n - k - 1 <= 0:
        return float("inf")
    return n * float(np.log(max(rss / n, 1e-300))) + 2 * k + 2 * k * (k + 1) / (n - k - 1)


@dataclass
class Choice:
    """The chosen terms of one axis, their coefficients, and every candidate's score."""

    terms: list[str]
    coef: np.ndarray
    scores: dict[str, float] = field(default_factory=dict)


def select_terms(
    candidates: Sequence[Sequence[str]],
    variables: Mapping[str, np.ndarray],
    y: np.ndarray,
    w: np.ndarray,
) -> Choice:
    """The candidate term list with the lowest :func:`aicc` (weights normalised to mean 1)."""
    w = np.asarray(w, dtype=np.float64)
    w = w * (len(w) / w.sum())
    best: Choice | None = None
    best_score = float("inf")
    scores = {}
    for terms in candidates:
        x = design(terms, variables)
        coef = weighted_lstsq(x, y, w)
        r = y - x @ coef
        score = aicc(float(np.sum(w * r * r)), len(y), len(terms))
        scores[" + ".join(terms)] = score
        if best is None or score < best_score:
            best, best_score = Choice(list(terms), coef), score
    assert best is not None
    best.scores = scores
    return best


@dataclass
class LagFit:
    """The fitted time constant ``tau_s`` and the cost profile ``taus``/``costs`` searched
    (cost: sum over axes of ln RSS, i.e. the likelihood with one noise level per axis)."""

    tau_s: float
    taus: np.ndarray
    costs: np.ndarray
    at_bound: str | None
    """``"low"`` or ``"high"`` when the best time constant is at an end of the search range."""


def lag_variables(
    centre: np.ndarray, temp: np.ndarray, keep: np.ndarray, tau_s: float, tref: float
) -> dict[str, np.ndarray]:
    """``Ts - Tref`` and ``dTs`` at the blocks ``keep`` (indices into every block of the log)."""
    lagged, _ = first_order_lag(centre, temp, tau_s)
    return {"Ts": lagged[keep] - tref, "dTs": (temp[keep] - lagged[keep]) / tau_s}


def fit_lag(
    centre: np.ndarray,
    temp: np.ndarray,
    keep: np.ndarray,
    bias: np.ndarray,
    w: np.ndarray,
    terms: Sequence[str],
    tref: float,
    bounds: tuple[float, float],
) -> LagFit:
    """The time constant of the sensing element's lag that best explains ``bias`` (m, k) at the
    blocks ``keep`` with ``terms`` (in Ts, dTs) on every axis: a log-spaced grid of 41 time
    constants over ``bounds`` (s), then a bounded scalar search between the best point's
    neighbours. ``centre``/``temp`` are every block of the log (the lag runs over them all)."""

    def cost(log_tau: float) -> float:
        variables = lag_variables(centre, temp, keep, float(np.exp(log_tau)), tref)
        x = design(terms, variables)
        total = 0.0
        for i in range(bias.shape[1]):
            r = bias[:, i] - x @ weighted_lstsq(x, bias[:, i], w)
            total += float(np.log(max(float(np.sum(w * r * r)), 1e-300)))
        return total

    from scipy.optimize import minimize_scalar  # a fit only: applying a step needs no scipy

    grid = np.linspace(np.log(bounds[0]), np.log(bounds[1]), 41)
    costs = np.array([cost(g) for g in grid])
    best = int(np.argmin(costs))
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    res = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    log_tau = float(res.x) if res.fun < costs[best] else float(grid[best])
    at_bound = "low" if best == 0 else "high" if best == len(grid) - 1 else None
    return LagFit(float(np.exp(log_tau)), np.exp(grid), costs, at_bound)


def segment_knots(lo: float, hi: float, width: float) -> np.ndarray:
    """Knots from ``lo`` to ``hi`` (inclusive), about ``width`` apart (at least one segment)."""
    count = max(1, int(np.ceil((hi - lo) / width - 1e-9)))
    return np.linspace(lo, hi, count + 1)


def fit_piecewise(
    variables: Mapping[str, np.ndarray], y: np.ndarray, w: np.ndarray, knots: np.ndarray
) -> tuple[list[str], np.ndarray]:
    """The gyro patent's model: bias linear in T per segment (hats on ``knots``), then
    ``k_dt * dT + c`` fitted on the residual (without ``dT`` in ``variables``: the hats alone).
    Returns the terms (hats, ``dT``, ``1``) and their coefficients."""
    hats = [f"hat{i}" for i in range(len(knots))]
    h = design(hats, variables, knots)
    c_hat = weighted_lstsq(h, y, w)
    if "dT" not in variables:
        return hats, c_hat
    residual = y - h @ c_hat
    rate = variables["dT"]
    k_dt, const = weighted_lstsq(np.column_stack([rate, np.ones_like(rate)]), residual, w)
    return hats + ["dT", "1"], np.r_[c_hat, k_dt, const]


def evaluate(
    terms: Sequence[str],
    coef: np.ndarray,
    variables: Mapping[str, np.ndarray],
    knots: np.ndarray | None = None,
) -> np.ndarray:
    """The model's bias at the given variables. Summed term by term (elementwise, in the order
    of the terms), not by a matrix product, so that a sample's value does not depend on how
    many samples are evaluated with it (BLAS sums in an order that depends on the shape)."""
    x = design(terms, variables, knots)
    out = np.zeros(x.shape[0])
    for j, c in enumerate(np.asarray(coef, dtype=np.float64)):  # terms, not samples
        out += c * x[:, j]
    return out


# -- scale factor from turntable runs (the gyro patent) ---------------------------------------


def turning_runs(t_ns: np.ndarray, raw: np.ndarray, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: run id and turning state of one gyro axis, +1 where ``raw > rate / 2``, -1
    where ``raw < -rate / 2``, 0 otherwise; a run is a stretch of equal state."""
    state = np.where(raw > rate / 2, 1, np.where(raw < -rate / 2, -1, 0))
    run = np.r_[0, np.cumsum(np.diff(state) != 0)]
    return run, state


def turntable_pairs(
    t_ns: np.ndarray,
    raw: np.ndarray,
    temp: np.ndarray,
    rate: float,
    trim_s: float = 2.0,
    max_gap_s: float = 10.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The gyro patent's scale factor at each temperature: ``(out(+rate) - out(-rate)) / (2 rate)``
    for each +rate run followed (within ``max_gap_s``) by a -rate run or the reverse, on one
    gyro axis (``raw`` rad/s, ``rate`` rad/s > 0). Returns (mean temperature, scale factor) of
    each pair. ``trim_s`` seconds at both ends of a run are left out (spin-up, spin-down)."""
    run, state = turning_runs(t_ns, raw, rate)
    n_runs = int(run[-1]) + 1 if len(run) else 0
    t = (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    first = np.full(n_runs, np.inf)
    last = np.full(n_runs, -np.inf)
    np.minimum.at(first, run, t)
    np.maximum.at(last, run, t)
    inner = ((t - first[run]) >= trim_s) & ((last[run] - t) >= trim_s)
    count = np.bincount(run, weights=inner, minlength=n_runs)
    mean = np.bincount(run, weights=raw * inner, minlength=n_runs) / np.maximum(count, 1)
    mean_t = np.bincount(run, weights=temp * inner, minlength=n_runs) / np.maximum(count, 1)
    run_state = np.zeros(n_runs, dtype=np.int64)
    run_state[run] = state
    turning = np.flatnonzero((run_state != 0) & (count > 0))
    temps, scales = [], []
    k = 0
    while k + 1 < len(turning):  # loops over runs (a few per turntable stop), not samples
        a, b = turning[k], turning[k + 1]
        if run_state[a] == -run_state[b] and first[b] - last[a] <= max_gap_s:
            plus, minus = (a, b) if run_state[a] > 0 else (b, a)
            scales.append((mean[plus] - mean[minus]) / (2.0 * rate))
            temps.append(0.5 * (mean_t[a] + mean_t[b]))
            k += 2
        else:
            k += 1
    return np.array(temps), np.array(scales)
