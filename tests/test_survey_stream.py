"""Issue 30 item 4: a log's survey streams in batches (memory bounded by a batch, not a log) and
gives the figures of the whole-log computation: the same periods and the same numbers, a still
period spanning several batches found whole, stamps going back across batches caught.

The accumulators of :mod:`imupipe.stages.survey.streaming` are checked against direct formulas
(split anywhere, they give what one pass gives), the noise floor against ``numpy.quantile`` and
the batch-means standard error against the ten-batch rule it replaced."""

from __future__ import annotations

import dataclasses

import numpy as np
import pyarrow as pa
import pytest

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.pipeline.survey.scan import imu_topics
from imupipe.pipeline.survey.stream import survey_topic
from imupipe.readers.dispatch import iter_input, read_input
from imupipe.readers.spec import InputSpec
from imupipe.stages.static_detector import Intervals
from imupipe.stages.steps import steps_from_json
from imupipe.stages.survey.stats import StillOptions
from imupipe.stages.survey.streaming import (
    BATCHES,
    Acc,
    LogHistogram,
    cumsum0,
    extend,
)

FIGURES = (
    "gyro_bias",
    "gyro_bias_se",
    "gyro_noise",
    "accel_mean",
    "accel_mean_se",
    "accel_noise",
    "temperature",
)


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """One simulated fleet log (100 s at 100 Hz, still moments of 8 to 30 s) as MCAP."""
    root = tmp_path_factory.mktemp("stream")
    fleet, _ = simulate(
        "fleet", {"vehicles": 1, "imus": 1, "logs": 1, "log_s": 100.0, "events": False}, seed=3
    )
    write_log(root / "logs", fleet)
    (path,) = sorted((root / "logs").rglob("*.mcap"))
    imu, temp, mag = imu_topics(InputSpec(path=path))[0]
    return InputSpec(path=path, imu_topic=imu, temperature_topic=temp, mag_topic=mag)


def _survey(spec, batch_rows, steps=None):
    warnings: list[str] = []
    found = survey_topic(spec, StillOptions(), steps, warnings, batch_rows=batch_rows)
    assert found is not None, warnings
    return found, warnings


def _same(a, b):
    assert len(a["start_ns"]) > 0
    assert np.array_equal(a["start_ns"], b["start_ns"])
    assert np.array_equal(a["stop_ns"], b["stop_ns"])
    assert np.array_equal(a["samples"], b["samples"])
    np.testing.assert_allclose(a["gyro_bias"], b["gyro_bias"], rtol=0, atol=1e-12)
    for name in FIGURES:
        np.testing.assert_allclose(a[name], b[name], rtol=1e-9, err_msg=name)


def test_batches_give_the_whole_log_figures(log):
    assert sum(1 for _ in iter_input(log, batch_rows=2_000, carry=False)) >= 4
    whole, _ = _survey(log, 10**9)
    streamed, warnings = _survey(log, 2_000)
    assert whole.reads == 1 and streamed.reads == 2  # one read when the log is one batch
    assert not warnings
    _same(whole.stats, streamed.stats)
    assert np.isfinite(whole.stats["temperature"]).all()


def test_a_still_period_across_many_batches_is_found_whole(log):
    whole, _ = _survey(log, 10**9)
    longest = int(whole.stats["samples"].max())
    batch = 300
    assert longest > 4 * batch  # spans at least four batch boundaries
    streamed, _ = _survey(log, batch)
    _same(whole.stats, streamed.stats)


def test_calibrated_figures_streamed(log):
    chain = [
        {
            "type": "gyro_bias",
            "sensor": "gyro",
            "kind": "linear",
            "matrix": np.eye(3).tolist(),
            "offset": [1e-3, -2e-3, 3e-3],
        }
    ]
    steps = steps_from_json(chain)
    whole, _ = _survey(log, 10**9, steps)
    streamed, _ = _survey(log, 1_500, steps)
    assert whole.cal is not None and streamed.cal is not None
    _same(whole.cal, streamed.cal)
    np.testing.assert_allclose(
        whole.cal["gyro_bias"], whole.stats["gyro_bias"] - [1e-3, -2e-3, 3e-3], atol=1e-12
    )


def test_time_going_back_across_batches_is_caught(log, tmp_path):
    """Stamps of a block of rows moved back 20 s (log times in order): the batches come out
    each sorted but going back against each other; the topic is read whole and sorted instead,
    with a warning, and its figures are those of the sorted log."""
    from imupipe.pipeline.writers.mcap import write_mcap

    table, _ = read_input(log)
    t = table.column("t_ns").to_numpy().copy()
    if "log_time_ns" not in table.column_names:
        table = table.append_column("log_time_ns", pa.array(t))
    n = len(t)
    t[n // 2 : n // 2 + 1_000] -= 20_000_000_000
    table = table.set_column(table.column_names.index("t_ns"), "t_ns", pa.array(t))
    path = tmp_path / "back.mcap"
    write_mcap(path, table, chunk_bytes=16_000)
    spec = dataclasses.replace(log, path=path)
    starts = [int(b.column("t_ns")[0].as_py()) for b, _ in iter_input(spec, 500, carry=False)]
    ends = [int(b.column("t_ns")[-1].as_py()) for b, _ in iter_input(spec, 500, carry=False)]
    assert any(s < e for s, e in zip(starts[1:], ends[:-1], strict=True))
    streamed, warnings = _survey(spec, 500)
    assert any("time goes back" in w for w in warnings), warnings
    whole, _ = _survey(spec, 10**9)
    _same(whole.stats, streamed.stats)


# -- the accumulators ----------------------------------------------------------------------------


def _split_extend(values, intervals, m, cuts):
    """``extend`` over one interval fed in the pieces ``cuts`` gives (batch by batch)."""
    cs = cumsum0(values - values.mean(axis=0))
    acc = Acc.empty(1, values.shape[1])
    edges = [int(intervals.start[0]), *cuts, int(intervals.stop[0])]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        acc = extend(acc, cs, np.array([lo]), np.array([hi]), m)
    return acc


def test_extend_split_anywhere_equals_direct_formulas():
    rng = np.random.default_rng(4)
    x = rng.standard_normal((5_000, 2)) + [3.0, -1.0]
    iv = Intervals(np.array([137]), np.array([4_871]))
    length = 4_871 - 137
    m = 7
    one = _split_extend(x, iv, m, [])
    many = _split_extend(x, iv, m, sorted(rng.choice(np.arange(140, 4_860), 25, replace=False)))
    seg = x[137:4_871]
    # direct: mean, blocks of the least power of two s with length // s < 2B, cluster Allan
    s = 1
    while length // s >= 2 * BATCHES:
        s *= 2
    blocks = seg[: (length // s) * s].reshape(-1, s, 2).mean(axis=1)
    se = blocks.std(axis=0, ddof=1) / np.sqrt(len(blocks))
    clusters = seg[: (length // m) * m].reshape(-1, m, 2).mean(axis=1)
    adev = np.sqrt(np.mean(np.diff(clusters, axis=0) ** 2, axis=0) / 2)
    for acc in (one, many):
        assert acc.n[0] == length
        np.testing.assert_allclose(acc.mean()[0] + x.mean(axis=0), seg.mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(acc.batch_se()[0], se, rtol=1e-10)
        np.testing.assert_allclose(acc.adev()[0], adev, rtol=1e-10)


def test_batch_means_se_agrees_with_the_ten_batch_rule():
    """The streamed rule (10 to 19 blocks) against the rule it replaced (10 blocks of L // 10)
    on 400 periods of white noise: the two standard errors agree within their own scatter."""
    from imupipe.stages.survey.stats import batch_means_se

    rng = np.random.default_rng(5)
    length = 3_000
    starts = np.arange(400) * length
    iv = Intervals(starts, starts + length)
    x = rng.standard_normal((400 * length, 1))
    new = batch_means_se(x, iv)[:, 0]
    size = length // 10
    old = x.reshape(400, 10, size, 1).mean(axis=2).std(axis=1, ddof=1)[:, 0] / np.sqrt(10)
    truth = 1 / np.sqrt(length)
    assert np.median(new) == pytest.approx(truth, rel=0.1)
    assert np.median(old) == pytest.approx(truth, rel=0.1)
    assert np.median(new / old) == pytest.approx(1.0, rel=0.1)
    assert np.std(new / truth) < np.std(old / truth)  # more blocks: a steadier estimate


def test_histogram_quantile_matches_numpy():
    rng = np.random.default_rng(6)
    v = np.exp(rng.normal(-12, 2, 100_000))
    hist = LogHistogram()
    for part in np.array_split(v, 7):
        hist.add(part)
    for q in (0.02, 0.1, 0.5):
        assert hist.quantile(q) == pytest.approx(np.quantile(v, q), rel=2.5e-3)
    empty = LogHistogram()
    empty.add(np.array([0.0, 0.0, 1.0, np.inf]))
    assert empty.quantile(0.02) == 0.0 and empty.n == 3


def test_a_gap_that_changes_the_window_reads_pass_one_again(log, tmp_path):
    """The first batch's rate sets pass 1's window; 30 s missing from the log lower the log's
    rate so that its window differs: pass 1 runs again, the figures are the whole log's."""
    from imupipe.pipeline.writers.mcap import write_mcap
    from imupipe.stages.survey.streaming import Rule

    table, _ = read_input(log)
    t = table.column("t_ns").to_numpy()
    cut = (t > t[0] + 40_000_000_000) & (t < t[0] + 70_000_000_000)
    table = table.filter(pa.array(~cut))
    path = tmp_path / "gap.mcap"
    write_mcap(path, table)
    spec = dataclasses.replace(log, path=path)
    imu = t[~cut][table.column("gyro_x").is_valid().to_numpy(zero_copy_only=False)]
    first = Rule.at(StillOptions(), (1_999) / ((imu[1_999] - imu[0]) * 1e-9))
    overall = Rule.at(StillOptions(), (len(imu) - 1) / ((imu[-1] - imu[0]) * 1e-9))
    assert first.half != overall.half  # the case this test is for
    whole, _ = _survey(spec, 10**9)
    streamed, _ = _survey(spec, 2_000)
    assert whole.reads == 1 and streamed.reads == 3
    _same(whole.stats, streamed.stats)


def test_stamps_back_and_repeated_within_a_batch_reach_the_manifest(log, tmp_path):
    """A stamp going back within a batch (two neighbours swapped) and a stamp repeated: the
    reader's warnings reach the survey's manifest, once per topic with the counts of the whole
    read, whether the log is streamed in batches or read as one."""
    import json

    from imupipe.pipeline.survey.scan import survey
    from imupipe.pipeline.writers.mcap import write_mcap

    table, _ = read_input(log)
    t = table.column("t_ns").to_numpy().copy()
    if "log_time_ns" not in table.column_names:
        table = table.append_column("log_time_ns", pa.array(t))
    imu = np.flatnonzero(table.column("gyro_x").is_valid().to_numpy(zero_copy_only=False))
    a, b = imu[len(imu) // 3], imu[len(imu) // 3 + 1]
    t[a], t[b] = t[b], t[a]  # goes back by one period, inside a batch
    c, d = imu[2 * len(imu) // 3], imu[2 * len(imu) // 3 + 1]
    t[d] = t[c]  # a stamp repeated
    table = table.set_column(table.column_names.index("t_ns"), "t_ns", pa.array(t))
    (root := tmp_path / "logs").mkdir()
    write_mcap(root / "one.mcap", table, chunk_bytes=16_000)
    spec = dataclasses.replace(log, path=root / "one.mcap")
    whole, expected = read_input(spec)
    assert [w for w in expected if "out of header time order" in w]
    assert [w for w in expected if "repeat the previous header stamp" in w]
    lines = {}
    for name, rows in (("streamed", 500), ("one batch", 10**9)):
        survey([root], tmp_path / name, jobs=1, rerun=False, quiet=True, batch_rows=rows)
        manifest = (tmp_path / name / "manifest.jsonl").read_text().splitlines()
        (line,) = [json.loads(m) for m in manifest if json.loads(m).get("warnings") is not None]
        lines[name] = line["warnings"]
    assert not any("time goes back" in w for w in lines["streamed"])  # streamed, not re-read
    streamed = [w for w in lines["streamed"] if "time order" in w or "repeat the" in w]
    assert streamed == [w for w in expected if "time order" in w or "repeat the" in w]
    assert sorted(streamed) == sorted(
        w for w in lines["one batch"] if "time order" in w or "repeat the" in w
    )
    # convert streams the same way: its manifest carries the same warnings
    from conftest import run_cli

    cal = tmp_path / "identity.json"
    step = {"type": "gyro_bias", "sensor": "gyro", "kind": "linear", "matrix": np.eye(3).tolist()}
    step["offset"] = [0.0] * 3
    cal.write_text(json.dumps({"chain": [step]}))
    proc = run_cli("convert", "--calibration", cal, "--out", tmp_path / "conv", root / "one.mcap")
    assert proc.returncode == 0, proc.stderr
    (line,) = [
        json.loads(m) for m in (tmp_path / "conv" / "manifest.jsonl").read_text().splitlines()
    ]
    assert [w for w in line["warnings"] if "time order" in w or "repeat the" in w] == streamed


def test_split_gyro_and_accel_topics_are_one_imu(tmp_path):
    """A RealSense-style camera (``imupipe simulate camera``: /camera/gyro/sample at 400 Hz,
    /camera/accel/sample at 250 Hz) is one IMU of the survey, not two: one device whose topic
    names both, its gyro bias and ``|a| - g`` those simulated (the accelerometer interpolated
    onto the gyro's stamps), in an MCAP and a ROS 1 bag alike."""
    import pyarrow.parquet as pq

    from imupipe.pipeline.simulate import simulate, write_log
    from imupipe.pipeline.survey.scan import survey
    from imupipe.readers.topics import split_pairs

    table, truth = simulate("camera", {"duration_s": 40.0}, seed=3)
    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("cam_a.mcap", "cam_b.bag"):
        write_log(logs / name, table)
    survey([logs], tmp_path / "out", jobs=1, quiet=True, rerun=False)
    rows = pq.read_table(tmp_path / "out" / "survey.parquet").to_pylist()
    assert {r["device_id"] for r in rows} == {"logs:/camera/gyro/sample+/camera/accel/sample"}, {
        r["device_id"] for r in rows
    }
    assert sorted(r["log"] for r in rows) == ["cam_a", "cam_b"]
    g = np.asarray(truth["gravity"])
    for r in rows:
        bias = np.array([r[f"gyro_bias_{a}"] for a in "xyz"])
        se = np.array([r[f"gyro_bias_se_{a}"] for a in "xyz"])
        assert np.all(np.abs(bias - truth["gyro"]["bias"]) < 5 * se + 1e-5), (bias, se)
        expected = np.linalg.norm(np.asarray(truth["accel"]["bias"]) + g) - np.linalg.norm(g)
        assert r["accel_norm_error"] == pytest.approx(expected, abs=2e-3)
    # several cameras: each gyro with the accelerometer of its own name
    two = ["/cam1/gyro/sample", "/cam1/accel/sample", "/cam2/gyro/sample", "/cam2/accel/sample"]
    assert split_pairs(two) == [
        {"gyro": "/cam1/gyro/sample", "accel": "/cam1/accel/sample"},
        {"gyro": "/cam2/gyro/sample", "accel": "/cam2/accel/sample"},
    ]
    assert split_pairs(["/imu/data", "/cam1/gyro/sample", "/cam2/accel/sample"]) == []
