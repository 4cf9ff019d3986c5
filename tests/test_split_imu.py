"""A gyro and an accelerometer on topics of their own (``gyro_topic``, ``accel_topic``): a
RealSense-style camera's ``/camera/gyro/sample`` (400 Hz) and ``/camera/accel/sample`` (250 Hz).

Checked against the reference readers (``mcap`` + ``mcap_ros2`` for MCAP, ``rosbags`` for ROS 1
and ROS 2 bags): every message of each topic reaches the table with its stamp and vector, the
corrected log keeps both topics message for message, and the Allan noise densities of both
sensors come from their own samples."""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import pytest

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.readers.dispatch import read_input
from imupipe.readers.errors import ImupipeError
from imupipe.readers.spec import InputSpec
from imupipe.readers.table import (
    imu_pairs,
    make_table,
    metadata,
    sensor,
    sensor_mask,
    split_imu,
)

GYRO, ACCEL = "/camera/gyro/sample", "/camera/accel/sample"
FORMATS = ("cam.mcap", "cam.bag", "cam_ros2", "cam_mcap_bag")


def reference(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """topic -> (header stamps ns, angular_velocity (n, 3), linear_acceleration (n, 3)) of its
    messages in log order, decoded by the reference libraries."""
    out: dict[str, list] = {}

    def add(topic: str, msg) -> None:  # noqa: ANN001
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        w, a = msg.angular_velocity, msg.linear_acceleration
        out.setdefault(topic, []).append((stamp, (w.x, w.y, w.z), (a.x, a.y, a.z)))

    if path.suffix == ".mcap":
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        with open(path, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, channel, _, msg in reader.iter_decoded_messages(log_time_order=True):
                add(channel.topic, msg)
    else:
        from rosbags.highlevel import AnyReader

        with AnyReader([path]) as reader:
            for conn, _, data in reader.messages():
                msg = reader.deserialize(data, conn.msgtype)
                if not hasattr(msg.header.stamp, "nanosec"):  # ROS 1 time
                    msg.header.stamp.nanosec = msg.header.stamp.nsec
                add(conn.topic, msg)
    return {
        t: (
            np.array([m[0] for m in v], np.int64),
            np.array([m[1] for m in v]),
            np.array([m[2] for m in v]),
        )
        for t, v in out.items()
    }


@pytest.fixture(scope="module")
def camera(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object, dict]:
    folder = tmp_path_factory.mktemp("camera")
    table, truth = simulate("camera", {"duration_s": 8.0}, seed=1)
    for name in FORMATS[:3]:
        write_log(folder / name, table)
    from imupipe.pipeline.writers.bag import write_ros2_bag

    write_ros2_bag(folder / FORMATS[3], table, storage="mcap")
    return folder, table, truth


@pytest.mark.parametrize("name", FORMATS)
def test_each_sensor_from_its_topic_as_the_reference_reads_it(camera, name: str) -> None:
    folder, simulated, _ = camera
    table, warnings = read_input(InputSpec(path=folder / name))
    assert any("gyro from /camera/gyro/sample" in w for w in warnings)  # chosen, and said so
    meta = metadata(table)
    assert meta["topics"] == {"gyro": GYRO, "accel": ACCEL}
    assert split_imu(table)
    ref = reference(folder / name)
    assert set(ref) == {GYRO, ACCEL}
    g, a = sensor(table, "gyro"), sensor(table, "accel")
    assert len(g) == len(ref[GYRO][0]) == 3200 and len(a) == len(ref[ACCEL][0]) == 2000
    # no row holds both; nothing else is in the table
    assert not np.any(sensor_mask(table, "gyro") & sensor_mask(table, "accel"))
    assert table.num_rows == len(g) + len(a)
    np.testing.assert_array_equal(g.t_ns, ref[GYRO][0])
    np.testing.assert_array_equal(g.values, ref[GYRO][1])
    np.testing.assert_array_equal(a.t_ns, ref[ACCEL][0])
    np.testing.assert_array_equal(a.values, ref[ACCEL][2])
    # the zeros of the vector a topic does not carry are not samples
    assert not np.any(ref[GYRO][2]) and not np.any(ref[ACCEL][1])
    np.testing.assert_array_equal(g.values, sensor(simulated, "gyro").values)


def test_topics_named_explicitly_and_the_mistakes(camera) -> None:
    folder, _, _ = camera
    path = folder / "cam.mcap"
    spec = InputSpec(path=path, name="cam", gyro_topic=GYRO, accel_topic=ACCEL)
    table, warnings = read_input(spec)
    assert not any("gyro from" in w for w in warnings)  # chosen by the user: nothing to say
    assert len(sensor(table, "gyro")) == 3200
    only = read_input(dataclasses.replace(spec, accel_topic=None))[0]
    assert len(sensor(only, "gyro")) == only.num_rows == 3200
    assert sensor_mask(only, "accel").sum() == 0
    with pytest.raises(ImupipeError, match="sets imu_topic and gyro_topic"):
        read_input(dataclasses.replace(spec, imu_topic=GYRO))
    with pytest.raises(ImupipeError, match="gyro_topic '/nope' is not in the log"):
        read_input(dataclasses.replace(spec, gyro_topic="/nope"))
    with pytest.raises(ImupipeError, match="name the same topic"):
        read_input(dataclasses.replace(spec, accel_topic=GYRO))
    # one topic named as imu_topic: that topic alone, as before
    one = read_input(InputSpec(path=path, imu_topic=ACCEL))[0]
    assert metadata(one)["topics"] == {"imu": ACCEL}


def test_a_split_topic_that_carries_the_other_vector_is_named(tmp_path: Path) -> None:
    table, _ = simulate("camera", {"duration_s": 2.0}, seed=2)
    write_log(tmp_path / "full.mcap", table)
    # the same log, each topic read as a whole Imu topic and written back with both vectors
    whole = [
        read_input(InputSpec(path=tmp_path / "full.mcap", imu_topic=t))[0] for t in (GYRO, ACCEL)
    ]
    t0 = whole[0].column("t_ns").to_numpy()
    rng = np.random.default_rng(0)
    filled = make_table(
        t0,
        gyro=sensor(whole[0], "gyro").values,
        accel=rng.normal(size=(len(t0), 3)),
        metadata={"topics": {"imu": "/camera/gyro/sample"}},
    )
    write_log(tmp_path / "gyro_with_accel.mcap", filled)
    spec = InputSpec(path=tmp_path / "gyro_with_accel.mcap", gyro_topic=GYRO)
    _, warnings = read_input(spec)
    assert any(
        f"topic {GYRO} (gyro_topic): {len(t0)} of {len(t0)} messages carry a "
        "linear_acceleration that is not zeros" in w
        for w in warnings
    )


def test_several_imu_topics_not_a_pair_still_ask() -> None:
    from imupipe.readers.topics import select_topics, split_pair

    assert split_pair([ACCEL, GYRO]) == {"gyro": GYRO, "accel": ACCEL}
    realsense_viewer = ["/device_0/sensor_2/Accel_0/imu/data", "/device_0/sensor_2/Gyro_0/imu/data"]
    assert split_pair(realsense_viewer) == {
        "gyro": realsense_viewer[1],
        "accel": realsense_viewer[0],
    }
    assert split_pair(["/imu0", "/imu1"]) is None
    assert split_pair([ACCEL, GYRO, "/camera/imu"]) is None
    types = {"/imu0": "sensor_msgs/msg/Imu", "/imu1": "sensor_msgs/msg/Imu"}
    with pytest.raises(ImupipeError, match="several sensor_msgs/msg/Imu topics.*gyro_topic"):
        select_topics("log.mcap", InputSpec(path=Path("log.mcap")), types)


@pytest.mark.parametrize("name", ["cam.mcap", "cam.bag", "cam_ros2"])
def test_corrected_log_keeps_both_topics(camera, tmp_path: Path, name: str) -> None:
    """Counts in == counts out per topic, each message back on its topic with its stamp, the
    vector it carries corrected, the other zeros as it came."""
    from imupipe.pipeline.writers.mcap import write_mcap
    from imupipe.stages.steps import LinearStep

    folder, _, _ = camera
    table, _ = read_input(InputSpec(path=folder / name))
    step = LinearStep("test", "gyro", np.eye(3), np.array([0.002, -0.003, 0.001]))
    corrected = step.apply(table)
    counts = write_mcap(tmp_path / "out.mcap", corrected)
    assert counts == {GYRO: 3200, ACCEL: 2000}
    ref_in, ref_out = reference(folder / name), reference(tmp_path / "out.mcap")
    for topic in (GYRO, ACCEL):
        np.testing.assert_array_equal(ref_out[topic][0], ref_in[topic][0])
    np.testing.assert_allclose(ref_out[GYRO][1], ref_in[GYRO][1] - step.offset, atol=1e-15)
    np.testing.assert_array_equal(ref_out[ACCEL][2], ref_in[ACCEL][2])
    assert not np.any(ref_out[GYRO][2]) and not np.any(ref_out[ACCEL][1])
    again, _ = read_input(InputSpec(path=tmp_path / "out.mcap"))
    assert metadata(again)["topics"] == {"gyro": GYRO, "accel": ACCEL}


def test_convert_keeps_both_topics(camera, tmp_path: Path) -> None:
    from imupipe.pipeline.convert.verify import counts_by_topic

    folder, _, _ = camera
    table, _ = read_input(InputSpec(path=folder / "cam.bag"))
    assert counts_by_topic(table) == {GYRO: 3200, ACCEL: 2000}


def test_imu_pairs_interpolates_explicitly() -> None:
    t_g = np.arange(0, 1_000_000_000, 2_500_000)  # 400 Hz
    t_a = np.arange(1_000_000, 1_000_000_000, 4_000_000)  # 250 Hz, offset
    t = np.concatenate([t_g, t_a])
    order = np.argsort(t, kind="stable")
    is_g = (np.arange(len(t)) < len(t_g))[order]
    slope = np.array([1.0, 2.0, 3.0])
    accel = np.where(is_g[:, None], 0.0, (t[order] * 1e-9)[:, None] * slope)
    gyro = np.where(is_g[:, None], np.full((len(t), 3), 0.5), 0.0)
    table = make_table(
        t[order],
        gyro=gyro,
        accel=accel,
        valid={"gyro": is_g, "accel": ~is_g},
        metadata={"topics": {"gyro": GYRO, "accel": ACCEL}},
    )
    g, a, note = imu_pairs(table)
    assert note is not None and "interpolated linearly onto the gyro's stamps" in note
    assert len(g) == len(a) == len(t_g)
    np.testing.assert_array_equal(g.t_ns, t_g)
    inside = (t_g >= t_a[0]) & (t_g <= t_a[-1])
    np.testing.assert_allclose(a.values[inside], (t_g[inside] * 1e-9)[:, None] * slope)
    held = ~inside & (t_g >= t_a[0] - 4_000_000) & (t_g <= t_a[-1] + 4_000_000)
    assert held.sum() == 2  # the gyro's first stamp, 1 ms before the first accel, and its last
    np.testing.assert_allclose(a.values[t_g < t_a[0]], (t_a[0] * 1e-9) * slope[None, :])
    assert np.isnan(a.values[~inside & ~held]).all()  # never extrapolated further
    g2, a2, _ = imu_pairs(table, on="accel")
    np.testing.assert_array_equal(a2.t_ns, t_a)
    np.testing.assert_allclose(g2.values[np.isfinite(g2.values).all(axis=1)], 0.5)
    # an Imu whose rows hold both: as they are, nothing said
    both = make_table(t_g, gyro=np.ones((len(t_g), 3)), accel=np.ones((len(t_g), 3)))
    assert imu_pairs(both)[2] is None and not split_imu(both)


# -- a dead axis ---------------------------------------------------------------------------------
DEAD = {"zero": 0.0, "constant": 0.25, "nan": float("nan")}
STAGES = [
    # (stage, scenario, its params, the sensor with the dead axis, the other axes fitted;
    # None: a constant axis is a valid reading for the stage, which fits it as it is, and only
    # an axis with no finite value is named)
    ("allan", "static", {"duration_s": 600.0, "rate_hz": 100.0}, "gyro", True),
    ("allan", "static", {"duration_s": 600.0, "rate_hz": 100.0}, "accel", True),
    ("gyro_bias", "static", {"duration_s": 60.0}, "gyro", None),
    ("accel_calibration", "poses", {}, "accel", False),
    ("gyro_calibration", "poses", {}, "gyro", False),
    ("gyro_calibration", "poses", {}, "accel", False),
    ("mag_calibration", "mag", {}, "mag", False),
    ("temperature", "thermal", {}, "gyro", None),
    (
        "thermal_soak",
        "thermal_soak",
        {"levels": [0.0, 25.0, 50.0], "soak_s": 300.0},
        "accel",
        False,
    ),
]


def _dead(table, name: str, value: float):  # noqa: ANN001, ANN202
    import pyarrow as pa

    from imupipe.readers.table import SENSOR_COLUMNS

    col = SENSOR_COLUMNS[name][2]
    column = table.column(col).combine_chunks()
    filled = np.full(len(column), value)
    idx = table.schema.get_field_index(col)
    return table.set_column(idx, col, pa.array(filled, mask=~sensor_mask(table, name)))


@functools.cache
def _simulated(scenario: str, params: str):  # noqa: ANN202 - one session per scenario
    return simulate(scenario, json.loads(params), seed=4)[0]


@pytest.mark.parametrize("kind", list(DEAD))
@pytest.mark.parametrize(("stage", "scenario", "params", "name", "others"), STAGES)
def test_a_dead_axis_is_named(stage, scenario, params, name, others, kind) -> None:  # noqa: ANN001
    """A constant, all-zero or all-NaN z axis: where each axis is fitted on its own (allan),
    the others with a warning naming input, sensor and axis, nothing for it; where the fit
    couples the axes, a failed check naming them (the CLI's exit 2 unless accepted), never a
    traceback; where a constant is a valid reading (gyro_bias, temperature), only an axis
    without a finite value is named."""
    import imupipe
    from imupipe.stages.errors import FitError

    table = _dead(_simulated(scenario, json.dumps(params, sort_keys=True)), name, DEAD[kind])
    fit = getattr(imupipe, stage)
    if others is None:  # gyro_bias (its mean), temperature (a zero drift on that axis)
        if kind == "nan":
            with pytest.raises(FitError, match=rf"input 'table': .*{name} z \(no finite value\)"):
                fit(table)
        else:
            fit(table, accept_failed_checks=True)
        return
    if not others:
        with pytest.raises(FitError, match=rf"input 'table': .*{name}\w* z .*dead axis"):
            fit(table)
        if kind != "nan":  # a failed quality check: kept when asked, never a traceback
            try:
                out = fit(table, accept_failed_checks=True)
            except FitError:
                return
            assert any("dead axis" in w for w in out.failed_checks)
        return
    with pytest.warns(UserWarning, match=rf"input 'table': {name} z \(.*\): a dead axis"):
        out = fit(table, accept_failed_checks=True)
    metrics = out.results["metrics"]
    assert f"{name} z" in metrics["dead_axes"]
    assert set(out.results[name]) == {"x", "y"}  # nothing fitted for z
    other = "accel" if name == "gyro" else "gyro"
    assert set(out.results[other]) == {"x", "y", "z"}


def test_allan_of_a_camera_each_sensor_at_its_own_rate() -> None:
    """20 simulated minutes of a camera's gyro (400 Hz) and accelerometer (250 Hz) on clocks of
    their own: each noise density within 10 % of the truth, each from its own samples."""
    import imupipe

    table, truth = simulate("camera", {"duration_s": 1200.0}, seed=3)
    with pytest.warns(UserWarning, match="sampled apart"):
        out = imupipe.allan(table)
    per = out.results["metrics"]["per_sensor"]
    assert per["gyro"]["samples"] == 480_000 and per["accel"]["samples"] == 300_000
    assert per["gyro"]["rate_hz"] == pytest.approx(400.0)
    assert per["accel"]["rate_hz"] == pytest.approx(250.0)
    assert out.results["metrics"]["rate_hz"] == pytest.approx(400.0)  # the gyro's, for exports
    for name in ("gyro", "accel"):
        for i, axis in enumerate("xyz"):
            assert out.results[name][axis]["N"] == pytest.approx(truth[name]["N"][i], rel=0.10)


def test_exports_of_an_allan_fit_with_a_dead_axis() -> None:
    """Kalibr, VINS and imu_utils files from the axes fitted: the dead one is left out."""
    import imupipe
    from imupipe.pipeline.exports.common import noise
    from imupipe.pipeline.exports.imu_utils import imu_utils_doc
    from imupipe.pipeline.exports.kalibr import noise_yaml

    table, _ = simulate("static", {"duration_s": 600.0, "rate_hz": 100.0}, seed=5)
    with pytest.warns(UserWarning, match="gyro z"):
        results = imupipe.allan(_dead(table, "gyro", 0.0), accept_failed_checks=True).results
    gyro = noise(results, "gyro")
    assert gyro is not None and gyro.density_axis in ("x", "y")
    doc = imu_utils_doc(results)
    assert "z-axis" not in doc["Gyr"] and "z-axis" in doc["Acc"]
    assert "gyroscope_noise_density" in noise_yaml("allan", results)


def test_one_topic_of_the_two_read_alone(camera) -> None:
    """gyro_topic without accel_topic: the gyro alone, its Allan fit and its bias (the stages
    that need the accelerometer too find it absent, as in a CSV without it)."""
    import imupipe

    folder, _, truth = camera
    table = imupipe.read(folder / "cam.mcap", gyro_topic=GYRO)
    out = imupipe.allan(table, accept_failed_checks=True)
    assert set(out.results["metrics"]["per_sensor"]) == {"gyro"} and "accel" not in out.results
    table = imupipe.read(folder / "cam.bag", accel_topic=ACCEL)
    out = imupipe.allan(table, accept_failed_checks=True)
    assert out.results["metrics"]["per_sensor"]["accel"]["samples"] == 2000


def test_multi_position_on_two_clocks() -> None:
    """A multi-position session whose gyro and accelerometer samples alternate (each sensor at
    half the rate, on stamps of its own): accel_calibration fits the accelerometer's own
    samples, gyro_calibration the gyro's with the accelerometer interpolated onto them (said
    so); both land where the one-clock session does."""
    import imupipe

    table, _ = simulate("poses", seed=1)
    g, a = sensor(table, "gyro"), sensor(table, "accel")
    even = np.arange(len(g)) % 2 == 0
    split = make_table(
        g.t_ns,
        gyro=g.values,
        accel=a.values,
        valid={"gyro": even, "accel": ~even},
        metadata={"topics": {"gyro": GYRO, "accel": ACCEL}},
    )
    for stage in ("accel_calibration", "gyro_calibration"):
        fit = getattr(imupipe, stage)
        one = fit(table).results
        if stage == "gyro_calibration":
            with pytest.warns(UserWarning, match="interpolated linearly onto the gyro's stamps"):
                two = fit(split).results
        else:
            two = fit(split).results
        np.testing.assert_allclose(two["scale"], one["scale"], atol=2e-4)
        np.testing.assert_allclose(two["bias"], one["bias"], atol=2e-3)
