"""A cut-off MCAP or ROS 1 log (issue #36): refused by default, as the SPEC's error behaviour
says; with ``--read-truncated`` read up to the cut by ``convert`` and ``survey`` alike (one path:
the readers' ``iter_input``), every complete message before the cut read, with a warning naming
the file and the byte where the damage starts, on the terminal and in the manifest.

The reference for what can be recovered is another tool: the mcap library's ``StreamReader``
(every Message record before the first damaged record, chunked or not) for MCAP; for ROS 1,
rosbags' index of the whole bag (the messages of every chunk whose record ends before the cut:
rosbags itself refuses a bag without its index).
"""

from __future__ import annotations

import collections
import json
import subprocess
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers import dispatch
from imupipe.readers.errors import ReadError
from imupipe.readers.spec import InputSpec

from conftest import run_cli

CUTS = (0.35, 0.6, 0.8, 0.95)
"""Where the copies are cut, as a fraction of the file's bytes."""


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 120 s static log at 100 Hz (several chunks) as MCAP and as a ROS 1 bag, and a
    calibration with one gyro-bias step."""
    d = tmp_path_factory.mktemp("truncated")
    table, _ = simulate("static", {"duration_s": 120.0, "rate_hz": 100.0}, seed=7)
    out = {}
    for suffix in ("mcap", "bag"):
        write_log(d / f"full.{suffix}", table)
        out[suffix] = d / f"full.{suffix}"
    chain = [  # fmt: skip
        {
            "type": "gyro_bias",
            "sensor": "gyro",
            "kind": "linear",
            "matrix": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            "offset": [1e-3, -2e-3, 5e-4],
        },
    ]
    cal = d / "calibration.json"
    cal.write_text(json.dumps({"imupipe_version": "test", "chain": chain, "results": {}}))
    out["cal"] = cal
    return out


def _cut(full: Path, fraction: float, folder: Path) -> Path:
    data = full.read_bytes()
    path = folder / f"cut{int(fraction * 100)}{full.suffix}"
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


def reference_counts(full: Path, cut: Path) -> dict[str, int]:
    """Messages per topic that another tool recovers from ``cut`` (see the module docstring)."""
    counts: collections.Counter[str] = collections.Counter()
    if full.suffix == ".mcap":
        from mcap.records import Channel, Message
        from mcap.stream_reader import StreamReader

        topics: dict[int, str] = {}
        with open(cut, "rb") as fh:
            try:
                for record in StreamReader(fh).records:
                    if isinstance(record, Channel):
                        topics[record.id] = record.topic
                    elif isinstance(record, Message):
                        counts[topics[record.channel_id]] += 1
            except Exception:  # noqa: BLE001 - the damaged record: the stream ends there
                pass
        return dict(counts)
    from rosbags.rosbag1 import Reader

    size = cut.stat().st_size
    with Reader(full) as bag:
        topic = {c.id: c.topic for c in bag.connections}
        for info in bag.chunk_infos:
            chunk = bag.chunks[info.pos]
            if chunk.datapos + chunk.datasize <= size:
                for cid, n in info.connection_counts.items():
                    counts[topic[cid]] += n
    return dict(counts)


def read_counts(path: Path) -> tuple[dict[str, int], list[str]]:
    """Messages per topic read by the shared path (``iter_input``, small batches)."""
    spec = InputSpec(path=path, read_truncated=True)
    warnings: list[str] = []
    counts: collections.Counter[str] = collections.Counter()
    for table, raw in dispatch.iter_input(spec, batch_rows=500, warnings=warnings):
        streams = {"imu": "gyro_x", "temperature": "temperature"}
        for stream, column in streams.items():
            if column in table.column_names:
                counts[stream] += table.num_rows - table.column(column).null_count
        for message in raw:
            counts[message.topic] += 1
    return dict(counts), warnings


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
@pytest.mark.parametrize("fraction", CUTS)
def test_reader_reads_every_complete_message_before_the_cut(logs, tmp_path, fmt, fraction):
    cut = _cut(logs[fmt], fraction, tmp_path)
    ref = reference_counts(logs[fmt], cut)
    full = reference_counts(logs[fmt], logs[fmt])
    assert 0 < sum(ref.values()) < sum(full.values())
    counts, warnings = read_counts(cut)
    assert sorted(counts.values()) == sorted(ref.values()), (counts, ref)
    [warning] = [w for w in warnings if "truncated" in w]
    assert str(cut) in warning and "read up to the cut" in warning
    assert f"{cut.stat().st_size} bytes" in warning
    with pytest.raises(ReadError, match="truncated .*--read-truncated"):
        list(dispatch.iter_input(InputSpec(path=cut), batch_rows=500))


@pytest.fixture(scope="module")
def converted(logs, tmp_path_factory):
    """fmt -> (the cut copies at CUTS, the output folder, the process) of one ``imupipe convert
    --read-truncated`` of them, run once for the convert and the survey tests below."""
    done = {}

    def get(fmt: str) -> tuple[list[Path], Path, subprocess.CompletedProcess]:
        if fmt not in done:
            d = tmp_path_factory.mktemp(f"converted_{fmt}")
            (d / "in").mkdir()
            cuts = [_cut(logs[fmt], f, d / "in") for f in CUTS]
            out = d / "out"
            proc = run_cli(
                "convert", "--read-truncated", "--calibration", logs["cal"], "--out", out, *cuts
            )
            done[fmt] = (cuts, out, proc)
        return done[fmt]

    return get


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_convert_reads_up_to_the_cut(logs, converted, tmp_path, fmt):
    cuts, out, proc = converted(fmt)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    records = {Path(r["input"]): r for r in read_manifest(out)}
    for cut in cuts:
        ref = reference_counts(logs[fmt], cut)
        rec = records[cut]
        assert rec["status"] == "converted"
        assert rec["counts"] == ref, (cut, rec["counts"], ref)
        assert rec["messages"] == sum(ref.values())
        assert any("read up to the cut" in w for w in rec["warnings"]), rec["warnings"]
        lines = [
            line
            for line in proc.stderr.splitlines()
            if line.startswith(f"imupipe: warning: {cut}: truncated")
        ]
        assert len(lines) == 1, proc.stderr
    # without the option: refused, one line naming the option, no output
    plain = tmp_path / "plain"
    proc = run_cli("convert", "--calibration", logs["cal"], "--out", plain, cuts[1])
    assert proc.returncode == 1
    [line] = [x for x in proc.stderr.splitlines() if x.startswith("imupipe: error:")]
    assert str(cuts[1]) in line and "--read-truncated" in line
    assert not list(plain.glob("*.mcap"))


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_survey_reads_up_to_the_cut(logs, converted, tmp_path, fmt):
    """The survey of a cut copy reads what convert reads: its one still period (the log is
    static) ends within the messages recovered, and holds almost all of them."""
    from mcap.reader import make_reader

    all_cuts, converted, proc = converted(fmt)  # convert's output of the same cut copies
    assert proc.returncode == 0, proc.stderr
    cuts = [cut for cut, f in zip(all_cuts, CUTS, strict=True) if f in (0.6, 0.95)]
    out = tmp_path / "survey"
    proc = run_cli("survey", "--read-truncated", "--no-rerun", *cuts, "--out", out)
    assert proc.returncode == 0, proc.stderr
    records = {Path(r["input"]): r for r in read_manifest(out)}
    table = pq.read_table(out / "survey.parquet").to_pylist()
    for cut in cuts:
        rec = records[cut]
        assert rec["status"] == "surveyed"
        assert any("read up to the cut" in w and str(cut) in w for w in rec["warnings"])
        assert sum(x.startswith(f"imupipe: warning: {cut}: truncated") for x in
                   proc.stderr.splitlines()) == 1, proc.stderr  # fmt: skip
        with open(converted / f"{cut.stem}.mcap", "rb") as fh:
            stamps = [
                m.log_time
                for _, ch, m in make_reader(fh).iter_messages()
                if ch.topic.endswith("imu/data") or ch.topic.endswith("/imu")
            ]
        ref_imu = min(reference_counts(logs[fmt], cut).values())
        assert len(stamps) >= ref_imu
        [period] = [r for r in table if r["log"] == cut.stem]
        assert 0.9 * ref_imu <= period["samples"] <= ref_imu + 1
        assert period["stop_ns"] <= max(stamps) + 20_000_000
    proc = run_cli("survey", "--no-rerun", cuts[0], "--out", tmp_path / "plain")
    assert proc.returncode == 1
    [line] = [x for x in proc.stderr.splitlines() if x.startswith("imupipe: error:")]
    assert str(cuts[0]) in line and "--read-truncated" in line


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_cut_before_the_first_complete_chunk_is_one_line(logs, tmp_path, fmt):
    cut = _cut(logs[fmt], 0.05, tmp_path)
    assert reference_counts(logs[fmt], cut) == {}
    with pytest.raises(ReadError, match=r"truncated .* before its first complete \w+: nothing"):
        read_counts(cut)


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_inspect_describes_what_is_read_up_to_the_cut(logs, tmp_path, fmt):
    cut = _cut(logs[fmt], 0.6, tmp_path)
    proc = run_cli("inspect", "--read-truncated", "--json", cut)
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    counts = {topic: t["count"] for topic, t in info["topics"].items()}
    assert counts == reference_counts(logs[fmt], cut)
    assert any("read up to the cut" in w for w in info["warnings"])
    proc = run_cli("inspect", cut)
    assert proc.returncode == 2 and "--read-truncated" in proc.stderr


def test_default_settings_hash_is_the_one_before_the_option():
    """Outputs converted before ``read_truncated`` existed stay "already done"."""
    import dataclasses
    import hashlib

    from imupipe.pipeline.convert.settings import settings_sha256

    spec = InputSpec(path=Path("x.mcap"))
    old = dataclasses.asdict(spec)  # the read keys of 0.3.0, whose hashes manifests hold
    old = {k: old[k] for k in ("csv", "imu_topic", "mag_topic", "temperature_topic", "time")}
    canonical = json.dumps(old, sort_keys=True, default=str, separators=(",", ":"))
    assert settings_sha256(spec) == hashlib.sha256(canonical.encode()).hexdigest()
    assert settings_sha256(dataclasses.replace(spec, read_truncated=True)) != settings_sha256(spec)


def test_ros2_bag_with_a_cut_off_mcap_storage_file(tmp_path):
    """A ROS 2 bag (mcap storage) whose file is cut off: its ``metadata.yaml`` counts what the
    file no longer holds; convert reads the file up to the cut, its counts the reference's."""
    import shutil

    from bag_variants import write_ros2

    full = write_ros2(tmp_path / "full", "mcap", "none", n=6000)
    [storage] = full.glob("*.mcap")
    bags, cal = [], tmp_path / "calibration.json"
    cal.write_text(json.dumps({"imupipe_version": "test", "chain": [], "results": {}}))
    for fraction in (0.6, 0.9):
        bag = tmp_path / f"cut{int(fraction * 100)}"
        shutil.copytree(full, bag)
        _cut(storage, fraction, tmp_path).replace(bag / storage.name)
        bags.append(bag)
    out = tmp_path / "out"
    proc = run_cli("convert", "--read-truncated", "--calibration", cal, "--out", out, *bags)
    assert proc.returncode == 0, proc.stderr
    records = {Path(r["input"]): r for r in read_manifest(out)}
    for bag in bags:
        ref = reference_counts(storage, bag / storage.name)
        assert 0 < sum(ref.values()) < sum(reference_counts(storage, storage).values())
        assert records[bag]["counts"] == ref
        assert any("read up to the cut" in w for w in records[bag]["warnings"])
    proc = run_cli("convert", "--calibration", cal, "--out", tmp_path / "plain", bags[0])
    assert proc.returncode == 1 and "truncated" in proc.stderr
