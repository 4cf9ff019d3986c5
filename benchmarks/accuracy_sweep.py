"""Accuracy sweep (issue 25): the sessions users record, with truths that differ from the fitted
forms where real sensors do, through each stage with its default options.

Every module of ``benchmarks/sweep_cases/`` is a family (``FAMILY``, ``run(quick)``; see
``sweep_cases/__init__.py`` for the row and the verdicts). Prints one table (family, case,
outcome, verdict, error against the truth, stated 95 % uncertainty, covered), the count of each
verdict, and the coverage of the stated 95 % intervals (target 90 to 99 %). Exits 1 when any
case is a wrong answer or a wrong-cause refusal.

Usage: ``python benchmarks/accuracy_sweep.py [--quick] [--family NAME ...] [--json PATH]``
(``--quick``: the subset CI runs, short recordings and low rates; ``--json``: the rows, uncut,
for the docs' tables).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sweep_cases import VERDICTS, WRONG, modules  # noqa: E402

COLUMNS = ("family", "case", "outcome", "verdict", "error", "stated", "covered")


def table(rows: list[dict]) -> str:
    """The rows as one fixed-width text table."""
    cells = [[str(r.get(c, "")) if r.get(c) is not None else "-" for c in COLUMNS] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(COLUMNS)]
    widths = [min(w, 70) for w in widths]
    lines = ["  ".join(c.ljust(w) for c, w in zip(COLUMNS, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    for row in cells:
        lines.append("  ".join(v[:w].ljust(w) for v, w in zip(row, widths, strict=True)))
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """Counts per verdict and the coverage of the stated 95 % intervals."""
    counts = {v: sum(r["verdict"] == v for r in rows) for v in VERDICTS}
    judged = [r["covered"] for r in rows if r["covered"] is not None]
    cover = (
        f"{sum(judged)} of {len(judged)} ({100 * sum(judged) / len(judged):.0f} %; target 90-99 %)"
        if judged
        else "no stated intervals"
    )
    parts = [f"{len(rows)} cases: " + ", ".join(f"{v} {n}" for v, n in counts.items())]
    parts.append(f"truth inside the stated 95 % interval: {cover}")
    for family in dict.fromkeys(r["family"] for r in rows):
        mine = [r for r in rows if r["family"] == family]
        n = {v: sum(r["verdict"] == v for r in mine) for v in VERDICTS}
        cov = [r["covered"] for r in mine if r["covered"] is not None]
        parts.append(
            f"  {family}: {len(mine)} cases, within tolerance {n['within tolerance']}, "
            f"right-cause refusal {n['right-cause refusal']}, "
            f"wrong {n['wrong answer'] + n['wrong-cause refusal']}; covered "
            + (f"{sum(cov)} of {len(cov)}" if cov else "-")
        )
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="the CI subset")
    p.add_argument("--family", nargs="*", help="only these families")
    p.add_argument("--json", type=Path, help="also write the rows to this JSON file (whole)")
    args = p.parse_args(argv)
    rows: list[dict] = []
    for mod in modules():
        if args.family and mod.FAMILY not in args.family:
            continue
        t0 = time.perf_counter()
        got = mod.run(args.quick)
        rows += got
        print(
            f"[{mod.FAMILY}: {len(got)} cases in {time.perf_counter() - t0:.1f} s]", file=sys.stderr
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print(table(rows))
    print()
    print(summary(rows))
    return 1 if any(r["verdict"] in WRONG for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
