"""``imupipe run CFG.toml``: read every input, run the stages in order, write the outputs.

Order: inputs are read once; each stage fits on its input as corrected by the correction stages
before it, and a correction stage's step then joins the chain. Outputs (``calibration.json``,
artifacts such as ``imu.yaml``, one corrected ``<input>.mcap`` per ``apply_to`` input,
``recording.rrd``) are staged under temporary names and renamed into ``[output] dir`` only when
everything succeeded.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

from imupipe.pipeline.atomic import OutputGuard, remove_stale_temps, staged_outputs
from imupipe.pipeline.config import Config, load_config
from imupipe.pipeline.mcap_writer import write_mcap
from imupipe.pipeline.progress import progress_bar
from imupipe.pipeline.signals import signals_deferred
from imupipe.pipeline.version import VERSION
from imupipe.readers.dispatch import carry_over, read_input
from imupipe.readers.table import SENSOR_COLUMNS, STREAM_OF_SENSOR, has_stream, sensor
from imupipe.stages.base import NullRecorder, StageContext
from imupipe.stages.registry import stage_class
from imupipe.stages.steps import Step, apply_chain


class CorrectedTables(Mapping[str, pa.Table]):
    """Every input as corrected by the chain so far, computed on first use and kept: when the
    chain grows (:meth:`extend`), a kept table gets only the new steps, never the whole chain
    again."""

    def __init__(self, raw: Mapping[str, pa.Table]) -> None:
        self._raw = raw
        self.chain: list[Step] = []
        self._kept: dict[str, tuple[pa.Table, int]] = {}  # input -> (table, steps applied)

    def extend(self, steps: list[Step]) -> None:
        self.chain.extend(steps)

    def keep_only(self, name: str | None) -> None:
        """Forget the corrected tables of every input but ``name`` (bounds memory: at most the
        inputs one stage uses are held corrected besides the raw tables)."""
        self._kept = {k: v for k, v in self._kept.items() if k == name}

    def __getitem__(self, name: str) -> pa.Table:
        table, applied = self._kept.get(name, (self._raw[name], 0))
        if applied < len(self.chain):
            table = apply_chain(table, self.chain[applied:])
            self._kept[name] = (table, len(self.chain))
        return table

    def __iter__(self) -> Iterator[str]:
        return iter(self._raw)

    def __len__(self) -> int:
        return len(self._raw)


@dataclass
class RunSummary:
    out_dir: Path
    files: list[Path]
    calibration: dict[str, Any]
    counts: dict[str, dict[str, int]] = field(default_factory=dict)


def calibration_document(chain: list[Step], results: dict[str, Any]) -> dict[str, Any]:
    """The ``calibration.json`` document (SPEC)."""
    return {
        "imupipe_version": VERSION,
        "chain": [step.to_json() for step in chain],
        "results": results,
    }


def record_sensors(recorder: Any, prefix: str, table: pa.Table, sensors: tuple[str, ...]) -> None:
    for name in sensors:
        if has_stream(table, STREAM_OF_SENSOR[name]):
            data = sensor(table, name)
            axes = tuple(c.split("_")[-1] for c in SENSOR_COLUMNS[name])
            recorder.series(f"{prefix}/{name}", data.t_ns, data.values, axes)


def output_guard(cfg: Config) -> OutputGuard:
    """The guard of ``[output] dir``, with the outputs known before the stages run checked: none
    may lie outside the folder or replace an input (the inputs, a CSV's gyro file, the config)."""
    inputs = [cfg.path, *(spec.path for spec in cfg.inputs.values())]
    inputs += [spec.csv.gyro_file for spec in cfg.inputs.values() if spec.csv.gyro_file]
    guard = OutputGuard(cfg.output.dir, inputs, "[output] dir")
    known = ["calibration.json", *(f"{name}.mcap" for name in cfg.output.apply_to)]
    for name in known + (["recording.rrd"] if cfg.output.rerun else []):
        guard.check(name)
    guard.probe()
    return guard


def run(config: Config | str | Path, *, spawn: bool = False, quiet: bool = False) -> RunSummary:
    """Run a config end to end; returns what was written."""
    cfg = config if isinstance(config, Config) else load_config(config)
    out_dir = cfg.output.dir
    guard = output_guard(cfg)
    remove_stale_temps(out_dir)
    raw: dict[str, pa.Table] = {}
    n_steps = len(cfg.inputs) + len(cfg.stages) + len(cfg.output.apply_to) + 1
    with progress_bar("imupipe run", total=n_steps, quiet=quiet) as bar:
        for name, spec in cfg.inputs.items():
            bar.describe(f"reading {name}")
            table, warnings = read_input(spec)
            for w in warnings:
                if not quiet:
                    print(f"imupipe: warning: [inputs.{name}] {w}", file=sys.stderr)
            raw[name] = table
            bar.advance()

        tables = CorrectedTables(raw)
        results: dict[str, Any] = {}
        with staged_outputs(guard) as out:
            files: list[Path] = []
            recorder: Any = NullRecorder()
            if cfg.output.rerun:
                from imupipe.pipeline.recording import Recorder

                rrd = out_dir / "recording.rrd"
                with signals_deferred():  # never a half-made recording stream
                    recorder = Recorder(
                        out.path(rrd), spawn=spawn, max_points=cfg.output.rerun_max_points
                    )
                files.append(rrd)
            for st in cfg.stages:
                bar.describe(f"stage {st.name}")
                stage = stage_class(st.type)(st.options)
                tables.keep_only(st.input)
                table = tables[st.input]
                ctx = StageContext(
                    name=st.name,
                    input_name=st.input,
                    recorder=recorder,
                    tables=tables,
                    quiet=quiet,
                    accept_failed_checks=st.accept_failed_checks,
                )
                sensors = stage.sensors_for(st.options)
                record_sensors(recorder, f"/{st.name}/input", table, sensors)
                output = stage.fit(table, ctx)
                if output.steps:
                    tables.extend(output.steps)
                    record_sensors(recorder, f"/{st.name}/output", tables[st.input], sensors)
                recorder.ensure_stage(st.name)
                results[st.name] = {
                    "type": st.type,
                    "input": st.input,
                    **output.results,
                    "warnings": ctx.warnings,
                }
                if ctx.failed_checks:
                    results[st.name]["failed_checks"] = ctx.failed_checks
                for fname, text in output.artifacts.items():
                    out.write_text(out_dir / fname, text)
                    files.append(out_dir / fname)
                bar.advance()

            doc = calibration_document(tables.chain, results)
            out.write_text(out_dir / "calibration.json", json.dumps(doc, indent=2) + "\n")
            files.append(out_dir / "calibration.json")
            counts: dict[str, dict[str, int]] = {}
            for name in cfg.output.apply_to:
                bar.describe(f"writing {name}.mcap")
                tables.keep_only(name)
                corrected = tables[name]
                target = out_dir / f"{name}.mcap"
                counts[name] = write_mcap(
                    out.path(target),
                    corrected,
                    calibration=doc,
                    carry_over=carry_over(cfg.inputs[name]),
                )
                files.append(target)
                bar.advance()
            recorder.close()
            bar.advance()
    return RunSummary(out_dir=out_dir, files=files, calibration=doc, counts=counts)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="calibrate: read the inputs, run the stages, write the outputs")
    p.add_argument("config", type=Path, help="the TOML config file")
    p.add_argument(
        "--spawn", action="store_true", help="also stream the recording to a Rerun viewer"
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or warnings on stderr")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    summary = run(args.config, spawn=args.spawn, quiet=args.quiet)
    if not args.quiet:
        for path in summary.files:
            print(path)
    return 0
