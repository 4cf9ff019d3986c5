"""What the thermal stages show in Rerun (under ``/<stage name>``), one unit per plot.

Curves against temperature are 2D plots (x in degC) that open readable on any timeline: the
data as points, the fitted curve as a line.

``temperature`` stage:

- ``<sensor> <axis> bias vs temperature`` (one plot per axis, SI unit): the complete blocks'
  bias, heating in red, cooling in blue, soak in grey, and the fitted curve at zero rate and at
  the median heating and cooling rates (their gap is the hysteresis the rate terms model). With
  the lag model the x axis is the sensing element's temperature Ts: heating and cooling collapse
  onto one curve where the lag explains the hysteresis.
- ``temperature`` (degC, over time): the measured block temperature, the ambient one, and with
  the lag model the sensing element's lagged temperature Ts; ``temperature rate`` (degC/min).
- ``<sensor> bias`` and ``<sensor> residual`` (SI, over time): the block bias before and after.
- ``lag fit`` (lag model): the cost (sum over axes of ln RSS) against the time constant (s).
- ``surface``: the fitted surface B(T, dT) (B(Ts, dTs) for the lag model) per axis as an
  ``rr.Mesh3D`` with the blocks on it (the MATLAB example's ``mesh`` and ``plot3``); each axis in
  its own 3D view and unit box, the arrows' labels give the ranges.
- ``<axis> scale vs temperature`` (turntable runs): each +/-rate pair and the fitted sf(T).

``thermal_soak`` stage (:func:`record_soak`): per sensor, ``bias``, ``scale`` and
``misalignment`` against temperature (one plot per quantity and unit): the value fitted at each
soak temperature (points) and the polynomial in T (lines), x, y, z (and the angles) as series.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from imupipe.readers.table import SENSOR_UNITS

if TYPE_CHECKING:
    from imupipe.stages.base import StageContext
    from imupipe.stages.thermal.step import Prepared, TemperatureStep

AXES = ("x", "y", "z")
HEATING, COOLING, SOAK, FIT = (220, 50, 50), (50, 90, 220), (150, 150, 150), (20, 20, 20)
AXIS_COLORS = [(230, 60, 60), (60, 180, 75), (60, 100, 230), (200, 140, 20), (150, 60, 200)]
GRID_T, GRID_R = 41, 21


def _colormap(z: np.ndarray) -> np.ndarray:
    """Blue (0) -> yellow (1), RGB uint8."""
    z = np.clip(z, 0.0, 1.0)[:, None]
    low, high = np.array([40, 60, 200]), np.array([250, 220, 40])
    return (low + (high - low) * z).astype(np.uint8)


def _grid_triangles(nx: int, ny: int) -> np.ndarray:
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    b, c, d = a + ny, a + 1, a + ny + 1
    return np.vstack([np.column_stack([a, b, d]), np.column_stack([a, d, c])]).astype(np.uint32)


def record_fit(
    ctx: StageContext,
    prep: Prepared,
    step: TemperatureStep,
    fitted: np.ndarray,
    rel: dict[str, np.ndarray],
    lag: dict[str, Any] | None = None,
) -> None:
    """Send the ``temperature`` stage's figures (see the module docstring); ``fitted`` is the
    model at the blocks of ``prep``, ``rel`` the model's variables there."""
    rec, name, sensor = ctx.recorder, ctx.name, step.sensor
    unit = SENSOR_UNITS[sensor]
    lagged = "Ts" in rel
    xvar, rvar = ("Ts", "dTs") if lagged else ("T", "dT")
    x = rel[xvar] + step.tref
    rate = rel["dTs"] if lagged else prep.variables["dT"]
    lo, hi = float(x.min()), float(x.max())

    rec.series(
        f"/{name}/bias",
        prep.t_ns,
        prep.bias,
        [f"{sensor} {a} bias" for a in AXES],
        unit=unit,
        title=f"{sensor} block bias",
    )
    rec.series(
        f"/{name}/residual",
        prep.t_ns,
        prep.bias - fitted,
        [f"{sensor} {a} residual" for a in AXES],
        unit=unit,
        title=f"{sensor} residual after the fit",
    )
    temps = [prep.variables["T"]]
    labels = ["measured T"]
    if "Ta" in prep.variables:
        temps.append(prep.variables["Ta"])
        labels.append("ambient Ta")
    if lagged:
        temps.append(x)
        labels.append(f"sensing element Ts (lag {step.lag_s:.4g} s)")
    rec.series(
        f"/{name}/temperature",
        prep.t_ns,
        np.column_stack(temps),
        labels,
        unit="degC",
        title="block temperature",
    )
    rec.series(
        f"/{name}/temperature_rate",
        prep.t_ns,
        prep.variables["dT"] * 60.0,
        ("dT/dt",),
        unit="degC/min",
        title="temperature rate",
    )

    # bias against (element) temperature: the data by direction, the fitted curve at rates
    heat = rate[prep.direction > 0]
    cool = rate[prep.direction < 0]
    curves = [(f"fit at {rvar} = 0", 0.0, FIT)]
    if len(heat):
        curves.append(
            (f"fit heating {np.median(heat) * 60:.3g} degC/min", np.median(heat), HEATING)
        )
    if len(cool):
        curves.append(
            (f"fit cooling {np.median(cool) * 60:.3g} degC/min", np.median(cool), COOLING)
        )
    grid = np.linspace(lo, hi, 200)
    x_label = "sensing element temperature Ts" if lagged else "temperature"
    for i, axis in enumerate(AXES):
        base = f"/{name}/bias_vs_temperature/{axis}"
        plot = dict(
            plot=f"bias_vs_temperature/{axis}",
            title=f"{sensor} {axis} bias",
            unit=unit,
            x_label=x_label,
            x_unit="degC",
        )
        for label, sign, color in (
            ("heating", 1, HEATING),
            ("cooling", -1, COOLING),
            ("soak", 0, SOAK),
        ):
            mask = prep.direction == sign
            if mask.any():
                rec.curve(
                    f"{base}/{label}", x[mask], prep.bias[mask, i],
                    (f"{sensor} {axis} bias {label}",), colors=[color], points=True, **plot,
                )  # fmt: skip
        values = np.column_stack(
            [_model_at(step, grid, np.full(len(grid), r), lagged)[:, i] for _, r, _ in curves]
        )
        rec.curve(
            f"{base}/fit", grid, values, [c[0] for c in curves], colors=[c[2] for c in curves],
            **plot,
        )  # fmt: skip

    if lag is not None and "profile" in lag:
        taus = np.asarray(lag["profile"]["lag_s"])
        rec.curve(
            f"/{name}/lag_fit", taus, np.asarray(lag["profile"]["cost"]),
            ("sum of ln RSS over axes",), colors=[FIT], points=True, plot="lag_fit",
            title="lag fit: cost", x_label="time constant", x_unit="s",
        )  # fmt: skip

    for axis, model in (step.scale or {}).items():
        pair_t, pair_sf = prep.pairs[axis]
        base = f"/{name}/scale_vs_temperature/{axis}"
        plot = dict(
            plot=f"scale_vs_temperature/{axis}",
            title=f"gyro {axis} scale factor",
            x_label="temperature",
            x_unit="degC",
        )
        rec.curve(
            f"{base}/pairs", pair_t, pair_sf, (f"gyro {axis} scale +/-rate pairs",),
            colors=[SOAK], points=True, **plot,
        )  # fmt: skip
        rec.curve(
            f"{base}/fit", grid, step.scale_factor(model, {"T": grid - step.tref}),
            (f"gyro {axis} scale fit",), colors=[FIT], **plot,
        )  # fmt: skip

    _surface(ctx, prep, step, x, rate, lagged)


def _model_at(
    step: TemperatureStep, temp: np.ndarray, rate: np.ndarray, lagged: bool
) -> np.ndarray:
    """(n, 3) modelled bias at absolute (element) temperatures ``temp`` and rates ``rate``;
    ambient terms take Ta = T and dTa = dT."""
    rel = temp - step.tref
    if lagged:
        return step.bias({"T": rel, "Ts": rel, "dTs": rate})
    return step.bias({"T": rel, "dT": rate, "Ta": rel, "dTa": rate})


def _surface(
    ctx: StageContext,
    prep: Prepared,
    step: TemperatureStep,
    x: np.ndarray,
    rate: np.ndarray,
    lagged: bool,
) -> None:
    """The fitted surface over (temperature, rate) with the blocks on it, one box per axis."""
    rec, name = ctx.recorder, ctx.name
    lo, hi = float(x.min()), float(x.max())
    rlo, rhi = float(rate.min()), float(rate.max())
    tg, rg = np.meshgrid(np.linspace(lo, hi, GRID_T), np.linspace(rlo, rhi, GRID_R), indexing="ij")
    surface = _model_at(step, tg.ravel(), rg.ravel(), lagged)
    triangles = _grid_triangles(GRID_T, GRID_R)
    u = (tg.ravel() - lo) / max(hi - lo, 1e-12)
    v = (rg.ravel() - rlo) / max(rhi - rlo, 1e-12)
    ud = (x - lo) / max(hi - lo, 1e-12)
    vd = (rate - rlo) / max(rhi - rlo, 1e-12)
    colors = np.where(
        (prep.direction > 0)[:, None],
        HEATING,
        np.where((prep.direction < 0)[:, None], COOLING, SOAK),
    ).astype(np.uint8)
    tname, rname = ("Ts", "dTs") if lagged else ("T", "dT")
    for i, axis in enumerate(AXES):
        zmin = min(surface[:, i].min(), prep.bias[:, i].min())
        zmax = max(surface[:, i].max(), prep.bias[:, i].max())
        span = max(zmax - zmin, 1e-300)
        w, wd = (surface[:, i] - zmin) / span, (prep.bias[:, i] - zmin) / span
        off = np.zeros(3)  # each axis in its own view
        base = f"/{name}/surface/{axis}"
        rec.log(
            f"{base}/mesh",
            rr.Mesh3D(
                vertex_positions=np.column_stack([u, v, w]) + off,
                triangle_indices=triangles,
                vertex_colors=_colormap(w),
            ),
        )
        rec.log(
            f"{base}/data",
            rr.Points3D(np.column_stack([ud, vd, wd]) + off, colors=colors, radii=0.006),
        )
        tips = np.eye(3) * 1.1
        rec.log(
            f"{base}/axes",
            rr.Arrows3D(origins=[off, off, off], vectors=tips, colors=[(200, 200, 200)] * 3),
        )
        rec.log(  # labelled points at the arrow tips: Rerun draws an arrow's label at its middle,
            # where the three crowd into one another and onto the surface
            f"{base}/axis_names",
            rr.Points3D(
                tips * 1.08 + off,
                radii=0.001,
                colors=[(200, 200, 200)] * 3,
                labels=[
                    f"{axis}: {tname} {lo:.3g}..{hi:.3g} degC",
                    f"{rname} {rlo * 60:.3g}..{rhi * 60:.3g} degC/min",
                    f"bias {zmin:.3g}..{zmax:.3g} {SENSOR_UNITS[step.sensor]}",
                ],
            ),
        )
        rec.add_view(
            name,
            rrb.Spatial3DView(origin=base, name=f"{step.sensor} {axis} B({tname}, {rname})"),
        )


def record_soak(
    ctx: StageContext,
    sensor: str,
    temps: np.ndarray,
    values: dict[str, tuple[np.ndarray, list[str], str]],
    curves: dict[str, np.ndarray],
    grid: np.ndarray,
) -> None:
    """The ``thermal_soak`` stage's figures for one sensor: for each quantity (``bias``,
    ``scale``, ``misalignment``), ``values[q]`` = (fitted at each soak temperature (m, k),
    series labels, unit) and ``curves[q]`` the polynomial at ``grid`` (degC) (g, k)."""
    rec, name = ctx.recorder, ctx.name
    for quantity, (data, labels, unit) in values.items():
        base = f"/{name}/{sensor}_{quantity}_vs_temperature"
        colors = AXIS_COLORS[: len(labels)]
        plot = dict(
            plot=f"{sensor}_{quantity}_vs_temperature",
            title=f"{sensor} {quantity}",
            unit=unit,
            x_label="temperature",
            x_unit="degC",
        )
        rec.curve(
            f"{base}/soaks", temps, data, [f"{label} at each soak" for label in labels],
            colors=colors, points=True, **plot,
        )  # fmt: skip
        rec.curve(
            f"{base}/fit", grid, curves[quantity], [f"{label} fit" for label in labels],
            colors=colors, **plot,
        )  # fmt: skip
