"""Benchmark (issue 24): reading rosbag2-compressed ROS 2 bags and bz2 / lz4 ROS 1 bags.

The same Imu log (``--n`` messages at 200 Hz, random values, as rosbags' writers write them) in
each layout, read into the common table by imupipe (best of ``--repeat``) and by rosbags'
``AnyReader`` (iterating the raw messages, no deserialization: less than a reader of values
does). Prints, per layout, imupipe's time, its ratio to the same bag uncompressed, and its ratio
to rosbags (below 1: faster).

    python benchmarks/bench_bag_compression.py [--n 200000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import bag_variants as bv  # noqa: E402

from imupipe.readers.dispatch import read_input  # noqa: E402
from imupipe.readers.spec import InputSpec  # noqa: E402


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def rosbags_raw(path: Path) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for _ in reader.messages():
            pass


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        rows = []
        for storage, mode in bv.ROS2_VARIANTS:
            rows.append(
                (
                    f"ros2 {storage} {mode}",
                    bv.write_ros2(d / f"{storage}_{mode}", storage, mode, n=args.n),
                )
            )
        for comp in bv.ROS1_VARIANTS:
            rows.append(
                (f"ros1 {comp}", bv.write_ros1(d / f"{comp}.bag", comp, n=args.n, chunk=1 << 20))
            )
        plain: dict[str, float] = {}
        print(f"{'layout':24} {'imupipe s':>10} {'x plain':>8} {'rosbags s':>10} {'ratio':>6}")
        for name, path in rows:
            ours = best(lambda p=path: read_input(InputSpec(path=p)), args.repeat)
            theirs = best(lambda p=path: rosbags_raw(p), 1)
            key = name.rsplit(" ", 1)[0]
            plain.setdefault(key, ours)
            print(
                f"{name:24} {ours:10.3f} {ours / plain[key]:8.2f} {theirs:10.3f} {ours / theirs:6.2f}"
            )


if __name__ == "__main__":
    main()
