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
| ``px4_calibration.params`` | PX4 ``CAL_*`` and ``TC_*`` (QGroundControl's ``.params``) | an accel, gyro, mag or temperature step maps |
| ``ardupilot_calibration.param`` | ArduPilot ``INS_*``, ``COMPASS_*``, ``INS_TCAL*`` (Mission Planner's ``.param``) | the same |

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


def export_all(doc: dict[str, Any]) -> tuple[dict[str, str], dict[str, dict[str, Any]]]:
    """Every export of a calibration document: (file name -> text, file name -> report). A
    report has ``notes`` (what was left out or approximated) and facts such as the frame
    rotation of Kalibr's intrinsics; ``run`` keeps the reports in ``calibration.json`` under
    ``exports`` and prints the notes as warnings."""
    files: dict[str, str] = {}
    report: dict[str, dict[str, Any]] = {}
    for name in EXPORTERS:
        out: Export = importlib.import_module(f"imupipe.pipeline.exports.{name}").export(doc)
        files.update(out.files)
        for fname in set(out.notes) | set(out.info):
            entry = report.setdefault(fname, {})
            entry.update(out.info.get(fname, {}))
            if out.notes.get(fname):
                entry.setdefault("notes", []).extend(out.notes[fname])
    return files, report
