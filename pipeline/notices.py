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
words, from :data:`MEANINGS` (a message none of them matches: :data:`FALLBACK`, by where it was
raised).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from typing import Literal

Level = Literal["warning", "note"]

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
        r"not read: several (candidates|instances)",
        "the log has more than one sensor of that kind and imupipe does not guess which one "
        "belongs to your IMU: that sensor is left out of this run. Name the one you want with "
        "the key the message gives (imupipe inspect lists the log's topics).",
    ),
    (
        r"temperature not read",
        "the log holds no temperature of this IMU's own chip, so this input has no temperature "
        "(no thermal figures for it). If one of the candidates sits on the same board, name it "
        "with temperature_topic.",
    ),
    (
        r"logger dropped data",
        "the flight controller's logger could not keep up and lost messages for that long in "
        "total; the fit uses what was logged. A few milliseconds are harmless; many drops make "
        "the log's timing unreliable.",
    ),
    (
        r"not carried into the corrected MCAP",
        "the corrected MCAP holds the IMU, magnetometer and temperature; the log's other topics "
        "(the autopilot's state, estimator, setpoints) have no ROS message type and are not "
        "copied into it. The original log keeps them.",
    ),
    (
        r"out of (time )?order",
        "the logger wrote some samples out of time order; they were sorted by time, none "
        "dropped. Many such samples can mean two clocks are mixed in the log.",
    ),
    (
        r"times from the rate",
        "the file has no time column, so each sample's time was made from the rate, as if no "
        "sample were missing; a gap in the recording would go unseen.",
    ),
    (
        r"skipped \d+ line",
        "the lines before the column names were not data and were left out; check they held "
        "nothing you need (a rate line is used for the times).",
    ),
    (
        r"not indexed|was not closed|cannot be decompressed|corrupt in places",
        "the file is damaged (most often a recording cut off by a power loss or a full disk): "
        "everything that could be read is used, the damaged part is lost.",
    ),
    (
        r"paired by nearest|within half a period",
        "PX4 logs the gyro and the accelerometer as separate messages; imupipe put each gyro "
        "sample with the accelerometer sample nearest in time. Harmless for a recording at "
        "rest; a sample with no partner is NaN and left out of fits.",
    ),
    (
        r"read as NaN",
        "those messages carry no usable value (no integration interval), so they are read as "
        "NaN and left out of the fits.",
    ),
    (
        r"rotation to the body is unknown",
        "the log does not say how this magnetometer is mounted, so its field cannot be turned "
        "into the vehicle's axes: it is used in its own axes.",
    ),
    (
        r"only \d+ s of data|a minute or more",
        "a short recording gives a bias whose uncertainty is large and says little about the "
        "drift; record the IMU at rest for a minute or more (docs/how-to/recordings.md).",
    ),
    (
        r"samples are NaN|NaN or Inf|empty or NaN cells",
        "those samples were skipped by the fit; the rest is used. Check the logger if there "
        "are many.",
    ),
    (
        r"refused: .*left out of the chain",
        "that sensor's fit failed its own quality check, so it is not applied: the calibration "
        "and the parameter files hold the other sensors' fits only, and the vehicle keeps its "
        "present calibration of this one. Look at its plots; name it in accept_failed_checks "
        "to use the fit anyway.",
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


FALLBACK: dict[str, str] = {
    "inputs": "the reader met this in the log; the samples it read are used as they are. "
    "Check the input if the figures look wrong.",
    "stage": "the stage fitted, but flagged this about its data or its fit: look at its plots "
    "in report.html before using the result.",
    "step": "applying the calibration to a log met this: the corrected samples there are less "
    "certain than the rest.",
    "exports": "a file for another tool could not hold everything; calibration.json has it all.",
}
"""What a message no pattern of :data:`MEANINGS` matches means, by where it was raised (a test
keeps every message the readers and stages are known to write matched by a pattern)."""


def meaning(message: str, source: str = "stage") -> str:
    """What ``message`` means for the user and what to do (plain words); ``source``: where it
    was raised (``inputs.NAME``, ``stage``, ``step``, ``exports``), for a message no pattern
    matches."""
    for pattern, text in MEANINGS:
        if re.search(pattern, message):
            return text
    return FALLBACK.get(source.split(".")[0], FALLBACK["stage"])


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
        return meaning(self.message, self.source)

    @property
    def where(self) -> str:
        """What the message is about: the input for a reader's warning (``inputs.gyro1``),
        else the stage (or the source of a message of the whole run)."""
        if self.source.startswith("inputs."):
            return self.source
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
