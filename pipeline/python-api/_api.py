"""What ``import imupipe`` offers, written over the pipeline's own functions.

Every internal module the public API stands on is imported here, at the top of this one module
(the stage functions of :mod:`imupipe._stages` call :func:`fit_stage`), so that a later move of
an internal module changes one import block. The command line and this API share those
functions: ``imupipe run`` and :func:`run` both call :func:`imupipe.pipeline.run.run`,
``imupipe inspect`` and :func:`inspect` both call :func:`imupipe.pipeline.inspect_log.inspect`,
``imupipe convert`` and :func:`convert` both call :func:`imupipe.pipeline.convert.fleet.convert`.

This module is imported on first use of a public name (``import imupipe`` alone loads none of
it: no numpy, no pyarrow). The fleet conversion and the run (:func:`convert`,
:class:`ConvertSummary`, :func:`run`) are imported when first used, not here: they load the
process pool, the MCAP writer and the run's outputs, 0.05-0.08 s of CPU that
``imupipe.read`` of one log does not need (issue 39).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect as inspect_module
import io
import os
import sys
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import pyarrow as pa

from imupipe.pipeline.atomic import atomic_path
from imupipe.pipeline.calibration_file import (
    calibration_json,
    check_calibration,
    fitted_on,
    load_calibration,
)
from imupipe.pipeline.config import Config, build_options, load_config, parse_config, parse_input
from imupipe.pipeline.errors import ConfigError
from imupipe.pipeline.inspect_log import inspect as inspect_log
from imupipe.pipeline.inspect_log import render as render_inspection
from imupipe.pipeline.report.summary import (
    StageSummary,
    print_summary,
    raw_count_sensors,
    summarise,
)
from imupipe.readers.dispatch import read_input
from imupipe.readers.errors import ImupipeError
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import FLIGHT_COLUMNS, SENSOR_COLUMNS, metadata, on_imu_rows
from imupipe.stages.base import StageContext
from imupipe.stages.registry import stage_class
from imupipe.stages.steps import Step, apply_chain

if TYPE_CHECKING:
    from imupipe.pipeline.convert.fleet import ConvertSummary, convert
    from imupipe.pipeline.run import RunSummary

LAZY = {
    "convert": "imupipe.pipeline.convert.fleet",
    "ConvertSummary": "imupipe.pipeline.convert.fleet",
}
"""Public names of other modules, imported on first use (:func:`__getattr__`)."""


def __getattr__(name: str) -> Any:
    """:data:`LAZY` names, their module imported on first use (PEP 562)."""
    if name in LAZY:
        import importlib

        value = getattr(importlib.import_module(LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ArgumentError",
    "Calibration",
    "ConvertSummary",
    "ImupipeError",
    "ImupipeWarning",
    "Inspection",
    "RunResult",
    "StageResult",
    "convert",
    "fit_stage",
    "inspect",
    "keywords_checked",
    "read",
    "run",
]

BOOKKEEPING = (
    "type",
    "input",
    "metrics",
    "standard_errors",
    "warnings",
    "failed_checks",
    "fitted_on",
)
"""Keys of a stage's results that are not fitted values (see :attr:`StageResult.values`)."""
FLIGHT_STAGES = ("mag_inflight",)
"""Stage types that fit on a log's flight streams (attitude, position, current, throttle), which
:func:`read`'s default ``rows="samples"`` leaves out."""
UNCERTAINTY_SUFFIXES = ("_std", "_std_error", "_range_68", "_upper_68", "uncertainty")
"""Metric names that hold an uncertainty (see :attr:`StageResult.uncertainties`)."""


class ImupipeWarning(UserWarning):
    """A warning of a reader or a stage (the line ``imupipe run`` prints as ``imupipe: warning:
    ...``), issued with :func:`warnings.warn`: shown in a notebook, caught with
    ``warnings.catch_warnings(record=True)``, turned into errors with
    ``warnings.simplefilter("error", imupipe.ImupipeWarning)``."""


def keywords_checked(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function`` whose bad calls (a misspelt keyword, a missing argument) raise
    :class:`ArgumentError` naming the keywords it takes; its signature, annotations and
    docstring are kept (``functools.wraps``). The call itself is not slowed: the arguments are
    bound only when Python refused them."""
    signature = inspect_module.signature(function)

    @functools.wraps(function)
    def checked(*args: Any, **kwargs: Any) -> Any:
        try:
            return function(*args, **kwargs)
        except TypeError as error:
            try:
                signature.bind(*args, **kwargs)
            except TypeError:
                raise ArgumentError(_bad_call(function.__name__, signature, kwargs)) from error
            raise

    return checked


def _bad_call(name: str, signature: inspect_module.Signature, kwargs: Mapping[str, Any]) -> str:
    """The one line for a call that does not fit ``signature``."""
    keywords = [p.name for p in signature.parameters.values() if p.kind is p.KEYWORD_ONLY]
    unknown = [k for k in kwargs if k not in signature.parameters]
    if unknown:
        close = difflib.get_close_matches(unknown[0], keywords, n=1)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        return (
            f"imupipe.{name}(): unknown keyword '{unknown[0]}'{hint} "
            f"(allowed: {', '.join(keywords)})"
        )
    needed = [
        p.name
        for p in signature.parameters.values()
        if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    return (
        f"imupipe.{name}(): takes {', '.join(needed)} as argument{'s' * (len(needed) > 1)}, "
        f"then only keywords ({', '.join(keywords)})"
    )


class ArgumentError(ConfigError, TypeError):
    """A wrong argument to a function of the API (a type, a table without the columns it
    needs): an :class:`ImupipeError` with one line, as the command line says it, and a
    ``TypeError`` as Python says it."""


def _table_arg(table: Any, where: str, sensors: Sequence[str] = ()) -> pa.Table:
    """``table`` when it is a common table with the columns of ``sensors``; ArgumentError
    otherwise (a one-line message naming ``where``)."""
    if not isinstance(table, pa.Table):
        raise ArgumentError(
            f"{where}: table must be a pyarrow.Table (from imupipe.read), not "
            f"{type(table).__name__}"
        )
    need = ["t_ns", *(c for s in sensors for c in SENSOR_COLUMNS.get(s, ()))]
    missing = [c for c in need if c not in table.column_names]
    if missing:
        raise ArgumentError(
            f"{where}: the table has no column {', '.join(missing)} (a common table from "
            "imupipe.read has them)"
        )
    return table


def _warn(messages: Sequence[str], where: str) -> None:
    """Issue ``messages`` as :class:`ImupipeWarning`, attributed to the user's line: the first
    frame outside the ``imupipe`` package (however many of its functions called this one)."""
    package = os.path.dirname(__file__) + os.sep
    frame, level = sys._getframe(1), 2
    while frame is not None and frame.f_code.co_filename.startswith(package):
        frame, level = frame.f_back, level + 1
    for message in messages:
        warnings.warn(f"[{where}] {message}", ImupipeWarning, stacklevel=level)


def _text(summaries: Sequence[StageSummary]) -> str:
    """The terminal summary of ``imupipe run`` (:func:`~imupipe.pipeline.report.summary.print_summary`)
    as plain text."""
    from rich.console import Console

    buffer = io.StringIO()
    console = Console(file=buffer, width=110, color_system=None, force_terminal=False)
    print_summary(summaries, console)
    return buffer.getvalue().rstrip() + "\n"


def _input_raw(path: str | os.PathLike[str], options: Mapping[str, Any]) -> dict[str, Any]:
    """An ``[inputs.NAME]`` table from keyword arguments (None: the key is left out)."""
    raw: dict[str, Any] = {"path": os.fspath(path)}
    for key, value in options.items():
        if value is not None:
            raw[key] = dict(value) if key in ("csv", "fields") else value
    return raw


def input_spec(path: str | os.PathLike[str], where: str, **options: Any) -> InputSpec:
    """The input ``path`` with the keys of an ``[inputs.NAME]`` table, checked as the config
    checks them (:func:`imupipe.pipeline.config.parse_input`; relative paths from the current
    folder); a :class:`~imupipe.pipeline.errors.ConfigError` naming ``where`` and the key."""
    spec = parse_input("input", _input_raw(path, options), Path.cwd(), where)
    return dataclasses.replace(spec, keys_in=f"{where.split('(')[0]}()'s keywords")


def read(
    path: str | os.PathLike[str],
    *,
    imu_topic: str | None = None,
    mag_topic: str | None = None,
    temperature_topic: str | None = None,
    time: Literal["header", "log"] = "header",
    csv: Mapping[str, Any] | None = None,
    gyro_topic: str | None = None,
    accel_topic: str | None = None,
    fields: Mapping[str, Any] | None = None,
    rows: Literal["samples", "messages"] = "samples",
) -> pa.Table:
    """Read a log (CSV, MCAP, ROS 1 or ROS 2 bag, PX4 ULog, ArduPilot DataFlash) into the common
    table: a ``pyarrow.Table`` with ``t_ns`` (int64 ns) and the SI columns ``gyro_x`` (rad/s),
    ``accel_x`` (m/s^2), ``mag_x`` (T), ``temperature`` (degC)... (see the reference page "The
    common table").

    ``rows="samples"`` (the default): one row per IMU sample, so that ``gyro_x`` has no gaps;
    the magnetometer, temperature and pressure are carried onto the IMU stamps by linear
    interpolation in time between their own samples (held constant before the first and after
    the last; a row that has its own value keeps it), and the rows of other messages are
    dropped (:func:`imupipe.readers.table.on_imu_rows`; a warning says how many when a flight
    stream's are). ``rows="messages"``: one row per message, as ``imupipe run`` reads it, every
    sensor null on the rows of the others; fit magnetometer stages on this one, so that each
    magnetometer sample counts once.

    The other keywords are the keys of a config's ``[inputs.NAME]`` table, with the same checks
    (``csv`` is the ``[inputs.NAME.csv]`` mapping as a dict: ``csv={"time": 0, "time_unit":
    "s", "accel": [1, 2, 3]}``; ``fields`` the ``[inputs.NAME.fields]`` mapping:
    ``fields={"gyro": "/fmu/out/sensor_combined.gyro_rad", "time": "log"}``; ``gyro_topic`` and
    ``accel_topic``: a gyro and an accelerometer published on topics of their own, each read at
    its own stamps). The reader's warnings (a topic chosen among several, stamps out of order) are issued as :class:`ImupipeWarning`. Raises :class:`ImupipeError` (one line
    naming the file and what is wrong) when the log cannot be read.
    """
    if rows not in ("samples", "messages"):
        raise ConfigError(f"imupipe.read(): rows={rows!r}: must be 'samples' or 'messages'")
    where = f"imupipe.read({os.fspath(path)!r})"
    spec = input_spec(
        path,
        where,
        imu_topic=imu_topic,
        mag_topic=mag_topic,
        temperature_topic=temperature_topic,
        time=time,
        csv=csv,
        gyro_topic=gyro_topic,
        accel_topic=accel_topic,
        fields=fields,
    )
    table, found = read_input(spec)
    if rows == "samples":
        table, dropped = on_imu_rows(table)
        flight = {k: n for k, n in dropped.items() if k in FLIGHT_COLUMNS}
        if flight:
            found = [
                *found,
                f"rows='samples' keeps the IMU samples: the rows of "
                f"{', '.join(f'{n} {k}' for k, n in flight.items())} samples are left out; "
                "read with rows='messages' for them",
            ]
    _warn(found, where)
    return table


@dataclass
class Inspection:
    """What a log holds (``imupipe inspect``): :attr:`info` is the dict ``imupipe inspect
    --json`` prints; the text and the notebook show what ``imupipe inspect`` prints."""

    info: dict[str, Any]

    def __getitem__(self, key: str) -> Any:
        return self.info[key]

    def __repr__(self) -> str:
        return render_inspection(self.info)

    def _repr_html_(self) -> str:
        import html

        return f"<pre>{html.escape(render_inspection(self.info))}</pre>"


def inspect(
    path: str | os.PathLike[str],
    *,
    imu_topic: str | None = None,
    mag_topic: str | None = None,
    temperature_topic: str | None = None,
    time: Literal["header", "log"] = "header",
    csv: Mapping[str, Any] | None = None,
    gyro_topic: str | None = None,
    accel_topic: str | None = None,
    fields: Mapping[str, Any] | None = None,
) -> Inspection:
    """What a log holds and what :func:`read` would take from it: topics, message types,
    counts, rates, time spans, the topic each stream is read from and the columns filled (for
    a PX4 ULog or a DataFlash log also the autopilot's calibration parameters). Same keywords
    as :func:`read`."""
    spec = input_spec(
        path,
        f"imupipe.inspect({os.fspath(path)!r})",
        imu_topic=imu_topic,
        mag_topic=mag_topic,
        temperature_topic=temperature_topic,
        time=time,
        csv=csv,
        gyro_topic=gyro_topic,
        accel_topic=accel_topic,
        fields=fields,
    )
    return Inspection(inspect_log(spec))


def _uncertainties(results: Mapping[str, Any]) -> dict[str, Any]:
    """The uncertainties a stage reported: its ``standard_errors`` and every metric whose name
    says it is one (:data:`UNCERTAINTY_SUFFIXES`), keyed by their path in the results
    (``metrics.gyro.x.K_range_68``)."""
    found: dict[str, Any] = {}
    if "standard_errors" in results:
        found["standard_errors"] = results["standard_errors"]

    def walk(value: Any, path: str) -> None:
        if not isinstance(value, Mapping):
            return
        for key, inner in value.items():
            where = f"{path}.{key}"
            if str(key).endswith(UNCERTAINTY_SUFFIXES):
                found[where] = inner
            else:
                walk(inner, where)

    walk(results.get("metrics", {}), "metrics")
    return found


@dataclass
class StageResult:
    """The result of one stage: what ``calibration.json`` records under ``results.<name>``, with
    the correction it adds to the chain.

    - :attr:`values`: the fitted values (``bias``, ``scale``, the Allan coefficients...), SI;
    - :attr:`uncertainties`: their standard errors and ranges;
    - :attr:`metrics`: the quality figures;
    - :attr:`warnings`: what the stage warned about;
    - :attr:`step` / :attr:`steps`: the correction (None / ``[]`` for an analysis stage);
      :meth:`apply` applies it, :meth:`calibration` makes a :class:`Calibration` of it.

    Shown as the table ``imupipe run`` prints (``repr``) and as the report's section in Jupyter.
    """

    name: str
    type: str
    results: dict[str, Any]
    steps: list[Step] = field(default_factory=list)
    counts: frozenset[str] = frozenset()
    """Sensors whose input was read in raw counts (``<sensor>_unit = "raw"``): their offsets
    are in counts, and the tables say so."""

    @property
    def values(self) -> dict[str, Any]:
        """The fitted values: the results without the metrics, the uncertainties and the bookkeeping
        (:data:`BOOKKEEPING`); SI units (raw counts where :attr:`counts` says so)."""
        return {k: v for k, v in self.results.items() if k not in BOOKKEEPING}

    @property
    def uncertainties(self) -> dict[str, Any]:
        """The uncertainties the stage reported, by their place in the results: its
        ``standard_errors`` and every metric named ``*_std``, ``*_std_error``, ``*_range_68``,
        ``*_upper_68`` or ``uncertainty`` (``metrics.gyro.x.K_range_68``)."""
        return _uncertainties(self.results)

    @property
    def metrics(self) -> dict[str, Any]:
        """The quality figures (``results["metrics"]``: residuals, sample counts, the model
        chosen and why)."""
        return dict(self.results.get("metrics", {}))

    @property
    def warnings(self) -> list[str]:
        """What the stage warned about (also issued as :class:`ImupipeWarning`)."""
        return list(self.results.get("warnings", []))

    @property
    def failed_checks(self) -> list[str]:
        """Quality checks that failed and were kept with ``accept_failed_checks=True``."""
        return list(self.results.get("failed_checks", []))

    @property
    def step(self) -> Step | None:
        """The correction step (the first, when one fit corrects several sensors)."""
        return self.steps[0] if self.steps else None

    def apply(self, table: pa.Table) -> pa.Table:
        """``table`` with this stage's correction applied (unchanged for an analysis stage)."""
        return apply_chain(table, self.steps)

    def calibration(self) -> Calibration:
        """This result alone as a calibration (see :meth:`Calibration.from_results`)."""
        return Calibration.from_results(self)

    def summary(self) -> StageSummary:
        """The summary ``imupipe run`` prints and the report shows."""
        counts = {str(self.results.get("input")): set(self.counts)}
        return summarise({self.name: self.results}, counts)[0]

    def __repr__(self) -> str:
        return _text([self.summary()])

    def _repr_html_(self) -> str:
        from imupipe.pipeline.report.page import stage_html

        return stage_html(self.summary())


def fit_stage(
    type_name: str,
    table: pa.Table,
    options: Mapping[str, Any],
    *,
    name: str | None = None,
    accept_failed_checks: bool = False,
) -> StageResult:
    """Fit a stage of type ``type_name`` on ``table`` (a common table, e.g. from :func:`read`).

    ``options`` are the stage's config keys, checked as the config checks them (names, types,
    ranges); a None value of a key whose default is a list or table keeps that default. What
    the stage warns about is in the result and issued as :class:`ImupipeWarning`; a fit that
    fails its own quality check raises :class:`ImupipeError` unless ``accept_failed_checks``.
    The stage functions (``imupipe.allan``, ...) call this.
    """
    cls = stage_class(type_name)
    _table_arg(table, f"imupipe.{type_name}()", getattr(cls, "sensors", ()))
    factory = {
        f.name
        for f in dataclasses.fields(cls.Options)
        if f.default_factory is not dataclasses.MISSING
    }
    given = {k: v for k, v in options.items() if not (v is None and k in factory)}
    given = {k: list(v) if isinstance(v, tuple) else v for k, v in given.items()}
    stage_name = name or type_name
    opts = build_options(cls.Options, given, f"imupipe.{type_name}()")
    left_out = [s for s in metadata(table).get("left_out", {}) if s in FLIGHT_COLUMNS]
    if type_name in FLIGHT_STAGES and left_out:
        raise ConfigError(
            f"imupipe.{type_name}(): the table was read with rows='samples' (imupipe.read's "
            f"default), which leaves out the flight streams the stage fits on "
            f"({', '.join(left_out)}): read the log with imupipe.read(path, rows='messages')"
        )
    ctx = StageContext(
        name=stage_name,
        input_name="table",
        tables={"table": table},
        quiet=True,
        accept_failed_checks=accept_failed_checks,
    )
    try:
        output = cls(opts).fit(table, ctx)
    except KeyError as exc:  # a column a stage reads beyond its sensors'
        raise ArgumentError(
            f"imupipe.{type_name}(): the table has no column {exc} (a common table from "
            "imupipe.read has it)"
        ) from None
    if "mag_x" in metadata(table).get("carried", ()) and "mag" in cls.sensors_for(opts):
        ctx.warnings.append(
            "the table's magnetometer was interpolated onto the IMU samples (imupipe.read's "
            "default rows='samples'): read the log with rows='messages' to fit on the "
            "magnetometer's own samples, each counted once"
        )
    source = metadata(table).get("source")
    results: dict[str, Any] = {
        "type": type_name,
        "input": "table",
        **output.results,
        "warnings": ctx.warnings,
        "fitted_on": fitted_on("table", InputSpec(path=Path(source or "")), table),
    }
    if ctx.failed_checks:
        results["failed_checks"] = ctx.failed_checks
    _warn(ctx.warnings, stage_name)
    units = metadata(table).get("units", {})
    raw = frozenset(s for s, unit in units.items() if unit == "raw")
    return StageResult(stage_name, type_name, results, output.steps, raw)


@dataclass
class Calibration:
    """A correction chain and the results it was fitted with: the document of a
    ``calibration.json`` (see the reference page "calibration.json") and its steps.

    ``Calibration.load(path)`` reads one (``imupipe run``'s, ``imupipe import``'s, or a
    corrected MCAP's attached copy), :meth:`apply` corrects a common table, :meth:`save` writes
    it (``imupipe convert`` takes it), :meth:`from_results` makes one from stage results.
    """

    document: dict[str, Any]
    steps: list[Step]
    fitted: dict[str, StageResult] = field(default_factory=dict, repr=False)
    """The stage results it was made from (:meth:`from_results`), by stage name."""

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Calibration:
        """Read and check a calibration file (every chain entry; one-line
        :class:`ImupipeError` naming the file, the entry and the field)."""
        doc, steps = load_calibration(path)
        return cls(doc, steps)

    @classmethod
    def from_results(cls, *results: StageResult) -> Calibration:
        """The chain of the given stage results' steps, in the order given (fit each on the
        table corrected by the ones before it: ``b = imupipe.gyro_bias(t)``,
        ``a = imupipe.accel_calibration(b.apply(t))``, ``Calibration.from_results(b, a)``)."""
        for i, r in enumerate(results):
            if not isinstance(r, StageResult):
                raise ArgumentError(
                    f"Calibration.from_results(): argument {i + 1} must be a stage result "
                    f"(imupipe.gyro_bias(table), ...), not {type(r).__name__}"
                )
        chain = [step for r in results for step in r.steps]
        fitted = [r.results.get("fitted_on") for r in results for _ in r.steps]
        from imupipe.pipeline.run import calibration_document

        doc = calibration_document(chain, {r.name: r.results for r in results}, fitted)
        return cls(doc, chain, {r.name: r for r in results})

    def apply(
        self, table: pa.Table, *, on_mismatch: Literal["warn", "refuse"] = "warn"
    ) -> pa.Table:
        """``table`` corrected by every step of the chain, in order, each step on the data of
        its own device, as ``imupipe convert`` applies it. A table from another sensor than the
        one the calibration was fitted on (its topics, frames, instances or device ids differ
        from the chain's ``fitted_on``) is corrected with an :class:`ImupipeWarning` naming
        the difference, or refused (``on_mismatch="refuse"``: :class:`ImupipeError`), as
        ``convert --on-mismatch``."""
        from imupipe.pipeline.calibration_file import on_device
        from imupipe.pipeline.convert.provenance import ProvenanceCheck

        if on_mismatch not in ("warn", "refuse"):
            raise ArgumentError(
                f"Calibration.apply(): on_mismatch must be 'warn' or 'refuse', not {on_mismatch!r}"
            )
        _table_arg(table, "Calibration.apply()", [s.sensor for s in self.steps])
        chain = self.document.get("chain", [])
        where = str(metadata(table).get("source") or "the table")
        check = ProvenanceCheck(chain, on_mismatch, where)
        _warn(check.check(metadata(table)), "Calibration.apply()")
        steps = self.steps
        if len(chain) == len(steps):
            steps = on_device(steps, chain, lenient=True)
        return apply_chain(table, steps)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the calibration as JSON to ``path`` (written whole or not at all); returns it.
        A folder, or a path that cannot be written, is an :class:`ImupipeError` (one line)."""
        target = Path(path)
        if target.is_dir():
            raise ArgumentError(
                f"Calibration.save(): {target} is a folder; give a file name "
                f"({target / 'calibration.json'})"
            )
        try:
            with atomic_path(target) as tmp:
                tmp.write_text(calibration_json(self.document), encoding="utf-8")
        except OSError as exc:
            raise ConfigError(
                f"Calibration.save(): {target}: cannot write: {exc.strerror or exc}"
            ) from None
        return target

    @property
    def results(self) -> dict[str, StageResult]:
        """The stage results recorded with the chain, by stage name."""
        if self.fitted:
            return dict(self.fitted)
        return {
            name: StageResult(name, str(r.get("type", "?")), r, [])
            for name, r in self.document.get("results", {}).items()
        }

    def _chain_lines(self) -> list[str]:
        lines = []
        for i, entry in enumerate(self.document.get("chain", [])):
            source = (entry.get("fitted_on") or {}).get("path") or "-"
            lines.append(
                f"{i + 1}. {entry.get('sensor')}: {entry.get('type')} ({entry.get('kind', 'linear')}), "
                f"fitted on {source}"
            )
        return lines

    def __repr__(self) -> str:
        head = f"Calibration: {len(self.steps)} step(s)\n" + "\n".join(self._chain_lines())
        summaries = [r.summary() for r in self.results.values()]
        return head + ("\n\n" + _text(summaries) if summaries else "\n")

    def _repr_html_(self) -> str:
        import html

        from imupipe.pipeline.report.page import stage_html

        items = "".join(f"<li>{html.escape(line[3:])}</li>" for line in self._chain_lines())
        body = "".join(stage_html(r.summary()) for r in self.results.values())
        return f"<p><b>Calibration</b>: {len(self.steps)} step(s)</p><ol>{items}</ol>{body}"


@dataclass
class RunResult:
    """What :func:`run` did: the output folder and the files written, the calibration
    (:class:`Calibration`) and each stage's result (:class:`StageResult`, by stage name)."""

    out_dir: Path
    files: list[Path]
    calibration: Calibration
    stages: dict[str, StageResult]
    counts: dict[str, dict[str, int]]
    """Input -> messages written per topic into its corrected MCAP (``apply_to``)."""

    def __repr__(self) -> str:
        files = "\n".join(str(p) for p in self.files)
        return _text([s.summary() for s in self.stages.values()]) + files + "\n"

    def _repr_html_(self) -> str:
        import html

        from imupipe.pipeline.report.page import overview_html, stage_html

        summaries = [s.summary() for s in self.stages.values()]
        files = "".join(f"<li>{html.escape(str(p))}</li>" for p in self.files)
        return (
            overview_html(summaries)
            + "".join(stage_html(s) for s in summaries)
            + f"<p>Files written:</p><ul>{files}</ul>"
        )


def load_run_config(config: str | os.PathLike[str] | Mapping[str, Any]) -> Config:
    """A config from a TOML file, or from a dict with the same tables (relative paths from the
    current folder; messages name it ``<dict>``)."""
    if isinstance(config, Mapping):
        base = Path.cwd()
        return parse_config(dict(config), base / "<dict>", base)
    return load_config(config)


def run(
    config: str | os.PathLike[str] | Mapping[str, Any],
    *,
    quiet: bool = True,
    spawn: bool = False,
) -> RunResult:
    """``imupipe run``: read the inputs, run the stages in order, write the outputs into the
    config's ``[output] dir`` (all or nothing).

    ``config`` is a TOML file or a dict with the same tables (``{"inputs": {"static": {"path":
    "static.mcap"}}, "stages": [{"type": "allan"}], "output": {"dir": "out"}}``). ``quiet``:
    no progress bar and no warnings on stderr (the stages' warnings are in the results either
    way); ``spawn``: also stream the recording to a Rerun viewer.
    """
    from imupipe.pipeline.run import run as run_config

    cfg = load_run_config(config)
    summary: RunSummary = run_config(cfg, quiet=quiet, spawn=spawn)
    doc = summary.calibration
    steps = check_calibration(doc, str(summary.out_dir / "calibration.json"))
    stages = Calibration(doc, steps).results
    raw = raw_count_sensors(cfg.inputs)
    for result in stages.values():
        result.counts = frozenset(raw.get(str(result.results.get("input")), ()))
    # each step to the stage that fitted it, where its type says which (one stage of that type)
    types = [s.type for s in stages.values()]
    for step, entry in zip(steps, doc["chain"], strict=True):
        if types.count(str(entry.get("type"))) == 1:
            stages[next(n for n, s in stages.items() if s.type == entry["type"])].steps.append(step)
    return RunResult(
        summary.out_dir, summary.files, Calibration(doc, steps), stages, summary.counts
    )
