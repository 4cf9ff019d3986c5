"""What a conversion applies and how it reads: the calibration, the read settings, their hashes.

The two SHA-256 hashes decide whether a log already converted can be skipped
(:mod:`imupipe.pipeline.convert.done`): the chain's (what decides the corrected values) and the
read settings' (topics, time source, CSV mapping: what decides which samples are read).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from imupipe.pipeline.digests import sha256_hex
from imupipe.pipeline.errors import ConfigError
from imupipe.readers.spec import InputSpec


def chain_sha256(calibration: Mapping[str, Any]) -> str:
    """SHA-256 of the calibration chain in canonical JSON (what decides the corrected values)."""
    canonical = json.dumps(calibration.get("chain", []), sort_keys=True, separators=(",", ":"))
    return sha256_hex(canonical.encode())


def load_read_settings(path: Path | None) -> InputSpec:
    """The ``--config`` TOML: the keys of one ``[inputs.NAME]`` table except ``path``
    (``imu_topic``, ``gyro_topic``, ``accel_topic``, ``mag_topic``, ``temperature_topic``,
    ``time`` and a ``[csv]`` mapping)."""
    if path is None:  # the keys a log's reader may ask for go in a --config file
        return InputSpec(path=Path("."), keys_in="a --config TOML file (e.g. read.toml)")
    import tomllib  # with --config only: not on a command's fixed cost (issue 39)

    try:
        raw = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"--config {path}: no such file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"--config {path}: not a readable TOML file: {exc}") from None
    if "path" in raw:
        raise ConfigError(f"--config {path}: 'path' is not allowed (the logs are the arguments)")
    base = Path(path).resolve().parent
    from imupipe.pipeline.config import parse_input  # numpy, pyarrow: not for the hashes above

    spec = parse_input("convert", {**raw, "path": str(base)}, base, f"--config {path}")
    return dataclasses.replace(spec, keys_in=f"{path} (--config)")


def settings_sha256(spec: InputSpec) -> str:
    """SHA-256 of what decides how a log is read (topics, time source, CSV mapping)."""
    settings = dataclasses.asdict(spec)
    settings.pop("path"), settings.pop("name"), settings.pop("keys_in")
    for key in ("gyro_topic", "accel_topic", "fields", "read_truncated"):
        if not settings.get(key):  # unset: the hash of the settings before the key existed
            settings.pop(key, None)
    canonical = json.dumps(settings, sort_keys=True, default=str, separators=(",", ":"))
    return sha256_hex(canonical.encode())
