"""Stage type -> implementing class. A new stage registers here (lazy imports keep start-up fast)."""

from __future__ import annotations

import importlib

from imupipe.stages.base import Stage

STAGE_TYPES: dict[str, str] = {
    "average": "imupipe.stages.average:AverageStage",
    "gyro_bias": "imupipe.stages.gyro_bias:GyroBiasStage",
    "allan": "imupipe.stages.allan.stage:AllanStage",
    "accel_calibration": "imupipe.stages.multiposition.accel_calibration:AccelCalibrationStage",
    "gyro_calibration": "imupipe.stages.multiposition.gyro_calibration:GyroCalibrationStage",
    "mag_calibration": "imupipe.stages.magnetometer.calibration:MagCalibrationStage",
    "mag_inflight": "imupipe.stages.magnetometer.inflight:MagInflightStage",
    "temperature": "imupipe.stages.thermal.temperature:TemperatureStage",
    "thermal_soak": "imupipe.stages.thermal.soak:ThermalSoakStage",
    "baro_temperature": "imupipe.stages.thermal.baro:BaroTemperatureStage",
}


FIRST_USE_IMPORTS: dict[str, tuple[str, ...]] = {"allan": ("imupipe.stages.special",)}
"""Stage type -> the heavy modules its stage imports on first use rather than at the top of its
module (the ``allan`` stage loads scipy only when it fits)."""


def stage_modules(type_name: str) -> list[str]:
    """The modules a stage of ``type_name`` imports to run: its own module, then those it loads
    on first use (:data:`FIRST_USE_IMPORTS`); KeyError when the type is unknown."""
    return [STAGE_TYPES[type_name].split(":")[0], *FIRST_USE_IMPORTS.get(type_name, ())]


def stage_class(type_name: str) -> type[Stage]:
    """The class of stage ``type_name`` (KeyError when unknown)."""
    module, name = STAGE_TYPES[type_name].split(":")
    return getattr(importlib.import_module(module), name)
