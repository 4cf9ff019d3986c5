"""Fault injection: damaged logs through ``imupipe convert`` and ``imupipe inspect`` (issue 18).

An MCAP (with a carried-over topic), a ROS 1 bag and a ROS 2 bag are truncated, bit-flipped and
zeroed in places (seeded); the whole lot is converted in one fleet run. Every damaged log is
either converted completely (its output verified against the log's own index) or named in one
line; the good logs beside them are converted as if the damaged ones were not there; nothing is
left behind; ``inspect`` on each ends in its output or one line.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from faults import TALLY, check, cli, snapshot
from test_convert import CHAIN, _status_messages, raw_messages, write_bag_with_rosbags

from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap


def damage(data: bytes, how: str, rng: np.random.Generator) -> bytes:
    buf = bytearray(data)
    if how == "truncate":
        return bytes(buf[: int(rng.integers(1, len(buf)))])
    if how == "flip":
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(0, len(buf)))
            buf[i] ^= 1 << int(rng.integers(0, 8))
        return bytes(buf)
    if how == "zero":
        i = int(rng.integers(0, len(buf)))
        buf[i : i + 4096] = bytes(len(buf[i : i + 4096]))
        return bytes(buf)
    raise ValueError(how)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp("damaged")
    clean, logs = root / "clean", root / "logs"
    clean.mkdir()
    logs.mkdir()
    table, _ = simulate("static", {"duration_s": 3.0, "rate_hz": 200.0}, seed=1)
    write_mcap(clean / "a.mcap", table, carry_over=_status_messages(9, int(table["t_ns"][0].as_py())),
               chunk_bytes=1 << 14)  # fmt: skip
    ros, _ = simulate("static", {"duration_s": 1.0, "rate_hz": 100.0, "temperature": None}, seed=2)
    write_bag_with_rosbags(clean / "r1.bag", ros, 1, status=5)
    write_bag_with_rosbags(clean / "r2", ros, 2, status=4)
    rng = np.random.default_rng(18)
    variants = []
    for how in ("truncate", "flip", "zero"):
        for k in range(4):
            name = f"a_{how}{k}.mcap"
            (logs / name).write_bytes(damage((clean / "a.mcap").read_bytes(), how, rng))
            variants.append(name)
        for k in range(2):
            name = f"r1_{how}{k}.bag"
            (logs / name).write_bytes(damage((clean / "r1.bag").read_bytes(), how, rng))
            variants.append(name)
            bag = logs / f"r2_{how}{k}"
            shutil.copytree(clean / "r2", bag)
            db3 = next(bag.glob("*.db3"))
            db3.write_bytes(damage(db3.read_bytes(), how, rng))
            variants.append(bag.name)
    for name in ("a.mcap", "r1.bag"):
        shutil.copy(clean / name, logs / name)
    shutil.copytree(clean / "r2", logs / "r2")
    cal = root / "cal.json"
    cal.write_text(json.dumps({"chain": CHAIN}))
    before = snapshot(root)
    code, err = cli("convert", "--calibration", cal, "--out", root / "out", "-j", "2", "-q",
                    "--retries", "0", logs)  # fmt: skip
    return root, variants, code, err, before


def test_damaged_logs_in_a_fleet(fleet):
    root, variants, code, err, before = fleet
    check("damaged fleet", code, err, root, before, [root / "out"], fleet=True)
    lines = {Path(r["input"]).name: r for r in read_manifest(root / "out")}
    assert set(lines) == set(variants) | {"a.mcap", "r1.bag", "r2"}
    for good in ("a", "r1", "r2"):  # the good logs, converted as if alone
        assert (
            lines[good + (".mcap" if good == "a" else ".bag" if good == "r1" else "")]["status"]
            == "converted"
        )
    failed = [n for n, r in lines.items() if r["status"] == "failed"]
    errors = [line for line in err.splitlines() if line.startswith("imupipe: error: ")]
    assert len(errors) == len(failed) and (code == 1) == bool(failed)
    for name in failed:
        assert any(name in e for e in errors), name
        assert "Traceback" not in lines[name]["error"]
    converted = [n for n, r in lines.items() if r["status"] == "converted" and n in variants]
    identical = sum(
        raw_messages(root / "out" / (Path(n).stem + ".mcap"))
        == raw_messages(root / "out" / (n.split("_")[0] + ".mcap"))
        for n in converted
    )
    TALLY["damaged logs"] += len(variants)
    TALLY["damaged: refused with one line"] += len(failed)
    TALLY["damaged: converted, same messages as the clean log"] += identical
    TALLY["damaged: converted, messages differ (the damage was in the data)"] += (
        len(converted) - identical
    )
    for n in converted:  # a converted log is complete: counts verified against its own index
        assert lines[n]["messages"] > 0


def test_inspect_damaged_logs(fleet):
    root, variants, *_ = fleet
    for name in variants:
        before = snapshot(root / "logs")
        code, err = cli("inspect", root / "logs" / name)
        check(f"inspect {name}", code, err, root / "logs", before, [])
