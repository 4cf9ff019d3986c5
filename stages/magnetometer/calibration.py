"""``mag_calibration`` stage: hard and soft iron from a tumbling recording (Magneto; Li &
Griffiths 2004; Dorveaux et al. 2009 for the iterative sphere mapping of the same model).

Model (tesla, or the sensor's counts): ``corrected = matrix @ (raw - offset)`` with ``offset``
the hard iron (the centre of the fitted ellipsoid) and ``matrix = F * W``, ``W`` the ellipsoid's
symmetric shape matrix (:mod:`imupipe.stages.magnetometer.ellipsoid`) and ``F`` the local field magnitude
(``field_ut``; default the ellipsoid's equal-volume radius, i.e. the data's own scale). ``model``
picks ``W``:

- ``general``: symmetric (hard iron + soft iron with rotated axes; no rotation added), Li &
  Griffiths' ellipsoid-specific fit refined by Levenberg-Marquardt;
- ``axis_aligned``: diagonal (the axis-aligned least squares ``a x^2 + ... + f z = 1``, refined);
- ``sphere``: ``w I`` (hard iron only).

Procedure: non-finite samples are left out (one counted warning); a sphere fit gives the field
directions; the coverage check fails when the smallest eigenvalue of their covariance is below
``min_spread`` (planar or narrow data); the directions are thinned (at most a capped number of
samples per equal-area direction cell); the model is fitted, samples whose residual is beyond
``outlier_k`` robust sigmas are rejected and the fit repeated; the coverage is checked again on
the corrected directions; the acceptance bounds are checked (offset size, soft-iron diagonal).

Quality is judged against the noise. The residual ``|W (h - c)| - 1`` of a good fit is the
sensor's per-sample noise (white from sample to sample) plus a model error that depends on the
direction, which changes slowly while the sensor turns. The noise is the white part of the
residual series in time order (:func:`~imupipe.stages.magnetometer.ellipsoid.white_part_std`: second
differences); the spread it does not explain, ``sqrt(std^2 - noise^2)``, is what tells an
ellipsoid from data that is not one (a field that changed, a magnet that moved with the sensor).
Real tumbles leave 1.4-2 % of the field unexplained (the QMC5883L sets of
tomisuarez2/MagnetometerCalibration, noisy 6.2 % and filtered 2.8 % in all; the ICM-20948 and
FXOS8700 sets of Magneto users); a hard iron that jumps by 20 % of the field halfway leaves 6 %
at any noise level: above ``max_unexplained_pct`` (5) the check fails. Every check is a
:meth:`~imupipe.stages.base.StageContext.check` (``accept_failed_checks = true`` keeps the fit).

Figures and warnings are in the data's unit: counts when the table's metadata says the
magnetometer is ``raw`` (a CSV with ``mag_unit = "raw"``), else uT. Results and quality figures
go to ``calibration.json``; Rerun gets the raw and corrected points, the fitted ellipsoid, the
target sphere and the norm over time before and after.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from imupipe.readers.table import has_stream, metadata, sensor
from imupipe.stages.base import Stage, StageContext, StageOutput
from imupipe.stages.magnetometer import ellipsoid as ell
from imupipe.stages.steps import LinearStep

SPIKE_K = 5.0
"""Residuals beyond this many robust sigmas are spikes: left out of the noise judgement."""
MAX_3D_POINTS = 20_000
"""Points sent to Rerun per 3D cloud (evenly strided beyond this)."""


@dataclass
class FitReport:
    """What the robust fit used: the ellipsoid and the sample masks."""

    ellipsoid: ell.Ellipsoid
    thinned: np.ndarray
    used: np.ndarray
    iterations: int
    cap: int


@dataclass(frozen=True)
class SensorUnit:
    """The unit of the magnetometer values: tesla, or the sensor's own counts (the table's
    ``units`` metadata says ``raw``, e.g. a CSV mapped with ``mag_unit = "raw"``)."""

    raw: bool

    @classmethod
    def of(cls, table: pa.Table) -> SensorUnit:
        return cls((metadata(table).get("units") or {}).get("mag") == "raw")

    @property
    def name(self) -> str:
        return "counts" if self.raw else "T"

    @property
    def plotted(self) -> str:
        """The unit a plot is given: ``raw counts``, or tesla (the recorder shows it as uT)."""
        return "raw counts" if self.raw else "T"

    def format(self, value: float) -> str:
        """A field value in the data's unit: counts, or uT for tesla."""
        return f"{value:.4g} counts" if self.raw else f"{value * 1e6:.4g} uT"


CONE_DEG = 30.0
"""A raw field inside a cone this narrow (deg) about its mean direction, with the sphere through
it beyond ``max_offset`` radii from zero: the sensor did not turn."""
NORMALISED_PCT = 1e-4
"""A field norm whose std is below this % of its mean was normalised before it was logged: even
a 24-bit magnetometer's quantisation leaves more."""


def norm_std_pct(values: np.ndarray) -> float:
    """Std of the vector norms in % of their mean."""
    norms = np.linalg.norm(values, axis=1)
    return float(100.0 * norms.std() / norms.mean())


class MagCalibrationStage(Stage):
    type = "mag_calibration"
    sensors = ("mag",)
    corrects = True

    @dataclass
    class Options:
        model: Literal["general", "axis_aligned", "sphere"] = "general"
        """``general`` (symmetric soft iron), ``axis_aligned`` (diagonal soft iron) or ``sphere``."""
        field_ut: float | None = None
        """Local field magnitude, uT (the corrected norm); default: the fitted mean radius."""
        geometric: bool = True
        """Refine the algebraic fit by Levenberg-Marquardt on the calibrated-space residual."""
        thinning: bool = True
        """Cap the samples per direction cell so over-sampled orientations do not pull the fit."""
        thinning_cells: int = 200
        """Equal-area direction cells for thinning."""
        thinning_max_per_cell: int | None = None
        """Cap per cell, samples; default ``max(2 m, m + 4 sqrt(m) + 2)``, m the median count of
        the occupied cells (an orientation held for long then weighs like a typical one)."""
        outlier_k: float | None = 4.0
        """Reject samples whose residual is beyond k robust sigmas (1.4826 MAD); None: keep all."""
        outlier_iterations: int = 3
        """Fit-reject rounds at most."""
        min_samples: int = 20
        """Fewer magnetometer samples than this are refused."""
        min_spread: float = 0.02
        """Smallest eigenvalue of the covariance of the field directions (1/3: all orientations,
        0.083: a hemisphere, ~0.003: a cap of +-35 deg, ~0: planar); below it the data is
        refused."""
        max_offset: float = 10.0
        """Largest accepted hard iron, in multiples of the field radius."""
        soft_iron_range: list[float] = field(default_factory=lambda: [0.5, 2.0])
        """Accepted range of the diagonal of the soft-iron correction normalised to det 1."""
        max_unexplained_pct: float | None = 5.0
        """Largest accepted std of the corrected norm that the per-sample noise does not explain,
        % of the field (``sqrt(std^2 - noise^2)``; the noise is the white part of the residual
        series, :func:`~imupipe.stages.magnetometer.ellipsoid.white_part_std`); None: no limit."""

    # -- fit ---------------------------------------------------------------------------------
    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        o = self.options
        self._check_options(ctx)
        if not has_stream(table, "mag"):
            raise ctx.fail(
                "the input has no magnetometer samples (map csv.mag, or set mag_topic for a log)"
            )
        data = ctx.finite(sensor(table, "mag"), "magnetometer", minimum=o.min_samples)
        ctx.dead_axes(data, "mag")  # an ellipsoid needs every axis
        values = data.values
        unit = SensorUnit.of(table)
        self._check_not_normalised(ctx, values, unit)

        try:
            sphere = ell.fit_sphere(values)
        except ell.EllipsoidFitError as exc:
            raise ctx.fail(f"magnetometer data is degenerate: {exc}") from None
        self._check_turned(ctx, values, sphere, unit)
        directions = ell.unit(values - sphere.centre)
        spread_raw = ell.direction_spread(directions)
        self._check_spread(ctx, spread_raw, "raw")

        try:
            report = self._robust_fit(values, directions)
        except ell.EllipsoidFitError as exc:
            raise ctx.fail(f"{o.model} fit failed: {exc}") from None
        e = report.ellipsoid
        unit_corrected = e.to_unit(values)
        spread = ell.direction_spread(ell.unit(unit_corrected[report.used]))
        self._check_spread(ctx, spread, "corrected")

        radius = e.mean_radius
        target = o.field_ut * 1e-6 if o.field_ut is not None else radius
        if o.field_ut is None:
            self._warn_scale(ctx, unit, radius)
        fixed = SensorUnit(unit.raw and o.field_ut is None)  # field_ut scales counts to tesla
        matrix = target * e.shape
        corrected = target * unit_corrected
        off_sphere = np.linalg.norm(unit_corrected, axis=1) - 1.0  # every sample, time order
        residual = off_sphere[report.used]
        core = ell.inliers(off_sphere, SPIKE_K)  # what the noise is judged against: no spikes
        total_pct = float(100 * off_sphere[core].std())
        noise = ell.white_part_std(off_sphere, SPIKE_K)  # per sample
        noise_pct = float(100 * noise) if np.isfinite(noise) else 0.0
        unexplained_pct = float(np.sqrt(max(total_pct**2 - noise_pct**2, 0.0)))
        shape_unit = e.shape / np.linalg.det(e.shape) ** (1.0 / 3.0)
        offset_se, scale_se = ell.standard_errors(values[report.used], e, o.model)
        radii, axes = e.axes
        metrics = {
            "samples": len(values),
            "samples_after_thinning": int(report.thinned.sum()),
            "samples_used": int(report.used.sum()),
            "outliers": int(report.thinned.sum() - report.used.sum()),
            "thinning_cap_per_cell": report.cap,
            "fit_iterations": report.iterations,
            "unit": unit.name,
            "rms_residual": float(target * np.sqrt(np.mean(residual**2))),
            "rms_residual_pct": float(100 * np.sqrt(np.mean(residual**2))),
            "norm_std_pct": norm_std_pct(corrected),
            "norm_std_pct_used": norm_std_pct(corrected[report.used]),
            "norm_std_pct_core": total_pct,
            "noise_pct": noise_pct,
            "noise": float(radius * noise) if np.isfinite(noise) else 0.0,
            "unexplained_pct": unexplained_pct,
            "raw_norm_std_pct": norm_std_pct(values),
            "corrected_norm_mean": float(np.linalg.norm(corrected, axis=1).mean()),
            "fitted_radius": radius,
            "direction_spread": spread.tolist(),
            "direction_spread_raw": spread_raw.tolist(),
            "coverage_fraction": ell.coverage_fraction(ell.unit(unit_corrected[report.used])),
            "offset_over_radius": float(np.linalg.norm(e.centre) / radius),
            "soft_iron_diagonal": np.diag(shape_unit).tolist(),
            "standard_errors": {
                "offset": offset_se.tolist(),
                "soft_iron_diagonal": scale_se.tolist(),
            },
        }
        self._check_bounds(ctx, metrics, unit)
        self._record(ctx, data.t_ns, values, corrected, e, target, report, unit, fixed)

        params = {
            "model": o.model,
            "centre": e.centre.tolist(),
            "radii": radii.tolist(),
            "axes": axes.tolist(),
            "soft_iron": shape_unit.tolist(),
            "field": target,
        }
        step = LinearStep(
            type=self.type, sensor="mag", matrix=matrix, offset=e.centre, params=params
        )
        results = {"model": o.model, **params, "metrics": metrics}
        return StageOutput(results=results, step=step, counts=("mag",) if fixed.raw else ())

    def _robust_fit(self, values: np.ndarray, directions: np.ndarray) -> FitReport:
        o = self.options
        thinned = np.ones(len(values), dtype=bool)
        cap = 0
        if o.thinning:
            thin = ell.thin_by_direction(directions, o.thinning_cells, o.thinning_max_per_cell)
            thinned, cap = thin.keep, thin.cap
        used = thinned
        e = ell.fit(values[used], o.model, geometric=o.geometric)
        iterations = 1
        while o.outlier_k is not None and iterations < o.outlier_iterations + 1:
            candidates = np.flatnonzero(thinned)
            keep = ell.inliers(e.residuals(values[candidates]), o.outlier_k)
            new_used = np.zeros(len(values), dtype=bool)
            new_used[candidates[keep]] = True
            if np.array_equal(new_used, used):
                break
            used = new_used
            e = ell.fit(values[used], o.model, geometric=o.geometric)
            iterations += 1
        return FitReport(e, thinned, used, iterations, cap)

    # -- checks ------------------------------------------------------------------------------
    def _check_options(self, ctx: StageContext) -> None:
        o = self.options
        if o.field_ut is not None and o.field_ut <= 0:
            raise ctx.fail(f"field_ut must be > 0 (uT), got {o.field_ut}")
        if o.thinning_cells < 6:
            raise ctx.fail(f"thinning_cells must be >= 6, got {o.thinning_cells}")
        if o.thinning_max_per_cell is not None and o.thinning_max_per_cell < 1:
            raise ctx.fail(f"thinning_max_per_cell must be >= 1, got {o.thinning_max_per_cell}")
        if o.outlier_iterations < 0:
            raise ctx.fail(f"outlier_iterations must be >= 0, got {o.outlier_iterations}")
        if o.outlier_k is not None and o.outlier_k <= 0:
            raise ctx.fail(f"outlier_k must be > 0, got {o.outlier_k}")
        lo_hi = o.soft_iron_range
        if len(lo_hi) != 2 or not 0 < lo_hi[0] < 1 < lo_hi[1]:
            raise ctx.fail(f"soft_iron_range must be [low < 1, high > 1], got {lo_hi}")

    def _check_not_normalised(
        self, ctx: StageContext, values: np.ndarray, unit: SensorUnit
    ) -> None:
        """A real magnetometer's norm varies by its noise at least (0.1 % and more); one that is
        constant to :data:`NORMALISED_PCT` was scaled to one length before it was logged (some
        drivers publish field directions), which removes the hard and soft iron to be fitted."""
        spread = norm_std_pct(values)
        ctx.check(
            not spread < NORMALISED_PCT,
            f"the magnetometer norm is constant: |h| = "
            f"{unit.format(float(np.linalg.norm(values, axis=1).mean()))} on every sample "
            f"(std {spread:.2g} % < {NORMALISED_PCT:g} %): the log holds field directions "
            "normalised by the driver, from which no hard or soft iron can be fitted; log the "
            "magnetometer's raw readings",
        )

    def _check_turned(
        self, ctx: StageContext, values: np.ndarray, sphere: ell.Ellipsoid, unit: SensorUnit
    ) -> None:
        """A sensor that did not turn gives a cluster of noise: the sphere through it is as small
        as the noise and lies far from zero, and its directions look spread all round. A centre
        beyond ``max_offset`` radii with the raw field inside a narrow cone (:data:`CONE_DEG`,
        about its mean direction) says so before any ellipsoid is fitted; a wide cone is left to
        the hard-iron bound on the fitted ellipsoid."""
        radius = sphere.mean_radius
        ratio = float(np.linalg.norm(sphere.centre) / radius)
        mean = ell.unit(values.mean(axis=0)[None, :])[0]
        cone = float(np.degrees(np.arccos(np.clip(ell.unit(values) @ mean, -1.0, 1.0))).max())
        o = self.options
        ctx.check(
            ratio <= o.max_offset or cone >= CONE_DEG,
            f"the raw magnetometer field stays within {cone:.2g} deg of one direction: the "
            f"sensor did not turn, or a hard iron of more than max_offset = {o.max_offset:g} "
            f"field radii hides its turns (the sphere through the samples: radius "
            f"{unit.format(radius)}, {ratio:.3g} radii from zero); tumble the sensor through all "
            "orientations",
        )

    def _check_spread(self, ctx: StageContext, spread: np.ndarray, where: str) -> None:
        ctx.check(
            spread[0] >= self.options.min_spread,
            f"the magnetometer data covers too few orientations: the smallest spread of the "
            f"{where} field directions is {spread[0]:.3g} < min_spread = "
            f"{self.options.min_spread:g} (0.333 = all orientations, ~0 = planar); tumble the "
            "sensor through all orientations",
        )

    def _warn_scale(self, ctx: StageContext, unit: SensorUnit, radius: float) -> None:
        """The corrected field keeps the data's own scale when ``field_ut`` is not set: say so
        when that scale is not tesla (raw counts, or a unit mapped wrongly)."""
        if unit.raw:
            ctx.warn(
                f"the magnetometer data are raw counts: the corrected field keeps their scale "
                f"(radius {unit.format(radius)}); set field_ut to the local field to get tesla"
            )
        elif not 1e-6 <= radius <= 1e-3:
            ctx.warn(
                f"the fitted field radius is {unit.format(radius)}, far from the Earth's 25-65 "
                'uT: check the input\'s mag unit (mag_unit = "raw" for counts), or set field_ut'
            )

    def _check_bounds(self, ctx: StageContext, m: dict[str, Any], unit: SensorUnit) -> None:
        o = self.options
        ctx.check(
            m["offset_over_radius"] <= o.max_offset,
            f"hard iron {m['offset_over_radius']:.3g} times the field radius > max_offset = "
            f"{o.max_offset:g}",
        )
        lo, hi = o.soft_iron_range
        diag = np.array(m["soft_iron_diagonal"])
        ctx.check(
            lo <= diag.min() and diag.max() <= hi,
            f"soft-iron diagonal {np.round(diag, 3).tolist()} is outside soft_iron_range "
            f"{o.soft_iron_range}",
        )
        if o.max_unexplained_pct is not None:
            ctx.check(
                m["unexplained_pct"] <= o.max_unexplained_pct,
                f"the corrected field norm varies by {m['norm_std_pct_core']:.3g} % (std), of "
                f"which the per-sample noise ({unit.format(m['noise'])}, "
                f"{m['noise_pct']:.3g} %) explains all but {m['unexplained_pct']:.3g} % > "
                f"max_unexplained_pct = {o.max_unexplained_pct:g}: the data is not one "
                "ellipsoid (a field that changed during the recording, a magnet moving with "
                "the sensor, saturation?)",
            )

    # -- Rerun -------------------------------------------------------------------------------
    def _record(
        self,
        ctx: StageContext,
        t_ns: np.ndarray,
        raw: np.ndarray,
        corrected: np.ndarray,
        e: ell.Ellipsoid,
        target: float,
        report: FitReport,
        unit: SensorUnit,
        fixed: SensorUnit,
    ) -> None:
        """``unit``: of the raw samples; ``fixed``: of the corrected ones."""
        rec = ctx.recorder
        if not getattr(rec, "enabled", False):
            return
        name = ctx.name
        unit_name, fixed_unit = unit.plotted, fixed.plotted
        stride = max(1, int(np.ceil(len(raw) / MAX_3D_POINTS)))
        used, outlier, thinned_out = (60, 100, 230), (230, 60, 60), (150, 150, 150)
        colors = np.where(
            report.used[:, None],
            np.array([used]),
            np.where(report.thinned[:, None], np.array([outlier]), np.array([thinned_out])),
        ).astype(np.uint8)[::stride]
        meaning = {
            used: "used in the fit",
            outlier: "outliers, left out",
            thinned_out: "thinned out (a direction's samples past its cap)",
        }
        raw_plot = dict(unit=unit_name, plot="raw", title="raw samples and the fitted ellipsoid")
        rec.points3d(
            f"/{name}/raw/points",
            raw[::stride],
            name="raw samples",
            colors=colors,
            color_names=meaning,
            **raw_plot,
        )
        radii, axes = e.axes
        rec.ellipsoid(
            f"/{name}/raw/ellipsoid", e.centre, radii, axes, name="fitted ellipsoid", **raw_plot
        )
        fixed_plot = dict(
            unit=fixed_unit, plot="corrected", title="corrected samples and the field sphere"
        )
        rec.points3d(
            f"/{name}/corrected/points",
            corrected[::stride],
            name="corrected samples",
            colors=colors,
            color_names=meaning,
            **fixed_plot,
        )
        rec.ellipsoid(
            f"/{name}/corrected/sphere",
            np.zeros(3),
            [target] * 3,
            name="field sphere",
            color=(60, 180, 75),
            **fixed_plot,
        )
        norms = np.column_stack(
            [
                np.linalg.norm(raw, axis=1),
                np.linalg.norm(corrected, axis=1),
                np.full(len(raw), target),
            ]
        )
        names = ("|h| raw", "|h| corrected", "field magnitude")
        colors = [(150, 150, 150), (40, 100, 230), (30, 160, 60)]
        first = 0 if unit_name == fixed_unit else 1  # one unit per plot: raw counts apart
        parts = [(slice(1, 2), False)] if first else [(slice(0, 1), True), (slice(1, 2), False)]
        for keep, under in parts:  # the raw magnitude beneath the others
            rec.series(
                f"/{name}/norm",
                t_ns,
                norms[:, keep],
                names[keep],
                unit=fixed_unit,
                title="|h|",
                colors=colors[keep],
                under=under,
            )
        # the field's magnitude over |h| corrected (the viewer draws lines in entity-path
        # order: under it, the noisy |h| hid it), in the same plot
        rec.series(
            f"/{name}/norm/reference",
            t_ns,
            norms[:, 2],
            names[2:],
            unit=fixed_unit,
            title="|h|",
            colors=colors[2:],
            plot="norm",
        )
