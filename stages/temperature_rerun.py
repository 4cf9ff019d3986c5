"""What the ``temperature`` stage shows in Rerun (under ``/<stage name>``).

- ``bias_vs_temperature/<axis>``: the block bias against temperature (a 2D plot), heating
  blocks in red, cooling in blue, soak in grey (markers), and the fitted curve (lines) at dT = 0
  and at the median heating and cooling rates: the gap between the two is the hysteresis the
  rate terms model.
- ``surface``: the fitted surface B(T, dT) per axis as an ``rr.Mesh3D`` with the data points on
  it (seed 000 draws the same with ``mesh`` and ``plot3``). Each axis sits in its own unit box
  (x: T from Tmin to Tmax, y: dT from its min to max, z: bias from its min to max, offset 1.5
  apart along x for axes x, y, z); the arrows' labels give the ranges.
- ``scale_vs_temperature/<axis>`` (gyro with ``turntable_rate``): the scale factor of each
  +/-rate pair against temperature and the fitted curve.
- ``bias``, ``residual``, ``block_temperature``, ``rate``: the block bias, the residual after
  the fit, the block temperature(s) (degC) and rate (degC/min) over time, one plot each.

For models with ambient terms the curves and the surface take Ta = T and dTa = dT.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from imupipe.readers.table import SENSOR_UNITS

if TYPE_CHECKING:
    from imupipe.stages.base import StageContext
    from imupipe.stages.temperature_step import Prepared, TemperatureStep

AXES = ("x", "y", "z")
HEATING, COOLING, SOAK = (220, 50, 50), (50, 90, 220), (150, 150, 150)
GRID_T, GRID_R = 41, 21


def _model_at(step: TemperatureStep, temp: np.ndarray, rate: np.ndarray) -> np.ndarray:
    """(n, 3) modelled bias at absolute temperatures ``temp`` and rates ``rate``."""
    variables = {"T": temp - step.tref, "dT": rate, "Ta": temp - step.tref, "dTa": rate}
    return step.bias(variables)


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
) -> None:
    """Send the stage's figures (see the module docstring); ``fitted`` is the model at the
    blocks of ``prep``."""
    rec, name = ctx.recorder, ctx.name
    unit = SENSOR_UNITS[step.sensor]
    temp, rate = prep.variables["T"], prep.variables["dT"]
    lo, hi = step.ranges["T"]
    rlo, rhi = step.ranges["dT"]

    sn = step.sensor
    rec.series(f"/{name}/bias", prep.t_ns, prep.bias, [f"{sn} {a} bias" for a in AXES], unit=unit)
    rec.series(f"/{name}/residual", prep.t_ns, prep.bias - fitted,
               [f"{sn} {a} residual after fit" for a in AXES], unit=unit)  # fmt: skip
    temps = [prep.variables[k] for k in ("T", "Ta") if k in prep.variables]
    rec.series(f"/{name}/block_temperature", prep.t_ns, np.column_stack(temps),
               ("T", "Ta")[: len(temps)], unit="degC", title="block temperature")  # fmt: skip
    rec.series(f"/{name}/rate", prep.t_ns, rate * 60.0, ("dT/dt",), unit="degC/min",
               title="temperature rate")  # fmt: skip

    # bias against temperature: data by direction, fitted curves at 0 and the median rates
    x = temp
    grid = np.linspace(lo, hi, 200)
    grid_x = grid
    heat = rate[prep.direction > 0]
    cool = rate[prep.direction < 0]
    curves = [("fit dT=0", 0.0, (20, 20, 20))]
    if len(heat):
        curves.append(
            (f"fit heating {np.median(heat) * 60:.3g} degC/min", np.median(heat), HEATING)
        )
    if len(cool):
        curves.append(
            (f"fit cooling {np.median(cool) * 60:.3g} degC/min", np.median(cool), COOLING)
        )
    for i, axis in enumerate(AXES):
        base = f"/{name}/bias_vs_temperature/{axis}"
        plot = dict(plot=f"bias_vs_temperature/{axis}", title=f"{sn} {axis} bias", unit=unit,
                    x_label="temperature", x_unit="degC")  # fmt: skip
        for label, sign, color in (
            ("heating", 1, HEATING),
            ("cooling", -1, COOLING),
            ("soak", 0, SOAK),
        ):
            mask = prep.direction == sign
            if mask.any():
                rec.curve(
                    f"{base}/{label}",
                    x[mask],
                    prep.bias[mask, i],
                    (label,),
                    colors=[color],
                    points=True,
                    **plot,
                )
        values = np.column_stack(
            [_model_at(step, grid, np.full(len(grid), r))[:, i] for _, r, _ in curves]
        )
        rec.curve(
            f"{base}/fit",
            grid_x,
            values,
            [c[0] for c in curves],
            colors=[c[2] for c in curves],
            **plot,
        )

    # the gyro scale factor against temperature (turntable pairs and the fitted curve)
    for axis, model in (step.scale or {}).items():
        pair_t, pair_sf = prep.pairs[axis]
        base = f"/{name}/scale_vs_temperature/{axis}"
        plot = dict(plot=f"scale_vs_temperature/{axis}", title=f"{sn} {axis} scale factor",
                    x_label="temperature", x_unit="degC")  # fmt: skip
        rec.curve(
            f"{base}/pairs", pair_t, pair_sf, ("+/-rate pairs",), colors=[SOAK], points=True,
            **plot,
        )  # fmt: skip
        rec.curve(
            f"{base}/fit", grid_x, step.scale_factor(model, {"T": grid - step.tref}), ("fit",),
            colors=[(20, 20, 20)], **plot,
        )  # fmt: skip

    # the fitted surface B(T, dT) with the data on it
    tg, rg = np.meshgrid(np.linspace(lo, hi, GRID_T), np.linspace(rlo, rhi, GRID_R), indexing="ij")
    surface = _model_at(step, tg.ravel(), rg.ravel())
    triangles = _grid_triangles(GRID_T, GRID_R)
    u = (tg.ravel() - lo) / max(hi - lo, 1e-12)
    v = (rg.ravel() - rlo) / max(rhi - rlo, 1e-12)
    ud = (temp - lo) / max(hi - lo, 1e-12)
    vd = (rate - rlo) / max(rhi - rlo, 1e-12)
    colors = np.where(
        (prep.direction > 0)[:, None],
        HEATING,
        np.where((prep.direction < 0)[:, None], COOLING, SOAK),
    ).astype(np.uint8)
    for i, axis in enumerate(AXES):
        zmin = min(surface[:, i].min(), prep.bias[:, i].min())
        zmax = max(surface[:, i].max(), prep.bias[:, i].max())
        span = max(zmax - zmin, 1e-300)
        w, wd = (surface[:, i] - zmin) / span, (prep.bias[:, i] - zmin) / span
        off = np.array([1.5 * i, 0.0, 0.0])
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
        rec.log(
            f"{base}/axes",
            rr.Arrows3D(
                origins=[off, off, off],
                vectors=[[1.1, 0, 0], [0, 1.1, 0], [0, 0, 1.1]],
                labels=[
                    f"{axis}: T {lo:.3g}..{hi:.3g} degC",
                    f"dT {rlo * 60:.3g}..{rhi * 60:.3g} degC/min",
                    f"bias {zmin:.3g}..{zmax:.3g} {unit}",
                ],
                colors=[(200, 200, 200)] * 3,
            ),
        )
    for axis in AXES:
        rec.add_view(
            name, rrb.Spatial3DView(origin=f"/{name}/surface/{axis}", name=f"{sn} {axis} B(T, dT)")
        )
