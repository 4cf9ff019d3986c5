"""The ``temperature`` correction step (applied by ``run`` and ``convert``) and the block data
the ``temperature`` stage fits it on.

The model, its units and its references are described in :mod:`imupipe.stages.temperature`.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from imupipe.readers.table import (
    has_stream,
    interpolate,
    metadata,
    replace_sensor,
    sensor,
)
from imupipe.stages import thermal_models as tm
from imupipe.stages.blocks import block_means
from imupipe.stages.errors import CalibrationError
from imupipe.stages.steps import Step

WARN_MARGIN = 0.5
"""degC: temperatures further than this outside the fitted range are warned about (all are
clamped); rates more than 10 % of their fitted span outside it are warned about (not clamped:
a rate term extrapolates linearly)."""
AXES = ("x", "y", "z")


# -- preprocessing shared by the fit and the correction --------------------------------------


def temperature_at(table: pa.Table, t_ns: np.ndarray, column: str = "temperature") -> np.ndarray:
    """The temperature (``temperature`` or ``ambient_temperature``) at ``t_ns``, interpolated."""
    if column == "temperature":
        data = sensor(table, "temperature")
        return interpolate(data.t_ns, data.values[:, 0], t_ns)
    values = table.column(column).to_numpy(zero_copy_only=False).astype(np.float64)
    ok = np.isfinite(values)
    return interpolate(table.column("t_ns").to_numpy()[ok], values[ok], t_ns)


def block_rate(
    t_ns: np.ndarray, temp: np.ndarray, window: int | None, window_s: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block centres (ns), block-mean temperature (degC) and its rate (degC/s, gradient over
    the block centres; zero with a single block)."""
    blocks = block_means(t_ns, temp, window, window_s)
    if len(blocks.t_ns) < 2:
        return blocks.t_ns, blocks.means, np.zeros(len(blocks.t_ns))
    t_s = (blocks.t_ns - blocks.t_ns[0]).astype(np.float64) * 1e-9
    return blocks.t_ns, blocks.means, np.gradient(blocks.means, t_s)


def rate_at(
    t_ns: np.ndarray, temp: np.ndarray, window: int | None, window_s: float | None
) -> np.ndarray:
    """dT/dt at every ``t_ns``: the block rate of :func:`block_rate`, interpolated."""
    bt, _, rate = block_rate(t_ns, temp, window, window_s)
    return interpolate(bt, rate, t_ns)


# -- the correction step ---------------------------------------------------------------------


@dataclass
class TemperatureStep(Step):
    """``corrected = raw - f(T, dT [, Ta, dTa])`` per axis; see the module docstring.

    ``axes`` holds, per axis x, y, z, ``{"terms": [...], "coefficients": [...]}``; ``ranges``
    the fitted range of each variable (absolute degC for T and Ta, degC/s for the rates), used to
    clamp; ``knots`` (absolute degC) the piecewise model's segment ends.
    """

    kind: ClassVar[str] = "temperature"
    type: str
    sensor: str
    model: str
    tref: float
    window: int | None
    window_s: float | None
    axes: list[dict[str, Any]]
    ranges: dict[str, list[float]]
    knots: list[float] | None = None
    scale: dict[str, dict[str, Any]] | None = None
    """Gyro scale factor against temperature per axis that was turned (seed 004): axis ->
    ``{"terms", "coefficients"}`` of ``sf(T)``; ``corrected = (raw - f) / sf(T)`` there."""
    params: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    quiet: bool = False
    """Collect warnings without printing them (``run --quiet``); not part of the chain entry."""

    def variables(self, table: pa.Table, t_ns: np.ndarray) -> dict[str, Any]:
        """T, dT (and Ta, dTa when a term uses them) at ``t_ns``: T and Ta clamped to the fitted
        range and made relative to Tref; warns about samples outside the fitted ranges."""
        needed = tm.term_variables([t for ax in self.axes for t in ax["terms"]])
        out: dict[str, np.ndarray] = {}
        temp = temperature_at(table, t_ns)
        out["T"], out["dT"] = temp, rate_at(t_ns, temp, self.window, self.window_s)
        if needed & {"Ta", "dTa"}:
            amb = temperature_at(table, t_ns, "ambient_temperature")
            out["Ta"], out["dTa"] = amb, rate_at(t_ns, amb, self.window, self.window_s)
        notes = []
        for name, values in out.items():
            lo, hi = self.ranges[name]
            if name in ("T", "Ta"):
                far = int(
                    np.count_nonzero((values < lo - WARN_MARGIN) | (values > hi + WARN_MARGIN))
                )
                out[name] = np.clip(values, lo, hi)
                what = "clamped to"
            else:
                pad = 0.1 * (hi - lo)
                far = int(np.count_nonzero((values < lo - pad) | (values > hi + pad)))
                what = "extrapolated beyond"
            if far:
                notes.append(
                    f"{name} {what} the fitted range [{lo:.4g}, {hi:.4g}] at {far} of "
                    f"{len(values)} samples (seen {values.min():.4g}..{values.max():.4g})"
                )
        if notes:
            self._warn("; ".join(notes))
        out["T"] = out["T"] - self.tref
        if "Ta" in out:
            out["Ta"] = out["Ta"] - self.tref
        return out

    def _warn(self, message: str) -> None:
        """Print a warning once per step (the chain is applied to the same log several times)."""
        if message not in self.warnings:
            self.warnings.append(message)
            if not self.quiet:
                print(f"imupipe: warning: [{self.type} {self.sensor}] {message}", file=sys.stderr)

    def bias(self, variables: dict[str, np.ndarray]) -> np.ndarray:
        """(n, 3) modelled bias at the given variables."""
        knots = None if self.knots is None else np.asarray(self.knots) - self.tref
        return np.column_stack(
            [tm.evaluate(ax["terms"], ax["coefficients"], variables, knots) for ax in self.axes]
        )

    def apply(self, table: pa.Table) -> pa.Table:
        if not has_stream(table, "imu"):
            return table
        source = metadata(table).get("source", "the log")
        if not has_stream(table, "temperature"):
            raise CalibrationError(
                f"{source}: no temperature samples; the {self.sensor} temperature correction "
                "needs the temperature stream"
            )
        needs_ambient = bool(
            tm.term_variables([t for ax in self.axes for t in ax["terms"]]) & {"Ta", "dTa"}
        )
        if needs_ambient and (
            "ambient_temperature" not in table.column_names
            or table.column("ambient_temperature").null_count == len(table)
        ):
            raise CalibrationError(
                f"{source}: no ambient_temperature column; the {self.sensor} temperature "
                "correction was fitted with ambient terms"
            )
        data = sensor(table, self.sensor)
        variables = self.variables(table, data.t_ns)
        corrected = data.values - self.bias(variables)
        for axis, model in (self.scale or {}).items():
            i = AXES.index(axis)
            corrected[:, i] /= self.scale_factor(model, variables)
        return replace_sensor(table, self.sensor, data.rows, corrected)

    def scale_factor(self, model: dict[str, Any], variables: dict[str, np.ndarray]) -> np.ndarray:
        """sf(T) of one axis at the given variables."""
        knots = None if self.knots is None else np.asarray(self.knots) - self.tref
        return tm.evaluate(model["terms"], model["coefficients"], variables, knots)

    def to_json(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "sensor": self.sensor,
            "kind": self.kind,
            "model": self.model,
            "tref": self.tref,
            "window": self.window,
            "window_s": self.window_s,
            "ranges": self.ranges,
            "knots": self.knots,
            "scale": None
            if self.scale is None
            else {
                axis: {
                    "terms": list(m["terms"]),
                    "coefficients": [float(c) for c in m["coefficients"]],
                }
                for axis, m in self.scale.items()
            },
            "axes": [
                {"terms": list(ax["terms"]), "coefficients": [float(c) for c in ax["coefficients"]]}
                for ax in self.axes
            ],
            **self.params,
        }

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> TemperatureStep:
        known = {"type", "sensor", "kind", "model", "tref", "window", "window_s", "ranges"}
        known |= {"knots", "axes", "scale"}
        axes = entry["axes"]
        if len(axes) != 3:
            raise ValueError("'axes' must hold 3 entries (x, y, z)")
        for ax in axes:
            for term in ax["terms"]:
                tm.parse_term(term)
            if len(ax["terms"]) != len(ax["coefficients"]):
                raise ValueError("terms and coefficients differ in length")
        return cls(
            type=entry["type"],
            sensor=entry["sensor"],
            model=entry["model"],
            tref=float(entry["tref"]),
            window=entry.get("window"),
            window_s=entry.get("window_s"),
            axes=[
                {"terms": list(ax["terms"]), "coefficients": np.asarray(ax["coefficients"], float)}
                for ax in axes
            ],
            ranges={k: [float(v[0]), float(v[1])] for k, v in entry["ranges"].items()},
            knots=entry.get("knots"),
            scale=None
            if entry.get("scale") is None
            else {
                axis: {
                    "terms": list(m["terms"]),
                    "coefficients": np.asarray(m["coefficients"], float),
                }
                for axis, m in entry["scale"].items()
            },
            params={k: v for k, v in entry.items() if k not in known},
        )


# -- the stage -------------------------------------------------------------------------------


@dataclass
class Prepared:
    """Block means of one input: centres ``t_ns``, ``bias`` (m, 3) = means - reference, the
    absolute temperatures and rates (``T``, ``dT``, maybe ``Ta``, ``dTa``), and ``direction``
    (+1 heating, -1 cooling, 0 soak)."""

    t_ns: np.ndarray
    bias: np.ndarray
    variables: dict[str, np.ndarray]
    direction: np.ndarray
    reference: np.ndarray
    pairs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    """Turntable runs per turned axis: (temperature degC, scale factor) of each +/-rate pair."""
