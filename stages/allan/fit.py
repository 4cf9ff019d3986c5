"""The five-term Allan-variance noise model (IEEE Std 952-1997 Annex C) and its fit.

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
whole fit. The non-negative log-space least squares is solved by projected Gauss-Newton: each
step is a non-negative least-squares problem of the linearised residuals
(:func:`imupipe.stages.allan.nnls.nnls`), with step halving. Terms the data does not support are left
out by best-subset selection: every subset of the requested terms is fitted and the one with
the least ``cost + penalty * terms`` wins (an information criterion; ``penalty`` default 10),
with the weights thinned to about one independent point per octave of tau (overlapping estimates
at nearby taus are strongly correlated, a denser grid must not make spurious terms significant);
left-out terms are exactly zero. The rate ramp R pays the penalty twice: over a few hours one
realisation of a rate random walk often looks like a ramp, and a stochastic K is the better
default explanation unless the ramp clearly fits better.

The random walk K is not subject to the selection (:data:`ALWAYS`): it is in every candidate
model and may come out zero. Selected like the others, a bias instability B absorbed the first
rise of K over a recording of a few hours (2 h, B = 5e-5 rad/s, K = 2e-6 rad/s^2/sqrt(Hz):
K zero on 22 of 24 simulated axes; kept, its mean error over those axes is -9 %). Its 68 %
interval is a profile likelihood (:func:`profile_interval`): the other selected terms re-fitted
at every K, so the B that could hide a random walk widens it -- also where the selection left B
out (:func:`always_interval`: the interval is joined with the one of the model with B). K's single-run scatter is the
data's own, not the fit's: on 180 simulated axis-runs of that gyro it is 47 % with B and 17 %
without, 1.03 x and 1.08 x the Cramer-Rao bound of K with every term unknown (46 % and 16 %,
from the exact Gaussian likelihood of the data; the maximum-likelihood estimate scatters as
much), see ``test_random_walk_kept_under_bias_instability`` and docs/explanation/allan.md.

The IEEE/Kalibr slope readings are reported too: N from the -1/2 slope line at tau = 1 s, K from
the +1/2 slope line at tau = 3 s (each line through the measured point whose local log-log slope
is closest to the line's, within 0.25), B = min(sigma) / sqrt(2 ln2 / pi) (= min / 0.664).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from imupipe.stages.allan.nnls import nnls

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
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    """68 % profile interval of each always-fitted term (K): ``(low, high)``, low 0 when the
    curve cannot tell the term from zero."""

    def variance(self, taus: np.ndarray) -> np.ndarray:
        return sum(term_variance(t, self.params[t], taus) for t in TERMS)

    def deviation(self, taus: np.ndarray) -> np.ndarray:
        return np.sqrt(self.variance(taus))


def term_variance(term: str, value: float, taus: np.ndarray) -> np.ndarray:
    """The Allan variance of one term of size ``value`` at ``taus`` (s)."""
    return FACTORS[term] * value * value * np.asarray(taus, dtype=np.float64) ** POWERS[term]


def log_variance_moments(edf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(bias, variance) of ln(s^2 / sigma^2) for s^2 ~ sigma^2 chi2(edf) / edf."""
    from imupipe.stages.special import digamma, polygamma  # scipy: loaded on first use

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


def _solve(
    a: np.ndarray,
    target: np.ndarray,
    w: np.ndarray,
    iters: int = 60,
    fixed: np.ndarray | None = None,
    start: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """min_c sum w (ln(a c + fixed) - target)^2, c >= 0; ``a`` (t, p) positive columns,
    ``fixed`` (t,) a known non-negative variance added to the model (default none). Returns
    ``(c, cost)``.

    The log objective is not convex in c. Projected Gauss-Newton runs from the relative-residual
    NNLS solution (the first-order fit); when that is all zero, from the mean of the terms'
    lower-envelope tangents and from their sum, and the better end point wins; with ``start``
    (a previous solution, for a profile) from that one only. (On 96 simulated curves x 16 subsets
    the first-order start was never beaten by the two others.)"""
    return _Scaled(a, target, w).solve(iters, fixed, start)


class _Scaled:
    """The columns ``a`` (t, p) of one log-space problem (``target``, weights ``w``), scaled so
    that each term's largest share of the curve is 1: ``u = c / scale``, ``u_k = 1`` is term k's
    tangent to the curve from below. Built once per set of terms and reused by every solve on it
    (the profile of K solves the same columns at every K)."""

    def __init__(self, a: np.ndarray, target: np.ndarray, w: np.ndarray) -> None:
        self.target, self.w = target, w
        self.sw = np.sqrt(w)
        self.sw_col = self.sw[:, None]
        self.level = np.exp(target)
        self.rel = a / self.level[:, None]
        self.scale = 1.0 / self.rel.max(axis=0)
        self.a_s = a * self.scale

    def evaluate(
        self, u: np.ndarray, off: np.ndarray | None
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """(cost, model variance mu, log residual r) at scaled coefficients ``u`` plus the fixed
        variance ``off`` (None: none); cost inf where the model is not positive."""
        mu = self.a_s @ u
        if off is not None:
            mu += off
        if not mu.min() > 0:
            return np.inf, mu, mu
        r = np.log(mu) - self.target
        return float(r @ (self.w * r)), mu, r

    def descend(
        self, u: np.ndarray, off: np.ndarray | None, iters: int
    ) -> tuple[np.ndarray, float]:
        """Projected Gauss-Newton from ``u`` (>= 0): each step the NNLS solution of the
        linearised residuals, halved until the cost falls; stops when a step gains less than
        1e-9 of the cost. Each point's cost is evaluated once (its model and residual are the
        next step's linearisation). A start where the model is not positive takes no step."""
        sw, sw_col, a_s = self.sw, self.sw_col, self.a_s
        f, mu, r = self.evaluate(u, off)
        for _ in range(iters):
            if not math.isfinite(f):
                break
            jac = a_s / mu[:, None]
            new = nnls(sw_col * jac, sw * (jac @ u - r))
            step = new - u
            lam = 1.0
            while lam > 1e-6:
                trial = u + step if lam == 1.0 else u + lam * step  # the same sum: 1.0 * s == s
                ft, mu_t, r_t = self.evaluate(trial, off)
                if not ft >= f:
                    break
                lam *= 0.5
            if lam <= 1e-6:
                break
            done = f - ft <= 1e-9 * max(f, 1e-300)
            u, f, mu, r = trial, ft, mu_t, r_t
            if done:
                break
        if np.any(u < 0.0):  # never from non-negative steps; kept as the projection's guarantee
            u = np.maximum(u, 0.0)
            f = self.evaluate(u, off)[0]
        return u, f

    def solve(
        self, iters: int = 60, fixed: np.ndarray | None = None, start: np.ndarray | None = None
    ) -> tuple[np.ndarray, float]:
        """:func:`_solve` on these columns."""
        # no fixed variance: none added (adding zeros changes no value)
        off = None if fixed is None else np.asarray(fixed, dtype=np.float64)
        p = self.a_s.shape[1]
        if start is not None:
            starts = [np.maximum(np.asarray(start, dtype=np.float64) / self.scale, 1e-12)]
        else:
            share = np.ones(len(self.target)) if off is None else 1.0 - off / self.level
            first = nnls(self.sw_col * self.rel * self.scale, self.sw * np.maximum(share, 0.0))
            starts = [first] if np.any(first > 0) else [np.full(p, 1.0 / p), np.ones(p)]
        u, f = min((self.descend(s0, off, iters) for s0 in starts), key=lambda item: item[1])
        return u * self.scale, f


@dataclass(frozen=True)
class _Problem:
    """One curve prepared for the log-space fit: ``taus``, bias-corrected ``target`` (ln of the
    variance), weights ``w``. Each term's column and each set of terms' scaled columns are
    computed once (``_cache``)."""

    taus: np.ndarray
    target: np.ndarray
    w: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def power(self, term: str) -> np.ndarray:
        """``taus ** POWERS[term]``."""
        key = ("power", term)
        if key not in self._cache:
            self._cache[key] = self.taus ** POWERS[term]
        return self._cache[key]

    def columns(self, terms: list[str]) -> np.ndarray:
        return np.column_stack([FACTORS[t] * self.power(t) for t in terms])

    def scaled(self, terms: list[str]) -> _Scaled:
        key = tuple(terms)
        if key not in self._cache:
            self._cache[key] = _Scaled(self.columns(terms), self.target, self.w)
        return self._cache[key]

    def solve(self, terms: list[str]) -> tuple[np.ndarray, float]:
        if not terms:
            return np.zeros(0), float(np.sum(self.w * self.target**2))
        key = ("solve", tuple(terms))  # deterministic: the full set is solved twice otherwise
        if key not in self._cache:
            self._cache[key] = self.scaled(terms).solve()
        c, cost = self._cache[key]
        return c.copy(), cost

    def profile(self, terms: list[str], term: str, c_term: float, start: np.ndarray | None):
        """(c of the other terms, cost) with ``term``'s variance coefficient held at ``c_term``."""
        fixed = c_term * FACTORS[term] * self.power(term)
        others = [t for t in terms if t != term]
        if not others:
            mu = fixed
            cost = (
                np.inf
                if np.any(mu <= 0)
                else float(np.sum(self.w * (np.log(mu) - self.target) ** 2))
            )
            return np.zeros(0), cost
        return self.scaled(others).solve(iters=30, fixed=fixed, start=start)


PROFILE_DELTA = 2.0
"""Cost increase that bounds a 68 % profile interval. For a chi-square cost 1 would be one
sigma; the log-space cost counts one point per octave as independent, which overstates the
information at the longest taus, where neighbouring octaves share most of the data: with 1, the
interval of K covered the truth on 54 % of 24 simulated 2 h axes with B present (71 % without);
with 2, on 75 % and 69 % of 36 (tests/test_allan_fit.py, ``k_study``)."""


def profile_interval(
    problem: _Problem, terms: list[str], term: str, c_best: np.ndarray, cost_best: float
) -> tuple[float, float]:
    """68 % interval of ``term``'s variance coefficient, the other ``terms`` re-fitted at every
    value (profile likelihood): where the weighted log-space cost rises by
    :data:`PROFILE_DELTA` above its minimum ``cost_best`` (the lower end is 0 when the cost at 0
    stays below that). Bisection in log space, to 2 % of the coefficient."""
    k = terms.index(term)
    others = [i for i in range(len(terms)) if i != k]
    c0 = float(c_best[k])
    bound = cost_best + PROFILE_DELTA
    warm = c_best[others]

    def cost_at(c: float) -> float:
        nonlocal warm
        sol, cost = problem.profile(terms, term, c, warm if len(others) else None)
        if np.isfinite(cost) and len(others):
            warm = sol
        return cost

    # a scale for the coefficient when the best value is zero: the level of the curve
    unit = FACTORS[term] * problem.taus ** POWERS[term]
    scale = c0 if c0 > 0 else float(np.min(np.exp(problem.target) / unit)) * 1e-3
    hi_in, hi_out = c0, scale * 2.0
    while cost_at(hi_out) < bound and hi_out < 1e12 * scale:
        hi_in, hi_out = hi_out, hi_out * 4.0
    for _ in range(40):
        if hi_out <= 1.02 * max(hi_in, 1e-300) and hi_in > 0:
            break
        mid = np.sqrt(hi_in * hi_out) if hi_in > 0 else hi_out / 4.0
        if hi_in == 0 and mid < scale * 1e-6:
            break
        if cost_at(mid) < bound:
            hi_in = mid
        else:
            hi_out = mid
    upper = hi_in if hi_in > 0 else hi_out
    warm = c_best[others]
    if c0 == 0 or cost_at(0.0) < bound:
        return 0.0, upper
    lo_in, lo_out = c0, c0 / 4.0
    while cost_at(lo_out) < bound:
        lo_in, lo_out = lo_out, lo_out / 4.0
        if lo_out < c0 * 1e-8:
            return 0.0, upper
    while lo_in > 1.02 * lo_out:
        mid = np.sqrt(lo_in * lo_out)
        if cost_at(mid) < bound:
            lo_in = mid
        else:
            lo_out = mid
    return lo_in, upper


ALWAYS: tuple[str, ...] = ("K",)
"""Terms kept in every candidate model when asked for (their fitted value may still be zero):
the random walk K, which every inertial sensor has and Kalibr needs. Left to the information
criterion, a bias instability B absorbs the first rise of a random walk over a recording of a
few hours, and K came out exactly zero with an upper bound below the truth."""


HIDERS: tuple[str, ...] = ("B",)
"""Terms that can take over part of an always-fitted term's curve: the bias instability, whose
flat floor a random walk rising only at the longest taus (two or three octaves of EDF 1 to 10)
is hard to tell from. Left out by the selection, B still widens K's interval."""


def always_interval(
    problem: _Problem,
    asked: list[str],
    active: list[str],
    term: str,
    c: np.ndarray,
    cost: float,
) -> tuple[float, float]:
    """68 % interval of the always-fitted ``term`` (its square root: K, not K^2/3): the profile
    interval in the selected model ``active`` (coefficients ``c``, cost ``cost``), joined with
    the one in that model plus every asked :data:`HIDERS` term the selection left out (each
    profiled from that larger model's own minimum). The selection's choice is itself uncertain:
    on a 1 h gyro low-passed at 2 Hz (bias instability 3e-5 rad/s, K 3e-6 rad/s^2/sqrt(Hz))
    the selection dropped B, K came out +92 % and its interval in the selected model alone was
    +59 to +129 %; with B re-fitted the interval reaches down to the truth."""
    lo, hi = profile_interval(problem, active, term, c, cost)
    extra = [t for t in HIDERS if t in asked and t not in active]
    if extra:
        wider = [t for t in TERMS if t in active or t in extra]
        c2, cost2 = problem.solve(wider)
        lo2, hi2 = profile_interval(problem, wider, term, c2, cost2)
        lo, hi = min(lo, lo2), max(hi, hi2)
    return float(np.sqrt(lo)), float(np.sqrt(hi))


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
    problem = _Problem(taus, target, density_weights(taus) / (var + (2.0 * model_error) ** 2))

    asked = [t for t in TERMS if t in terms]
    always = [t for t in asked if t in ALWAYS]
    optional = [t for t in asked if t not in ALWAYS]
    best: tuple[float, list[str], np.ndarray, float] | None = None
    # no subset fits better than every term together: a subset whose penalty alone, added to
    # that floor, reaches the best score so far cannot win and is not fitted (branch and bound)
    floor = problem.solve(asked)[1]
    for size in range(0 if always else 1, len(optional) + 1):
        for subset in itertools.combinations(optional, size):
            charge = penalty * (size + ("R" in subset))
            if best is not None and floor + charge >= best[0]:
                continue
            active = [t for t in TERMS if t in subset or t in always]
            c, cost = problem.solve(active)
            floor = min(floor, cost)
            if any(ci <= 0 for t, ci in zip(active, c, strict=True) if t in subset):
                continue  # the same curve as a smaller subset, which is scored on its own
            if not np.any(c > 0):
                continue
            score = cost + charge
            if best is None or score < best[0]:
                best = (score, active, c, cost)
    if best is None:
        raise ValueError("no term of the model fits the curve")
    _, active, c, cost = best
    ranges = {t: always_interval(problem, asked, active, t, c, cost) for t in always}
    params = dict.fromkeys(TERMS, 0.0)
    for t, ci in zip(active, c, strict=True):
        params[t] = float(np.sqrt(ci))
    dropped = [t for t in asked if params[t] == 0.0]
    fit = AllanFit(
        params, tuple(terms), cost, max(len(taus) - len(active), 0), 0.0, dropped, ranges
    )
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
