"""The results of a run in short: per stage the fitted values with their units and
uncertainties, the quality figures, the warnings and what to look at.

One summary, three renderings: the terminal (:func:`print_summary`, with rich), the Rerun
recording (:func:`stage_markdown` and :func:`run_markdown`, markdown ``TextDocument`` s) and
``report.html``. It reads the ``results`` of ``calibration.json``; a key a stage does not write
is left out, so a stage that gains or loses a figure never breaks the summary, and a stage type
without a summariser here still gets its vectors, scalars and warnings listed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from imupipe.pipeline.notices import Notice, counted, meaning

AXES = ("x", "y", "z")


@dataclass
class Row:
    """One fitted quantity: up to three cells (x, y, z; or the axes named in ``name``)."""

    name: str
    cells: list[str]
    unit: str = ""

    @property
    def label(self) -> str:
        """``bias (rad/s)``: the name with the unit."""
        return f"{self.name} ({self.unit})" if self.unit else self.name


@dataclass
class StageSummary:
    name: str
    type: str
    input: str
    headline: str = ""
    rows: list[Row] = field(default_factory=list)
    quality: list[tuple[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    """The stage's own warnings (its fit's, its steps'); a reader's are in ``input_warnings``."""
    input_warnings: list[tuple[str, str]] = field(default_factory=list)
    """(input, message): what the reader of an input this stage read warned about; listed under
    the input (``[inputs.NAME]``), not the stage, in every rendering."""
    failed_checks: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    """The failed checks that refused this fit (one instance of several: the run went on
    without it, :mod:`imupipe.pipeline.instances`)."""
    caveats: list[str] = field(default_factory=list)
    """What the status line says beside ``ok`` (``at rest not judged (5 s)``)."""
    look_at: str = ""
    counts: frozenset[str] = frozenset()
    """Sensors the stage's input holds in raw counts (not SI): their offsets are in counts."""

    def unit(self, sensor: str, si: str) -> str:
        return "counts" if sensor in self.counts else si

    @property
    def status(self) -> str:
        """``ok``, ``ok, 2 warnings``, or ``1 failed check accepted, 2 warnings``: never a bare
        ``ok`` for a stage that warned; its caveats after the ``ok`` (``ok, at rest not judged
        (5 s), 1 warning``)."""
        n = len(self.warnings) + len(self.input_warnings)
        warned = f", {counted(n, 'warning')}" if n else ""
        said = "".join(f", {c}" for c in self.caveats)
        if self.refused:
            return f"refused ({counted(len(self.refused), 'failed check')}, not applied){warned}"
        if self.failed_checks:
            return f"{counted(len(self.failed_checks), 'failed check')} accepted{said}{warned}"
        return f"ok{said}{warned}"


# -- number formatting -------------------------------------------------------------------------
def fmt(value: Any, digits: int = 5) -> str:
    """A number with ``digits`` significant digits (``-`` when missing)."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if not isinstance(value, float) or not math.isfinite(value):
        return str(value)
    if value == 0:
        return "0"
    if 1e-3 <= abs(value) < 1e6:
        return f"{value:.{digits}g}"
    return sci(value, digits)


def sci(value: float, digits: int) -> str:
    """``value`` with ``digits`` significant digits in powers of ten: ``1.71e-4``, ``3.0e5``."""
    mantissa, exponent = f"{value:.{digits - 1}e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def fmt_pm(value: Any, sigma: Any) -> str:
    """``value ± sigma``, the value rounded to the second significant digit of ``sigma``; a
    sigma below 0.001 in powers of ten (``1.0199964 ± 6.8e-6``: no zeros to count, and a table
    of three such cells fits beside the plots)."""
    if value is None:
        return "-"
    if sigma is None or not isinstance(sigma, (int, float)) or not sigma > 0:
        return fmt(value)
    value = float(value)
    if not math.isfinite(sigma) or not math.isfinite(value):
        return f"{fmt(value)} ± {fmt(float(sigma))}"
    last = math.floor(math.log10(sigma)) - 1  # decimal position of sigma's second digit
    if 1e-3 <= abs(value) < 1e6 and last >= -9:
        decimals = max(0, -last)
        if decimals <= 4:
            return f"{value:.{decimals}f} ± {sigma:.{decimals}f}"
        return f"{value:.{decimals}f} ± {sci(sigma, 2)}"
    top = math.floor(math.log10(abs(value))) if value else last + 1
    return f"{sci(value, max(0, top - last) + 1)} ± {sci(sigma, 2)}"


def _get(d: Any, *keys: str, default: Any = None) -> Any:
    for key in keys:
        if not isinstance(d, dict) or key not in d:
            return default
        d = d[key]
    return d


def _vector(values: Any, scale: float = 1.0, sigmas: Any = None) -> list[str] | None:
    """Three cells from a list of three numbers (with ``sigmas``: value ± sigma)."""
    if not isinstance(values, (list, tuple)) or not values:
        return None
    if not all(isinstance(v, (int, float)) for v in values):
        return None
    if isinstance(sigmas, (list, tuple)) and len(sigmas) == len(values):
        return [fmt_pm(v * scale, s * scale) for v, s in zip(values, sigmas, strict=True)]
    return [fmt(v * scale) for v in values]


def _row(rows: list[Row], name: str, cells: list[str] | None, unit: str = "") -> None:
    if cells:
        rows.append(Row(name, cells, unit))


# -- per stage type ----------------------------------------------------------------------------
TERM_NAMES = {
    "Q": "quantization",
    "N": "white noise density",
    "B": "bias instability",
    "K": "random walk",
    "R": "rate ramp",
}


def _allan(r: dict[str, Any], s: StageSummary) -> None:
    units = _get(r, "metrics", "units", default={})
    heads = []
    for sensor in ("gyro", "accel"):
        per_axis = r.get(sensor)
        if not isinstance(per_axis, dict):
            continue
        for term in ("N", "B", "K", "Q", "R"):
            values = [_get(per_axis, a, term) for a in AXES]
            if not all(isinstance(v, (int, float)) for v in values):
                continue
            if term not in ("N", "K") and not any(values):
                continue
            cells = [fmt(v, 3) for v in values]
            if term == "K":
                upper = [_get(r, "metrics", sensor, a, "K_upper_68") for a in AXES]
                cells = [
                    f"< {fmt(u, 3)} (68%)" if v == 0 and isinstance(u, (int, float)) else c
                    for v, u, c in zip(values, upper, cells, strict=True)
                ]
            unit = _get(units, sensor, term, default="")
            s.rows.append(Row(f"{sensor} {term}, {TERM_NAMES[term]}", cells, unit))
            if term == "N":
                heads.append(f"{sensor} N {fmt(max(values), 3)} {unit}")
        fits = [_get(r, "metrics", sensor, a, "fit_rms_log10") for a in AXES]
        if any(isinstance(f, (int, float)) for f in fits):
            s.quality.append(
                (
                    f"{sensor} fit rms (log10 deviation)",
                    ", ".join(f"{a} {fmt(f, 2)}" for a, f in zip(AXES, fits, strict=True)),
                )
            )
    m = r.get("metrics", {})
    if "duration_s" in m:
        s.quality.append(
            ("recording", f"{fmt(m['duration_s'] / 3600, 3)} h at {fmt(m.get('rate_hz'), 4)} Hz")
        )
    if "static" in m:
        s.quality.append(("at rest", fmt(m["static"])))
    s.headline = "; ".join(heads)


def _gyro_bias(r: dict[str, Any], s: StageSummary) -> None:
    m = r.get("metrics", {})
    cells = _vector(r.get("bias"), sigmas=m.get("bias_std_error"))
    unit = s.unit("gyro", "rad/s")
    _row(s.rows, "bias", cells, unit)
    _row(s.rows, "noise std", _vector(m.get("std")), unit)
    if "duration_s" in m:
        s.quality.append(
            ("recording", f"{fmt(m['duration_s'], 4)} s, {m.get('samples', '-')} samples")
        )
    if "max_1s_excursion" in m:
        s.quality.append(("largest 1 s mean excursion", f"{fmt(m['max_1s_excursion'], 3)} {unit}"))
    rest = _at_rest(m)
    if rest:
        s.quality.append(("at rest", rest))
    if m.get("static_judged") is False:  # the status line says it, not only a warning
        s.caveats.append(f"at rest not judged ({fmt(m.get('duration_s'), 2)} s)")
    if cells:
        s.headline = (
            "bias " + ", ".join(f"{a} {c}" for a, c in zip(AXES, cells, strict=True)) + f" {unit}"
        )


def _at_rest(m: dict[str, Any]) -> str:
    """``yes``, ``no``, or ``not judged (5 s, need a minute or more)`` for a recording too short
    to tell (``static_judged`` false; ``""`` without ``static``)."""
    if "static" not in m:
        return ""
    if m.get("static_judged") is False:
        return f"not judged ({fmt(m.get('duration_s'), 2)} s, need a minute or more)"
    return fmt(m["static"])


def _residual(rms: Any, largest: Any, before: Any, unit: str) -> str:
    """``0.0075 mg rms (max 0.018 mg); before calibration 10.1 mg``."""
    text = f"{fmt(rms, 3)} {unit} rms"
    if largest is not None:
        text += f" (max {fmt(largest, 3)} {unit})"
    if before is not None:
        text += f"; before calibration {fmt(before, 3)} {unit}"
    return text


def _misalignment(r: dict[str, Any], s: StageSummary, sigmas: Any = None) -> None:
    mis = r.get("misalignment_rad")
    if not isinstance(mis, dict):
        return
    names = list(mis)
    sig = sigmas if isinstance(sigmas, list) and len(sigmas) == len(names) else [None] * len(names)
    for i in range(0, len(names), 3):
        part = names[i : i + 3]
        cells = [
            fmt_pm(mis[n] * 1e3, None if sig[i + j] is None else sig[i + j] * 1e3)
            for j, n in enumerate(part)
        ]
        s.rows.append(Row(f"misalignment ({', '.join(part)})", cells, "mrad"))


def _accel_calibration(r: dict[str, Any], s: StageSummary) -> None:
    m = r.get("metrics", {})
    u = m.get("uncertainty", {})
    _row(s.rows, "scale", _vector(r.get("scale"), sigmas=u.get("scale_std")))
    _misalignment(r, s, u.get("misalignment_std_rad"))
    bias = _vector(r.get("bias"), sigmas=u.get("bias_std"))
    _row(s.rows, "bias", bias, s.unit("accel", "m/s^2"))
    res = m.get("residual_mg", {})
    if "means_rms" in res:
        text = _residual(res["means_rms"], res.get("means_max"), res.get("raw_means_rms"), "mg")
        s.quality.append(("residual |a| - g of the pose means", text))
        if res.get("start_means_rms") is not None:
            s.quality.append(
                (
                    "residual |a| - g of the start (sphere centre, one scale)",
                    f"{fmt(res['start_means_rms'], 3)} mg rms",
                )
            )
        s.headline = f"residual {fmt(res['means_rms'], 3)} mg rms over {m.get('poses', '?')} poses"
    if m.get("error_95_mg") is not None:
        s.quality.append(
            ("error over all orientations (95 % bound)", f"{fmt(m['error_95_mg'], 3)} mg rms")
        )
    if "samples_rms" in res:
        s.quality.append(
            ("residual |a| - g of every still sample", f"{fmt(res['samples_rms'], 3)} mg rms")
        )
    if "intervals" in m:
        text = f"{m['intervals']}, grouped into {m.get('poses', '?')} poses"
        s.quality.append(
            ("still intervals", f"{text} ({m.get('distinct_poses', '?')} distinct directions)")
        )
    if "condition_number" in u:
        s.quality.append(("condition number", fmt(u["condition_number"], 3)))
    if r.get("method"):
        s.quality.append(("method", str(r["method"])))


def _gyro_calibration(r: dict[str, Any], s: StageSummary) -> None:
    m = r.get("metrics", {})
    _row(s.rows, "scale", _vector(r.get("scale")))
    _misalignment(r, s)
    _row(s.rows, "bias", _vector(r.get("bias")), s.unit("gyro", "rad/s"))
    res = m.get("gravity_direction_residual_deg", {})
    if "rms" in res:
        text = _residual(res["rms"], res.get("max"), res.get("raw_rms"), "deg")
        s.quality.append(("gravity direction after each rotation", text))
        if res.get("start_rms") is not None:
            s.quality.append(
                (
                    "gravity direction, start (bias removed, one scale)",
                    f"{fmt(res['start_rms'], 3)} deg rms",
                )
            )
        s.headline = f"gravity direction residual {fmt(res['rms'], 3)} deg rms over {m.get('transitions', '?')} rotations"
    if "condition_number" in m:
        s.quality.append(("condition number", fmt(m["condition_number"], 3)))


def _mag_calibration(r: dict[str, Any], s: StageSummary) -> None:
    m = r.get("metrics", {})
    unit, scale = ("counts", 1.0) if "mag" in s.counts else ("uT", 1e6)
    _row(s.rows, "hard iron, centre", _vector(r.get("centre"), scale), unit)
    _row(s.rows, "ellipsoid radii", _vector(r.get("radii"), scale), unit)
    _row(s.rows, "soft iron diagonal", _vector(m.get("soft_iron_diagonal")))
    if isinstance(r.get("field"), (int, float)):
        s.rows.append(Row("field magnitude", [fmt(r["field"] * scale)], unit))
    if "norm_std_pct" in m:
        text = f"{fmt(m['norm_std_pct'], 3)} %"
        if "raw_norm_std_pct" in m:
            text += f" (raw {fmt(m['raw_norm_std_pct'], 3)} %)"
        s.quality.append(("spread of |h| after calibration", text))
        s.headline = (
            f"|h| spread {fmt(m['norm_std_pct'], 3)} % (raw {fmt(m.get('raw_norm_std_pct'), 3)} %)"
        )
    if "coverage_fraction" in m:
        s.quality.append(("sphere coverage", f"{fmt(m['coverage_fraction'] * 100, 3)} %"))
    if "samples_used" in m:
        s.quality.append(
            (
                "samples used",
                f"{m['samples_used']} of {m.get('samples', '?')} ({_dropped(m)})",
            )
        )


MG_PER_UT = 10.0
"""1 uT = 10 mG (milligauss: ArduPilot's COMPASS_OFS and COMPASS_MOT unit)."""


def _mag_inflight(r: dict[str, Any], s: StageSummary) -> None:
    """The in-flight compass fit in the units people use: offsets in uT and mG, the soft-iron
    matrix row by row, the motor term in uT and mG per ampere (or per unit of throttle), the
    residual against the WMM in uT and the heading error in deg, before and after."""
    m = r.get("metrics", {})
    se = r.get("parameter_se") if isinstance(r.get("parameter_se"), dict) else {}
    offset = _vector(r.get("offset_t"), 1e6)
    _row(s.rows, "hard iron, offset", offset, "uT")
    _row(s.rows, "hard iron, offset", _vector(r.get("offset_t"), 1e6 * MG_PER_UT), "mG")
    matrix = r.get("matrix")
    if isinstance(matrix, list) and len(matrix) == 3 and r.get("model") != "offsets":
        for axis, row in zip(AXES, matrix, strict=True):
            if isinstance(row, list) and all(isinstance(v, (int, float)) for v in row):
                s.rows.append(Row(f"soft iron, row {axis}", [f"{v:.4f}" for v in row]))
    per, key = (
        ("throttle", "motor_t_per_throttle")
        if "motor_t_per_throttle" in r
        else (
            "A",
            "motor_t_per_a",
        )
    )
    motor = r.get(key)
    if r.get("motor_term") and isinstance(motor, list):
        names = [f"motor_{a} [uT/{'A' if per == 'A' else 'throttle'}]" for a in AXES]
        sig = [se.get(n) for n in names]
        sig_t = [v * 1e-6 for v in sig] if all(isinstance(v, (int, float)) for v in sig) else None
        _row(s.rows, "motor interference", _vector(motor, 1e6, sig_t), f"uT/{per}")
        _row(s.rows, "motor interference", _vector(motor, 1e6 * MG_PER_UT), f"mG/{per}")
    model = r.get("model")
    if model:
        held = m.get("held_out_rms_ut", {})
        text = str(model)
        if isinstance(held, dict) and held:
            text += (
                " (held-out residual: "
                + ", ".join(f"{k} {fmt(v, 3)} uT" for k, v in held.items())
                + ")"
            )
        s.quality.append(("model", text))
    source = r.get("motor_source")
    s.quality.append(("motor term", f"per {source}" if r.get("motor_term") else "not fitted"))
    if "residual_rms_ut_after" in m:
        s.quality.append(
            (
                "vector residual against the WMM",
                f"{fmt(m['residual_rms_ut_after'], 3)} uT rms; before "
                f"{fmt(m.get('residual_rms_ut_before'), 3)} uT",
            )
        )
    if "heading_rms_deg_after" in m:
        s.quality.append(
            (
                "heading error",
                f"{fmt(m['heading_rms_deg_after'], 3)} deg rms; before "
                f"{fmt(m.get('heading_rms_deg_before'), 3)} deg",
            )
        )
        s.headline = (
            f"heading error {fmt(m.get('heading_rms_deg_before'), 3)} -> "
            f"{fmt(m['heading_rms_deg_after'], 3)} deg rms"
        )
    if "field_ut" in m:
        year = f" (WMM, {fmt(r['year'], 5)})" if isinstance(r.get("year"), (int, float)) else ""
        s.quality.append(("field magnitude" + year, f"{fmt(m['field_ut'], 4)} uT"))
    cov = r.get("coverage", {})
    if isinstance(cov, dict) and "yaw_coverage_deg" in cov:
        s.quality.append(
            (
                "attitudes flown",
                f"yaw {fmt(cov['yaw_coverage_deg'], 3)} deg, tilt up to "
                f"{fmt(cov.get('tilt_max_deg'), 3)} deg",
            )
        )
    if "samples" in m:
        s.quality.append(("samples", f"{m['samples']} ({m.get('outliers', 0)} outliers)"))
    for name, f in (m.get("flights") or {}).items():
        if isinstance(f, dict):
            s.quality.append(
                (
                    f"flight {name}",
                    f"{fmt(f.get('residual_rms_ut_after'), 3)} uT rms (before "
                    f"{fmt(f.get('residual_rms_ut_before'), 3)}), heading "
                    f"{fmt(f.get('heading_rms_deg_after'), 3)} deg rms",
                )
            )
    if r.get("not_fitted"):
        s.quality.append(("not fitted", "; ".join(str(x) for x in r["not_fitted"])))


def _dropped(m: dict[str, Any]) -> str:
    """Where the samples a magnetometer fit did not use went: ``7 thinned, 6 outliers``."""
    samples, thinned = m.get("samples"), m.get("samples_after_thinning")
    parts = (
        [f"{samples - thinned} thinned"]
        if isinstance(samples, int) and isinstance(thinned, int)
        else []
    )
    return ", ".join([*parts, f"{m.get('outliers', 0)} outliers"])


def _temperature(r: dict[str, Any], s: StageSummary) -> None:
    m = r.get("metrics", {})
    unit = r.get("unit", "")
    coef = r.get("coefficients", {})
    terms = r.get("terms", {})
    if r.get("model"):
        s.quality.append(
            (
                "model",
                f"{r['model']}: " + ", ".join(terms.get("x", [])) if terms else str(r["model"]),
            )
        )
    if isinstance(r.get("tref"), (int, float)):
        const = [
            coef.get(a, [None])[terms.get(a, []).index("1")] if "1" in terms.get(a, []) else None
            for a in AXES
        ]
        if all(isinstance(c, (int, float)) for c in const):
            _row(s.rows, f"bias at {fmt(r['tref'], 4)} degC", [fmt(c) for c in const], unit)
    for key, name in (("rms_before", "rms before"), ("rms_after", "rms after")):
        _row(s.rows, name, _vector([_get(m, a, key) for a in AXES]), unit)
    _row(s.rows, "reduction (rms before / after)", _vector([_get(m, a, "reduction") for a in AXES]))
    _row(s.rows, "R^2", _vector([_get(m, a, "r2") for a in AXES]))
    if "validate" in m:
        v = m["validate"]
        _row(
            s.rows,
            f"held-out rms after ({v.get('input', '?')})",
            _vector([_get(v, a, "rms_after") for a in AXES]),
            unit,
        )
    if "temperature_range" in r:
        lo, hi = r["temperature_range"]
        s.quality.append(("temperature range", f"{fmt(lo, 3)} .. {fmt(hi, 3)} degC"))
    if "rate_range" in r:
        lo, hi = r["rate_range"]  # degC/min
        s.quality.append(("rate range", f"{fmt(lo, 3)} .. {fmt(hi, 3)} degC/min"))
    if isinstance(r.get("choice"), dict) and r["choice"].get("reason"):
        s.quality.append(("model choice", str(r["choice"]["reason"])))
    held = [_get(m, a, "held_out_rms") for a in AXES]
    if all(isinstance(v, (int, float)) for v in held):
        _row(s.rows, "held-out rms (model)", _vector(held), unit)
        _row(
            s.rows,
            "held-out rms (no compensation)",
            _vector([_get(m, a, "held_out_baseline") for a in AXES]),
            unit,
        )
        upper = [_get(m, a, "remaining_rms_95", default=[None, None])[1] for a in AXES]
        _row(s.rows, "remaining bias rms, 95 % upper", _vector(upper), unit)
    after = [_get(m, a, "rms_after") for a in AXES]
    if all(isinstance(v, (int, float)) for v in after):
        s.headline = f"{r.get('sensor', '')} bias rms after {fmt(max(after), 3)} {unit}"


def _at_tref(r: dict[str, Any], sensor: str, quantity: str) -> list[Any]:
    """Per axis the constant term (the value at tref) of a thermal_soak parameter polynomial."""
    per_axis = _get(r, sensor, "parameters", quantity, default={})
    return [
        p["coefficients"][p["terms"].index("1")] if "1" in p.get("terms", []) else None
        for p in (per_axis.get(a, {}) for a in AXES)
    ]


def _thermal_soak(r: dict[str, Any], s: StageSummary) -> None:
    tref = fmt(r.get("tref"), 4)
    for sensor, unit in (("accel", "m/s^2"), ("gyro", "rad/s")):
        if sensor in r:
            _row(s.rows, f"{sensor} scale at {tref} degC", _vector(_at_tref(r, sensor, "scale")))
            bias = _vector(_at_tref(r, sensor, "bias"))
            _row(s.rows, f"{sensor} bias at {tref} degC", bias, s.unit(sensor, unit))
    temps = [soak.get("temperature") for soak in r.get("soaks", [])]
    if temps:
        s.quality.append(
            ("soaks", f"{len(temps)}, at " + ", ".join(fmt(t, 3) for t in temps) + " degC")
        )
    res = _get(r, "metrics", "accel_norm_residual_mg", default={})
    if "thermal_model" in res:
        one = res.get("one_temperature")
        text = f"{fmt(res['thermal_model'], 3)} mg with the thermal model; raw {fmt(res.get('raw'), 3)} mg"
        if one is not None:
            text += f"; {fmt(one, 3)} mg with the {fmt(res.get('one_temperature_at'), 3)} degC soak's calibration everywhere"
        s.quality.append(("| |a| - g | at the soaks' poses", text))
        s.headline = f"| |a| - g | {fmt(res['thermal_model'], 3)} mg over {len(temps)} soaks"


def _average(r: dict[str, Any], s: StageSummary) -> None:
    window = f"{r['window']} samples" if r.get("window") else f"{fmt(r.get('window_s'))} s"
    s.quality.append(("window", window))
    for name, m in r.get("metrics", {}).items():
        if isinstance(m, dict) and "blocks" in m:
            s.quality.append((name, f"{m.get('samples')} samples -> {m['blocks']} block means"))
    s.headline = f"block means over {window}"


def _generic(r: dict[str, Any], s: StageSummary) -> None:
    skip = {"type", "input", "warnings", "failed_checks", "metrics"}
    for key, value in r.items():
        if key in skip:
            continue
        if cells := _vector(value):
            s.rows.append(Row(key, cells[:3] if len(cells) == 3 else [", ".join(cells)]))
        elif isinstance(value, (int, float, str)) and not isinstance(value, bool):
            s.quality.append((key, fmt(value)))
    for key, value in r.get("metrics", {}).items():
        if isinstance(value, (int, float, str)):
            s.quality.append((key, fmt(value)))


LOOK_AT: dict[str, str] = {
    "allan": (
        "The measured deviation (markers) should follow the fitted model inside its 68% band. "
        "The slope reads the noise: -1/2 at short tau is white noise (N), flat is bias "
        "instability (B), +1/2 at long tau is random walk (K). A bump or a step away from the "
        "model means the IMU moved or its temperature drifted during the recording; a band that "
        "widens at long tau asks for a longer recording (IEEE Std 952, Annex C)."
    ),
    "gyro_bias": (
        "The corrected gyro should sit on zero with no trend; a drift or steps in the one-second "
        "means mean the IMU moved or warmed up during the recording."
    ),
    "accel_calibration": (
        "After calibration |a| should equal g in every still pose: the residual per pose should "
        "be small and even across poses (one pose far above the rest was not still, or was "
        "touched). The poses should cover many directions (Tedaldi et al., ICRA 2014)."
    ),
    "gyro_calibration": (
        "Integrating the calibrated gyro between two still poses should turn gravity into the "
        "next pose's gravity: the residual per transition should be small everywhere "
        "(Tedaldi et al., ICRA 2014)."
    ),
    "mag_calibration": (
        "The raw samples should lie on the fitted ellipsoid and cover it all round; after "
        "calibration they should lie on the sphere of the field's magnitude, and |h| should be "
        "flat over time. Gaps in the coverage leave the soft-iron terms poorly determined."
    ),
    "temperature": (
        "The fitted curves should pass through the bias blocks at every temperature; heating and "
        "cooling apart means hysteresis, which the rate (dT) terms model. The residual over time "
        "should be flat, and the held-out run's residual as small as the fitted one's."
    ),
    "average": "The block means show slow drift that the raw noise hides.",
    "mag_inflight": (
        "The heading error after calibration should stay near zero along the whole flight, "
        "with no steps where the current or throttle changes; the vector residual after should "
        "be flat against the current (a slope left over means a motor term is missing). Offsets "
        "of more than a few hundred mG or a soft-iron row far from (1, 0, 0) point to a magnet "
        "or steel near the compass. The fit needs full turns and banks of tens of degrees: "
        "with less, the offsets and the scale cannot be told apart (ArduPilot MagFit)."
    ),
}
"""What a person should check in each stage's plots (the report and the recording say it)."""


SUMMARISERS: dict[str, Callable[[dict[str, Any], StageSummary], None]] = {
    "allan": _allan,
    "gyro_bias": _gyro_bias,
    "accel_calibration": _accel_calibration,
    "gyro_calibration": _gyro_calibration,
    "mag_calibration": _mag_calibration,
    "mag_inflight": _mag_inflight,
    "temperature": _temperature,
    "thermal_soak": _thermal_soak,
    "average": _average,
}


def raw_count_sensors(inputs: Mapping[str, Any]) -> dict[str, set[str]]:
    """Input name -> the sensors a CSV mapping reads in raw counts (``<sensor>_unit = "raw"``)."""
    return {
        name: {s for s in ("gyro", "accel", "mag") if getattr(spec.csv, f"{s}_unit", "") == "raw"}
        for name, spec in inputs.items()
    }


def summarise(
    results: dict[str, dict[str, Any]],
    counts: Mapping[str, set[str]] | None = None,
    notices: Sequence[Notice] = (),
) -> list[StageSummary]:
    """One :class:`StageSummary` per stage of ``calibration.json``'s ``results``, in run order;
    ``counts``: input -> sensors in raw counts (:func:`raw_count_sensors`); ``notices``: the
    run's record (:class:`~imupipe.pipeline.notices.Notices`), which tells a reader's warnings
    (listed under their input) from the stage's own."""
    out = []
    for name, r in results.items():
        s = StageSummary(name=name, type=str(r.get("type", "?")), input=str(r.get("input", "?")))
        s.counts = frozenset((counts or {}).get(s.input, ()))
        try:
            SUMMARISERS.get(s.type, _generic)(r, s)
        except (TypeError, ValueError, KeyError, IndexError, ZeroDivisionError) as exc:
            s.quality.append(("summary", f"incomplete ({type(exc).__name__}: {exc})"))
        s.look_at = LOOK_AT.get(s.type, "")
        read = {n.message: n.source.split(".", 1)[1] for n in notices if n.stage == name and n.source.startswith("inputs.")}  # fmt: skip
        warnings = [" ".join(str(w).split()) for w in r.get("warnings", [])]
        s.warnings = [w for w in warnings if w not in read]
        s.input_warnings = [(read[w], w) for w in warnings if w in read]
        s.failed_checks = [str(c) for c in r.get("failed_checks", [])]
        s.refused = [str(c) for c in r.get("refused", [])]
        if s.refused:
            s.headline = f"refused: {s.refused[0]}"
        out.append(s)
    return out


# -- renderings --------------------------------------------------------------------------------
def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _md_table(rows: Sequence[Row]) -> list[str]:
    if not rows:
        return []
    lines = ["| quantity | x | y | z |", "|---|---:|---:|---:|"]
    for row in rows:
        cells = (row.cells + ["", "", ""])[:3]
        lines.append("| " + " | ".join(_md_escape(c) for c in [row.label, *cells]) + " |")
    return lines


def stage_markdown(s: StageSummary, heading: str = "#") -> str:
    """A stage's summary as markdown (its tab's document in the recording)."""
    lines = [f"{heading} {s.name}", "", f"`{s.type}` on input `{s.input}`: {s.status}", ""]
    lines += _md_table(s.rows)
    if s.quality:
        lines += ["", "**Quality**", ""]
        lines += [f"- {_md_escape(k)}: {_md_escape(v)}" for k, v in s.quality]
    if s.failed_checks:
        lines += ["", "**Failed checks (accepted)**", ""] + [f"- {c}" for c in s.failed_checks]
    if s.refused:
        lines += ["", "**Failed checks (refused: not applied)**", ""]
        lines += [f"- {_md_escape(c)}" for c in s.refused]
    if s.warnings:
        lines += ["", "**Warnings**", ""]
        lines += [f"- {_md_escape(w)}  \n  *What it means:* {meaning(w)}" for w in s.warnings]
    for name, messages in by_input(s.input_warnings).items():
        lines += ["", f"{_from_input(name, len(messages))}, listed under `inputs.{name}` in the Summary."]  # fmt: skip
    if s.look_at:
        lines += ["", f"**What to look at.** {s.look_at}"]
    return "\n".join(lines) + "\n"


def notes_markdown(summaries: Sequence[StageSummary], notes: Sequence[Notice] = ()) -> list[str]:
    """Every warning of the stages and every note of the run (``notes``), each with its
    meaning: the list the run's summary opens with (none: nothing)."""
    items = [(where, "warning", m) for where, m in reader_items(summaries)]
    items += [(s.name, "warning", w) for s in summaries for w in s.warnings]
    items += [(n.where, n.level, n.message) for n in notes]
    if not items:
        return []
    lines = ["", f"**Warnings and notes ({len(items)})**", ""]
    for where, level, message in items:
        lines.append(f"- {level} [{_md_escape(where)}]: {_md_escape(message)}  ")
        lines.append(f"  *What it means:* {meaning(message, where)}")
    return lines


def by_input(items: Sequence[tuple[str, str]]) -> dict[str, list[str]]:
    """(input, message) pairs as input -> its messages, each once, in the order raised."""
    out: dict[str, list[str]] = {}
    for name, message in items:
        if message not in out.setdefault(name, []):
            out[name].append(message)
    return out


def inputs_warned(summaries: Sequence[StageSummary]) -> dict[str, list[str]]:
    """Input -> what its reader warned about (each once, however many stages read it)."""
    return by_input([item for s in summaries for item in s.input_warnings])


def reader_items(summaries: Sequence[StageSummary]) -> list[tuple[str, str]]:
    """(``inputs.NAME``, message) of every reader warning of the run, each once."""
    return [(f"inputs.{n}", m) for n, ms in inputs_warned(summaries).items() for m in ms]


def _from_input(name: str, n: int) -> str:
    """``The reader of its input gyro1 warned (3)``: a stage's pointer to its input's warnings."""
    return f"The reader of its input `{name}` warned ({n})"


def inputs_markdown(summaries: Sequence[StageSummary]) -> list[str]:
    """A section per input whose reader warned: its warnings with their meanings."""
    lines: list[str] = []
    for name, messages in inputs_warned(summaries).items():
        lines += ["", f"## inputs.{name}", "", "**Warnings of its reader**", ""]
        where = f"inputs.{name}"
        lines += [f"- {_md_escape(m)}  \n  *What it means:* {meaning(m, where)}" for m in messages]
    return lines


def run_markdown(
    summaries: Sequence[StageSummary], title: str = "imupipe run", notes: Sequence[Notice] = ()
) -> str:
    """The run's summary: a table of the stages, every warning and note (``notes``: the run's
    own, the exports'), then each stage's summary."""
    lines = [
        f"# {title}",
        "",
        "| stage | type | input | result | status |",
        "|---|---|---|---|---|",
    ]
    for s in summaries:
        lines.append(
            "| "
            + " | ".join(
                _md_escape(c) for c in (s.name, s.type, s.input, s.headline or "-", s.status)
            )
            + " |"
        )
    lines += notes_markdown(summaries, notes)
    lines += inputs_markdown(summaries)
    for s in summaries:
        lines += ["", stage_markdown(s, heading="##")]
    return "\n".join(lines) + "\n"


def print_summary(summaries: Sequence[StageSummary], console: Any = None) -> None:
    """The summary on the terminal (rich tables; plain text when not a terminal)."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    if console is None:  # a pipe or a file gets the long lines whole
        import sys

        tty = sys.stdout.isatty()
        console = Console(width=None if tty else 160, soft_wrap=not tty)
    for s in summaries:
        # the title on its own line: as a table's title it wrapped to the table's width
        console.print(
            f"[bold]{escape(s.name)}[/bold] ({escape(s.type)} on {escape(s.input)}): {s.status}"
        )
        if s.rows:
            table = Table(show_edge=False, pad_edge=False)
            table.add_column("quantity")
            for axis in AXES:
                table.add_column(axis, justify="right", no_wrap=True)
            for row in s.rows:
                table.add_row(row.label, *(row.cells + ["", "", ""])[:3])
            console.print(table)
        for key, value in s.quality:
            console.print(f"  {key}: {value}", highlight=False)
        for check in s.failed_checks:
            console.print(f"  [red]failed check (accepted):[/red] {escape(check)}", highlight=False)
        for check in s.refused:
            console.print(f"  [red]failed check (refused):[/red] {escape(check)}", highlight=False)
        for warning in s.warnings:
            console.print(f"  [yellow]warning:[/yellow] {escape(warning)}", highlight=False)
        for name, messages in by_input(s.input_warnings).items():
            text = _from_input(name, len(messages)).replace("`", "")
            under = escape(f"[inputs.{name}]")
            console.print(f"  [yellow]{text}[/yellow]: listed under {under} below", highlight=False)
        console.print()


def print_notices(notices: Sequence[Notice], console: Any = None) -> None:
    """Every warning and note of the run, each with what it means: the end of the summary on
    the terminal, just above the files written (the warnings printed while the run went have
    scrolled away)."""
    # a reader's warning once, however many stages read the input
    notices = list({(n.level, n.where, n.message): n for n in notices}.values())
    if not notices:
        return
    from rich.console import Console
    from rich.markup import escape

    if console is None:
        import sys

        console = Console(width=None if sys.stdout.isatty() else 160)
    warnings = sum(n.level == "warning" for n in notices)
    head = ", ".join(
        c
        for c in (
            counted(warnings, "warning") if warnings else "",
            counted(len(notices) - warnings, "note") if len(notices) > warnings else "",
        )
        if c
    )
    console.print(f"[bold]{head}[/bold] (also in calibration.json and report.html):")
    for n in notices:
        color = "yellow" if n.level == "warning" else "cyan"
        where, message = escape(f"[{n.where}]"), escape(n.message)
        console.print(f"- [{color}]{n.level}[/{color}] {where}: {message}", highlight=False)
        console.print(f"  what it means: {escape(n.meaning)}", highlight=False, style="dim")
    console.print()
