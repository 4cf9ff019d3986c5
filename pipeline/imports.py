"""``imupipe import TOOL FILE... --out CAL.json``: a calibration made by another tool as chain
steps, so ``convert`` (or a later ``run``'s chain, with ``--into``) applies it.

| tool | files | what becomes a step (``corrected = matrix @ (raw - offset)``) |
|---|---|---|
| ``kalibr`` | Kalibr's IMU result YAML, ``model: scale-misalignment`` | accel ``matrix = M_a^-1``, gyro ``matrix = (M_g C_gyro_i)^-1``, offsets 0 |
| ``imu_tk`` | one or two ``.calib`` files (accel, then gyro) | ``matrix = T K``, ``offset = B`` |
| ``magneto`` | Magneto's printed result | ``matrix = Ainv``, ``offset = B`` |

Kalibr's model (ethz-asl/kalibr ``IccSensors.py``, ``IccScaledMisalignedImu``) is
``a_m = M_a a + b_a``, ``w_m = M_g C_gyro_i w + A a + b_g``: its biases are estimated online
and not in the file (offsets 0: add a ``gyro_bias`` stage or let the filter estimate them), and
its g-sensitivity ``A`` has no chain step (a non-zero ``A`` is reported, not applied). imu_tk's
``.calib`` (``CalibratedTriad_::save``, Tedaldi et al., ICRA 2014) holds the misalignment matrix
T, the scale matrix K (row-major, 3x3 each) and the bias B, with ``X' = T K (X - B)``. Magneto
(Merayo's ellipsoid fit, sailboatinstruments.blogspot.com) prints ``Combined bias vector B``
and ``Correction matrix Ainv``, with ``Hcalc = Ainv (H - B)``.

``--unit`` says in which unit the file's numbers are (the raw readings and the corrected output
alike, as Magneto's and imu_tk's are when fed scaled data): they are converted to SI; ``raw``
(default) keeps them for data read with ``*_unit = "raw"``. Each imported step's ``fitted_on``
is ``{"input": null, "path": FILE, "format": TOOL}``. The document is checked as ``convert``
checks it (:func:`imupipe.pipeline.calibration_file.check_calibration`) before it is written.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from imupipe.pipeline.atomic import staged_outputs
from imupipe.pipeline.calibration_file import (
    calibration_json,
    check_calibration,
    load_calibration,
)
from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.version import VERSION
from imupipe.readers.spec import ACCEL_UNITS, GYRO_UNITS, MAG_UNITS
from imupipe.stages.steps import LinearStep

UNITS = {"gyro": GYRO_UNITS, "accel": ACCEL_UNITS, "mag": MAG_UNITS}
TOOLS = ("kalibr", "imu_tk", "magneto")
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None


def _matrix(value: Any, where: str, shape: tuple[int, ...] = (3, 3)) -> np.ndarray:
    try:
        out = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        out = np.zeros(0)
    if out.shape != shape or not np.isfinite(out).all():
        raise ConfigError(f"{where}: {'x'.join(map(str, shape))} finite numbers expected")
    return out


def _invert(m: np.ndarray, where: str) -> np.ndarray:
    if abs(np.linalg.det(m)) < 1e-12 * np.abs(m).max() ** 3:
        raise ConfigError(f"{where}: singular matrix")
    return np.linalg.inv(m)


def _step(
    tool: str, sensor: str, matrix: np.ndarray, offset: np.ndarray, path: Path, **params: Any
) -> dict[str, Any]:
    entry = LinearStep(f"import_{tool}", sensor, matrix, offset, params).to_json()
    entry["fitted_on"] = {"input": None, "path": str(path), "format": tool}
    return entry


def from_kalibr(path: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """Accel and gyro steps of a Kalibr scale-misalignment IMU file (``imu0`` or the first IMU)."""
    import yaml

    try:
        doc = yaml.safe_load(_read(path).replace("%YAML:1.0", "", 1))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not readable YAML: {' '.join(str(exc).split())}") from None
    imu = doc
    if isinstance(doc, dict) and "model" not in doc:
        keys = sorted(k for k in doc if str(k).startswith("imu"))
        imu = doc[keys[0]] if keys else None
    if not isinstance(imu, dict):
        raise ConfigError(f"{path}: no Kalibr IMU block (imu0)")
    model = imu.get("model")
    if model not in ("scale-misalignment", "scale-misalignment-size-effect"):
        raise ConfigError(
            f"{path}: Kalibr model '{model}' has no IMU intrinsics to import (expected "
            "scale-misalignment)"
        )
    try:
        m_a = _matrix(imu["accelerometers"]["M"], f"{path}: accelerometers.M")
        m_g = _matrix(imu["gyroscopes"]["M"], f"{path}: gyroscopes.M")
        c = _matrix(imu["gyroscopes"]["C_gyro_i"], f"{path}: gyroscopes.C_gyro_i")
        a = _matrix(imu["gyroscopes"].get("A", np.zeros((3, 3))), f"{path}: gyroscopes.A")
    except (KeyError, TypeError):
        raise ConfigError(
            f"{path}: a scale-misalignment model needs accelerometers.M, gyroscopes.M and "
            "gyroscopes.C_gyro_i"
        ) from None
    notes = []
    if np.any(a):
        notes.append(
            f"{path}: the gyro g-sensitivity A (up to {np.abs(a).max():.3g} (rad/s)/(m/s^2)) "
            "has no chain step: not applied"
        )
    notes.append(f"{path}: Kalibr estimates biases online: the imported offsets are 0")
    steps = [
        _step("kalibr", "accel", _invert(m_a, f"{path}: accelerometers.M"), np.zeros(3), path),
        _step(
            "kalibr", "gyro", _invert(m_g @ c, f"{path}: gyroscopes.M C_gyro_i"), np.zeros(3), path
        ),
    ]
    return steps, notes


def from_imu_tk(path: Path, sensor: str) -> dict[str, Any]:
    """The step of one imu_tk ``.calib`` file: ``T`` (3x3), ``K`` (3x3), ``B`` (3)."""
    numbers = re.findall(_NUMBER, _read(path))
    if len(numbers) != 21:
        raise ConfigError(
            f"{path}: an imu_tk .calib holds 21 numbers (misalignment 3x3, scale 3x3, bias 3), "
            f"found {len(numbers)}"
        )
    v = np.asarray(numbers, dtype=np.float64)
    t, k, b = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:]
    return _step("imu_tk", sensor, t @ k, b, path, misalignment=t.tolist(), scale=k.tolist())


def from_magneto(path: Path, sensor: str) -> dict[str, Any]:
    """The step of Magneto's printed result (``Combined bias vector B``, ``Correction matrix
    Ainv``)."""
    text = _read(path)
    bias = re.search(r"bias vector B:?\s*((?:" + _NUMBER + r"\s+){3})", text + "\n")
    ainv = re.search(r"Correction matrix Ainv[^\n]*\n((?:\s*(?:" + _NUMBER + r")\s*){9})", text)
    if bias is None or ainv is None:
        raise ConfigError(
            f"{path}: no 'Combined bias vector B' and 'Correction matrix Ainv' (Magneto's output)"
        )
    b = np.asarray(re.findall(_NUMBER, bias.group(1)), dtype=np.float64)
    a = np.asarray(re.findall(_NUMBER, ainv.group(1)), dtype=np.float64).reshape(3, 3)
    return _step("magneto", sensor, a, b, path)


def import_steps(
    tool: str, files: list[Path], sensor: str | None, unit: str
) -> tuple[list[dict[str, Any]], list[str]]:
    """The chain entries (SI) of another tool's calibration files, and notes."""
    notes: list[str] = []
    if tool == "kalibr":
        if len(files) != 1:
            raise ConfigError("kalibr: give one IMU result YAML file")
        steps, notes = from_kalibr(files[0])
    elif tool == "imu_tk":
        if not 1 <= len(files) <= 2:
            raise ConfigError("imu_tk: give the accelerometer .calib, then optionally the gyro's")
        sensors = ["accel", "gyro"] if len(files) == 2 else [sensor or "accel"]
        steps = [from_imu_tk(f, s) for f, s in zip(files, sensors, strict=True)]
    else:
        if len(files) != 1:
            raise ConfigError("magneto: give one result file")
        steps = [from_magneto(files[0], sensor or "mag")]
    for entry in steps:
        table = UNITS[entry["sensor"]]
        if unit not in table:
            raise ConfigError(f"--unit {unit}: not a {entry['sensor']} unit ({', '.join(table)})")
        entry["offset"] = (np.asarray(entry["offset"]) * table[unit]).tolist()
        entry["unit"] = unit
    return steps, notes


def import_calibration(
    tool: str,
    files: list[Path],
    out: Path,
    *,
    into: Path | None = None,
    sensor: str | None = None,
    unit: str = "raw",
) -> tuple[dict[str, Any], list[str]]:
    """Write ``out``: ``into``'s document (or a new one) with the imported steps appended;
    returns (document, notes)."""
    steps, notes = import_steps(tool, [Path(f) for f in files], sensor, unit)
    if into is not None:
        doc, _ = load_calibration(into)
    else:
        doc = {"imupipe_version": VERSION, "chain": [], "results": {}}
    doc["chain"] = list(doc["chain"]) + steps
    doc.setdefault("results", {})[f"import_{tool}"] = {
        "type": "import",
        "tool": tool,
        "files": [str(f) for f in files],
        "unit": unit,
        "notes": notes,
    }
    check_calibration(doc, str(out))
    with staged_outputs() as staged:
        staged.write_text(Path(out), calibration_json(doc))
    return doc, notes


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import", help="turn another tool's calibration (Kalibr, imu_tk, Magneto) into chain steps"
    )
    p.add_argument("tool", choices=TOOLS, help="the tool that made the files")
    p.add_argument("files", type=Path, nargs="+", help="its result file(s)")
    p.add_argument("--out", type=Path, required=True, help="the calibration.json to write")
    p.add_argument("--into", type=Path, help="append to this calibration.json's chain")
    p.add_argument("--sensor", choices=("gyro", "accel", "mag"), help="one-file tools: the sensor")
    p.add_argument("--unit", default="raw", help="the unit of the file's numbers (default raw)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    _doc, notes = import_calibration(
        args.tool, args.files, args.out, into=args.into, sensor=args.sensor, unit=args.unit
    )
    for note in notes:
        print(f"imupipe: warning: {note}", file=sys.stderr)
    print(args.out)
    return 0
