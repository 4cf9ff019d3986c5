"""Files other tools read, made from the calibration document (``chain`` + ``results``).

One module per consumer; each has ``export(doc) -> Export`` (file name -> text, and notes on
what did not map) and writes a file only when the stages that fill it ran:

| file | consumer | written when |
|---|---|---|
| ``imu.yaml`` | Kalibr's IMU noise model | an ``allan`` stage ran |
| ``<stage>_imu_utils.yaml`` | imu_utils' layout (``gyr_n``...) | an ``allan`` stage ran |
| ``vins_imu.yaml`` | VINS-Mono/VINS-Fusion noise block (``%YAML:1.0``, OpenCV) | an ``allan`` stage ran |
| ``kalibr_imu_intrinsics.yaml`` | Kalibr's ``scale-misalignment`` IMU model | accel or gyro scale/misalignment fitted |
| ``kalibr_imu_chain.yaml`` | OpenVINS ``imu0`` (noise + ``Tw``, ``R_IMUtoGYRO``, ``Ta``, ``R_IMUtoACC``, ``Tg``) | an ``allan`` stage ran |
| ``px4_calibration.params`` | PX4 ``CAL_*`` and ``TC_*`` (QGroundControl's ``.params``), one slot per device | an accel, gyro, mag or temperature step maps |
| ``ardupilot_calibration.param`` | ArduPilot ``INS_*``, ``COMPASS_*``, ``INS_TCAL*`` (Mission Planner's ``.param``), one slot per device | the same |

Every file is produced by a serializer (PyYAML's ``safe_dump``, the ``csv`` module): no value of
the document reaches a file by string formatting. The model mappings are in each module's
docstring and in the exports reference page.
"""

from __future__ import annotations

import importlib
from typing import Any

from imupipe.pipeline.exports.common import Export

EXPORTERS: tuple[str, ...] = ("kalibr", "imu_utils", "vins", "openvins", "px4", "ardupilot")
"""The exporter modules, in the order their files are listed."""


YAML_WRITERS: tuple[str, ...] = ("kalibr", "imu_utils", "vins", "openvins")
"""The exporters whose files are YAML (:func:`~imupipe.pipeline.exports.common.yaml_text`,
which imports PyYAML on first use)."""


DEFAULT: tuple[str, ...] = ("kalibr", "imu_utils", "vins", "openvins")
"""Written unless ``[output] exports`` says otherwise: the ROS and VIO tools' files."""


def chosen(doc: dict[str, Any], asked: list[str] | None) -> list[str]:
    """The exporters to run: ``asked`` (``[output] exports``), else :data:`DEFAULT` plus ``px4``
    when a chain step was fitted on a PX4 log (``ulog``) and ``ardupilot`` when one was fitted
    on an ArduPilot log (``dataflash``). Kalibr's noise file ``imu.yaml`` is written whenever
    an ``allan`` stage ran, whatever was asked."""
    if asked is not None:
        return [name for name in EXPORTERS if name in asked or name == "kalibr"]
    formats = {(e.get("fitted_on") or {}).get("format") for e in doc.get("chain", [])}
    autopilots = {name for name, fmt in AUTOPILOT_FORMATS.items() if fmt in formats}
    return [name for name in EXPORTERS if name in DEFAULT or name in autopilots]


AUTOPILOT_FORMATS = {"px4": "ulog", "ardupilot": "dataflash"}
"""Autopilot exporter -> the log format (``imupipe.readers.dispatch``) that makes it a default."""


PARAMETER_FILES: tuple[str, ...] = ("px4", "ardupilot")
"""The exporters of autopilot parameter files: only the estimated parameters, or (``complete``)
merged over the log's own."""


def export_all(
    doc: dict[str, Any], names: list[str] | None = None, complete: bool = False
) -> tuple[dict[str, str], dict[str, dict[str, Any]]]:
    """The exports ``names`` (default: every exporter) of a calibration document: (file name ->
    text, file name -> report). A report has ``notes`` (what was left out or approximated) and
    facts such as the frame rotation of Kalibr's intrinsics; ``run`` keeps the reports in
    ``calibration.json`` under ``exports``. ``complete``: the autopilot parameter files hold the
    log's own calibration parameters too (``[output] params = "complete"``)."""
    files: dict[str, str] = {}
    report: dict[str, dict[str, Any]] = {}
    for name in EXPORTERS if names is None else names:
        module = importlib.import_module(f"imupipe.pipeline.exports.{name}")
        extra = {"complete": complete} if name in PARAMETER_FILES else {}
        out: Export = module.export(doc, **extra)
        files.update(out.files)
        for fname in set(out.notes) | set(out.info):
            entry = report.setdefault(fname, {})
            entry.update(out.info.get(fname, {}))
            if out.notes.get(fname):
                entry.setdefault("notes", []).extend(out.notes[fname])
    return files, report
