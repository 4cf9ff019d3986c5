"""Ellipsoid fitting for magnetometer calibration (Li & Griffiths 2004, Magneto, ArduPilot).

Model. A magnetometer with hard iron ``c`` (3,) and soft iron reads points ``h`` on an ellipsoid
``|W (h - c)| = 1`` with ``W`` symmetric positive definite (3x3, inverse length). The correction
``R * W @ (h - c)`` maps them onto a sphere of radius ``R`` centred at the origin; a symmetric
``W`` adds no rotation to the sensor frame. Units are those of the points (tesla in the pipeline).

Fits (all on points shifted to their centroid and scaled to unit RMS, for conditioning):

- :func:`fit_sphere`: ``|h|^2 = 2 c.h + k`` by linear least squares; ``W = I / R``.
- :func:`fit_axis_aligned`: the axis-aligned ellipsoid ``a x^2 + b y^2 + c z^2 + d x + e y + f z = 1`` by linear
  least squares; centre ``-d/(2a)``..., radii ``sqrt(G/a)``... with
  ``G = 1 + d^2/(4a) + e^2/(4b) + f^2/(4c)``; ``W = diag(1/radii)``.
- :func:`fit_li_griffiths`: the ellipsoid-specific algebraic fit of Li & Griffiths (2004) with
  ``k = 4`` (the fit Magneto uses): the general quadric ``x'Mx + 2n'x + d = 0`` under the
  constraint ``4J - I^2 = 1``; centre ``-M^-1 n``, ``W = sqrtm(M / (n'M^-1 n - d))``.
- :func:`refine`: Levenberg-Marquardt (``scipy.optimize.least_squares``, analytic Jacobian) on the
  residual ``|W (h - c)| - 1``, i.e. the distance of the corrected point from the unit sphere (the
  geometric error in the calibrated space, ArduPilot's ellipsoid fitness), with ``W`` constrained
  to ``w I`` (sphere), diagonal (axis_aligned) or symmetric (general).

Robustness helpers: :func:`thin_by_direction` (cap the samples per direction cell so over-sampled
orientations do not pull the fit), :func:`inliers` (k-sigma on the residuals with a MAD sigma),
:func:`white_part_std` (the per-sample noise of a time-ordered residual series),
:func:`direction_spread` (the coverage check: eigenvalues of the covariance of the unit directions;
a full sphere gives 1/3 each, planar data or a narrow cone gives ~0 for the smallest).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.linalg import eigh
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

Model = Literal["sphere", "axis_aligned", "general"]
MODELS: tuple[str, ...] = ("sphere", "axis_aligned", "general")


class EllipsoidFitError(ValueError):
    """The points cannot support the fit (too few, degenerate, not an ellipsoid)."""


@dataclass(frozen=True)
class Ellipsoid:
    """Points ``h`` with ``|W (h - centre)| = 1``; ``shape`` is ``W`` (symmetric positive definite)."""

    centre: np.ndarray
    shape: np.ndarray

    @property
    def radii(self) -> np.ndarray:
        """Semi-axis lengths, ascending (units of the points)."""
        return 1.0 / np.linalg.eigvalsh(self.shape)[::-1]

    @property
    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(radii, rotation)``: radii largest first; column i of ``rotation`` (a proper
        rotation) is the direction of semi-axis i."""
        values, vectors = np.linalg.eigh(self.shape)
        if np.linalg.det(vectors) < 0:
            vectors[:, 2] *= -1
        return 1.0 / values, vectors

    @property
    def mean_radius(self) -> float:
        """The radius of the sphere of equal volume: ``det(W)^(-1/3)``."""
        return float(np.linalg.det(self.shape) ** (-1.0 / 3.0))

    def to_unit(self, points: np.ndarray) -> np.ndarray:
        """``W (h - centre)`` for (n, 3) points: on the unit sphere when the fit is exact."""
        return (np.asarray(points, dtype=np.float64) - self.centre) @ self.shape.T

    def residuals(self, points: np.ndarray) -> np.ndarray:
        """``|W (h - centre)| - 1`` (dimensionless; multiply by the radius for point units)."""
        return np.linalg.norm(self.to_unit(points), axis=1) - 1.0


@dataclass(frozen=True)
class _Frame:
    """Normalising frame: ``q = (h - mean) / scale``."""

    mean: np.ndarray
    scale: float

    @classmethod
    def of(cls, points: np.ndarray) -> _Frame:
        mean = points.mean(axis=0)
        scale = float(np.sqrt(((points - mean) ** 2).sum(axis=1).mean()))
        if not np.isfinite(scale) or scale <= 0:
            raise EllipsoidFitError("the points are all equal")
        return cls(mean, scale)

    def forward(self, points: np.ndarray) -> np.ndarray:
        return (points - self.mean) / self.scale

    def back(self, e: Ellipsoid) -> Ellipsoid:
        return Ellipsoid(self.mean + self.scale * e.centre, e.shape / self.scale)


def _points(points: np.ndarray, minimum: int) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise EllipsoidFitError(f"expected (n, 3) points, got shape {points.shape}")
    if len(points) < minimum:
        raise EllipsoidFitError(f"{len(points)} points; the fit needs at least {minimum}")
    return points


def _spd_sqrt(matrix: np.ndarray) -> np.ndarray:
    """Symmetric square root of a symmetric positive-definite matrix."""
    values, vectors = np.linalg.eigh((matrix + matrix.T) / 2)
    if values.min() <= 0:
        raise EllipsoidFitError("the fitted quadric is not an ellipsoid")
    return (vectors * np.sqrt(values)) @ vectors.T


def fit_sphere(points: np.ndarray) -> Ellipsoid:
    """Algebraic sphere fit: ``|h|^2 = 2 c.h + k``, ``R = sqrt(k + |c|^2)``."""
    points = _points(points, 4)
    frame = _Frame.of(points)
    q = frame.forward(points)
    design = np.column_stack([2 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(design, (q * q).sum(axis=1), rcond=None)
    centre, k = sol[:3], sol[3]
    r2 = k + centre @ centre
    if not np.isfinite(r2) or r2 <= 0:
        raise EllipsoidFitError("the sphere fit failed")
    return frame.back(Ellipsoid(centre, np.eye(3) / np.sqrt(r2)))


def fit_axis_aligned(points: np.ndarray) -> Ellipsoid:
    """The axis-aligned ellipsoid ``a x^2 + b y^2 + c z^2 + d x + e y + f z = 1`` by linear
    least squares."""
    points = _points(points, 6)
    frame = _Frame.of(points)
    q = frame.forward(points)
    design = np.column_stack([q * q, q])
    sol, *_ = np.linalg.lstsq(design, np.ones(len(q)), rcond=None)
    quad, lin = sol[:3], sol[3:]
    if np.any(quad <= 0):
        raise EllipsoidFitError("the axis-aligned fit is not an ellipsoid")
    centre = -lin / (2 * quad)
    g = 1.0 + np.sum(lin * lin / (4 * quad))
    radii = np.sqrt(g / quad)
    return frame.back(Ellipsoid(centre, np.diag(1.0 / radii)))


_LG_CONSTRAINT = np.zeros((6, 6))
_LG_CONSTRAINT[:3, :3] = np.array([[-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, -1.0]])
_LG_CONSTRAINT[3:, 3:] = -4.0 * np.eye(3)
"""Li & Griffiths' constraint matrix for ``k = 4`` (``4J - I^2 = 1``)."""


def fit_li_griffiths(points: np.ndarray) -> Ellipsoid:
    """Li & Griffiths (2004) ellipsoid-specific least squares, ``k = 4`` (Magneto's fit).

    Design rows ``[x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1]``; the quadric's 6 quadratic
    coefficients are the eigenvector of ``C^-1 (S11 - S12 S22^-1 S21)`` with the largest
    eigenvalue, the 4 others ``-S22^-1 S21 v1``.
    """
    points = _points(points, 10)
    frame = _Frame.of(points)
    q = frame.forward(points)
    x, y, z = q.T
    design = np.column_stack(
        [x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones(len(q))]
    )
    s = design.T @ design
    s11, s12, s22 = s[:6, :6], s[:6, 6:], s[6:, 6:]
    try:
        s22_s21 = np.linalg.solve(s22, s12.T)
    except np.linalg.LinAlgError:
        raise EllipsoidFitError("the ellipsoid fit is singular (degenerate points)") from None
    reduced = s11 - s12 @ s22_s21
    values, vectors = np.linalg.eig(np.linalg.solve(_LG_CONSTRAINT, reduced))
    values = np.real(values)
    v1 = np.real(vectors[:, int(np.argmax(values))])
    v2 = -s22_s21 @ v1
    a, b, c, f, g, h = v1
    m = np.array([[a, h, g], [h, b, f], [g, f, c]])
    n = v2[:3]
    d = v2[3]
    try:
        centre = -np.linalg.solve(m, n)
    except np.linalg.LinAlgError:
        raise EllipsoidFitError("the ellipsoid fit is singular (degenerate points)") from None
    level = n @ np.linalg.solve(m, n) - d
    if not np.isfinite(level) or level == 0:
        raise EllipsoidFitError("the ellipsoid fit is degenerate")
    return frame.back(Ellipsoid(centre, _spd_sqrt(m / level)))


ALGEBRAIC = {"sphere": fit_sphere, "axis_aligned": fit_axis_aligned, "general": fit_li_griffiths}
"""Model -> its closed-form (algebraic) fit, the starting point of :func:`refine`."""

_SYM = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))


def _shape_params(shape: np.ndarray, model: str) -> np.ndarray:
    if model == "sphere":
        return np.array([np.trace(shape) / 3.0])
    if model == "axis_aligned":
        return np.diag(shape).copy()
    return np.array([shape[i, j] for i, j in _SYM])


def _shape(params: np.ndarray, model: str) -> np.ndarray:
    if model == "sphere":
        return params[0] * np.eye(3)
    if model == "axis_aligned":
        return np.diag(params)
    w = np.empty((3, 3))
    for value, (i, j) in zip(params, _SYM, strict=True):
        w[i, j] = w[j, i] = value
    return w


def _jacobian(q: np.ndarray, c: np.ndarray, w: np.ndarray, model: str) -> np.ndarray:
    """(n, 3 + k) derivatives of ``r_i = |W (q_i - c)| - 1`` by the centre and ``model``'s k
    shape parameters (:func:`_shape_params` order)."""
    d = q - c
    u = d @ w.T
    e = u / np.maximum(np.linalg.norm(u, axis=1), 1e-300)[:, None]
    d_centre = -e @ w
    if model == "sphere":
        d_shape = (e * d).sum(axis=1)[:, None]
    elif model == "axis_aligned":
        d_shape = e * d
    else:
        d_shape = np.column_stack(
            [e[:, i] * d[:, j] + (e[:, j] * d[:, i] if i != j else 0.0) for i, j in _SYM]
        )
    return np.column_stack([d_centre, d_shape])


def standard_errors(points: np.ndarray, e: Ellipsoid, model: str) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors of a geometric fit ``e`` of ``model`` to ``points``: of the centre (3,
    units of the points) and of the diagonal of the unit-determinant shape
    ``W / det(W)^(1/3)`` (3,, the soft-iron scales the correction applies). Covariance of the
    parameters ``s^2 (J'J)^-1`` with ``J`` the residuals' Jacobian at the fit and ``s^2`` the
    residual sum of squares over ``n - p`` (Gauss-Newton, e.g. Seber & Wild 1989, 5.1); the
    scales' by the delta method (central differences). NaN without degrees of freedom."""
    points = np.asarray(points, dtype=np.float64)
    frame = _Frame.of(points)
    q = frame.forward(points)
    c = (e.centre - frame.mean) / frame.scale
    w = e.shape * frame.scale
    p = np.concatenate([c, _shape_params(w, model)])
    dof = len(q) - len(p)
    if dof <= 0:
        return np.full(3, np.nan), np.full(3, np.nan)
    r = np.linalg.norm((q - c) @ w.T, axis=1) - 1.0
    cov = np.linalg.pinv((j := _jacobian(q, c, w, model)).T @ j) * float(r @ r) / dof

    def scales(params: np.ndarray) -> np.ndarray:
        shape = _shape(params[3:], model)
        return np.diag(shape) / np.linalg.det(shape) ** (1.0 / 3.0)

    grad = np.empty((3, len(p)))
    for k in range(len(p)):
        h = 1e-6 * max(abs(p[k]), 1.0)
        up, down = p.copy(), p.copy()
        up[k] += h
        down[k] -= h
        grad[:, k] = (scales(up) - scales(down)) / (2 * h)
    centre_se = frame.scale * np.sqrt(np.maximum(np.diag(cov)[:3], 0.0))
    scale_se = np.sqrt(np.maximum(np.einsum("ik,kl,il->i", grad, cov, grad), 0.0))
    return centre_se, scale_se


def refine(points: np.ndarray, start: Ellipsoid, model: str, max_nfev: int = 200) -> Ellipsoid:
    """Levenberg-Marquardt on ``r_i = |W (h_i - c)| - 1`` from ``start`` (see the module doc)."""
    points = _points(points, {"sphere": 4, "axis_aligned": 6, "general": 9}[model])
    frame = _Frame.of(points)
    q = frame.forward(points)
    s0 = Ellipsoid((start.centre - frame.mean) / frame.scale, start.shape * frame.scale)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return p[:3], _shape(p[3:], model)

    def fun(p: np.ndarray) -> np.ndarray:
        c, w = unpack(p)
        return np.linalg.norm((q - c) @ w.T, axis=1) - 1.0

    def jac(p: np.ndarray) -> np.ndarray:
        return _jacobian(q, *unpack(p), model)

    p0 = np.concatenate([s0.centre, _shape_params(s0.shape, model)])
    sol = least_squares(fun, p0, jac=jac, method="lm", max_nfev=max_nfev, xtol=1e-12, ftol=1e-12)
    if not np.all(np.isfinite(sol.x)):
        raise EllipsoidFitError("the Levenberg-Marquardt refinement diverged")
    c, w = unpack(sol.x)
    w = (w + w.T) / 2
    values, vectors = np.linalg.eigh(w)
    if values.min() <= 0:
        if values.max() < 0:  # the sign of W is free in |W d|: flip it
            w = -w
        else:
            raise EllipsoidFitError("the refined fit is not an ellipsoid")
    return frame.back(Ellipsoid(c, w))


def fit(points: np.ndarray, model: str, *, geometric: bool = True) -> Ellipsoid:
    """The closed-form fit of ``model``, refined by :func:`refine` when ``geometric``."""
    if model not in ALGEBRAIC:
        raise ValueError(f"unknown model {model!r} (known: {', '.join(MODELS)})")
    start = ALGEBRAIC[model](points)
    return refine(points, start, model) if geometric else start


def inliers(residuals: np.ndarray, k: float) -> np.ndarray:
    """Mask of ``|r - median(r)| <= k * sigma`` with ``sigma = 1.4826 * MAD`` (robust k-sigma)."""
    residuals = np.asarray(residuals, dtype=np.float64)
    centre = np.median(residuals)
    sigma = 1.4826 * np.median(np.abs(residuals - centre))
    if sigma <= 0:
        sigma = float(np.std(residuals))
    if sigma <= 0:
        return np.ones(len(residuals), dtype=bool)
    return np.abs(residuals - centre) <= k * sigma


def white_part_std(series: np.ndarray, clip: float = 5.0) -> float:
    """Std of the white (sample-to-sample) part of a time-ordered series: the std of its second
    differences over sqrt(6) (a white sequence's second difference has 6 times its variance;
    a part that changes slowly from sample to sample, such as a calibration residual that
    depends on the direction of a slowly turning sensor, cancels). Differences beyond ``clip``
    robust sigmas (spikes, a jump) are left out."""
    series = np.asarray(series, dtype=np.float64)
    if len(series) < 8:
        return float("nan")
    d2 = np.diff(series, n=2)
    d2 = d2[inliers(d2, clip)]
    return float(np.sqrt(np.mean(d2 * d2) / 6.0))


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` nearly uniform unit vectors (Fibonacci lattice): the centres of direction cells."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5**0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def direction_cells(directions: np.ndarray, cells: int) -> np.ndarray:
    """Index of the nearest of ``cells`` equal-area direction cells for each unit vector."""
    _, index = cKDTree(fibonacci_directions(cells)).query(directions)
    return np.asarray(index, dtype=np.int64)


def unit(vectors: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(vectors, axis=1)
    return vectors / np.where(norms > 0, norms, 1.0)[:, None]


@dataclass(frozen=True)
class Thinning:
    """Result of :func:`thin_by_direction`: ``keep`` mask, ``cap`` per cell, ``occupied`` cells."""

    keep: np.ndarray
    cap: int
    occupied: int


def thin_by_direction(
    directions: np.ndarray, cells: int, max_per_cell: int | None = None
) -> Thinning:
    """Keep at most ``max_per_cell`` samples per direction cell, evenly spread in time within
    the cell. Default cap: twice the median count of the occupied cells, and at least 4 Poisson
    sigmas above it (``median + 4 sqrt(median) + 2``: a uniform tumble of few samples per cell
    fills some cells three or four times by chance, which is no reason to drop samples), so an
    orientation held for long contributes like a typical one."""
    cell = direction_cells(directions, cells)
    counts = np.bincount(cell, minlength=cells)
    occupied = counts[counts > 0]
    typical = float(np.median(occupied))
    cap = (
        int(max_per_cell) if max_per_cell else int(max(2 * typical, typical + 4 * typical**0.5 + 2))
    )
    order = np.argsort(cell, kind="stable")
    sorted_cells = cell[order]
    starts = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.arange(len(order)) - starts
    count = counts[sorted_cells]
    # keep ranks floor(j * count / cap), j = 0..cap-1: evenly spaced picks within each cell
    picked = (rank * cap) // np.maximum(count, 1)
    first = np.r_[True, (picked[1:] != picked[:-1]) | (sorted_cells[1:] != sorted_cells[:-1])]
    keep_sorted = (count <= cap) | first
    keep = np.zeros(len(order), dtype=bool)
    keep[order] = keep_sorted
    return Thinning(keep=keep, cap=cap, occupied=len(occupied))


def direction_spread(directions: np.ndarray) -> np.ndarray:
    """Eigenvalues (ascending) of the covariance of unit vectors: 1/3 each for a full sphere;
    the smallest is ~0 for planar data (a circle or a cone of constant angle) or a narrow cap."""
    if len(directions) < 2:
        return np.zeros(3)
    return eigh(np.cov(directions.T, bias=True), eigvals_only=True)


def coverage_fraction(directions: np.ndarray, cells: int = 100) -> float:
    """Fraction of ``cells`` equal-area direction cells holding at least one sample."""
    return float(len(np.unique(direction_cells(directions, cells))) / cells)
