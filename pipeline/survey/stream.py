"""One IMU topic of one log surveyed in batches: a worker's memory is bounded by a batch.

:func:`survey_topic` reads the topic with :func:`imupipe.readers.dispatch.iter_input` in batches
of about ``batch_rows`` rows (MCAP, ROS 1 and ROS 2 bags; CSV, ULog and DataFlash logs are read
whole by their readers and come as one batch) and runs the two passes of
:mod:`imupipe.stages.survey.streaming`:

1. the log's rate and the noise floors of the windowed accelerometer and gyro variances;
2. a second read: each sample classified, the still periods tracked across batches and their
   sums accumulated, the temperature rows of the same batches assigned by time, and with a
   calibration the corrected samples (:func:`~imupipe.stages.steps.apply_chain_stream` on the
   batches, as ``convert`` corrects them) summed alike.

A log that comes as one batch is read once: pass 1 keeps its rows and their variances.

The window of pass 1 is set from the rate of the first batch; when the whole log's rate gives a
different window (gaps in the log), pass 1 is run again with the right one, so the result never
depends on the batch size. Batches are each sorted by time but not against each other: when a
batch starts before the previous one ended (stamps going back across the log's chunks), the
topic is read whole and sorted instead (:func:`~imupipe.readers.dispatch.read_input`, as before
the survey streamed), with a warning that its memory was not bounded.

The reader's own warnings (stamps out of order or repeated within a batch, counted per topic
over the batches: :func:`imupipe.readers.dispatch.iter_input`'s ``warnings``) are taken from the
first read that runs to its end, once.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np
import pyarrow as pa

# Rows per batch, as convert reads: 25,000. Issue 36, one 80-minute log at 400 Hz (1.92 million
# samples), one worker: peak RSS 395 MB at 200,000 rows (flat from 40 minutes on: bounded by the
# batch), 206 MB at 50,000, 164 MB at 25,000, the same CPU time within the noise (5.9, 5.6, 5.2 s).
from imupipe.pipeline.convert.options import DEFAULT_BATCH_ROWS


@dataclasses.dataclass
class Surveyed:
    """The figures of one IMU topic: raw (``stats``) and, with a calibration, corrected
    (``cal``), as :func:`imupipe.stages.survey.stats.figures` gives them; ``frame``: the IMU's
    frame id."""

    stats: dict[str, np.ndarray]
    cal: dict[str, np.ndarray] | None
    frame: str | None
    reads: int
    """How many times the topic was read: 1 when it came as one batch, 2 streamed, 3 when the
    first batch's rate gave another window than the log's."""


def _rows(table: pa.Table) -> tuple[np.ndarray, np.ndarray] | None:
    """(t_ns, x (n, 6): gyro then accel) of the IMU rows with finite samples; None when the
    batch has no gyro or no accelerometer."""
    from imupipe.readers.table import has_sensor, imu_pairs

    if not (has_sensor(table, "gyro") and has_sensor(table, "accel")):
        return None
    gyro, accel, _ = imu_pairs(table)  # on the imu rows (sampled apart: the gyro's stamps)
    x = np.column_stack([gyro.values, accel.values])
    keep = np.isfinite(x).all(axis=1)
    return gyro.t_ns[keep], x[keep]


def _temperature(table: pa.Table) -> tuple[np.ndarray, np.ndarray] | None:
    """(t_ns, degC) of the batch's finite temperature samples; None without any, or when every
    one is exactly 0 (a field the log fills with 0 when its sensor has no thermometer, such as
    ArduPilot's ``IMU2.T`` or PX4's ``sensor_gyro.temperature``: not logged, never 0.0 degC)."""
    from imupipe.readers.table import finite, has_stream, sensor

    if not has_stream(table, "temperature"):
        return None
    data, _ = finite(sensor(table, "temperature"))
    values = data.values[:, 0]
    if not len(values) or not values.any():
        return None
    return data.t_ns, values


class _Backwards(Exception):
    """A batch starts before the previous one ended."""


def _first_pass(tables: Iterator[pa.Table], opts: Any, half: int | None) -> tuple[Any, Any]:
    """Pass 1 over ``tables``: (FloorPass, the one table when there was only one)."""
    from imupipe.stages.survey.streaming import FloorPass, Rule, rate_of

    floor = None
    head: list[tuple[np.ndarray, np.ndarray]] = []  # rows before the rate can be guessed
    only: pa.Table | None = None
    count = 0
    last = None
    for table in tables:
        count += 1
        only = table if count == 1 else None
        rows = _rows(table)
        if rows is None or not len(rows[0]):
            continue
        t, x = rows
        if (last is not None and t[0] < last) or (np.diff(t) < 0).any():
            raise _Backwards
        last = int(t[-1])
        if floor is None:
            head.append((t, x))
            if half is None:
                ht = np.concatenate([h[0] for h in head])
                rate = rate_of(len(ht), int(ht[0]), int(ht[-1]))
                if rate is None:
                    continue
                half = Rule.at(opts, rate).half
            floor = FloorPass(half, keep=True)
            for ht_, hx in head:
                floor.feed(ht_, hx)
            head = []
        else:
            floor.keep = False
            floor.held = []
            floor.feed(t, x)
    if floor is None:  # too few rows or no time span: a pass over what there is
        floor = FloorPass(half or 1, keep=True)
        for ht_, hx in head:
            floor.feed(ht_, hx)
    if count > 1:
        floor.keep = False
        floor.held = []
    return floor, only


def _with_corrected(
    tables: Iterator[pa.Table], steps: list[Any] | None
) -> Iterator[tuple[pa.Table, pa.Table | None]]:
    """(raw batch, the same rows corrected by ``steps``) pairs; a step may hold rows back (its
    context), so the raw rows are queued and matched by count (the corrected stream holds
    every row once, in order: :meth:`~imupipe.stages.steps.Step.apply_stream`)."""
    if steps is None:
        for table in tables:
            yield table, None
        return
    from imupipe.stages.steps import apply_chain_stream

    queue: collections.deque[pa.Table] = collections.deque()

    def source() -> Iterator[pa.Table]:
        for table in tables:
            queue.append(table)
            yield table

    for corrected in apply_chain_stream(source(), steps):
        parts, need = [], corrected.num_rows
        while need:
            head = queue[0]
            if head.num_rows <= need:
                parts.append(queue.popleft())
                need -= head.num_rows
            else:
                parts.append(head.slice(0, need))
                queue[0] = head.slice(need)
                need = 0
        raw = parts[0] if len(parts) == 1 else pa.concat_tables(parts)
        yield raw, corrected


def survey_topic(
    spec: Any,
    opts: Any,
    steps: list[Any] | None,
    warnings: list[str],
    batch_rows: int | None = None,
) -> Surveyed | None:
    """Survey one IMU topic (``spec`` names it) in batches of about ``batch_rows`` rows (see the
    module docstring); None (with a warning appended) when it cannot be surveyed."""
    from imupipe.readers import dispatch
    from imupipe.readers.table import metadata
    from imupipe.readers.topics import SPLIT
    from imupipe.stages.survey.stats import figures
    from imupipe.stages.survey.streaming import PeriodPass, Rule

    topic = spec.imu_topic or SPLIT.join(t for t in (spec.gyro_topic, spec.accel_topic) if t)
    where = f"{spec.path}: {topic or 'imu'}"
    batch_rows = batch_rows or DEFAULT_BATCH_ROWS
    whole: pa.Table | None = None
    half: int | None = None
    reads = 0
    meta: dict[str, Any] | None = None

    warned_once: list[bool] = []  # the reader's warnings: from the first read to its end

    def batches() -> Iterator[pa.Table]:
        nonlocal meta
        if whole is not None:
            yield whole
            return
        read: list[str] | None = None if warned_once else []
        for table, _ in dispatch.iter_input(
            spec, batch_rows=batch_rows, carry=False, warnings=read
        ):
            if meta is None:
                meta = metadata(table)
            yield table
        if read is not None:  # the read ran to its end: its warnings, once per topic
            warned_once.append(True)
            warnings.extend(read)

    if dispatch.detect_format(spec.path) not in dispatch.ITERATORS:  # CSV, ULog, DataFlash
        whole, warned = dispatch.read_input(spec)
        warnings += warned
        meta = metadata(whole)
    while True:
        reads += 1
        try:
            floor, only = _first_pass(batches(), opts, half)
        except _Backwards:
            table, warned = dispatch.read_input(spec)
            warnings += warned
            warnings.append(
                f"{where}: time goes back across the log's chunks: read whole and sorted "
                "(memory not bounded by a batch)"
            )
            whole, half, meta = table, None, metadata(table)
            continue
        rate = floor.rate
        if floor.first_ns is None:
            warnings.append(f"{where} lacks a gyro or an accelerometer: not surveyed")
            return None
        if floor.n < 3:
            warnings.append(f"{where}: too few samples: not surveyed")
            return None
        if rate is None or floor.n < Rule.at(opts, rate).window:
            return Surveyed(
                _empty(opts), None if steps is None else _empty(opts), _frame(meta), reads
            )
        rule = Rule.at(opts, rate)
        if rule.half == floor.windowed.half:
            break
        half = rule.half  # the first batch's rate set another window: pass 1 again
        if only is not None:
            whole = only
    floors = floor.floors(opts)
    columns = 6 if steps is None else 12
    periods = PeriodPass(rule, floors, opts, columns, floor.reference)
    if only is not None and steps is None:
        periods.classified(*floor.kept())
        temp = _temperature(only)
        if temp is not None:
            periods.temperature(*temp)
    else:
        source = iter([only]) if only is not None else batches()
        if only is None:
            reads += 1
        for raw, corrected in _with_corrected(source, steps):
            temp = _temperature(raw)
            if temp is not None:
                periods.temperature(*temp)
            rows = _rows(raw)
            if rows is None:
                continue
            t, x = rows
            if corrected is not None:
                fixed = _rows(corrected)
                assert fixed is not None and len(fixed[0]) == len(t)
                x = np.column_stack([x, fixed[1]])
            periods.feed(t, x)
    found = periods.finish()
    start_ns, stop_ns = found.flat("start_ns"), found.flat("stop_ns")
    if not len(start_ns):
        warnings.append(
            f"{where}: no still period (none of {opts.min_duration_s:g} s and "
            f"{rule.min_samples} samples at its {rate:.3g} Hz): nothing measured"
        )
    acc = _join(found.acc, columns)
    tsum, tcount = found.flat("temp_sum").astype(np.float64), found.flat("temp_count")
    stats = figures(start_ns, stop_ns, acc, periods.reference, tsum, tcount, rule, opts)
    cal = None
    if steps is not None:
        cal = figures(
            start_ns, stop_ns, acc, periods.reference, tsum, tcount, rule, opts,
            columns=slice(6, 12),
        )  # fmt: skip
    return Surveyed(stats, cal, _frame(meta), reads)


def _frame(meta: dict[str, Any] | None) -> str | None:
    return ((meta or {}).get("frame_id") or {}).get("imu")


def _join(parts: list[Any], columns: int) -> Any:
    from imupipe.stages.survey.streaming import Acc

    return Acc.join(parts) if parts else Acc.empty(0, columns)


def _empty(opts: Any) -> dict[str, np.ndarray]:
    from imupipe.stages.survey.stats import figures
    from imupipe.stages.survey.streaming import Acc, Rule

    z = np.zeros(0, np.int64)
    return figures(z, z, Acc.empty(0, 6), np.zeros(6), np.zeros(0), z, Rule.at(opts, 1.0), opts)
