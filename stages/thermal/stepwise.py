"""Stepwise regression: choose the terms of a linear model (the multi-factor temperature model
of "MEMS 惯性测量组件的温度误差补偿模型研究", whose terms are chosen by stepwise regression).

Candidates: every monomial of degree <= 2 in the available variables (device temperature T and
its rate dT, and ambient temperature Ta and its rate dTa when the log has an ambient column),
plus the powers T^3 .. T^order of the device temperature. With four variables that is
1 + 4 + 10 = 15 terms (+ T^3). The paper's list has 21 terms because it also takes the sensor's
own output V as a variable; on a static recording the error *is* V minus the reference, so V
terms would explain it trivially: imupipe leaves them out.

Selection (the constant ``1`` is always in):

- ``f_test``: forward-backward. Add the candidate with the largest partial F statistic while its
  p-value is below ``alpha_in``; after each addition drop the term with the smallest F whose
  p-value is above ``alpha_out`` (alpha_out >= alpha_in, so no cycle). F for a term in a model
  of ``p`` terms on ``n`` points: ``(RSS_without - RSS_with) / (RSS_with / (n - p))``.
- ``adj_r2``: forward; add the candidate that raises the adjusted R^2
  ``1 - (1 - R^2)(n - 1)/(n - p)`` most, stop when none raises it.

All sums are weighted (weights normalised to mean 1). Block means of a slow ramp are not
independent, so the p-values are optimistic; the selection is a guide, validate on held-out data.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from imupipe.stages.thermal.models import weighted_lstsq


def candidate_terms(variables: Sequence[str], order: int = 3) -> list[str]:
    """``1``, each variable, each product or square of two, then ``T^3 .. T^order``."""
    names = list(variables)
    terms = ["1"] + names
    for a, b in itertools.combinations_with_replacement(names, 2):
        terms.append(f"{a}^2" if a == b else f"{a}*{b}")
    terms += [f"T^{p}" for p in range(3, order + 1)]
    return terms


@dataclass
class Selection:
    """The chosen terms (in order of entry), their coefficients, and the steps taken."""

    terms: list[str]
    coef: np.ndarray
    adj_r2: float
    history: list[str] = field(default_factory=list)


def _rss(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> float:
    coef = weighted_lstsq(x, y, w)
    r = y - x @ coef
    return float(np.sum(w * r * r))


def stepwise(
    x: np.ndarray,
    y: np.ndarray,
    names: Sequence[str],
    w: np.ndarray | None = None,
    *,
    criterion: str = "f_test",
    alpha_in: float = 0.05,
    alpha_out: float = 0.10,
    max_steps: int = 100,
) -> Selection:
    """Select columns of ``x`` (named ``names``, ``"1"`` among them) to explain ``y``."""
    n = len(y)
    w = np.ones(n) if w is None else np.asarray(w, dtype=np.float64) * (n / np.sum(w))
    ybar = np.sum(w * y) / n
    tss = float(np.sum(w * (y - ybar) ** 2)) or 1.0
    names = list(names)
    chosen = [names.index("1")] if "1" in names else []
    history: list[str] = []

    def adj(cols: list[int]) -> float:
        p = len(cols)
        return 1.0 - (_rss(x[:, cols], y, w) / tss) * (n - 1) / max(n - p, 1)

    for _ in range(max_steps):
        rest = [j for j in range(x.shape[1]) if j not in chosen]
        if not rest:
            break
        if criterion == "adj_r2":
            base = adj(chosen)
            gains = [adj(chosen + [j]) - base for j in rest]
            best = int(np.argmax(gains))
            if gains[best] <= 0:
                break
            chosen.append(rest[best])
            history.append(f"+{names[rest[best]]} (adj R^2 +{gains[best]:.3g})")
            continue
        rss0 = _rss(x[:, chosen], y, w)
        f_in = []
        for j in rest:
            rss1 = _rss(x[:, chosen + [j]], y, w)
            dof = n - len(chosen) - 1
            f_in.append((rss0 - rss1) / max(rss1 / max(dof, 1), 1e-300))
        best = int(np.argmax(f_in))
        p_in = float(stats.f.sf(f_in[best], 1, n - len(chosen) - 1))
        if p_in >= alpha_in:
            break
        chosen.append(rest[best])
        history.append(f"+{names[rest[best]]} (F={f_in[best]:.3g}, p={p_in:.2g})")
        rss_full = _rss(x[:, chosen], y, w)
        dof = n - len(chosen)
        removable = [j for j in chosen if names[j] != "1" and j != rest[best]]
        if removable:
            f_out = [
                (_rss(x[:, [k for k in chosen if k != j]], y, w) - rss_full) / (rss_full / dof)
                for j in removable
            ]
            worst = int(np.argmin(f_out))
            p_out = float(stats.f.sf(f_out[worst], 1, dof))
            if p_out > alpha_out:
                chosen.remove(removable[worst])
                history.append(f"-{names[removable[worst]]} (F={f_out[worst]:.3g}, p={p_out:.2g})")
    coef = weighted_lstsq(x[:, chosen], y, w)
    return Selection([names[j] for j in chosen], coef, adj(chosen), history)
