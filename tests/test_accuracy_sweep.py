"""Issue 25: the accuracy sweep's CI subset (``benchmarks/accuracy_sweep.py --quick``), one test
per family module of ``benchmarks/sweep_cases/``: every case an answer within the tolerance the
stage states, or a refusal naming the true cause; never a wrong answer or a wrong-cause refusal."""

from __future__ import annotations

import json
import sys
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import accuracy_sweep  # noqa: E402
from sweep_cases import VERDICTS, WRONG, modules  # noqa: E402

KEYS = {"family", "case", "outcome", "verdict", "error", "stated", "covered"}
FAMILIES = {m.FAMILY: m for m in modules()}


@cache
def quick_rows(family: str) -> list[dict]:
    """The quick subset of one family, run once per test session."""
    return FAMILIES[family].run(quick=True)


@pytest.mark.parametrize("module", modules(), ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_quick_sweep_has_no_wrong_answer_and_no_wrong_cause_refusal(module):
    rows = quick_rows(module.FAMILY)
    assert rows, f"{module.FAMILY}: no cases in the quick subset"
    for row in rows:
        assert set(row) >= KEYS, row  # a family may add its own columns (thermal: model, message)
        assert row["family"] == module.FAMILY
        assert row["verdict"] in VERDICTS
        assert row["outcome"] in ("answer", "refused")
        assert (row["outcome"] == "refused") == ("refusal" in row["verdict"])
        assert row["covered"] in (True, False, None)
    wrong = [f"{r['case']}: {r['verdict']}: {r['error']}" for r in rows if r["verdict"] in WRONG]
    assert not wrong, "\n".join(wrong)


def test_driver_prints_one_table_the_counts_and_the_coverage(capsys, tmp_path):
    path = tmp_path / "rows.json"
    code = accuracy_sweep.main(["--quick", "--family", "magnetometer", "--json", str(path)])
    out = capsys.readouterr().out
    assert code == 0
    rows = json.loads(path.read_text())
    assert rows and all(set(r) == KEYS for r in rows)
    assert all(r["covered"] is not None for r in rows if r["outcome"] == "answer")
    assert out.splitlines()[0].split()[:4] == ["family", "case", "outcome", "verdict"]
    assert "wrong answer 0, wrong-cause refusal 0" in out
    assert "truth inside the stated 95 % interval" in out


def test_thermal_quick_sweep_exercises_answers_and_refusals_that_name_what_to_record():
    rows = quick_rows("thermal")
    assert len(rows) >= 5
    assert {r["verdict"] for r in rows} == {"within tolerance", "right-cause refusal"}
    for r in rows:
        if r["outcome"] == "refused":
            assert "record" in r["message"] or "heat or cool" in r["message"], r["message"]
