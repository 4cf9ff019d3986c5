"""Issue 37: peak memory of ``imupipe convert`` on a large log read through a field mapping.

Writes ``--messages`` ``px4_msgs/msg/SensorCombined`` messages (ROS 2 CDR in an MCAP, zstd
chunks of 1 MB, 200 Hz) and a JSON text topic beside them (carried over), then runs
``imupipe convert --config read.toml --batch-rows R --jobs 1`` in a fresh Python (the mapping
in ``[fields]``, a gyro bias as the calibration) and prints its seconds, its own peak RSS
(``VmHWM``) and the messages per topic in and out (counts in == counts out).

    PYTHONPATH=.shim python benchmarks/bench_mapped_memory.py [--messages 2000000]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_mapped_fields import SENSOR_COMBINED  # noqa: E402
from proc_memory import run_measured  # noqa: E402

TOPIC = "/fmu/out/sensor_combined"


def write(path: Path, n: int) -> dict[str, int]:
    from mcap.writer import CompressionType, Writer

    rng = np.random.default_rng(0)
    t = 10**18 + np.arange(n, dtype=np.int64) * 5_000_000
    sc = np.zeros((n, 52), np.uint8)
    sc[:, 1] = 1
    sc[:, 4:12] = (t // 1000).astype("<u8").view(np.uint8).reshape(n, 8)
    sc[:, 12:24] = rng.normal(0, 0.01, (n, 3)).astype("<f4").view(np.uint8).reshape(n, 12)
    accel = rng.normal(0, 0.05, (n, 3)) + [0, 0, 9.81]
    sc[:, 32:44] = accel.astype("<f4").view(np.uint8).reshape(n, 12)
    notes = 0
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        w.start()
        sid = w.register_schema("px4_msgs/msg/SensorCombined", "ros2msg", SENSOR_COMBINED.encode())
        cid = w.register_channel(TOPIC, "cdr", sid)
        js = w.register_schema("note", "jsonschema", b'{"type": "object"}')
        note = w.register_channel("/note", "json", js)
        for i in range(n):
            ti = int(t[i])
            w.add_message(cid, log_time=ti, data=sc[i].tobytes(), publish_time=ti)
            if i % 200 == 0:
                w.add_message(note, log_time=ti + 1, data=b'{"i": %d}' % i, publish_time=ti + 1)
                notes += 1
        w.finish()
    return {TOPIC: n, "/note": notes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--messages", type=int, default=2_000_000)
    ap.add_argument("--batch-rows", type=int, default=200_000)
    args = ap.parse_args()
    from mcap.reader import make_reader

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        log = folder / "px4.mcap"
        counts_in = write(log, args.messages)
        read = folder / "read.toml"
        read.write_text(
            f'[fields]\ngyro = "{TOPIC}.gyro_rad"\naccel = "{TOPIC}.accelerometer_m_s2"\n'
            f'time = "{TOPIC}.timestamp"\ntime_unit = "us"\n'
        )
        chain = [
            {"type": "gyro_bias", "sensor": "gyro", "kind": "linear",
             "matrix": np.eye(3).tolist(), "offset": [0.01, -0.02, 0.005]},
        ]  # fmt: skip
        cal = folder / "cal.json"
        cal.write_text(json.dumps({"imupipe_version": "bench", "chain": chain, "results": {}}))
        seconds, peak = run_measured(
            [
                "convert", str(log), "--calibration", str(cal), "--out", str(folder / "out"),
                "--config", str(read), "--batch-rows", str(args.batch_rows), "--jobs", "1",
                "--quiet",
            ],
            folder / "peak",
        )  # fmt: skip
        with open(next((folder / "out").rglob("*.mcap")), "rb") as fh:
            counts_out = Counter(c.topic for _, c, _ in make_reader(fh).iter_messages())
        size = log.stat().st_size / 1e6
        print(
            f"{args.messages} messages ({size:.0f} MB MCAP), --batch-rows {args.batch_rows}: "
            f"{seconds:.1f} s, peak RSS {peak:.0f} MB"
        )
        print(f"messages in {dict(counts_in)}, out {dict(counts_out)}")
        assert dict(counts_out) == counts_in, "counts in != counts out"


if __name__ == "__main__":
    main()
