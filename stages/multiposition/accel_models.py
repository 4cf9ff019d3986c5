"""Accelerometer models fitted on static poses: the six-position method, and the 9-parameter
model (Tedaldi, Pretto and Menegatti, "A robust and easy to implement method for IMU
calibration without external equipments", ICRA 2014; Xiangtan University's patent "Accelerometer
calibration method based on the Frank-Wolfe method", 2023) solved by
Levenberg-Marquardt (scipy) or by Frank-Wolfe (the patent's method), with or without its three
misalignment angles (the 6-parameter model).

9-parameter model (units of the raw input, e.g. m/s^2 or ADC counts, to m/s^2)::

    a = S K (a_t - b),   S = diag(s_x, s_y, s_z),
    K = [[1, -a_yz, a_zy], [0, 1, -a_zx], [0, 0, 1]]   (non-orthogonality, three small angles, rad)

fitted so that |a| = g at rest: minimise ``sum_i (|S K (a_t,i - b)| - g)^2`` over the static
samples (or static-interval means). The patent writes ``S K (a_t + B)``: its ``B`` is ``-b`` here.
The correction exported to the chain is ``matrix = S K``, ``offset = b``.

Both solvers work on the same normalised unknowns ``x`` (9,) around a data-derived start
(:func:`initial_guess`): ``s = s0 (1 + x[0:3])``, angles ``= x[3:6]``, ``b = b0 + r0 x[6:9]``
(``r0`` the median raw radius of the poses), so every unknown is O(1e-2) whatever the raw unit.
Residuals are ``(|a| - g) / g`` (dimensionless).

**Model choice** (:func:`fit_model`, :func:`choose_model`): the 9- and the 6-parameter model are
both fitted and judged by *prediction*: each pose's | |a| - g | predicted by the model fitted on
the other poses (leave-one-pose-out, by the exact-for-linear PRESS formula ``r_i / (1 - h_ii)``,
``h`` the hat matrix of the Jacobian: Allen, Technometrics 1974), combined with the predicted
error over all orientations (below) as ``sqrt(PRESS_rms^2 + predicted^2)``: the model with the
smaller expected error of a new orientation is kept. Where the 9-parameter model cannot be judged (9 poses: every
``h_ii = 1``), the 6-parameter model is kept if its residual is within
:data:`ADEQUATE_FACTOR` times the noise of a pose mean, and the 9-parameter model otherwise
(then nothing is left to check it, and the stage says so). The corrected Akaike criterion
(Hurvich and Tsai, Biometrika 1989), used before, estimates the noise from the residual itself:
at 12 poses its penalty (108 for 9 parameters, 29 for 6) outweighs a residual a thousand times
smaller, and it chose the wrong model; it is still reported.

Each fit also reports its parameters' standard errors (``sigma^2 (J^T J)^-1``, ``sigma^2 =
max(RSS / (n - p), s_m^2)`` with ``s_m`` the noise of one pose mean measured on the poses
themselves: the two halves of each still interval), its *predicted error*: the RMS over 200
directions evenly spread on the sphere (a Fibonacci lattice) of the standard deviation of the
calibrated | |a| - g | that those standard errors imply, in mg -- what the poses leave
undetermined --, and the 95 % bound of that RMS error (:meth:`ModelFit.error_95_mg`; where the
poses cannot see misalignment, it includes misalignment angles of :data:`ANGLE_PRIOR_RAD`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from imupipe.stages.errors import FitError

MG = 9.80665e-3
"""One milli-g in m/s^2 (the unit of the accelerometer metrics)."""


def misalignment_matrix(angles: np.ndarray) -> np.ndarray:
    """K from the three non-orthogonality angles ``(a_yz, a_zy, a_zx)`` (rad)."""
    yz, zy, zx = angles
    return np.array([[1.0, -yz, zy], [0.0, 1.0, -zx], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class NineParams:
    """``scale`` s (3) [(m/s^2)/raw unit], ``angles`` (a_yz, a_zy, a_zx) rad, ``bias`` b (3) raw."""

    scale: np.ndarray
    angles: np.ndarray
    bias: np.ndarray

    @property
    def matrix(self) -> np.ndarray:
        return np.diag(self.scale) @ misalignment_matrix(self.angles)

    def apply(self, raw: np.ndarray) -> np.ndarray:
        return (raw - self.bias) @ self.matrix.T


def sphere_centre(points: np.ndarray) -> np.ndarray:
    """Centre of the sphere through ``points`` (m, 3) by linear least squares:
    ``|p|^2 = 2 c.p + (r^2 - |c|^2)``."""
    a = np.column_stack([2 * points, np.ones(len(points))])
    sol, *_ = np.linalg.lstsq(a, (points**2).sum(axis=1), rcond=None)
    return sol[:3]


def initial_guess(means: np.ndarray, g: float) -> NineParams:
    """Data-derived start: bias = centre of the static means (sphere fit), scale = g / median
    distance of the means from that centre, no misalignment. Works on any raw unit."""
    centre = sphere_centre(means)
    radius = float(np.median(np.linalg.norm(means - centre, axis=1)))
    if not np.isfinite(radius) or radius <= 0:
        raise FitError("cannot derive a start from the static means (they do not span a sphere)")
    return NineParams(np.full(3, g / radius), np.zeros(3), centre)


@dataclass
class NormProblem:
    """``(|S K (a_t - b)| - g) / g`` over ``samples`` (m, 3), unknowns normalised around ``start``."""

    samples: np.ndarray
    g: float
    start: NineParams
    free: np.ndarray = field(default_factory=lambda: np.ones(9, dtype=bool))
    """Which unknowns are fitted (the others stay at the start; e.g. the angles when the poses
    cannot observe misalignment)."""
    radius: float = field(init=False)

    def __post_init__(self) -> None:
        self.samples = np.asarray(self.samples, dtype=np.float64)
        self.radius = self.g / float(np.mean(self.start.scale))

    def params(self, x: np.ndarray) -> NineParams:
        return NineParams(
            self.start.scale * (1 + x[0:3]),
            np.array(x[3:6]),
            self.start.bias + self.radius * x[6:9],
        )

    def _parts(self, x: np.ndarray) -> tuple[NineParams, np.ndarray, np.ndarray, np.ndarray]:
        p = self.params(x)
        v = self.samples - p.bias
        u = v @ misalignment_matrix(p.angles).T
        a = u * p.scale
        return p, v, u, a

    def residual(self, x: np.ndarray) -> np.ndarray:
        a = self._parts(x)[3]
        return (np.linalg.norm(a, axis=1) - self.g) / self.g

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Analytic (m, 9) Jacobian of :meth:`residual`."""
        p, v, u, a = self._parts(x)
        n = np.linalg.norm(a, axis=1)[:, None]
        dn_du = a * p.scale / n  # d|a|/du
        jac = np.empty((len(v), 9))
        jac[:, 0:3] = (a * u / n) * self.start.scale
        jac[:, 3] = -dn_du[:, 0] * v[:, 1]
        jac[:, 4] = dn_du[:, 0] * v[:, 2]
        jac[:, 5] = -dn_du[:, 1] * v[:, 2]
        jac[:, 6:9] = -(dn_du @ misalignment_matrix(p.angles)) * self.radius
        return jac / self.g

    def cost(self, x: np.ndarray) -> float:
        r = self.residual(x)
        return 0.5 * float(r @ r)


@dataclass
class Solution:
    params: NineParams
    x: np.ndarray
    info: dict[str, Any]


def solve_lm(problem: NormProblem, *, xtol: float = 1e-12, max_nfev: int = 200) -> Solution:
    """Levenberg-Marquardt (``scipy.optimize.least_squares(method="lm")``, analytic Jacobian)."""
    t0 = time.perf_counter()
    free = problem.free

    def full(z: np.ndarray) -> np.ndarray:
        x = np.zeros(9)
        x[free] = z
        return x

    res = least_squares(
        lambda z: problem.residual(full(z)),
        np.zeros(int(free.sum())),
        jac=lambda z: problem.jacobian(full(z))[:, free],
        method="lm",
        xtol=xtol,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=max_nfev,
    )
    info = {
        "solver": "scipy.optimize.least_squares(method='lm')",
        "iterations": int(res.njev if res.njev is not None else res.nfev),
        "function_evaluations": int(res.nfev),
        "time_s": time.perf_counter() - t0,
        "cost": float(res.cost),
        "stop": res.message,
    }
    return Solution(problem.params(full(res.x)), full(res.x), info)


def solve_frank_wolfe(
    problem: NormProblem,
    *,
    box: np.ndarray | None = None,
    max_iter: int = 20000,
    gap_rtol: float = 1e-2,
    rms_tol: float = 1e-5,
    x0: np.ndarray | None = None,
) -> Solution:
    """Frank-Wolfe (conditional gradient) over the box ``|x_j| <= box_j`` (the patent's method).

    Objective ``f(x) = 0.5 sum r_i(x)^2``, gradient ``J^T r``. Each iteration: the linear
    minimisation oracle over the box gives the vertex ``s = -box * sign(grad)``; direction
    ``d = s - x``; step ``gamma`` in [0, 1] from the Gauss-Newton model along ``d``
    (``-(r . J d) / |J d|^2``), halved until ``f`` decreases (Armijo, up to 30 times).
    Stopping rule: the Frank-Wolfe duality gap ``-grad . d`` (an upper bound of ``f - f*`` where
    the objective is convex) falls below ``max(gap_rtol * f, m rms_tol^2 / 2)``: the cost is
    within a fraction ``gap_rtol`` of the best in the box, or the RMS residual (fraction of g) is
    within ``sqrt(rms^2 - rms*^2) <= rms_tol`` of it (1e-5 g ~ 0.01 mg); or ``max_iter``.
    The default box is +-5 % on scale and bias (bias relative to g) and +-0.05 rad on the angles
    around the data-derived start; ``x0`` (inside the box) is the first iterate (default the
    start). The result reports ``active_bounds``: the unknowns that end on the box with the
    gradient pushing outward (:func:`solve_frank_wolfe_enlarging` enlarges those).
    """
    t0 = time.perf_counter()
    if box is None:
        box = np.full(9, 0.05)
    box = np.where(problem.free, box, 0.0)
    x = np.zeros(9) if x0 is None else np.clip(np.asarray(x0, dtype=float), -box, box)
    r = problem.residual(x)
    f = 0.5 * float(r @ r)
    n_eval = 1
    stop = f"max_iter ({max_iter}) reached"
    gap = np.inf
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported)
        jac = problem.jacobian(x)
        grad = jac.T @ r
        d = np.where(grad > 0, -box, box) - x
        gap = float(-grad @ d)
        if gap <= max(gap_rtol * f, 0.5 * len(r) * rms_tol**2):
            stop = f"duality gap {gap:.3g} <= max(gap_rtol * cost, m * rms_tol^2 / 2)"
            break
        jd = jac @ d
        denom = float(jd @ jd)
        gamma = min(max(-float(r @ jd) / denom, 0.0), 1.0) if denom > 0 else 1.0
        for _ in range(30):
            r_new = problem.residual(x + gamma * d)
            n_eval += 1
            f_new = 0.5 * float(r_new @ r_new)
            if f_new <= f - 1e-4 * gamma * gap:
                break
            gamma *= 0.5
        else:
            stop = "line search found no decrease"
            break
        x = x + gamma * d
        r, f = r_new, f_new
    grad = problem.jacobian(x).T @ r
    active = (box > 0) & (np.abs(x) >= ACTIVE_FRACTION * box) & (grad * np.sign(x) < 0)
    info = {
        "solver": "frank_wolfe",
        "iterations": it,
        "function_evaluations": n_eval,
        "time_s": time.perf_counter() - t0,
        "cost": f,
        "duality_gap": gap,
        "stop": stop,
        "box": box.tolist(),
        "active_bounds": [UNKNOWNS[j] for j in np.flatnonzero(active)],
    }
    return Solution(problem.params(x), x, info)


ACTIVE_FRACTION = 0.9
"""An unknown beyond this fraction of its box half-width, with the gradient pushing it outward,
is on an active bound: the optimum may lie outside the box."""

UNKNOWNS = ("scale_x", "scale_y", "scale_z", "a_yz", "a_zy", "a_zx", "bias_x", "bias_y", "bias_z")
"""Names of the nine normalised unknowns (for messages)."""


def solve_frank_wolfe_enlarging(
    problem: NormProblem,
    *,
    box: np.ndarray,
    max_enlargements: int = 8,
    **kwargs: Any,
) -> Solution:
    """Frank-Wolfe that never stops on its box: while the solution has active bounds (see
    :func:`solve_frank_wolfe`), the half-widths of those unknowns are doubled and the problem is
    solved again from the last iterate. ``FitError`` naming the unknowns still on their bound
    after ``max_enlargements`` doublings. ``info`` adds ``box_enlargements``, the iterations and
    time summed over the solves, and the box it ended with."""
    box = np.asarray(box, dtype=float).copy()
    x0 = None
    total_iter = total_eval = 0
    total_time = 0.0
    for enlargement in range(max_enlargements + 1):
        sol = solve_frank_wolfe(problem, box=box, x0=x0, **kwargs)
        total_iter += sol.info["iterations"]
        total_eval += sol.info["function_evaluations"]
        total_time += sol.info["time_s"]
        active = [UNKNOWNS.index(name) for name in sol.info["active_bounds"]]
        if not active:
            break
        if enlargement == max_enlargements:
            names = ", ".join(sol.info["active_bounds"])
            raise FitError(
                f"frank_wolfe: {names} still on the bound of a box enlarged {max_enlargements} "
                f"times (half-widths {np.round(box[active], 4).tolist()}): the start is far from "
                "the optimum; check the units, or use method lm"
            )
        box[active] *= 2
        x0 = sol.x
    sol.info.update(
        {
            "box_enlargements": enlargement,
            "iterations": total_iter,
            "function_evaluations": total_eval,
            "time_s": total_time,
            "box": box.tolist(),
        }
    )
    return sol


def uncertainty(problem: NormProblem, x: np.ndarray, sigma2: float | None = None) -> dict[str, Any]:
    """Parameter standard deviations from ``sigma^2 (J^T J)^-1`` (sigma^2 = residual variance per
    degree of freedom, or ``sigma2`` when given: :attr:`ModelFit.sigma2`) and the condition
    number of the column-normalised Jacobian."""
    free = problem.free
    jac = problem.jacobian(x)[:, free]
    r = problem.residual(x)
    dof = len(r) - int(free.sum())
    norms = np.linalg.norm(jac, axis=0)
    norms[norms == 0] = 1.0
    sv = np.linalg.svd(jac / norms, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    out: dict[str, Any] = {"condition_number": cond, "degrees_of_freedom": dof}
    if sigma2 is None:
        sigma2 = float(r @ r) / dof if dof > 0 else 0.0
    if not sigma2 > 0 or not np.isfinite(cond):
        return out
    cov = np.linalg.pinv(jac.T @ jac) * sigma2
    std = np.zeros(9)
    std[free] = np.sqrt(np.maximum(np.diag(cov), 0))
    out["scale_std"] = (std[0:3] * problem.start.scale).tolist()
    out["misalignment_std_rad"] = std[3:6].tolist()
    out["bias_std"] = (std[6:9] * problem.radius).tolist()
    return out


def six_position(means: np.ndarray, g: float, max_angle_deg: float = 30.0) -> NineParams:
    """The six-position method: per axis ``b = (max + min) / 2``, ``k = 2 g / (max - min)`` over the static
    means; the max (min) must come from a pose with that axis up (down) within ``max_angle_deg``
    (directions taken about the sphere centre of the means, so raw counts work).
    ``FitError`` naming the missing face otherwise."""
    centred = means - sphere_centre(means)
    unit = centred / np.linalg.norm(centred, axis=1)[:, None]
    cos_max = np.cos(np.radians(max_angle_deg))
    hi = np.empty(3)
    lo = np.empty(3)
    for axis, name in enumerate("xyz"):
        i_hi = int(np.argmax(means[:, axis]))
        i_lo = int(np.argmin(means[:, axis]))
        for sign, i in (("+", i_hi), ("-", i_lo)):
            along = unit[i, axis] if sign == "+" else -unit[i, axis]
            if along < cos_max:
                raise FitError(
                    f"six_position: no static pose with {sign}{name} along gravity (the best is "
                    f"{np.degrees(np.arccos(np.clip(along, -1, 1))):.0f} deg off; "
                    f"need <= {max_angle_deg:g}); record all six faces"
                )
        hi[axis], lo[axis] = means[i_hi, axis], means[i_lo, axis]
    return NineParams(2 * g / (hi - lo), np.zeros(3), (hi + lo) / 2)


def distinct_poses(means: np.ndarray, min_angle_deg: float = 10.0) -> int:
    """How many interval means point in directions at least ``min_angle_deg`` apart (greedy),
    about the sphere centre of the means."""
    centred = means - sphere_centre(means)
    unit = centred / np.linalg.norm(centred, axis=1)[:, None]
    cos_min = np.cos(np.radians(min_angle_deg))
    kept: list[np.ndarray] = []
    for u in unit:  # m intervals (tens), not samples
        if all(float(u @ k) < cos_min for k in kept):
            kept.append(u)
    return len(kept)


# -- model choice ----------------------------------------------------------------------------

MODEL_FREE: dict[str, np.ndarray] = {
    "9-parameter": np.ones(9, dtype=bool),
    "6-parameter": np.r_[np.ones(3, dtype=bool), np.zeros(3, dtype=bool), np.ones(3, dtype=bool)],
}
"""The models and which unknowns each fits (the 6-parameter model keeps the angles at 0)."""


def fibonacci_sphere(n: int = 200) -> np.ndarray:
    """(n, 3) unit vectors evenly spread over the sphere (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * i / n)
    azimuth = np.pi * (1 + 5**0.5) * i
    return np.column_stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)]
    )


SPHERE = fibonacci_sphere()
ADEQUATE_FACTOR = 3.0
"""With 9 poses (the 9-parameter model cannot be judged by prediction), the 6-parameter model is
kept while its | |a| - g | RMS is at most this many times the noise of a pose mean."""
ANGLE_PRIOR_RAD = 0.01
"""rad: standard deviation of the misalignment angles a 6-parameter answer assumes where its
poses cannot see them (the six faces): cross-axis sensitivity of +-2 % (95 %), the datasheet
figure of MEMS accelerometers (ADXL355 +-1 %, BMI088 +-1 %, ICM-42688 +-2 %)."""
ERROR_DRAWS = 4000
"""Monte Carlo draws behind :meth:`ModelFit.error_95_mg` (fixed seed: the same data give the
same bound)."""


@dataclass
class ModelFit:
    """One model fitted by Levenberg-Marquardt on the pose means, with its statistics."""

    name: str
    problem: NormProblem
    solution: Solution
    mean_noise: float = 0.0
    """Noise of one pose mean along gravity, fraction of g (0: unknown)."""
    angles_unseen: bool = False
    """The poses cannot see misalignment (a 6-parameter fit where the 9-parameter one cannot be
    judged): :meth:`error_95_mg` adds angles of :data:`ANGLE_PRIOR_RAD`."""

    @property
    def params(self) -> NineParams:
        return self.solution.params

    @property
    def n_params(self) -> int:
        return int(self.problem.free.sum())

    @property
    def residual_mg(self) -> np.ndarray:
        """Signed | |a| - g | per pose, mg."""
        return self.problem.residual(self.solution.x) * self.problem.g / MG

    @property
    def rss(self) -> float:
        r = self.problem.residual(self.solution.x)
        return float(r @ r)

    @property
    def aicc(self) -> float:
        return aicc(len(self.problem.samples), self.n_params, self.rss)

    def covariance(self) -> np.ndarray | None:
        """Covariance of the free normalised unknowns, ``sigma^2 (J^T J)^-1`` (None without
        degrees of freedom)."""
        sigma2 = self.sigma2
        if not sigma2 > 0:
            return None
        jac = self.problem.jacobian(self.solution.x)[:, self.problem.free]
        return np.linalg.pinv(jac.T @ jac) * sigma2

    @property
    def dof(self) -> int:
        return len(self.problem.samples) - self.n_params

    @property
    def sigma2(self) -> float:
        """Variance of one pose's residual (fraction of g squared): the residual variance per
        degree of freedom, never below the measured noise of a pose mean (0: undetermined)."""
        fitted = self.rss / self.dof if self.dof > 0 else 0.0
        return max(fitted, self.mean_noise**2) if self.dof > 0 or self.mean_noise > 0 else 0.0

    def press_mg(self) -> np.ndarray:
        """Each pose's | |a| - g | (mg) predicted by the model fitted on the other poses,
        linearised (PRESS: ``r_i / (1 - h_ii)``); infinite where a pose alone determines a
        parameter (``h_ii = 1``)."""
        jac = self.problem.jacobian(self.solution.x)[:, self.problem.free]
        r = self.residual_mg
        q, _ = np.linalg.qr(jac)
        h = np.sum(q * q, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.where(h < 1 - 1e-9, r / (1 - h), np.inf)
        return out

    def expected_error_mg(self) -> float:
        """What the model choice minimises: ``sqrt(PRESS_rms^2 + predicted^2)`` (mg), the misfit a
        left-out pose sees plus the spread the poses leave over all orientations (a model of 9
        parameters on 10 poses can predict its poses and still leave most orientations
        undetermined)."""
        return float(np.hypot(self.press_rms_mg(), self.predicted_error_mg()))

    def press_rms_mg(self) -> float:
        """RMS of :meth:`press_mg` (infinite where a pose is not predicted)."""
        p = self.press_mg()
        return float(np.sqrt(np.mean(p**2))) if np.all(np.isfinite(p)) else float("inf")

    def sphere_jacobian(self) -> np.ndarray:
        """(200, 9) derivative of the calibrated | |a| - g | (fraction of g) over the sphere with
        respect to the normalised unknowns."""
        p = self.params
        raw = (self.problem.g * SPHERE) @ np.linalg.inv(p.matrix).T + p.bias
        on_sphere = NormProblem(raw, self.problem.g, self.problem.start, self.problem.free)
        return on_sphere.jacobian(self.solution.x)

    def error_95_mg(self) -> float:
        """95 % bound (mg) of the RMS over the sphere of the calibrated | |a| - g | error:
        the 95th percentile over :data:`ERROR_DRAWS` draws of the unknowns from their covariance
        (its variance drawn from its scaled inverse chi-square: with the residual's degrees of
        freedom where it comes from the residual, else with one per pose, the half-differences
        :attr:`mean_noise` is measured from), plus unseen misalignment (:attr:`angles_unseen`)."""
        cov = self.covariance()
        if cov is None:
            return float("inf")
        try:
            jac = self.sphere_jacobian()
        except np.linalg.LinAlgError:
            return float("inf")
        rng = np.random.default_rng(0)
        free = self.problem.free
        try:
            chol = np.linalg.cholesky(cov + 1e-30 * np.eye(len(cov)))
        except np.linalg.LinAlgError:  # singular to rounding (a dead axis): a symmetric root
            w, v = np.linalg.eigh((cov + cov.T) / 2)
            chol = v * np.sqrt(np.clip(w, 0.0, None))
        dx = rng.standard_normal((ERROR_DRAWS, len(cov))) @ chol.T
        if self.dof > 0 and self.rss / self.dof >= self.mean_noise**2:
            dx *= np.sqrt(self.dof / rng.chisquare(self.dof, ERROR_DRAWS))[:, None]
        else:  # the measured noise of a pose mean: one half-difference per pose, as many dof
            poses = len(self.problem.samples)
            dx *= np.sqrt(poses / rng.chisquare(poses, ERROR_DRAWS))[:, None]
        err = dx @ jac[:, free].T
        if self.angles_unseen:
            angles = rng.normal(0.0, ANGLE_PRIOR_RAD, (ERROR_DRAWS, 3))
            err = err + angles @ jac[:, 3:6].T
        rms_draws = np.sqrt(np.mean(err**2, axis=1))
        return float(np.quantile(rms_draws, 0.95) * self.problem.g / MG)

    def predicted_error_mg(self) -> float:
        """RMS over the sphere of the standard deviation of the calibrated | |a| - g | (mg)."""
        cov = self.covariance()
        if cov is None:
            return float("inf")
        try:
            jac = self.sphere_jacobian()[:, self.problem.free]
        except np.linalg.LinAlgError:  # a scale or angle fitted to nothing: undetermined
            return float("inf")
        var = np.einsum("ij,jk,ik->i", jac, cov, jac)
        return float(np.sqrt(np.mean(var)) * self.problem.g / MG)

    def leave_one_out_mg(self) -> np.ndarray:
        """Each pose's | |a| - g | (mg) predicted by the model fitted on the other poses
        (NaN where the others cannot support the fit)."""
        means = self.problem.samples
        out = np.full(len(means), np.nan)
        if len(means) - 1 < self.n_params:
            return out
        for i in range(len(means)):  # one small LM fit per pose (tens of poses)
            keep = np.arange(len(means)) != i
            try:
                sub = NormProblem(
                    means[keep], self.problem.g, self.problem.start, self.problem.free
                )
                params = solve_lm(sub).params
            except (FitError, np.linalg.LinAlgError, ValueError):
                continue
            out[i] = (np.linalg.norm(params.apply(means[i : i + 1])) - self.problem.g) / MG
        return out

    def summary(self) -> dict[str, Any]:
        """The figures the results report for this model."""
        r = self.residual_mg
        aicc = self.aicc
        return {
            "parameters": self.n_params,
            "aicc": float(aicc) if np.isfinite(aicc) else None,
            "residual_mg_rms": float(np.sqrt(np.mean(r**2))),
            "leave_one_pose_out_mg_rms": finite_or_none(self.press_rms_mg()),
            "predicted_error_mg": finite_or_none(self.predicted_error_mg()),
        }


def aicc(n: int, n_params: int, rss: float) -> float:
    """Corrected Akaike information criterion of a least-squares fit of ``n_params`` parameters
    to ``n`` observations with residual sum of squares ``rss`` (Hurvich and Tsai 1989):
    ``n ln(rss / n) + 2K + 2K(K + 1) / (n - K - 1)``, ``K = n_params + 1`` (the noise variance
    counts); infinite where ``n - K - 1 <= 0`` (too few observations to support the fit)."""
    k = n_params + 1
    if n - k - 1 <= 0:
        return float("inf")
    return float(n * np.log(max(rss, 1e-300) / n) + 2 * k + 2 * k * (k + 1) / (n - k - 1))


def fmt_criterion(value: float) -> str:
    """An information criterion for a message ("undefined" where infinite)."""
    return f"{value:.4g}" if np.isfinite(value) else "undefined (too few observations)"


def finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def fit_model(
    means: np.ndarray,
    g: float,
    name: str,
    start: NineParams | None = None,
    mean_noise: float = 0.0,
) -> ModelFit:
    """Fit the model ``name`` (a key of :data:`MODEL_FREE`) on the pose means by LM;
    ``mean_noise``: the noise of one pose mean along gravity (fraction of g)."""
    start = start if start is not None else initial_guess(means, g)
    problem = NormProblem(means, g, start, MODEL_FREE[name].copy())
    if len(means) < problem.free.sum():
        raise FitError(
            f"{len(means)} static intervals: the {name} model needs at least {problem.free.sum()}"
        )
    return ModelFit(name, problem, solve_lm(problem), mean_noise)


def choose_model(fits: list[ModelFit], asked: Sequence[str] = ()) -> tuple[ModelFit, str]:
    """The model that predicts left-out poses best (see the module docstring), and the reason in
    one sentence. ``asked``: the models the options allowed; one of them missing from ``fits``
    had more parameters than poses."""
    n = len(fits[0].problem.samples)
    if len(fits) == 1:
        best = fits[0]
        short = [
            f"the {m} model needs at least {int(MODEL_FREE[m].sum())}"
            for m in asked
            if m not in {f.name for f in fits}
        ]
        best.angles_unseen = best.name == "6-parameter" and bool(short)
        if short:
            return best, f"{n} poses: " + "; ".join(short)
        return best, f"the {best.name} model was asked for"
    judged = [f for f in fits if np.isfinite(f.press_rms_mg())]
    figures = "; ".join(
        f"{f.name}: leave-one-pose-out {_fmt_mg(f.press_rms_mg())}, predicted error over all "
        f"orientations {_fmt_mg(f.predicted_error_mg())}, residual "
        f"{f.summary()['residual_mg_rms']:.3g} mg"
        for f in sorted(fits, key=lambda f: f.expected_error_mg())
    )
    if len(judged) == len(fits):
        best = min(fits, key=lambda f: (f.expected_error_mg(), f.n_params))
        return best, f"best prediction of left-out poses and of all orientations ({figures})"
    small = min(fits, key=lambda f: f.n_params)
    large = max(fits, key=lambda f: f.n_params)
    noise_mg = small.mean_noise * small.problem.g / MG
    residual = small.summary()["residual_mg_rms"]
    if noise_mg > 0 and residual <= ADEQUATE_FACTOR * noise_mg:
        small.angles_unseen = True
        return small, (
            f"{n} poses cannot judge the {large.name} model by prediction; the {small.name} "
            f"model's residual {residual:.3g} mg is within {ADEQUATE_FACTOR:g} x the noise of a "
            f"pose mean ({noise_mg:.3g} mg)"
        )
    return large, (
        f"the {small.name} model leaves {residual:.3g} mg against a pose-mean noise of "
        f"{noise_mg:.3g} mg (the sensor is misaligned); the {large.name} model fits the {n} "
        "poses exactly, with nothing left to check it"
    )


def _fmt_mg(value: float) -> str:
    return f"{value:.4g} mg" if np.isfinite(value) else "unbounded"
