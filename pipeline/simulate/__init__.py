"""``imupipe simulate SCENARIO --out FILE``: synthetic logs with a known truth.

Each scenario module exposes ``DEFAULTS`` (parameter -> default value, SI units) and
``simulate(params, rng) -> (table, truth)``. The log is written by the file's suffix (``.csv``,
``.mcap``, ``.bag``, ``.db3`` or a folder for a ROS 2 bag) and the truth as ``<FILE>.truth.json``.
The ``flight`` scenario (a compass with attitude, GPS and current) is written as DataFlash
(``.bin``) or as a PX4 ULog (``.ulg``). A scenario of several devices (``board``: a PX4 flight controller's IMUs and barometer) returns
a :class:`~imupipe.pipeline.writers.ulog.UlogData` instead of a table and names the suffixes it
is written in (``WRITES``: ``.ulg``); the ``fleet`` scenario returns many logs and is written as a
folder of MCAP logs.
Parameters are set with ``--set key=value`` (values parsed as JSON, e.g. ``--set gyro_N=[1e-4,1e-4,2e-4]``).
"""

from __future__ import annotations

import argparse
import importlib
import json
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pyarrow as pa

from imupipe.pipeline.atomic import staged_outputs
from imupipe.pipeline.errors import ConfigError

SCENARIOS: dict[str, str] = {
    "static": "imupipe.pipeline.simulate.static",
    "camera": "imupipe.pipeline.simulate.camera",
    "poses": "imupipe.pipeline.simulate.poses",
    "mag": "imupipe.pipeline.simulate.mag",
    "thermal": "imupipe.pipeline.simulate.thermal",
    "thermal_soak": "imupipe.pipeline.simulate.thermal_soak",
    "board": "imupipe.pipeline.simulate.board",
    "flight": "imupipe.pipeline.simulate.flight",
    "fleet": "imupipe.pipeline.simulate.fleet",
}

WRITERS: dict[str, str] = {
    ".csv": "imupipe.pipeline.writers.csv:write_csv",
    ".mcap": "imupipe.pipeline.writers.mcap:write_mcap",
    ".bag": "imupipe.pipeline.writers.bag:write_ros1_bag",
    ".db3": "imupipe.pipeline.writers.bag:write_ros2_bag",
    "": "imupipe.pipeline.writers.bag:write_ros2_bag",
    ".ulg": "imupipe.pipeline.writers.ulog:write_ulog",
    ".bin": "imupipe.pipeline.writers.dataflash:write_dataflash",
}
"""Suffix -> "module:function(path, table)"; no suffix means a ROS 2 bag folder."""


def scenario_module(name: str) -> ModuleType:
    if name not in SCENARIOS:
        raise ConfigError(f"unknown scenario '{name}' (known: {', '.join(SCENARIOS)})")
    return importlib.import_module(SCENARIOS[name])


def resolve_params(module: ModuleType, overrides: dict[str, Any]) -> dict[str, Any]:
    params = dict(module.DEFAULTS)
    for key, value in overrides.items():
        if key not in params:
            raise ConfigError(f"--set {key}: unknown parameter (known: {', '.join(params)})")
        params[key] = value
    return params


def simulate(
    name: str, overrides: dict[str, Any] | None = None, seed: int = 0
) -> tuple[pa.Table, dict[str, Any]]:
    """Run scenario ``name``; returns (table, truth). The truth names the scenario and its params."""
    module = scenario_module(name)
    params = resolve_params(module, overrides or {})
    table, truth = module.simulate(params, np.random.default_rng(seed))
    return table, {"scenario": name, "seed": seed, "params": params, **truth}


def write_log(path: Path, table: Any) -> None:
    """Write ``table`` (a scenario's log: a table, or a board's ``UlogData``) to ``path`` in the
    format its suffix names (atomically)."""
    from imupipe.pipeline.simulate.fleet import FleetLogs
    from imupipe.pipeline.writers.ulog import UlogData

    suffix = path.suffix.lower()
    if isinstance(table, FleetLogs):
        if suffix:
            raise ConfigError(f"{path}: a fleet is written as a folder of logs (give no suffix)")
        table.write(path)
        return
    board = isinstance(table, UlogData)
    if not board and suffix == ".ulg" and "attitude_w" in table.column_names:
        from imupipe.pipeline.simulate.flight import flight_ulog  # the flight scenario

        table, board = flight_ulog(table), True
    if suffix not in WRITERS or board != (suffix == ".ulg"):
        known = (
            ".ulg" if board else ", ".join(s for s in WRITERS if s and s not in (".ulg", ".bin"))
        )
        raise ConfigError(f"{path}: unknown output format '{suffix}' for this log (use {known})")
    if not board:
        from imupipe.readers.table import FLIGHT_COLUMNS, has_flight_stream, has_stream, metadata

        flight = any(has_flight_stream(table, s) for s in FLIGHT_COLUMNS)
        if suffix == ".bin" and ((metadata(table).get("px4") or {}).get("parameters")):
            raise ConfigError(
                f"{path}: 'px4_parameters' describe a PX4 vehicle (its compass in its own axes): "
                "write it as .ulg"
            )
        if flight != (suffix == ".bin") or (suffix == ".bin" and not has_stream(table, "mag")):
            use = (
                ".bin"
                if flight
                else ", ".join(s for s in WRITERS if s and s not in (".ulg", ".bin"))
            )
            raise ConfigError(f"{path}: unknown output format '{suffix}' for this log (use {use})")
    module, fn = WRITERS[suffix].split(":")
    writer = getattr(importlib.import_module(module), fn)
    with staged_outputs() as out:
        writer(out.path(path) if suffix in (".csv", ".mcap", ".ulg", ".bin") else path, table)


def _parse_set(items: list[str]) -> dict[str, Any]:
    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item}: expected key=value")
        try:
            overrides[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key.strip()] = value
    return overrides


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write a synthetic log with a known truth")
    p.add_argument("scenario", help=f"one of: {', '.join(SCENARIOS)}")
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="output log (.csv, .mcap, .bag, .db3, folder; board: .ulg; fleet: a folder)",
    )
    p.add_argument("--rate", type=float, help="sample rate, Hz")
    p.add_argument("--duration", type=float, help="duration, s")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a scenario parameter (JSON value); repeatable",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from imupipe.pipeline.progress import progress_bar

    overrides = _parse_set(args.set)
    if args.rate is not None:
        overrides["rate_hz"] = args.rate
    if args.duration is not None:
        overrides["duration_s"] = args.duration
    with progress_bar(f"simulating {args.scenario}", None, quiet=args.quiet) as bar:
        scenario_module(args.scenario)  # an unknown scenario: its error before any wait
        table, truth = simulate(args.scenario, overrides, args.seed)
        rows = getattr(table, "num_rows", None)  # a board or a fleet: no one table
        bar.phase(f"writing {args.out.name}", rows, "rows" if rows else "")
        with bar.listen():  # the MCAP and bag writers tell how far they are
            write_log(args.out, table)
    truth_path = args.out.with_name(args.out.name + ".truth.json")
    with staged_outputs() as out:
        out.write_text(truth_path, json.dumps(truth, indent=2) + "\n")
    print(args.out)
    return 0
