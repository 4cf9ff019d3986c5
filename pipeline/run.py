"""``imupipe run CFG.toml``: read every input, run the stages in order, write the outputs.

Order: inputs are read once; each stage fits on its input as corrected by the correction stages
before it, and a correction stage's step then joins the chain. Outputs (``calibration.json``,
with where each step was fitted; each stage's artifacts; the files other tools read, made from
the calibration by :mod:`imupipe.pipeline.exports` such as ``imu.yaml``; one corrected
``<input>.mcap`` per ``apply_to`` input; ``recording.rrd``) are staged under temporary names and
renamed into ``[output] dir`` only when everything succeeded.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

from imupipe.pipeline.atomic import OutputGuard, remove_stale_temps, staged_outputs
from imupipe.pipeline.calibration_file import applying, calibration_json, fitted_on, on_device
from imupipe.pipeline.config import Config, load_config
from imupipe.pipeline.exports import YAML_WRITERS, export_all
from imupipe.pipeline.exports import chosen as chosen_exports
from imupipe.pipeline.instances import expand_instances
from imupipe.pipeline.notices import Notice, Notices
from imupipe.pipeline.progress import progress_bar, size_of
from imupipe.pipeline.report.summary import (
    StageSummary,
    raw_count_sensors,
    run_markdown,
    stage_markdown,
    summarise,
)
from imupipe.pipeline.signals import signals_deferred
from imupipe.pipeline.version import VERSION
from imupipe.pipeline.warm_imports import WarmImports
from imupipe.readers.arrays import to_numpy
from imupipe.readers.dispatch import detect_format, read_input, reader_for
from imupipe.readers.table_buffer import small_pages
from imupipe.stages.base import StageContext, StageOutput
from imupipe.stages.registry import stage_class, stage_modules
from imupipe.stages.steps import Step, apply_chain


class CorrectedTables(Mapping[str, pa.Table]):
    """Every input as corrected by the chain so far, computed on first use and kept: when the
    chain grows (:meth:`extend`), a kept table gets only the new steps, never the whole chain
    again. An input not in ``raw`` is read with ``read(name)`` when a stage first asks for it."""

    def __init__(
        self, raw: dict[str, pa.Table], names: list[str], read: Callable[[str], pa.Table]
    ) -> None:
        self._raw = raw
        self._names = names
        self._read = read
        self.chain: list[Step] = []
        self._kept: dict[str, tuple[pa.Table, int]] = {}  # input -> (table, steps applied)

    def extend(self, steps: list[Step]) -> None:
        self.chain.extend(steps)

    def keep_only(self, name: str | None) -> None:
        """Forget the corrected tables of every input but ``name`` (bounds memory: at most the
        inputs one stage uses are held corrected besides the raw tables)."""
        self._kept = {k: v for k, v in self._kept.items() if k == name}

    def release(self) -> None:
        """Forget every table (the stages are done; the outputs are streamed from the logs)."""
        self._raw.clear()
        self._kept.clear()

    def __getitem__(self, name: str) -> pa.Table:
        if name not in self._names:
            raise KeyError(name)
        if name not in self._raw:
            self._raw[name] = self._read(name)
        table, applied = self._kept.get(name, (self._raw[name], 0))
        if applied < len(self.chain):
            table = apply_chain(table, self.chain[applied:])
            self._kept[name] = (table, len(self.chain))
        return table

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


@dataclass
class RunSummary:
    out_dir: Path
    files: list[Path]
    calibration: dict[str, Any]
    counts: dict[str, dict[str, int]] = field(default_factory=dict)
    summaries: list[StageSummary] = field(default_factory=list)
    notices: list[Notice] = field(default_factory=list)


def first_sample(tables: Iterable[pa.Table]) -> int | None:
    """The earliest ``t_ns`` of ``tables`` (the start of the recording; None: no rows)."""
    firsts = [int(to_numpy(t.column("t_ns")).min()) for t in tables if t.num_rows]
    return min(firsts, default=None)


def calibration_document(
    chain: list[Step], results: dict[str, Any], fitted: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    """The ``calibration.json`` document; ``fitted`` gives each chain entry's ``fitted_on``
    (:func:`imupipe.pipeline.calibration_file.fitted_on`)."""
    entries = [step.to_json() for step in chain]
    for entry, where in zip(entries, fitted or [], strict=False):
        entry["fitted_on"] = where
    return {"imupipe_version": VERSION, "chain": entries, "results": results}


def publish(
    summaries: Sequence[StageSummary],
    recorder: Any,
    cfg: Any,
    out: Any,
    notes: Sequence[Notice] = (),
) -> list[Any]:
    """The summary into the recording (a document per stage, and the Summary tab) and, with
    ``[output] report``, into ``report.html`` (staged in ``out``); returns the files written.
    ``notes``: the warnings and notes of no stage (the exports'), listed after the stages'."""
    for s in summaries:
        recorder.document(s.name, stage_markdown(s))
    recorder.document(None, run_markdown(summaries, f"imupipe run {cfg.path.name}", notes))
    if not cfg.output.report:
        return []
    from imupipe.pipeline.report.page import write_report  # imported only when a report is written

    target = cfg.output.dir / "report.html"
    write_report(out.path(target), summaries, recorder.figures, cfg, notes)
    return [target]


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


def warm_modules(cfg: Config) -> list[str]:
    """What a run imports after reading its inputs, imported while it reads them
    (:mod:`imupipe.pipeline.warm_imports`): each stage's modules, the recorder's (with Rerun:
    imported also when nothing is recorded), the report's and the exporters' asked for (else the
    default ones: PX4's, added for a ULog, loads when needed), and PyYAML when one of them
    writes YAML."""
    modules: list[str] = []
    for st in cfg.stages:
        modules += [m for m in stage_modules(st.type) if m not in modules]
    modules.append("imupipe.pipeline.report.recording")
    if cfg.output.report:
        modules.append("imupipe.pipeline.report.page")
    exporters = chosen_exports({}, cfg.output.exports)  # the chain is not known yet
    modules += [f"imupipe.pipeline.exports.{n}" for n in exporters]
    if any(n in YAML_WRITERS for n in exporters):  # PyYAML: 17-40 ms at the end of the run
        modules.append("yaml")
    return modules


ONE_THREAD_CSV_BYTES = 150_000_000
"""Below this many bytes of CSV inputs, a run whose Rerun import is still to come parses them
leaving a core to that import (:func:`parse_threads`)."""


def parse_threads(cfg: Config, used: Sequence[str]) -> int | None:
    """pyarrow's thread count for reading the inputs ``used`` while Rerun imports on the warm
    thread (:mod:`imupipe.pipeline.warm_imports`); None: pyarrow's own (one per core).

    One thread fewer than pyarrow's own (one on two cores) when every input is a CSV, of under
    :data:`ONE_THREAD_CSV_BYTES` together, and Rerun is not yet imported. The import (0.45-0.5 s
    of CPU, all of it holding the GIL) is what the run waits for after reading a small CSV;
    with the parse's two threads beside it on two cores it got two thirds of a core. Parsed on
    one thread, the 30-min, 103 MB CSV of issue 39's benchmark left the whole run 0.87x-0.94x
    the wall time and 0.97x-0.99x the CPU (8 and 10 alternated pairs, load 1.2 to 1.7);
    206 MB: 0.98x and 0.96x (6 pairs); 412 MB: 1.07x the wall time (4 pairs), so larger files
    keep every thread. The same values are parsed either way."""
    cores = pa.cpu_count()
    if cores < 2 or "rerun" in sys.modules or not used:
        return None
    paths = [Path(cfg.inputs[name].path) for name in used]
    if any(detect_format(p) != "csv" for p in paths):
        return None
    return cores - 1 if sum(size_of(p) for p in paths) < ONE_THREAD_CSV_BYTES else None


@contextmanager
def pyarrow_threads(count: int | None) -> Iterator[None]:
    """pyarrow's CPU thread pool at ``count`` threads inside the block (None: unchanged)."""
    if count is None:
        yield
        return
    before = pa.cpu_count()
    pa.set_cpu_count(count)
    try:
        yield
    finally:
        pa.set_cpu_count(before)


def instance_groups(cfg: Config) -> dict[str, list[str]]:
    """Configured stage -> the stages expanded from it over two or more instances of its
    input's log (:mod:`imupipe.pipeline.instances`): a fit of one of them that fails its quality
    check is refused alone (:func:`refused_line`)."""
    groups: dict[str, list[str]] = {}
    for st in cfg.stages:
        if st.instance_of is not None:
            groups.setdefault(st.instance_of, []).append(st.name)
    return {k: v for k, v in groups.items() if len(v) > 1}


def refused_line(instance: str, refused: list[str]) -> str:
    """The warning of a fit of one instance refused by its quality check (``refused``: the
    failed checks, the first named): left out of the chain and so of every file made from it."""
    more = f" (and {len(refused) - 1} more failed checks)" if len(refused) > 1 else ""
    return (
        f"{instance} refused: {refused[0]}{more}; its fit is left out of the chain and the "
        f"parameter files (the vehicle keeps its own calibration of {instance}); "
        f'accept_failed_checks = ["{instance}"] in this stage to use it anyway'
    )


def run(
    config: Config | str | Path,
    *,
    spawn: bool = False,
    quiet: bool = False,
    one_shot: bool = False,
) -> RunSummary:
    """Run a config end to end; returns what was written. ``one_shot``: the process ends with
    the run (the command line): the modules imported are frozen for the garbage collector
    (:class:`~imupipe.pipeline.warm_imports.WarmImports`)."""
    cfg = expand_instances(config if isinstance(config, Config) else load_config(config))
    out_dir = cfg.output.dir
    guard = output_guard(cfg)
    remove_stale_temps(out_dir)
    raw: dict[str, pa.Table] = {}
    used = [name for name in cfg.inputs if any(st.input == name for st in cfg.stages)]
    notices = Notices()  # every warning and note, wherever raised: one record (notices.py)
    read_warnings: dict[str, list[str]] = {}  # input -> its reader's warnings
    running: list[str] = []  # the stage running (an input read inside it is its own)

    def read(name: str) -> pa.Table:
        table, warnings = read_input(cfg.inputs[name])
        read_warnings[name] = list(warnings)
        for w in warnings:
            if running:
                notices.add("warning", running[0], f"inputs.{name}", w)
            if not quiet:
                print(f"imupipe: warning: [inputs.{name}] {w}", file=sys.stderr)
        return table

    with progress_bar("imupipe run", total=None, quiet=quiet) as bar:
        for name in used:  # the readers' modules, before a second thread imports alongside
            reader_for(cfg.inputs[name])
        threads = parse_threads(cfg, used)
        with WarmImports(warm_modules(cfg), freeze=one_shot), pyarrow_threads(threads):
            for name in used:  # inputs only written (apply_to) are never held: streamed below
                path = Path(cfg.inputs[name].path)
                size = size_of(path) or None
                bar.phase(f"reading {name} ({path.name})", size, "bytes", when_reported=True)
                with bar.listen():  # the chunked readers tell how far through the file
                    raw[name] = read(name)
        bar.phase("imupipe run", len(cfg.stages))

        tables = CorrectedTables(raw, list(cfg.inputs), read)
        results: dict[str, Any] = {}
        groups = instance_groups(cfg)
        refusals: dict[str, StageContext] = {}  # stage -> its refused fit's context
        fitted: list[dict[str, Any]] = []  # fitted_on of each chain entry
        owners: list[tuple[str, Step]] = []  # (stage, step): a step's warnings are its stage's

        def sweep_steps() -> None:
            """The steps' own warnings (raised when a step corrects a log) to their stages."""
            for owner, step in owners:
                for w in getattr(step, "warnings", None) or []:
                    notices.add("warning", owner, "step", w)

        with staged_outputs(guard) as out:
            from imupipe.pipeline.report.recording import open_recorder  # rerun: loaded when run

            with signals_deferred():  # never a half-made recording stream
                recorder, files = open_recorder(cfg, out, spawn=spawn, quiet=quiet)
            recorder.start_at(first_sample(raw.values()))  # its time line: time since then
            for st in cfg.stages:
                bar.describe(f"stage {st.name}")
                running[:] = [st.name]
                for w in read_warnings.get(st.input, []):
                    notices.add("warning", st.name, f"inputs.{st.input}", w)
                stage = stage_class(st.type)(st.options)
                tables.keep_only(st.input)
                table = tables[st.input]
                ctx = StageContext(
                    name=st.name,
                    input_name=st.input,
                    recorder=recorder,
                    tables=tables,
                    quiet=quiet,
                    accept_failed_checks=bool(st.accept_failed_checks),
                    refuse_alone=(st.instance_of or "") in groups,
                )
                sensors = stage.sensors_for(st.options)
                mine = applying(tables.chain, table)  # the steps of this input's devices
                recorder.sensors(st.name, table, sensors, input_name=st.input, chain=mine)
                output = stage.fit(table, ctx)
                if ctx.refused:  # one instance's fit refused: the others' stand
                    refusals[st.name] = ctx
                    group = groups[st.instance_of or ""]
                    if all(n in refusals for n in group):  # every one: stop, as one stage does
                        raise refusals[group[0]].refusal()
                    ctx.warn(refused_line(st.instance or st.name, ctx.refused))
                    output = StageOutput(results={**output.results, "refused": ctx.refused})
                for w in ctx.warnings:
                    notices.add("warning", st.name, "stage", w)
                owners.extend((st.name, step) for step in output.steps)
                sweep_steps()
                where = fitted_on(st.input, cfg.inputs[st.input], table)
                if output.steps:  # each applies to its own device's data only
                    tables.extend(on_device(output.steps, [where] * len(output.steps)))
                    fitted.extend([where] * len(output.steps))
                    fixed = [n for n in sensors if any(s.sensor == n for s in output.steps)]
                    recorder.sensors(
                        st.name,
                        tables[st.input],
                        fixed,
                        input_name=st.input,
                        corrected=True,
                        counts=output.counts,
                    )
                recorder.ensure_stage(st.name)
                results[st.name] = {
                    "type": st.type,
                    "input": st.input,
                    **output.results,
                    "warnings": ctx.warnings,
                    "fitted_on": where,
                }
                if ctx.failed_checks:
                    results[st.name]["failed_checks"] = ctx.failed_checks
                for fname, text in output.artifacts.items():
                    out.write_text(out_dir / fname, text)
                    files.append(out_dir / fname)
                bar.advance()

            running.clear()
            doc = calibration_document(tables.chain, results, fitted)
            # staged (its place in the commit order: before the corrected logs) now, written
            # once correcting them has added its warnings
            calibration = out.path(out_dir / "calibration.json")
            corrected: list[Path] = []  # listed after the other files, as before
            counts: dict[str, dict[str, int]] = {}
            tables.release()
            if cfg.output.apply_to:  # the MCAP writer: imported only when something is written
                from imupipe.pipeline.writers.corrected import write_corrected
            for name in cfg.output.apply_to:  # first: correcting a log may warn (extrapolation)
                target = out_dir / f"{name}.mcap"
                size = size_of(Path(cfg.inputs[name].path))
                text = f"writing {target.name} (reading {name})"
                bar.phase(text, size or None, "bytes", when_reported=True)
                with bar.listen():  # the log is streamed: its reader tells how far
                    counts[name] = write_corrected(
                        out.path(target), cfg.inputs[name], tables.chain, doc
                    )
                corrected.append(target)
            bar.phase("imupipe run: report and recording", None)
            exported, report = export_all(
                doc,
                chosen_exports(doc, cfg.output.exports),
                complete=cfg.output.params == "complete",
            )
            if report:  # what each tool's file leaves out: in the document, and one line
                doc["exports"] = report
            noted = [name for name, rep in report.items() if rep.get("notes")]
            if noted:
                line = exports_note(noted)
                if not quiet:
                    print(line, file=sys.stderr)
                details = "; ".join(f"{n}: {'; '.join(report[n]['notes'])}" for n in noted)
                notices.add("note", None, "exports", f"{line.split('] ', 1)[1]} ({details})")
            sweep_steps()
            for name in results:
                results[name]["warnings"] = [n.message for n in notices.of_stage(name)]
            doc["warnings"] = notices.to_json()
            calibration.write_text(calibration_json(doc), encoding="utf-8")
            files.append(out_dir / "calibration.json")
            for fname, text in exported.items():
                out.write_text(out_dir / fname, text)
                files.append(out_dir / fname)
            summaries = summarise(results, raw_count_sensors(cfg.inputs), notices.items)
            files += publish(summaries, recorder, cfg, out, notices.of_run())
            files += corrected
            recorder.close()
            bar.advance()
    return RunSummary(
        out_dir=out_dir,
        files=files,
        calibration=doc,
        counts=counts,
        summaries=summaries,
        notices=notices.items,
    )


def exports_note(noted: list[str]) -> str:
    """The one line that says which files for other tools left something out."""
    verb = (
        "leaves out what its format has" if len(noted) == 1 else "leave out what their formats have"
    )
    return (
        f'imupipe: note: [exports] {", ".join(noted)} {verb} no place for: see "exports" in '
        "calibration.json"
    )


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="calibrate: read the inputs, run the stages, write the outputs")
    p.add_argument("config", type=Path, help="the TOML config file")
    p.add_argument(
        "--spawn", action="store_true", help="also stream the recording to a Rerun viewer"
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or warnings on stderr")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    # one run per process: numpy's large arrays without the huge-page hint, as the readers'
    # columns already are (first touch of a fresh 23 MB array 0.047 s with it, 0.010 s
    # without, on the 2-core test machine; the 2 h Allan run's stage 0.46-0.47 s against
    # 0.50-0.60 s, six of six pairs of runs)
    with small_pages():
        summary = run(args.config, spawn=args.spawn, quiet=args.quiet, one_shot=True)
    if not args.quiet:
        from imupipe.pipeline.report.summary import print_notices, print_summary

        print_summary(summary.summaries)
        print_notices(summary.notices)  # the summary ends with them; then the files written
        for path in summary.files:
            print(path)
    return 0
