"""Every raw sensor instance of a log in one run: an input with ``instances = "all"`` (or a list
of topic instances) stands for each raw sensor instance of its ULog or DataFlash log.

A stage on such an input runs once per instance of the kind it works on
(:func:`stage_kind`): a barometer stage (``baro_temperature``) on every barometer
(``sensor_baro[_N]``, ``BARO[_N]``), a magnetometer stage on every magnetometer
(``sensor_mag[_N]``, ``MAG[_N]``), any other stage on every IMU (``sensor_gyro[_N]`` with its
``sensor_accel`` partner, ``IMU[_N]``), as PX4's ``Tools/process_sensor_caldata.py`` fits every
instance it finds. The instances come from the log (:func:`imupipe.readers.dispatch.
raw_instances`); a list keeps only the instances it names.

Each instance becomes an input of its own, ``<input>-<instance>`` (``board-sensor_gyro_1``): the
input's settings with the instance's topic key set and the other streams left out (``""``,
so that no step of another device meets a temperature that is not its own): an IMU:
``imu_topic`` and its own temperature; a barometer: ``temperature_topic``, which also fills the
``pressure`` column; a magnetometer: ``mag_topic`` and its own temperature where logged), and each stage becomes
``<stage>_<instance>`` on it. ``apply_to`` names the expanded input for all of its instances.
Every step records its device, so each goes to its own parameter slot.

A fit of one instance that fails its quality check does not stop the run while another instance
of the same stage is fitted: that fit is refused alone (left out of the chain, so out of
``calibration.json``'s chain, the corrected logs and the parameter files: a vehicle keeps its
own calibration of that sensor), with one warning naming it and the figure that failed and
``refused`` in its results; the others' fits stand. When every instance is refused, the run stops
on the first refusal, as a single stage does. ``accept_failed_checks`` takes a list of
instances (``["sensor_mag_1"]``) to keep those fits anyway.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from imupipe.pipeline.config import Config, StageConfig
from imupipe.pipeline.errors import ConfigError
from imupipe.readers.dispatch import raw_instances
from imupipe.readers.spec import InputSpec
from imupipe.stages.registry import stage_class

KIND_NAMES = {"imu": "IMU", "mag": "magnetometer", "baro": "barometer"}


def stage_kind(st: StageConfig) -> str:
    """The instance kind a configured stage works on: ``baro``, ``mag`` or ``imu``."""
    if st.type == "baro_temperature":
        return "baro"
    sensors = stage_class(st.type).sensors_for(st.options)
    return "mag" if "mag" in sensors else "imu"


def instance_spec(
    spec: InputSpec, name: str, kind: str, key: str, listed: dict[str, list[str]]
) -> InputSpec:
    """The input of one instance (module docstring)."""
    if kind == "imu":
        return dataclasses.replace(
            spec, name=name, imu_topic=key, temperature_topic=None, mag_topic=spec.mag_topic or ""
        )
    if kind == "baro":
        return dataclasses.replace(
            spec, name=name, imu_topic="", mag_topic="", temperature_topic=key
        )
    own = key if key in listed.get("temperature", []) else ""
    return dataclasses.replace(spec, name=name, imu_topic="", mag_topic=key, temperature_topic=own)


def expand_instances(cfg: Config) -> Config:
    """``cfg`` with every input that has ``instances`` expanded (module docstring); the
    listing reads each such log's sensor topics once. ConfigError when a stage's kind has no
    instance, or a listed instance is not in the log."""
    if not cfg.instances:
        return cfg
    listed = {name: raw_instances(cfg.inputs[name]) for name in cfg.instances}
    for name, wanted in cfg.instances.items():
        known = [k for kind in KIND_NAMES for k in listed[name][kind]]
        missing = [k for k in wanted if k not in known] if isinstance(wanted, list) else []
        if missing:
            raise ConfigError(
                f"{cfg.path}: [inputs.{name}].instances: {', '.join(missing)} not among the "
                f"log's raw sensor instances ({', '.join(known) or 'none'})"
            )
    inputs: dict[str, InputSpec] = {k: v for k, v in cfg.inputs.items() if k not in cfg.instances}
    derived: dict[str, list[str]] = {}
    stages: list[StageConfig] = []
    for st in cfg.stages:
        if st.input not in cfg.instances:
            stages.append(st)
            continue
        kind = stage_kind(st)
        wanted: Any = cfg.instances[st.input]
        keys = [k for k in listed[st.input][kind] if wanted == "all" or k in wanted]
        if not keys:
            raise ConfigError(
                f"{cfg.path}: stages[{st.index}] ({st.type}) on input '{st.input}': no raw "
                f"{KIND_NAMES[kind]} instance in the log"
                + ("" if wanted == "all" else " among its instances")
            )
        accept = st.accept_failed_checks
        unknown = [k for k in accept if k not in keys] if isinstance(accept, list) else []
        if unknown:
            raise ConfigError(
                f"{cfg.path}: stages[{st.index}].accept_failed_checks: {', '.join(unknown)} not "
                f"among the instances this stage runs on ({', '.join(keys)})"
            )
        for key in keys:
            name = f"{st.input}-{key}"
            if name not in inputs:
                inputs[name] = instance_spec(
                    cfg.inputs[st.input], name, kind, key, listed[st.input]
                )
                derived.setdefault(st.input, []).append(name)
            stages.append(
                dataclasses.replace(
                    st,
                    name=f"{st.name}_{key}",
                    input=name,
                    accept_failed_checks=key in accept if isinstance(accept, list) else accept,
                    instance_of=st.name,
                    instance=key,
                )
            )
    names = [st.name for st in stages]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(
            f"{cfg.path}: the stages expanded over instances take names given twice "
            f"({', '.join(twice)}); rename the stages"
        )
    apply_to: list[str] = []
    for name in cfg.output.apply_to:
        apply_to += derived.get(name, []) if name in cfg.instances else [name]
    output = dataclasses.replace(cfg.output, apply_to=apply_to)
    return dataclasses.replace(cfg, inputs=inputs, stages=stages, output=output, instances={})
