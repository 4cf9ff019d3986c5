"""Fault injection: hostile calibrations through ``imupipe convert`` (issue 18).

Every calibration that cannot be applied must end in one line and exit 2 before any log is
touched, naming the file (and the step and field). Hypothesis writes chains of every shape; the
campaign's cases follow. Values are validated on load (finite, sizes, sensor names, nesting:
``pipeline/calibration_file.py``).
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import pytest
from faults import check, cli, snapshot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap

EYE = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> bytes:
    table, _ = simulate("static", {"duration_s": 0.5, "rate_hz": 100.0}, seed=1)
    path = tmp_path_factory.mktemp("cal") / "a.mcap"
    write_mcap(path, table)
    return path.read_bytes()


def convert_case(root: Path, log: bytes, doc: str | bytes, case: str) -> tuple[int, str]:
    (root / "a.mcap").write_bytes(log)
    cal = root / "cal.json"
    cal.write_bytes(doc if isinstance(doc, bytes) else doc.encode())
    before = snapshot(root)
    code, err = cli("convert", "--calibration", cal, "--out", root / "out", "-q", "-j", "1",
                    root / "a.mcap")  # fmt: skip
    check(case, code, err, root, before, [root / "out"])
    assert code in (0, 2), f"{case}: exit {code} (a calibration fault is not a log's failure)"
    return code, err


def linear(sensor="gyro", matrix=EYE, offset=(0.0, 0.0, 0.0), **extra) -> dict:
    return {"type": "t", "sensor": sensor, "kind": "linear", "matrix": matrix,
            "offset": list(offset), **extra}  # fmt: skip


finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False)
shapes = st.one_of(
    st.lists(st.lists(finite, min_size=3, max_size=3), min_size=3, max_size=3),
    st.lists(st.lists(finite, max_size=4), max_size=4),
    st.lists(finite, max_size=10),
    finite,
    st.text(max_size=3),
    st.none(),
)
entries = st.fixed_dictionaries(
    {"kind": st.sampled_from(["linear", "linear", "temperature", "nope"])},
    optional={
        "type": st.text(max_size=5),
        "sensor": st.sampled_from(["gyro", "accel", "mag"]),
        "matrix": shapes,
        "offset": shapes,
    },
)
documents = st.one_of(
    st.fixed_dictionaries({"chain": st.lists(entries, max_size=3)}),
    st.fixed_dictionaries({"chain": st.sampled_from([{}, "x", 3, None])}),
    st.lists(st.integers(), max_size=2),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(documents)
def test_generated_calibrations_keep_the_contract(log, doc):
    with tempfile.TemporaryDirectory() as d:
        convert_case(Path(d), log, json.dumps(doc), json.dumps(doc)[:200])


@pytest.mark.parametrize(
    "doc,needles",
    [
        ("{not json", ("cal.json", "JSON")),
        (b"\xff\xfe{}", ("cal.json",)),
        ('{"chain": {}}', ("cal.json", "no 'chain' list")),
        (json.dumps({"chain": [linear(matrix=[[1, 2], [3, 4]])]}), ("cal.json", "chain[0]")),
        (
            json.dumps({"chain": [{"type": "x", "sensor": "gyro", "kind": "spline"}]}),
            ("unknown step kind 'spline'",),
        ),
        ("[" * 100_000 + "]" * 100_000, ("cal.json", "nested")),
    ],
    ids=["not-json", "not-utf8", "chain-not-list", "matrix-2x2", "unknown-kind", "deep-nesting"],
)
def test_found_calibration_faults(tmp_path, log, doc, needles):
    code, err = convert_case(tmp_path, log, doc, str(needles))
    assert code == 2 and all(n in err for n in needles), err


@pytest.mark.parametrize(
    "step",
    [
        linear(matrix=[[math.nan, 0, 0], [0, 1, 0], [0, 0, 1]]),
        linear(offset=(math.inf, 0, 0)),
        linear(matrix=[[1e300, 0, 0], [0, 1e300, 0], [0, 0, 1e300]]),
        linear(sensor="foo"),
        linear(sensor="temperature"),
    ],
    ids=["nan-matrix", "inf-offset", "1e300-matrix", "unknown-sensor", "linear-on-temperature"],
)
def test_values_are_validated_on_load(tmp_path, log, step):
    code, err = convert_case(tmp_path, log, json.dumps({"chain": [step]}), str(step))
    assert code == 2 and "chain[0]" in err, err


def test_a_huge_calibration_is_refused(tmp_path, log):
    """A real calibration is kilobytes; one of 70 MB is refused before it is parsed."""
    doc = json.dumps({"chain": [linear()], "results": {"pad": "x" * 70_000_000}})
    code, err = convert_case(tmp_path, log, doc, "70 MB")
    assert code == 2 and "cal.json" in err, err
