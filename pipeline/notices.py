"""One record of what a run warned about: every warning and note, wherever it was raised.

Warnings come from four places: a reader (``[inputs.<name>]``: samples out of order, a guessed
rate), a stage's fit (``ctx.warn``), a correction step applied to a log (a temperature model
extrapolated past its fitted rates, on the held-out run or on an ``apply_to`` log), and the
exporters (a file for another tool that has no place for part of the calibration: a note).
:class:`Notices` collects them as they happen, each with where it belongs (the stage, or the
input or ``exports``); the run then puts them, the same words each time, in ``calibration.json``
(``results.<stage>.warnings`` and the top-level ``warnings`` list), in ``report.html`` and in the
recording beside their stage, and at the end of the terminal summary.

Every entry carries ``meaning``: what the message means for the user and what to do, in plain
words, from :data:`MEANINGS` (a message none of them matches points to the reference page).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from typing import Literal

Level = Literal["warning", "note"]

DOCS = "docs/reference/outputs.md#warnings-and-notes"
"""Where the warnings are explained (the fallback meaning links there)."""

MEANINGS: list[tuple[str, str]] = [
    (
        r"extrapolated beyond the fitted range",
        "the log being corrected heats or cools faster than the calibration session did, so "
        "there the temperature correction extrapolates its model and may be less accurate. "
        "If these samples matter, calibrate on a chamber session that covers these rates "
        "(docs/how-to/choose-thermal-model.md).",
    ),
    (
        r"clamped to the fitted range",
        "the log being corrected is colder or hotter than any temperature of the calibration "
        "session; the correction holds its value at the edge of the fitted range there. "
        "Calibrate over the temperatures the IMU will see.",
    ),
    (
        r"Allan fits want two hours",
        "a short still recording pins down the white noise (N) well, but bias instability (B), "
        "random walk (K) and rate ramp (R) poorly. Record two hours or more at rest for those "
        "(docs/explanation/allan.md).",
    ),
    (
        r"IEEE slope readings differ",
        "the slopes read straight off the Allan deviation curve (-1/2: white noise, +1/2: "
        "random walk) disagree with the fitted noise model: the long-tau terms (K, B) rest on "
        "few independent samples. Treat them as rough, or record longer "
        "(docs/explanation/allan.md).",
    ),
    (
        r"no place for",
        "that file's format cannot hold part of the calibration (a temperature model, a "
        "misalignment convention): the tool reading it will not apply that part. What was "
        'left out is listed under "exports" in calibration.json.',
    ),
    (
        r"samples are NaN|NaN or Inf",
        "those samples were skipped by the fit; the rest is used. Check the logger if there "
        "are many.",
    ),
    (
        r"accepted: accept_failed_checks",
        "the fit failed one of its quality checks and was kept only because the stage sets "
        "accept_failed_checks = true: check its plots before using it.",
    ),
    (
        r"gap\(s\)|samples missing",
        "the IMU dropped samples; the fit accounts for them, but many or long gaps bias the "
        "long-tau noise terms. Check the logger's load.",
    ),
    (
        r"misalignment not fitted|misalignment is not estimated",
        "the poses did not turn the IMU through enough distinct directions to estimate the "
        "axes' misalignment; only scale and bias were fitted. Record more distinct poses "
        "(docs/how-to/recordings.md).",
    ),
    (
        r"temperature spans only",
        "the chamber session covered a narrow temperature range; outside it the correction is "
        "held constant. Record over the temperatures the IMU will see.",
    ),
    (
        r"raw counts|far from the Earth",
        "the magnetometer's unit is not what the config says, so the corrected field has the "
        "wrong scale. Set the input's mag unit or the stage's field_ut.",
    ),
]
"""(regular expression, meaning and what to do): the first that matches a message explains it."""


def meaning(message: str) -> str:
    """What ``message`` means for the user and what to do (plain words)."""
    for pattern, text in MEANINGS:
        if re.search(pattern, message):
            return text
    return f"see {DOCS} for what each warning means."


@dataclass
class Notice:
    """One warning or note: ``stage`` it concerns (None: the whole run, e.g. ``exports``),
    ``source`` where it was raised (``stage``, ``inputs.<name>``, ``step``, ``exports``)."""

    level: Level
    stage: str | None
    source: str
    message: str

    @property
    def meaning(self) -> str:
        return meaning(self.message)

    @property
    def where(self) -> str:
        return self.stage or self.source

    def line(self) -> str:
        """``warning [temp_gyro]: message``: how the terminal lists it."""
        return f"{self.level} [{self.where}]: {self.message}"

    def to_json(self) -> dict[str, str | None]:
        return {**asdict(self), "meaning": self.meaning}


class Notices:
    """The run's warnings and notes in the order they were raised, each kept once per stage."""

    def __init__(self) -> None:
        self.items: list[Notice] = []

    def add(self, level: Level, stage: str | None, source: str, message: str) -> None:
        message = " ".join(str(message).split())
        if not any(n.stage == stage and n.message == message for n in self.items):
            self.items.append(Notice(level, stage, source, message))

    def of_stage(self, stage: str) -> list[Notice]:
        return [n for n in self.items if n.stage == stage]

    def of_run(self) -> list[Notice]:
        """The entries that belong to no stage (the exports' notes)."""
        return [n for n in self.items if n.stage is None]

    def to_json(self) -> list[dict[str, str | None]]:
        return [n.to_json() for n in self.items]


def counted(n: int, word: str) -> str:
    """``1 warning``, ``2 warnings``."""
    return f"{n} {word}" + ("" if n == 1 else "s")
