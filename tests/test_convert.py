"""Issue 8, done-when: ``imupipe convert`` over a folder of logs plus a corrupt one.

Every good log's output holds all its messages with ``matrix @ (raw - offset)`` applied (checked
to 1e-9 against numpy on the simulated raw data, decoded with the ``mcap`` library's ROS 2
decoder), other topics carried over byte for byte; the corrupt log is named and has no output;
the exit status is non-zero; a second run rewrites nothing; the Ray engine (a local
``ray.init(num_cpus=2)``) writes the same messages as the local process pool.
"""

from __future__ import annotations

import collections
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader

from imupipe.pipeline.convert.engines import run_tasks
from imupipe.pipeline.convert.fleet import convert
from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.convert.plan import find_logs
from imupipe.pipeline.convert.settings import chain_sha256
from imupipe.pipeline.errors import ImupipeError
from imupipe.pipeline.simulate import simulate, write_log
from imupipe.pipeline.writers.mcap import msgdef, write_mcap
from imupipe.readers.dispatch import detect_format
from imupipe.readers.spec import RawMessage

from conftest import run_cli
from helpers import decode_mcap, mcap_attachments, stamps_ns, vec

M_ACCEL = [[1.01, 0.002, -0.001], [0.0, 0.99, 0.003], [0.001, 0.0, 1.02]]
M_GYRO = [[1.0, 0.001, 0.0], [-0.002, 1.0, 0.0], [0.0, 0.002, 0.998]]
M_MAG = [[0.9, 0.01, 0.0], [0.01, 1.1, 0.02], [0.0, 0.02, 0.95]]
CHAIN = [
    {"type": "accel_calibration", "sensor": "accel", "kind": "linear", "matrix": M_ACCEL,
     "offset": [0.05, -0.03, 0.08]},
    {"type": "gyro_calibration", "sensor": "gyro", "kind": "linear", "matrix": M_GYRO,
     "offset": [0.01, -0.02, 0.005]},
    {"type": "mag_calibration", "sensor": "mag", "kind": "linear", "matrix": M_MAG,
     "offset": [1.2e-5, -8.0e-6, 2.1e-5]},
]  # fmt: skip
SENSORS = {"gyro": ("angular_velocity", 1), "accel": ("linear_acceleration", 0)}


def _status_messages(n: int, t0: int) -> list[RawMessage]:
    """``/status`` std_msgs/String messages: a topic convert must carry over unchanged."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    string = ts.types["std_msgs/msg/String"]
    schema = msgdef("std_msgs/msg/String").encode()
    return [
        RawMessage(
            "/status", "std_msgs/msg/String", "ros2msg", schema, "cdr",
            bytes(ts.serialize_cdr(string(data=f"ok {i}"), "std_msgs/msg/String")),
            t0 + i * 100_000_000, t0 + i * 100_000_000,
        )
        for i in range(n)
    ]  # fmt: skip


def write_bag_with_rosbags(path: Path, table, ros: int, status: int) -> None:
    """A ROS ``ros`` (1 or 2, sqlite3) bag of the table's IMU samples plus ``status``
    std_msgs/String messages on ``/status``, written message by message with rosbags (a peer)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    t = ts.types
    if ros == 1:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, serialize = Writer(path, version=9), ts.serialize_cdr
    t_ns = table.column("t_ns").to_numpy()
    g = np.column_stack([table.column(f"gyro_{a}").to_numpy() for a in "xyz"])
    a = np.column_stack([table.column(f"accel_{a}").to_numpy() for a in "xyz"])
    imu_type, str_type = "sensor_msgs/msg/Imu", "std_msgs/msg/String"
    with writer:
        imu = writer.add_connection("/imu/data", imu_type, typestore=ts)
        txt = writer.add_connection("/status", str_type, typestore=ts)
        cov = np.zeros(9)
        for i, stamp in enumerate(t_ns.tolist()):
            time_ = t["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
            header = t["std_msgs/msg/Header"](
                **({"seq": i} if ros == 1 else {}), stamp=time_, frame_id="imu_link"
            )
            msg = t[imu_type](
                header=header,
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=cov,
                angular_velocity=t["geometry_msgs/msg/Vector3"](*g[i]),
                angular_velocity_covariance=cov,
                linear_acceleration=t["geometry_msgs/msg/Vector3"](*a[i]),
                linear_acceleration_covariance=cov,
            )
            writer.write(imu, stamp, serialize(msg, imu_type))
        for i in range(status):
            msg = t[str_type](data=f"ok {i}")
            writer.write(txt, int(t_ns[0]) + i * 10**8, serialize(msg, str_type))


def expected(table, sensor: str) -> np.ndarray:
    """numpy's ``matrix @ (raw - offset)`` on the simulated raw samples of ``sensor``."""
    step = next(s for s in CHAIN if s["sensor"] == sensor)
    cols = [f"{sensor}_{a}" for a in "xyz"]
    raw = np.column_stack([table.column(c).to_numpy(zero_copy_only=False) for c in cols])
    raw = raw[~np.isnan(raw).any(axis=1)]
    return (np.array(step["matrix"]) @ (raw - np.array(step["offset"])).T).T


def raw_messages(path: Path) -> dict[str, list[tuple[int, int, bytes]]]:
    """topic -> (log_time, publish_time, payload) in file order, undecoded."""
    out = collections.defaultdict(list)
    with open(path, "rb") as fh:
        for _, channel, msg in make_reader(fh).iter_messages(log_time_order=False):
            out[channel.topic].append((msg.log_time, msg.publish_time, bytes(msg.data)))
    return dict(out)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    logs = d / "logs"
    (logs / "site1").mkdir(parents=True)
    (logs / "site2").mkdir()
    static, _ = simulate("static", {"duration_s": 2.0, "rate_hz": 200.0}, seed=1)
    status = _status_messages(7, int(static.column("t_ns")[0].as_py()))
    write_mcap(logs / "a.mcap", static, carry_over=status)
    mag, _ = simulate("mag", {"duration_s": 3.0, "rate_hz": 50.0}, seed=2)
    write_log(logs / "site1" / "m.mcap", mag)
    ros, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 100.0, "temperature": None}, seed=3)
    write_bag_with_rosbags(logs / "site2" / "r1.bag", ros, 1, status=5)
    write_bag_with_rosbags(logs / "site2" / "r2", ros, 2, status=4)
    # a truncated copy: the footer, summary and the last chunk are gone
    data = (logs / "a.mcap").read_bytes()
    (logs / "corrupt.mcap").write_bytes(data[: len(data) // 2])
    cal = d / "calibration.json"
    cal.write_text(json.dumps({"imupipe_version": "test", "chain": CHAIN, "results": {}}))
    proc = run_cli(
        "convert",
        "--calibration",
        cal,
        "--out",
        d / "out",
        "--jobs",
        "2",
        "--parquet",
        logs,
    )
    tables = {"a": static, "site1/m": mag, "site2/r1": ros, "site2/r2": ros}
    return d, cal, tables, status, proc


def test_corrupt_log_is_named_and_has_no_output(fleet):
    d, _, _, _, proc = fleet
    assert proc.returncode == 1, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("imupipe: error:")]
    assert len(errors) == 1 and "corrupt.mcap" in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert "4 converted, 0 skipped (already done), 1 failed of 5 logs" in proc.stdout
    out = d / "out"
    assert not (out / "corrupt.mcap").exists()
    assert not (out / "parquet" / "corrupt.parquet").exists()
    assert [p.name for p in out.rglob("*.tmp")] == []
    lines = list(read_manifest(out))
    status = {Path(r["input"]).name: r["status"] for r in lines}
    assert status == {
        "a.mcap": "converted",
        "m.mcap": "converted",
        "r1.bag": "converted",
        "r2": "converted",
        "corrupt.mcap": "failed",
    }


def test_every_message_corrected(fleet):
    d, _, tables, status, _ = fleet
    for name, table in tables.items():
        out = d / "out" / f"{name}.mcap"
        topics = decode_mcap(out)
        imu = topics["/imu/data"]
        n_imu = int(np.count_nonzero(~np.isnan(table.column("gyro_x").to_numpy(False))))
        assert len(imu) == n_imu
        t_imu = table.filter(table.column("gyro_x").is_valid()).column("t_ns").to_numpy()
        np.testing.assert_array_equal(stamps_ns(imu), t_imu)
        for sensor, (field, _) in SENSORS.items():
            np.testing.assert_allclose(vec(imu, field), expected(table, sensor), rtol=0, atol=1e-9)
        if name == "site1/m":
            mag = topics["/imu/mag"]
            np.testing.assert_allclose(
                vec(mag, "magnetic_field"), expected(table, "mag"), rtol=0, atol=1e-9
            )
        elif name.startswith("site2"):
            # ROS 1 and ROS 2 carry-over, decoded from the output (ROS 1 converted to CDR)
            n = 5 if name.endswith("r1") else 4
            assert [m.data for _, m in topics["/status"]] == [f"ok {i}" for i in range(n)]
            assert {m.header.frame_id for _, m in imu} == {"imu_link"}
        else:
            assert len(topics["/imu/temperature"]) == table.num_rows
            # the carried-over topic: every message, byte for byte, at its times
            got = raw_messages(out)["/status"]
            assert got == [(m.log_time, m.publish_time, m.data) for m in status]
        attached = json.loads(mcap_attachments(out)["calibration.json"])
        assert attached["chain"] == CHAIN
        assert attached["conversion"]["calibration_sha256"] == chain_sha256({"chain": CHAIN})


def test_counts_read_without_the_attachments(fleet):
    """The worker's count check reads an MCAP's summary without its attachments (half of a
    short log's summary read, issue 39); the counts are the same, the attachment is left."""
    from imupipe.pipeline.convert.verify import mcap_counts, mcap_summary

    d, _, tables, _, _ = fleet
    out = d / "out" / "a.mcap"
    counts, attached = mcap_summary(out)
    assert attached is not None and attached["chain"] == CHAIN
    assert mcap_summary(out, attachments=False) == (counts, None)
    assert mcap_counts(out) == counts
    assert counts["/imu/data"] == tables["a"].num_rows


def test_manifest_and_parquet(fleet):
    d, _, tables, _, _ = fleet
    lines = {Path(r["input"]).stem: r for r in read_manifest(d / "out")}
    a = lines["a"]
    assert a["counts"] == {"/imu/data": 400, "/imu/temperature": 400, "/status": 7}
    assert a["calibration_sha256"] == chain_sha256({"chain": CHAIN})
    assert a["output"] == str(d / "out" / "a.mcap") and a["seconds"] > 0
    assert "corrupt.mcap" in lines["corrupt"]["error"]
    dataset = pq.read_table(d / "out" / "parquet" / "a.parquet")
    # one row per message of the log: 400 Imu and 400 Temperature messages
    assert dataset.num_rows == 800
    imu = dataset.filter(dataset.column("gyro_x").is_valid())
    np.testing.assert_array_equal(imu.column("t_ns").cast("int64"), tables["a"].column("t_ns"))
    np.testing.assert_allclose(
        np.column_stack([imu.column(f"accel_{a}").to_numpy() for a in "xyz"]),
        expected(tables["a"], "accel"),
        rtol=0,
        atol=1e-9,
    )
    meta = json.loads(dataset.schema.metadata[b"imupipe"])
    assert meta["format"] == "mcap" and meta["topics"]["imu"] == "/imu/data"
    assert meta["calibration"]["conversion"]["calibration_sha256"] == a["calibration_sha256"]
    assert meta["calibration"]["chain"] == CHAIN
    # every file has the same schema (one pyarrow dataset)
    assert pq.read_schema(d / "out" / "parquet" / "site1" / "m.parquet") == dataset.schema


def test_second_run_rewrites_nothing(fleet):
    d, cal, _, _, _ = fleet
    outputs = sorted((d / "out").rglob("*.mcap")) + sorted((d / "out").rglob("*.parquet"))
    before = {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in outputs}
    # the same command again: the good logs are skipped, the corrupt one fails again
    proc = run_cli("convert", "--calibration", cal, "--out", d / "out", "--parquet", d / "logs")
    assert proc.returncode == 1 and "corrupt.mcap" in proc.stderr, proc.stderr
    assert "0 converted, 4 skipped (already done), 1 failed of 5 logs" in proc.stdout
    assert {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in outputs} == before
    lines = list(read_manifest(d / "out"))[-5:]
    assert sorted(r["status"] for r in lines) == ["failed"] + ["skipped"] * 4


def test_new_calibration_or_force_converts_again(fleet, tmp_path):
    d, _, tables, _, _ = fleet
    out = tmp_path / "out"
    src = d / "logs" / "a.mcap"
    cal2 = tmp_path / "cal2.json"
    chain2 = [dict(CHAIN[0], offset=[0.0, 0.0, 0.0])]
    cal2.write_text(json.dumps({"chain": CHAIN}))
    first = convert([src], cal2, out, jobs=1)
    assert len(first.converted) == 1
    assert len(convert([src], cal2, out, jobs=1).skipped) == 1
    assert len(convert([src], cal2, out, jobs=1, force=True).converted) == 1
    cal2.write_text(json.dumps({"chain": chain2}))
    again = convert([src], cal2, out, jobs=1)
    assert len(again.converted) == 1
    imu = decode_mcap(out / "a.mcap")["/imu/data"]
    raw = np.column_stack([tables["a"].column(f"accel_{a}").to_numpy() for a in "xyz"])
    np.testing.assert_allclose(
        vec(imu, "linear_acceleration"), raw @ np.array(M_ACCEL).T, atol=1e-9
    )


def test_discovery_and_refusals(fleet, tmp_path):
    d, cal, _, _, _ = fleet
    logs = tmp_path / "logs"
    shutil.copytree(d / "logs", logs)
    (logs / "ros2bag").mkdir()
    (logs / "ros2bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (logs / "ros2bag" / "ros2bag_0.mcap").write_bytes(b"")
    (logs / "r.bag").write_bytes(b"")
    (logs / "notes.csv").write_text("x\n1\n")
    (logs / ".hidden.mcap").write_bytes(b"")
    (logs / "out").mkdir()
    (logs / "out" / "old.mcap").write_bytes(b"")
    found = {str(rel) for _, rel in find_logs([logs], logs / "out")}
    assert found == {
        "corrupt", "a", "site1/m", "site2/r1", "site2/r2", "r", "ros2bag"
    }  # fmt: skip
    assert "notes" in {str(rel) for _, rel in find_logs([logs], logs / "out", csv=True)}
    # an output that would replace its input is refused before anything is written
    proc = run_cli("convert", "--calibration", cal, "--out", logs, logs / "corrupt.mcap")
    assert proc.returncode == 2 and "would overwrite the input" in proc.stderr
    proc = run_cli("convert", "--calibration", tmp_path / "nope.json", "--out", logs / "o", logs)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "nope.json: no such file" in proc.stderr


def test_ray_engine_matches_local(fleet, tmp_path):
    ray = pytest.importorskip("ray")
    d, cal, _, _, _ = fleet
    logs = [d / "logs"]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        summary = convert(logs, cal, tmp_path / "out", engine="ray", parquet=True)
        # the failure model on Ray: a task whose worker dies is retried, then reported; bad
        # input is final at once
        outcomes = []
        tasks = [3, Path("/no/such.mcap")]
        run_tasks(os._exit, tasks[:1], outcomes.append, engine="ray", retries=1)
        run_tasks(detect_format, tasks[1:], outcomes.append, engine="ray", retries=1)
    finally:
        ray.shutdown()
    died, bad = outcomes
    assert died.attempts == 2 and "WorkerCrashedError" in died.error
    assert bad.attempts == 1 and bad.error == "/no/such.mcap: no such file or folder"
    assert [Path(p).name for p, _ in summary.failed] == ["corrupt.mcap"]
    assert len(summary.converted) == 4
    for name in ("a", "site1/m", "site2/r1", "site2/r2"):
        ours, theirs = tmp_path / "out" / f"{name}.mcap", d / "out" / f"{name}.mcap"
        assert raw_messages(ours) == raw_messages(theirs)
        assert pq.read_table(tmp_path / "out" / "parquet" / f"{name}.parquet").equals(
            pq.read_table(d / "out" / "parquet" / f"{name}.parquet")
        )


def test_csv_logs_with_a_config_mapping(tmp_path):
    """``--config`` maps a foreign CSV (deg/s, g, seconds); folders then yield .csv files."""
    table, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 100.0}, seed=4)
    t_s = table.column("t_ns").to_numpy() * 1e-9
    gyro = np.column_stack([table.column(f"gyro_{a}").to_numpy() for a in "xyz"])
    accel = np.column_stack([table.column(f"accel_{a}").to_numpy() for a in "xyz"])
    (tmp_path / "logs").mkdir()
    rows = np.column_stack([t_s, np.degrees(gyro), accel / 9.80665])
    np.savetxt(tmp_path / "logs" / "foreign.csv", rows, delimiter=",", fmt="%.17g",
               header="time,gx,gy,gz,ax,ay,az", comments="")  # fmt: skip
    (tmp_path / "read.toml").write_text(
        '[csv]\ntime = "time"\ntime_unit = "s"\ngyro = ["gx", "gy", "gz"]\ngyro_unit = "deg/s"\n'
        'accel = ["ax", "ay", "az"]\naccel_unit = "g"\n'
    )
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"chain": CHAIN}))
    summary = convert(
        [tmp_path / "logs"], cal, tmp_path / "out", config=tmp_path / "read.toml", jobs=1
    )
    assert not summary.failed and len(summary.converted) == 1
    imu = decode_mcap(tmp_path / "out" / "foreign.mcap")["/imu/data"]
    step = {s["sensor"]: s for s in CHAIN}
    pairs = [(gyro, "gyro", "angular_velocity"), (accel, "accel", "linear_acceleration")]
    for raw, sensor, field in pairs:
        want = (np.array(step[sensor]["matrix"]) @ (raw - step[sensor]["offset"]).T).T
        np.testing.assert_allclose(vec(imu, field), want, rtol=0, atol=1e-9)
    # without --config a folder's .csv files are not logs
    with pytest.raises(ImupipeError, match="no logs found"):
        convert([tmp_path / "logs"], cal, tmp_path / "out2", jobs=1)


def test_a_log_no_step_applies_to_is_said_so(tmp_path):
    """A magnetometer calibration converted onto a log without a magnetometer (robot_localization's
    bags hold only Imu) changes nothing: the log is written, and a warning says that no step of
    the calibration applied. A log some step applies to gets no such warning."""
    logs = tmp_path / "logs"
    logs.mkdir()
    imu_only, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 100.0}, seed=5)
    write_log(logs / "imu_only.mcap", imu_only)
    mag, _ = simulate("mag", {"duration_s": 1.0, "rate_hz": 50.0}, seed=6)
    write_log(logs / "with_mag.mcap", mag)
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"chain": [CHAIN[2]]}))
    summary = convert([logs], cal, tmp_path / "out", jobs=1, quiet=True)
    assert len(summary.converted) == 2
    warned = {Path(s.input).name: s.warnings for s in summary.converted}
    assert warned["with_mag.mcap"] == []
    assert warned["imu_only.mcap"] == [
        "no step of the calibration applies (it corrects mag; the log has no mag samples): "
        "written uncorrected"
    ]
    # on stderr each warning names its log (several logs convert at once)
    done = run_cli("convert", "--calibration", cal, "--out", tmp_path / "out2", logs)
    assert done.returncode == 0, done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        f"imupipe: warning: {logs / 'imu_only.mcap'}: no step of the calibration applies (it "
        "corrects mag; the log has no mag samples): written uncorrected"
    )
