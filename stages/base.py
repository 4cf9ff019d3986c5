"""The stage protocol.

A stage knows math, not files. The pipeline hands it the common table of its input, *as corrected
by the correction stages before it*, and a :class:`StageContext`; the stage returns a
:class:`StageOutput`: JSON-ready results (with a ``metrics`` dict), and, for a correction stage, a
:class:`~imupipe.stages.steps.Step` that applies vectorised to any common table.

Options: each stage declares a dataclass ``Options``; the config's keys for the stage are checked
against its fields (unknown keys and wrong types are errors naming the key).
"""

from __future__ import annotations

import dataclasses
import sys
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from imupipe.readers.table import MAX_MAGNITUDE, SensorData, finite, usable
from imupipe.stages.errors import FitError
from imupipe.stages.steps import Step

AXES = ("x", "y", "z")


def is_dead(column: np.ndarray) -> bool:
    """An axis that carries no signal: no usable value (all NaN, Inf), or every usable value
    the same (stuck or unconnected: exactly 0.0 throughout). Its noise is zero and its fits
    divide by zero, so stages fit nothing on it."""
    lo, hi = column.min(initial=np.inf), column.max(initial=-np.inf)
    if usable(lo) and usable(hi):
        return bool(lo == hi)
    ok = column[usable(column)]
    return len(ok) == 0 or bool(ok.min() == ok.max())


def dead_value(column: np.ndarray) -> str:
    """What a dead axis reads, for messages: ``always 0.0`` or ``no finite value``."""
    ok = column[usable(column)]
    return f"always {float(ok[0])!r}" if len(ok) else "no finite value"


class NullRecorder:
    """Stand-in for the Rerun recorder when recording is off: every call does nothing."""

    enabled = False

    def __getattr__(self, name: str) -> Callable[..., None]:
        return lambda *args, **kwargs: None


@dataclass
class StageContext:
    """What a stage gets besides its input table.

    - ``name``: the stage's name (its ``name`` key, else its type); Rerun paths go under ``/<name>``.
    - ``input_name``: the config input the stage fits on.
    - ``recorder``: a :class:`imupipe.pipeline.report.recording.Recorder` (or a no-op stand-in).
    - ``tables``: every input's table, corrected by the chain so far (for ``validate`` inputs).
    - ``warnings``: collected warnings; :meth:`warn` also prints them on stderr.
    - ``accept_failed_checks``: the stage's ``accept_failed_checks`` key: a fit that fails one of
      its quality checks (:meth:`check`) is kept, with a warning, instead of stopping the run.
    - ``failed_checks``: the checks that failed and were accepted (recorded in the results).
    - ``refuse_alone``: a failed check (not accepted) refuses this fit without stopping the run:
      it is listed under ``refused`` and the stage goes on to its results, which the run keeps
      while leaving the fit out of the chain (one of several instances of a log's sensor: the
      others' fits stand, :mod:`imupipe.pipeline.instances`).
    - ``refused``: the checks that failed and refused the fit (with ``refuse_alone``).
    """

    name: str
    input_name: str
    recorder: Any = field(default_factory=NullRecorder)
    tables: Mapping[str, pa.Table] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    quiet: bool = False
    accept_failed_checks: bool = False
    failed_checks: list[str] = field(default_factory=list)
    refuse_alone: bool = False
    refused: list[str] = field(default_factory=list)

    def warn(self, message: str) -> None:
        message = " ".join(message.split())
        self.warnings.append(message)
        if not self.quiet:
            print(f"imupipe: warning: [{self.name}] {message}", file=sys.stderr)

    def fail(self, message: str) -> FitError:
        """An error to raise: ``raise ctx.fail("...")``; names the stage and its input."""
        return FitError(f"stage '{self.name}' on input '{self.input_name}': {message}")

    def check(self, ok: bool, message: str) -> None:
        """A quality check of the fit. ``message`` names the check and the figure against its
        bound (``residual 4.2 mg > 3 x noise 0.9 mg``). A failed check stops the stage with one
        line (the fit is not applied) unless the stage sets ``accept_failed_checks = true``; then
        it is a warning and is listed under ``failed_checks`` in the stage's results. With
        ``refuse_alone`` it is listed under ``refused`` and the stage goes on."""
        if ok:
            return
        if not self.accept_failed_checks:
            if not self.refuse_alone:
                raise self.refusal(message)
            self.refused.append(" ".join(message.split()))
            return
        self.failed_checks.append(" ".join(message.split()))
        self.warn(f"{message} (accepted: accept_failed_checks = true)")

    def refusal(self, message: str | None = None) -> FitError:
        """The error of a failed check (``message``; default: the first of :attr:`refused`):
        what stops the run when a fit fails its quality check."""
        text = message if message is not None else self.refused[0]
        return self.fail(
            f"{text}; the fit is not applied (set accept_failed_checks = true in this "
            "stage to use it anyway)"
        )

    def finite(
        self, data: SensorData, what: str, minimum: int = 1, axes: Sequence[str] | None = None
    ) -> SensorData:
        """``data`` without its samples that cannot enter a fit (NaN, Inf, or beyond
        :data:`~imupipe.readers.table.MAX_MAGNITUDE`), with one warning that counts them (``6990
        of 13964 magnetometer samples are NaN or Inf; fitted on 6974``); a stage error when
        fewer than ``minimum`` remain, naming the axis (``axes``: each column's name; default
        ``<what> x``, ...) when one has no usable value at all (a dead axis)."""
        kept, bad = finite(data)
        if bad and len(kept) < minimum and len(data):
            k = data.values.shape[1]
            names = list(axes or ([what] if k == 1 else [f"{what} {a}" for a in AXES[:k]]))
            none = [names[i] for i in range(k) if not usable(data.values[:, i]).any()]
            if none:
                raise self.fail(self.dead_text(", ".join(f"{n} (no finite value)" for n in none)))
        if bad:
            huge = int(np.count_nonzero(np.isfinite(data.values).all(axis=1))) - len(kept)
            kind = "NaN or Inf" if not huge else f"NaN, Inf or beyond {MAX_MAGNITUDE:g}"
            self.warn(f"{bad} of {len(data)} {what} samples are {kind}; fitted on {len(kept)}")
        if len(kept) < minimum:
            raise self.fail(
                f"{len(kept)} finite {what} samples of {len(data)}; the fit needs at least {minimum}"
            )
        return kept

    def dead_axes(self, data: SensorData, sensor: str, independent: bool = False) -> list[int]:
        """The axes of ``data`` (n, 3) that carry no signal (:func:`is_dead`). A fit that needs
        every axis (``independent`` false: an ellipsoid, a pose model) fails a quality check
        (:meth:`check`) with one line naming the input, the sensor and the axis: the stage stops
        unless ``accept_failed_checks``; one that fits each axis on its own warns (the same
        names) and gets the dead axes, to fit the others only. Every axis dead is an error."""
        values = data.values
        dead = [i for i in range(values.shape[1]) if is_dead(values[:, i])]
        if not dead:
            return []
        axes = ", ".join(f"{sensor} {AXES[i]} ({dead_value(values[:, i])})" for i in dead)
        if len(dead) == values.shape[1]:
            raise self.fail(self.dead_text(axes))
        if not independent:
            self.check(False, self.dead_text(axes))
            return dead
        self.warn(self.dead_text(axes, fitted_others=True))
        return dead

    def dead_text(self, axes: str, fitted_others: bool = False) -> str:
        """The one line about dead axes (``gyro z (always 0.0)``); a warning names the input
        (an error does: :meth:`fail`)."""
        head = f"{axes}: a dead axis (every sample the same value, or none finite)"
        if fitted_others:
            return (
                f"input '{self.input_name}': {head}; nothing is fitted for it, the other axes are"
            )
        return (
            f"{head}; nothing can be fitted on it (a stuck or unconnected sensor, or a driver that "
            "does not fill the field)"
        )


@dataclass
class StageOutput:
    """A stage's result.

    - ``results``: JSON-serialisable; goes to ``calibration.json`` under ``results.<name>``.
      Put quality figures under ``results["metrics"]``.
    - ``step``: the correction this stage adds to the chain (None for analysis stages), or a list
      of steps when one fit corrects several sensors (e.g. accel and gyro together).
    - ``artifacts``: extra output files, file name -> text, written atomically in the output dir.
    - ``counts``: the sensors whose corrected values are still the input's raw counts, not SI
      (a magnetometer fitted in counts without a field magnitude keeps their scale).
    """

    results: dict[str, Any]
    step: Step | list[Step] | None = None
    artifacts: dict[str, str] = field(default_factory=dict)
    counts: tuple[str, ...] = ()

    @property
    def steps(self) -> list[Step]:
        if self.step is None:
            return []
        return list(self.step) if isinstance(self.step, list) else [self.step]


class Stage(ABC):
    """Base class of every stage. Subclasses set ``type``, ``Options``, ``sensors``, ``corrects``."""

    type: ClassVar[str]
    sensors: ClassVar[tuple[str, ...]] = ()
    """The sensors the stage works on; the pipeline records them before and after the stage."""
    corrects: ClassVar[bool] = False

    @dataclass
    class Options:
        pass

    def __init__(self, options: Any) -> None:
        self.options = options

    @abstractmethod
    def fit(self, table: pa.Table, ctx: StageContext) -> StageOutput:
        """Fit on ``table`` (the input as corrected so far)."""

    @classmethod
    def option_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls.Options)]

    @classmethod
    def sensors_for(cls, options: Any) -> tuple[str, ...]:
        """The sensors this configured stage works on (override when an option picks them)."""
        return cls.sensors
