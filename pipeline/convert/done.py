"""Skip-if-done: whether a log's output already holds it converted the same way.

The corrected MCAP carries the applied calibration as the attachment ``calibration.json``,
extended with a ``conversion`` record: the SHA-256 of the chain, of the read settings and the
input's size. A log whose output holds the same three (and whose Parquet file exists when asked
for) is skipped unless ``--force``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from imupipe.pipeline.convert.plan import LogTask
from imupipe.pipeline.convert.verify import mcap_summary


def input_size(path: Path) -> int:
    """Bytes of a log file, or of every file of a log folder."""
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


def existing_output(task: LogTask, size: int) -> dict[str, int] | None:
    """The output's counts when it already holds this log converted with this calibration and these
    settings (and the Parquet file exists when asked for); else None."""
    if not task.output.is_file() or (task.parquet is not None and not task.parquet.is_file()):
        return None
    try:
        summary = mcap_summary(task.output)
    except Exception:  # noqa: BLE001 - an unreadable output is simply not done
        return None
    return same_conversion(summary, task, size)


def same_conversion(
    summary: tuple[dict[str, int], dict[str, Any] | None] | None, task: LogTask, size: int
) -> dict[str, int] | None:
    """The counts of an output's ``summary`` (:func:`mcap_summary`) when its attached record
    names this calibration, these settings and an input of ``size`` bytes; else None."""
    if summary is None or summary[1] is None:
        return None
    conversion = summary[1].get("conversion", {})
    same = (
        conversion.get("calibration_sha256") == task.calibration_sha256
        and conversion.get("settings_sha256") == task.settings_sha256
        and conversion.get("input_size") == size
    )
    return summary[0] if same else None
