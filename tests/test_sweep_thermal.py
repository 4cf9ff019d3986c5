"""Issue 25, thermal family of the accuracy sweep (``benchmarks/sweep_cases/thermal.py``), quick
subset: with default options every case is answered within the tolerance the stage states
against the simulated truth, or refused naming the true cause and what to record. No confident
wrong answer, no refusal that blames the wrong cause."""

from __future__ import annotations

import importlib.util
import sys

from conftest import REPO


def load_family():
    path = REPO / "benchmarks" / "sweep_cases" / "thermal.py"
    spec = importlib.util.spec_from_file_location("sweep_case_thermal", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_quick_thermal_sweep_has_no_wrong_outcome():
    family = load_family()
    rows = family.run(quick=True)
    assert family.FAMILY == "thermal"
    assert len(rows) >= 5
    keys = {"family", "case", "outcome", "verdict", "error", "stated", "covered"}
    for row in rows:
        assert keys <= set(row), row
        assert row["outcome"] in ("answer", "refused")
        assert row["verdict"] in (
            "within tolerance", "right-cause refusal", "wrong answer", "wrong-cause refusal",
        )  # fmt: skip
    bad = [r for r in rows if r["verdict"] in ("wrong answer", "wrong-cause refusal")]
    assert not bad, bad
    # both outcomes are exercised: answers within the stated tolerance and right refusals
    verdicts = {r["verdict"] for r in rows}
    assert verdicts == {"within tolerance", "right-cause refusal"}, verdicts
    # the refusals name what to record instead
    for r in rows:
        if r["outcome"] == "refused":
            assert "record" in r["message"] or "heat or cool" in r["message"], r["message"]
