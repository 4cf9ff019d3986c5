"""What the exporters share: the noise figures of an ``allan`` stage, the chain of one sensor
composed into one raw-domain model, the IMU intrinsics in Kalibr's form, and the serializers.

**Devices** (:func:`device_models`). The chain's entries of a sensor are grouped by the device
they were fitted on (:func:`imupipe.pipeline.calibration_file.same_device`: ``device_id``, else
the log's ``instance``), in the order the devices first appear. An entry that names neither (a
CSV or ROS input, a step imported from another tool) belongs to every device, as ``run`` and
``convert`` apply it to every device's data. Steps of one device compose; steps of different devices never do: each device is
one :class:`SensorModel`, which the autopilot exports put in its own parameter slot.

**Composition** (:func:`device_models`). The chain's steps of one device's sensor, in order, become

    corrected = M @ (raw - o - b(T)),   b(T) = sum_k C[:, k] (T - Tref)^k  (k <= 3, clamped T)

A linear step ``M2 @ (x - o2)`` after it gives ``M <- M2 M``, ``o <- o + M^-1 o2``; a
temperature step ``x - f(T)`` gives ``b <- b + M^-1 f`` (re-expanded about the first Tref). This
is the form of PX4 (``Correct``: ``(data - _thermal_offset - _offset) * _scale``, PX4-Autopilot
``src/lib/sensor_calibration/Accelerometer.hpp``) and ArduPilot
(``_rotate_and_correct_accel``: temperature correction, ``-= offset``, ``*= scale``,
``libraries/AP_InertialSensor/AP_InertialSensor_Backend.cpp``). A temperature model maps only
when every axis is a polynomial of order <= 3 in T (no rate, ambient, piecewise or scale terms);
anything else is reported as an issue and left out.

**Kalibr's form** (:func:`kalibr_intrinsics`): Kalibr's ``scale-misalignment`` model
(ethz-asl/kalibr ``IccSensors.py``, ``IccScaledMisalignedImu``) measures
``a_m = M_a a + b_a`` and ``w_m = M_g C_gyro_i w + A a + b_g`` with ``M_a``, ``M_g`` lower
triangular and ``C_gyro_i`` a rotation, in an IMU frame whose x axis is the accelerometer's.
From imupipe's ``a = A (a_m - o_a)``: the LQ decomposition ``A^-1 = M_a Q`` gives ``M_a`` and
the rotation ``Q`` from imupipe's corrected frame to Kalibr's; then ``G^-1 Q^T = M_g C_gyro_i``.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imupipe.pipeline.calibration_file import UNNAMED, device, device_key, same_device

AXES = ("x", "y", "z")
POLY_TERMS = ("1", "T", "T^2", "T^3")
"""The temperature-model terms the autopilots' thermal polynomials can hold."""
OFF_DIAGONAL = ((0, 1), (0, 2), (1, 2))
"""The autopilots' order of a symmetric matrix's off-diagonal elements (X, Y, Z)."""
RELATIVE_TOLERANCE = 1e-9
"""Off-diagonal (or asymmetric) parts below this fraction of the diagonal count as zero."""


@dataclass
class Export:
    """An exporter's output: file name -> text; file name -> notes (what did not map, printed
    as warnings); file name -> facts recorded in ``calibration.json`` (``exports``)."""

    files: dict[str, str] = field(default_factory=dict)
    notes: dict[str, list[str]] = field(default_factory=dict)
    info: dict[str, dict[str, Any]] = field(default_factory=dict)

    def note(self, fname: str, text: str) -> None:
        self.notes.setdefault(fname, []).append(" ".join(text.split()))


# -- noise ---------------------------------------------------------------------------------------


def allan_results(doc: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(stage name, results) of every ``allan`` stage, in run order."""
    return [(n, r) for n, r in doc.get("results", {}).items() if r.get("type") == "allan"]


@dataclass(frozen=True)
class Noise:
    """One sensor's Kalibr-style noise: the largest axis of N and K, and where they came from.
    ``k_bound`` is true when the fit resolved no random walk and K is the upper bound of the
    68 % band (a zero would make a filter overconfident)."""

    density: float
    density_axis: str
    random_walk: float
    random_walk_axis: str
    k_bound: bool
    n_bound: bool = False
    """The fit resolved no white noise on that axis: ``density`` is the upper bound from the
    shortest taus (``N_upper``), never a zero."""


def noise(results: Mapping[str, Any], sensor: str) -> Noise | None:
    """The noise of ``sensor`` (gyro or accel) in an allan stage's results (continuous time:
    N per sqrt(Hz), K per second per sqrt(Hz)); None when the stage did not fit it."""
    if sensor not in results:
        return None
    per_axis = results[sensor]
    axes = [a for a in AXES if a in per_axis]  # a dead axis has no fit (allan's dead_axes)
    if not axes:
        return None
    bounds = results.get("metrics", {}).get(sensor, {})
    density = {
        a: (float(per_axis[a]["N"]), False)
        if per_axis[a]["N"] > 0 or "N_upper" not in bounds.get(a, {})
        else (float(bounds[a]["N_upper"]), True)
        for a in axes
    }
    n_axis = max(axes, key=lambda a: density[a][0])
    k_axis = max(axes, key=lambda a: per_axis[a]["K"])
    k, bound = float(per_axis[k_axis]["K"]), False
    if k == 0.0:
        upper = results["metrics"][sensor]
        k_axis = max(axes, key=lambda a: upper[a]["K_upper_68"])
        k, bound = float(upper[k_axis]["K_upper_68"]), True
    return Noise(density[n_axis][0], n_axis, k, k_axis, bound, density[n_axis][1])


def first_allan(doc: Mapping[str, Any]) -> tuple[str, dict[str, Any]] | None:
    """(name, results) of the first ``allan`` stage, or None."""
    found = allan_results(doc)
    return found[0] if found else None


def imu_topic(results: Mapping[str, Any], default: str = "/imu/data") -> str:
    """The IMU topic a stage fitted on (its ``fitted_on``), else ``default``."""
    return (results.get("fitted_on") or {}).get("topics", {}).get("imu") or default


def rate_hz(results: Mapping[str, Any]) -> float:
    """The sample rate measured from the timestamps, Hz, to 9 significant digits (a 400 Hz clock
    reads 400.0, not 399.99999999999994)."""
    return float(f"{float(results['metrics']['rate_hz']):.9g}")


# -- composition ---------------------------------------------------------------------------------


@dataclass
class Thermal:
    """A raw-domain thermal bias ``b(T) = sum_k C[:, k] (T - tref)^k``, valid (clamped) over
    ``t_range`` degC; ``C`` (3, 4) in the sensor's unit."""

    tref: float
    coefficients: np.ndarray
    t_range: tuple[float, float]

    def about(self, t0: float) -> np.ndarray:
        """The coefficients re-expanded about ``t0``: ``b(T) = sum_k D[:, k] (T - t0)^k``."""
        shift = np.polynomial.Polynomial([t0 - self.tref, 1.0])
        out = np.zeros((3, 4))
        for i in range(3):
            c = np.polynomial.Polynomial(self.coefficients[i])(shift).coef
            out[i, : len(c)] = c
        return out

    def at(self, t: float) -> np.ndarray:
        x = float(np.clip(t, *self.t_range)) - self.tref
        return self.coefficients @ (x ** np.arange(4))


LINEAR_KINDS = ("linear", "mag_current", "mag_throttle")
"""Step kinds with a matrix and an offset (``mag_current`` adds a per-ampere term: ``motor``;
``mag_throttle`` a term per unit of throttle)."""
MOTOR_SOURCE = {"mag_current": "current", "mag_throttle": "throttle"}
"""The power signal each motor step kind multiplies ``motor`` by."""


@dataclass
class SensorModel:
    """One device's sensor chain composed (see the module docstring): ``corrected = matrix @
    (raw - offset - thermal(T))``; ``entries`` are the chain entries used, ``issues`` what could
    not be composed (left out), ``device`` the device (:func:`entry_device`)."""

    sensor: str
    matrix: np.ndarray
    offset: np.ndarray
    thermal: Thermal | None
    entries: list[dict[str, Any]]
    issues: list[str]
    device: dict[str, Any] = field(default_factory=dict)
    motor: np.ndarray | None = None
    """A magnetometer's field per ampere of battery current (T/A), or per unit of throttle
    (``motor_source``), added after ``matrix`` (a ``mag_current``/``mag_throttle`` step,
    ``mag_inflight``); None when no step estimated one."""
    motor_source: str = "current"
    """What ``motor`` multiplies: ``"current"`` (A) or ``"throttle"`` (0..1)."""

    @property
    def linear(self) -> bool:
        """Whether a linear step (offset, and a matrix) was estimated."""
        return any(e.get("kind", "linear") in LINEAR_KINDS for e in self.entries)

    @property
    def scaled(self) -> bool:
        """Whether a step estimated a matrix other than the identity."""
        return bool(np.abs(self.matrix - np.eye(3)).max() > 0)

    @property
    def fitted_on(self) -> dict[str, Any]:
        return next((e["fitted_on"] for e in self.entries if e.get("fitted_on")), {})

    def fitted(self, type_: str) -> bool:
        return any(e.get("type") == type_ for e in self.entries)


def _thermal(entry: Mapping[str, Any]) -> Thermal | str:
    """The entry's polynomial as a :class:`Thermal`, or why it does not map."""
    if entry.get("scale"):
        return "the temperature model has a scale-factor part (turntable): not mapped"
    coef = np.zeros((3, 4))
    for i, ax in enumerate(entry["axes"]):
        extra = [t for t in ax["terms"] if t not in POLY_TERMS]
        if extra:
            return (
                f"the temperature model's terms {', '.join(extra)} (axis {AXES[i]}) are not a "
                "polynomial of order <= 3 in T: not mapped"
            )
        for term, c in zip(ax["terms"], ax["coefficients"], strict=True):
            coef[i, POLY_TERMS.index(term)] += float(c)
    lo, hi = entry["ranges"]["T"]
    return Thermal(float(entry["tref"]), coef, (float(lo), float(hi)))


def entry_device(entry: Mapping[str, Any]) -> dict[str, Any]:
    """The device of a chain entry: its ``device``, else derived from its ``fitted_on``."""
    if isinstance(entry.get("device"), Mapping):
        return {**device(entry.get("fitted_on"), entry["sensor"]), **entry["device"]}
    return device(entry.get("fitted_on"), entry["sensor"])


def device_models(doc: Mapping[str, Any], sensor: str) -> list[SensorModel]:
    """One composed model per device of ``sensor`` (module docstring), in the order the devices
    first appear in the chain."""
    entries = [e for e in doc.get("chain", []) if e.get("sensor") == sensor]
    devices = [entry_device(e) for e in entries]
    unnamed = [i for i, d in enumerate(devices) if device_key(d) == UNNAMED]
    groups: list[tuple[dict[str, Any], list[int]]] = []
    for i, dev in enumerate(devices):
        if i in unnamed:
            continue
        group = next((g for rep, g in groups if same_device(rep, dev)), None)
        if group is None:
            groups.append((dev, [i]))
        else:
            group.append(i)
    if not groups:
        return [_compose(sensor, entries, devices[0])] if entries else []
    return [
        _compose(sensor, [entries[i] for i in sorted(members + unnamed)], rep)
        for rep, members in groups
    ]


def single_device(
    doc: Mapping[str, Any], sensor: str, out: Export, fname: str
) -> SensorModel | None:
    """The first device's model of ``sensor``, for a file that describes one IMU (Kalibr,
    OpenVINS); the other devices are noted as left out."""
    models = device_models(doc, sensor)
    for m in models[1:]:
        out.note(
            fname,
            f"{sensor}: the file describes one IMU; the chain of device "
            f"{m.device.get('device_id', m.device.get('topic', '?'))} is left out",
        )
    return models[0] if models else None


def _compose(sensor: str, entries: list[dict[str, Any]], dev: dict[str, Any]) -> SensorModel:
    """The entries of one device's sensor composed (module docstring)."""
    m, o = np.eye(3), np.zeros(3)
    motor: np.ndarray | None = None
    source = "current"
    thermal: Thermal | None = None
    issues: list[str] = []
    for e in entries:
        kind = e.get("kind", "linear")
        if kind in LINEAR_KINDS:
            m2 = np.asarray(e["matrix"], dtype=np.float64)
            o = o + np.linalg.solve(m, np.asarray(e["offset"], dtype=np.float64))
            m = m2 @ m
            motor = None if motor is None else m2 @ motor
            if kind in MOTOR_SOURCE and np.any(e["motor"]):  # zero: no motor term fitted
                if motor is not None and MOTOR_SOURCE[kind] != source:
                    issues.append(
                        f"a {MOTOR_SOURCE[kind]}-based motor term after a {source}-based one: "
                        "the earlier one is left out"
                    )
                    motor = None
                source = MOTOR_SOURCE[kind]
                motor = np.asarray(e["motor"], dtype=np.float64) + (0.0 if motor is None else motor)
        elif kind == "temperature":
            t = _thermal(e)
            if isinstance(t, str):
                issues.append(t)
                continue
            if thermal is not None:
                issues.append("a second temperature step: not mapped")
                continue
            minv = np.linalg.inv(m)
            thermal = Thermal(t.tref, minv @ t.coefficients, t.t_range)
        else:
            issues.append(f"a '{kind}' step: not mapped")
    return SensorModel(sensor, m, o, thermal, entries, issues, dev, motor, source)


def left_alone(names: Iterable[str], families: Iterable[tuple[str, str]]) -> list[str]:
    """The parameter families (prefix, suffix) no name in ``names`` belongs to, written
    ``prefix*suffix`` (``CAL_ACC0_*SCALE``; a prefix not ending in ``_`` is a whole name):
    what a parameter file leaves as the vehicle has it."""
    names = list(names)
    return [
        f"{prefix}*{suffix}" if prefix.endswith("_") else prefix + suffix
        for prefix, suffix in families
        if not any(n.startswith(prefix) and n.endswith(suffix) for n in names)
    ]


def off_diagonal(m: np.ndarray) -> float:
    """The largest off-diagonal element of ``m`` relative to its mean absolute diagonal."""
    return float(np.abs(m - np.diag(np.diag(m))).max() / np.abs(np.diag(m)).mean())


def soft_iron(m: np.ndarray, out: Export, fname: str) -> tuple[np.ndarray, np.ndarray]:
    """(diagonal, off-diagonal X Y Z) of the symmetric part of a magnetometer matrix, the form
    both autopilots store; an asymmetric matrix is noted."""
    asym = float(np.abs(m - m.T).max() / np.abs(np.diag(m)).mean())
    if asym > RELATIVE_TOLERANCE:
        out.note(
            fname,
            f"mag: the soft-iron matrix is not symmetric (up to {asym:.2g} of its diagonal); "
            "its symmetric part is written",
        )
    sym = (m + m.T) / 2
    return np.diag(sym).copy(), np.array([sym[i, j] for i, j in OFF_DIAGONAL])


# -- Kalibr's intrinsics form --------------------------------------------------------------------


def lq(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x = L @ Q`` with L lower triangular (positive diagonal where a proper rotation allows)
    and Q a proper rotation (det +1)."""
    q1, r1 = np.linalg.qr(np.asarray(x, dtype=np.float64).T)
    lower, q = r1.T, q1.T
    signs = np.sign(np.diag(lower))
    signs[signs == 0] = 1.0
    lower, q = lower * signs, (q.T * signs).T
    if np.linalg.det(q) < 0:  # a reflection in x: keep it in L's last diagonal element
        lower[:, 2] *= -1.0
        q[2] *= -1.0
    return lower, q


@dataclass(frozen=True)
class KalibrIntrinsics:
    """Kalibr's ``scale-misalignment`` matrices (module docstring) and ``frame``, the rotation
    from imupipe's corrected IMU frame to Kalibr's (accelerometer-anchored) one."""

    m_accel: np.ndarray
    m_gyro: np.ndarray
    c_gyro_i: np.ndarray
    frame: np.ndarray


def kalibr_intrinsics(accel: np.ndarray | None, gyro: np.ndarray | None) -> KalibrIntrinsics:
    """From imupipe's accel and gyro matrices (``corrected = matrix @ (raw - offset)``; None:
    identity)."""
    a = np.eye(3) if accel is None else np.asarray(accel, dtype=np.float64)
    g = np.eye(3) if gyro is None else np.asarray(gyro, dtype=np.float64)
    m_accel, q = lq(np.linalg.inv(a))
    m_gyro, c = lq(np.linalg.inv(g) @ q.T)
    return KalibrIntrinsics(m_accel, m_gyro, c, q)


# -- serializers ---------------------------------------------------------------------------------


def plain(value: Any) -> Any:
    """numpy scalars and arrays as Python floats and lists (for the serializers)."""
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, float):
        return value + 0.0  # no -0.0
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    return value


def yaml_text(data: Mapping[str, Any], comments: Iterable[str] = (), opencv: bool = False) -> str:
    """``data`` as YAML by PyYAML's ``safe_dump`` (keys in order, matrix rows in flow style),
    after ``comments`` (fixed text written by imupipe, one ``#`` line each). ``opencv`` starts
    the file with ``%YAML:1.0``, the directive OpenCV's ``FileStorage`` requires."""
    import yaml

    class Dumper(yaml.SafeDumper):
        """Block sequences indented under their key (OpenCV's parser needs it)."""

        def increase_indent(self, flow: bool = False, indentless: bool = False) -> None:
            return super().increase_indent(flow, False)

    def text(dumper: yaml.SafeDumper, value: str) -> yaml.ScalarNode:
        """Strings with line breaks double-quoted and escaped on one line (OpenCV's parser
        takes no multi-line scalars)."""
        style = '"' if any(c in value for c in "\n\r\t") else None
        return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)

    def mapping(dumper: yaml.SafeDumper, value: dict) -> yaml.MappingNode:
        """Mappings in block style (one key a line, as Kalibr's and OpenCV's files are); only
        sequences of numbers (matrix rows, vectors) go in flow style."""
        return dumper.represent_mapping("tag:yaml.org,2002:map", value.items(), flow_style=False)

    Dumper.add_representer(str, text)
    Dumper.add_representer(dict, mapping)

    head = ["%YAML:1.0", "---"] if opencv else []
    head += [f"# {line}" for c in comments for line in c.splitlines()]
    body = yaml.dump(
        plain(dict(data)),
        Dumper=Dumper,
        sort_keys=False,
        default_flow_style=None,
        width=float("inf"),
    )
    return "\n".join(head + [body.rstrip("\n")]) + "\n"


def params_text(
    rows: Iterable[tuple[str, float | int]], comments: Iterable[str], delimiter: str
) -> str:
    """Parameter rows through the ``csv`` module (``delimiter`` tab: QGroundControl's
    ``vehicle component name value type`` rows; comma: Mission Planner's ``name,value``)."""
    buf = io.StringIO()
    for c in comments:
        buf.write(f"# {c}\n")
    writer = csv.writer(buf, delimiter=delimiter, lineterminator="\n")
    for row in rows:
        writer.writerow(row)
    return buf.getvalue()


def number(value: float) -> str:
    """A parameter value written so that it reads back as the same float."""
    return repr(float(value))
