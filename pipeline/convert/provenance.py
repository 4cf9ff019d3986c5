"""Does a log come from the sensor a calibration was fitted on?

``imupipe run`` records in each chain entry where its step was fitted::

    "fitted_on": {"input": ..., "path": ..., "format": ..., "topics": {stream: topic},
                  "frame_id": {stream: frame}, "instance": {stream: id},
                  "t_start_ns": ..., "t_end_ns": ..., "rate_hz": {stream: Hz}}

``convert`` compares ``topics``, ``frame_id``, ``instance`` and ``device_id`` with the log's own (the common
table's metadata), stream by stream, wherever both sides name one: a calibration fitted on one
robot's IMU should not be applied silently to another's. What a mismatch does is the user's
choice (``--on-mismatch warn|refuse``); either way the manifest records it. A calibration
without ``fitted_on`` (written before it was recorded) cannot be checked: the logs are converted
and the manifest says ``unknown``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from imupipe.pipeline.calibration_file import UNNAMED, device, device_key, same_device
from imupipe.pipeline.errors import ImupipeError

COMPARED = ("topics", "frame_id", "instance", "device_id")
"""The ``fitted_on`` keys compared with the log (each maps stream -> value; ``instance`` and
``device_id`` come from logs that have them, e.g. PX4 ULog)."""


class ProvenanceMismatch(ImupipeError):
    """The log does not come from the sensor the calibration was fitted on (``--on-mismatch
    refuse``)."""


def fitted_on(chain: Sequence[Mapping[str, Any]]) -> list[tuple[int, Mapping[str, Any]]]:
    """(index, fitted_on) of every chain entry that records where it was fitted."""
    return [
        (i, entry["fitted_on"])
        for i, entry in enumerate(chain)
        if isinstance(entry, Mapping) and isinstance(entry.get("fitted_on"), Mapping)
    ]


def mismatches(chain: Sequence[Mapping[str, Any]], log_meta: Mapping[str, Any]) -> list[str]:
    """One line per difference between the chain's ``fitted_on`` records and a log's metadata
    (``topics``, ``frame_id``, ``instance``: stream -> value), where both sides name a value.
    A chain of several devices of a sensor (two PX4 IMUs) is compared only by the entries of the
    log's device: the others are not applied to it
    (:class:`~imupipe.pipeline.calibration_file.OnDevice`)."""
    found = []
    named: dict[str, list[dict[str, Any]]] = {}  # sensor -> the devices its entries name
    for i, where in fitted_on(chain):
        sensor = chain[i]["sensor"]
        dev = device(where, sensor)
        named.setdefault(sensor, [])
        if device_key(dev) != UNNAMED:
            named[sensor].append(dev)
    devices = {s: {device_key(d) for d in devs} for s, devs in named.items()}
    for sensor, keys in sorted(devices.items()):
        ours = device(log_meta, sensor)
        mine = device_key(ours)
        if (
            len(keys) > 1
            and mine != UNNAMED
            and not any(same_device(d, ours) for d in named[sensor])
        ):
            listed = ", ".join(f"{k} {v!r}" for k, v in sorted(keys, key=str))
            found.append(
                f"the calibration's {sensor} steps are for {len(keys)} devices ({listed}); "
                f"this log's {sensor} ({mine[0]} {mine[1]!r}) is none of "
                "them: none of their steps is applied"
            )
    for i, where in fitted_on(chain):
        sensor = chain[i]["sensor"]
        if len(devices[sensor]) > 1 and not same_device(
            device(where, sensor), device(log_meta, sensor)
        ):
            continue  # another device's step: not applied to this log
        for key in COMPARED:
            ours, theirs = where.get(key), log_meta.get(key)
            if not isinstance(ours, Mapping) or not isinstance(theirs, Mapping):
                continue
            for stream in sorted(set(ours) & set(theirs)):
                if (
                    ours[stream] is not None
                    and theirs[stream] is not None
                    and str(ours[stream]) != str(theirs[stream])
                ):
                    step = chain[i].get("type", chain[i].get("kind", "step"))
                    found.append(
                        f"chain[{i}] ({step}) was fitted on {key} {ours[stream]!r} for {stream}, "
                        f"this log has {theirs[stream]!r}"
                    )
    return found


class ProvenanceCheck:
    """Accumulates the mismatches of one log's batches; :attr:`status` is what the manifest
    records: ``match``, ``mismatch: ...`` or ``unknown`` (the calibration records no
    ``fitted_on``)."""

    def __init__(self, chain: Sequence[Mapping[str, Any]], on_mismatch: str, where: str) -> None:
        self.chain, self.on_mismatch, self.where = chain, on_mismatch, where
        self.known = bool(fitted_on(chain))
        self.found: list[str] = []

    def check(self, log_meta: Mapping[str, Any]) -> list[str]:
        """Compare one batch's metadata; returns the new mismatches (raises
        :class:`ProvenanceMismatch` with ``refuse``)."""
        if not self.known:
            return []
        new = [m for m in mismatches(self.chain, log_meta) if m not in self.found]
        self.found += new
        if new and self.on_mismatch == "refuse":
            raise ProvenanceMismatch(
                f"{self.where}: not the sensor of the calibration: {new[0]} "
                "(--on-mismatch warn converts it anyway)"
            )
        return new

    @property
    def status(self) -> str:
        if not self.known:
            return "unknown"
        return "match" if not self.found else "mismatch: " + "; ".join(self.found)
