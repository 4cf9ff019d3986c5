"""The five-term Allan-variance noise model (seed 001, IEEE Std 952) and its fit.

Model, continuous-time SI parameters (gyro units shown; accel: m/s, m/s/sqrt(Hz), m/s^2,
m/s^2/sqrt(Hz), m/s^3)::

    sigma^2(tau) = 3 Q^2 / tau^2       quantisation             Q  rad
                 + N^2 / tau           angle random walk        N  rad/s/sqrt(Hz)
                 + B^2 * 2 ln2 / pi    bias instability         B  rad/s
                 + K^2 tau / 3         rate random walk         K  rad/s^2/sqrt(Hz)
                 + R^2 tau^2 / 2       rate ramp                R  rad/s^2

The fit is linear in the non-negative variance coefficients ``c = (3Q^2, N^2, B^2 2ln2/pi,
K^2/3, R^2/2)`` but is done on the *logarithm* of the variance (each decade of tau counts alike),
weighted by the confidence of each point: an overlapping Allan variance with ``edf`` equivalent
degrees of freedom is distributed as ``sigma^2 chi2(edf) / edf``, so ``ln`` of it has variance
``trigamma(edf / 2)`` and mean ``ln sigma^2 + digamma(edf / 2) - ln(edf / 2)``; the weights are the
inverse variances and the bias is removed from the targets (it matters at the long taus, where
the random walk lives). A relative model error ``model_error`` (default 5 % of the deviation) is
added to every point's variance, so that the short taus, with their enormous EDF, cannot let a
feature the five terms do not describe (anti-alias filters, Gauss-Markov roll-offs) dictate the
whole fit. The non-negative log-space least squares is solved by projected
Gauss-Newton: each step is a non-negative least-squares problem (``scipy.optimize.nnls``) of the
linearised residuals, with step halving. Terms the data does not support are left out by best-subset
selection: every subset of the requested terms is fitted and the one with the least
``cost + penalty * terms`` wins (an information criterion; ``penalty`` default 10), with the
weights thinned to about one independent point per octave of tau (overlapping estimates at
nearby taus are strongly correlated, a denser grid must not make spurious terms significant);
left-out terms are exactly zero. The rate ramp R pays the penalty twice: over a few hours one
realisation of a rate random walk often looks like a ramp, and a stochastic K is the better
default explanation unless the ramp clearly fits better.

The IEEE/Kalibr slope readings are reported too: N from the -1/2 slope line at tau = 1 s, K from
the +1/2 slope line at tau = 3 s (each line through the measured point whose local log-log slope
is closest to the line's, within 0.25), B = min(sigma) / sqrt(2 ln2 / pi) (= min / 0.664).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import nnls
from scipy.special import digamma, polygamma

TERMS: tuple[str, ...] = ("Q", "N", "B", "K", "R")
POWERS: dict[str, int] = {"Q": -2, "N": -1, "B": 0, "K": 1, "R": 2}
FACTORS: dict[str, float] = {
    "Q": 3.0,
    "N": 1.0,
    "B": 2.0 * np.log(2.0) / np.pi,
    "K": 1.0 / 3.0,
    "R": 0.5,
}
"""sigma^2(tau) = sum over terms of FACTORS[t] * P_t^2 * tau^POWERS[t]."""
B_FLOOR = float(np.sqrt(FACTORS["B"]))
"""The Allan deviation of bias instability B is flat at B * 0.664."""


@dataclass
class AllanFit:
    """Fitted parameters (all five, zero where not fitted or not supported), the terms asked
    for, the weighted log-space residual sum ``cost`` and its degrees of freedom, the RMS of the
    log10 deviation residuals, and the slope readings."""

    params: dict[str, float]
    terms: tuple[str, ...]
    cost: float
    dof: int
    rms_log10: float
    dropped: list[str] = field(default_factory=list)

    def variance(self, taus: np.ndarray) -> np.ndarray:
        return sum(term_variance(t, self.params[t], taus) for t in TERMS)

    def deviation(self, taus: np.ndarray) -> np.ndarray:
        return np.sqrt(self.variance(taus))


def term_variance(term: str, value: float, taus: np.ndarray) -> np.ndarray:
    """The Allan variance of one term of size ``value`` at ``taus`` (s)."""
    return FACTORS[term] * value * value * np.asarray(taus, dtype=np.float64) ** POWERS[term]


def log_variance_moments(edf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(bias, variance) of ln(s^2 / sigma^2) for s^2 ~ sigma^2 chi2(edf) / edf."""
    half = 0.5 * np.asarray(edf, dtype=np.float64)
    return digamma(half) - np.log(half), polygamma(1, half)


def fit_start(taus: np.ndarray, dev: np.ndarray) -> float:
    """The shortest tau the model can describe: every term's deviation falls or stays flat at
    short taus, so a curve that *rises* first (an anti-alias or averaging filter correlates the
    samples) is fitted from its first peak on, before the minimum; else from the first tau."""
    dev = np.asarray(dev, dtype=np.float64)
    finite = np.isfinite(dev)
    if len(dev) < 3 or not finite.all() or dev[1] <= dev[0]:
        return float(taus[0])
    head = dev[: int(np.argmin(dev)) + 1]
    return float(taus[int(np.argmax(head))])


def density_weights(taus: np.ndarray) -> np.ndarray:
    """Per-point factor <= 1 that counts about one point per octave of tau as independent:
    overlapping deviations at nearby taus are strongly correlated, so a denser grid must not
    weigh more (nor make spurious terms look significant)."""
    lt = np.log2(np.asarray(taus, dtype=np.float64))
    if len(lt) < 2:
        return np.ones(len(lt))
    edges = np.concatenate([[lt[0] - (lt[1] - lt[0]) / 2], (lt[1:] + lt[:-1]) / 2])
    edges = np.concatenate([edges, [lt[-1] + (lt[-1] - lt[-2]) / 2]])
    return np.minimum(np.diff(edges), 1.0)


def _solve(a: np.ndarray, target: np.ndarray, w: np.ndarray, iters: int = 60) -> np.ndarray:
    """min_c sum w (ln(a c) - target)^2, c >= 0; ``a`` (t, p) positive columns.

    The log objective is not convex in c, so projected Gauss-Newton runs from three starts
    (the relative-residual NNLS solution, the mean of the terms' lower-envelope tangents, and
    their sum) and the best end point wins."""
    sw = np.sqrt(w)
    rel = a / np.exp(target)[:, None]
    scale = 1.0 / rel.max(axis=0)
    a_s = a * scale  # u = c / scale; u_k = 1 is term k's tangent to the curve from below
    p = a.shape[1]

    def cost(u: np.ndarray) -> float:
        mu = a_s @ u
        if np.any(mu <= 0):
            return np.inf
        return float(np.sum(w * (np.log(mu) - target) ** 2))

    def descend(u: np.ndarray) -> tuple[np.ndarray, float]:
        f = cost(u)
        for _ in range(iters):
            mu = a_s @ u
            jac = a_s / mu[:, None]
            new, _ = nnls(sw[:, None] * jac, sw * (1.0 - (np.log(mu) - target)))
            step = new - u
            lam = 1.0
            while lam > 1e-6 and cost(u + lam * step) >= f:
                lam *= 0.5
            if lam <= 1e-6:
                break
            trial = u + lam * step
            ft = cost(trial)
            done = f - ft <= 1e-12 * max(f, 1e-300)
            u, f = trial, ft
            if done:
                break
        return np.maximum(u, 0.0), f

    first, _ = nnls(sw[:, None] * rel * scale, sw)  # first order: relative residuals
    starts = [np.full(p, 1.0 / p), np.ones(p)]
    if np.any(first > 0):
        starts.insert(0, first)
    u, _ = min((descend(s0) for s0 in starts), key=lambda item: item[1])
    return u * scale


def fit_allan(
    taus: np.ndarray,
    dev: np.ndarray,
    edf: np.ndarray,
    terms: tuple[str, ...] = TERMS,
    penalty: float = 10.0,
    model_error: float = 0.05,
    tau_range: tuple[float, float] | None = None,
) -> AllanFit:
    """Fit the model's ``terms`` to one measured deviation curve (``taus`` s, ``dev``, ``edf``)
    over ``tau_range`` (s; default: all taus from the curve's first peak on, see
    :func:`fit_start`)."""
    taus = np.asarray(taus, dtype=np.float64)
    dev = np.asarray(dev, dtype=np.float64)
    ok = np.isfinite(dev) & (dev > 0) & np.isfinite(edf)
    if tau_range is None:
        ok &= taus >= fit_start(taus, dev)
    else:
        ok &= (taus >= tau_range[0]) & (taus <= tau_range[1])
    if ok.sum() < 2:
        raise ValueError(f"only {int(ok.sum())} usable taus to fit")
    taus, dev, edf = taus[ok], dev[ok], np.asarray(edf, dtype=np.float64)[ok]
    bias, var = log_variance_moments(edf)
    target = np.log(dev * dev) - bias
    w = density_weights(taus) / (var + (2.0 * model_error) ** 2)

    def solve(active: list[str]) -> tuple[np.ndarray, float]:
        a = np.column_stack([FACTORS[t] * taus ** POWERS[t] for t in active])
        c = _solve(a, target, w)
        mu = a @ c
        return c, float(np.sum(w * (np.log(mu) - target) ** 2))

    asked = [t for t in TERMS if t in terms]
    best: tuple[float, list[str], np.ndarray, float] | None = None
    for size in range(1, len(asked) + 1):
        for subset in itertools.combinations(asked, size):
            c, cost = solve(list(subset))
            if np.any(c <= 0):
                continue  # the same curve as a smaller subset, which is scored on its own
            score = cost + penalty * (size + ("R" in subset))
            if best is None or score < best[0]:
                best = (score, list(subset), c, cost)
    if best is None:
        raise ValueError("no term of the model fits the curve")
    _, active, c, cost = best
    dropped = [t for t in asked if t not in active]
    params = dict.fromkeys(TERMS, 0.0)
    for t, ci in zip(active, c, strict=True):
        params[t] = float(np.sqrt(ci))
    fit = AllanFit(params, tuple(terms), cost, max(len(taus) - len(active), 0), 0.0, dropped)
    fit.rms_log10 = float(np.sqrt(np.mean(np.log10(fit.deviation(taus) / dev) ** 2)))
    return fit


def slope_readings(taus: np.ndarray, dev: np.ndarray) -> dict[str, float | None]:
    """IEEE/Kalibr readings from the measured curve: ``N`` (the -1/2 line at 1 s), ``K`` (the
    +1/2 line at 3 s), ``B`` (min / 0.664), each None when the curve has no such region."""
    taus = np.asarray(taus, dtype=np.float64)
    dev = np.asarray(dev, dtype=np.float64)
    out: dict[str, float | None] = {"N": None, "K": None, "B": None}
    if len(taus) >= 2:
        lt, ld = np.log10(taus), np.log10(dev)
        slope = np.diff(ld) / np.diff(lt)
        mid_t, mid_d = (lt[1:] + lt[:-1]) / 2, (ld[1:] + ld[:-1]) / 2
        for name, s, at in (("N", -0.5, 1.0), ("K", 0.5, 3.0)):
            miss = np.abs(slope - s)
            i = int(np.argmin(miss))
            if miss[i] <= 0.25:
                out[name] = float(10 ** (mid_d[i] + s * (np.log10(at) - mid_t[i])))
    if len(dev):
        out["B"] = float(np.min(dev) / B_FLOOR)
    return out
