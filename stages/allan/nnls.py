"""Non-negative least squares for a handful of unknowns, by exhausting the active sets.

``min ||A x - b||^2 subject to x >= 0`` (Lawson & Hanson, *Solving Least Squares Problems*,
1974, ch. 23). Its solution is the unconstrained least-squares solution on some subset S of the
columns (the others zero) that is itself non-negative, and every such candidate is a feasible
point, so the candidate of least residual is the solution. With p <= 6 unknowns all 2^p - 1
subsets are solved at once: the normal equations of each subset, stacked into one batched
``numpy.linalg.solve`` (a singular subset: its pseudo-inverse, the least-norm solution). First,
and enough for most calls, the unconstrained solution: when it is non-negative it is the answer.

Why not :func:`scipy.optimize.nnls`: the Allan fit is the only user of ``scipy.optimize`` in a
static run, and importing that package costs 0.13 s of the 0.27 s scipy takes (2-core test
machine), against 8 ms for the 522 small problems of a 2 h 6-axis fit here (15 us each, 452 of
them feasible unconstrained; scipy's compiled core 2 us). The Allan fit's columns are scaled to
unit shares of the curve (condition numbers 1 to 76 on the 2 h static benchmark), so the squared
condition of the normal equations costs nothing measurable: the 522 solutions of that run agree
with scipy's to 1.3e-14 (``tests/test_nnls.py`` checks random problems against scipy's).
"""

from __future__ import annotations

import functools

import numpy as np

MAX_UNKNOWNS = 6
"""The most columns solved by exhausting the subsets (63 of them)."""


@functools.cache
def _subsets(p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(keep (s, p) bool: the columns of each non-empty subset, keep x keep (s, p, p),
    the identity on the left-out columns (s, p, p))."""
    keep = (np.arange(1, 1 << p)[:, None] >> np.arange(p)) & 1 == 1
    pair = keep[:, :, None] & keep[:, None, :]
    rest = (~keep)[:, :, None] * np.eye(p)
    return keep, pair, rest


def nnls(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The x >= 0 (p,) that minimises ``||a x - b||`` for ``a`` (m, p) with p <= 6, ``b`` (m,)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    p = a.shape[1]
    if not 0 < p <= MAX_UNKNOWNS:
        raise ValueError(f"nnls solves 1 to {MAX_UNKNOWNS} unknowns, not {p}")
    gram = a.T @ a
    rhs = a.T @ b
    if p == 1:  # the unconstrained solution, clipped at 0
        return np.array([max(rhs[0] / gram[0, 0], 0.0)]) if gram[0, 0] > 0 else np.zeros(1)
    if p == 2:  # Cramer's rule, then each column alone (the Allan fit's common case)
        (g00, g01), (_, g11) = gram.tolist()
        r0, r1 = rhs.tolist()
        det = g00 * g11 - g01 * g01
        if det > 1e-12 * g00 * g11:
            x0, x1 = (g11 * r0 - g01 * r1) / det, (g00 * r1 - g01 * r0) / det
            if x0 >= 0.0 and x1 >= 0.0:
                return np.array([x0, x1])
        # one column alone: the larger fall of ||a x - b||^2, -r^2 / g, among r > 0
        fall0 = r0 * r0 / g00 if r0 > 0.0 and g00 > 0.0 else 0.0
        fall1 = r1 * r1 / g11 if r1 > 0.0 and g11 > 0.0 else 0.0
        if fall0 == fall1 == 0.0:
            return np.zeros(2)
        return np.array([r0 / g00, 0.0]) if fall0 >= fall1 else np.array([0.0, r1 / g11])
    try:  # when the unconstrained solution is feasible it is the solution (most calls)
        x = np.linalg.solve(gram, rhs)
        if (x >= 0.0).all():
            return x
    except np.linalg.LinAlgError:
        pass
    keep, pair, rest = _subsets(p)
    lhs = np.where(pair, gram, 0.0) + rest  # each subset's normal equations, the rest x = 0
    right = (rhs * keep)[:, :, None]
    try:
        x = np.linalg.solve(lhs, right)[:, :, 0]
    except np.linalg.LinAlgError:  # a subset of dependent columns: its least-norm solution
        x = (np.linalg.pinv(lhs) @ right)[:, :, 0]
    # ||a x - b||^2 - ||b||^2, which is 0 at x = 0 (always feasible)
    cost = np.einsum("si,ij,sj->s", x, gram, x) - 2.0 * (x @ rhs)
    cost[~(x >= 0.0).all(axis=1)] = np.inf
    best = int(np.argmin(cost))
    return x[best] if cost[best] < 0.0 else np.zeros(p)
