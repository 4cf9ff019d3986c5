"""Issue 16: a calibration that knows its sensor. ``calibration.json`` is checked on load (one
line naming the entry and the field), a linear step written by hand as the chain format shows it
is accepted (by ``load_calibration`` and by ``imupipe convert``), and every entry written by
``run`` records where it was fitted."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.pipeline import calibration_file
from imupipe.pipeline.calibration_file import load_calibration
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.stages.errors import CalibrationError
from imupipe.stages.steps import LinearStep

from conftest import run_cli
from helpers import decode_mcap, vec

HAND = {
    "type": "accel_calibration",
    "sensor": "accel",
    "matrix": [[1.01, 0.0, 0.0], [0.0, 0.99, 0.0], [0.0, 0.0, 1.0]],
    "offset": [0.1, -0.2, 0.3],
}


def _write(tmp_path, chain, **extra) -> str:
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({"chain": chain, **extra}))
    return path


def test_hand_written_linear_step_is_accepted(tmp_path):
    doc, steps = load_calibration(_write(tmp_path, [HAND]))
    assert isinstance(steps[0], LinearStep) and steps[0].kind == "linear"
    np.testing.assert_array_equal(steps[0].matrix, HAND["matrix"])


def test_convert_applies_a_hand_written_step(tmp_path):
    table, _ = simulate("static", {"duration_s": 2.0, "rate_hz": 50.0}, seed=2)
    write_log(tmp_path / "log.mcap", table)
    cal = _write(tmp_path, [HAND])
    proc = run_cli(
        "convert", "--calibration", cal, "--out", tmp_path / "out", tmp_path / "log.mcap"
    )
    assert proc.returncode == 0, proc.stderr
    raw = vec(decode_mcap(tmp_path / "log.mcap")["/imu/data"], "linear_acceleration")
    got = vec(decode_mcap(tmp_path / "out" / "log.mcap")["/imu/data"], "linear_acceleration")
    np.testing.assert_allclose(got, (raw - HAND["offset"]) @ np.array(HAND["matrix"]).T)


@pytest.mark.parametrize(
    "entry, message",
    [
        (
            {**HAND, "matrix": [[1, 0], [0, 1]]},
            "chain[0].matrix: 3x3 numbers expected, got [[1, 0], [0, 1]]",
        ),
        ({**HAND, "offset": [0, "a", 0]}, "chain[0].offset: 3 numbers expected"),
        ({**HAND, "offset": [0, True, 0]}, "chain[0].offset: 3 numbers expected"),
        ({**HAND, "matrix": [[1, 2, 3], [2, 4, 6], [0, 0, 1]]}, "chain[0].matrix: singular"),
        ({**HAND, "sensor": "baro"}, "chain[0].sensor: unknown sensor 'baro'"),
        ({**HAND, "sensor": "temperature"}, "chain[0].sensor: a linear step corrects gyro"),
        ({**HAND, "kind": "spline"}, "chain[0].kind: unknown step kind 'spline'"),
        ({**HAND, "type": 3}, "chain[0].type: a string expected"),
        ({"type": "x", "sensor": "gyro"}, "chain[0]: no 'kind', and not a linear step"),
        ([1, 2], "chain[0]: an object expected"),
        ({**HAND, "fitted_on": "robot 1"}, "chain[0].fitted_on: an object expected"),
    ],
)
def test_bad_entries_are_one_line(tmp_path, entry, message):
    with pytest.raises(CalibrationError) as err:
        load_calibration(_write(tmp_path, [HAND, entry][1:]))
    assert message in str(err.value) and str(tmp_path) in str(err.value)
    assert "\n" not in str(err.value)


def test_non_finite_numbers_are_named(tmp_path):
    path = tmp_path / "cal.json"
    path.write_text(
        '{"chain": [{"type": "t", "sensor": "gyro", "matrix": [[1,0,0],[0,1,0],'
        '[0,0,1]], "offset": [0, NaN, 0]}]}'
    )
    with pytest.raises(CalibrationError, match=r"chain\[0\]\.offset\[1\]: not a finite number"):
        load_calibration(path)


def test_document_level_checks(tmp_path, monkeypatch):
    deep = tmp_path / "deep.json"
    deep.write_text('{"chain": [], "x": ' + "[" * 200 + "]" * 200 + "}")
    with pytest.raises(CalibrationError, match="nested deeper than 64"):
        load_calibration(deep)
    very = tmp_path / "very.json"
    very.write_text('{"chain": [], "x": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(CalibrationError, match="nested deeper"):
        load_calibration(very)
    with pytest.raises(CalibrationError, match="no such file"):
        load_calibration(tmp_path / "missing.json")
    (tmp_path / "bin.json").write_bytes(b'{"chain": ["\xff"]}')
    with pytest.raises(CalibrationError, match="not UTF-8"):
        load_calibration(tmp_path / "bin.json")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(CalibrationError, match="no 'chain' list"):
        load_calibration(tmp_path / "list.json")
    monkeypatch.setattr(calibration_file, "MAX_BYTES", 10)
    with pytest.raises(CalibrationError, match="at most 10 bytes"):
        load_calibration(_write(tmp_path, [HAND]))


def test_run_records_where_each_step_was_fitted(tmp_path):
    table, _ = simulate("static", {"duration_s": 20.0, "rate_hz": 100.0}, seed=4)
    write_log(tmp_path / "still.mcap", table)
    (tmp_path / "cfg.toml").write_text(
        '[inputs.still]\npath = "still.mcap"\n\n[[stages]]\ntype = "gyro_bias"\n\n'
        '[output]\ndir = "out"\nrerun = false\napply_to = []\n'
    )
    proc = run_cli("run", tmp_path / "cfg.toml")
    assert proc.returncode == 0, proc.stderr
    doc, steps = load_calibration(tmp_path / "out" / "calibration.json")
    where = doc["chain"][0]["fitted_on"]
    t = table.column("t_ns").to_numpy()
    assert where == {
        "input": "still",
        "path": str(tmp_path / "still.mcap"),  # resolved against the config's folder
        "format": "mcap",
        "topics": {"imu": "/imu/data", "temperature": "/imu/temperature"},
        "frame_id": where["frame_id"],
        "t_start_ns": int(t.min()),
        "t_end_ns": int(t.max()),
        "rate_hz": where["rate_hz"],
    }
    assert where["rate_hz"]["imu"] == pytest.approx(100.0, rel=1e-6)
    assert set(where["frame_id"]) == {"imu", "temperature"}
    assert steps[0].to_json()["fitted_on"] == where  # kept through a load


def test_calibration_json_is_standard_json():
    """Non-finite floats (a fit's metric that overflowed) are written as null, at any depth;
    the text parses with a strict reader and loads back."""
    import math

    from imupipe.pipeline.calibration_file import calibration_json, parse_calibration

    doc = {
        "chain": [],
        "results": {"s": {"metrics": {"std": [math.inf, -math.inf, 1.5], "rms": math.nan}}},
        "tuple": (1.0, math.nan),
    }
    text = calibration_json(doc)

    def refuse(constant):
        raise ValueError(constant)

    strict = json.loads(text, parse_constant=refuse)
    assert strict["results"]["s"]["metrics"] == {"std": [None, None, 1.5], "rms": None}
    assert strict["tuple"] == [1.0, None]
    assert parse_calibration(text, "x")["chain"] == []
    assert doc["results"]["s"]["metrics"]["std"][0] == math.inf  # the document is not changed


@pytest.mark.parametrize(
    "conversion",
    [
        {"calibration_sha256": "ab" * 32, "input": "/logs/ä b.mcap", "input_size": 123},
        {},
        [1, {"x": [float("nan"), 2.5]}],
        "just text",
    ],
)
def test_calibration_json_of_a_conversion_is_the_plain_text(conversion):
    """convert's documents (a calibration, then a last ``conversion`` key) reuse the text of the
    calibration from call to call; the text is exactly ``json.dumps(..., indent=2)``'s, every
    time, also after the calibration changed."""
    import math

    from imupipe.pipeline.calibration_file import _finite, calibration_json

    base = {
        "imupipe_version": "0.3",
        "chain": [{"type": "gyro_calibration", "matrix": [[1.0, 0.0], [0.0, 1.0]]}],
        "results": {"s": {"metrics": {"rms": math.inf, "names": ["é", "\n"]}}, "empty": {}},
    }
    for doc in (
        {**base, "conversion": conversion},
        {**base, "conversion": conversion},  # from the kept text
        {**base, "results": {}, "conversion": conversion},  # another calibration
        {"conversion": conversion},
        {"conversion": conversion, "chain": []},  # not the last key
    ):
        plain = json.dumps(_finite(doc), indent=2, allow_nan=False) + "\n"
        assert calibration_json(doc) == plain
