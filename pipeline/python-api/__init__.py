"""imupipe: raw IMU logs into calibrated data, from Python.

::

    import imupipe

    table = imupipe.read("static.mcap")              # the common table (pyarrow), SI units
    imupipe.inspect("static.mcap")                   # what the log holds
    noise = imupipe.allan(table)                     # one function per stage type
    bias = imupipe.gyro_bias(table, interval=[0, 60])
    cal = imupipe.Calibration.from_results(bias)     # a correction chain
    cal.save("calibration.json"); imupipe.Calibration.load("calibration.json").apply(table)
    imupipe.run("cfg.toml")                          # imupipe run, from a file or a dict
    imupipe.convert(["fleet/"], "calibration.json", "out/")

The public names are those of ``__all__``; the subpackages ``imupipe.readers`` (formats),
``imupipe.stages`` (math) and ``imupipe.pipeline`` (order, outputs, command line) are the
implementation. This package lives in the folder ``pipeline/python-api/`` (mapped to
``imupipe`` by ``[tool.setuptools.package-dir]``; a folder name with a hyphen cannot be imported
as ``imupipe.pipeline.<name>``, so no module has two names): see DEVELOPERS.md.

**Start-up.** ``import imupipe`` loads nothing heavy: each public name is imported on first use
(PEP 562 ``__getattr__``), so the command line, which imports ``imupipe.pipeline.cli`` through
this package, still starts in a few tens of milliseconds.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if __name__ != "imupipe":  # the folder reached by another name (importlib, a source tree)
    raise ImportError(f"{__name__}: this folder is the package 'imupipe'; import imupipe")

if TYPE_CHECKING:  # what editors and type checkers see; loaded lazily at run time (below)
    from imupipe._api import (
        Calibration,
        ConvertSummary,
        ImupipeError,
        ImupipeWarning,
        Inspection,
        RunResult,
        StageResult,
        convert,
        inspect,
        read,
        run,
    )
    from imupipe._stages import (
        accel_calibration,
        allan,
        average,
        baro_temperature,
        gyro_bias,
        gyro_calibration,
        mag_calibration,
        mag_inflight,
        temperature,
        thermal_soak,
    )

__all__ = [
    "read",
    "inspect",
    "run",
    "convert",
    "Calibration",
    "StageResult",
    "RunResult",
    "Inspection",
    "ConvertSummary",
    "ImupipeError",
    "ImupipeWarning",
    "average",
    "gyro_bias",
    "allan",
    "accel_calibration",
    "gyro_calibration",
    "mag_calibration",
    "mag_inflight",
    "temperature",
    "thermal_soak",
    "baro_temperature",
    "__version__",
]

STAGES = (
    "average",
    "gyro_bias",
    "allan",
    "accel_calibration",
    "gyro_calibration",
    "mag_calibration",
    "mag_inflight",
    "temperature",
    "thermal_soak",
    "baro_temperature",
)
"""The stage functions (:mod:`imupipe._stages`), one per type of
:data:`imupipe.stages.registry.STAGE_TYPES` (a test checks they are the same); the other public
names come from :mod:`imupipe._api`."""

_HOME = {name: "imupipe._stages" if name in STAGES else "imupipe._api" for name in __all__}


def __getattr__(name: str) -> Any:
    """A public name, its module imported on first use (PEP 562)."""
    if name == "__version__":  # the installed distribution's, read only when asked
        from imupipe.pipeline.version import VERSION

        return VERSION
    module = _HOME.get(name)
    if module is None:
        raise AttributeError(f"module 'imupipe' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    if callable(value) and not isinstance(value, type):  # a misspelt keyword: the allowed
        from imupipe._api import keywords_checked  # list, as the config says

        value = keywords_checked(value)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public names (``__all__``), not this module's own imports and helpers."""
    return sorted(__all__)
